"""The fused stereo pair from the simulated head."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.fusion.accuracy import band_errors, depth_edges, exact_mapping
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.stereo import StereoFusion


@pytest.fixture(scope="module")
def scene():
    scenario = InspectionScenario(seed=3)
    frames, truth = scenario.render(3.0)
    rig = scenario.rig
    colors = {e: frames[rig.eyes[e].color].image for e in ("left", "right")}
    thermals = {e: frames[rig.eyes[e].thermal].image for e in ("left", "right")}
    return scenario, frames, truth, colors, thermals


def test_side_by_side_pair_with_one_shared_span(scene) -> None:
    scenario, frames, _truth, colors, thermals = scene
    fusion = StereoFusion(scenario.rig)
    with pytest.raises(RuntimeError, match="no TOF frame"):
        fusion.compose(colors, thermals, DisplaySettings())
    fusion.update_depth(frames["tof"].distance_m)
    out = fusion.compose(colors, thermals, DisplaySettings(mode="color"))
    assert out.shape == (960, 2560, 3)
    assert np.array_equal(out[:, :1280], colors["left"])
    assert np.array_equal(out[:, 1280:], colors["right"])
    fusion.compose(colors, thermals, DisplaySettings(mode="blend"))
    lo, hi = fusion.span_k
    # One span for both eyes: it covers both imagers' readings (1.5 K apart by default).
    for e in ("left", "right"):
        t = fusion.thermal_on_color[e]
        assert np.nanpercentile(t, 50) > lo and np.nanpercentile(t, 50) < hi
    assert fusion.anaglyph().shape == (960, 1280, 3)


@pytest.mark.parametrize(
    "settings",
    [
        DisplaySettings(mode="blend"),
        DisplaySettings(mode="edges", agc="dde"),
        DisplaySettings(mode="pip", agc="linear"),
    ],
    ids=["blend", "edges-dde", "pip-linear"],
)
def test_eyes_on_two_threads_give_the_same_mappings_and_picture(scene, settings) -> None:
    """The console runs each eye's mapping update, warp and composition on two threads
    (``map_eyes``): the mappings and the picture are those of one eye after the other."""
    scenario, frames, _truth, colors, thermals = scene
    one, two = StereoFusion(scenario.rig), StereoFusion(scenario.rig)
    with ThreadPoolExecutor(2) as pool:
        two.map_eyes = pool.map
        for fusion in (one, two):
            fusion.update_depth(frames["tof"].distance_m)
        for e in ("left", "right"):
            a, b = one.fusion[e].forward, two.fusion[e].forward
            assert np.array_equal(a.map_x, b.map_x) and np.array_equal(a.map_y, b.map_y)
        for stamp_ns in (0, 40_000_000):  # the second with the span smoothed over time
            assert np.array_equal(
                one.compose(colors, thermals, settings, stamp_ns),
                two.compose(colors, thermals, settings, stamp_ns),
            )


def test_reverse_direction_draws_colour_into_the_thermal_view(scene) -> None:
    scenario, frames, truth, colors, _thermals = scene
    fusion = StereoFusion(scenario.rig)
    fusion.update_depth(frames["tof"].distance_m)
    view = fusion.color_in_thermal_view("left", colors["left"])
    assert view.shape == (288, 382, 3) and view.dtype == np.uint8
    # Its mapping agrees with the exact one (colour pixels), away from depth edges.
    rev = fusion.fusion["left"].reverse
    exact = exact_mapping(
        scenario.rig,
        "thermal_left",
        "ccd_left",
        truth["thermal_left"].range_m,
        truth["ccd_left"].range_m,
    )
    mask = ~depth_edges(exact.depth_m, 5) & rev.visible & ~rev.fallback
    far = [
        b
        for b in band_errors(np.stack([rev.map_x, rev.map_y], -1), exact, mask)
        if b.band_m[0] >= 2.0
    ]
    assert sum(b.pixels for b in far) > 20000
    # The TOF's ~40 mm range error moves a colour pixel by f b dz / z^2 < 0.2 px beyond 2 m.
    assert all(b.median_px < 0.5 for b in far if b.pixels), far


def test_point_cloud_coloured_by_colour_temperature_and_depth(scene) -> None:
    scenario, frames, _truth, colors, thermals = scene
    fusion = StereoFusion(scenario.rig)
    fusion.update_depth(frames["tof"].distance_m)
    pts, rgb = fusion.point_cloud(colors, thermals, "color")
    assert pts.shape[1] == 3 and rgb.shape == (len(pts), 3) and rgb.dtype == np.uint8
    assert np.isfinite(pts).all() and len(pts) > 15000
    _, hot = fusion.point_cloud(
        colors, thermals, "temperature", span=(290.0, 360.0), palette="white_hot"
    )
    # The hot pipe (358 K) is among the brightest points in white-hot, the walls dark.
    lum = hot.astype(float).mean(axis=1)
    assert np.percentile(lum, 99.5) > 200 and np.median(lum) < 80
    _, by_depth = fusion.point_cloud(colors, thermals, "depth", span=(0.5, 8.0))
    assert len(np.unique(by_depth, axis=0)) > 50


def test_mapping_aside_leaves_the_depth_in_use_until_it_is_put_in_use(scene) -> None:
    """``map_aside`` (the console's worker) maps a TOF frame without touching the mappings
    in use: the picture composed meanwhile is that of the previous depth; once put in use,
    the mappings and the picture are those ``update_depth`` makes of the same frame."""
    scenario, frames, _truth, colors, thermals = scene
    later, _ = scenario.render(3.4)
    settings = DisplaySettings(mode="blend")
    plain, aside = StereoFusion(scenario.rig), StereoFusion(scenario.rig)
    for fusion in (plain, aside):
        fusion.update_depth(frames["tof"].distance_m)
    before = plain.compose(colors, thermals, settings).copy()
    use = aside.map_aside(later["tof"].distance_m)
    assert np.array_equal(aside.compose(colors, thermals, settings), before)
    use()
    plain.update_depth(later["tof"].distance_m)
    for e in ("left", "right"):
        a, b = plain.fusion[e].forward, aside.fusion[e].forward
        assert np.array_equal(a.map_x, b.map_x) and np.array_equal(a.map_y, b.map_y)
        assert np.array_equal(a.fallback, b.fallback)
    assert np.array_equal(plain.points, aside.points)
    after = plain.compose(colors, thermals, settings)
    assert not np.array_equal(after, before)  # the head moved: the depth changed the picture
    assert np.array_equal(aside.compose(colors, thermals, settings), after)
    # and again: the set put aside by the first swap is the one mapped next
    use = aside.map_aside(frames["tof"].distance_m)
    use()
    assert np.array_equal(aside.compose(colors, thermals, settings), before)
