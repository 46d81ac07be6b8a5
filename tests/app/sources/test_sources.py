"""Live-like sources: the simulated head (rates, order, pacing, newest frame, truth) and
OpenCV cameras read from video files and image sequences (no devices needed)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import WAIT_S, FakeClock, wait_until
from trifuse.app.sources.base import FrameSetAssembler, frame_sets
from trifuse.app.sources.camera import (
    CameraConfig,
    CameraError,
    CameraSource,
    NewestFrameSlots,
    cameras_config_from_dict,
    color_to_rgb,
    counts_to_kelvin,
    load_cameras_config,
)
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.app.sources.sim.render import HeadModel
from trifuse.app.sources.simulated import SimulatedHeadSource

SENSOR_RATES = {
    "ccd_left": 30,
    "ccd_right": 30,
    "thermal_left": 27,
    "thermal_right": 27,
    "tof": 15,
}


@pytest.fixture(scope="module")
def scenario() -> InspectionScenario:
    """One scenario for the module: its renderer caches the ray grids (a cold first pose
    takes about 3 s, a warm one about 1 s). No supersampling of edges: faster, and the
    pictures' quality is not what these tests check."""
    model = HeadModel(supersample={"color": 1, "thermal": 1, "tof": 1})
    return InspectionScenario(model=model, seed=3)


# -- the simulated head ---------------------------------------------------------------------


def test_simulated_rates_order_and_rig(scenario):
    with SimulatedHeadSource(scenario, duration_s=1.0) as src:
        assert src.rig is scenario.rig
        assert src.sensors == ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
        frames = list(src.frames())
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps)
    assert all(0 <= s < 1_000_000_000 for s in stamps)
    for sensor, rate in SENSOR_RATES.items():
        own = [f.stamp_ns for f in frames if f.sensor == sensor]
        assert abs(len(own) - rate) <= 1, (sensor, len(own))
        assert np.allclose(np.diff(own), 1e9 / rate, atol=1)
    truth = default_rig()
    for name in truth.names:
        assert src.rig[name].intrinsics == truth[name].intrinsics
        assert np.allclose(src.rig[name].T_rig_sensor, truth[name].T_rig_sensor)
    by_sensor = {f.sensor: f for f in frames}
    assert by_sensor["ccd_left"].image.shape == (960, 1280, 3)
    assert by_sensor["ccd_left"].image.dtype == np.uint8
    assert by_sensor["thermal_left"].image.shape == (288, 382)
    assert by_sensor["thermal_left"].image.dtype == np.float32
    assert 250 < np.nanmedian(by_sensor["thermal_left"].image) < 350  # kelvin
    assert by_sensor["tof"].distance_m.shape == (144, 176)
    assert not by_sensor["ccd_left"].image.flags.writeable  # the cache is shared
    assert src.first_pose_s is not None and src.first_pose_s > 0  # measured


def test_simulated_frame_sets_have_all_sensors(scenario):
    with SimulatedHeadSource(scenario, duration_s=1.0) as src:
        sets = list(frame_sets(src, reference="ccd_left", tolerance_s=0.05))
    assert len(sets) == 30
    for fs in sets:
        assert set(fs.frames) == set(SENSOR_RATES), fs.missing
        assert not fs.missing
        # The nearest TOF frame is at most half a TOF period away.
        assert abs(fs["tof"].stamp_ns - fs.stamp_ns) <= 1e9 / 15 / 2 + 1
        assert abs(fs["thermal_right"].stamp_ns - fs.stamp_ns) <= 1e9 / 27 / 2 + 1


def test_simulated_rates_offsets_and_start_configurable(scenario):
    with SimulatedHeadSource(
        scenario,
        sensors=["tof", "thermal_left"],
        rates_hz={"thermal": 9.0, "tof": 5},
        offsets_s={"tof": 0.01},
        start_ns=10**18,
        duration_s=2.0,
    ) as src:
        frames = list(src.frames())
        assert src.rates_hz == {"tof": 5.0, "thermal_left": 9.0}
    tof = [f.stamp_ns - 10**18 for f in frames if f.sensor == "tof"]
    thermal = [f.stamp_ns - 10**18 for f in frames if f.sensor == "thermal_left"]
    assert len(tof) == 10 and len(thermal) == 18
    assert tof[0] == 10_000_000 and tof[1] == 210_000_000
    assert {f.sensor for f in frames} == {"tof", "thermal_left"}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sensors": ["nope"]}, "subset of the rig's sensors"),
        ({"rates_hz": {"color": 0}}, "positive number of Hz"),
        ({"rates_hz": {"lidar": 10}}, "neither sensors"),
        ({"offsets_s": {"tof": 0.5}}, "one frame period"),
        ({"render_hz": -1}, "render_hz"),
        ({"speed": 0}, "speed"),
    ],
)
def test_simulated_rejects_bad_arguments(scenario, kwargs, message):
    with pytest.raises(ValueError, match=message):
        SimulatedHeadSource(scenario, **kwargs)


def test_simulated_truth_matches_delivered_pose(scenario):
    # Two samples 0.5 s apart; waiting for the render makes each stamp show its own pose.
    with SimulatedHeadSource(
        scenario,
        sensors=["tof"],
        render_hz=2.0,
        loop_s=1.0,
        duration_s=1.0,
        wait_for_render=True,
        keep_truth=True,
    ) as src:
        assert src.pose_count == 2
        frames = list(src.frames())
        range_at = {t: src.truth_at(round(t * 1e9)).sensors["tof"].range_m for t in (0.0, 0.5)}
        assert np.nanmax(np.abs(range_at[0.0] - range_at[0.5])) > 0.01  # the head pans
        for f in frames:
            truth = src.truth_at(f.stamp_ns)
            t = f.stamp_ns / 1e9
            want = 0.0 if (t < 0.25 or t > 0.75) else 0.5
            assert truth.pose_t_s == want
            assert np.allclose(truth.T_world_rig, scenario.T_world_rig(want))
            rng = truth.sensors["tof"].range_m
            ok = np.isfinite(rng) & np.isfinite(f.distance_m)
            assert ok.mean() > 0.5
            # The delivered distances are the truth plus the TOF's noise and systematic
            # range error (up to about 0.2 m uncalibrated), and fit the other pose worse.
            err = np.abs(f.distance_m - rng)[ok]
            other = np.abs(f.distance_m - range_at[0.5 - want])[ok]
            assert np.median(err) < 0.2
            assert np.mean(err) < np.nanmean(other)
        a = range_at[0.0]
    # Without keep_truth the pose is rendered again: the same truth.
    with SimulatedHeadSource(scenario, sensors=["tof"], loop_s=1.0, duration_s=0.1) as src2:
        f0 = next(iter(src2.frames()))
        again = src2.truth_at(f0.stamp_ns)
        assert again.pose_t_s == 0.0
        np.testing.assert_array_equal(again.sensors["tof"].range_m, a)


def _paced_stream(src: SimulatedHeadSource, clock: FakeClock, until_ns: int) -> list:
    """(clock reading, frame) of a real-time stream, the frames stamped before ``until_ns``."""
    got = []
    for f in src.frames():
        if f.stamp_ns >= until_ns:
            break
        got.append((clock.now, f))
    return got


def test_simulated_realtime_pacing(scenario):
    """Real time: each frame is released when the clock reaches its stamp, every sensor at
    its own rate, nothing dropped for a consumer that keeps up (a simulated clock)."""
    clock = FakeClock(50.0)
    with SimulatedHeadSource(scenario, realtime=True, clock=clock, sleep=clock.sleep) as src:
        assert src.wait_ready(WAIT_S)
        got = _paced_stream(src, clock, 1_000_000_000)
        stats = src.stats()
    for t, f in got:
        assert t - 50.0 == pytest.approx(f.stamp_ns / 1e9, abs=1e-9), f
    for sensor, rate in SENSOR_RATES.items():
        own = [f.stamp_ns for _, f in got if f.sensor == sensor]
        assert own == [round(k * 1e9 / rate) for k in range(rate)], sensor
        assert stats[sensor]["dropped"] == 0
    assert clock.now == pytest.approx(51.0, abs=1e-9)  # waited for the frames at 1 s


def test_simulated_realtime_speed(scenario):
    """``speed`` 4: four simulated seconds per second of the clock."""
    clock = FakeClock()
    with SimulatedHeadSource(
        scenario, sensors=["tof"], realtime=True, speed=4.0, clock=clock, sleep=clock.sleep
    ) as src:
        assert src.wait_ready(WAIT_S)
        got = _paced_stream(src, clock, 2_000_000_000)
    assert [f.stamp_ns for _, f in got] == [round(k * 1e9 / 15) for k in range(30)]
    for t, f in got:
        assert 4 * t == pytest.approx(f.stamp_ns / 1e9, abs=1e-9)


def test_simulated_slow_consumer_gets_newest(scenario):
    """A consumer busy for 0.61 s gets one frame per sensor, each its newest due one (the
    older ones dropped and counted), then frames at the rate again."""
    clock = FakeClock()
    with SimulatedHeadSource(scenario, realtime=True, clock=clock, sleep=clock.sleep) as src:
        assert src.wait_ready(WAIT_S)
        it = src.frames()
        first = next(it)
        assert first.stamp_ns == 0 and first.sensor == src.sensors[0]
        clock.advance(0.61)
        batch = [next(it) for _ in range(5)]
        assert clock.now == 0.61  # all due at once
        newest = {s: src.stamp_ns(s, math.floor(0.61 * r)) for s, r in SENSOR_RATES.items()}
        assert {f.sensor: f.stamp_ns for f in batch} == newest
        stamps = [f.stamp_ns for f in batch]
        assert stamps == sorted(stamps)
        nxt = next(it)  # back to the rate: the next due frame, when its time comes
        assert nxt.stamp_ns == min(
            src.stamp_ns(s, math.floor(0.61 * r) + 1) for s, r in SENSOR_RATES.items()
        )
        assert clock.now == pytest.approx(nxt.stamp_ns / 1e9, abs=1e-9)
        stats = src.stats()
    for sensor, rate in SENSOR_RATES.items():
        delivered_before = 1 if sensor == first.sensor else 0
        assert stats[sensor]["dropped"] == math.floor(0.61 * rate) - delivered_before, sensor


def test_simulated_close_stops_thread(scenario):
    src = SimulatedHeadSource(scenario)
    assert src.render_thread_alive
    assert src.wait_ready(WAIT_S)
    it = src.frames()
    next(it)
    src.close()
    assert not src.render_thread_alive  # close() joined it
    assert list(it) == []  # the stream ends
    src.close()  # idempotent


class _HeldScenario:
    """The module's scenario, except that rendering any moment after t = 0 waits until
    ``release`` is set: the source has its first pose and nothing else meanwhile."""

    def __init__(self, inner: InspectionScenario) -> None:
        self.inner = inner
        self.rig = inner.rig
        self.pan_period_s = inner.pan_period_s
        self.release = threading.Event()

    def T_world_rig(self, t_s: float) -> np.ndarray:
        return self.inner.T_world_rig(t_s)

    def render(self, t_s: float, sensors: list[str] | None = None):
        if t_s > 0:
            assert self.release.wait(120), "test: the held render was never released"
        return self.inner.render(t_s, sensors)


def _shift_px(a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal shift (px) between two colour images by phase correlation (blurred a
    little so that the sensor noise does not take part; a Hann window so that the image
    borders do not)."""
    ga, gb = (
        cv2.GaussianBlur(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), 1.5)
        for x in (a, b)
    )
    window = cv2.createHanningWindow(ga.shape[::-1], cv2.CV_32F)
    return cv2.phaseCorrelate(ga, gb, window)[0][0]


def test_simulated_live_mode_turns_the_nearest_rendered_pose(scenario):
    """Live mode: while a pose is not rendered yet, its frames show the nearest rendered
    pose turned to its head orientation (the picture moves from the start instead of
    standing still); once it is rendered, the rendering itself."""
    held = _HeldScenario(scenario)
    src = SimulatedHeadSource(held, live=True, cache_dir=False, render_process=False)
    try:
        assert src.live and src.wait_ready(120)
        first = None
        turned = None
        for f in src.frames():  # as fast as asked: pose 1 (t = 0.5 s) is still held
            if f.sensor != "ccd_left":
                continue
            if f.stamp_ns == 0:
                first = f.image
            if f.stamp_ns >= 500_000_000:  # sample 1 of the cache (2 Hz)
                turned = f.image
                break
        assert first is not None and turned is not None
        assert src.rendered_count == 1 and src.provisional_made >= 1
        assert not turned.flags.writeable
        # The truth: the head at 0.5 s, rendered once the render is released.
        held.release.set()
        real = scenario.render(0.5, ["ccd_left"])[0]["ccd_left"].image
        # Pose 0 is off by the turn (2.09 deg: 48.6 px); the turned picture is not.
        yaw = np.radians(held.inner.pan_deg * np.sin(2 * np.pi * 0.5 / 30.0))
        fx = scenario.rig["ccd_left"].intrinsics.fx
        assert abs(_shift_px(first, real)) == pytest.approx(fx * np.tan(yaw), rel=0.05)
        assert abs(_shift_px(turned, real)) < 0.5
        # Once rendered, frames of that pose show the rendering itself.
        wait_until(lambda: src.rendered_count >= 2, "the held pose to be rendered")
        for f in src.frames():
            if f.sensor == "ccd_left" and f.stamp_ns >= 500_000_000:
                np.testing.assert_array_equal(f.image, real)
                break
    finally:
        held.release.set()
        src.close()


def test_first_minute_benchmark_measures_moves_and_stills():
    """``trifuse bench --only sim-first-minute`` judges the picture by the JPEGs the
    viewer receives: a new size is a change, changes within 0.15 s are one move."""
    from trifuse.app.devtools.bench import REGISTRY
    from trifuse.app.devtools.bench_motion import motion_figures

    assert {"sim-first-minute", "sim-live"} <= set(REGISTRY)
    pictures = [(0.0, 10), (0.1, 10), (0.5, 11), (0.55, 12), (1.0, 12), (2.5, 13), (3.2, 14)]
    got = motion_figures(pictures, 0.0, 3.0)  # the last picture is after the window
    assert got == {
        "moves_per_s": pytest.approx(2 / 3),  # at 0.5 (with 0.55) and 2.5 s
        "longest_still_s": pytest.approx(2.0),  # 0.5 .. 2.5 s
        "pictures_per_s": pytest.approx(6 / 3),
        "distinct": 4.0,
    }
    assert motion_figures([(0.0, 1), (1.0, 1)], 0.0, 60.0)["longest_still_s"] == 60.0


def test_simulated_live_mode_needs_a_turning_head():
    from trifuse.app.sources.sim.scenarios import CalibrationScenario

    with pytest.raises(ValueError, match="only the head turns"):
        SimulatedHeadSource(CalibrationScenario(n_poses=2), live=True)


# -- newest-frame slots ---------------------------------------------------------------------


def test_newest_frame_slots_keep_only_newest():
    slots = NewestFrameSlots(["a", "b"])
    img = np.zeros((2, 2), np.float32)
    for i in range(5):
        slots.put(Frame("a", i, img))
    slots.put(Frame("b", 3, img))
    assert [(f.sensor, f.stamp_ns) for f in (slots.take(0), slots.take(0))] == [
        ("b", 3),
        ("a", 4),
    ]
    assert slots.take(0) is None
    assert slots.stats()["a"] == {
        "received": 5,
        "delivered": 1,
        "dropped": 4,
        "last_stamp_ns": 4,
        "finished": False,
    }
    with pytest.raises(KeyError, match="unknown sensor"):
        slots.put(Frame("c", 0, img))


# -- OpenCV cameras -------------------------------------------------------------------------


def wait_for_state(src: CameraSource, sensor: str, state: str) -> None:
    wait_until(lambda: src.status()[sensor].state == state, f"{sensor} {state}")


def write_video(path: Path, n: int, size=(64, 48)) -> Path:
    """An MJPG .avi whose frames are red (RGB 200, 0, 0) with a green bar of width 2i."""
    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (w, h))
    assert writer.isOpened()
    for i in range(n):
        bgr = np.zeros((h, w, 3), np.uint8)
        bgr[..., 2] = 200
        bgr[:, : 2 * i, 1] = 255
        writer.write(bgr)
    writer.release()
    return path


def write_sequence(folder: Path, stem: str, images: list[np.ndarray]) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        assert cv2.imwrite(str(folder / f"{stem}_{i:03d}.png"), img)
    return str(folder / f"{stem}_%03d.png")


def test_camera_video_file_gives_rgb(tmp_path):
    video = write_video(tmp_path / "colour.avi", 20)
    cfg = CameraConfig("ccd_left", str(video), "color", max_rate_hz=200)
    with CameraSource([cfg]) as src:
        frames = list(src.frames())  # ends at the end of the file
        status = src.status()["ccd_left"]
    assert status.state == "stopped" and "end of file" in status.reason
    assert status.frames == 20 and status.size == (64, 48)
    assert 1 <= len(frames) <= 20
    for f in frames:
        assert f.sensor == "ccd_left"
        assert f.image.shape == (48, 64, 3) and f.image.dtype == np.uint8
        right = f.image[:, -8:].reshape(-1, 3).mean(axis=0)  # never under the green bar
        assert right[0] > 180 and right[2] < 20  # red stays red: BGR became RGB
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps)
    assert abs(stamps[0] / 1e9 - time.time()) < 60  # host clock


def test_camera_image_sequence_16bit_thermal_kelvin(tmp_path):
    rng = np.random.default_rng(1)
    counts = [rng.integers(27000, 33000, (288, 382), dtype=np.uint16) for _ in range(4)]
    for c in counts:
        c[0, :5] = 0  # no reading
    pattern = write_sequence(tmp_path / "th", "frame", counts)
    cfg = CameraConfig("thermal_left", pattern, "thermal", max_rate_hz=20)
    with CameraSource([cfg]) as src:
        got = list(src.frames())
    assert 1 <= len(got) <= 4
    for f in got:
        # Which image it is (a slow consumer may have missed some): 16 bits arrive exactly.
        k = int(np.argmin([abs(float(f.image[10, 10]) - c[10, 10] * 0.01) for c in counts]))
        want = (counts[k].astype(np.float64) * 0.01).astype(np.float32)
        want[counts[k] == 0] = np.nan
        assert f.image.dtype == np.float32
        np.testing.assert_array_equal(f.image, want)
        assert np.isnan(f.image[0, :5]).all()
    # Scale and offset (raw counts of a core, kelvin = counts * 0.04 + 100).
    cfg2 = CameraConfig("thermal_left", pattern, "thermal", scale=0.04, offset=100.0)
    with CameraSource([cfg2]) as src:
        f = src.take(WAIT_S)
    k = int(np.argmin([abs(float(f.image[10, 10]) - (c[10, 10] * 0.04 + 100.0)) for c in counts]))
    np.testing.assert_allclose(f.image[10], counts[k][10] * 0.04 + 100.0, rtol=1e-6)


def test_camera_drops_frames_when_consumer_is_slow(tmp_path):
    images = [np.full((24, 32, 3), 5 * i, np.uint8) for i in range(40)]
    pattern = write_sequence(tmp_path / "c", "c", images)
    cfg = CameraConfig("ccd_left", pattern, "color", max_rate_hz=400)
    with CameraSource([cfg]) as src:
        first = src.take(WAIT_S)
        wait_for_state(src, "ccd_left", "stopped")  # the reader reads all 40 meanwhile
        rest = list(src.frames())
        stats = src.stats()["ccd_left"]
    assert first.image[0, 0, 0] < 5 * 39
    assert len(rest) == 1 and rest[0].image[0, 0, 0] == 5 * 39  # only the newest survives
    assert stats["received"] == 40
    assert stats["dropped"] == 40 - 2


def test_camera_open_failure_names_device(tmp_path):
    video = write_video(tmp_path / "ok.avi", 5)
    missing = str(tmp_path / "no_such_camera.avi")
    configs = [
        CameraConfig("ccd_left", str(video), "color"),
        CameraConfig("thermal_left", missing, "thermal"),
    ]
    with pytest.raises(CameraError, match=r"sensor 'thermal_left' \(device '.*no_such_camera"):
        CameraSource(configs)
    with pytest.raises(CameraError, match=r"device 7\).*cannot open"):
        CameraSource([CameraConfig("ccd_right", 7, "color", backend="v4l2")], open_timeout_s=5)
    # Not strict: the others run; the failed sensor is reported, and missing in frame sets.
    with CameraSource(configs, strict=False) as src:
        status = src.status()
        assert status["thermal_left"].state == "failed"
        assert "no_such_camera" in status["thermal_left"].reason
        assembler = FrameSetAssembler(src.sensors, reference="ccd_left")
        sets = []
        for f in src.frames():
            sets += assembler.push(f)
        sets += assembler.flush()
    assert sets and all("thermal_left" in fs.missing for fs in sets)
    assert all("ccd_left" in fs for fs in sets)


def test_camera_one_stops_others_continue(tmp_path):
    short = write_sequence(tmp_path / "s", "s", [np.full((24, 32), 100, np.uint16)] * 3)
    long_ = write_sequence(
        tmp_path / "l", "l", [np.full((24, 32, 3), i, np.uint8) for i in range(5)]
    )
    configs = [
        CameraConfig("thermal_left", short, "thermal", max_rate_hz=100),
        CameraConfig("ccd_left", long_, "color", max_rate_hz=50, loop=True),
    ]
    with CameraSource(configs) as src:
        wait_for_state(src, "thermal_left", "stopped")  # the short sequence has ended
        stopped_ns = time.time_ns()  # frames are stamped with this clock when grabbed
        seen = []
        for f in src.frames():  # until three frames grabbed after the stop
            seen.append(f)
            if sum(g.stamp_ns > stopped_ns for g in seen) >= 3:
                break
        status = src.status()
    assert status["thermal_left"].state == "stopped"
    assert "end of file" in status["thermal_left"].reason
    assert status["ccd_left"].state == "running", status["ccd_left"]
    # thermal frames grabbed before the stop may still be queued; none may come after it
    late = [f for f in seen if f.stamp_ns > stopped_ns]
    assert {f.sensor for f in late} == {"ccd_left"}  # looping over its 5 images


def test_camera_config_yaml(tmp_path):
    video = write_video(tmp_path / "v.avi", 5)
    (tmp_path / "cams.yaml").write_text(
        "format: trifuse-cameras/1\n"
        "stall_timeout_s: 1.5\n"
        "sensors:\n"
        "  ccd_left: {device: v.avi, max_rate_hz: 100}\n"
        "  thermal_left: {device: 4, modality: thermal, scale: 0.04, offset: 100}\n"
    )
    cfg = load_cameras_config(tmp_path / "cams.yaml")
    left, thermal = cfg.sensors
    assert left.device == str(video) and left.modality == "color" and left.is_file
    assert thermal.device == 4 and thermal.scale == 0.04 and thermal.offset == 100.0
    assert cfg.stall_timeout_s == 1.5
    bad = {
        "format: trifuse-cameras/1\nsensors:\n  tof: {device: 0}\n": "push ingest",
        "format: trifuse-cameras/1\nsensors:\n  a: {device: 0, colour: x}\n": "unknown keys",
        "sensors:\n  ccd: {device: 0}\n": "format",
        "format: trifuse-cameras/1\nsensors:\n  cam: {device: 0}\n": "missing 'modality'",
        "format: trifuse-cameras/1\nsensors:\n  ccd: {device: 0, width: -3}\n": "width",
    }
    for text, message in bad.items():
        path = tmp_path / "bad.yaml"
        path.write_text(text)
        with pytest.raises(CameraError, match=message) as err:
            load_cameras_config(path)
        assert str(path) in str(err.value)
    with pytest.raises(CameraError, match="backend"):
        cameras_config_from_dict(
            {"format": "trifuse-cameras/1", "sensors": {"ccd": {"device": 0, "backend": "dshow"}}}
        )


def test_pixel_conversions():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    rgb = color_to_rgb(grey)
    assert rgb.shape == (3, 4, 3) and (rgb[..., 0] == grey).all()
    bgra = np.zeros((2, 2, 4), np.uint8)
    bgra[..., 0] = 255  # blue
    assert (color_to_rgb(bgra)[..., 2] == 255).all()
    # The raw Y16 buffer some V4L2 backends hand over with CONVERT_RGB = 0.
    counts = np.arange(6, dtype=np.uint16).reshape(2, 3) + 30000
    raw = counts.astype("<u2").view(np.uint8).reshape(1, -1)
    kelvin = counts_to_kelvin(raw, 0.01, 0.0, size=(3, 2))
    np.testing.assert_array_equal(kelvin, (counts * 0.01).astype(np.float32))
    colour = np.zeros((2, 3, 3), np.uint8)
    colour[..., 0] = 9
    with pytest.raises(CameraError, match="false-colour"):
        counts_to_kelvin(colour, 0.01, 0.0)
    assert math.isnan(counts_to_kelvin(np.zeros((1, 1), np.uint16), 0.01, 0.0)[0, 0])


class _FakeDevice:
    """Stands in for cv2.VideoCapture on a device index: n frames, then nothing (unplugged)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.props: dict[int, float] = {}
        self.released = False

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return {cv2.CAP_PROP_FRAME_WIDTH: 8.0, cv2.CAP_PROP_FRAME_HEIGHT: 6.0}.get(prop, 0.0)

    def grab(self) -> bool:
        if self.n <= 0:
            time.sleep(0.01)
            return False
        self.n -= 1
        time.sleep(0.005)
        return True

    def retrieve(self):
        # What V4L2 hands over for Y16 with CONVERT_RGB = 0 on some versions: a raw buffer.
        counts = np.full((6, 8), 30000, np.uint16)
        return True, counts.view(np.uint8).reshape(1, -1)

    def release(self) -> None:
        self.released = True


def test_camera_device_that_stops_is_reported_and_others_continue(tmp_path, monkeypatch):
    real = cv2.VideoCapture
    devices: list[_FakeDevice] = []

    def fake_capture(device, api=cv2.CAP_ANY):
        if isinstance(device, int):
            devices.append(_FakeDevice(10))
            return devices[-1]
        return real(device, api)

    monkeypatch.setattr(cv2, "VideoCapture", fake_capture)
    colour = write_sequence(
        tmp_path / "l", "l", [np.full((24, 32, 3), i, np.uint8) for i in range(5)]
    )
    configs = [
        CameraConfig("thermal_left", 3, "thermal"),
        CameraConfig("ccd_left", colour, "color", max_rate_hz=50, loop=True),
    ]
    with CameraSource(configs, stall_timeout_s=0.3) as src:
        dev = devices[0]
        assert dev.props[cv2.CAP_PROP_CONVERT_RGB] == 0
        assert dev.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"Y16 ")
        f = src.take(WAIT_S)
        while f.sensor != "thermal_left":
            f = src.take(WAIT_S)
        np.testing.assert_array_equal(f.image, np.full((6, 8), 300.0, np.float32))
        wait_for_state(src, "thermal_left", "stopped")  # 10 frames, then 0.3 s of silence
        status = src.status()
        assert status["thermal_left"].state == "stopped"
        assert "no frame for 0.3 s" in status["thermal_left"].reason
        assert "device 3" in status["thermal_left"].reason
        assert dev.released
        assert status["ccd_left"].state == "running"
        later = [src.take(WAIT_S) for _ in range(6)]
        assert {g.sensor for g in later[1:]} == {"ccd_left"}
