"""The balance between the two thermal imagers (fusion.balance) and the shared colour span
over time (fusion.span): robust fits on synthetic pairs with known truth, the terms that
make both imagers agree, the temporal filters, and the whole chain on the simulated head
(which injects +0.75 K into the left imager and -0.75 K into the right one)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.inspection import inspection_scene
from trifuse.app.sources.sim.render import HeadModel, Renderer
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.balance import (
    REJECTION_REASONS,
    BalanceEstimate,
    BalanceFilter,
    SharedTemperatures,
    balance_terms,
    estimate_balance,
    shared_temperatures,
)
from trifuse.fusion.span import SpanSmoother, level_from_span, span_from_level
from trifuse.fusion.stereo import StereoFusion

NETD_K = 0.08  # the simulated imagers' noise (app.sources.sim.render), 1 sigma per reading
SIGMA_DIFF_K = NETD_K * math.sqrt(2.0)  # 1 sigma of a left - right difference: 0.113 K
L, R = "thermal_left", "thermal_right"
SENSORS = [L, R, "tof"]
SIM_OFFSETS = {L: 0.75, R: -0.75}


def pairs(
    seed: int,
    n: int = 2000,
    *,
    gain: float = 1.0,
    intercept_k: float = 1.5,
    low_k: float = 285.0,
    high_k: float = 305.0,
    outliers: float = 0.10,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synthetic readings of n points: ``left = gain * right + intercept`` exactly for the
    true temperatures (uniform in [low, high]), NETD noise on each reading, and a fraction
    of gross outliers (2-20 K added to the left reading, one-sided like a reflection, so a
    plain mean is biased). Returns float32 (t_left, t_right) and the outlier mask."""
    rng = np.random.default_rng(seed)
    right_true = rng.uniform(low_k, high_k, n)
    left_true = gain * right_true + intercept_k
    t_left = left_true + NETD_K * rng.standard_normal(n)
    t_right = right_true + NETD_K * rng.standard_normal(n)
    bad = rng.random(n) < outliers
    t_left[bad] += rng.uniform(2.0, 20.0, bad.sum())
    return t_left.astype(np.float32), t_right.astype(np.float32), bad


def offset_on_line(gain: float, intercept_k: float, reference_k: float) -> float:
    """``left - right`` on the line ``left = gain * right + c`` where (left + right) / 2 is
    ``reference_k`` (the estimate's definition of ``offset_k``)."""
    r = (2.0 * reference_k - intercept_k) / (1.0 + gain)
    return (gain - 1.0) * r + intercept_k


def estimate(
    offset_k: float, gain: float = 1.0, reference_k: float = 300.0, n: int = 1000
) -> BalanceEstimate:
    """A hand-made usable estimate."""
    return BalanceEstimate(
        ok=True,
        offset_k=offset_k,
        gain=gain,
        gain_fitted=gain != 1.0,
        n_points=n,
        n_inliers=n,
        spread_k=20.0,
        mad_k=SIGMA_DIFF_K,
        reference_k=reference_k,
    )


REFUSED = BalanceEstimate(ok=False, reason="only 3 points seen by both thermal imagers")


# -- estimate_balance on synthetic pairs -----------------------------------------------------


def test_offset_with_noise_and_outliers() -> None:
    t_left, t_right, bad = pairs(0, low_k=290.0, high_k=305.0)
    # The outliers matter: a plain mean is off by about 0.1 * 11 K.
    assert np.mean(t_left - t_right) - 1.5 > 0.5
    e = estimate_balance(t_left, t_right)
    assert e.ok and e.reason is None
    # 1 sigma of the Tukey location over ~1800 inliers (95 % efficient):
    # 0.113 / sqrt(0.95 * 1800) = 0.0028 K; 5 sigma = 0.014 K.
    assert e.offset_k == pytest.approx(1.5, abs=0.015)
    assert not e.gain_fitted and e.gain == 1.0
    assert "offset only" in (e.note or "") and "span" in (e.note or "")
    assert e.n_points == 2000
    # Every outlier is >= 2 K = 17 sigma off: all get zero weight, (almost) all inliers
    # keep one (Tukey's cut is at 4.685 sigma: 3e-6 of the inliers fall beyond it).
    assert e.n_inliers == pytest.approx((~bad).sum(), abs=3)
    # The robust scatter is the difference's noise, 1 sigma. The 10 % outliers move the
    # median |residual| to the 0.5 / 0.9 = 56th percentile of the inliers' (|N| quantile
    # 0.765 instead of 0.674: +13 %); a MAD over 1800 points is good to ~4 %.
    assert e.mad_k == pytest.approx(SIGMA_DIFF_K * 1.13, rel=0.1)
    # 5-95 % of uniform 290-305 K: 13.5 K (of the inliers: the outliers' mean
    # temperature is no reading of anything).
    assert e.spread_k == pytest.approx(13.5, abs=0.5)


@pytest.mark.parametrize("gain", [1.03, 0.92, 1.08])
def test_gain_is_fitted_over_a_wide_span(gain: float) -> None:
    c = 1.5 - (gain - 1.0) * 300.0  # 1.5 K apart at 300 K
    t_left, t_right, _bad = pairs(1, gain=gain, intercept_k=c, low_k=280.0, high_k=340.0)
    e = estimate_balance(t_left, t_right)
    assert e.ok and e.gain_fitted, e.note
    # Orthogonal fit, residual 0.08 * sqrt(1 + g^2) = 0.115 K over ~1800 inliers spread
    # with sigma 60 / sqrt(12) = 17.3 K: 1 sigma of the gain 0.115 / (17.3 * 42) = 1.6e-4;
    # 5 sigma = 8e-4.
    assert e.gain == pytest.approx(gain, abs=1e-3)
    # The offset at the estimate's reference temperature: a location over ~1800 points,
    # 0.115 / 42 = 0.003 K, 5 sigma 0.015 K.
    assert e.offset_k == pytest.approx(offset_on_line(gain, c, e.reference_k), abs=0.015)
    assert e.intercept_k == pytest.approx(c, abs=0.015 + 1e-3 * 310.0)
    assert e.spread_k >= 15.0


def test_gain_is_not_fitted_over_a_narrow_span() -> None:
    gain, c = 1.03, -7.5
    t_left, t_right, bad = pairs(2, gain=gain, intercept_k=c, low_k=295.0, high_k=300.0)
    e = estimate_balance(t_left, t_right)
    assert e.ok and not e.gain_fitted and e.gain == 1.0
    assert "span 4." in (e.note or "") and "< 15 K" in (e.note or "")
    # Offset only: the typical difference of these points ((g - 1) T + c varies by only
    # 0.15 K over the 5 K), within the location's noise (5 sigma, 0.015 K) plus the
    # asymmetry of that variation (0.15 K / 2 at most, uniform: far less in practice).
    d_true = (gain - 1.0) * t_right[~bad].astype(np.float64) + c
    assert e.offset_k == pytest.approx(float(np.median(d_true)), abs=0.03)


def test_implausible_gain_falls_back_to_offset_only() -> None:
    t_left, t_right, _ = pairs(3, gain=1.3, intercept_k=-88.0, low_k=280.0, high_k=340.0)
    e = estimate_balance(t_left, t_right)
    assert e.ok and not e.gain_fitted and e.gain == 1.0
    assert "outside 1 +- 0.1" in (e.note or "") and "1.30" in (e.note or "")
    assert estimate_balance(t_left, t_right, max_gain_deviation=0.5).gain_fitted


def test_refuses_too_few_points_with_the_numbers() -> None:
    t_left, t_right, _ = pairs(4, n=37)
    e = estimate_balance(t_left, t_right)
    assert not e.ok and e.n_points == 37 and math.isnan(e.offset_k)
    assert e.reason == (
        "only 37 points seen by both thermal imagers (need 200): their views do not "
        "overlap, or the TOF has too few valid points"
    )
    assert estimate_balance(t_left, t_right, min_points=30).ok


def test_empty_and_nan_input_is_refused_not_raised() -> None:
    empty = np.empty(0, np.float32)
    e = estimate_balance(empty, empty)
    assert not e.ok and e.n_points == 0 and "only 0 points" in (e.reason or "")
    nan = np.full(500, np.nan, np.float32)
    assert not estimate_balance(nan, nan).ok
    # Non-finite pairs are dropped, the rest used.
    t_left, t_right, _ = pairs(5, outliers=0.0)
    t_left[:100] = np.nan
    t_right[100:150] = np.inf
    e = estimate_balance(t_left, t_right)
    assert e.ok and e.n_points == 1850


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"t_left": np.zeros(3), "t_right": np.zeros(4)}, "same length, got (3,) and (4,)"),
        ({"min_points": 0}, "min_points: expected a positive integer, got 0"),
        ({"gain_min_spread_k": -1.0}, "gain_min_spread_k: expected >= 0 kelvin"),
        ({"max_gain_deviation": 0.0}, "max_gain_deviation: expected > 0"),
    ],
)
def test_estimate_rejects_bad_arguments(kwargs: dict, message: str) -> None:
    args = {"t_left": np.zeros(3), "t_right": np.zeros(3), **kwargs}
    with pytest.raises(ValueError) as e:
        estimate_balance(args.pop("t_left"), args.pop("t_right"), **args)
    assert message in str(e.value)


# -- balance_terms ---------------------------------------------------------------------------


def apply_terms(
    terms: dict[str, tuple[float, float]], t_left: np.ndarray, t_right: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    return (
        Radiometry().with_balance(*terms[L]).apply(t_left),
        Radiometry().with_balance(*terms[R]).apply(t_right),
    )


@pytest.mark.parametrize("reference", [None, L, R])
def test_terms_make_the_imagers_agree(reference: str | None) -> None:
    gain, c = 1.03, -7.5
    t_left, t_right, bad = pairs(6, gain=gain, intercept_k=c, low_k=280.0, high_k=340.0)
    e = estimate_balance(t_left, t_right)
    assert e.gain_fitted
    terms = balance_terms(e, L, R, reference)
    # On the estimate's own line they agree to float32 rounding (3e-5 K at 340 K).
    r = np.linspace(280.0, 340.0, 61).astype(np.float32)
    on_line = (e.gain * r.astype(np.float64) + e.intercept_k).astype(np.float32)
    a, b = apply_terms(terms, on_line, r)
    np.testing.assert_allclose(a, b, rtol=0, atol=2e-4)
    # On the noisy inliers: the difference is back to noise, median |N(0, 0.115 K)| =
    # 0.078 K, plus the fit's error (< 0.015 K + 1e-3 * 30 K at the span's ends).
    a, b = apply_terms(terms, t_left[~bad], t_right[~bad])
    assert np.median(np.abs(a - b)) < 0.078 + 0.045
    assert abs(np.median(a - b)) < 0.015
    if reference is not None:
        assert terms[reference] == (1.0, 0.0)


def test_even_split_of_a_pure_offset() -> None:
    terms = balance_terms(estimate(1.5), L, R)
    assert terms == {L: (1.0, -0.75), R: (1.0, 0.75)}
    a, b = apply_terms(terms, np.float32([301.5, 281.5]), np.float32([300.0, 280.0]))
    np.testing.assert_array_equal(a, b)


def test_even_split_of_a_gain_moves_both_imagers() -> None:
    terms = balance_terms(estimate(0.9, gain=1.04, reference_k=300.0), L, R)
    (g_l, o_l), (g_r, o_r) = terms[L], terms[R]
    assert g_l * g_r == pytest.approx(1.0) and g_r == pytest.approx(math.sqrt(1.04))
    # Both map the reference point (300 -/+ 0.45 K) onto its mean, 300 K.
    assert g_l * 300.45 + o_l == pytest.approx(300.0)
    assert g_r * 299.55 + o_r == pytest.approx(300.0)


def test_reference_imager_is_unchanged() -> None:
    assert balance_terms(estimate(1.5), L, R, reference=R) == {L: (1.0, -1.5), R: (1.0, 0.0)}
    assert balance_terms(estimate(1.5), L, R, reference=L) == {L: (1.0, 0.0), R: (1.0, 1.5)}


def test_terms_refuse_a_refused_estimate_and_an_unknown_reference() -> None:
    with pytest.raises(ValueError, match="cannot balance the thermal imagers: only 3 points"):
        balance_terms(REFUSED, L, R)
    with pytest.raises(ValueError, match="reference: expected None, 'thermal_left' or"):
        balance_terms(estimate(1.5), L, R, reference="ccd_left")


# -- BalanceFilter ---------------------------------------------------------------------------

SECOND = 1_000_000_000


def test_filter_converges_to_a_constant_input() -> None:
    f = BalanceFilter(time_constant_s=5.0)
    assert f.state is None
    assert f.update(estimate(0.0), 0) == estimate(0.0)  # the first one initialises
    dt_ns = SECOND // 10
    for k in range(1, 301):
        state = f.update(estimate(1.5, gain=1.02), k * dt_ns)
        assert state is not None
        # Steps of alpha = 1 - exp(-dt / tau) compound to exactly 1 - exp(-t / tau).
        remaining = math.exp(-k * 0.1 / 5.0)
        assert state.offset_k == pytest.approx(1.5 * (1.0 - remaining), abs=1e-9)
        assert state.gain == pytest.approx(1.02 - 0.02 * remaining, abs=1e-12)
    # After 30 s = 6 tau: 1.5 * exp(-6) = 0.0037 K left.
    assert state.offset_k == pytest.approx(1.5, abs=0.004)
    assert f.state is state and f.last_reason is None


def test_filter_keeps_its_state_through_a_refusal() -> None:
    f = BalanceFilter()
    assert f.update(REFUSED, 0) is None and f.last_reason == REFUSED.reason
    first = f.update(estimate(1.2), SECOND)
    assert f.last_reason is None
    assert f.update(REFUSED, 2 * SECOND) is first
    assert f.state is first and f.last_reason == REFUSED.reason
    # The refusal does not advance the time base: the next estimate blends over 2 s.
    state = f.update(estimate(2.2), 3 * SECOND)
    assert state is not None
    assert state.offset_k == pytest.approx(1.2 + (1.0 - math.exp(-2.0 / 5.0)))


def test_filter_treats_time_going_backwards_as_a_new_time_base() -> None:
    f = BalanceFilter(time_constant_s=5.0)
    f.update(estimate(1.0), 10 * SECOND)
    assert f.update(estimate(9.0), 0) == estimate(1.0)  # looped replay: no step at all
    assert f.update(estimate(9.0), 0) == estimate(1.0)  # zero step: nothing either
    state = f.update(estimate(3.0), SECOND // 10)  # then 0.1 s from the new base
    assert state is not None and math.isfinite(state.offset_k)
    assert state.offset_k == pytest.approx(1.0 + 2.0 * (1.0 - math.exp(-0.02)))


def test_filter_without_smoothing_and_reset() -> None:
    f = BalanceFilter(time_constant_s=0.0)
    f.update(estimate(1.0), 0)
    assert f.update(estimate(2.0), 1).offset_k == 2.0  # type: ignore[union-attr]
    f.update(REFUSED, 2)
    f.reset()
    assert f.state is None and f.last_reason is None
    assert f.update(estimate(5.0), 0) == estimate(5.0)
    with pytest.raises(ValueError, match="time_constant_s: expected a finite number >= 0"):
        BalanceFilter(-1.0)


# -- SpanSmoother and level/span ---------------------------------------------------------------


def test_span_smoother_snaps_then_smooths() -> None:
    s = SpanSmoother(time_constant_s=1.0)
    assert s.span is None
    assert s.update((290.0, 310.0), 5 * SECOND) == (290.0, 310.0)  # first: snap
    low, high = s.update((300.0, 330.0), 5 * SECOND + SECOND // 2)
    a = 1.0 - math.exp(-0.5)
    assert (low, high) == pytest.approx((290.0 + 10.0 * a, 310.0 + 20.0 * a))
    # Many small steps reach the target; it never overshoots.
    for k in range(2, 200):
        low, high = s.update((300.0, 330.0), 5 * SECOND + k * SECOND // 10)
        assert low <= 300.0 and high <= 330.0
    assert (low, high) == pytest.approx((300.0, 330.0), abs=1e-6)


def test_span_smoother_snaps_when_time_goes_back_or_stands_still() -> None:
    s = SpanSmoother(time_constant_s=2.0)
    s.update((290.0, 310.0), 10 * SECOND)
    assert s.update((250.0, 260.0), 0) == (250.0, 260.0)  # looped replay
    assert s.update((270.0, 280.0), 0) == (270.0, 280.0)  # same stamp
    s.reset()
    assert s.span is None
    assert s.update((1.0, 2.0), 7) == (1.0, 2.0)
    unsmoothed = SpanSmoother(time_constant_s=0.0)
    unsmoothed.update((290.0, 310.0), 0)
    assert unsmoothed.update((280.0, 300.0), 1) == (280.0, 300.0)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: SpanSmoother(-1.0), "time_constant_s: expected >= 0 seconds, got -1.0"),
        (lambda: SpanSmoother(math.nan), "time_constant_s: expected a finite number"),
        (lambda: SpanSmoother().update((310.0, 290.0), 0), "expected low < high"),
        (lambda: SpanSmoother().update((300.0, 300.0), 0), "expected low < high"),
        (lambda: SpanSmoother().update((math.nan, 300.0), 0), "span low: expected a finite"),
        (lambda: SpanSmoother().update((1.0, 2.0, 3.0), 0), "span: expected (low, high)"),
        (lambda: SpanSmoother().update((1.0, 2.0), 0.5), "stamp_ns: expected an integer"),
        (lambda: span_from_level(300.0, 0.0), "span_k: expected a width > 0 kelvin, got 0.0"),
        (lambda: span_from_level(math.inf, 10.0), "level_k: expected a finite number"),
        (lambda: level_from_span(300.0, 290.0), "expected low < high"),
    ],
)
def test_span_arguments_are_checked(call, message: str) -> None:
    with pytest.raises(ValueError) as e:
        call()
    assert message in str(e.value)


def test_level_and_span() -> None:
    assert span_from_level(300.0, 20.0) == (290.0, 310.0)
    assert level_from_span(290.0, 310.0) == (300.0, 20.0)
    assert span_from_level(*level_from_span(273.15, 373.15)) == pytest.approx((273.15, 373.15))


# -- the simulated head ------------------------------------------------------------------------


def render_head(rig: Rig, model: HeadModel) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Both thermal images and the TOF points (N, 3) float32 (the stereo fusion's own) of
    the inspection room, head at the origin, noise seed 0."""
    frames, _truth = Renderer(rig, model).render(
        inspection_scene(), np.eye(4), 0, np.random.default_rng(0), SENSORS
    )
    fusion = StereoFusion(rig)
    fusion.update_depth(frames["tof"].distance_m)
    return {name: frames[name].image for name in (L, R)}, fusion.points


@pytest.fixture(scope="module")
def head() -> tuple[Rig, dict[str, np.ndarray], np.ndarray]:
    rig = default_rig()
    images, points = render_head(rig, HeadModel(thermal_offset_k=dict(SIM_OFFSETS)))
    return rig, images, points


def shared(rig: Rig, images: dict[str, np.ndarray], points: np.ndarray, **kw) -> SharedTemperatures:
    return shared_temperatures(rig, "tof", points, L, R, images[L], images[R], **kw)


def test_shared_points_of_the_simulated_head(head) -> None:
    rig, images, points = head
    s = shared(rig, images, points)
    assert s.n_candidates == len(points) > 20000
    assert list(s.rejected) == list(REJECTION_REASONS)
    assert s.n_points + sum(s.rejected.values()) == s.n_candidates
    # The TOF sees wider than the thermal imagers; the pole 0.6 m ahead hides different
    # parts of the room from each; hot and cold objects have edges.
    assert s.rejected["outside"] > 1000
    assert s.rejected["occluded"] > 500
    assert s.rejected["edge"] > 200
    assert s.n_points > 5000
    assert s.t_left.dtype == np.float32 and np.isfinite(s.t_left).all()
    assert np.isfinite(s.t_right).all() and len(s.index) == s.n_points
    assert "TOF points shared" in s.summary() and "outside an image" in s.summary()

    # What the filters are for: without them, the pairs include gross mismatches
    # (occluder on one side, background on the other; edges): a plain mean is biased.
    loose = shared(rig, images, points, max_gradient_k_per_px=1e9, occlusion_rel=1e3)
    d_loose = loose.t_left - loose.t_right
    d = s.t_left - s.t_right
    assert np.mean(d_loose) - 1.5 > 0.2
    assert np.mean(np.abs(d - 1.5) > 1.0) < 0.01 < np.mean(np.abs(d_loose - 1.5) > 1.0)


def test_balance_of_the_simulated_head(head) -> None:
    rig, images, points = head
    s = shared(rig, images, points)
    e = estimate_balance(s.t_left, s.t_right)
    assert e.ok, e.reason
    # The simulator injects +0.75 / -0.75 K: 1.50 K. Per pair the difference has 1 sigma
    # ~0.077 K (0.113 K of two NETDs, lowered by the bilinear sampling averaging
    # neighbouring pixels' noise): the robust location over ~11,900 inliers has 1 sigma
    # 0.077 / sqrt(11900) = 0.0007 K. Eight seeds and poses measured within 0.001 K; the
    # 0.01 K tolerance (14 sigma) leaves room for the simulator's systematic
    # misregistration (TOF range error, optics blur at edges), yet is 150x smaller than
    # the offset under test.
    assert e.offset_k == pytest.approx(1.50, abs=0.01)
    assert e.mad_k == pytest.approx(SIGMA_DIFF_K, rel=0.4)
    terms = balance_terms(e, L, R)
    assert terms[L][1] == pytest.approx(-0.75, abs=0.005)
    assert terms[R][1] == pytest.approx(+0.75, abs=0.005)
    a, b = apply_terms(terms, s.t_left, s.t_right)
    # Balanced: the median |left - right| is the noise's, median |N(0, 0.077 K)| = 0.052 K.
    assert np.median(np.abs(a - b)) < 0.2
    assert abs(float(np.median(a - b))) < 0.01


def test_gain_of_the_simulated_head() -> None:
    """A left imager with gain 1.02: left = 1.02 T + 0.75, right = T - 0.75, so
    left = 1.02 right + 1.515 K. The room spans about 32 K (5-95 %) once edges are
    dropped (the cold window and the second person, issue 19; 14 K before them): enough
    for the default spread threshold, not for one of 40 K."""
    rig = default_rig()
    images, points = render_head(
        rig, HeadModel(thermal_offset_k=dict(SIM_OFFSETS), thermal_gain={L: 1.02})
    )
    s = shared(rig, images, points)
    assert not estimate_balance(s.t_left, s.t_right, gain_min_spread_k=40.0).gain_fitted
    e = estimate_balance(s.t_left, s.t_right)
    assert e.gain_fitted, e.note
    # 1 sigma of the gain ~0.077 K / (sigma of the temperatures ~5 K * sqrt(11900)) =
    # 1.4e-4; 0.002 is 14 sigma (the same margin for systematic effects as above).
    assert e.gain == pytest.approx(1.02, abs=0.002)
    assert e.intercept_k == pytest.approx(1.02 * 0.75 + 0.75, abs=0.002 * 300.0)
    a, b = apply_terms(balance_terms(e, L, R), s.t_left, s.t_right)
    assert np.median(np.abs(a - b)) < 0.2


def rotated_right_imager(rig: Rig) -> Rig:
    """The rig with thermal_right turned 180 degrees about its y axis: it looks backwards
    and shares no view with anything."""
    s = rig[R]
    turned = s.T_rig_sensor @ make_T(rotation_from_euler_deg(0.0, 180.0, 0.0), (0, 0, 0))
    sensors = {**rig.sensors, R: dataclasses.replace(s, T_rig_sensor=turned)}
    return Rig(sensors=sensors, reference=rig.reference, eyes=dict(rig.eyes))


def test_no_overlap_or_no_depth_is_refused_and_the_filter_holds(head) -> None:
    rig, images, points = head
    s = shared(rig, images, points)
    good = estimate_balance(s.t_left, s.t_right)
    f = BalanceFilter(time_constant_s=5.0)
    assert f.update(good, 0) is good

    away = shared(rotated_right_imager(rig), images, points)
    assert away.n_points == 0 and away.rejected["outside"] == len(points)
    e = estimate_balance(away.t_left, away.t_right)
    assert not e.ok
    assert e.reason is not None and e.reason.startswith("only 0 points seen by both")
    assert f.update(e, SECOND) is good and f.last_reason == e.reason

    fusion = StereoFusion(rig)
    fusion.update_depth(np.full((144, 176), np.nan, np.float32))  # no valid TOF depth
    assert fusion.points.shape == (0, 3)
    none = shared(rig, images, fusion.points)
    assert none.n_candidates == 0 and none.n_points == 0
    e = estimate_balance(none.t_left, none.t_right)
    assert not e.ok and "only 0 points" in (e.reason or "")
    assert f.update(e, 2 * SECOND) is good and f.state is good


def test_shared_temperatures_checks_its_input(head) -> None:
    rig, images, points = head
    with pytest.raises(ValueError, match=r"points_tof: expected shape \(N, 3\), got \(5, 2\)"):
        shared(rig, images, np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"image of 'thermal_right': expected shape \(288, 382"):
        shared_temperatures(rig, "tof", points, L, R, images[L], images[R].T)
    with pytest.raises(ValueError, match="max_gradient_k_per_px: expected a positive number"):
        shared(rig, images, points, max_gradient_k_per_px=0.0)
    # Non-finite points are counted, not used.
    pts = points[:1000].copy()
    pts[:10] = np.nan
    s = shared(rig, images, pts)
    assert s.rejected["invalid_point"] == 10 and not np.isin(np.arange(10), s.index).any()
