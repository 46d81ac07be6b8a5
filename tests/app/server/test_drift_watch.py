"""The console's background drift check (app/server/runtime/drift_watch.py): with a stand-in
pipeline and check on a simulated clock, a measure is due at most every period and holds the
next back to its share of a core; only synchronous frame sets with every camera and the TOF
are measured (else the status says why); a new rig drops the old report and a measure under
way for it; a failure is worded and the next measure goes on; the status's shape, its health
line and alerts. Refine saves the corrected rig as the next version and puts it in use, or
refuses. On a real pipeline over synthetic frames the fusion thread hands sets to the real
check. The Calibration panel's health line, alert and Refine rig."""

from __future__ import annotations

import contextlib
import dataclasses
import io
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import pytest
import viser

from tests.support import FakeClock, ListSource, small_rig, synth_frame, synth_frames, wait_until
from trifuse.app.server.panels.drift_health import DriftHealth
from trifuse.app.server.runtime import drift_watch as watch_module
from trifuse.app.server.runtime.drift_watch import (
    CPU_SHARE,
    DriftWatch,
    alerts,
    health_summary,
)
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.workflows.calib_session import CalibrationSession, RigVersion
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_rvec
from trifuse.fusion.drift import DriftReport, RefineRefused, SensorCheck

T0_NS = 5_000_000_000


def frame_set(rig: Rig, stamp_ns: int, seed: int, spread_ns: int = 0, skip: tuple = ()) -> FrameSet:
    """One synthetic frame of every sensor of ``rig`` (but ``skip``), the i-th sensor's
    stamp ``i * spread_ns`` after ``stamp_ns``."""
    rng = np.random.default_rng(seed)
    frames = {
        n: synth_frame(rig, n, stamp_ns + i * spread_ns, rng)
        for i, n in enumerate(rig.names)
        if n not in skip
    }
    return FrameSet(stamp_ns, frames)


def report_of(
    rig: Rig, verdicts: dict[str, tuple[str, tuple[float, float, float] | None]]
) -> DriftReport:
    """A report with each sensor's verdict and rotation (degrees, its own axes); sensors not
    named are ``ok`` and unturned."""
    sensors = {}
    for name in rig.names:
        verdict, rot = verdicts.get(name, ("ok", (0.0, 0.0, 0.0)))
        sigma = None if rot is None else (0.01, 0.01, 0.02)
        sensors[name] = SensorCheck(verdict, rot, sigma, f"{name}: {verdict}", ("ccd_left",))  # type: ignore[arg-type]
    return DriftReport(sensors, (), instants=7)


class FakeCheck:
    """Stands for fusion.drift.DriftCheck: each measure takes ``spent_s`` of the clock (or
    raises ``fail``), the report is ``report``; the instances made are counted."""

    made: ClassVar[list[FakeCheck]] = []
    spent_s = 0.5
    fail: Exception | None = None
    report_for: ClassVar[dict[int, DriftReport]] = {}

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.measured: list[tuple[float, dict[str, Frame]]] = []
        FakeCheck.made.append(self)

    def measure(self, t_s: float, frames: dict[str, Frame]) -> list:
        self.measured.append((t_s, frames))
        CLOCK.advance(FakeCheck.spent_s)
        if FakeCheck.fail is not None:
            raise FakeCheck.fail
        return []

    def report(self, now_s: float | None = None) -> DriftReport:
        return FakeCheck.report_for.get(id(self.rig)) or report_of(self.rig, {})


CLOCK = FakeClock(100.0)


@pytest.fixture
def fake(monkeypatch):
    """A watch over a stand-in pipeline (the small rig, wanted) with FakeCheck and a worker
    that only collects the jobs (the test runs them: ``watch._compute(jobs[i])``)."""
    CLOCK.now = 100.0
    FakeCheck.made, FakeCheck.spent_s, FakeCheck.fail, FakeCheck.report_for = [], 0.5, None, {}
    monkeypatch.setattr(watch_module, "DriftCheck", FakeCheck)
    rig = small_rig()
    pipeline = SimpleNamespace(set_listeners=[], wanted=True, rig=rig)
    watch = DriftWatch(pipeline, period_s=2.0, clock=CLOCK)  # type: ignore[arg-type]
    jobs: list = []
    watch._worker = SimpleNamespace(submit=jobs.append, busy=False, stop=lambda s: None)  # type: ignore[assignment]
    assert pipeline.set_listeners == [watch._on_set]
    return watch, pipeline, jobs


def test_a_measure_is_due_at_most_every_period_and_within_its_share_of_a_core(fake) -> None:
    watch, pipeline, jobs = fake
    rig = pipeline.rig
    watch._on_set(frame_set(rig, T0_NS, 1))
    assert len(jobs) == 1 and set(jobs[0].frames) == set(rig.names)
    CLOCK.advance(1.0)
    watch._on_set(frame_set(rig, T0_NS + 10**9, 2))  # within the period: not taken
    assert len(jobs) == 1
    CLOCK.now = 100.0
    watch._compute(jobs[0])  # took 0.5 s: the next waits 0.5 / 0.10 = 5 s after its end
    assert watch._due_s == pytest.approx(100.5 + 0.5 / CPU_SHARE)
    CLOCK.now = 103.0  # past the period, not the share
    watch._on_set(frame_set(rig, T0_NS + 3 * 10**9, 3))
    assert len(jobs) == 1
    CLOCK.now = 105.5
    fs = frame_set(rig, T0_NS + 5 * 10**9, 4)
    watch._on_set(fs)
    assert len(jobs) == 2
    watch._compute(jobs[1])
    assert watch.measures == 2 and len(FakeCheck.made) == 1  # one check of one rig
    measured = FakeCheck.made[0].measured
    assert [t for t, _ in measured] == [100.0, 105.5]  # the check's time line: the clock
    # measured share: 0.5 s of every 5.5 s, under the limit
    assert watch.measured_share() == pytest.approx(0.5 / 5.5)
    share = watch.status()["cpu_share"]
    assert share == pytest.approx(0.5 / 5.5, abs=1e-4) and share < CPU_SHARE
    # none while a measure is under way (it may take longer than the period)
    CLOCK.now = 300.0
    watch._worker.busy = True
    watch._on_set(frame_set(rig, T0_NS + 9 * 10**9, 5))
    assert len(jobs) == 2
    watch._worker.busy = False
    # the same frame set again (a paused replay) is not measured twice
    CLOCK.now = 200.0
    watch._on_set(fs)
    assert len(jobs) == 2 and "again" in (watch.waiting or "")


def test_nothing_is_measured_while_the_fusion_is_not_wanted(fake) -> None:
    watch, pipeline, jobs = fake
    pipeline.wanted = False
    watch._on_set(frame_set(pipeline.rig, T0_NS, 1))
    assert jobs == [] and watch.waiting is None
    pipeline.wanted = True
    watch._on_set(frame_set(pipeline.rig, T0_NS, 1))
    assert len(jobs) == 1


def test_only_synchronous_sets_with_every_camera_and_the_tof_are_measured(fake) -> None:
    watch, pipeline, jobs = fake
    rig = pipeline.rig
    watch._on_set(frame_set(rig, T0_NS, 1, skip=("thermal_right",)))
    assert jobs == [] and "(missing: thermal_right)" in watch.waiting
    assert watch.status()["summary"] == f"not checked yet: {watch.waiting}"
    watch._on_set(frame_set(rig, T0_NS, 1, spread_ns=5_000_000))  # 20 ms from first to last
    assert jobs == [] and "spread 20 ms, at most 12 ms" in watch.waiting
    no_depth = frame_set(rig, T0_NS, 1)
    no_depth.frames["tof"] = dataclasses.replace(no_depth.frames["tof"], distance_m=None)
    watch._on_set(no_depth)
    assert jobs == [] and "TOF's depth" in watch.waiting
    watch._on_set(frame_set(rig, T0_NS, 1, spread_ns=3_000_000))  # 12 ms: taken
    assert len(jobs) == 1 and watch.waiting is None


def test_a_writeable_frame_is_copied_a_read_only_one_shared(fake) -> None:
    watch, pipeline, jobs = fake
    fs = frame_set(pipeline.rig, T0_NS, 1)
    fs.frames["ccd_left"].image.flags.writeable = False
    watch._on_set(fs)
    kept = jobs[0].frames
    assert kept["ccd_left"].image is fs.frames["ccd_left"].image
    assert kept["ccd_right"].image is not fs.frames["ccd_right"].image
    np.testing.assert_array_equal(kept["ccd_right"].image, fs.frames["ccd_right"].image)
    assert kept["tof"].distance_m is not fs.frames["tof"].distance_m


def test_a_new_rig_drops_the_old_report_and_the_measure_under_way(fake) -> None:
    watch, pipeline, jobs = fake
    old = pipeline.rig
    FakeCheck.report_for[id(old)] = report_of(old, {"thermal_left": ("drifted", (0, 0.4, 0))})
    watch._on_set(frame_set(old, T0_NS, 1))
    watch._compute(jobs[0])
    assert watch.status()["drifted"] == ["thermal_left"]
    CLOCK.advance(100.0)
    watch._on_set(frame_set(old, T0_NS + 10**9, 2))  # taken for the old rig ...
    new = dataclasses.replace(old)
    pipeline.rig = new  # ... which is replaced before it is measured
    status = watch.status()
    assert watch.state() is None and status["sensors"] == {} and status["drifted"] == []
    assert status["instants"] == 0 and status["age_s"] is None and status["alerts"] == []
    watch._compute(jobs[1])
    assert len(FakeCheck.made[0].measured) == 1 and watch.measures == 1  # discarded
    CLOCK.advance(100.0)
    watch._on_set(frame_set(new, T0_NS + 2 * 10**9, 3))
    watch._compute(jobs[2])
    assert len(FakeCheck.made) == 2 and FakeCheck.made[1].rig is new  # a new check
    assert watch.state().rig is new and watch.status()["drifted"] == []


def test_a_failure_is_worded_and_the_next_measure_goes_on(fake) -> None:
    watch, pipeline, jobs = fake
    FakeCheck.fail = ValueError("no structure for this test")
    watch._on_set(frame_set(pipeline.rig, T0_NS, 1))
    watch._compute(jobs[0])
    status = watch.status()
    assert status["error"] == "ValueError: no structure for this test"
    assert watch.error_count == 1 and watch.measures == 0 and status["sensors"] == {}
    assert watch._due_s == pytest.approx(100.5 + 0.5 / CPU_SHARE)  # a failure costs too
    FakeCheck.fail = None
    CLOCK.advance(10.0)
    watch._on_set(frame_set(pipeline.rig, T0_NS + 10**9, 2))
    watch._compute(jobs[1])
    assert watch.status()["error"] is None and watch.measures == 1


def test_the_status_block_and_its_health_line_and_alerts(fake) -> None:
    watch, pipeline, jobs = fake
    rig = pipeline.rig
    FakeCheck.report_for[id(rig)] = report_of(rig, {"thermal_left": ("drifted", (0, 0.31, 0))})
    watch._on_set(frame_set(rig, T0_NS, 1))
    watch._compute(jobs[0])
    CLOCK.advance(1.25)
    status = watch.status()
    assert set(status) == {
        "sensors", "instants", "age_s", "drifted", "summary", "alerts", "error", "waiting",
        "problems", "measures", "cpu_share", "last_refine",
    }  # fmt: skip
    assert list(status["sensors"]) == rig.names
    left = status["sensors"]["thermal_left"]
    assert left["verdict"] == "drifted" and left["rotation_deg"] == [0, 0.31, 0]
    assert left["angle_deg"] == pytest.approx(0.31) and left["sigma_deg"] == [0.01, 0.01, 0.02]
    assert left["sigma_max_deg"] == 0.02 and left["reason"] and left["pairs"] == ["ccd_left"]
    assert status["sensors"]["tof"]["angle_deg"] == 0.0
    assert status["instants"] == 7 and status["age_s"] == 1.25 and status["measures"] == 1
    assert status["drifted"] == ["thermal_left"] and status["cpu_share"] is None  # one measure
    assert status["summary"] == "thermal_left DRIFTED 0.31° (σ 0.02°); others ok"
    assert status["alerts"] == [
        "⚠ thermal_left has turned 0.31° against the rig: refine or recalibrate"
    ]


def test_the_health_line_in_words() -> None:
    rig = small_rig()

    def line(verdicts: dict) -> str:
        return health_summary(watch_module.DriftState(report_of(rig, verdicts), rig, 0.0, 0.1))

    assert health_summary(None) == "checking… (0 instants)"
    assert health_summary(None, "the rig has no single TOF") == (
        "not checked yet: the rig has no single TOF"
    )
    assert line({}) == "ok: every sensor within 0.15° (7 instants)"
    undecided = ("undecided", None)
    assert line({"thermal_left": undecided, "thermal_right": undecided}) == (
        "checking… (7 instants; ok: tof, ccd_left, ccd_right)"
    )
    assert line({n: undecided for n in rig.names}) == "checking… (7 instants)"
    assert line({"thermal_left": ("drifted", (0, 0.3, 0)), "ccd_right": undecided}) == (
        "thermal_left DRIFTED 0.30° (σ 0.02°); ok: tof, ccd_left, thermal_right; undecided: "
        "ccd_right"
    )
    far = report_of(rig, {"ccd_left": ("drifted", (2.5, 0, 0))})
    assert alerts(watch_module.DriftState(far, rig, 0.0, 0.1)) == [
        "⚠ ccd_left has turned 2.50° against the rig: recalibrate with the board (more than "
        "2° is not refined)"
    ]
    assert alerts(None) == []


def turned(rig: Rig, name: str, rotation_deg: tuple[float, float, float]) -> np.ndarray:
    """``T_rig_name @ [[R(rotation), 0], [0, 1]]`` (the correction's convention)."""
    R = rotation_from_rvec(np.radians(rotation_deg))
    return rig[name].T_rig_sensor @ make_T(R, np.zeros(3))


def test_refine_saves_the_next_version_puts_it_in_use_and_checks_again(fake, tmp_path) -> None:
    watch, pipeline, jobs = fake
    rig = pipeline.rig
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    used: list[Rig] = []
    try:
        with pytest.raises(ValueError, match="has not been checked yet"):
            watch.refine(session.save_rig, used.append)
        watch._on_set(frame_set(rig, T0_NS, 1))
        watch._compute(jobs[0])  # every camera ok
        with pytest.raises(ValueError, match="no sensor is drifted"):
            watch.refine(session.save_rig, used.append)
        far = report_of(rig, {"thermal_left": ("drifted", (0.0, 2.4, 0.0))})
        FakeCheck.report_for[id(rig)] = far
        CLOCK.advance(10.0)
        watch._on_set(frame_set(rig, T0_NS + 10**9, 2))
        watch._compute(jobs[1])
        with pytest.raises(RefineRefused, match=r"more than 2°: .* recalibrate with the board"):
            watch.refine(session.save_rig, used.append)
        assert session.versions() == [] and used == [] and watch.state() is not None
        rotation = (0.01, 0.4, -0.02)
        FakeCheck.report_for[id(rig)] = report_of(rig, {"thermal_left": ("drifted", rotation)})
        CLOCK.advance(10.0)
        watch._on_set(frame_set(rig, T0_NS + 2 * 10**9, 3))
        watch._compute(jobs[2])
        result = watch.refine(session.save_rig, used.append)
        assert isinstance(result.version, RigVersion) and result.version.name == "rig-0001"
        assert [v.name for v in session.versions()] == ["rig-0001"]
        saved = session.load_version("rig-0001")
        assert used == [result.rig] and set(result.corrected) == {"thermal_left"}
        np.testing.assert_allclose(
            saved["thermal_left"].T_rig_sensor, turned(rig, "thermal_left", rotation), atol=1e-12
        )
        for name in ("ccd_left", "ccd_right", "thermal_right", "tof"):
            np.testing.assert_allclose(saved[name].T_rig_sensor, rig[name].T_rig_sensor)
        report = (session.rigs_dir / "rig-0001.report.json").read_text()
        assert '"drift_refine"' in report and '"thermal_left"' in report
        # the check starts again: the report is dropped, a measure taken before is discarded
        status = watch.status()
        assert status["sensors"] == {} and status["instants"] == 0
        assert status["last_refine"] == {
            "saved_as": "rig-0001",
            "sensors": {"thermal_left": pytest.approx(0.4007, abs=1e-4)},
            "age_s": 0.0,
        }
        assert watch_module.refine_text(result) == (
            "refined thermal_left (0.40°): saved as rig-0001, now in use; checking again"
        )
        with pytest.raises(ValueError, match="has not been checked yet"):
            watch.refine(session.save_rig, used.append)
    finally:
        session.close()


class IdleGatedSource(ListSource):
    """The frames, each only once :attr:`watch` has measured what it was handed (the
    pipeline notes sets in the thread that reads the source): every usable set is measured
    however slow the machine, as on a live head whose watch keeps up."""

    watch: DriftWatch | None = None

    def frames(self):
        for frame in super().frames():
            wait_until(lambda: self.watch is not None and not self.watch.busy, "an idle watch")
            yield frame


def test_on_a_real_pipeline_the_fusion_thread_hands_sets_to_the_real_check() -> None:
    """Synthetic frames (smooth patterns: little structure, so no verdict) fused by a real
    pipeline: the watch measures synchronous sets with the real DriftCheck; the report
    names every sensor and why it is undecided; nothing failed. (Seed 3's frames give the
    colour pair and the thermal pair a measure but neither eye: fusion.drift's
    solve_sensors then raises LinAlgError, which the watch reports as its error.)"""
    rig = small_rig()
    source = IdleGatedSource(synth_frames(rig, 1.0, seed=1))
    pipeline = FusionPipeline(source, rig, FrameHub())
    watch = source.watch = DriftWatch(pipeline, period_s=0.0, clock=FakeClock(10.0)).start()
    try:
        pipeline.start()
        assert pipeline.join(120.0) and pipeline.status.error is None
        wait_until(lambda: not watch.busy, "the last measure")
        status = watch.status()
        assert status["error"] is None and watch.error_count == 0
        assert status["measures"] >= 3 and status["instants"] == status["measures"]
        assert list(status["sensors"]) == rig.names
        assert all(s["verdict"] in ("ok", "undecided") for s in status["sensors"].values())
        tof = status["sensors"]["tof"]
        assert tof["verdict"] == "undecided" and tof["reason"], tof
        assert status["drifted"] == [] and status["alerts"] == []
    finally:
        watch.stop()
        pipeline.stop()


@contextlib.contextmanager
def health_panel(watch: DriftWatch, session: CalibrationSession, used: list):
    """The health line, alert and Refine rig in a Calibration folder on a real Viser server."""
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    ctx = SimpleNamespace(server=server, drift=watch, use_rig=used.append)
    try:
        with server.gui.add_folder("Calibration"):
            yield DriftHealth(ctx, session)  # type: ignore[arg-type]
    finally:
        server.stop()


def test_the_calibration_panel_shows_the_health_the_alert_and_refines(fake, tmp_path) -> None:
    watch, pipeline, jobs = fake
    rig = pipeline.rig
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    used: list[Rig] = []
    try:
        with health_panel(watch, session, used) as panel:
            panel.tick()
            assert panel.line.content == "**Calibration health:** checking… (0 instants)"
            assert not panel.alert.visible and panel.refine.disabled
            panel.press()  # nothing to refine: said, nothing saved
            assert panel.message.content.startswith("**Not refined:** refine: the rig in use")
            FakeCheck.report_for[id(rig)] = report_of(
                rig, {"thermal_left": ("drifted", (0, 0.5, 0))}
            )
            watch._on_set(frame_set(rig, T0_NS, 1))
            watch._compute(jobs[0])
            panel.tick()
            assert "thermal_left DRIFTED 0.50°" in panel.line.content
            assert panel.alert.visible and not panel.refine.disabled
            assert "⚠ thermal_left has turned 0.50° against the rig" in panel.alert.content
            assert "role='alert'" in panel.alert.content
            panel.press()
            assert session.versions()[-1].name == "rig-0001" and len(used) == 1
            assert (
                "Refined thermal" in panel.message.content and "rig-0001" in panel.message.content
            )
            assert panel.refine.disabled and not panel.alert.visible  # checking again
            assert panel.line.content == "**Calibration health:** checking… (0 instants)"
    finally:
        session.close()
