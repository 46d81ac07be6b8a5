"""The layout of a trifuse recording: topics, frame ids, metadata (docs/FORMATS.md).

One topic per sensor and stream, named ``/<sensor>/<stream>``; every message's frame id is
the sensor's name, its log time the frame's ``stamp_ns``.

* ``color``: ``/<sensor>/image``, ``foxglove.CompressedImage``, JPEG.
* ``thermal``: ``/<sensor>/temperature``, ``foxglove.RawImage``, ``16UC1`` centi-kelvin,
  0 = no reading (or ``32FC1`` kelvin).
* ``tof_distance``: ``/<sensor>/distance``, ``foxglove.RawImage``, ``16UC1`` millimetres,
  0 = invalid.
* ``tof_amplitude``: ``/<sensor>/amplitude``, ``foxglove.RawImage``, ``16UC1``.
* ``calibration``: ``/<sensor>/calibration``, ``foxglove.CameraCalibration`` (K, D, size).
* the rig: ``/tf``, ``foxglove.FrameTransform`` ``T_rig_<sensor>`` with parent ``rig``, and
  the rig file's text as the attachment ``rig.yaml``.
* the head's pose, where the source knows it (the simulated head; a robot's localisation):
  ``/tf``, ``foxglove.FrameTransform`` ``T_world_rig`` with parent ``world``
  (:data:`WORLD_FRAME`) and child ``rig``, one per frame set, its timestamp and log time the
  frame set's stamp (:meth:`~app.recording.writer.RecordingWriter.write_pose`). Readers
  (:mod:`app.recording.poses`) also accept the parents ``map`` and ``odom``
  (:data:`POSE_PARENTS`) and, as the child, the rig's reference sensor (whose frame is the
  rig frame).

Optionally (``trifuse record --fused-video``, the console's "Record fused video") the fused
stereo picture as video: ``/fused/video`` (:data:`FUSED_VIDEO_TOPIC`),
``foxglove.CompressedVideo``, ``format: h264``, one Annex B access unit per message, log time
the picture's frame-set stamp, frame id the left eye's colour camera (the left half of the
picture is drawn in its image; :mod:`app.recording.video_track`). It is no sensor stream:
:func:`parse_topic` gives None for it and readers skip it.
"""

from __future__ import annotations

import re

RECORDING_FORMAT = "trifuse-recording/1"
RIG_ATTACHMENT = "rig.yaml"
"""Name of the attachment holding the rig file's text (media type application/yaml)."""
METADATA_NAME = "trifuse.recording"
"""Name of the metadata record (format, writer options)."""
TF_TOPIC = "/tf"
RIG_FRAME = "rig"
"""Parent frame id of the FrameTransforms: the rig frame (= the reference sensor's frame)."""
WORLD_FRAME = "world"
"""Parent frame id of the head's pose (``T_world_rig``, child :data:`RIG_FRAME`)."""
POSE_PARENTS = (WORLD_FRAME, "map", "odom")
"""Parent frame ids read as the head's pose, in order of preference (a recording with
several uses the first)."""

STREAMS = {
    "color": "image",
    "thermal": "temperature",
    "tof_distance": "distance",
    "tof_amplitude": "amplitude",
    "calibration": "calibration",
}
KIND_OF_STREAM = {v: k for k, v in STREAMS.items()}
MODALITY_OF_KIND = {
    "color": "color",
    "thermal": "thermal",
    "tof_distance": "tof",
    "tof_amplitude": "tof",
}
SCHEMA_OF_KIND = {
    "color": "foxglove.CompressedImage",
    "thermal": "foxglove.RawImage",
    "tof_distance": "foxglove.RawImage",
    "tof_amplitude": "foxglove.RawImage",
    "calibration": "foxglove.CameraCalibration",
}

MEASUREMENTS_TOPIC = "/trifuse/measurements"
"""The console's measurement notes (issue 35) as ``foxglove.Log`` (Foxglove's Log panel and
timeline): ``name`` ``trifuse.alarm`` (level WARNING raised, INFO cleared) or
``trifuse.measurement_settings`` (INFO: the object parameters, regions and alarm rules in
force, at the recording's start and at each change); ``message`` a JSON object."""
ALARM_NOTE = "trifuse.alarm"
"""The ``name`` of an alarm event's note."""
SETTINGS_NOTE = "trifuse.measurement_settings"
"""The ``name`` of the measurement settings' note."""

FUSED_VIDEO_TOPIC = "/fused/video"
"""The fused stereo picture (left | right eye) as H.264."""
FUSED_VIDEO_KIND = "fused_video"
"""``trifuse.kind`` of the fused-video channel (it has no ``trifuse.sensor``)."""
FUSED_VIDEO_SCHEMA = "foxglove.CompressedVideo"
FUSED_VIDEO_FORMAT = "h264"

_TOPIC_RE = re.compile(r"^/(?P<sensor>[^/]+)/(?P<stream>[a-z]+)$")


def topic_of(sensor: str, kind: str) -> str:
    """The topic of a sensor's stream, e.g. ``topic_of("tof", "tof_distance")`` ->
    ``/tof/distance``."""
    return f"/{sensor}/{STREAMS[kind]}"


def parse_topic(topic: str) -> tuple[str, str] | None:
    """(sensor, kind) of a recording topic, or None for ``/tf`` and foreign topics."""
    m = _TOPIC_RE.match(topic)
    if m is None or m["stream"] not in KIND_OF_STREAM:
        return None
    return m["sensor"], KIND_OF_STREAM[m["stream"]]
