"""ROS 2 image messages as the DDS wire carries them (OMG CDR, little endian, XCDR1: the
encapsulation ``00 01 00 00`` every ROS 2 middleware on DDS uses), without ROS or an IDL
compiler (issue 36): ``sensor_msgs/msg/Image``, ``sensor_msgs/msg/CompressedImage`` and
``tf2_msgs/msg/TFMessage`` read and written; ``sensor_msgs/msg/CameraInfo`` written (what
the console publishes back).

:func:`decode` gives an object with the message's fields (``header.stamp.sec`` /
``.nanosec``, ``header.frame_id``; ``height``, ``width``, ``encoding``, ``is_bigendian``,
``step``, ``data`` or ``format``, ``data``), what :func:`app.recording.ros2.convert_image`
takes from a bag's decoder; ``data`` is a read-only ``memoryview`` of the payload (no
copy). :func:`encode` is its inverse (tests, a publisher). DDS type names:
:data:`TYPE_NAMES`.

Pure: bytes in, fields out. A malformed or truncated payload raises ValueError in one line.
"""

from __future__ import annotations

import struct
from types import SimpleNamespace
from typing import Any

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TYPE_NAMES = {
    IMAGE: "sensor_msgs::msg::dds_::Image_",
    COMPRESSED: "sensor_msgs::msg::dds_::CompressedImage_",
    CAMERA_INFO: "sensor_msgs::msg::dds_::CameraInfo_",
    TF_MESSAGE: "tf2_msgs::msg::dds_::TFMessage_",
}
"""ROS 2 message type -> its DDS type name."""
CDR_LE = b"\x00\x01\x00\x00"
_BE = b"\x00\x00\x00\x00"  # CDR big endian (accepted when decoding)


class _Reader:
    """Reads CDR fields from ``buf`` (after the 4-byte encapsulation), aligning each to its
    size from the start of the body."""

    def __init__(self, buf: memoryview, little: bool) -> None:
        self.buf, self.pos, self.end = buf, 4, "<" if little else ">"

    def _take(self, fmt: str, size: int) -> Any:
        self.pos += -(self.pos - 4) % size
        if self.pos + size > len(self.buf):
            raise ValueError(f"CDR: truncated at byte {self.pos} of {len(self.buf)}")
        (value,) = struct.unpack_from(self.end + fmt, self.buf, self.pos)
        self.pos += size
        return value

    def u8(self) -> int:
        return self._take("B", 1)

    def u32(self) -> int:
        return self._take("I", 4)

    def i32(self) -> int:
        return self._take("i", 4)

    def octets(self) -> memoryview:
        n = self.u32()
        if self.pos + n > len(self.buf):
            raise ValueError(f"CDR: a sequence of {n} bytes at byte {self.pos} runs past the end")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def f64(self) -> float:
        return self._take("d", 8)

    def string(self) -> str:
        raw = self.octets()
        if len(raw) == 0 or raw[-1] != 0:
            raise ValueError("CDR: a string without its terminating NUL")
        return bytes(raw[:-1]).decode("utf-8", errors="replace")


def decode(datatype: str, payload: bytes | memoryview) -> SimpleNamespace:
    """The fields of one serialised ``datatype`` message (see the module doc)."""
    buf = memoryview(payload).toreadonly()
    if len(buf) < 4 or bytes(buf[:4]) not in (CDR_LE, _BE):
        head = bytes(buf[:4]).hex()
        raise ValueError(f"CDR: expected the encapsulation 00010000 (XCDR1), got {head!r}")
    r = _Reader(buf, little=bytes(buf[:4]) == CDR_LE)
    if datatype == TF_MESSAGE:
        transforms = []
        for _ in range(r.u32()):
            header = _header(r)
            child = r.string()
            tr = SimpleNamespace(x=r.f64(), y=r.f64(), z=r.f64())
            rot = SimpleNamespace(x=r.f64(), y=r.f64(), z=r.f64(), w=r.f64())
            transforms.append(SimpleNamespace(header=header, child_frame_id=child,
                transform=SimpleNamespace(translation=tr, rotation=rot)))  # fmt: skip
        return SimpleNamespace(transforms=transforms)
    header = _header(r)
    if datatype == IMAGE:
        height, width, encoding = r.u32(), r.u32(), r.string()
        is_bigendian, step = r.u8(), r.u32()
        return SimpleNamespace(header=header, height=height, width=width, encoding=encoding,
                               is_bigendian=is_bigendian, step=step, data=r.octets())  # fmt: skip
    if datatype == COMPRESSED:
        return SimpleNamespace(header=header, format=r.string(), data=r.octets())
    raise ValueError(f"CDR: expected {IMAGE}, {COMPRESSED} or {TF_MESSAGE}, got {datatype!r}")


def _header(r: _Reader) -> SimpleNamespace:
    stamp = SimpleNamespace(sec=r.i32(), nanosec=r.u32())
    return SimpleNamespace(stamp=stamp, frame_id=r.string())


class _Writer:
    def __init__(self) -> None:
        self.parts: list[bytes] = [CDR_LE]
        self.pos = 0  # from the start of the body

    def _put(self, fmt: str, size: int, value: Any) -> None:
        pad = -self.pos % size
        self.parts.append(b"\x00" * pad + struct.pack("<" + fmt, value))
        self.pos += pad + size

    def octets(self, data: bytes | memoryview) -> None:
        self._put("I", 4, len(data))
        self.parts.append(bytes(data))
        self.pos += len(data)

    def string(self, text: str) -> None:
        self.octets(text.encode("utf-8") + b"\x00")

    def header(self, header: Any) -> None:
        self._put("i", 4, int(header.stamp.sec))
        self._put("I", 4, int(header.stamp.nanosec))
        self.string(header.frame_id)

    def doubles(self, values: Any) -> None:
        for v in values:
            self._put("d", 8, float(v))


def encode(datatype: str, msg: Any) -> bytes:
    """One ``datatype`` message (an object with its fields, as :func:`decode` gives; for
    :data:`CAMERA_INFO` and :data:`TF_MESSAGE` the ROS 2 fields: ``d`` a sequence, ``k``,
    ``r``, ``p`` 9, 9 and 12 numbers, ``roi`` with ``x_offset``, ``y_offset``, ``height``,
    ``width``, ``do_rectify``; ``transforms`` of ``header``, ``child_frame_id`` and
    ``transform.translation`` x/y/z, ``transform.rotation`` x/y/z/w) serialised as the DDS
    wire carries it."""
    w = _Writer()
    if datatype == TF_MESSAGE:
        w._put("I", 4, len(msg.transforms))
        for t in msg.transforms:
            w.header(t.header)
            w.string(t.child_frame_id)
            tr, rot = t.transform.translation, t.transform.rotation
            w.doubles((tr.x, tr.y, tr.z, rot.x, rot.y, rot.z, rot.w))
        return b"".join(w.parts)
    w.header(msg.header)
    if datatype == CAMERA_INFO:
        w._put("I", 4, int(msg.height))
        w._put("I", 4, int(msg.width))
        w.string(msg.distortion_model)
        w._put("I", 4, len(msg.d))
        w.doubles(msg.d)
        for fixed, n in ((msg.k, 9), (msg.r, 9), (msg.p, 12)):
            if len(fixed) != n:
                raise ValueError(f"CDR: CameraInfo: expected {n} numbers, got {len(fixed)}")
            w.doubles(fixed)
        w._put("I", 4, int(msg.binning_x))
        w._put("I", 4, int(msg.binning_y))
        roi = msg.roi
        for v in (roi.x_offset, roi.y_offset, roi.height, roi.width):
            w._put("I", 4, int(v))
        w._put("B", 1, int(bool(roi.do_rectify)))
        return b"".join(w.parts)
    if datatype == IMAGE:
        w._put("I", 4, int(msg.height))
        w._put("I", 4, int(msg.width))
        w.string(msg.encoding)
        w._put("B", 1, int(msg.is_bigendian))
        w._put("I", 4, int(msg.step))
    elif datatype == COMPRESSED:
        w.string(msg.format)
    else:
        raise ValueError(f"CDR: expected {IMAGE} or {COMPRESSED}, got {datatype!r}")
    w.octets(msg.data)
    return b"".join(w.parts)
