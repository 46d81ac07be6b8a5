"""The console's background estimate of the registration sigma
(app/server/runtime/registration_watch.py) on a real pipeline over synthetic frames: each
eye gets an estimate that /api/status reports and the fusion draws; a new rig drops the old
estimates; failures are reported while the pictures and the next estimates go on; an eye
whose thermal imager sees none of the depth gets no figures; the stride keeps the cells
evaluated under the limit. The Fusion folder offers the mode and shows the figures."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.panel_support import display_panels
from tests.support import FakeClock, ListSource, small_rig, synth_frames, wait_until
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime import registration_watch as watch_module
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.registration_watch import (
    NO_COVARIANCE,
    RegistrationWatch,
    stride_for,
)
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.parameter_covariance import ParameterCovariance
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.compose import DISPLAY_MODES, DisplaySettings

DURATION_S = 0.6
START_NS = 1_000_000_000  # synth_frames' first stamp


def fused_pipeline(rig: Rig, seed: int) -> tuple[FusionPipeline, RegistrationWatch]:
    """A pipeline over DURATION_S of synthetic frames (every set fused, each TOF frame
    mapped) with a watch that estimates at every new depth (its clock never moves,
    period 0)."""
    frames = synth_frames(rig, DURATION_S, seed=seed, start_ns=START_NS)
    pipeline = FusionPipeline(ListSource(frames), rig, FrameHub())
    watch = RegistrationWatch(pipeline, period_s=0.0, clock=FakeClock(10.0)).start()
    return pipeline, watch


def run(pipeline: FusionPipeline, watch: RegistrationWatch) -> None:
    """Fuse every frame, then wait for the watch's last estimate."""
    pipeline.start()
    assert pipeline.join(120.0) and pipeline.status.error is None
    assert pipeline.status.pictures_out > 5
    wait_until(lambda: not watch.busy, "the last estimate")


def test_each_eye_gets_an_estimate_the_status_reports_and_a_new_rig_drops_it() -> None:
    rig = small_rig()
    pipeline, watch = fused_pipeline(rig, seed=1)
    seen: dict = {}

    def new_rig_midway(fs: FrameSet) -> None:  # the fusion thread, at 0.4 s of frame time
        if "before" in seen or fs.stamp_ns < START_NS + 400_000_000:
            return
        wait_until(lambda: all(watch.results().values()) and not watch.busy, "estimates")
        seen["before"], seen["fusion"] = watch.results(), pipeline.fusion
        seen["status"] = client.get("/api/status").json()["registration"]
        watch.stop()  # no estimate for the new rig: what is left of the old ones shows
        pipeline.set_rig(dataclasses.replace(rig))  # swapped in at the next set

    client = TestClient(
        create_app(
            pipeline.hub, None, pipeline, SourceControl(pipeline, pipeline.hub), registration=watch
        )
    )
    pipeline.set_listeners.append(new_rig_midway)
    try:
        run(pipeline, watch)
        old = seen["fusion"]
        for eye, r in seen["before"].items():
            assert r is not None and r.fusion is old, eye
            assert old.registration[eye] is r.overlay  # what the mode drew
            assert r.stride == 1  # 32 x 24 cells: every one
        block = seen["status"]
        assert block["error"] is None
        for eye in ("left", "right"):
            e = block[eye]
            assert math.isfinite(e["median_px"]) and math.isfinite(e["p95_px"]), e
            assert 0 < e["median_px"] <= e["p95_px"] and e["cells"] > 100
            assert e["calibration_covariance"] is False  # the small rig carries none
            assert e["range_source"] == "no range correction: 41 mm" and e["age_s"] == 0.0
        # the new rig made a new fusion: the old estimates are dropped, drawn nowhere
        assert pipeline.fusion is not old and pipeline.rig is not rig
        assert watch.results() == {"left": None, "right": None}
        assert pipeline.fusion.registration == {"left": None, "right": None}
        block = client.get("/api/status").json()["registration"]
        assert block == {"left": None, "right": None, "error": None}
    finally:
        watch.stop()
        pipeline.stop()


def test_failures_are_reported_while_the_pictures_and_the_estimates_go_on(monkeypatch) -> None:
    rig = small_rig()
    pipeline, watch = fused_pipeline(rig, seed=3)

    def fails(*_args, **_kwargs):
        raise ValueError("no depth for this test")

    monkeypatch.setattr(watch_module, "registration_sigma", fails)
    try:
        run(pipeline, watch)  # every set still fused and published (run's asserts)
        assert watch.error_count >= 4  # two eyes a time, estimate after estimate
        worded = "ValueError: no depth for this test"
        assert watch.error == f"left: {worded}; right: {worded}"
        status = watch.status()
        assert status == {"left": None, "right": None, "error": watch.error}
        assert f"failed: left: {worded}" in watch.summary_text()
    finally:
        watch.stop()
        pipeline.stop()


def test_an_eye_whose_imager_sees_none_of_the_depth_gets_no_figures() -> None:
    rig = small_rig()
    back = rig["thermal_right"]
    turned = make_T(rotation_from_euler_deg(0, 180, 0), back.T_rig_sensor[:3, 3])
    rig = rig.with_sensor(dataclasses.replace(back, T_rig_sensor=turned))  # looks backwards
    pipeline, watch = fused_pipeline(rig, seed=5)
    try:
        run(pipeline, watch)
        status = watch.status()
        assert status["right"]["median_px"] is None and status["right"]["cells"] == 0
        assert status["left"]["cells"] > 100 and status["error"] is None
        assert "right: no cell with depth seen by the thermal imager" in watch.summary_text()
    finally:
        watch.stop()
        pipeline.stop()


def test_the_calibration_covariance_adds_its_share_to_the_eye_it_covers() -> None:
    """The same frames with a rig carrying a covariance of the left eye's sensors: the left
    eye's sigma grows by the calibration's share and says so; the right eye's is the same."""
    rig = small_rig()
    names = [f"{s}.{p}" for s in ("ccd_left", "thermal_left") for p in ("fx", "cx", "ry", "tx")]
    sigma = np.array([2.0, 1.0, 0.002, 0.002] * 2)  # px, px, rad, m
    covariance = ParameterCovariance.from_matrix(names, np.diag(sigma**2))
    figures = {}
    for cov in (None, covariance):
        pipeline, watch = fused_pipeline(dataclasses.replace(rig, covariance=cov), seed=7)
        try:
            run(pipeline, watch)
            figures[cov is not None] = watch.status()
        finally:
            watch.stop()
            pipeline.stop()
    without, with_cov = figures[False], figures[True]
    assert with_cov["left"]["calibration_covariance"] is True
    assert with_cov["right"]["calibration_covariance"] is False
    assert with_cov["left"]["median_px"] > without["left"]["median_px"] + 0.05, figures
    assert with_cov["right"]["median_px"] == without["right"]["median_px"]
    assert with_cov["left"]["cells"] == without["left"]["cells"]


def test_the_stride_keeps_the_cells_with_depth_under_the_limit() -> None:
    rng = np.random.default_rng(4)
    ok = rng.random((240, 320)) < 0.8  # the default head's coarse grid, 80 % with depth
    s = stride_for(ok, 3000)
    assert np.count_nonzero(ok[::s, ::s]) <= 3000 < np.count_nonzero(ok[:: s - 1, :: s - 1])
    assert stride_for(ok[:40, :50], 3000) == 1


def test_the_fusion_folder_offers_the_mode_and_shows_the_estimate(server) -> None:
    pipeline = SimpleNamespace(
        rig=small_rig(),
        settings=DisplaySettings(),
        radiometry={"thermal_left": Radiometry(), "thermal_right": Radiometry()},
        latest_set=FrameSet(START_NS, {}),
        fusion=SimpleNamespace(span_k=None),
        set_manual_offset=lambda name, k: None,
    )
    text = "left: median 0.08 px, p95 0.43 px (2309 cells)\nright: not estimated yet"
    registration = SimpleNamespace(summary_text=lambda: f"{text}\n{NO_COVARIANCE}")
    watch = SimpleNamespace(latest=None, enabled=False)
    panels = display_panels(server, pipeline, watch, registration=registration)
    assert "registration" in DISPLAY_MODES and "registration" in panels.mode.options
    panels.tick()
    md = panels.registration.content
    assert md.startswith("**Registration σ**") and "median 0.08 px, p95 0.43 px" in md
    assert "right: not estimated yet" in md and NO_COVARIANCE in md
    panels.mode.value = "registration"
    panels.apply()
    assert pipeline.settings.mode == "registration"


def test_an_estimate_holds_the_next_one_back_to_its_share_of_a_core() -> None:
    """An estimate that took t seconds delays the next by t / CPU_SHARE (0.5 s -> 10 s),
    also when it failed."""
    ticks = iter([100.0, 100.5, 100.5, 200.0, 200.2, 200.2])
    pipeline = SimpleNamespace(set_listeners=[], fusion=None)
    watch = RegistrationWatch(pipeline, period_s=2.0, clock=lambda: next(ticks))  # type: ignore[arg-type]
    job = watch_module._Job(fusion=None, rig=small_rig(), tof="tof", cells={})  # type: ignore[arg-type]
    watch._compute(job)
    assert watch._due_s == pytest.approx(100.5 + 0.5 / watch_module.CPU_SHARE)
    broken = watch_module._Job(fusion=None, rig=None, tof="tof", cells={})  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        watch._compute(broken)  # range_error of no rig (the worker reports it)
    assert watch._due_s == pytest.approx(200.2 + 0.2 / watch_module.CPU_SHARE)
