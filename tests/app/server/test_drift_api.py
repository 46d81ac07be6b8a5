"""The calibration's health over REST: ``drift`` in ``GET /api/status`` (null without the
check; its block once measured) and ``POST /api/drift/refine`` (409 with the reason when
the rig in use is not checked yet, nothing is drifted, or a correction exceeds 2 degrees;
else the corrected rig saved as the next version, never over an existing one, and put in
use). A slow test drives the real check with the simulated inspection room seen by a head
whose left thermal imager has turned 0.4 degrees, and refines the rig back to the truth."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.support import FakeClock, ListSource, small_rig, synth_frame
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.routers.drift_api import make_drift_router
from trifuse.app.server.runtime import drift_watch as watch_module
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import FrameSet
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.workflows.calib_session import CalibrationSession
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_rvec
from trifuse.fusion.drift import DriftReport, SensorCheck

T0_NS = 5_000_000_000


def report_of(rig: Rig, drifted: dict[str, tuple[float, float, float]]) -> DriftReport:
    """Every sensor ``ok`` and unturned but ``drifted`` (name -> rotation, degrees)."""
    sensors = {}
    for name in rig.names:
        if name in drifted:
            sensors[name] = SensorCheck("drifted", drifted[name], (0.01,) * 3, "turned")
        else:
            sensors[name] = SensorCheck("ok", (0.0, 0.0, 0.0), (0.01,) * 3, "within 0.15°")
    return DriftReport(sensors, (), instants=5)


def turned(T_rig_sensor: np.ndarray, rotation_deg: tuple[float, float, float]) -> np.ndarray:
    """``T_rig_sensor @ [[R, 0], [0, 1]]``, R of the rotation vector (degrees)."""
    return T_rig_sensor @ make_T(rotation_from_rvec(np.radians(rotation_deg)), np.zeros(3))


class Console:
    """The status and refine routes over a real (not started) pipeline of the small rig, a
    drift watch on a simulated clock whose check reports :attr:`report`, and a calibration
    session in ``workdir``; :meth:`measure` makes the watch measure one frame set."""

    def __init__(self, workdir, monkeypatch) -> None:
        self.rig = small_rig()
        self.pipeline = FusionPipeline(ListSource([]), self.rig, FrameHub())
        self.clock = FakeClock(50.0)
        self.watch = DriftWatch(self.pipeline, clock=self.clock)
        self.report = report_of(self.rig, {})
        console = self

        class Check:  # stands for fusion.drift.DriftCheck
            def __init__(self, rig: Rig) -> None:
                self.rig = rig

            def measure(self, t_s: float, frames: dict) -> list:
                return []

            def report(self, now_s: float | None = None) -> DriftReport:
                return console.report

        monkeypatch.setattr(watch_module, "DriftCheck", Check)
        self.session = CalibrationSession(workdir, self.rig, CALIBRATION_BOARD)
        self.used: list[Rig] = []
        app = create_app(
            self.pipeline.hub,
            None,
            self.pipeline,
            SourceControl(self.pipeline, self.pipeline.hub),
            drift=self.watch,
        )
        app.include_router(make_drift_router(self.watch, self.session.save_rig, self.use))
        self.client = TestClient(app)
        self.jobs: list = []
        self.watch._worker = SimpleNamespace(submit=self.jobs.append, busy=False)  # type: ignore[assignment]

    def use(self, rig: Rig) -> None:
        self.used.append(rig)
        self.pipeline.rig = rig  # as the fusion thread does at the next frame set

    def measure(self, report: DriftReport) -> None:
        self.report = report
        self.clock.advance(60.0)
        rng = np.random.default_rng(len(self.jobs))
        stamp = T0_NS + len(self.jobs) * 10**9
        rig = self.pipeline.rig
        self.watch._on_set(FrameSet(stamp, {n: synth_frame(rig, n, stamp, rng) for n in rig.names}))
        self.watch._compute(self.jobs[-1])

    def drift(self) -> dict:
        return self.client.get("/api/status").json()["drift"]

    def refine(self) -> tuple[int, dict]:
        r = self.client.post("/api/drift/refine")
        return r.status_code, r.json()


@pytest.fixture
def console(tmp_path, monkeypatch):
    c = Console(tmp_path / "work", monkeypatch)
    try:
        yield c
    finally:
        c.session.close()


def test_the_status_reports_no_drift_block_without_the_check() -> None:
    rig = small_rig()
    pipeline = FusionPipeline(ListSource([]), rig, FrameHub())
    client = TestClient(
        create_app(pipeline.hub, None, pipeline, SourceControl(pipeline, pipeline.hub))
    )
    assert client.get("/api/status").json()["drift"] is None
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    assert {"DriftInfo", "DriftSensor", "DriftRefine"} <= set(schema)


def test_the_status_reports_the_drift_block(console) -> None:
    block = console.drift()
    assert block["sensors"] == {} and block["instants"] == 0 and block["age_s"] is None
    assert block["summary"] == "checking… (0 instants)" and block["alerts"] == []
    console.measure(report_of(console.rig, {"thermal_left": (0.0, 0.31, 0.0)}))
    console.clock.advance(0.5)
    block = console.drift()
    assert block["drifted"] == ["thermal_left"] and block["instants"] == 5
    assert block["age_s"] == 0.5 and block["error"] is None and block["measures"] == 1
    assert list(block["sensors"]) == console.rig.names
    left = block["sensors"]["thermal_left"]
    assert left["verdict"] == "drifted" and left["rotation_deg"] == [0.0, 0.31, 0.0]
    assert left["angle_deg"] == pytest.approx(0.31) and left["sigma_max_deg"] == 0.01
    assert block["sensors"]["tof"] == {
        "verdict": "ok",
        "rotation_deg": [0.0, 0.0, 0.0],
        "sigma_deg": [0.01, 0.01, 0.01],
        "angle_deg": 0.0,
        "sigma_max_deg": 0.01,
        "reason": "within 0.15°",
        "pairs": [],
    }
    assert block["summary"] == "thermal_left DRIFTED 0.31° (σ 0.01°); others ok"
    assert block["alerts"] == [
        "⚠ thermal_left has turned 0.31° against the rig: refine or recalibrate"
    ]


def test_refine_answers_409_and_changes_nothing_when_it_cannot(console) -> None:
    status, body = console.refine()
    assert status == 409 and "has not been checked yet" in body["detail"]
    console.measure(report_of(console.rig, {}))
    status, body = console.refine()
    assert (
        status == 409 and body["detail"] == "refine: no sensor is drifted; the rig stays as it is"
    )
    console.measure(report_of(console.rig, {"thermal_right": (0.0, 0.0, -2.3)}))
    status, body = console.refine()
    assert status == 409, body
    assert body["detail"] == (
        "refine: thermal_right would turn by 2.30°, more than 2°: that is not a drift to "
        "correct but a moved sensor; recalibrate with the board"
    )
    assert console.session.versions() == [] and console.used == []
    assert console.drift()["drifted"] == ["thermal_right"]  # the check goes on as it was


def test_refine_saves_the_next_version_and_puts_it_in_use(console) -> None:
    before = console.session.save_rig(console.rig, {"saved": "by hand"})  # rig-0001 exists
    first = before.path.read_bytes()
    rotation = (0.02, 0.35, -0.01)
    console.measure(report_of(console.rig, {"thermal_left": rotation}))
    status, body = console.refine()
    assert status == 201, body
    assert body["saved_as"] == body["in_use"] == "rig-0002"
    assert body["path"].endswith("rigs/rig-0002.yaml")
    assert body["corrected"]["thermal_left"]["rotation_deg"] == list(rotation)
    assert body["message"] == (
        "refined thermal_left (0.35°): saved as rig-0002, now in use; checking again"
    )
    assert before.path.read_bytes() == first  # never over an existing version
    saved = console.session.load_version("rig-0002")
    np.testing.assert_allclose(
        saved["thermal_left"].T_rig_sensor,
        turned(console.rig["thermal_left"].T_rig_sensor, rotation),
        atol=1e-12,
    )
    assert len(console.used) == 1 and console.pipeline.rig is console.used[0]
    np.testing.assert_allclose(
        console.used[0]["thermal_left"].T_rig_sensor, saved["thermal_left"].T_rig_sensor
    )
    report = json.loads((console.session.rigs_dir / "rig-0002.report.json").read_text())
    assert report["drift_refine"]["check"]["sensors"]["thermal_left"]["verdict"] == "drifted"
    # the check starts again on the refined rig
    block = console.drift()
    assert block["sensors"] == {} and block["drifted"] == [] and block["alerts"] == []
    assert block["last_refine"] == {
        "saved_as": "rig-0002",
        "sensors": {"thermal_left": pytest.approx(0.3507, abs=1e-4)},
        "age_s": 0.0,
    }
    status, body = console.refine()
    assert status == 409 and "has not been checked yet" in body["detail"]
    console.measure(report_of(console.pipeline.rig, {}))
    assert console.drift()["summary"] == "ok: every sensor within 0.15° (5 instants)"


@pytest.mark.slow  # renders 4 instants of the inspection room: 10-30 s
def test_the_check_finds_a_turned_imager_in_the_simulator_and_refine_turns_it_back(
    tmp_path,
) -> None:
    """The simulated head with thermal_left turned 0.4° about its own y axis (rendered from
    the moved rig) against the console's rig as calibrated: the real check calls it
    drifted within four measures; refine saves a rig whose thermal_left is within 0.05° of
    where it really is, the others unmoved."""
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.sources.sim.inspection import InspectionScenario

    rig = default_rig()
    rotation = (0.0, 0.4, 0.0)
    T_true = turned(rig["thermal_left"].T_rig_sensor, rotation)
    moved = rig.with_sensor(dataclasses.replace(rig["thermal_left"], T_rig_sensor=T_true))
    scenario = InspectionScenario(rig=moved, live=True)
    pipeline = SimpleNamespace(set_listeners=[], wanted=True, rig=rig)
    clock = FakeClock(0.0)
    watch = DriftWatch(pipeline, period_s=2.0, clock=clock)  # type: ignore[arg-type]
    jobs: list = []
    watch._worker = SimpleNamespace(submit=jobs.append, busy=False)  # type: ignore[assignment]
    for i in range(4):
        clock.advance(10.0)  # all four in the check's 60 s window
        fs, _ = scenario.render(1.0 + 3.0 * i)
        watch._on_set(fs)
        assert len(jobs) == i + 1, watch.waiting
        watch._compute(jobs[-1])
    status = watch.status()
    assert status["error"] is None and status["drifted"] == ["thermal_left"], status
    session = CalibrationSession(tmp_path / "work", rig, CALIBRATION_BOARD)
    used: list[Rig] = []
    try:
        result = watch.refine(session.save_rig, used.append)
    finally:
        session.close()
    refined = used[0]
    R_err = refined["thermal_left"].T_rig_sensor[:3, :3].T @ T_true[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1)))
    assert angle < 0.05, (angle, result.corrected)
    for name in ("ccd_left", "ccd_right", "thermal_right", "tof"):
        np.testing.assert_allclose(refined[name].T_rig_sensor, rig[name].T_rig_sensor, atol=1e-9)
