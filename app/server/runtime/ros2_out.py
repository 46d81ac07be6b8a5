"""What a robot wants back from the console, on its ROS 2 domain (``trifuse serve --ros2``;
issue 36, item 1): the calibration as ROS 2 nodes use it, and the fused pair.

- ``/tf_static`` (``tf2_msgs/msg/TFMessage``; reliable, transient local, as tf2's static
  broadcaster: a node started later still gets it): the rig's transforms, parent
  :data:`app.recording.layout.RIG_FRAME` (the TOF's frame), child each sensor's name, at the
  start and with each new rig;
- ``/trifuse/<sensor>/camera_info`` (``sensor_msgs/msg/CameraInfo``; reliable, transient
  local): each sensor's calibrated intrinsics (``plumb_bob``, or ``rational_polynomial``
  for 8 coefficients; ``P`` = ``K`` with no translation, ``R`` identity), frame id the
  sensor's name, likewise;
- ``/trifuse/fused/compressed`` (``sensor_msgs/msg/CompressedImage``, JPEG; best effort):
  each new fused picture, at most :data:`FUSED_HZ` a second, stamped with its frame set.

rviz2 and other nodes then use the calibration directly. Written raw (the CDR of
:mod:`app.sources.ros2_cdr`) through Cyclone DDS's C layer, in a thread of its own
(``ros2-out``); the fused pair only while the console fuses (someone watches).
"""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace
from typing import Any

import cv2

from trifuse.app.errors import describe_error
from trifuse.app.recording.layout import RIG_FRAME
from trifuse.app.recording.ros2_live import dds_topic, require_cyclonedds
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.ros2_cdr import CAMERA_INFO, COMPRESSED, TF_MESSAGE, encode
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.transforms import quaternion_from_rotation

FUSED_TOPIC = "/trifuse/fused/compressed"
TF_STATIC_TOPIC = "/tf_static"
FUSED_HZ = 10.0
"""Fused pictures published a second, at most."""


def camera_info_topic(sensor: str) -> str:
    return f"/trifuse/{sensor}/camera_info"


def _header(stamp_ns: int, frame_id: str) -> SimpleNamespace:
    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return SimpleNamespace(stamp=stamp, frame_id=frame_id)


def camera_info(sensor: Sensor, stamp_ns: int) -> bytes:
    """A sensor's ``CameraInfo`` (CDR)."""
    i = sensor.intrinsics
    d = list(i.distortion)
    model = "rational_polynomial" if len(d) == 8 else "plumb_bob"
    if model == "plumb_bob":
        d = (d + [0.0] * 5)[:5]
    k = [i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0]
    msg = SimpleNamespace(
        header=_header(stamp_ns, sensor.name), height=sensor.height, width=sensor.width,
        distortion_model=model, d=d, k=k, r=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
        p=[i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        binning_x=0, binning_y=0,
        roi=SimpleNamespace(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )  # fmt: skip
    return encode(CAMERA_INFO, msg)


def tf_static(rig: Rig, stamp_ns: int) -> bytes:
    """The rig's transforms ``RIG_FRAME`` -> each sensor (CDR ``TFMessage``)."""
    transforms = []
    for name, s in rig.sensors.items():
        T = s.T_rig_sensor
        x, y, z, w = quaternion_from_rotation(T[:3, :3])
        tr = SimpleNamespace(x=T[0, 3], y=T[1, 3], z=T[2, 3])
        rot = SimpleNamespace(x=x, y=y, z=z, w=w)
        transforms.append(SimpleNamespace(
            header=_header(stamp_ns, RIG_FRAME), child_frame_id=name,
            transform=SimpleNamespace(translation=tr, rotation=rot),
        ))  # fmt: skip
    return encode(TF_MESSAGE, SimpleNamespace(transforms=transforms))


class Ros2Out:
    """Publishes the rig's transforms, each sensor's ``CameraInfo`` and the fused pair on a
    ROS 2 domain (see the module doc).

    Attributes:
        published: messages written; ``error``: the last failure, worded (it goes on).
    """

    def __init__(self, pipeline: FusionPipeline, hub: FrameHub, domain_id: int = 0) -> None:
        require_cyclonedds()
        from cyclonedds.core import Policy, Qos
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        from trifuse.app.sources.ros2_types import IDL_TYPES

        self.pipeline, self.hub = pipeline, hub
        self.published = 0
        self.error: str | None = None
        self._dp = DomainParticipant(domain_id)
        latched = Qos(Policy.Reliability.Reliable(1_000_000_000), Policy.History.KeepLast(1),
                      Policy.Durability.TransientLocal)  # fmt: skip
        best_effort = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1))

        def writer(topic: str, datatype: str, qos: Any) -> Any:
            return DataWriter(self._dp, Topic(self._dp, dds_topic(topic), IDL_TYPES[datatype]),
                              qos=qos)  # fmt: skip

        self._tf = writer(TF_STATIC_TOPIC, TF_MESSAGE, latched)
        self._fused = writer(FUSED_TOPIC, COMPRESSED, best_effort)
        self._info = {n: writer(camera_info_topic(n), CAMERA_INFO, latched)
                      for n in pipeline.rig.names}  # fmt: skip
        self._rig: Rig | None = None
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ros2-out", daemon=True)

    def start(self) -> Ros2Out:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        from cyclonedds._clayer import ddspy_write

        while not self._stop.wait(1.0 / FUSED_HZ):
            try:
                rig = self.pipeline.rig
                if rig is not self._rig:  # the start, or a new rig
                    now = time.time_ns()
                    ddspy_write(self._tf._ref, tf_static(rig, now))
                    for name, w in self._info.items():
                        if name in rig.sensors:
                            ddspy_write(w._ref, camera_info(rig[name], now))
                    self._rig = rig
                    self.published += 1 + len(self._info)
                latest = self.hub.latest
                if latest is not None and latest.seq != self._seq:
                    self._seq = latest.seq
                    stamp = int(latest.meta.get("stamp_ns", time.time_ns()))
                    jpeg = latest.jpeg
                    if jpeg is None:  # the hub encodes for JPEG viewers only: here, then
                        ok, buf = cv2.imencode(".jpg", latest.bgr, [cv2.IMWRITE_JPEG_QUALITY, 80])
                        jpeg = buf.tobytes() if ok else None
                    if jpeg is None:
                        continue
                    msg = SimpleNamespace(header=_header(stamp, RIG_FRAME), format="jpeg",
                                          data=jpeg)  # fmt: skip
                    ddspy_write(self._fused._ref, encode(COMPRESSED, msg))
                    self.published += 1
            except Exception as exc:  # worded; the next round goes on
                self.error = describe_error(exc)
