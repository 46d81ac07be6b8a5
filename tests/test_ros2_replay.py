"""ROS 2 bags stored as MCAP: written here with mcap-ros2-support, replayed via a topic map."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap_ros2.writer import Writer

from app.recording import RecordingDamaged, RecordingError, TopicMapError
from app.recording.ros2 import MSGDEFS, Ros2BagSource
from app.recording.topicmap import load_topic_map, topic_map_from_yaml
from app.sources.base import frame_sets
from calib.camera import Intrinsics

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


@pytest.fixture
def bag(tmp_path) -> tuple[Path, dict]:
    path = tmp_path / "bag.mcap"
    return path, make_bag(path)


def test_bag_replays_through_the_topic_map(bag):
    path, truth = bag
    tmap = topic_map_from_yaml(TOPIC_MAP)
    with Ros2BagSource(path, tmap, realtime=False) as src:
        assert src.sensors == ["ccd_left", "ccd_right", "thermal_left", "thermal_right", "tof"]
        assert src.notes == [] and src.rig is None
        intr, size = src.camera_info["ccd_left"]
        assert intr == Intrinsics(70.0, 71.0, 31.5, 23.5, (-0.1, 0.02, 0.001, -0.002, 0.0))
        assert size == COLOR
        frames = list(src.frames())
    assert len(frames) == 4 * 5
    by_sensor: dict[str, list] = {}
    for f in frames:
        by_sensor.setdefault(f.sensor, []).append(f)
    for k in range(4):
        stamp = START_NS + k * PERIOD_NS
        assert all(by_sensor[s][k].stamp_ns == stamp for s in by_sensor)  # header stamps
        np.testing.assert_array_equal(by_sensor["ccd_left"][k].image, truth["color"][k])
        right = by_sensor["ccd_right"][k].image
        assert right.dtype == np.uint8 and right.shape == (COLOR[1], COLOR[0], 3)
        mse = np.mean((right.astype(float) - truth["jpeg"][k]) ** 2)
        assert 10 * np.log10(255**2 / mse) > 30
        th = by_sensor["thermal_left"][k].image
        counts = truth["thermal"][k]
        assert th.dtype == np.float32 and np.isnan(th[0, :3]).all()
        ok = counts != 0
        np.testing.assert_allclose(th[ok], counts[ok] * 0.01, rtol=0, atol=1e-4)
        np.testing.assert_allclose(
            by_sensor["thermal_right"][k].image, truth["thermal_f"][k] + 273.15, atol=1e-4
        )
        tof = by_sensor["tof"][k]
        mm, amp = truth["tof"][k]
        assert np.isnan(tof.distance_m[1, 1]) and np.isnan(tof.distance_m[2, 2])
        valid = (mm != 0) & (mm != 65535)
        np.testing.assert_allclose(tof.distance_m[valid], mm[valid] / 1000.0, atol=1e-6)
        np.testing.assert_array_equal(tof.image, amp.astype(np.float32))


def test_frame_sets_of_a_bag(bag, tmp_path):
    path, _ = bag
    tm = tmp_path / "map.yaml"
    tm.write_text(TOPIC_MAP)
    with Ros2BagSource(path, tm, realtime=False) as src:
        sets = list(frame_sets(src, reference="ccd_left"))
    assert len(sets) == 4
    assert all(fs.frames.keys() == set(src.sensors) for fs in sets[:-1])


def test_log_time_stamps_and_tof_pairing_tolerance(tmp_path):
    path = tmp_path / "bag.mcap"
    make_bag(path, n=3, skew_ns=400_000)  # amplitude stamped 0.4 ms after the distance
    tmap = topic_map_from_yaml(TOPIC_MAP)
    with Ros2BagSource(path, tmap, realtime=False) as src:
        tofs = [f for f in src.frames() if f.sensor == "tof"]
    assert len(tofs) == 3 and all(f.distance_m is not None for f in tofs)
    with Ros2BagSource(path, tmap, realtime=False, pair_tolerance_s=0.0001) as src:
        tofs = [f for f in src.frames() if f.sensor == "tof"]
    assert len(tofs) == 6  # unpaired halves: distance alone, amplitude alone
    assert sum(f.distance_m is None for f in tofs) == 3
    assert all(np.isnan(f.image).all() for f in tofs if f.distance_m is not None)
    log_map = topic_map_from_yaml(TOPIC_MAP.replace("sensors:", "stamp: log_time\nsensors:", 1))
    with Ros2BagSource(path, log_map, realtime=False) as src:
        left = [f for f in src.frames() if f.sensor == "ccd_left"]
    assert left[0].stamp_ns == START_NS + 900_000


def test_missing_topics_and_wrong_types(bag):
    path, _ = bag
    extra = TOPIC_MAP + "  depth2:\n    tof_distance: /not/in/bag\n"
    with Ros2BagSource(path, topic_map_from_yaml(extra), realtime=False) as src:
        assert any("/not/in/bag" in n for n in src.notes)
        assert "depth2" in src.sensors
        sets = list(frame_sets(src, reference="ccd_left"))
    assert all("depth2" in fs.missing for fs in sets)
    wrong = TOPIC_MAP.replace("camera_info: /cam_left/camera_info", "camera_info: /tof/amplitude")
    wrong = wrong.replace("tof_amplitude: /tof/amplitude\n", "")
    with pytest.raises(
        RecordingError, match=r"/tof/amplitude .*expected sensor_msgs/msg/CameraInfo"
    ):
        Ros2BagSource(path, topic_map_from_yaml(wrong))


def test_truncated_bag_replays_up_to_the_cut(bag, tmp_path):
    path, _ = bag
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 3 // 4])
    got = []
    with Ros2BagSource(cut, topic_map_from_yaml(TOPIC_MAP), realtime=False) as src:
        with pytest.raises(RecordingDamaged, match="truncated"):
            for f in src.frames():
                got.append(f)
    # the whole bag is one chunk (mcap-ros2-support's 1 MB default): nothing survives,
    # and that is said, not hidden
    assert src.damage is not None and src.damage.frames_delivered == len(got)


def test_truncated_bag_with_small_chunks(tmp_path):
    # small chunks: the frames before the cut come through
    path = tmp_path / "bag.mcap"
    make_bag(path, n=6, chunk_size=8 * 1024)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    got = []
    with Ros2BagSource(cut, topic_map_from_yaml(TOPIC_MAP), realtime=False) as src:
        with pytest.raises(RecordingDamaged):
            for f in src.frames():
                got.append(f)
        assert src.index.indexed_by == "scan"
    assert 5 <= len(got) < 30
    stamps = [f.stamp_ns for f in got]
    assert stamps == sorted(stamps)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("format: other/1\nsensors: {a: {color: /a}}", "expected 'trifuse-topic-map/1'"),
        ("format: trifuse-topic-map/1\nsensors: {a: {colour: /a}}", "unknown kind"),
        (
            "format: trifuse-topic-map/1\nsensors: {a: {color: /a, thermal: /b}}",
            "kinds of one modality",
        ),
        ("format: trifuse-topic-map/1\nsensors: {a: {camera_info: /a}}", "kinds of one modality"),
        (
            "format: trifuse-topic-map/1\nsensors: {a: {color: /a}, b: {color: /a}}",
            "mapped twice",
        ),
        (
            "format: trifuse-topic-map/1\nsensors: {a: {thermal: {topic: /a, scale: 0}}}",
            "non-zero",
        ),
        (
            "format: trifuse-topic-map/1\nsensors: {a: {color: {topic: /a, scale: 2}}}",
            "unknown key",
        ),
        ("format: trifuse-topic-map/1\nsensors: {a: {color: a}}", "expected a topic name"),
        ("format: trifuse-topic-map/1\nstamp: now\nsensors: {a: {color: /a}}", "field 'stamp'"),
        ("format: trifuse-topic-map/1\nsensors: [", "not valid YAML"),
    ],
)
def test_topic_map_errors(text, message):
    with pytest.raises(TopicMapError, match=message):
        topic_map_from_yaml(text)


def test_topic_map_file(tmp_path):
    p = tmp_path / "map.yaml"
    p.write_text(TOPIC_MAP)
    tmap = load_topic_map(p)
    assert tmap.modalities == {
        "ccd_left": "color",
        "ccd_right": "color",
        "thermal_left": "thermal",
        "thermal_right": "thermal",
        "tof": "tof",
    }
    spec = tmap.topics["/tof/distance"]
    assert (spec.sensor, spec.kind, spec.scale, spec.invalid) == (
        "tof",
        "tof_distance",
        0.001,
        (0.0, 65535.0),
    )
    with pytest.raises(TopicMapError, match=r"missing\.yaml: cannot read"):
        load_topic_map(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: trifuse-topic-map/1\nsensors: {a: {color: /a}}\nextra: 1\n")
    with pytest.raises(TopicMapError, match=r"bad\.yaml: unknown key\(s\) \['extra'\]"):
        load_topic_map(bad)


def test_bag_replay_with_a_rig(bag, tmp_path):
    from app.storage.rigfile import save_rig
    from calib.rig import Rig, Sensor

    path, _ = bag
    sensors = {
        "ccd_left": Sensor("ccd_left", "color", COLOR, Intrinsics(70, 71, 31.5, 23.5), np.eye(4)),
        "tof": Sensor("tof", "thermal", TOF, Intrinsics(20, 20, 10.5, 8.5), np.eye(4)),
    }
    rig = Rig(sensors, "ccd_left")
    one = "format: trifuse-topic-map/1\nsensors:\n  ccd_left: {color: /cam_left/image_raw}\n"
    with Ros2BagSource(
        path, topic_map_from_yaml(one), rig=save_rig(tmp_path / "r.yaml", rig)
    ) as src:
        assert src.rig == rig
    two = one + "  tof: {tof_distance: /tof/distance}\n"
    with pytest.raises(RecordingError, match="'tof' is tof by its topics, but thermal in the rig"):
        Ros2BagSource(path, topic_map_from_yaml(two), rig=rig)
