"""The Calibration panel: why auto-capture does not take a pose (live, under the checkbox),
the simulated board's wait for captures, and the "RMS error per view" chart."""

from __future__ import annotations

import math
import re
from types import SimpleNamespace

import numpy as np
import pytest

from tests.panel_support import panel_on
from tests.support import WAIT_S, wait_searched
from trifuse.app.server.panels.calibration import rms_chart
from trifuse.app.server.runtime.board_sighting import BoardSighting, Motion
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CaptureHold
from trifuse.app.workflows import calib_session
from trifuse.app.workflows.cross_validation import cross_validation_lines
from trifuse.calib.detect import Detection
from trifuse.calib.rig_result import ViewError


def plain(markdown: str) -> str:
    """Markdown text as the operator reads it (md_text's escapes undone)."""
    return re.sub(r"\\(.)", r"\1", markdown).replace("\u2060", "")


def grid_corners(x0: float, y0: float, step: float) -> np.ndarray:
    """The 9 x 6 board's corners (54, 2) as a regular grid, pixels."""
    g = np.stack(np.meshgrid(np.arange(9.0), np.arange(6.0)), -1).reshape(-1, 2)
    return np.array([x0, y0]) + step * g


SEEN = {  # sensor -> its corners of the stand-in board
    "tof": grid_corners(40, 30, 10),
    "ccd_left": grid_corners(300, 200, 60),
    "ccd_right": grid_corners(320, 210, 60),
}


def stand_in_detector(image: np.ndarray, board, modality: str) -> Detection:
    """The session's search of a view's images: the board where :data:`SEEN` says (by
    the image's size), in the TOF and colour cameras only."""
    if modality == "thermal":
        return Detection(None, "no board (stand-in)", None)
    name = "tof" if modality == "tof" else "ccd_left" if image[0, 0, 0] == 0 else "ccd_right"
    return Detection(SEEN[name].copy(), None, "stand-in")


def board_sighting(stamp_s: float, steady: bool, motion: Motion | None) -> BoardSighting:
    """The board seen by the TOF and the colour cameras, not by the thermal imagers."""
    stamp = round(stamp_s * 1e9)
    rig = default_rig()
    frames = {}
    for n, sensor in rig.sensors.items():
        w, h = sensor.image_size
        if sensor.modality == "color":  # told apart by their first pixel
            frames[n] = Frame(n, stamp, np.full((h, w, 3), n == "ccd_right", np.uint8))
        else:
            dist = np.ones((h, w), np.float32) if sensor.modality == "tof" else None
            frames[n] = Frame(n, stamp, np.full((h, w), 295.0, np.float32), dist)
    dets = {n: Detection(SEEN[n].copy(), None, "stand-in") for n in SEEN}
    dets |= {n: Detection(None, "no board (stand-in)", None) for n in rig.names if n not in SEEN}
    return BoardSighting(FrameSet(stamp, frames), dets, None, "ccd_left", steady, motion=motion)


def test_auto_capture_says_live_why_a_pose_is_not_taken_and_holds_the_simulated_board(
    tmp_path, monkeypatch
) -> None:
    """Ticking Auto-capture asks the simulated board to wait for captures; each sighting
    updates the line under the checkbox with the reason it is not taken (moving and by how
    much in frame time, which sensors see the board) and, once it is taken, the board may
    move on (its pose is released)."""
    monkeypatch.setattr(calib_session, "detect_cached", stand_in_detector)
    hold = CaptureHold(hold_s=2.0, n_poses=4, max_hold_s=30.0)
    source = SimpleNamespace(scenario=SimpleNamespace(capture_hold=hold))
    with panel_on(tmp_path, source, FrameSet(0, {})) as (panel, session, _):
        assert panel.capture_hold is hold and not hold.waiting
        panel.auto.value = True
        assert hold.waiting
        assert "waiting for frames" in plain(panel.why.content)
        hold.scenario_time(0, 0)  # the stream starts: pose 0
        hold.scenario_time(round(1.5e9), 0)

        moving = Motion(7.3, 0.5, "ccd_left")
        panel._on_sighting(board_sighting(1.0, False, moving))
        why = plain(panel.why.content)
        assert why.startswith("**Not taken:** moving: 7.3 px in 0.50 s of frame time"), why
        assert "(14.6 px/s) in ccd_left; still needs at most 4.0 px" in why, why
        assert "seen by 3 of 5 sensors (missing thermal_left, thermal_right)" in why, why
        assert "Board (moving): seen by tof, ccd_left, ccd_right" in plain(panel.seen.content)
        assert not session.views()

        panel._on_sighting(board_sighting(1.2, False, None))  # a first look
        assert "waiting for frames: a second look" in plain(panel.why.content)

        still = Motion(0.0, 0.0, "ccd_left", same_picture=True)
        panel._on_sighting(board_sighting(1.5, True, still))  # steady and new: taken
        assert [v.name for v in session.views()] == ["0001"]
        assert plain(panel.why.content) == "Auto-capture took view 0001."
        assert "Auto-captured view 0001 (new pose for" in plain(panel.message.content)
        # the simulated board goes on: its pose 0 was captured
        assert hold.pose_at(hold.scenario_time(round(2.0e9), 0)) == 1

        wait_searched(session)  # the same pose again: captured already, nothing to wait for
        hold.scenario_time(round(2.5e9), 0)
        panel._on_sighting(board_sighting(2.5, True, still))
        why = plain(panel.why.content)
        assert why.startswith("**Not taken:** already captured: view 0001 looks alike"), why
        assert len(session.views()) == 1
        panel.auto.value = False
        assert not hold.waiting and panel.why.content == ""


def result_of(views: dict[str, dict[str, float]]) -> SimpleNamespace:
    """What the chart reads of a CalibrationResult: view -> sensor -> RMS px."""
    return SimpleNamespace(
        views={v: {s: ViewError(rms, rms) for s, rms in e.items()} for v, e in views.items()}
    )


def test_the_chart_data_has_one_point_per_view_and_sensor_and_a_finite_range() -> None:
    """One x per view (its number), one y per sensor and view (its RMS), NaN where the
    sensor has none; a sensor with no error anywhere (not calibrated) must not leave the y
    axis to uPlot, which ranges it over NaN and draws nothing at all."""
    sensors = ["tof", "ccd_left", "thermal_right"]
    result = result_of(
        {
            "0003": {"tof": 0.08, "ccd_left": 0.05},
            "0001": {"tof": 0.04, "ccd_left": 0.03},
            "0007": {"ccd_left": 0.12},
        }
    )
    (x, tof, ccd, thermal), (y0, y1) = rms_chart(result, sensors)
    assert x.tolist() == [1.0, 3.0, 7.0]
    assert tof[:2].tolist() == [0.04, 0.08] and math.isnan(tof[2])
    assert ccd.tolist() == [0.03, 0.05, 0.12]
    assert np.isnan(thermal).all()  # thermal_right: not calibrated
    assert y0 == 0.0 and 0.12 < y1 < 0.2 and math.isfinite(y1)


@pytest.mark.slow  # a calibration of twelve simulated views: about a minute
def test_the_chart_after_a_calibration_run_from_the_panel(tmp_path, calibration_frame_sets):
    """Run calibration in the panel with thermal_right in two views only (too few: it is
    not calibrated): the chart is shown with one point per view and calibrated sensor, the
    RMS of the result, its y axis ranged by the panel, thermal_right marked as without
    points; the results show the cross-validation's line per eye (the right eye's: why it
    was skipped)."""
    with panel_on(tmp_path) as (panel, session, _):
        for k, fs in enumerate(calibration_frame_sets):
            frames = {n: f for n, f in fs.frames.items() if n != "thermal_right" or k < 2}
            session.take(FrameSet(fs.stamp_ns, frames))
        panel._act(panel._calibrate)  # what Run calibration does
        job = session.wait(WAIT_S * 4)
        assert job.state == "done", job.error
        panel.tick()
        result = job.result
        assert "thermal_right" not in {s for e in result.views.values() for s in e}
        assert panel.chart.visible
        x, *ys = panel.chart.data
        views = sorted(result.views)
        assert x.tolist() == [float(int(v)) for v in views]
        for sensor, y in zip(panel.sensors, ys, strict=True):
            want = [result.views[v][sensor].rms_px if sensor in result.views[v] else None
                    for v in views]  # fmt: skip
            got = [None if math.isnan(a) else a for a in y.tolist()]
            assert got == pytest.approx(want), sensor
        assert sum(np.isfinite(y).sum() for y in ys) == sum(len(e) for e in result.views.values())
        y_scale = panel.chart.scales["y"]
        lo, hi = y_scale["range"]
        assert lo == 0 and math.isfinite(hi) and hi > max(np.nanmax(y) for y in ys if
                                                          np.isfinite(y).any())  # fmt: skip
        labels = [s["label"] for s in panel.chart.series]
        assert labels == ["view", "tof", "ccd_left", "ccd_right", "thermal_left",
                          "thermal_right (none)"]  # fmt: skip
        # the cross-validation's line per eye, as the terminal's summary has it
        cv = job.report["cross_validation"]
        assert cv["eyes"]["right"]["skipped"].startswith("thermal_right is not calibrated: ")
        shown = plain(panel.results.content)
        lines = cross_validation_lines(cv)
        assert len(lines) == 2 and all(f"- {line}" in shown.splitlines() for line in lines)
        assert re.match(r"cross-validation \(2 halves of 12 views\): left eye worst [\d.]+ px at ",
                        lines[0])  # fmt: skip


def test_buttons_with_nothing_to_act_on_are_disabled(tmp_path, calibration_frame_sets):
    """No view: Delete view and Run calibration are disabled; no saved rig: Use this rig
    is. Each turns on once there is something to act on, and off again when it is gone."""
    with panel_on(tmp_path) as (panel, session, _):
        panel.tick()
        assert panel.delete.disabled and panel.run.disabled and panel.use.disabled
        assert not panel.capture.disabled
        name = session.take(calibration_frame_sets[0]).name
        panel._mark_dirty()
        panel.tick()
        assert not panel.delete.disabled and not panel.run.disabled
        assert panel.use.disabled  # nothing saved yet
        session.save_rig(default_rig(), {})
        panel._mark_dirty()
        panel.tick()
        assert not panel.use.disabled
        session.delete(name)
        panel._mark_dirty()
        panel.tick()
        assert panel.delete.disabled and panel.run.disabled
