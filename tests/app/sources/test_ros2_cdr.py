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
from trifuse.app.sources.ros2_cdr import (
    CAMERA_INFO,
    COMPRESSED,
    IMAGE,
    TF_MESSAGE,
    decode,
    encode,
)


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


_SEP = "=" * 80
TF_MSGDEF = "\n".join([
    "geometry_msgs/TransformStamped[] transforms", _SEP, "MSG: geometry_msgs/TransformStamped",
    "std_msgs/Header header", "string child_frame_id", "geometry_msgs/Transform transform",
    _SEP, "MSG: std_msgs/Header", "builtin_interfaces/Time stamp", "string frame_id", _SEP,
    "MSG: builtin_interfaces/Time", "int32 sec", "uint32 nanosec", _SEP,
    "MSG: geometry_msgs/Transform", "geometry_msgs/Vector3 translation",
    "geometry_msgs/Quaternion rotation", _SEP, "MSG: geometry_msgs/Vector3", "float64 x",
    "float64 y", "float64 z", _SEP, "MSG: geometry_msgs/Quaternion", "float64 x", "float64 y",
    "float64 z", "float64 w", "",
])  # fmt: skip


def _ns(d: dict) -> SimpleNamespace:
    return SimpleNamespace(**{k: _ns(v) if isinstance(v, dict) else v for k, v in d.items()})


@pytest.mark.parametrize("frame_id", ["", "tof", "ccd_left"])
def test_camera_info_and_tf_are_the_bytes_mcap_ros2_writes(frame_id: str) -> None:
    header = {"stamp": {"sec": 3, "nanosec": 4}, "frame_id": frame_id}
    info = {
        "header": header, "height": 960, "width": 1280, "distortion_model": "plumb_bob",
        "d": [-0.1, 0.02, 0.0003, -0.0002, 0.0], "k": [float(i) for i in range(9)],
        "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], "p": [float(i) for i in range(12)],
        "binning_x": 0, "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }  # fmt: skip
    theirs = serialize_dynamic(CAMERA_INFO, MSGDEFS[CAMERA_INFO])[CAMERA_INFO](info)
    assert encode(CAMERA_INFO, _ns(info)) == theirs
    tf = {"transforms": [
        {"header": header, "child_frame_id": c,
         "transform": {"translation": {"x": 0.1 * i, "y": -0.2, "z": 0.3},
                       "rotation": {"x": 0.0, "y": 0.0, "z": 0.6, "w": 0.8}}}
        for i, c in enumerate(["ccd_left", "t", "thermal_right"])
    ]}  # fmt: skip
    theirs = serialize_dynamic(TF_MESSAGE, TF_MSGDEF)[TF_MESSAGE](tf)
    msg = SimpleNamespace(transforms=[_ns(t) for t in tf["transforms"]])
    assert encode(TF_MESSAGE, msg) == theirs


def test_the_dds_types_serialise_as_the_codec_does() -> None:
    """The IdlStructs the DDS topics are declared with (app/sources/ros2_types.py) have the
    codec's layout: Cyclone DDS's own serialiser writes the same bytes."""
    pytest.importorskip("cyclonedds", reason="the [ros2] extra (in the test extra)")
    from trifuse.app.sources import ros2_types as t

    header = t.Header(t.Time(3, 4), "ccd_left")
    roi = t.RegionOfInterest(0, 0, 0, 0, False)
    messages = {
        IMAGE: t.Image(header, 2, 3, "rgb8", 0, 9, bytes(range(18))),
        COMPRESSED: t.CompressedImage(header, "jpeg", bytes(range(7))),
        CAMERA_INFO: t.CameraInfo(header, 960, 1280, "plumb_bob", [-0.1, 0.02, 0.0, 0.0, 0.0],
                                  [float(i) for i in range(9)], [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                                  [float(i) for i in range(12)], 0, 0, roi),
        TF_MESSAGE: t.TFMessage([t.TransformStamped(header, "tof", t.Transform(
            t.Vector3(0.1, 0.2, 0.3), t.Quaternion(0.0, 0.0, 0.6, 0.8)))]),
    }  # fmt: skip
    for datatype, msg in messages.items():
        assert msg.serialize() == encode(datatype, msg), datatype
