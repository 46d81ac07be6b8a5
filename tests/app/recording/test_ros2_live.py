"""Live ROS 2 topics (app/recording/ros2_live.py) from a publisher process that speaks the
DDS wire as ROS 2 camera drivers do (app/devtools/ros2_publisher.py: topics ``rt/...``, ROS 2's
type names, CDR, best effort), the small rig's sensors at the head's rates: every sensor's
frames arrive with their header stamps and the topic map's units (kelvin from
centi-kelvin, metres from millimetres with 0 as no reading, the right camera's JPEG
decoded), the TOF's distance and amplitude paired by stamp; a thermal imager stamped
150 ms early is named as running behind; the left camera's images of
the wrong size are refused and worded for its topic while the others go on; a real
pipeline fuses pictures from the source. A topic map naming a sensor the rig lacks: a
line per topic, the others read."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from tests.support import LOOPBACK_DDS, RATES_HZ, small_rig, wait_until
from trifuse.app.recording.topicmap import topic_map_from_yaml
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.storage.rigfile import save_rig

pytest.importorskip("cyclonedds", reason="the [ros2] extra (in the test extra)")
from trifuse.app.devtools.ros2_publisher import TOPIC_MAP, WRONG_SIZE_EVERY
from trifuse.app.recording.ros2_live import Ros2LiveSource

SECONDS = 6.0
DOMAIN = 42  # apart from any other DDS traffic of the machine


@pytest.fixture(autouse=True)
def loopback_dds(monkeypatch: pytest.MonkeyPatch) -> None:
    """DDS on loopback with unicast discovery (the publisher process inherits it)."""
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK_DDS)


def _publisher(
    seconds: float, rig_file: Path, *options: str, stdout: int = subprocess.DEVNULL
) -> subprocess.Popen:
    """The ROS 2 publisher stand-in for ``seconds`` on this test's domain (text output)."""
    command = [sys.executable, "-m", "trifuse.app.devtools.ros2_publisher", str(seconds),
               "--rig", str(rig_file), "--domain", str(DOMAIN), *options]  # fmt: skip
    return subprocess.Popen(command, stdout=stdout, text=True)


def test_frames_arrive_with_their_stamps_and_units_and_are_fused(tmp_path) -> None:
    rig = small_rig()
    rig_file = save_rig(tmp_path / "rig.yaml", rig)
    source = Ros2LiveSource(topic_map_from_yaml(TOPIC_MAP), rig, domain_id=DOMAIN)
    seen: dict[str, dict] = defaultdict(dict)  # sensor -> stamp -> frame (a set may
    hub = FrameHub()  # hold a frame the previous one held: the TOF's, at half the rate)
    pipeline = FusionPipeline(source, rig, hub)
    pipeline.set_listeners.append(
        lambda fs: [seen[n].setdefault(f.stamp_ns, f) for n, f in fs.frames.items()]  # type: ignore[func-returns-value]
    )
    publisher = _publisher(SECONDS, rig_file, stdout=subprocess.PIPE)
    try:
        with hub.watching():
            pipeline.start()
            out, _ = publisher.communicate(timeout=SECONDS + 60)
            wait_until(lambda: pipeline.status.pictures_out > 10, "pictures fused")
    finally:
        source.close()
        pipeline.stop()
    got = {n: [frames[t] for t in sorted(frames)] for n, frames in seen.items()}
    sent = dict(item.split("=") for item in out.split())
    assert set(sent) == set(rig.names)
    for name in rig.names:
        frames = got[name]
        modality = rig[name].modality
        # best effort on a busy machine may drop some; the newest-frame slots drop more
        # when the console is slower than the sensors: most of them arrive
        assert len(frames) > 0.3 * int(sent[name]), (name, len(frames), sent[name])
        rate = RATES_HZ[modality]
        stamps = np.array([f.stamp_ns for f in frames])
        assert (np.diff(stamps) > 0).all()
        k = np.rint((stamps - stamps[0]) * rate / 1e9)  # the stamps are the publisher's
        np.testing.assert_allclose((stamps - stamps[0]) * rate / 1e9, k, atol=1e-3)
        first = frames[-1]
        if modality == "color":
            assert first.image.shape == (96, 128, 3) and first.image.dtype == np.uint8
        elif modality == "thermal":
            assert np.allclose(first.image[1:, :], 293.15) and first.image.dtype == np.float32
        else:
            d = first.distance_m
            assert np.allclose(d[2:, :], 2.5) and np.isnan(d[1, :]).all()
            assert np.allclose(first.image, 1000.0)
    # the k in the first pixel: the thermal frame of stamp k/27 s carries 29315 + k cK
    t = got["thermal_left"][-1]
    k = round((t.stamp_ns - got["thermal_left"][0].stamp_ns) * 27 / 1e9)
    k0 = round(float(got["thermal_left"][0].image[0, 0]) * 100) - 29_315
    assert round(float(t.image[0, 0]) * 100) - 29_315 == k0 + k
    stats = source.topic_stats["/ccd_left/image_raw"]
    # the readers keep the newest sample only: on a busy machine some of the wrong-size
    # images are overwritten before they are read, never counted as received
    assert 0 < stats.refused <= int(sent["ccd_left"]) // WRONG_SIZE_EVERY
    assert stats.received + stats.refused <= int(sent["ccd_left"])
    assert "64x48" in source.problems["/ccd_left/image_raw"] and "128x96" in source.problems[
        "/ccd_left/image_raw"]  # fmt: skip
    assert set(source.problems) == {"/ccd_left/image_raw"}
    assert source.stamp_warnings() == {}
    [(sensor, r)] = source.stats()["rejected_by_sensor"].items()  # the console's health
    assert sensor == "ccd_left" and "64x48" in r["last_error"] and r["last_rejected_s"] > 0


def test_a_sensor_stamped_late_is_named(tmp_path) -> None:
    """thermal_left's header stamps 150 ms before its images are sent: behind the others
    by more than its 37 ms frame (the frame sets then lack it: it is never within 50 ms of
    a colour frame), said once in the Source panel's notes; the others are not named."""
    rig = small_rig()
    source = Ros2LiveSource(topic_map_from_yaml(TOPIC_MAP), rig, domain_id=DOMAIN)
    publisher = _publisher(4, save_rig(tmp_path / "rig.yaml", rig), "--late", "thermal_left:150")
    threading.Thread(target=lambda: [None for _ in source.frames()], daemon=True).start()
    try:
        publisher.wait(timeout=60)
        [(late, line)] = source.stamp_warnings().items()
    finally:
        source.close()
    assert late == "thermal_left" and line in source.notes
    behind_ms = float(line.split("run ")[1].split(" ms")[0])
    assert 100 < behind_ms < 200, line


def test_the_heads_pose_comes_from_tf2(tmp_path) -> None:
    """A topic map with ``pose: {world: odom, rig: tof_link}``: /tf gives odom -> base_link
    (0.1 m/s along x, 50 Hz), /tf_static base_link -> tof_link (published once, before the
    source joins: transient local); the source's head pose at a TOF frame's time is their
    product: the static rotation and offset, x moving 0.1 m a second between two frames
    (to one 50 Hz step: each lookup takes the nearest transform); a frame the tf2 tree does
    not join gives None."""
    from trifuse.app.devtools.ros2_publisher import BASE_T_RIG

    rig = small_rig()
    text = TOPIC_MAP + "pose: {world: odom, rig: tof_link}\n"
    publisher = _publisher(4, save_rig(tmp_path / "rig.yaml", rig), "--tf", "odom:tof_link")
    time.sleep(0.5)  # the static transform is out before the source exists
    source = Ros2LiveSource(topic_map_from_yaml(text), rig, domain_id=DOMAIN)
    tofs = []
    threading.Thread(
        target=lambda: [tofs.append(f.stamp_ns) for f in source.frames() if f.sensor == "tof"],
        daemon=True,
    ).start()
    try:
        publisher.wait(timeout=60)
        assert len(tofs) > 20
        a, b = tofs[5], tofs[-5]
        Ta, Tb = source.head_pose(a), source.head_pose(b)
        assert source.tf.lookup("odom", "nowhere", a) is None
    finally:
        source.close()
    assert Ta is not None and Tb is not None
    for T in (Ta, Tb):
        np.testing.assert_allclose(T[:3, :3], BASE_T_RIG[:3, :3], atol=1e-9)
        np.testing.assert_allclose(T[1:3, 3], BASE_T_RIG[1:3, 3], atol=1e-9)
    moved = Tb[0, 3] - Ta[0, 3]
    assert abs(moved - 0.1 * (b - a) * 1e-9) <= 0.1 / 50 + 1e-9, moved  # nearest: half a step each


def test_a_sensor_the_rig_lacks_is_a_line_per_topic_and_the_others_are_read() -> None:
    text = TOPIC_MAP.replace("  tof:\n", "  tof_front:\n")
    source = Ros2LiveSource(topic_map_from_yaml(text), small_rig(), domain_id=DOMAIN)
    try:
        assert source.sensors == ["ccd_left", "ccd_right", "thermal_left", "thermal_right"]
        assert [n.split(":")[0] for n in source.notes] == [
            "topic /tof/distance", "topic /tof/amplitude"]  # fmt: skip
        assert "sensor 'tof_front' is not a tof sensor of the rig" in source.notes[0]
    finally:
        source.close()
    only = "format: trifuse-topic-map/1\nsensors:\n  lwir:\n    thermal: /lwir\n"
    with pytest.raises(ValueError, match="no sensor of the rig in it"):
        Ros2LiveSource(topic_map_from_yaml(only), small_rig(), domain_id=DOMAIN)


def test_closing_ends_the_frames() -> None:
    source = Ros2LiveSource(topic_map_from_yaml(TOPIC_MAP), small_rig(), domain_id=DOMAIN)
    done = threading.Event()

    def consume() -> None:
        for _ in source.frames():
            pass
        done.set()

    threading.Thread(target=consume, daemon=True).start()
    time.sleep(0.3)
    source.close()
    assert done.wait(5.0)


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--ros2-domain", "3"], "--ros2-domain, --ros2-max-mb and --ros2-reliable are for --ros2"),
        (["--ros2", "t.yaml", "--ros2-max-mb", "0"], "--ros2-max-mb: expected 0 to 1024 MB"),
        (["--ros2", "t.yaml", "--push"], "choose one of --replay, --live, --push, --ros2"),
    ],
)
def test_serve_refuses_wrong_ros2_options_in_one_line(argv, says, tmp_path, capsys) -> None:
    from tests.support import run_cli

    workdir = tmp_path / "work"
    code, out, err = run_cli(["serve", "--port", "0", *argv, "--workdir", str(workdir)], capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert says in err and not workdir.exists()
