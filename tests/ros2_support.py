"""ROS 2 bags stored as MCAP, written with mcap-ros2-support: what a robot's recorder makes,
for the replay through a topic map (tests/app/recording/test_ros2_replay.py) and the loaders'
fuzzing (tests/app/recording/test_fuzz_streams.py)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from mcap_ros2.writer import Writer

from trifuse.app.recording.ros2 import MSGDEFS

TOPIC_MAP = """
format: trifuse-topic-map/1
sensors:
  ccd_left:
    color: /cam_left/image_raw
    camera_info: /cam_left/camera_info
  ccd_right:
    color: /cam_right/image_raw/compressed
  thermal_left:
    thermal: {topic: /lwir_left/image_raw, scale: 0.01, invalid: 0}
  thermal_right:
    thermal: {topic: /lwir_right/image_raw, scale: 1.0, offset: 273.15}
  tof:
    tof_distance: {topic: /tof/distance, scale: 0.001, invalid: [0, 65535]}
    tof_amplitude: /tof/amplitude
"""
COLOR = (64, 48)
THERMAL = (40, 30)
TOF = (22, 18)
PERIOD_NS = 1_000_000_000 // 15
START_NS = 1_700_000_000_000_000_000  # a ROS wall-clock time stamp


def header(stamp_ns: int, frame_id: str) -> dict:
    return {
        "stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9},
        "frame_id": frame_id,
    }


def image_msg(stamp_ns: int, array: np.ndarray, encoding: str, pad: int = 0, big=False) -> dict:
    h, w = array.shape[:2]
    row = array.reshape(h, -1).astype(array.dtype.newbyteorder(">" if big else "<"))
    raw = row.view(np.uint8).reshape(h, -1)
    if pad:
        raw = np.concatenate([raw, np.zeros((h, pad), np.uint8)], axis=1)
    return {
        "header": header(stamp_ns, "x"),
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": int(big),
        "step": raw.shape[1],
        "data": raw.tobytes(),
    }


def camera_info_msg(stamp_ns: int) -> dict:
    return {
        "header": header(stamp_ns, "cam_left"),
        "height": COLOR[1],
        "width": COLOR[0],
        "distortion_model": "plumb_bob",
        "d": [-0.1, 0.02, 0.001, -0.002, 0.0],
        "k": [70.0, 0, 31.5, 0, 71.0, 23.5, 0, 0, 1],
        "r": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
        "p": [70.0, 0, 31.5, 0, 0, 71.0, 23.5, 0, 0, 0, 1, 0],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def make_bag(
    path: Path, n: int = 4, seed: int = 0, skew_ns: int = 0, chunk_size: int = 1 << 20
) -> dict[str, list]:
    """A bag of ``n`` instants 1/15 s apart; returns what was written, per sensor."""
    rng = np.random.default_rng(seed)
    truth: dict[str, list] = {k: [] for k in ("color", "jpeg", "thermal", "thermal_f", "tof")}
    with path.open("wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        schema = {name: w.register_msgdef(name, text) for name, text in MSGDEFS.items()}
        img, comp, info = (
            schema["sensor_msgs/msg/Image"],
            schema["sensor_msgs/msg/CompressedImage"],
            schema["sensor_msgs/msg/CameraInfo"],
        )
        for k in range(n):
            t = START_NS + k * PERIOD_NS
            yy, xx = np.mgrid[0 : COLOR[1], 0 : COLOR[0]]
            rgb = np.stack(
                [(xx * 4 + k) % 256, (yy * 5) % 256, ((xx + yy) * 2) % 256], axis=-1
            ).astype(np.uint8)
            counts = rng.integers(28000, 31500, THERMAL[::-1]).astype(np.uint16)
            counts[0, :3] = 0  # no reading
            celsius = rng.normal(25.0, 3.0, THERMAL[::-1]).astype(np.float32)
            mm = rng.integers(300, 9000, TOF[::-1]).astype(np.uint16)
            mm[1, 1], mm[2, 2] = 0, 65535  # invalid
            amp = rng.integers(0, 4000, TOF[::-1]).astype(np.uint16)
            ok, jpg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            if k == 0:
                w.write_message("/cam_left/camera_info", info, camera_info_msg(t), log_time=t)
            # logged slightly after acquisition, in a driver's order
            w.write_message(
                "/cam_left/image_raw", img, image_msg(t, rgb, "rgb8", pad=4), log_time=t + 900_000
            )
            w.write_message(
                "/cam_right/image_raw/compressed",
                comp,
                {"header": header(t, "cam_right"), "format": "jpeg", "data": jpg.tobytes()},
                log_time=t + 1_000_000,
            )
            w.write_message(
                "/lwir_left/image_raw", img, image_msg(t, counts, "16UC1"), log_time=t + 2_000_000
            )
            w.write_message(
                "/lwir_right/image_raw", img, image_msg(t, celsius, "32FC1"), log_time=t + 2_100_000
            )
            w.write_message(
                "/tof/distance", img, image_msg(t, mm, "16UC1", big=True), log_time=t + 3_000_000
            )
            w.write_message(
                "/tof/amplitude",
                img,
                image_msg(t + skew_ns, amp, "mono16"),
                log_time=t + 3_500_000,
            )
            w.write_message("/unmapped/topic", img, image_msg(t, amp, "mono16"), log_time=t)
            truth["color"].append(rgb)
            truth["jpeg"].append(rgb)
            truth["thermal"].append(counts)
            truth["thermal_f"].append(celsius)
            truth["tof"].append((mm, amp))
        w.finish()
    return truth
