"""The display's AGC (fusion.agc), its use by the composer and the stream's colour scale, and
the quiet fallback marking (issue 19)."""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pytest

from trifuse.fusion.agc import (
    AGC_MODES,
    BIN_K,
    DEFAULT_MAX_GAIN,
    DEFAULT_PLATEAU,
    LINEAR_SHARE,
    LUT_PER_BIN,
    PaletteIndexer,
    ToneMap,
    ToneMapper,
    cap_gain,
    gain_span,
    index_entropy_bits,
    kelvin_histogram,
    plateau_cap,
    plateau_positions,
    tone_map,
)
from trifuse.fusion.compose import FALLBACK_DESATURATION, FALLBACK_FADE, DisplaySettings
from trifuse.fusion.composer import Composer
from trifuse.fusion.frame_meta import PALETTE_TICKS, scale_meta
from trifuse.fusion.palettes import palette, temperature_index
from trifuse.fusion.span import auto_span

W, H = 160, 120
WALL_K, FLOOR_K, PERSON_K, PIPE_K, COLD_K = 293.5, 292.3, 307.15, 358.0, 279.0
CRATE_K, CEILING_K, RADIATOR_K = 294.5, 294.3, 333.0


def room(seed: int, shift_px: int = 0, netd_k: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic eye of the inspection room with its temperatures (as
    ``app.sources.sim.inspection.inspection_scene`` has them, surfaces as read): ceiling,
    wall (a gentle vertical gradient), floor, a person, a small very hot pipe, a crate, a
    cold fridge and a radiator; NaN on the left tenth (outside the thermal view).
    ``shift_px`` moves the objects (the other eye's parallax). Returns the kelvin image
    (H, W) float32 and labels (H, W) int (0 wall, 1 floor, 2 person, 3 pipe, 4 fridge,
    5 crate, 6 ceiling, 7 radiator, -1 no reading)."""
    rng = np.random.default_rng(seed)
    yy, _ = np.mgrid[0:H, 0:W]
    labels = np.zeros((H, W), int)
    labels[: int(0.1 * H)] = 6
    labels[int(0.75 * H) :] = 1
    s = shift_px
    labels[30:110, 60 + s : 80 + s] = 2  # the person: about 13 % of the pixels
    labels[14:17, 20 + s : 150 + s] = 3  # the pipe: 2 %
    labels[30:75, 100 + s : 130 + s] = 4  # the fridge
    labels[80:120, 110 + s : 150 + s] = 5  # a crate in front
    labels[60:75, 25 + s : 45 + s] = 7  # the radiator
    temps = np.array([WALL_K, FLOOR_K, PERSON_K, PIPE_K, COLD_K, CRATE_K, CEILING_K, RADIATOR_K])
    t = temps[labels] + 0.5 * (1.0 - yy / H) * (labels == 0)
    t = (t + rng.normal(0.0, netd_k, (H, W))).astype(np.float32)
    t[:, : W // 10] = np.nan
    labels[:, : W // 10] = -1
    return t, labels


def both_eyes(seed: int = 0):
    left, ll = room(seed)
    right, rl = room(seed + 1, shift_px=6)
    return [left, right], [ll, rl]


def separation(index: list[np.ndarray], labels: list[np.ndarray]) -> float:
    """(median index of the person - median index of the wall) / 255, both eyes pooled."""
    person = np.concatenate([i[lab == 2] for i, lab in zip(index, labels, strict=True)])
    wall = np.concatenate([i[lab == 0] for i, lab in zip(index, labels, strict=True)])
    return (float(np.median(person)) - float(np.median(wall))) / 255.0


def indices(images: list[np.ndarray], tone: ToneMap) -> list[np.ndarray]:
    ix = PaletteIndexer(W, H)
    return [ix.index(t, tone).copy() for t in images]


# -- the histogram and the plateau ---------------------------------------------------------------


def test_histogram_counts_both_eyes_in_bins_over_the_span() -> None:
    images, _ = both_eyes(1)
    span = (290.0, 310.0)
    counts, edges = kelvin_histogram(images, span, step=1)
    assert len(counts) == round(20.0 / BIN_K) and edges[0] == 290.0 and edges[-1] == 310.0
    values = np.concatenate([t[np.isfinite(t)] for t in images])
    expected, _ = np.histogram(values, bins=edges)
    # the same counts (a value on a bin edge may fall either side in float32)
    assert np.abs(counts - expected).sum() <= 2 and counts.sum() == expected.sum()
    wide, wide_edges = kelvin_histogram(images, (0.0, 5000.0))
    assert len(wide) == 4096 and wide_edges[-1] == 5000.0  # wider bins, not more


def test_plateau_caps_each_bin() -> None:
    rng = np.random.default_rng(2)
    counts = rng.integers(0, 50, 200)
    counts[17] = 100_000  # one temperature fills most of the picture
    for plateau in (0.001, 0.01, 0.2):
        capped = plateau_cap(counts, plateau)
        cap = plateau * counts.sum()
        assert capped.max() <= cap + 1e-9
        np.testing.assert_array_equal(capped[counts <= cap], counts[counts <= cap])
        pos = plateau_positions(counts, plateau)
        assert pos[0] == 0.0 and pos[-1] == 1.0 and np.all(np.diff(pos) > 0)
        # no bin takes more of the palette than its capped share (plus the linear part)
        most = (1 - LINEAR_SHARE) * cap / capped.sum() + LINEAR_SHARE / len(counts)
        assert np.diff(pos).max() <= most + 1e-12
    plain = plateau_positions(counts, 1.0)  # plateau 1: plain histogram equalization
    assert np.diff(plain)[17] > 0.9 * (1 - LINEAR_SHARE)


def test_settings_validate_agc_and_plateau() -> None:
    s = DisplaySettings()
    assert s.agc == "plateau" and s.plateau == DEFAULT_PLATEAU
    assert s.max_gain == DEFAULT_MAX_GAIN == 12.0
    assert set(AGC_MODES) == {"linear", "plateau", "dde"}
    with pytest.raises(ValueError, match="agc: expected one of linear, plateau, dde"):
        DisplaySettings(agc="histogram")
    for bad in (0.0, 1.5, float("nan"), "x"):
        with pytest.raises(ValueError, match="plateau"):
            DisplaySettings(plateau=bad)
    assert DisplaySettings(max_gain=1).max_gain == 1.0
    for bad in (0.5, 1001.0, float("inf"), float("nan"), "x", None):
        with pytest.raises(ValueError, match="max_gain"):
            DisplaySettings(max_gain=bad)


# -- the maximum gain ----------------------------------------------------------------------------


def slopes(tone: ToneMap) -> np.ndarray:
    """The table's slope between its nodes, palette steps per kelvin."""
    return np.diff(tone.positions) * 255.0 / np.diff(tone.nodes_k)


def lut_steps_per_k(tone: ToneMap, window_k: float = 1.0) -> float:
    """The most the look-up table's index rises over ``window_k`` of temperature, per
    kelvin, over the whole table (rounding to whole entries included)."""
    m = round(window_k / tone.lut_step_k)
    n = (tone.nodes_k.size - 1) * LUT_PER_BIN + 1
    lut = tone.lut[:n].astype(int)
    return float((lut[m:] - lut[:-m]).max()) / (m * tone.lut_step_k)


@pytest.mark.parametrize("mode", ["plateau", "dde"])
@pytest.mark.parametrize("max_gain", [4.0, DEFAULT_MAX_GAIN, 30.0])
def test_the_table_never_exceeds_the_maximum_gain(mode: str, max_gain: float) -> None:
    """Over the whole table, of the synthetic room with and without its hot pipe, of random
    content and of a histogram with one huge bin: the slope stays within ``max_gain``, the
    look-up table rises by at most ``max_gain`` steps per kelvin (plus one of rounding per
    window), positions run from 0 to 1 strictly increasing, and the slope is at the cap
    somewhere (the cap bit: the uncapped table is steeper). A span narrower than
    ``255 / max_gain`` cannot keep to it (every bin at the cap would not fill the palette):
    its table is linear, the flattest there is."""
    images, _ = both_eyes(20)
    rng = np.random.default_rng(20)
    noisy = [(290.0 + 20.0 * rng.random((H, W))).astype(np.float32) for _ in range(2)]
    spiky = [np.full((H, W), np.float32(300.0)) for _ in range(2)]
    spiky[0][:10] = np.float32(330.0)
    cases = [
        (images, auto_span(images, 0.0, 100.0, step=1)),  # the pipe in the span
        (images, auto_span(images)),
        (noisy, (280.0, 320.0)),
        (spiky, (290.0, 340.0)),
        (noisy, (295.0, 305.0)),  # 10 K: too narrow for a maximum gain under 25.5
    ]
    for content, span in cases:
        tone = tone_map(content, mode, span, DEFAULT_PLATEAU, max_gain)
        free = tone_map(content, mode, span, DEFAULT_PLATEAU, 1000.0)
        assert tone.positions[0] == 0.0 and tone.positions[-1] == 1.0
        assert np.all(np.diff(tone.positions) > 0)
        if max_gain * (span[1] - span[0]) <= 255.0:
            np.testing.assert_allclose(slopes(tone), 255.0 / (span[1] - span[0]))
            continue
        assert slopes(tone).max() <= max_gain * (1 + 1e-9), (span, slopes(tone).max())
        assert lut_steps_per_k(tone) <= max_gain + 1.0
        if slopes(free).max() > max_gain:
            assert slopes(tone).max() == pytest.approx(max_gain)
    # shares within the cap come back as they were; a span too narrow for the cap: linear
    pos = plateau_positions(np.arange(1, 101), 1.0)
    np.testing.assert_allclose(cap_gain(pos, BIN_K, 1000.0), pos, atol=1e-12)
    np.testing.assert_allclose(cap_gain(pos, BIN_K, 20.0), np.linspace(0, 1, 101), atol=1e-12)


def test_the_smoothed_table_keeps_to_the_maximum_gain() -> None:
    """Over time, as the span grows and shrinks (a hot object comes and goes) and the scene
    changes: every table shown keeps to the cap."""
    mapper = ToneMapper()
    for k, stamp in enumerate(stamps(60)):
        images, _ = both_eyes(40 + k)
        high = 340.0 + 25.0 * np.sin(k / 6.0)  # at least 30 K: room for 10 steps per K
        tone = mapper.update(images, "plateau", (285.0, high), DEFAULT_PLATEAU, 1.0, stamp, 10.0)
        assert slopes(tone).max() <= 10.0 * (1 + 1e-9), k


def flat_wall(seed: int, sigma_k: float = 0.05) -> list[np.ndarray]:
    """Both eyes of a flat wall at 293.5 K with noise of ``sigma_k`` (seeded), NaN on the
    left tenth."""
    rng = np.random.default_rng(seed)
    eyes = []
    for _ in range(2):
        t = (WALL_K + rng.normal(0.0, sigma_k, (H, W))).astype(np.float32)
        t[:, : W // 10] = np.nan
        eyes.append(t)
    return eyes


def test_a_flat_noisy_wall_is_not_stretched_beyond_the_maximum_gain() -> None:
    """A flat wall with 0.05 K of noise: its automatic span (1 K at the least) is widened to
    255 / max_gain (:func:`gain_span`, as the stereo fusion does), and the palette index's
    noise is at most ``max_gain`` times the temperature's (plus the rounding to whole
    entries) where the uncapped equalization stretched the wall over most of the palette;
    with a wide manual span as well. (``dde`` adds its detail layer on top, at its own
    gain: ``fusion.agc.DDE_GAIN_PER_K``.)"""
    images = flat_wall(21)
    ok = [np.isfinite(t) for t in images]
    sigma = float(np.std(np.concatenate([t[o] for t, o in zip(images, ok, strict=True)])))
    assert sigma == pytest.approx(0.05, rel=0.05)

    def spread(tone: ToneMap) -> tuple[float, float]:
        """(std, 5-95 % range) of the index over both eyes' wall."""
        idx = np.concatenate([i[o] for i, o in zip(indices(images, tone), ok, strict=True)])
        p5, p95 = np.percentile(idx.astype(float), [5, 95])
        return float(idx.std()), float(p95 - p5)

    t5, t95 = np.percentile(
        np.concatenate([t[o] for t, o in zip(images, ok, strict=True)]), [5, 95]
    )
    auto = auto_span(images)
    assert auto[1] - auto[0] == pytest.approx(1.0)
    for g in (DEFAULT_MAX_GAIN, 5.0, 25.0):
        span = gain_span(auto, g)
        assert span[1] - span[0] == pytest.approx(255.0 / g)
        assert 0.5 * (span[0] + span[1]) == pytest.approx(0.5 * (auto[0] + auto[1]))
        for s in (span, (250.0, 350.0)):
            std, width = spread(tone_map(images, "plateau", s, DEFAULT_PLATEAU, g))
            # the index is round(f(T)) with f's slope <= g: its spread is g's plus rounding
            assert std <= np.hypot(g * sigma, 0.5), (g, s, std)
            assert width <= g * (t95 - t5) + 1.0, (g, s, width)
    stretched, _ = spread(tone_map(images, "plateau", auto, DEFAULT_PLATEAU, 1000.0))
    assert stretched > 10 * DEFAULT_MAX_GAIN * sigma  # what the cap prevents
    assert gain_span((280.0, 320.0), DEFAULT_MAX_GAIN) == (280.0, 320.0)  # wide enough


def test_the_stereo_fusion_widens_a_flat_scenes_automatic_span() -> None:
    """Through :class:`fusion.stereo.StereoFusion` (the console's path): a flat noisy wall
    in both imagers gets an automatic span of ``255 / max_gain`` under plateau (1 K under
    linear, as before), a manual span stays as it is, and the table keeps to the cap."""
    from tests.scene_support import ramp_distance
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.fusion.stereo import StereoFusion

    fusion = StereoFusion(default_rig())
    fusion.update_depth(ramp_distance(fusion.rig))
    rng = np.random.default_rng(22)
    thermals, colors = {}, {}
    for e in fusion.eyes:
        tw, th = fusion.rig[fusion.rig.eyes[e].thermal].image_size
        cw, ch = fusion.rig[fusion.rig.eyes[e].color].image_size
        thermals[e] = (WALL_K + rng.normal(0.0, 0.05, (th, tw))).astype(np.float32)
        colors[e] = np.full((ch, cw, 3), 128, np.uint8)
    fusion.compose(colors, thermals, DisplaySettings())
    low, high = fusion.span_k
    assert high - low == pytest.approx(255.0 / DEFAULT_MAX_GAIN)
    assert fusion.tone.span_k == fusion.span_k and fusion.tone.mode == "plateau"
    assert slopes(fusion.tone).max() <= DEFAULT_MAX_GAIN * (1 + 1e-9)
    fusion.compose(colors, thermals, DisplaySettings(agc="linear"))
    assert fusion.span_k[1] - fusion.span_k[0] == pytest.approx(1.0)
    fusion.compose(colors, thermals, DisplaySettings(span_k=(293.0, 294.0)))
    assert fusion.span_k == (293.0, 294.0) == fusion.tone.span_k


@pytest.mark.parametrize("mode", ["plateau", "dde"])
def test_the_maximum_gain_keeps_the_imagers_offset_small_and_the_people_apart(mode: str) -> None:
    """The synthetic room with its hot pipe in the span, the right imager reading 1.5 K
    warmer (the simulated head's pair, no balance): the same wall differs between the eyes
    by at most 1.5 K * max_gain palette steps (the uncapped table made it several times
    that), and the person still stands a quarter of the palette apart from the wall."""
    images, labels = both_eyes(23)
    images[1] = images[1] + np.float32(1.5)
    span = auto_span(images, 0.0, 100.0, step=1)
    assert span[1] > PIPE_K - 1.0

    def offset_and_separation(max_gain: float) -> tuple[float, float]:
        index = indices(images, tone_map(images, mode, span, DEFAULT_PLATEAU, max_gain))
        walls = [float(np.median(i[lab == 0])) for i, lab in zip(index, labels, strict=True)]
        return walls[1] - walls[0], separation(index, labels)

    offset, sep = offset_and_separation(DEFAULT_MAX_GAIN)
    assert 0 < offset <= 1.5 * DEFAULT_MAX_GAIN + 1.0, offset
    assert sep >= 0.25, sep
    free, _ = offset_and_separation(1000.0)
    assert free > 2 * 1.5 * DEFAULT_MAX_GAIN, free


# -- the mapping ---------------------------------------------------------------------------------


def test_linear_mode_reproduces_todays_mapping() -> None:
    images, _ = both_eyes(3)
    span = auto_span(images)
    tone = tone_map(images, "linear", span)
    for t in images:
        np.testing.assert_array_equal(indices([t], tone)[0], temperature_index(t, span))
        ok = np.isfinite(t)
        # index_of (numpy, float64) against OpenCV's float32: a rounding tie may differ
        diff = tone.index_of(t)[ok].astype(int) - temperature_index(t, span)[ok]
        assert np.abs(diff).max() <= 1 and (diff != 0).mean() < 1e-3
    color = np.random.default_rng(3).integers(0, 256, (H, W, 3), dtype=np.uint8)
    comp = Composer(W, H)
    for mode in ("blend", "thermal", "edges", "threshold", "isotherm", "pip"):
        s = DisplaySettings(mode=mode, agc="linear", threshold_k=300.0, isotherm_k=(290, 310))
        before = comp.compose(color, images[0], None, s, span).copy()  # no table: linear
        after = comp.compose(color, images[0], None, s, span, tone=tone)
        np.testing.assert_array_equal(after, before)


@pytest.mark.parametrize("mode", AGC_MODES)
def test_the_same_temperature_gets_the_same_index_in_both_eyes(mode: str) -> None:
    rng = np.random.default_rng(4)
    left = (290.0 + 20.0 * rng.random((H, W))).astype(np.float32)
    right = (300.0 + 15.0 * rng.random((H, W))).astype(np.float32)  # other content
    # The same uniform patch of 301.3 K in both, at different places.
    left[20:60, 20:70] = right[50:90, 80:130] = np.float32(301.3)
    tone = tone_map([left, right], mode, auto_span([left, right]))
    il, ir = indices([left, right], tone)
    inner_l, inner_r = il[32:48, 36:54], ir[62:78, 96:114]  # away from the patch's edge
    assert inner_l.min() == inner_l.max() == inner_r.min() == inner_r.max()
    if mode != "dde":  # without a detail layer: every equal temperature, anywhere
        values = np.round(np.linspace(291.0, 304.0, 200), 2).astype(np.float32)
        left[:2, :100], right[-2:, -100:] = values.reshape(2, 100), values.reshape(2, 100)
        il, ir = indices([left, right], tone)
        np.testing.assert_array_equal(il[:2, :100], ir[-2:, -100:])


def test_a_small_very_hot_object_does_not_flatten_the_rest() -> None:
    """Wall 20.4 C, person 34 C, a pipe at 85 C on 2 % of the pixels, a 6 C fridge: the
    linear span from the coldest to the hottest reading crushes the person and the wall
    into a sliver of the palette; plateau equalization separates them by more than a
    quarter of it (the issue's target), and so does dde."""
    images, labels = both_eyes(5)
    span = auto_span(images, 0.0, 100.0, step=1)  # the pipe in the span, as in the issue
    assert span[1] > PIPE_K - 1.0
    seps = {m: separation(indices(images, tone_map(images, m, span)), labels) for m in AGC_MODES}
    assert seps["linear"] < 0.25
    assert seps["plateau"] >= 0.25 and seps["dde"] >= 0.25, seps
    # and more palette levels are used
    lin = indices(images, tone_map(images, "linear", span))
    eq = indices(images, tone_map(images, "plateau", span))
    ok = [np.isfinite(t) for t in images]
    ent = [
        index_entropy_bits(np.concatenate([i[o] for i, o in zip(x, ok, strict=True)]))
        for x in (lin, eq)
    ]
    assert ent[1] > ent[0] + 1.0, ent
    # the pipe still reads hottest, the fridge coldest
    pipe, person = np.median(eq[0][labels[0] == 3]), np.median(eq[0][labels[0] == 2])
    assert pipe > 0.9 * 255 and pipe > person and np.median(eq[0][labels[0] == 4]) < 0.1 * 255


@pytest.mark.parametrize("mode", AGC_MODES)
def test_tick_temperatures_are_monotonic_and_match_the_mapping(mode: str) -> None:
    images, _ = both_eyes(6)
    span = auto_span(images)
    tone = tone_map(images, mode, span)
    at = tone.temperatures_k(np.arange(256) / 255.0)
    assert np.all(np.diff(at) > 0) and at[0] == span[0] and at[-1] == span[1]
    np.testing.assert_allclose(tone.ticks_k(9), tone.temperatures_k(np.linspace(0, 1, 9)))
    got = tone.index_of(at).astype(int)
    assert np.abs(got - np.arange(256)).max() <= 1  # the tick's temperature gets its entry
    # and the image path agrees with index_of: every tick temperature in a column (dde:
    # uniform images, whose detail layer is nil)
    if mode == "dde":
        for p in (0, 40, 128, 200, 255):
            img = np.full((H, W), at[p], np.float32)
            inner = indices([img], tone)[0][8:-8, 8:-8]
            assert np.abs(inner.astype(int) - p).max() <= 1
    else:
        img = np.repeat(at[np.linspace(0, 255, W).round().astype(int)][None, :], H, 0)
        img = img.astype(np.float32)
        # OpenCV rounds (T - low) / step in float32: a temperature within 0.0001 K of the
        # middle between two table entries may take the other one
        diff = np.abs(indices([img], tone)[0].astype(int) - tone.index_of(img))
        if tone.lut is not None:
            assert diff.max() <= np.abs(np.diff(tone.lut.astype(int))).max()
        assert (diff > 0).mean() < 0.02
    if mode == "linear":
        np.testing.assert_allclose(at, span[0] + (span[1] - span[0]) * np.arange(256) / 255)


def test_dde_adds_the_local_detail_the_span_hides() -> None:
    """A faint 0.3 K texture on a wall next to a hot pipe: linear shows it as about one
    palette step, dde as several."""
    rng = np.random.default_rng(7)
    _, xx = np.mgrid[0:H, 0:W]
    t = (WALL_K + 0.3 * (((xx // 8) % 2) - 0.5) + rng.normal(0, 0.02, (H, W))).astype(np.float32)
    t[:10] = np.float32(PIPE_K)
    span = auto_span([t], 0.0, 100.0)
    rows = slice(40, 100)
    contrast = {}
    for mode in AGC_MODES:
        idx = indices([t], tone_map([t], mode, span))[0][rows, 16:-16].astype(float)
        stripes = ((xx[rows, 16:-16] // 8) % 2).astype(bool)
        contrast[mode] = idx[stripes].mean() - idx[~stripes].mean()
    assert contrast["linear"] < 2.0
    assert contrast["dde"] > 3 * contrast["linear"] and contrast["dde"] > 5.0, contrast


# -- over time -----------------------------------------------------------------------------------


def stamps(n: int, hz: float = 30.0, start_ns: int = 1_000_000_000) -> list[int]:
    return [start_ns + round(k * 1e9 / hz) for k in range(n)]


def test_temporal_smoothing_does_not_pump_on_a_stable_scene() -> None:
    """A stable scene with fresh noise every frame (30 Hz): after the first second, the
    table moves by less than a palette step from frame to frame (each frame's own table
    jitters more), and it is settled on the very same images."""
    mapper = ToneMapper()
    span = (280.0, 360.0)
    probe = np.linspace(285.0, 310.0, 500)
    shown, own = [], []
    for k, stamp in enumerate(stamps(90)):
        images, _ = both_eyes(100 + k)
        tone = mapper.update(images, "plateau", span, DEFAULT_PLATEAU, 1.0, stamp)
        shown.append(tone.index_of(probe).astype(int))
        own.append(tone_map(images, "plateau", span).index_of(probe).astype(int))
    steady = np.abs(np.diff(np.array(shown[30:]), axis=0)).max()
    jitter = np.abs(np.diff(np.array(own[30:]), axis=0)).max()
    assert steady <= 1 and jitter >= steady, (steady, jitter)
    images, _ = both_eyes(7)
    for stamp in stamps(200, start_ns=10_000_000_000):  # the very same frame: settles
        mapper.update(images, "plateau", span, DEFAULT_PLATEAU, 1.0, stamp)
    assert mapper.settled


def test_temporal_smoothing_converges_after_a_change() -> None:
    """A warm rack (315-325 K) is rolled in: the table glides to the new scene's with the
    time constant (about 63 % of the way after one), converges, and is settled then."""
    span = (280.0, 360.0)
    before, _ = both_eyes(8)
    after = [t.copy() for t in before]
    for t in after:
        t[40:110, 90:150] = np.linspace(315.0, 325.0, 60, dtype=np.float32)
    target = tone_map(after, "plateau", span).positions
    mapper = ToneMapper()
    mapper.update(before, "plateau", span, DEFAULT_PLATEAU, 1.0, 0)
    start = mapper.tone.positions.copy()
    gaps = []
    for stamp in stamps(181, start_ns=33_333_333):  # 6 s at 30 Hz, time constant 1 s
        tone = mapper.update(after, "plateau", span, DEFAULT_PLATEAU, 1.0, stamp)
        gaps.append(np.abs(tone.positions - target).max())
        if stamp <= 1_050_000_000:
            assert not mapper.settled
    first = np.abs(start - target).max()
    at_1s = gaps[29]  # 1.0 s after the change
    assert 0.25 * first < at_1s < 0.5 * first, (first, at_1s)  # exp(-1) = 0.37
    assert gaps[-1] < 0.5 / 255 and mapper.settled
    assert np.all(np.diff(gaps) <= 1e-12)  # monotone approach, no overshoot


def test_smoothing_snaps_on_a_jump_back_in_time_or_without_time() -> None:
    span = (280.0, 360.0)
    a, _ = both_eyes(9)
    b = [np.where(np.isfinite(t), t + np.float32(10.0), t) for t in a]
    mapper = ToneMapper()
    mapper.update(a, "plateau", span, stamp_ns=5_000_000_000)
    own_b = tone_map(b, "plateau", span).positions
    for stamp in (4_000_000_000, None):  # a replay looped; a frame without a time stamp
        mapper.update(a, "plateau", span, stamp_ns=5_000_000_000)
        np.testing.assert_allclose(
            mapper.update(b, "plateau", span, stamp_ns=stamp).positions, own_b
        )
    linear = mapper.update(a, "linear", span, stamp_ns=6_000_000_000)
    assert linear.mode == "linear" and mapper.settled


# -- the composer and the stream -----------------------------------------------------------------


@pytest.mark.parametrize("agc", ["plateau", "dde"])
def test_every_palette_mode_uses_the_table(agc: str) -> None:
    images, _ = both_eyes(10)
    tone = tone_map(images, agc, auto_span(images))
    index = indices(images[:1], tone)[0]
    colour = palette("iron")[index]
    ok = np.isfinite(images[0])
    comp = Composer(W, H)
    black = np.zeros((H, W, 3), np.uint8)
    for mode in ("thermal", "threshold", "isotherm", "pip"):
        s = DisplaySettings(
            mode=mode, agc=agc, threshold_k=200.0, isotherm_k=(200.0, 400.0), pip_size=1.0,
            mark_fallback=False,
        )  # fmt: skip
        out = comp.compose(black, images[0], None, s, tone=tone)
        np.testing.assert_array_equal(out[ok], colour[ok])
    out = comp.compose(
        black, images[0], None, DisplaySettings(mode="blend", opacity=1.0), tone=tone
    )
    np.testing.assert_array_equal(out[ok], colour[ok])
    with pytest.raises(ValueError, match="tone: expected a ToneMap"):
        comp.compose(black, images[0], None, DisplaySettings(), tone=(290.0, 310.0))


def test_compose_with_a_table_allocates_no_frame() -> None:
    w, h = 1280, 960
    rng = np.random.default_rng(11)
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    thermal = (290.0 + 20.0 * rng.random((h, w))).astype(np.float32)
    thermal[:, :100] = np.nan
    fallback = np.zeros((h, w), bool)
    fallback[500:900, 200:700] = True
    comp = Composer(w, h)
    out = np.empty((h, w, 3), np.uint8)
    tones = [tone_map([thermal], m, (290.0, 310.0)) for m in ("plateau", "dde")]
    settings = [DisplaySettings(mode=m) for m in ("blend", "thermal", "pip")]
    for tone in tones:  # warm-up: dde's buffers are made on first use
        comp.compose(color, thermal, fallback, settings[0], tone=tone, out=out)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        for tone in tones:
            for s in settings:
                comp.compose(color, thermal, fallback, s, tone=tone, out=out)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < w * h * 3 / 10, f"peak {peak} bytes"


def test_stream_metadata_carries_the_tick_temperatures() -> None:
    images, _ = both_eyes(12)
    span = auto_span(images)
    for agc in AGC_MODES:
        settings = DisplaySettings(agc=agc)
        tone = tone_map(images, agc, span)
        meta = scale_meta(settings, span, tone)
        ticks = meta["palette_ticks_k"]
        assert meta["agc"] == agc and len(ticks) == PALETTE_TICKS
        assert ticks[0] == pytest.approx(span[0], abs=1e-3)
        assert ticks[-1] == pytest.approx(span[1], abs=1e-3)
        assert np.all(np.diff(ticks) > 0)
        expected = tone.temperatures_k(np.linspace(0, 1, PALETTE_TICKS))
        np.testing.assert_allclose(ticks, expected, atol=1e-3)
        assert meta["span_k"] == [span[0], span[1]] and meta["mark_fallback"] is True
    old = scale_meta(DisplaySettings(), span)  # no table: linear, as before
    assert old["agc"] == "linear"
    np.testing.assert_allclose(old["palette_ticks_k"], np.linspace(*span, PALETTE_TICKS), atol=1e-3)
    none = scale_meta(DisplaySettings(mode="color"), span)
    assert none["palette_ticks_k"] is None and none["agc"] is None


# -- the quiet marking ---------------------------------------------------------------------------


def veil_bound(name: str) -> float:
    """The largest mean absolute change per channel the veil can make on a colour of the
    palette ``name``: per channel ``|d (Y - c) + f (128 - c)| <= d |Y - c| + f |128 - c|``
    (d = FALLBACK_DESATURATION, f = FALLBACK_FADE, Y the luma), averaged over the three
    channels, the largest over the palette's entries, plus half a level of rounding."""
    table = palette(name).astype(float)
    y = table @ np.array([0.299, 0.587, 0.114])
    per_entry = (
        FALLBACK_DESATURATION * np.abs(y[:, None] - table) + FALLBACK_FADE * np.abs(128.0 - table)
    ).mean(axis=1)
    return float(per_entry.max()) + 0.5


def test_the_marking_changes_a_pixel_by_a_small_fraction_only() -> None:
    """Fallback pixels are veiled, not hatched: in the default picture (plateau, blend 0.6
    over a camera image of ordinary, low saturation) the mean absolute change over the
    fallback pixels is at most 8 % of full scale (20 of 255 levels) — below the old hatch
    (half the pixels moved by 48 levels in 2 px stripes: 24 on average, all in edges the
    eye is drawn to) — and in the palette-only picture it stays under the bound the veil's
    formula gives for the palette's most saturated entry (:func:`veil_bound`, about 13 %
    for iron). No other pixel changes; nothing high-frequency is added (the change is as
    smooth as the picture: the mean absolute difference between neighbours grows by
    under one level)."""
    images, _ = both_eyes(13)
    t = images[0]
    rng = np.random.default_rng(13)
    grey = rng.integers(60, 200, (H, W, 1)).astype(float)
    color = np.clip(grey + rng.normal(0, 12, (H, W, 3)), 0, 255).astype(np.uint8)
    fallback = np.zeros((H, W), bool)
    fallback[H // 2 :, W // 3 :] = True
    comp = Composer(W, H)
    tone = tone_map(images, "plateau", auto_span(images))
    for mode, name, bound in [
        ("blend", "iron", 20.0),
        ("thermal", "iron", veil_bound("iron")),
        ("thermal", "rainbow", veil_bound("rainbow")),
        ("thermal", "white_hot", veil_bound("white_hot")),
    ]:
        s = DisplaySettings(mode=mode, palette=name)
        off = comp.compose(
            color, t, fallback, dataclasses.replace(s, mark_fallback=False), tone=tone
        ).copy()
        on = comp.compose(color, t, fallback, s, tone=tone).copy()
        change = np.abs(on.astype(int) - off.astype(int))
        marked = fallback & np.isfinite(t)
        assert not change[~marked].any()
        assert 1.0 < change[marked].mean() <= bound, (mode, name, change[marked].mean(), bound)
        inside = marked[:, 1:] & marked[:, :-1]
        rough_on = np.abs(np.diff(on.astype(int), axis=1))[inside].mean()
        rough_off = np.abs(np.diff(off.astype(int), axis=1))[inside].mean()
        assert rough_on <= rough_off + 1.0
    assert veil_bound("iron") < 0.15 * 255


def test_entropy_of_palette_indices() -> None:
    assert index_entropy_bits(np.arange(256, dtype=np.uint8)) == pytest.approx(8.0)
    assert index_entropy_bits(np.full(100, 7, np.uint8)) == 0.0
    idx = np.array([0, 0, 255, 255], np.uint8)
    assert index_entropy_bits(idx, np.array([True, True, True, False])) == pytest.approx(
        0.9182958, abs=1e-6
    )
    with pytest.raises(ValueError, match="uint8"):
        index_entropy_bits(np.arange(4))


# -- the controls: the Fusion panel and the REST API ---------------------------------------------


def test_fusion_panel_sets_the_agc_the_plateau_and_the_max_gain(server) -> None:
    from types import SimpleNamespace

    from trifuse.app.server.panels.display import Panels
    from trifuse.app.server.runtime.context import ConsoleBandwidth
    from trifuse.app.server.runtime.video_presets import StreamSettings
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.calib.board import Board
    from trifuse.calib.radiometry import Radiometry

    pipeline = SimpleNamespace(
        rig=default_rig(),
        settings=DisplaySettings(),
        radiometry={"thermal_left": Radiometry(), "thermal_right": Radiometry()},
        latest_set=None,
        fusion=SimpleNamespace(span_k=None),
        set_manual_offset=lambda name, offset_k: None,
    )
    ctx = SimpleNamespace(
        server=server,
        pipeline=pipeline,
        board=Board(9, 6, 0.04),
        board_watch=SimpleNamespace(
            latest=None, latest_pose=None, pose_listeners=[], enabled=False
        ),
        balancer=None,
        save_rig=None,
        stream_settings=StreamSettings(),
        bandwidth=ConsoleBandwidth(),
        registration=None,
    )
    panels = Panels(ctx)
    assert panels.agc.value == "plateau" and panels.plateau.value == pytest.approx(0.5)
    assert panels.max_gain.value == DEFAULT_MAX_GAIN
    panels.agc.value, panels.plateau.value, panels.max_gain.value = "dde", 2.0, 20.0
    panels.apply()
    assert pipeline.settings.agc == "dde" and pipeline.settings.plateau == pytest.approx(0.02)
    assert pipeline.settings.max_gain == 20.0
    assert panels.error.content == ""


def test_rest_api_sets_the_agc_and_keeps_it_when_left_out() -> None:
    from fastapi.testclient import TestClient

    from tests.support import ListSource
    from trifuse.app.server.app_factory import create_app
    from trifuse.app.server.runtime.pipeline import FusionPipeline
    from trifuse.app.server.runtime.stream import FrameHub
    from trifuse.app.sources.sim.head import default_rig

    pipeline = FusionPipeline(ListSource(), default_rig(), FrameHub())
    client = TestClient(create_app(FrameHub(), None, pipeline))
    s = client.get("/api/fusion").json()
    assert (s["agc"], s["plateau"], s["max_gain"]) == ("plateau", DEFAULT_PLATEAU, 12.0)
    r = client.put("/api/fusion", json={**s, "agc": "linear", "plateau": 0.02, "max_gain": 20})
    assert r.status_code == 200
    assert (r.json()["agc"], r.json()["plateau"], r.json()["max_gain"]) == ("linear", 0.02, 20.0)
    old = {k: v for k, v in s.items() if k not in ("agc", "plateau", "max_gain")}  # before
    assert client.put("/api/fusion", json={**old, "mode": "thermal"}).status_code == 200
    assert (pipeline.settings.mode, pipeline.settings.agc) == ("thermal", "linear")
    assert pipeline.settings.max_gain == 20.0
    for bad in (
        {"agc": "histogram"},
        {"plateau": 0.0},
        {"plateau": 2.0},
        {"max_gain": 0.5},
        {"max_gain": 2000},
        {"max_gain": "high"},
    ):
        r = client.put("/api/fusion", json={**s, **bad})
        assert r.status_code == 422 and next(iter(bad)) in r.text
    assert (pipeline.settings.agc, pipeline.settings.plateau) == ("linear", 0.02)
    assert pipeline.settings.max_gain == 20.0
