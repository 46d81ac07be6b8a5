"""ROS 2 bags stored as MCAP: written here with mcap-ros2-support, replayed via a topic map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.ros2_support import (
    COLOR,
    PERIOD_NS,
    START_NS,
    TOF,
    TOPIC_MAP,
    make_bag,
)
from trifuse.app.recording import RecordingDamaged, RecordingError, TopicMapError
from trifuse.app.recording.ros2 import Ros2BagSource
from trifuse.app.recording.topicmap import load_topic_map, topic_map_from_yaml
from trifuse.app.sources.base import frame_sets
from trifuse.calib.camera import Intrinsics


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
    from trifuse.app.storage.rigfile import save_rig
    from trifuse.calib.rig import Rig, Sensor

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
