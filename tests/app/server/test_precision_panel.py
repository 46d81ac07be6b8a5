"""The console's Precision panel (the method's Table 1 for the rig in use, in a real Viser
server) and the Feeds panel's board overlay (corners drawn at the thumbnail's scale, the
reason when the board was not found)."""

from __future__ import annotations

import dataclasses
import re
from types import SimpleNamespace

import numpy as np
import pytest
import viser

from tests.panel_support import display_panels
from tests.support import wait_until
from trifuse.app.server.panels import display as panels_mod
from trifuse.app.server.panels.display import (
    FEED_WIDTH_PX,
    ROW_COLOURS,
    Panels,
    feed_image,
    scale_corners,
    short_reason,
)
from trifuse.app.server.panels.precision import PrecisionPanel, plot_data, short_names
from trifuse.app.server.runtime.board_sighting import BoardSighting
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.workflows.report_format import limit_distance_cell, pixel_cell
from trifuse.calib.board import Board
from trifuse.calib.detect import Detection
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.precision import analyze_precision


def _wait_for(panel: PrecisionPanel, rig: Rig, after: int = 0) -> None:
    """Until the panel shows its analysis of ``rig`` (its ``after``-th or later)."""
    wait_until(lambda: panel.analysed is rig and panel.updates > after, "the panel's analysis")


def _table_rows(markdown: str) -> dict[tuple[str, str, str], list[str]]:
    """(TOF pixel key "u,v", error cell, coord) -> the sensor cells, from the panel's table."""
    rows: dict[tuple[str, str, str], list[str]] = {}
    pixel, error = None, None
    for line in markdown.splitlines():
        m = re.match(r"\*\*TOF pixel (\([^)]+\))\*\*", line)
        if m:
            pixel = m.group(1)  # as printed: one decimal
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or cells[1] not in ("x", "y"):
            continue
        error = cells[0] or error
        rows[(pixel, error.replace("\u00a0", " "), cells[1])] = cells[2:]
    return rows


def _expected_rows(rig: Rig) -> dict[tuple[str, str, str], list[str]]:
    before = analyze_precision(rig)  # the method's defaults: 41 mm, 0.5 px, threshold 0.5 px
    after = analyze_precision(rig, distance_error_m=0.015)
    out = {}
    for key, (u, v) in zip(before.distance_error, before.tof_pixels, strict=True):
        for error, results in (
            ("41 mm", before.distance_error[key]),
            ("15 mm", after.distance_error[key]),
            ("0.5 px", before.tof_pixel_error[key]),
        ):
            for coord in ("x", "y"):
                out[(pixel_cell(u, v), error, coord)] = [
                    limit_distance_cell(getattr(results[s], f"{coord}_m"), 10.0)
                    for s in before.sensors
                ]
    return out


def _moved(rig: Rig, sensor: str, dx_m: float) -> Rig:
    """``rig`` with ``sensor`` moved ``dx_m`` along the rig's x axis."""
    s = rig[sensor]
    T = s.T_rig_sensor.copy()
    T[0, 3] += dx_m
    sensors = dict(rig.sensors)
    sensors[sensor] = dataclasses.replace(s, T_rig_sensor=T)
    return Rig(sensors=sensors, reference=rig.reference, eyes=dict(rig.eyes))


def test_panel_shows_table_1_of_the_rig_and_recomputes_when_it_is_replaced(server) -> None:
    rig = default_rig()
    ctx = SimpleNamespace(server=server, pipeline=SimpleNamespace(rig=rig))
    panel = PrecisionPanel(ctx, poll_s=0.05).start()
    try:
        _wait_for(panel, rig)
        assert panel.error is None and panel.status.content == ""
        expected = _expected_rows(rig)
        shown = _table_rows(panel.table.content)
        assert shown == expected
        # the same numbers, not only the same rounding
        ref = analyze_precision(rig)
        for key, per_sensor in ref.distance_error.items():
            for name, r in per_sensor.items():
                got = panel.result.before.distance_error[key][name]
                assert (got.x_m, got.y_m) == (r.x_m, r.y_m)
                np.testing.assert_array_equal(got.dx_px, r.dx_px)
        # the method's shape: the colour cameras' x and y both cross 0.5 px at 1-3 m
        key = next(iter(ref.distance_error))
        assert 1.0 < ref.distance_error[key]["ccd_left"].x_m < 3.0
        # two plots (|dx|, |dy|), each: distance + 8 curves (4 sensors x before/after) + threshold
        assert len(panel.plots) == 2
        dx_plot = panel.plots[0]
        assert len(dx_plot.data) == 1 + 8 + 1 == len(dx_plot.series)
        np.testing.assert_array_equal(
            dx_plot.data[0], ref.distance_error[key]["ccd_left"].distance_m
        )
        curve = np.abs(ref.distance_error[key]["ccd_left"].dx_px)
        floor = dx_plot.data[1].min()
        np.testing.assert_allclose(dx_plot.data[1], np.maximum(curve, floor))
        assert np.all(dx_plot.data[-1] == 0.5)

        # an operator loads another rig: the thermal imager 5 cm further from the TOF
        other = _moved(rig, "thermal_left", -0.05)
        ctx.pipeline.rig = other
        _wait_for(panel, other)
        shown = _table_rows(panel.table.content)
        assert shown == _expected_rows(other)
        assert shown != expected  # a longer baseline: the threshold distances grow
        # the plot choice switches the curves to the TOF pixel error (4 curves + threshold)
        panel.kind_choice.value = "TOF pixel error"
        assert len(panel.plots) == 2 and len(panel.plots[0].data) == 1 + 4 + 1
        # and to the registration sigma: one plot, per eye its total and two shares
        panel.kind_choice.value = "registration σ"
        assert len(panel.plots) == 1 and len(panel.plots[0].data) == 1 + 2 * 3
        total = panel.plots[0].data[1]  # the left eye's, falling with distance (1 / z^2)
        assert np.all(np.diff(total) < 0) and total[1] > 10 * total[-1]
        assert "**Registration σ**" in panel.table.content
        assert "no calibration covariance in the rig" in panel.table.content
    finally:
        panel.stop()


def test_panel_shows_an_error_and_keeps_running(server) -> None:
    rig = default_rig()
    no_tof = Rig(
        sensors={n: s for n, s in rig.sensors.items() if s.modality != "tof"},
        reference="ccd_left",
        eyes=dict(rig.eyes),
    )
    ctx = SimpleNamespace(server=server, pipeline=SimpleNamespace(rig=no_tof))
    panel = PrecisionPanel(ctx, poll_s=0.05).start()
    try:
        _wait_for(panel, no_tof)
        assert panel.error is not None and "tof" in panel.error.lower()
        assert "Cannot analyse" in panel.status.content and panel.table.content == ""
        # a bad threshold typed by the operator is an error too, then corrected
        ctx.pipeline.rig = rig
        _wait_for(panel, rig)
        assert panel.error is None
        panel.threshold.value = 0.0  # below the input's minimum only in the browser
        _wait_for(panel, rig, panel.updates)
        assert "threshold_px" in panel.error and panel.result is None
        panel.threshold.value = 1.0
        _wait_for(panel, rig, panel.updates)
        assert panel.error is None
        assert panel.result.before.threshold_px == 1.0
        assert "exceeds **1 px**" in panel.table.content
    finally:
        panel.stop()


def test_plot_data_clips_to_the_log_axis() -> None:
    from trifuse.app.server.panels.precision import compute

    result = compute(default_rig())
    key = next(iter(result.before.distance_error))
    data, series, (lo, hi) = plot_data(result, key, "distance error", "y")
    assert lo == pytest.approx(0.001) and hi >= 2 * 0.5
    assert all(np.all(np.isfinite(a)) and np.all(a[1:] > 0) for a in data[1:])
    assert all(np.all(a >= lo) for a in data[1:])
    assert series[1]["label"] == "col L 41 mm" and series[5].get("dash")
    with pytest.raises(ValueError, match="kind"):
        plot_data(result, key, "nonsense", "x")


def test_short_names_fall_back_to_the_sensor_names() -> None:
    rig = default_rig()
    names = ("ccd_left", "ccd_right", "thermal_left", "thermal_right")
    assert short_names(rig, names) == {
        "ccd_left": "col L",
        "ccd_right": "col R",
        "thermal_left": "th L",
        "thermal_right": "th R",
    }
    assert short_names(rig, ("tof",)) == {"tof": "tof"}


# -- Feeds: the detected board drawn ---------------------------------------------------------

BOARD = Board(3, 2, 0.04)


def _sighting(frames: FrameSet, detections: dict[str, Detection]) -> BoardSighting:
    return BoardSighting(frames, detections, None, None, False)


def _colour_near(img: np.ndarray, x: int, y: int, colour: tuple[int, int, int]) -> bool:
    """Some pixel within 1 px of (x, y) has ``colour`` (within JPEG-free rounding)."""
    patch = img[y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3).astype(int)
    return bool(np.min(np.abs(patch - np.array(colour)).sum(axis=1)) <= 40)


def test_scale_corners_keeps_pixel_centres() -> None:
    thumb = np.zeros((240, 320, 3), np.uint8)
    c = scale_corners(np.array([[-0.5, -0.5], [639.5, 479.5], [100.5, 300.5]]), (640, 480), thumb)
    np.testing.assert_allclose(c, [[-0.5, -0.5], [319.5, 239.5], [50.0, 150.0]])


def test_found_board_is_drawn_at_the_thumbnail_scale() -> None:
    img = np.zeros((480, 640, 3), np.uint8)  # 640 wide -> 320: half scale
    # 3 x 2 corners at full-resolution pixels that land on whole thumbnail pixels
    xs, ys = np.array([100.5, 300.5, 500.5]), np.array([100.5, 300.5])
    corners = np.array([(x, y) for y in ys for x in xs])
    out = feed_image(Frame("ccd_left", 0, img), Detection(corners, None, "sb"), BOARD.cols)
    assert out.shape == (240, FEED_WIDTH_PX, 3) and out.dtype == np.uint8
    for i, (x, y) in enumerate(scale_corners(corners, (640, 480), out)):
        colour = ROW_COLOURS[i // BOARD.cols]
        assert _colour_near(out, round(x), round(y), colour), (i, x, y, out[round(y), round(x)])
    assert ROW_COLOURS[0] != ROW_COLOURS[1]
    # nothing at the corners' unscaled positions (beyond the markers and lines), or far away
    assert not out[200:, 280:].any()  # (500.5, 300.5) unscaled would be here
    assert out[10, 10].tolist() == [0, 0, 0]


def test_not_found_board_shows_the_reason() -> None:
    reason = "board (9x6 inner corners) not found (tried sb-x3, classic-x3)"
    assert short_reason(reason) == "board not found"
    assert short_reason(
        "board touches the image border (corner 3 is 1.0 px from the left edge, at least "
        "4.0 px needed)"
    ) == ("board touches the image border")
    assert short_reason(None) == "board not found"
    img = np.tile(np.linspace(500.0, 1500.0, 176, dtype=np.float32), (144, 1))  # TOF amplitude
    plain = feed_image(Frame("tof", 0, img), None, BOARD.cols)
    noted = feed_image(Frame("tof", 0, img), Detection(None, reason, None), BOARD.cols)
    h = noted.shape[0]
    np.testing.assert_array_equal(noted[: h - 20], plain[: h - 20])  # the image stays
    strip = noted[h - 14 :]
    assert strip.max() == 255  # white text ...
    assert np.median(strip) < np.median(plain[h - 14 :]) / 2  # ... on a darkened strip


class _Watch:
    def __init__(self, latest: BoardSighting | None) -> None:
        self.latest, self.enabled = latest, True
        self.latest_pose = None
        self.pose_listeners: list = []


def _panels(server: viser.ViserServer, sighting: BoardSighting | None) -> Panels:
    rig = default_rig()
    pipeline = SimpleNamespace(
        rig=rig,
        settings=DisplaySettings(),
        radiometry={"thermal_left": Radiometry(), "thermal_right": Radiometry()},
        latest_set=None,
    )
    return display_panels(server, pipeline, _Watch(sighting), board=BOARD)


def test_feeds_draw_the_sightings_own_frames_while_it_is_recent(server) -> None:
    old = np.zeros((480, 640, 3), np.uint8)
    new = np.full((480, 640, 3), 90, np.uint8)
    corners = np.array([(x, y) for y in (100.5, 300.5) for x in (100.5, 300.5, 500.5)])
    t0 = 1_000_000_000_000
    searched = FrameSet(
        t0, {"ccd_left": Frame("ccd_left", t0, old), "tof": Frame("tof", t0, np.ones((144, 176)))}
    )
    sighting = _sighting(
        searched,
        {
            "ccd_left": Detection(corners, None, "sb"),
            "tof": Detection(None, "board (3x2 inner corners) not found (tried sb)", None),
        },
    )
    panels = _panels(server, sighting)
    t1 = t0 + 2_000_000_000  # the newest frame set, 2 s later
    newest = FrameSet(t1, {"ccd_left": Frame("ccd_left", t1, new)})
    panels.update_feeds(newest, sighting)
    shown = panels.feeds["ccd_left"].image
    assert shown[10, 10].tolist() == [0, 0, 0]  # the sighting's frame, not the newest
    assert _colour_near(shown, 50, 50, ROW_COLOURS[0])
    assert panels.feeds_shown["tof"][1] is sighting.detections["tof"]
    assert panels.feeds["ccd_left"].label == "ccd_left (board search: 2 s ago)"
    assert panels.feeds["ccd_right"].label == "ccd_right"  # not in the sighting
    # a stale sighting is not drawn: the newest frame as it is
    t2 = t0 + int((panels_mod.SIGHTING_RECENT_S + 1) * 1e9)
    later = FrameSet(t2, {"ccd_left": Frame("ccd_left", t2, new)})
    panels.update_feeds(later, sighting)
    shown = panels.feeds["ccd_left"].image
    assert np.all(np.abs(shown.astype(int) - 90) <= 1)  # no markers
    assert panels.feeds["ccd_left"].label == "ccd_left"
    panels.update_feeds(later, None)  # no sighting at all: the same
    assert panels.feeds_shown["ccd_left"][1] is None


def test_feeds_draw_the_next_views_outline_and_redraw_when_it_changes(server) -> None:
    """The next-pose advisor's outline (``ctx.next_outline``, full-image pixels) is drawn
    cyan at the thumbnail's scale in that sensor's feed only, on top of the corners; a new
    suggestion redraws the feed on the same frame and none clears it."""
    from trifuse.app.server.panels.display import NEXT_RGB

    t0 = 1_000_000_000_000
    frames = {n: Frame(n, t0, np.zeros((480, 640, 3), np.uint8)) for n in ("ccd_left", "ccd_right")}
    newest = FrameSet(t0, frames)
    panels = _panels(server, None)
    outline = np.array([[100.0, 80.0], [540.0, 80.0], [540.0, 400.0], [100.0, 400.0]])
    panels.ctx.next_outline = {"ccd_left": outline}
    panels.update_feeds(newest, None)
    left, right = panels.feeds["ccd_left"].image, panels.feeds["ccd_right"].image
    for x, y in scale_corners(outline, (640, 480), left):  # 640 -> 320: half scale
        assert _colour_near(left, round(x), round(y), NEXT_RGB), (x, y)
    assert not _colour_near(left, 160, 120, NEXT_RGB)  # inside the outline: the image
    assert not right.any()  # the other sensor's feed: the frame as it is
    moved = outline + 40.0
    panels.ctx.next_outline = {"ccd_left": moved}
    panels.update_feeds(newest, None)  # same frame, new outline: redrawn
    again = panels.feeds["ccd_left"].image
    x, y = scale_corners(moved, (640, 480), again)[2]
    assert _colour_near(again, round(x), round(y), NEXT_RGB)
    panels.ctx.next_outline = {}
    panels.update_feeds(newest, None)
    assert not panels.feeds["ccd_left"].image.any()


def test_close_corners_get_dots_that_leave_the_board_visible() -> None:
    img = np.zeros((960, 1280, 3), np.uint8)  # 1280 -> 320: quarter scale
    # 24 px apart in the image, 6 px in the thumbnail: dots, no lines between them
    corners = np.array(
        [(400.0 + 24 * c + 1.5, 400.0 + 24 * r + 1.5) for r in range(2) for c in range(3)]
    )
    out = feed_image(Frame("ccd_left", 0, img), Detection(corners, None, "sb"), BOARD.cols)
    pts = scale_corners(corners, (1280, 960), out)
    for i, (x, y) in enumerate(pts):
        assert _colour_near(out, round(x), round(y), ROW_COLOURS[i // BOARD.cols])
    mid = (pts[0] + pts[1]) / 2  # halfway between two corners of a row
    assert out[round(mid[1]), round(mid[0])].tolist() == [0, 0, 0]
