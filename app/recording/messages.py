"""The Foxglove messages of a recording, built from a rig's sensors and their frames.

One function per kind of message: :func:`frame_messages` (a frame's images: colour as JPEG
``foxglove.CompressedImage``, thermal and TOF as ``foxglove.RawImage``),
:func:`calibration_message` (``foxglove.CameraCalibration``), :func:`transform_message`
(``foxglove.FrameTransform`` on ``/tf``) and :func:`sensor_channels` (a sensor's channels,
topics and metadata). The recording writer (:class:`~app.recording.writer.RecordingWriter`)
and the console's live Foxglove server (:mod:`app.server.runtime.foxglove_live`) both build
their messages here: live and recorded, the same bytes. The layout (topics, schemas,
encodings) is in :mod:`app.recording.layout` and docs/FORMATS.md ("Recordings").
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import foxglove
import numpy as np
from foxglove.channels import (
    CameraCalibrationChannel,
    CompressedImageChannel,
    RawImageChannel,
)
from foxglove.messages import (
    CameraCalibration,
    CompressedImage,
    FrameTransform,
    Quaternion,
    RawImage,
    Timestamp,
    Vector3,
)

from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.layout import topic_of
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Sensor
from trifuse.calib.transforms import quaternion_from_rotation
from trifuse.calib.units import encode_amplitude, encode_distance, encode_thermal

THERMAL_ENCODINGS = ("16UC1", "32FC1")
"""How a thermal image may be kept: ``16UC1`` centi-kelvin or ``32FC1`` kelvin."""


def largest_message_bytes(s: Sensor, thermal_encoding: str = "16UC1") -> int:
    """Bytes of a sensor's largest frame message as :func:`frame_messages` writes it (for
    colour, its RGB size, more than its JPEG takes)."""
    w, h = s.image_size
    per_pixel = {"color": 3, "thermal": 2 if thermal_encoding == "16UC1" else 4, "tof": 2}
    return w * h * per_pixel[s.modality]


def distortion_model(distortion: tuple[float, ...]) -> tuple[str, list[float]]:
    """ROS/Foxglove distortion model name and coefficients for OpenCV's ``k1 k2 p1 p2 [k3
    [k4 k5 k6]]``: ``plumb_bob`` (5, a 4-coefficient model padded with k3 = 0) or
    ``rational_polynomial`` (8)."""
    d = [float(c) for c in distortion]
    if len(d) == 8:
        return "rational_polynomial", d
    return "plumb_bob", (d + [0.0] * 5)[:5]


def _timestamp(stamp_ns: int) -> Timestamp:
    return Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)


def channel_kinds(s: Sensor, thermal_encoding: str = "16UC1") -> list[tuple[str, type, str]]:
    """(kind, foxglove channel class, ``trifuse.unit``) of each channel a sensor has in a
    recording, its calibration last (:data:`app.recording.layout.SCHEMA_OF_KIND`)."""
    kinds: list[tuple[str, type, str]]
    if s.modality == "color":
        kinds = [("color", CompressedImageChannel, "rgb")]
    elif s.modality == "thermal":
        unit = "centikelvin" if thermal_encoding == "16UC1" else "kelvin"
        kinds = [("thermal", RawImageChannel, unit)]
    else:
        kinds = [
            ("tof_distance", RawImageChannel, "millimetre"),
            ("tof_amplitude", RawImageChannel, "amplitude"),
        ]
    return [*kinds, ("calibration", CameraCalibrationChannel, "pixel")]


def sensor_channels(
    context: foxglove.Context, s: Sensor, thermal_encoding: str = "16UC1"
) -> dict[tuple[str, str], object]:
    """A sensor's channels in ``context``, keyed by (sensor, kind): topics
    (:func:`~app.recording.layout.topic_of`), schemas and metadata (``trifuse.sensor``,
    ``trifuse.kind``, ``trifuse.unit``) as a recording has them."""
    name = s.name
    return {
        (name, kind): cls(
            topic_of(name, kind),
            context=context,
            metadata={"trifuse.sensor": name, "trifuse.kind": kind, "trifuse.unit": unit},
        )
        for kind, cls, unit in channel_kinds(s, thermal_encoding)
    }


def check_plane(a: object, s: Sensor, what: str) -> np.ndarray:
    """``a`` if it is a (H, W) array of numbers of the sensor's size, else RecordingError."""
    w, h = s.image_size
    if not isinstance(a, np.ndarray) or a.shape != (h, w):
        got = a.shape if isinstance(a, np.ndarray) else type(a).__name__
        raise RecordingError(
            f"frame of {s.name!r}: {what}: expected an array of shape ({h}, {w}) "
            f"(the rig's {w}x{h}), got {got}"
        )
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise RecordingError(f"frame of {s.name!r}: {what}: expected numbers, got dtype {a.dtype}")
    return a


def frame_messages(
    frame: Frame,
    s: Sensor,
    stamp: int,
    jpeg_quality: int = 90,
    thermal_encoding: str = "16UC1",
    wanted: Callable[[str], bool] | None = None,
) -> list[tuple[str, object]]:
    """(kind, message) of each stream of a sensor's frame taken at ``stamp`` (ns): a
    colour image as JPEG ``foxglove.CompressedImage``, a thermal image as
    ``foxglove.RawImage`` (``16UC1`` centi-kelvin or ``32FC1`` kelvin), a TOF frame's
    distance (if it has one) and amplitude as ``16UC1`` RawImages; frame id the sensor.

    The frame is checked against the sensor first (RecordingError: wrong type or size);
    ``wanted(kind)`` False leaves that message out (not encoded: nobody takes it).
    """
    name = s.name
    ts = _timestamp(stamp)
    w, h = s.image_size
    want = wanted or (lambda _kind: True)
    if s.modality == "color":
        img = frame.image
        if (
            not isinstance(img, np.ndarray)
            or img.dtype != np.uint8
            or img.shape not in ((h, w, 3), (h, w))
        ):
            got = f"{img.dtype} {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
            raise RecordingError(
                f"frame of {name!r}: expected a colour image uint8 ({h}, {w}, 3) RGB, got {got}"
            )
        if not want("color"):
            return []
        bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        if not ok:
            raise RecordingError(f"frame of {name!r}: OpenCV could not encode it as JPEG")
        msg = CompressedImage(timestamp=ts, frame_id=name, data=buf.tobytes(), format="jpeg")
        return [("color", msg)]
    if frame.distance_m is not None and s.modality != "tof":
        raise RecordingError(f"frame of {name!r}: a {s.modality} frame has no distance_m")
    image = check_plane(frame.image, s, "image")
    if s.modality == "thermal":
        if not want("thermal"):
            return []
        if thermal_encoding == "16UC1":
            raw = _raw(ts, name, encode_thermal(image), "16UC1")
        else:
            raw = _raw(ts, name, image.astype("<f4"), "32FC1")
        return [("thermal", raw)]
    out: list[tuple[str, object]] = []
    if frame.distance_m is not None:
        distance = check_plane(frame.distance_m, s, "distance_m")
        if want("tof_distance"):
            out.append(("tof_distance", _raw(ts, name, encode_distance(distance))))
    if want("tof_amplitude"):
        out.append(("tof_amplitude", _raw(ts, name, encode_amplitude(image))))
    return out


def calibration_message(s: Sensor, stamp: int) -> CameraCalibration:
    """The sensor's ``foxglove.CameraCalibration`` (K, D, size; frame id the sensor)."""
    i = s.intrinsics
    model, d = distortion_model(i.distortion)
    K = [float(v) for v in i.K.ravel()]
    P = [i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return CameraCalibration(
        timestamp=_timestamp(stamp),
        frame_id=s.name,
        width=int(s.image_size[0]),
        height=int(s.image_size[1]),
        distortion_model=model,
        D=d,
        K=K,
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=P,
    )


def transform_message(T: np.ndarray, parent: str, child: str, stamp: int) -> FrameTransform:
    """A ``foxglove.FrameTransform`` of the (4, 4) pose ``T`` of ``child`` in ``parent``:
    ``T_rig_<sensor>`` (parent :data:`~app.recording.layout.RIG_FRAME`) or the head's pose
    ``T_world_rig`` (parent :data:`~app.recording.layout.WORLD_FRAME`)."""
    x, y, z, w = quaternion_from_rotation(T[:3, :3])
    return FrameTransform(
        timestamp=_timestamp(stamp),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        rotation=Quaternion(x=x, y=y, z=z, w=w),
    )


def _raw(ts: Timestamp, frame_id: str, plane: np.ndarray, encoding: str = "16UC1") -> RawImage:
    """A RawImage of a (H, W) uint16 (little-endian) or float32 plane."""
    h, w = plane.shape
    if encoding == "16UC1":
        data = np.ascontiguousarray(plane, dtype="<u2")
        step = 2 * w
    else:
        data = np.ascontiguousarray(plane, dtype="<f4")
        step = 4 * w
    return RawImage(
        timestamp=ts,
        frame_id=frame_id,
        width=w,
        height=h,
        encoding=encoding,
        step=step,
        data=data.tobytes(),
    )
