"""Per-sensor health ("a sensor that stops sending, or sends garbage, is shown as such while
the rest keeps working"): the garbage check, the classification with injected times, the
monitor, the push ingest's per-sensor rejections, the fallback reference of the frame-set
assembly, the pipeline fusing without a dead sensor, and the whole console over a
PushSource with one sensor silent and two sending garbage."""

from __future__ import annotations

import threading
import time
from typing import ClassVar

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.support import ListSource, small_rig, synth_frame, wait_until
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.panels.source import health_text
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.sensor_health import (
    SUBSAMPLE,
    Expected,
    HealthMonitor,
    Rejections,
    SensorFacts,
    check_frame,
    classify,
    expected_of,
    human_s,
    short_error,
    silence_threshold_s,
)
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.base import FrameSetAssembler
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.encode import encode_frame
from trifuse.app.sources.push.protocol import PushError
from trifuse.app.sources.push.source import PushSource

RIG = small_rig()
EXPECTED = expected_of(RIG)
SENSORS = RIG.names


def good(sensor: str, stamp_ns: int = 1_000_000_000, seed: int = 0) -> Frame:
    return synth_frame(RIG, sensor, stamp_ns, np.random.default_rng(seed))


def check(frame: Frame) -> str | None:
    return check_frame(frame, EXPECTED[frame.sensor])


# -- the garbage check ----------------------------------------------------------------------


def test_legitimate_frames_pass() -> None:
    for s in SENSORS:
        assert check(good(s)) is None, s
    tof = good("tof")
    w, h = RIG["tof"].image_size
    # a TOF looking at the sky: one finite pixel anywhere (not on the subsample grid) is a frame
    sparse = np.full((h, w), np.nan, np.float32)
    sparse[h - 1, w - 2] = 4.2
    assert check(Frame("tof", 1, tof.image, sparse)) is None
    few = np.full((h, w), np.nan, np.float32)
    few[:3, :9] = 2.5  # a few valid pixels sharing one value: fine for a TOF
    assert check(Frame("tof", 1, tof.image, few)) is None
    # a dark, a saturated colour picture, a thermal frame with some NaN: pictures all the same
    for v in (0, 255):
        assert check(Frame("ccd_left", 1, np.full((96, 128, 3), v, np.uint8))) is None
    th = good("thermal_left").image.copy()
    th[:36] = np.nan
    assert check(Frame("thermal_left", 1, th)) is None
    # one hot pixel within the range is enough (e.g. an uncalibrated offset elsewhere)
    cold = np.full((72, 96), 20.0, np.float32) + np.random.default_rng(0).random((72, 96))
    cold[71, 95] = 300.0
    assert check(Frame("thermal_left", 1, cold.astype(np.float32))) is None


@pytest.mark.parametrize(
    ("frame", "why"),
    [
        (Frame("tof", 1, good("tof").image, np.full((36, 44), np.nan, np.float32)), "all NaN"),
        (Frame("tof", 1, good("tof").image, np.full((36, 44), 25.0, np.float32)), "implausible"),
        (Frame("tof", 1, good("tof").image, -np.ones((36, 44), np.float32)), "implausible"),
        (Frame("tof", 1, good("tof").image, None), "no distance"),
        (Frame("tof", 1, np.zeros((10, 10), np.float32), good("tof").distance_m), "amplitude"),
        (Frame("thermal_left", 1, np.zeros((72, 96), np.float32)), "implausible: 0..0 K"),
        (Frame("thermal_left", 1, np.full((72, 96), np.nan, np.float32)), "all NaN"),
        (Frame("thermal_left", 1, np.full((72, 96), 300.0, np.float32)), "all 300 K"),
        (Frame("thermal_left", 1, np.full((40, 50), 300.0, np.float32)), "50x40 (expected 96x72)"),
        (Frame("thermal_left", 1, np.zeros((72, 96, 3), np.float32)), "shape"),
        (Frame("ccd_left", 1, np.zeros((48, 64, 3), np.uint8)), "64x48 (expected 128x96)"),
        (Frame("ccd_left", 1, np.zeros((96, 128), np.uint8)), "shape"),
        (Frame("ccd_left", 1, np.zeros((96, 128, 3), np.float32)), "float32"),
        (Frame("ccd_left", 1, np.zeros((0, 0, 3), np.uint8)), "empty"),
    ],
)
def test_garbage_is_named(frame: Frame, why: str) -> None:
    got = check(frame)
    assert got is not None and why in got, got


def test_without_a_rig_the_modality_is_guessed() -> None:
    assert check_frame(good("tof")) is None and check_frame(good("ccd_left")) is None
    nan_tof = Frame("x", 1, good("tof").image, np.full((36, 44), np.nan, np.float32))
    assert "all NaN" in check_frame(nan_tof)
    assert "all NaN" in check_frame(Frame("x", 1, np.full((4, 4), np.nan, np.float32)))
    assert check_frame(Frame("x", 1, np.zeros((4, 4, 3), np.uint8)), Expected("color")) is None


class _Watched(np.ndarray):
    """An array that notes the size of every array numpy computes on (ufuncs and their
    reductions: comparisons, isfinite, min, any ...), views and selections of it included."""

    sizes: ClassVar[list[int]] = []

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        _Watched.sizes += [x.size for x in inputs if isinstance(x, np.ndarray)]
        plain = [x.view(np.ndarray) if isinstance(x, _Watched) else x for x in inputs]
        return getattr(ufunc, method)(*plain, **kwargs)


def test_the_check_of_a_usable_frame_reads_a_subsample() -> None:
    """The check is cheap on full-size frames: for a usable frame numpy computes only on a
    subsample of about SUBSAMPLE pixels, never on the whole frame (how long it takes is
    the machine's business)."""
    rng = np.random.default_rng(1)
    color = rng.integers(0, 255, (960, 1280, 3), dtype=np.uint8)
    thermal = (290 + rng.normal(0, 1, (288, 382))).astype(np.float32)
    dist = (1 + 5 * rng.random((480, 640))).astype(np.float32)
    dist[rng.random(dist.shape) < 0.3] = np.nan
    frames = [
        (Frame("c", 0, color.view(_Watched)), Expected("color", (1280, 960))),
        (Frame("t", 0, thermal.view(_Watched)), Expected("thermal", (382, 288))),
        (Frame("f", 0, dist.view(_Watched), dist.view(_Watched)), Expected("tof", (640, 480))),
    ]
    most = 4 * SUBSAMPLE[0] * SUBSAMPLE[1]  # the strides round down: up to 2x each way
    for f, e in frames:
        _Watched.sizes = []
        assert check_frame(f, e) is None
        assert max(_Watched.sizes, default=0) <= most < f.image.size / 4, (f.sensor, most)
    assert _Watched.sizes  # the TOF distances were looked at
    # A suspicious subsample is confirmed on the full frame: one valid pixel is enough.
    nan_but_one = np.full((480, 640), np.nan, np.float32)
    nan_but_one[1, 1] = 2.0  # not on the subsample's grid
    _Watched.sizes = []
    assert check_frame(Frame("f", 0, dist, nan_but_one.view(_Watched)), Expected("tof")) is None
    assert max(_Watched.sizes) == nan_but_one.size


# -- classification with injected times -----------------------------------------------------


def test_threshold_is_max_of_a_second_and_five_periods() -> None:
    assert silence_threshold_s(None) == 1.0
    assert silence_threshold_s(1 / 30) == 1.0
    assert silence_threshold_s(0.5) == pytest.approx(2.5)
    assert human_s(0.42) == "0.4 s" and human_s(12.4) == "12 s" and human_s(600) == "10 min"


def test_states_over_time() -> None:
    never = classify("tof", SensorFacts(), 100.0)
    assert never.state == "never" and never.last_frame_age_s is None
    assert never.reason == "no frame received yet" and never.line() == "tof: no frame yet"

    facts = SensorFacts(last_good_s=100.0, period_s=0.1)
    assert classify("tof", facts, 100.5, rate_hz=10.0).state == "ok"
    assert classify("tof", facts, 100.99).state == "ok"  # threshold max(1 s, 0.5 s)
    silent = classify("tof", facts, 112.0)
    assert silent.state == "silent" and silent.last_frame_age_s == pytest.approx(12.0)
    assert silent.line() == "tof: silent for 12 s"
    assert "no frame for 12 s" in silent.reason

    slow = SensorFacts(last_good_s=100.0, period_s=0.5)  # a 2 Hz sensor: 2.5 s of patience
    assert classify("t", slow, 102.4).state == "ok" and classify("t", slow, 102.6).state == "silent"

    # paused replay: nobody is silent
    paused = classify("tof", facts, 200.0, paused=True)
    assert paused.state == "ok" and paused.reason == "replay paused"

    # a camera reader that stopped says why
    dead = SensorFacts(last_good_s=100.0, device_state="stopped", device_reason="end of file")
    assert "end of file" in classify("c", dead, 105.0).reason
    assert classify("c", dead, 105.0).line() == "c: silent for 5.0 s (end of file)"
    failed = SensorFacts(device_state="failed", device_reason="cannot open /dev/video9")
    got = classify("c", failed, 105.0)
    assert got.state == "never" and "video9" in got.reason
    assert got.line() == "c: no frame yet (cannot open /dev/video9)"


def test_failing_while_bad_frames_arrive_then_silent_then_ok() -> None:
    bad = SensorFacts(
        last_good_s=100.0,
        last_bad_s=104.0,
        bad_since_good=40,
        bad_reason="distance all NaN",
        period_s=0.1,
    )
    h = classify("tof", bad, 104.1)
    assert h.state == "failing" and h.reason.startswith("40 frames rejected (distance all NaN)")
    assert h.line().startswith("tof: failing: 40 frames rejected (distance all NaN)")
    assert h.last_frame_age_s == pytest.approx(4.1)
    # the bad frames stopped too: silent, saying what came last
    later = classify("tof", bad, 110.0)
    assert later.state == "silent" and "40 frames rejected" in later.reason
    # bad frames only, never a good one: failing, then "never"
    only_bad = SensorFacts(last_bad_s=104.0, bad_since_good=3, bad_reason="bad size")
    assert classify("t", only_bad, 104.5).state == "failing"
    assert classify("t", only_bad, 120.0).state == "never"
    # a good frame after the bad ones: ok again (saying some were rejected)
    recovered = SensorFacts(last_good_s=104.2, last_bad_s=104.0, bad_reason="x", period_s=0.1)
    h = classify("tof", recovered, 104.3)
    assert h.state == "ok" and "rejected" in h.reason


def test_monitor_observes_frames_and_merges_rejections() -> None:
    m = HealthMonitor(SENSORS, EXPECTED)
    t = 1000.0
    for k in range(20):  # all sensors at 10 Hz
        for s in SENSORS:
            assert m.observe(good(s, 1_000_000_000 + k * 100_000_000, k), t + k * 0.1) is None
    t_end = t + 1.9
    r = m.report(t_end + 0.05)
    assert all(h.state == "ok" for h in r.values()), r
    assert m.facts()["tof"].period_s == pytest.approx(0.1)
    # tof sends garbage, thermal_right goes quiet, thermal_left's messages are rejected
    nan = Frame("tof", 3_000_000_000, good("tof").image, np.full((36, 44), np.nan, np.float32))
    for k in range(1, 16):
        now = t_end + k * 0.1
        assert m.observe(nan, now) == "distance all NaN"
        for s in ("ccd_left", "ccd_right"):
            m.observe(good(s, 3_000_000_000 + k), now)
    now = t_end + 1.6
    rejections = {
        "thermal_left": Rejections(
            7,
            now - 0.05,
            "sensor 'thermal_left' at stamp_ns 5, part 0: bad size: expected 96x72 "
            "(width x height) for 'thermal_left', got 50x40",
        )
    }
    r = m.report(now, rejections=rejections, rates_hz={"ccd_left": 10.0})
    assert r["ccd_left"].state == "ok" and r["ccd_left"].rate_hz == 10.0
    assert r["ccd_right"].state == "ok"
    assert r["tof"].state == "failing"
    assert "15 frames rejected (distance all NaN)" in r["tof"].reason
    assert r["thermal_right"].state == "silent" and r["thermal_right"].last_frame_age_s > 1.5
    assert r["thermal_left"].state == "failing"
    assert "7 frames rejected (bad size: expected 96x72" in r["thermal_left"].reason
    text = health_text(r)
    assert text.count("⚠") == 3 and "⚠ thermal_right: silent for 1.6 s" in text
    assert "tof: failing: 15 frames rejected (distance all NaN)" in text


def test_short_error_drops_the_push_prefix() -> None:
    assert short_error("sensor 'tof' at stamp_ns 12, part 1 (distance): corrupt png16") == (
        "corrupt png16"
    )
    assert short_error("unknown sensor 'x'") == "unknown sensor 'x'"
    assert len(short_error("x" * 500)) == 160


# -- the push ingest counts rejections per sensor -------------------------------------------


def test_push_source_counts_rejections_per_sensor() -> None:
    src = PushSource(RIG)
    try:
        wrong = Frame("thermal_left", 5, np.full((40, 50), 300.0, np.float32))
        for _ in range(3):
            with pytest.raises(PushError, match="bad size"):
                src.accept(encode_frame(wrong, "thermal"))
        with pytest.raises(PushError):
            src.accept(b"TFP1 garbage")  # no sensor to blame: counted only in total
        stats = src.stats()
        assert stats["rejected"] == 4
        by = stats["rejected_by_sensor"]
        assert set(by) == set(SENSORS)
        tl = by["thermal_left"]
        assert tl["rejected"] == 3 and tl["since_accepted"] == 3 and "bad size" in tl["last_error"]
        assert tl["last_rejected_s"] <= time.monotonic() and tl["last_accepted_s"] is None
        src.accept(encode_frame(good("thermal_left"), "thermal"))
        tl = src.stats()["rejected_by_sensor"]["thermal_left"]
        assert tl["rejected"] == 3 and tl["since_accepted"] == 0 and tl["last_accepted_s"]
        assert by["tof"]["rejected"] == 0
    finally:
        src.close()


# -- the frame sets go on without the left colour camera ------------------------------------


def test_fallback_reference_when_the_left_colour_camera_stops() -> None:
    img = np.zeros((2, 2, 3), np.uint8)
    asm = FrameSetAssembler(
        ["ccd_left", "ccd_right"], reference="ccd_left", fallback="ccd_right", tolerance_s=0.01
    )
    sets = []
    for k in range(60):  # 30 Hz; ccd_left stops after 1 s
        t = k * 33_333_333
        if k < 30:
            sets += asm.push(Frame("ccd_left", t, img))
        sets += asm.push(Frame("ccd_right", t + 1000, img))
    assert len([s for s in sets if "ccd_left" in s.frames]) == 30
    late = [s for s in sets if "ccd_left" not in s.frames]
    assert 10 <= len(late) <= 16  # after 0.5 s (and 3 frames) the right camera opens the sets
    assert all("ccd_left" in s.missing and "ccd_right" in s.frames for s in late)
    assert late[0].stamp_ns - 29 * 33_333_333 > 0.5e9
    # the left camera comes back: it opens the sets again
    back = asm.push(Frame("ccd_left", 60 * 33_333_333, img))
    back += asm.push(Frame("ccd_right", 60 * 33_333_333 + 1000, img))
    back += asm.push(Frame("ccd_left", 61 * 33_333_333, img))
    assert back and all(s.frames.keys() >= {"ccd_left"} for s in back)
    # no fallback without one; a bad fallback is refused
    plain = FrameSetAssembler(["ccd_left", "ccd_right"])
    assert all(plain.push(Frame("ccd_right", k * 10**8, img)) == [] for k in range(40))
    with pytest.raises(ValueError, match="fallback"):
        FrameSetAssembler(["ccd_left"], fallback="ccd_left")


def test_a_seek_forward_does_not_switch_to_the_fallback() -> None:
    img = np.zeros((2, 2, 3), np.uint8)
    asm = FrameSetAssembler(["ccd_left", "ccd_right"], fallback="ccd_right", tolerance_s=0.01)
    sets = []
    for t in (0, 33_000_000, 66_000_000):
        sets += asm.push(Frame("ccd_left", t, img)) + asm.push(Frame("ccd_right", t + 1, img))
    jump = 10**10  # 10 s later: the right camera's frame happens to come first
    sets += asm.push(Frame("ccd_right", jump + 1, img))
    sets += asm.push(Frame("ccd_left", jump, img))
    assert all(s.frames.get("ccd_left") is not None for s in sets)


# -- the pipeline fuses without the dead sensors ----------------------------------------------


def test_pipeline_goes_on_without_the_left_colour_and_right_thermal() -> None:
    frames = []
    for k in range(60):  # 30 Hz; after 1 s ccd_left and thermal_right stop
        t = 1_000_000_000 + k * 33_333_333
        for s in SENSORS:
            if k >= 30 and s in ("ccd_left", "thermal_right"):
                continue
            frames.append(good(s, t, k))
    hub = FrameHub()
    pipeline = FusionPipeline(ListSource(frames, RIG.names), RIG, hub).start()
    assert pipeline.join(60) and pipeline.status.error is None
    assert pipeline.status.frames_out >= 30 + 10  # fused frames went on without them
    meta = hub.latest.meta
    assert {"ccd_left", "thermal_right"} <= set(meta["missing"])
    assert meta["mode"] == pipeline.settings.mode  # still fused: the left eye has its thermal
    assert "health" not in meta  # no console around it: no health lines


def test_the_tap_withholds_garbage_and_reports_it() -> None:
    nan_tof = Frame("tof", 2, good("tof").image, np.full((36, 44), np.nan, np.float32))
    small_thermal = Frame("thermal_right", 3, np.full((40, 50), 300.0, np.float32))
    frames = [good("ccd_left", 1), nan_tof, small_thermal, good("thermal_left", 4)]
    tap = SourceTap(ListSource(frames, RIG.names, RIG))
    got = list(tap.frames())
    assert [f.sensor for f in got] == ["ccd_left", "thermal_left"]
    r = tap.health.report()
    assert r["tof"].state == "failing" and "distance all NaN" in r["tof"].reason
    assert r["thermal_right"].state == "failing" and "50x40" in r["thermal_right"].reason
    assert r["ccd_left"].state == "ok" and r["ccd_right"].state == "never"
    assert tap.meter.rates_hz()["tof"] > 0  # counted as arriving all the same


# -- the console over a PushSource: one sensor silent, two sending garbage ------------------


class Pusher:
    """Pushes frames of every sensor at ``hz`` until stopped; ``mode`` says what each sends."""

    def __init__(self, source: PushSource, hz: float = 20.0) -> None:
        self.source, self.period = source, 1.0 / hz
        self.broken = False
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        rng = np.random.default_rng(3)
        self.frames = {s: synth_frame(RIG, s, 1, rng) for s in SENSORS}
        self.nan_distance = np.full((36, 44), np.nan, np.float32)
        self.small_thermal = np.full((40, 50), 300.0, np.float32)

    def start(self) -> Pusher:
        self._thread.start()
        return self

    def _send(self, frame: Frame) -> None:
        try:
            self.source.accept(encode_frame(frame, RIG[frame.sensor].modality))
        except PushError:
            pass  # the console counts it; a driver would get an error reply

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            stamp = time.time_ns()
            for s, f in self.frames.items():
                if not self.broken:
                    self._send(Frame(s, stamp, f.image, f.distance_m))
                elif s == "thermal_right":
                    continue  # stopped sending
                elif s == "tof":
                    self._send(Frame(s, stamp, f.image, self.nan_distance))
                elif s == "thermal_left":
                    self._send(Frame(s, stamp, self.small_thermal))
                else:
                    self._send(Frame(s, stamp, f.image, f.distance_m))
            self.sent += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)


def wait_for(client: TestClient, what) -> dict:
    """The console's status once ``what(status)`` holds."""
    seen: list[dict] = []

    def status() -> dict | None:
        seen[:] = [client.get("/api/status").json()]
        return seen[0] if what(seen[0]) else None

    return wait_until(status, lambda: f"a status like that; the last one: {seen}")


def test_console_shows_silent_and_failing_sensors_while_fusion_goes_on() -> None:
    source = PushSource(RIG)
    hub = FrameHub()
    pipeline = FusionPipeline(SourceTap(source), RIG, hub).start()
    control = SourceControl(pipeline, hub, "frames pushed to /ingest")
    client = TestClient(create_app(hub, None, pipeline, control))
    pusher = Pusher(source).start()
    try:
        s = wait_for(
            client,
            lambda s: (
                s["frames_out"] > 10
                and set(s["sensors"]) == set(SENSORS)
                and all(v["state"] == "ok" for v in s["sensors"].values())
            ),
        )
        assert s["sensors"]["tof"]["last_frame_age_s"] >= 0  # ok: not silent
        pusher.broken = True
        s = wait_for(
            client,
            lambda s: (
                s["sensors"]["thermal_right"]["state"] == "silent"
                and s["sensors"]["tof"]["state"] == "failing"
                and s["sensors"]["thermal_left"]["state"] == "failing"
            ),
        )
        seq_broken = hub.latest.seq
        sensors = s["sensors"]
        assert "no frame for" in sensors["thermal_right"]["reason"]
        assert sensors["thermal_right"]["last_frame_age_s"] > 1.0
        assert "frames rejected (distance all NaN)" in sensors["tof"]["reason"]
        assert sensors["tof"]["rate_hz"] > 0  # arriving, but garbage
        assert "frames rejected (bad size: expected 96x72" in sensors["thermal_left"]["reason"]
        assert "got 50x40" in sensors["thermal_left"]["reason"]
        assert sensors["ccd_left"]["state"] == sensors["ccd_right"]["state"] == "ok"
        assert {"thermal_left", "thermal_right"} <= set(s["missing"])
        assert s["error"] is None

        # fusion goes on with the colour cameras: frames keep being published, and their
        # metadata names the sick sensors (for the viewer's overlay)
        wait_until(
            lambda: (
                hub.latest.seq >= seq_broken + 10 and len(hub.latest.meta.get("health", {})) >= 3
            ),
            "10 more fused frames naming three sick sensors",
        )
        meta = hub.latest.meta
        assert set(meta["health"]) == {"thermal_left", "thermal_right", "tof"}
        assert meta["health"]["thermal_right"].startswith("thermal_right: silent for")
        assert meta["health"]["tof"].startswith("tof: failing: ")
        text = health_text(control.sensor_health())
        assert "⚠ thermal_right: silent for" in text and "⚠ tof: failing:" in text

        # the sensors come back: ok again
        pusher.broken = False
        wait_for(client, lambda s: all(v["state"] == "ok" for v in s["sensors"].values()))
    finally:
        pusher.stop()
        pipeline.stop()
