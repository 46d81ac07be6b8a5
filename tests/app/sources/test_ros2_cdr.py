"""ROS 2 image messages on the DDS wire (app/sources/ros2_cdr.py), against mcap-ros2-support's
serialiser and decoder (the code that reads and writes ROS 2 bags): the same bytes for an
Image and a CompressedImage with awkward field lengths (every alignment), decoded back to
the same fields; the payload is a view, not a copy; bad payloads one line."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2._dynamic import serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

from trifuse.app.recording.ros2 import MSGDEFS
from trifuse.app.sources.ros2_cdr import COMPRESSED, IMAGE, decode, encode


def _image(frame_id: str, encoding: str, data: bytes) -> SimpleNamespace:
    stamp = SimpleNamespace(sec=1_764_000_000, nanosec=123_456_789)
    header = SimpleNamespace(stamp=stamp, frame_id=frame_id)
    return SimpleNamespace(
        header=header, height=3, width=5, encoding=encoding, is_bigendian=0, step=10, data=data
    )


def _theirs(datatype: str, msg: SimpleNamespace) -> tuple[bytes, object]:
    fields = {k: v for k, v in vars(msg).items() if k != "header"}
    as_dict = {"header": {"stamp": vars(msg.header.stamp), "frame_id": msg.header.frame_id},
               **fields}  # fmt: skip
    raw = serialize_dynamic(datatype, MSGDEFS[datatype])[datatype](as_dict)
    schema = Schema(id=1, name=datatype, encoding="ros2msg", data=MSGDEFS[datatype].encode())
    return raw, DecoderFactory().decoder_for("cdr", schema)


@pytest.mark.parametrize("frame_id", ["", "c", "cam", "left_camera_optical_frame"])
@pytest.mark.parametrize("encoding", ["16UC1", "rgb8", "mono16"])
def test_an_image_is_the_bytes_mcap_ros2_writes(frame_id: str, encoding: str) -> None:
    rng = np.random.default_rng(len(frame_id) + len(encoding))
    data = rng.integers(0, 256, 30, dtype=np.uint8).tobytes()
    msg = _image(frame_id, encoding, data)
    raw, theirs = _theirs(IMAGE, msg)
    assert encode(IMAGE, msg) == raw
    got = decode(IMAGE, raw)
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (1_764_000_000, 123_456_789)
    assert (got.header.frame_id, got.encoding, got.height, got.width, got.step) == (
        frame_id, encoding, 3, 5, 10)  # fmt: skip
    assert isinstance(got.data, memoryview) and bytes(got.data) == data
    assert bytes(theirs(encode(IMAGE, msg)).data) == data


@pytest.mark.parametrize("fmt", ["jpeg", "png", "16UC1; compressedDepth png"])
def test_a_compressed_image_is_the_bytes_mcap_ros2_writes(fmt: str) -> None:
    stamp = SimpleNamespace(sec=5, nanosec=6)
    msg = SimpleNamespace(header=SimpleNamespace(stamp=stamp, frame_id="tof"), format=fmt,
                          data=b"\xff\xd8" + bytes(range(17)))  # fmt: skip
    raw, theirs = _theirs(COMPRESSED, msg)
    assert encode(COMPRESSED, msg) == raw
    got = decode(COMPRESSED, raw)
    assert got.format == fmt and bytes(got.data) == bytes(msg.data)
    assert theirs(encode(COMPRESSED, msg)).format == fmt


@pytest.mark.parametrize(
    ("payload", "says"),
    [
        (b"\x00\x07\x00\x00" + b"\x00" * 40, "expected the encapsulation 00010000"),
        (b"\x00\x01\x00\x00\x01\x00", "truncated"),
        (b"\x00\x01\x00\x00" + b"\x00" * 8 + b"\xff\xff\x00\x00", "runs past the end"),
    ],
)
def test_a_bad_payload_is_one_line(payload: bytes, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        decode(IMAGE, payload)
