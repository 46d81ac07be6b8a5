"""Palettes, display composition and the stereo pair (fusion.palettes, fusion.compose)."""

from __future__ import annotations

import dataclasses
import tracemalloc

import cv2
import numpy as np
import pytest

from trifuse.fusion.cloud_colors import point_colors
from trifuse.fusion.compose import DISPLAY_MODES, DisplaySettings, pip_box
from trifuse.fusion.composer import Composer
from trifuse.fusion.palettes import (
    PALETTE_NAMES,
    apply_palette,
    check_span,
    palette,
    palette_bar,
    palette_colors,
    temperature_index,
)
from trifuse.fusion.span import auto_span, resolve_span
from trifuse.fusion.stereo_pair import anaglyph, side_by_side, stereo_halves

W, H = 64, 48
SPAN = (290.0, 310.0)


def luma(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def scene(seed: int = 0, width: int = W, height: int = H):
    """Random colour, temperatures on a 0.25 K grid in 288-312 K (so thresholds hit exactly),
    a NaN band and scattered NaN, a fallback block that overlaps the NaN band."""
    rng = np.random.default_rng(seed)
    color = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    thermal = (288.0 + 0.25 * rng.integers(0, 97, (height, width))).astype(np.float32)
    thermal[:, : width // 8] = np.nan
    thermal[rng.random((height, width)) < 0.05] = np.nan
    fallback = np.zeros((height, width), bool)
    fallback[height // 2 :, : width // 2] = True
    return color, thermal, fallback


def palette_image(thermal: np.ndarray, name: str = "iron", span=SPAN) -> np.ndarray:
    return apply_palette(thermal, span, name)


# -- palettes ------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PALETTE_NAMES)
def test_palette_tables_are_256_rgb(name: str) -> None:
    table = palette(name)
    assert table.shape == (256, 3) and table.dtype == np.uint8
    assert not table.flags.writeable
    assert len({tuple(c) for c in table}) > 200  # a real ramp, not a few steps


def test_grey_ramps_are_monotone() -> None:
    assert np.all(np.diff(luma(palette("white_hot"))) > 0)
    assert np.all(np.diff(luma(palette("black_hot"))) < 0)
    np.testing.assert_array_equal(palette("white_hot")[:, 0], np.arange(256))


@pytest.mark.parametrize("name", ["iron", "lava", "arctic"])
def test_warm_palettes_go_dark_to_bright(name: str) -> None:
    y = luma(palette(name))
    assert np.all(np.diff(y) > -1.0)  # non-decreasing up to rounding of the entries
    assert y[0] < 15 and y[-1] > 230


def test_iron_hot_end_is_warm_cold_end_dark() -> None:
    iron = palette("iron").astype(int)
    assert iron[0].max() < 10
    mid = iron[128]
    assert mid[0] > mid[2]  # reddish in the middle


def test_unknown_palette() -> None:
    with pytest.raises(ValueError, match="palette: expected one of iron"):
        palette("jet")


@pytest.mark.parametrize("name", PALETTE_NAMES)
def test_span_ends_map_to_first_and_last_entry(name: str) -> None:
    low, high = 293.15, 313.15
    k = np.arange(256)
    t = (low + (high - low) * k / 255.0).astype(np.float32)
    t = np.concatenate([t, [low - 5.0, high + 5.0]]).astype(np.float32).reshape(2, 129)
    idx = temperature_index(t, (low, high)).reshape(-1)
    np.testing.assert_array_equal(idx[:256], k)  # every entry reachable, low -> 0, high -> 255
    assert idx[256] == 0 and idx[257] == 255  # saturation outside the span
    rgb = apply_palette(t, (low, high), name).reshape(-1, 3)
    table = palette(name)
    np.testing.assert_array_equal(rgb[0], table[0])
    np.testing.assert_array_equal(rgb[255], table[255])
    np.testing.assert_array_equal(rgb[:256], table)


def test_apply_palette_writes_into_buffers_and_nan_color() -> None:
    _, t, _ = scene(1)
    out = np.zeros((H, W, 3), np.uint8)
    idx = np.zeros((H, W), np.uint8)
    r = apply_palette(t, SPAN, "white_hot", out=out, index_out=idx, nan_color=(1, 2, 3))
    assert r is out
    assert np.all(out[np.isnan(t)] == (1, 2, 3))
    ok = ~np.isnan(t)
    np.testing.assert_array_equal(out[ok][:, 0], idx[ok])  # white_hot: value = index
    with pytest.raises(ValueError, match=r"out: expected a uint8 array of shape \(48, 64, 3\)"):
        apply_palette(t, SPAN, out=np.zeros((H, W), np.uint8))
    with pytest.raises(ValueError, match="thermal_k: expected a"):
        apply_palette(np.zeros((H, W), np.int32), SPAN)


@pytest.mark.parametrize(
    ("span", "message"),
    [
        ((300.0, 300.0), "finite low_k < high_k"),
        ((310.0, 300.0), "finite low_k < high_k"),
        ((np.nan, 300.0), "finite low_k < high_k"),
        ((300.0,), "two finite numbers"),
        ("hot", "two finite numbers"),
    ],
)
def test_check_span_errors(span, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        check_span(span)


def test_palette_bar() -> None:
    bar = palette_bar("iron", 300, 20)
    assert bar.shape == (20, 300, 3) and bar.dtype == np.uint8
    np.testing.assert_array_equal(bar[5, 0], palette("iron")[0])
    np.testing.assert_array_equal(bar[5, -1], palette("iron")[-1])
    assert np.all(bar == bar[:1])  # every row the same
    vbar = palette_bar("white_hot", 16, 256)
    assert vbar.shape == (256, 16, 3)
    np.testing.assert_array_equal(vbar[:, 3, 0], np.arange(255, -1, -1))  # hot at the top
    with pytest.raises(ValueError, match="width: expected a positive integer"):
        palette_bar("iron", 0, 10)
    with pytest.raises(ValueError, match="orientation"):
        palette_bar("iron", 10, 10, "diagonal")


def test_palette_colors_matches_image_path() -> None:
    _, t, _ = scene(2)
    ok = ~np.isnan(t)
    c = palette_colors(t, SPAN, "lava", nan_color=(7, 8, 9))
    np.testing.assert_array_equal(c[ok], palette_image(t, "lava")[ok])
    assert np.all(c[~ok] == (7, 8, 9))


# -- settings ------------------------------------------------------------------------------------


def test_settings_defaults_and_normalisation() -> None:
    s = DisplaySettings(threshold_k=320, pip_size=0.25, span_k=[290, 300])
    assert s.threshold_k == (320.0, 320.0)
    assert s.pip_size == (0.25, 0.25)
    assert s.span_k == (290.0, 300.0)
    assert hash(s) == hash(dataclasses.replace(s))
    same = DisplaySettings(threshold_k=(320.0, 320.0), pip_size=(0.25, 0.25), span_k=(290.0, 300.0))
    assert s == same


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"mode": "overlay"}, "mode: expected one of color, blend"),
        ({"palette": "jet"}, "palette: expected one of iron"),
        ({"opacity": 1.5}, r"opacity: expected a number in \[0, 1\], got 1.5"),
        ({"opacity": "half"}, "opacity: expected a number"),
        ({"opacity": True}, "opacity: expected a number"),
        ({"span_k": (300, 290)}, "span_k: expected finite low_k < high_k"),
        ({"auto_low_pct": 50, "auto_high_pct": 40}, "auto_low_pct, auto_high_pct"),
        ({"threshold_k": (310, 300)}, "threshold_k: expected low_k <= high_k"),
        ({"threshold_k": (1, 2, 3)}, "threshold_k: expected"),
        ({"threshold_k": float("nan")}, "threshold_k: expected a finite number"),
        ({"threshold_direction": "over"}, "threshold_direction: expected one of above"),
        ({"isotherm_k": (320, 310)}, "isotherm_k: expected low_k <= high_k"),
        ({"isotherm_color": (0, 256, 0)}, r"isotherm_color: expected an \(R, G, B\)"),
        ({"isotherm_color": "green"}, "isotherm_color: expected"),
        ({"isotherm_background": "black"}, "isotherm_background: expected one of"),
        ({"edge_strength": -1}, r"edge_strength: expected a number in \[0, 10"),
        ({"pip_center": (1.2, 0.5)}, r"pip_center: expected values in \[0.0, 1.0\]"),
        ({"pip_size": 0}, r"pip_size: expected values in \(0.0, 1.0\]"),
        ({"pip_size": (0.5, 0.5, 0.5)}, "pip_size: expected a number or a pair"),
        ({"mark_fallback": "yes"}, "mark_fallback: expected True or False"),
    ],
)
def test_settings_validation(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DisplaySettings(**kwargs)


# -- composition ---------------------------------------------------------------------------------


def compose(mode: str, seed: int = 0, **kw):
    color, thermal, fallback = scene(seed)
    kw.setdefault("mark_fallback", False)
    out = Composer(W, H).compose(color, thermal, fallback, DisplaySettings(mode=mode, **kw), SPAN)
    return out.copy(), color, thermal, fallback


def test_color_mode_is_the_colour_image() -> None:
    out, color, _, _ = compose("color", mark_fallback=True)
    np.testing.assert_array_equal(out, color)


def test_blend_extremes() -> None:
    out, color, _, _ = compose("blend", opacity=0.0, mark_fallback=True)
    np.testing.assert_array_equal(out, color)  # nothing painted, hence nothing marked
    out, color, t, _ = compose("blend", opacity=1.0)
    ok = ~np.isnan(t)
    np.testing.assert_array_equal(out[ok], palette_image(t)[ok])
    np.testing.assert_array_equal(out[~ok], color[~ok])


def test_blend_is_the_weighted_mean() -> None:
    out, color, t, _ = compose("blend", opacity=0.25)
    ok = ~np.isnan(t)
    expected = 0.25 * palette_image(t).astype(float) + 0.75 * color.astype(float)
    assert np.abs(out[ok].astype(float) - expected[ok]).max() <= 0.51


def test_thermal_mode_is_the_palette_image() -> None:
    out, color, t, _ = compose("thermal", palette="arctic")
    ok = ~np.isnan(t)
    np.testing.assert_array_equal(out[ok], palette_image(t, "arctic")[ok])
    np.testing.assert_array_equal(out[~ok], color[~ok])


def test_edges_emboss_only_the_colour_edges() -> None:
    color = np.full((H, W, 3), 60, np.uint8)
    color[:, W // 2 :] = 200  # one vertical step at W/2
    thermal = np.full((H, W), 300.0, np.float32)
    comp = Composer(W, H)
    flat = comp.compose(color, thermal, None, DisplaySettings(mode="thermal"), SPAN).copy()
    none = comp.compose(color, thermal, None, DisplaySettings(mode="edges", edge_strength=0), SPAN)
    np.testing.assert_array_equal(none, flat)
    out = comp.compose(color, thermal, None, DisplaySettings(mode="edges"), SPAN).copy()
    diff = np.abs(out.astype(int) - flat.astype(int)).max(axis=2)
    far = np.ones(W, bool)
    far[W // 2 - 3 : W // 2 + 3] = False
    assert diff[:, far].max() == 0  # flat areas: the palette image
    assert diff[:, W // 2 - 1].min() > 20 and diff[:, W // 2].min() > 20  # the step shows
    assert np.all(out[:, W // 2 - 1].astype(int) < flat[:, W // 2 - 1])  # dark side darker
    assert np.all(out[:, W // 2].astype(int) > flat[:, W // 2])  # bright side brighter


PAINTING = [
    {"mode": "blend"},
    {"mode": "blend", "opacity": 1.0},
    {"mode": "edges", "edge_strength": 3.0},
    {"mode": "thermal"},
    {"mode": "threshold", "threshold_k": 300.0, "threshold_direction": "above"},
    {"mode": "threshold", "threshold_k": 300.0, "threshold_direction": "below"},
    {"mode": "threshold", "threshold_k": (295.0, 305.0), "threshold_direction": "inside"},
    {"mode": "isotherm", "isotherm_k": (295.0, 305.0)},
    {"mode": "isotherm", "isotherm_k": (295.0, 305.0), "isotherm_color": (0, 255, 0)},
    {"mode": "isotherm", "isotherm_background": "color"},
    {"mode": "pip"},
    {"mode": "pip", "pip_size": 1.0},
    {"mode": "color"},
    {"mode": "registration"},  # no estimate: the colour image (test_registration_overlay.py)
]


@pytest.mark.parametrize("kw", PAINTING, ids=lambda kw: "-".join(map(str, kw.values())))
@pytest.mark.parametrize("mark", [False, True])
def test_nan_pixels_are_never_painted(kw: dict, mark: bool) -> None:
    out, color, t, fallback = compose(seed=3, mark_fallback=mark, **kw)
    nan = np.isnan(t)
    assert (nan & fallback).any()  # the fallback block overlaps NaN pixels
    np.testing.assert_array_equal(out[nan], color[nan])


def test_every_mode_is_covered() -> None:
    assert {kw["mode"] for kw in PAINTING} == set(DISPLAY_MODES)


def selection(t: np.ndarray, direction: str, low: float, high: float) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return {"above": t > high, "below": t < low, "inside": (t >= low) & (t <= high)}[direction]


@pytest.mark.parametrize("direction", ["above", "below", "inside"])
def test_threshold_paints_exactly_the_selection(direction: str) -> None:
    low, high = 297.0, 303.0  # on the scene's 0.25 K grid: the boundaries occur exactly
    out, color, t, _ = compose(
        "threshold", seed=4, threshold_k=(low, high), threshold_direction=direction
    )
    assert (t == low).any() and (t == high).any()
    sel = selection(t, direction, low, high)
    pal = palette_image(t)
    assert sel.sum() > 100 and (~sel).sum() > 100
    np.testing.assert_array_equal(out[sel], pal[sel])
    np.testing.assert_array_equal(out[~sel], color[~sel])


def test_threshold_directions_partition_the_readings() -> None:
    _, t, _ = scene(5)
    black = np.zeros((H, W, 3), np.uint8)
    comp = Composer(W, H)
    total = np.zeros((H, W), int)
    for direction in ("above", "below", "inside"):
        s = DisplaySettings(
            mode="threshold",
            threshold_k=(299.0, 301.0),
            threshold_direction=direction,
            palette="white_hot",
            mark_fallback=False,
        )
        out = comp.compose(black, t, None, s, (280.0, 320.0))  # every reading paints > 0
        total += np.any(out > 0, axis=2)
    np.testing.assert_array_equal(total, (~np.isnan(t)).astype(int))


def test_threshold_single_temperature() -> None:
    out, color, t, _ = compose("threshold", seed=6, threshold_k=300.0)
    sel = t > 300.0
    np.testing.assert_array_equal(out[sel], palette_image(t)[sel])
    np.testing.assert_array_equal(out[~sel], color[~sel])


def test_isotherm_highlights_exactly_the_interval_solid_on_grey() -> None:
    low, high = 296.0, 300.0
    out, color, t, _ = compose(
        "isotherm", seed=7, isotherm_k=(low, high), isotherm_color=(0, 255, 0)
    )
    sel = selection(t, "inside", low, high)
    assert sel.sum() > 100
    assert np.all(out[sel] == (0, 255, 0))
    grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
    rest = ~sel & ~np.isnan(t)
    for k in range(3):
        np.testing.assert_array_equal(out[..., k][rest], grey[rest])
    nan = np.isnan(t)
    np.testing.assert_array_equal(out[nan], color[nan])


def test_isotherm_palette_colour_on_colour() -> None:
    low, high = 296.0, 300.0
    out, color, t, _ = compose(
        "isotherm", seed=8, isotherm_k=(low, high), isotherm_background="color", palette="rainbow"
    )
    sel = selection(t, "inside", low, high)
    np.testing.assert_array_equal(out[sel], palette_image(t, "rainbow")[sel])
    np.testing.assert_array_equal(out[~sel], color[~sel])


@pytest.mark.parametrize(
    ("center", "size", "box"),
    [
        ((0.5, 0.5), (0.5, 0.5), (16, 12, 48, 36)),
        ((0.25, 0.75), 0.25, (8, 30, 24, 42)),
        ((1.0, 0.0), (0.5, 0.5), (32, 0, 64, 24)),  # shifted to lie inside the image
        ((0.5, 0.5), 1.0, (0, 0, 64, 48)),
    ],
)
def test_pip_places_the_inset(center, size, box) -> None:
    s = DisplaySettings(mode="pip", pip_center=center, pip_size=size, mark_fallback=False)
    assert pip_box(s, W, H) == box
    color, t, fallback = scene(9)
    out = Composer(W, H).compose(color, t, fallback, s, SPAN)
    x0, y0, x1, y1 = box
    inside = np.zeros((H, W), bool)
    inside[y0:y1, x0:x1] = True
    painted = inside & ~np.isnan(t)
    np.testing.assert_array_equal(out[painted], palette_image(t)[painted])
    np.testing.assert_array_equal(out[~painted], color[~painted])


def painted_mask(kw: dict, t: np.ndarray) -> np.ndarray:
    """The pixels that show thermal information in the settings ``kw`` (module docstring)."""
    s = DisplaySettings(**kw)
    valid = ~np.isnan(t)
    if s.mode in ("blend", "edges", "thermal"):
        return valid
    if s.mode == "threshold":
        return selection(t, s.threshold_direction, *s.threshold_k)
    if s.mode == "isotherm":
        return selection(t, "inside", *s.isotherm_k)
    if s.mode == "pip":
        x0, y0, x1, y1 = pip_box(s, W, H)
        inside = np.zeros_like(valid)
        inside[y0:y1, x0:x1] = True
        return inside & valid
    return np.zeros_like(valid)


@pytest.mark.parametrize(
    "kw",
    # registration: no estimate where the depth is a fallback, so nothing to veil
    [k for k in PAINTING if k["mode"] not in ("color", "registration")],
    ids=str,
)
def test_fallback_marking_changes_only_painted_fallback_pixels(kw: dict) -> None:
    off, _, t, fallback = compose(seed=10, mark_fallback=False, **kw)
    on, _, _, _ = compose(seed=10, mark_fallback=True, **kw)
    changed = np.any(on != off, axis=2)
    marked = painted_mask(kw, t) & fallback
    assert marked.sum() > 20
    assert not (changed & ~marked).any()
    # visible: the veil moves (nearly) every marked pixel, by a step that shows over an area
    assert changed[marked].mean() > 0.9
    shift = np.abs(on.astype(int) - off.astype(int)).max(axis=2)
    assert np.median(shift[changed]) >= 15


def test_fallback_veil_shows_on_black_white_and_colour() -> None:
    """The veil (compose.py's docstring) fades black and white towards mid-grey and mutes
    colours; a uniform mid-grey, its fixed point, stays as it is."""
    comp = Composer(W, H)
    thermal = np.full((H, W), 300.0, np.float32)
    fallback = np.ones((H, W), bool)
    color = np.zeros((H, W, 3), np.uint8)
    for name, span, changes in [
        ("white_hot", (300.0, 310.0), True),  # black
        ("white_hot", (290.0, 300.0), True),  # white
        ("white_hot", (295.0, 305.0), False),  # mid-grey
        ("iron", (295.0, 305.0), True),  # a saturated red
    ]:
        s = DisplaySettings(mode="thermal", palette=name, mark_fallback=True)
        out = comp.compose(color, thermal, fallback, s, span)
        base = palette_image(thermal, name, span)
        shift = np.abs(out.astype(int) - base.astype(int)).max(axis=2)
        assert (shift.min() >= 6) if changes else (shift.max() <= 1), (name, span)


def test_compose_input_validation() -> None:
    color, t, fb = scene(11)
    comp = Composer(W, H)
    s = DisplaySettings()
    with pytest.raises(ValueError, match=r"color: expected uint8 \(48, 64, 3\) RGB"):
        comp.compose(color[:, :-1], t, fb, s)
    with pytest.raises(ValueError, match="thermal_k: expected float32"):
        comp.compose(color, np.zeros((H, W), np.uint16), fb, s)
    with pytest.raises(ValueError, match="fallback: expected bool"):
        comp.compose(color, t, fb.astype(np.uint8), s)
    with pytest.raises(ValueError, match="out: must not overlap"):
        comp.compose(color, t, fb, s, SPAN, out=color)
    with pytest.raises(ValueError, match="settings: expected DisplaySettings"):
        comp.compose(color, t, fb, {"mode": "blend"})
    with pytest.raises(ValueError, match="span: expected finite"):
        comp.compose(color, t, fb, s, (300.0, 290.0))
    with pytest.raises(ValueError, match="width: expected a positive integer"):
        Composer(0, 10)


def test_compose_without_span_uses_settings_or_auto() -> None:
    color, t, fb = scene(12)
    comp = Composer(W, H)
    fixed = DisplaySettings(mode="thermal", span_k=SPAN)
    np.testing.assert_array_equal(
        comp.compose(color, t, fb, fixed).copy(), comp.compose(color, t, fb, fixed, SPAN)
    )
    auto = DisplaySettings(mode="thermal")
    span = resolve_span(auto, t)
    np.testing.assert_array_equal(
        comp.compose(color, t, fb, auto).copy(), comp.compose(color, t, fb, auto, span)
    )
    all_nan = np.full_like(t, np.nan)
    np.testing.assert_array_equal(comp.compose(color, all_nan, fb, auto), color)


def test_float64_thermal_gives_the_same_picture() -> None:
    color, t, fb = scene(13)
    comp = Composer(W, H)
    for mode in DISPLAY_MODES:
        s = DisplaySettings(mode=mode, threshold_k=300.0)
        a = comp.compose(color, t, fb, s, SPAN).copy()
        b = comp.compose(color, t.astype(np.float64), fb, s, SPAN)
        np.testing.assert_array_equal(a, b)


def test_steady_state_compose_allocates_no_frame() -> None:
    w, h = 1280, 960
    frame_bytes = w * h * 3
    rng = np.random.default_rng(14)
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    thermal = (290.0 + 20.0 * rng.random((h, w))).astype(np.float32)
    thermal[:, :100] = np.nan
    fallback = np.zeros((h, w), bool)
    fallback[500:900, 200:700] = True
    comp = Composer(w, h)
    out = np.empty((h, w, 3), np.uint8)
    settings = [
        DisplaySettings(mode=m, threshold_k=300.0, isotherm_color=(0, 255, 0))
        for m in DISPLAY_MODES
    ]
    for s in settings:  # warm-up: first use of a solid colour fills a buffer
        comp.compose(color, thermal, fallback, s, None, out=out)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        for s in settings:
            comp.compose(color, thermal, fallback, s, SPAN, out=out)
            comp.compose(color, thermal, fallback, s, None)  # automatic span, internal out
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < frame_bytes / 10, f"peak {peak} bytes"


# -- automatic span ------------------------------------------------------------------------------


def test_auto_span_covers_both_eyes() -> None:
    rng = np.random.default_rng(15)
    left = (295.0 + 10.0 * rng.random((H * 4, W * 4))).astype(np.float32)
    left[:, :20] = np.nan
    right = left + np.float32(1.5)
    low, high = auto_span([left, right], step=2)
    assert 295.0 <= low < 295.5 and 306.0 < high <= 306.5
    _, l_high = auto_span(left, step=2)
    assert high - l_high > 1.0  # one eye alone would clip the other's hot end
    ok = ~np.isnan(left)
    assert np.mean(right[ok] > high) < 0.02 and np.mean(left[ok] < low) < 0.02
    assert resolve_span(DisplaySettings(), [left, right]) == auto_span([left, right])
    assert resolve_span(DisplaySettings(span_k=SPAN), [left, right]) == SPAN


def test_auto_span_edge_cases() -> None:
    uniform = np.full((H, W), 300.0, np.float32)
    assert auto_span(uniform, min_span_k=2.0) == (299.0, 301.0)
    nan = np.full((H, W), np.nan, np.float32)
    with pytest.raises(ValueError, match="at least one finite temperature"):
        auto_span([nan, nan])
    assert auto_span([nan], default=SPAN) == SPAN
    with pytest.raises(ValueError, match="low_pct, high_pct"):
        auto_span(uniform, 99, 1)
    with pytest.raises(ValueError, match="step: expected a positive integer"):
        auto_span(uniform, step=0)


# -- stereo pair ---------------------------------------------------------------------------------


def test_side_by_side_layout() -> None:
    left, _, _ = scene(16)
    right, _, _ = scene(17)
    sbs = side_by_side(left, right)
    assert sbs.shape == (H, 2 * W, 3)
    np.testing.assert_array_equal(sbs[:, :W], left)
    np.testing.assert_array_equal(sbs[:, W:], right)
    buf = np.zeros_like(sbs)
    assert side_by_side(left, right, buf) is buf
    with pytest.raises(ValueError, match=r"out: expected uint8 \(48, 128, 3\)"):
        side_by_side(left, right, np.zeros((H, W, 3), np.uint8))
    with pytest.raises(ValueError, match="right: expected the shape of left"):
        side_by_side(left, right[:, 1:])


def test_compose_into_stereo_halves() -> None:
    cl, tl, fl = scene(18)
    cr, tr, fr = scene(19)
    s = DisplaySettings(mode="blend", mark_fallback=True)
    span = resolve_span(s, [tl, tr])
    sbs = np.zeros((H, 2 * W, 3), np.uint8)
    lh, rh = stereo_halves(sbs)
    left, right = Composer(W, H), Composer(W, H)
    left.compose(cl, tl, fl, s, span, out=lh)
    right.compose(cr, tr, fr, s, span, out=rh)
    np.testing.assert_array_equal(sbs[:, :W], Composer(W, H).compose(cl, tl, fl, s, span))
    np.testing.assert_array_equal(sbs[:, W:], Composer(W, H).compose(cr, tr, fr, s, span))


def test_anaglyph_channels() -> None:
    left, _, _ = scene(20)
    right, _, _ = scene(21)
    a = anaglyph(left, right)
    np.testing.assert_array_equal(a[..., 0], left[..., 0])
    np.testing.assert_array_equal(a[..., 1:], right[..., 1:])
    g = anaglyph(left, right, np.zeros_like(left), method="grey")
    np.testing.assert_array_equal(g[..., 0], cv2.cvtColor(left, cv2.COLOR_RGB2GRAY))
    np.testing.assert_array_equal(g[..., 1], cv2.cvtColor(right, cv2.COLOR_RGB2GRAY))
    np.testing.assert_array_equal(g[..., 2], g[..., 1])
    with pytest.raises(ValueError, match="method: expected 'color' or 'grey'"):
        anaglyph(left, right, method="green-magenta")
    with pytest.raises(ValueError, match="out: must not overlap"):
        anaglyph(left, right, out=left)


# -- point colours -------------------------------------------------------------------------------


def test_point_colors() -> None:
    rng = np.random.default_rng(22)
    pts = rng.normal(0.0, 1.0, (100, 3))
    pts[5] = np.nan
    rgb = rng.integers(0, 256, (100, 3), dtype=np.uint8)
    c = point_colors(pts, "color", rgb)
    np.testing.assert_array_equal(c, rgb)
    assert c is not rgb

    temps = np.linspace(290.0, 310.0, 100)
    temps[7] = np.nan
    c = point_colors(pts, "temperature", temps, span=SPAN, palette="white_hot")
    assert tuple(c[0]) == (0, 0, 0) and tuple(c[-1]) == (255, 255, 255)
    assert tuple(c[5]) == (128, 128, 128) and tuple(c[7]) == (128, 128, 128)  # NaN point, NaN T
    assert np.all(np.diff(c[8:-1, 0].astype(int)) >= 0)

    pts = np.zeros((4, 3))
    pts[:, 2] = [1.0, 2.0, 3.0, np.nan]
    c = point_colors(pts, "depth", span=(1.0, 3.0), palette="white_hot")
    np.testing.assert_array_equal(c[:, 0], [0, 128, 255, 128])
    c = point_colors(pts, "depth", palette="white_hot")  # automatic span: 1st-99th pct
    assert c[0, 0] < 10 and c[2, 0] > 245

    with pytest.raises(ValueError, match="by: expected 'color', 'temperature' or 'depth'"):
        point_colors(pts, "amplitude")
    with pytest.raises(ValueError, match=r"values: expected uint8 \(4, 3\) RGB"):
        point_colors(pts, "color", np.zeros((3, 3), np.uint8))
    with pytest.raises(ValueError, match=r"values: expected shape \(4,\) in kelvin"):
        point_colors(pts, "temperature", np.zeros(3))
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 3\)"):
        point_colors(np.zeros((4, 2)), "depth")
