"""The balance between the two thermal imagers, from the points both see through the TOF.

Two radiometric imagers disagree by up to their absolute accuracy (about 2 K) even after
calibration; on a stereo display that shows as one eye warmer than the other. Every TOF
point that both imagers see, unoccluded and away from thermal edges, gives a pair
``(t_left, t_right)`` of readings of the same surface (the method's parallax-free
registration, docs/CONVENTIONS.md, "The geometry of the fusion"):

1. :func:`shared_temperatures` collects those pairs from one frame set;
2. :func:`estimate_balance` fits ``t_left = gain * t_right + c`` robustly (Tukey biweight
   IRLS with a MAD scale; the gain only when the scene's temperatures span enough);
3. :func:`balance_terms` turns the fit into each imager's ``(balance_gain,
   balance_offset_k)`` for :class:`calib.radiometry.Radiometry`;
4. :class:`BalanceFilter` smooths successive estimates over frame time.

Feed calibrated but unbalanced temperatures (``Radiometry.calibration.apply(raw)``): the
terms then *replace* the imagers' balance instead of stacking on it.

Frames: points in the TOF frame (metres); ``rig.T(dst, src)`` is ``T_dst_src``. Pixel
centres at integer coordinates. Temperatures in kelvin, float32 images (H, W).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np
import numpy.typing as npt

from trifuse.calib.numbers import is_int, is_int_or_float
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.calib.robust import MAD_TO_SIGMA, mad_sigma
from trifuse.fusion.geometry import in_image, project_to_sensor
from trifuse.fusion.mapping import DepthView, MappingOptions
from trifuse.fusion.stereo import sample_image

__all__ = [
    "REJECTION_REASONS",
    "BalanceEstimate",
    "BalanceFilter",
    "BalanceMeasurement",
    "SharedTemperatures",
    "balance_terms",
    "estimate_balance",
    "measure_balance",
    "shared_temperatures",
]

_MAPPING = MappingOptions()
# The thermal z-buffers at the imagers' own resolution: a thermal pixel is ~2.4 TOF pixels
# wide, so DepthView splats each TOF point over 3 x 3 cells and leaves no gaps.
_ZBUFFER_SCALE = 1
_TUKEY_C = 4.685  # Tukey biweight tuning constant (95 % efficiency at the normal)
_MIN_SCALE_K = 1e-3  # floor of the residual scale (readings quantised to 0.01 K)

# Why a TOF point is not a shared point, in the order they are checked.
REJECTION_REASONS: tuple[str, ...] = ("invalid_point", "outside", "occluded", "edge", "no_value")
_REASON_TEXT = {
    "invalid_point": "not finite",
    "outside": "outside an image",
    "occluded": "hidden from an imager",
    "edge": "on a thermal edge",
    "no_value": "without a reading",
}


# -- shared points --------------------------------------------------------------------------


@dataclass(eq=False)
class SharedTemperatures:
    """The readings of both imagers at the TOF points both see.

    Attributes:
        t_left, t_right: (M,) float32 kelvin, finite, pairwise of the same 3D point.
        index: (M,) int64 rows of ``points_tof`` the pairs come from.
        n_candidates: N, the number of points offered.
        rejected: reason (:data:`REJECTION_REASONS`) -> points dropped for it; each point
            counts once, under the first reason it fails, so ``M + sum(rejected) == N``.
    """

    t_left: np.ndarray
    t_right: np.ndarray
    index: np.ndarray
    n_candidates: int
    rejected: dict[str, int]

    @property
    def n_points(self) -> int:
        return len(self.t_left)

    def summary(self) -> str:
        """E.g. ``"4210 of 23998 TOF points shared; 19000 outside an image, ..."``."""
        parts = [f"{n} {_REASON_TEXT[k]}" for k, n in self.rejected.items() if n]
        tail = f"; {', '.join(parts)}" if parts else ""
        return f"{self.n_points} of {self.n_candidates} TOF points shared{tail}"


def _edge_strength(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 local gradient magnitude, kelvin per pixel, max over 3 x 3.

    Sobel on a float32 copy with NaN and inf set to 0 (so invalid pixels count as edges);
    a 3 x 3 Sobel of a ramp of slope g gives 8 g, hence the 1/8. The 3 x 3 maximum makes
    every point within a pixel of an edge an edge point.
    """
    img = np.nan_to_num(image.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return cv2.dilate(cv2.magnitude(gx, gy), np.ones((3, 3), np.uint8))


def shared_temperatures(
    rig: Rig,
    tof: str,
    points_tof: npt.ArrayLike,
    left: str,
    right: str,
    image_left: np.ndarray,
    image_right: np.ndarray,
    *,
    max_gradient_k_per_px: float = 1.0,
    occlusion_rel: float = _MAPPING.occlusion_rel,
    occlusion_abs_m: float = _MAPPING.occlusion_abs_m,
) -> SharedTemperatures:
    """Both imagers' readings at the TOF points both see cleanly.

    A point is kept when it is finite, projects inside both images (``rig.T(sensor, tof)``
    then the sensor's intrinsics), is not occluded in either imager (its depth exceeds the
    imager's z-buffer of all the TOF points, :class:`fusion.mapping.DepthView`, by no more
    than ``occlusion_rel * z + occlusion_abs_m``), is not on a thermal edge in either image
    (gradient above ``max_gradient_k_per_px`` within a pixel: a small registration error
    there gives a large difference), and both bilinear samples
    (:func:`fusion.stereo.sample_image`) are finite.

    Args:
        rig: the calibrated rig.
        tof: the TOF sensor's name (the frame of ``points_tof``).
        points_tof: (N, 3) TOF-frame points, metres (e.g. ``StereoFusion.points``).
        left, right: the two thermal imagers' sensor names.
        image_left, image_right: (H, W) kelvin images of ``left`` and ``right`` (float32;
            NaN where there is no reading).
        max_gradient_k_per_px: edge threshold, kelvin per pixel, > 0.
        occlusion_rel, occlusion_abs_m: the occlusion tolerance (defaults as the mapping's).

    Returns:
        The pairs and why the other points were dropped (:class:`SharedTemperatures`).

    Raises:
        ValueError: ``points_tof`` is not (N, 3), an image does not match its sensor's
            size, or a threshold is not a positive finite number.
        KeyError: a sensor is not in the rig.
    """
    P = np.asarray(points_tof, dtype=np.float32)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"points_tof: expected shape (N, 3), got {P.shape}")
    if not (math.isfinite(max_gradient_k_per_px) and max_gradient_k_per_px > 0):
        raise ValueError(
            f"max_gradient_k_per_px: expected a positive number, got {max_gradient_k_per_px!r}"
        )
    if not (
        math.isfinite(occlusion_rel)
        and math.isfinite(occlusion_abs_m)
        and occlusion_rel >= 0
        and occlusion_abs_m >= 0
    ):
        raise ValueError(
            "occlusion_rel, occlusion_abs_m: expected finite numbers >= 0, got "
            f"{occlusion_rel!r}, {occlusion_abs_m!r}"
        )
    sensors = (left, right)
    images = []
    for name, image in zip(sensors, (image_left, image_right), strict=True):
        w, h = rig[name].image_size
        img = np.asarray(image)
        if img.shape != (h, w):
            raise ValueError(
                f"image of {name!r}: expected shape ({h}, {w}) (its sensor's size), got {img.shape}"
            )
        images.append(img if img.dtype == np.float32 else img.astype(np.float32))
    rig[tof]  # KeyError naming it

    n = len(P)
    rejected = dict.fromkeys(REJECTION_REASONS, 0)

    def done(idx: np.ndarray, t_l: np.ndarray, t_r: np.ndarray) -> SharedTemperatures:
        return SharedTemperatures(t_l, t_r, idx.astype(np.int64), n, rejected)

    empty = np.empty(0, np.float32)
    finite = np.isfinite(P).all(axis=1)
    rejected["invalid_point"] = int(n - finite.sum())
    valid = P[finite]
    idx = np.flatnonzero(finite)
    if not len(idx):
        return done(idx, empty, empty)

    # Inside both images.
    uv = [project_to_sensor(valid, rig, s, tof) for s in sensors]
    inside = np.ones(len(idx), bool)
    for s, uv_s in zip(sensors, uv, strict=True):
        inside &= in_image(uv_s, *rig[s].image_size)
    rejected["outside"] = int((~inside).sum())
    idx, uv = idx[inside], [u[inside] for u in uv]
    if not len(idx):
        return done(idx, empty, empty)

    # Not occluded: the z-buffers hold every valid point (occluders may be anywhere).
    visible = np.ones(len(idx), bool)
    for s, uv_s in zip(sensors, uv, strict=True):
        zbuf = DepthView(rig, s, tof, _ZBUFFER_SCALE)
        zb = zbuf.render(valid)
        T = rig.T(s, tof)
        z = P[idx] @ T[2, :3] + T[2, 3]
        hc, wc = zbuf.shape
        cu = np.clip(np.floor((uv_s[:, 0] + 0.5) / zbuf.scale), 0, wc - 1).astype(np.intp)
        cv = np.clip(np.floor((uv_s[:, 1] + 0.5) / zbuf.scale), 0, hc - 1).astype(np.intp)
        visible &= ~(zb[cv, cu] < z * (1.0 - occlusion_rel) - occlusion_abs_m)
    rejected["occluded"] = int((~visible).sum())
    idx, uv = idx[visible], [u[visible] for u in uv]
    if not len(idx):
        return done(idx, empty, empty)

    # Away from thermal edges (nearest pixel of the 3 x 3-max gradient).
    smooth = np.ones(len(idx), bool)
    for img, uv_s in zip(images, uv, strict=True):
        grad = _edge_strength(img)
        h, w = img.shape
        iu = np.clip(np.rint(uv_s[:, 0]), 0, w - 1).astype(np.intp)
        iv = np.clip(np.rint(uv_s[:, 1]), 0, h - 1).astype(np.intp)
        smooth &= grad[iv, iu] <= max_gradient_k_per_px
    rejected["edge"] = int((~smooth).sum())
    idx = idx[smooth]
    if not len(idx):
        return done(idx, empty, empty)

    # Readings.
    pts = np.ascontiguousarray(P[idx])
    t_l, t_r = (
        np.asarray(sample_image(rig, s, tof, pts, img, np.nan), np.float32).reshape(-1)
        for s, img in zip(sensors, images, strict=True)
    )
    ok = np.isfinite(t_l) & np.isfinite(t_r)
    rejected["no_value"] = int((~ok).sum())
    return done(idx[ok], t_l[ok], t_r[ok])


# -- the estimate ---------------------------------------------------------------------------


@dataclass(frozen=True)
class BalanceEstimate:
    """The fitted relation ``t_left = gain * t_right + intercept_k`` between the imagers.

    Attributes:
        ok: True when the estimate can be used.
        reason: why it was refused (human readable), None when ok.
        offset_k: ``t_left - t_right`` on the fitted line where the two readings' mean is
            ``reference_k``, kelvin (with gain 1: the robust median difference).
            NaN when refused.
        gain: slope of ``t_left`` against ``t_right``; 1.0 when not fitted.
        gain_fitted: whether ``gain`` was fitted (else assumed 1).
        n_points: finite pairs offered to the fit.
        n_inliers: pairs with a non-zero final robust weight.
        spread_k: 5-95 percentile range of the inlying pairs' mean temperature, kelvin.
        mad_k: robust scatter of the residuals, kelvin (1.4826 MAD, ~1 sigma; two NETDs
            in quadrature for clean data).
        reference_k: median of the inlying pairs' mean temperature, kelvin.
        note: what the fit decided, e.g. why the gain was not fitted.
    """

    ok: bool
    reason: str | None = None
    offset_k: float = math.nan
    gain: float = 1.0
    gain_fitted: bool = False
    n_points: int = 0
    n_inliers: int = 0
    spread_k: float = math.nan
    mad_k: float = math.nan
    reference_k: float = math.nan
    note: str | None = None

    @property
    def intercept_k(self) -> float:
        """``c`` in ``t_left = gain * t_right + c``: the line through
        ``(reference_k - offset_k / 2, reference_k + offset_k / 2)`` with slope ``gain``."""
        m, d = self.reference_k, self.offset_k
        return m + d / 2.0 - self.gain * (m - d / 2.0)


def _tukey(residual: np.ndarray) -> tuple[np.ndarray, float]:
    """Tukey biweights (N,) of residuals and their MAD scale (kelvin, floored)."""
    scale = max(MAD_TO_SIGMA * float(np.median(np.abs(residual))), _MIN_SCALE_K)
    u = residual / (_TUKEY_C * scale)
    w = np.square(1.0 - np.square(u))
    w[np.abs(u) >= 1.0] = 0.0
    return w, scale


def _robust_offset(d: np.ndarray, iterations: int = 50) -> tuple[float, np.ndarray]:
    """Tukey M-estimate of the location of ``d`` (N,) float64, started at the median;
    returns it and the final weights."""
    mu = float(np.median(d))
    w = np.ones_like(d)
    for _ in range(iterations):
        w, _scale = _tukey(d - mu)
        if w.sum() <= 0:
            break
        new = float(np.sum(w * d) / np.sum(w))
        if abs(new - mu) < 1e-9:
            mu = new
            break
        mu = new
    return mu, w


def _robust_line(
    x: np.ndarray, y: np.ndarray, iterations: int = 50
) -> tuple[float, float, np.ndarray] | None:
    """Tukey IRLS fit of ``y = g x + c`` with an orthogonal (Deming, equal noise) weighted
    regression per step: both imagers have the same NETD, so neither is the "exact" axis.
    Started from the slope between the medians of the lower and upper halves of ``x``.
    Returns (g, c, weights) or None if the data cannot determine a slope."""
    order = np.argsort(x)
    half = len(x) // 2
    lo, hi = order[:half], order[half:]
    dx = float(np.median(x[hi]) - np.median(x[lo]))
    if dx <= 0:
        return None
    g = float(np.median(y[hi]) - np.median(y[lo])) / dx
    c = float(np.median(y - g * x))
    w = np.ones_like(x)
    for _ in range(iterations):
        w, _scale = _tukey(y - (g * x + c))
        sw = w.sum()
        if sw <= 0:
            return None
        mx, my = float(np.sum(w * x) / sw), float(np.sum(w * y) / sw)
        ex, ey = x - mx, y - my
        sxx, syy, sxy = (
            float(np.sum(w * ex * ex)),
            float(np.sum(w * ey * ey)),
            float(np.sum(w * ex * ey)),
        )
        if sxy == 0.0:
            return None
        g_new = (syy - sxx + math.sqrt((syy - sxx) ** 2 + 4.0 * sxy * sxy)) / (2.0 * sxy)
        c_new = my - g_new * mx
        converged = abs(g_new - g) < 1e-10 and abs(c_new - c) < 1e-9
        g, c = g_new, c_new
        if converged:
            break
    w, _scale = _tukey(y - (g * x + c))
    return g, c, w


def _span_of_inliers(mid: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    """(5-95 percentile range, median) kelvin of the mean temperatures ``mid`` (N,) of the
    pairs with a non-zero weight (all pairs if none has): an outlier is not a reading of
    one surface, its mean temperature means nothing."""
    inl = mid[weights > 0] if np.any(weights > 0) else mid
    p5, median, p95 = np.percentile(inl, [5.0, 50.0, 95.0])
    return float(p95 - p5), float(median)


def estimate_balance(
    t_left: npt.ArrayLike,
    t_right: npt.ArrayLike,
    *,
    min_points: int = 200,
    gain_min_spread_k: float = 15.0,
    max_gain_deviation: float = 0.1,
) -> BalanceEstimate:
    """Robust fit of ``t_left = gain * t_right + c`` over pairs of readings of the same
    points (e.g. :func:`shared_temperatures`).

    The offset is always fitted: Tukey biweight location of ``t_left - t_right`` (MAD scale,
    started at the median), so gross outliers (reflections, residual misregistration) get
    zero weight. The gain is fitted too only when the pairs' temperatures span at least
    ``gain_min_spread_k`` (5-95 percentiles; over a narrow span a slope is noise) and the
    fitted gain lies within ``1 +- max_gain_deviation`` (a larger one means a broken
    calibration, not an imbalance); otherwise the estimate is offset-only and ``note``
    says why. Never raises on empty or all-NaN input: refuses (``ok`` False, ``reason``).

    Args:
        t_left, t_right: (N,) kelvin, pairwise of the same points; non-finite pairs are
            ignored.
        min_points: fewest finite pairs to estimate from (positive).
        gain_min_spread_k: spread needed to fit a gain, kelvin (>= 0).
        max_gain_deviation: largest accepted ``|gain - 1|`` (> 0).

    Returns:
        A :class:`BalanceEstimate`.

    Raises:
        ValueError: the arrays' shapes differ or are not 1-D, or an option is invalid.
    """
    tl = np.asarray(t_left, dtype=np.float64)
    tr = np.asarray(t_right, dtype=np.float64)
    if tl.ndim != 1 or tl.shape != tr.shape:
        raise ValueError(
            f"t_left, t_right: expected two (N,) arrays of the same length, got {tl.shape} "
            f"and {tr.shape}"
        )
    if not is_int(min_points) or min_points < 1:
        raise ValueError(f"min_points: expected a positive integer, got {min_points!r}")
    if not (math.isfinite(gain_min_spread_k) and gain_min_spread_k >= 0):
        raise ValueError(f"gain_min_spread_k: expected >= 0 kelvin, got {gain_min_spread_k!r}")
    if not (math.isfinite(max_gain_deviation) and max_gain_deviation > 0):
        raise ValueError(f"max_gain_deviation: expected > 0, got {max_gain_deviation!r}")

    both = np.isfinite(tl) & np.isfinite(tr)
    tl, tr = tl[both], tr[both]
    n = len(tl)
    if n < min_points:
        return BalanceEstimate(
            ok=False,
            reason=(
                f"only {n} points seen by both thermal imagers (need {min_points}): their "
                "views do not overlap, or the TOF has too few valid points"
            ),
            n_points=n,
        )

    d = tl - tr
    mid = 0.5 * (tl + tr)
    offset, w = _robust_offset(d)
    spread, m = _span_of_inliers(mid, w)
    gain, fitted, residual = 1.0, False, d - offset
    note = f"offset only: temperatures span {spread:.1f} K (< {gain_min_spread_k:g} K)"
    # Try a line when all pairs span enough (the offset-only inliers may be a narrow band
    # of a scene whose gain differs from 1); keep it if its own inliers span enough too.
    if _span_of_inliers(mid, np.ones_like(mid))[0] >= gain_min_spread_k:
        line = _robust_line(tr - m, tl - m)  # centred on m for conditioning
        if line is None:
            note = "offset only: the readings do not determine a gain"
        else:
            g, c_centred, w_line = line
            spread_line, m_line = _span_of_inliers(mid, w_line)
            if abs(g - 1.0) > max_gain_deviation:
                note = (
                    f"offset only: fitted gain {g:.4f} is outside "
                    f"1 +- {max_gain_deviation:g} (check the radiometric calibration)"
                )
            elif spread_line < gain_min_spread_k:
                note = (
                    f"offset only: temperatures span {spread_line:.1f} K "
                    f"(< {gain_min_spread_k:g} K)"
                )
            else:
                # Back to absolute kelvin, then the difference where the mean reading is
                # the inliers' median.
                c = c_centred + m * (1.0 - g)
                m, spread, w = m_line, spread_line, w_line
                r_star = (2.0 * m - c) / (1.0 + g)
                gain, offset, fitted = g, (g - 1.0) * r_star + c, True
                residual = tl - (g * tr + c)
                note = f"gain and offset: temperatures span {spread:.1f} K"
    return BalanceEstimate(
        ok=True,
        offset_k=float(offset),
        gain=float(gain),
        gain_fitted=fitted,
        n_points=n,
        n_inliers=int(np.count_nonzero(w > 0)),
        spread_k=spread,
        mad_k=mad_sigma(residual),
        reference_k=m,
        note=note,
    )


def balance_terms(
    estimate: BalanceEstimate, left: str, right: str, reference: str | None = None
) -> dict[str, tuple[float, float]]:
    """Each imager's ``(balance_gain, balance_offset_k)`` so that both agree afterwards.

    With ``t_left = g * t_right + c`` on the shared points, maps ``f_L(t) = gL t + oL`` and
    ``f_R(t) = gR t + oR`` with ``f_L(t_left) == f_R(t_right)``:

    * ``reference=None``: neither imager is privileged; the gain is split geometrically
      (``gL = 1/sqrt(g)``, ``gR = sqrt(g)``) and both map the reference point of the
      estimate to its mean ``reference_k`` (with a pure offset d: ``oL = -d/2``,
      ``oR = +d/2``);
    * ``reference=left`` or ``right``: that imager keeps ``(1.0, 0.0)``, the other is
      mapped onto it.

    The terms act on calibrated temperatures (:meth:`calib.radiometry.Radiometry.
    with_balance` replaces the imager's balance with them).

    Raises:
        ValueError: the estimate was refused, or ``reference`` is neither imager.
    """
    if not estimate.ok:
        raise ValueError(f"cannot balance the thermal imagers: {estimate.reason}")
    if reference is not None and reference not in (left, right):
        raise ValueError(f"reference: expected None, {left!r} or {right!r}, got {reference!r}")
    g, c = estimate.gain, estimate.intercept_k
    if reference == right:
        return {left: (1.0 / g, -c / g), right: (1.0, 0.0)}
    if reference == left:
        return {left: (1.0, 0.0), right: (g, c)}
    m, d = estimate.reference_k, estimate.offset_k
    g_left, g_right = 1.0 / math.sqrt(g), math.sqrt(g)
    return {
        left: (g_left, m - g_left * (m + d / 2.0)),
        right: (g_right, m - g_right * (m - d / 2.0)),
    }


# -- over time ------------------------------------------------------------------------------


class BalanceFilter:
    """Exponential smoothing of successive :class:`BalanceEstimate` over frame time.

        ``offset_k``, ``gain`` and ``reference_k`` move ``alpha = 1 - exp(-dt / tau)`` of the
        way to each new estimate, ``dt`` from the frames' ``stamp_ns``. The first usable
        estimate initialises the state. A time stamp not later than the previous one (a replay
        that looped or was sought back) restarts the time base: the state is kept as it is and
        the next estimate is blended over the time since this one. A refused estimate leaves
        the state unchanged; its reason is kept in :attr:`last_reason` (None again after a
    usable one, so it always describes the newest update). The state's counts,
        spread, scatter, flag and note are the newest blended estimate's.
    """

    def __init__(self, time_constant_s: float = 5.0) -> None:
        if not (
            is_int_or_float(time_constant_s)
            and math.isfinite(time_constant_s)
            and time_constant_s >= 0
        ):
            raise ValueError(
                f"time_constant_s: expected a finite number >= 0 seconds, got {time_constant_s!r}"
            )
        self.time_constant_s = float(time_constant_s)
        self.last_reason: str | None = None
        self._state: BalanceEstimate | None = None
        self._stamp_ns: int | None = None

    @property
    def state(self) -> BalanceEstimate | None:
        """The filtered estimate (``ok`` True), None before the first usable one."""
        return self._state

    def reset(self) -> None:
        """Forget the state, the time base and the last refusal."""
        self._state = None
        self._stamp_ns = None
        self.last_reason = None

    def update(self, estimate: BalanceEstimate, stamp_ns: int) -> BalanceEstimate | None:
        """Blend in the estimate of the frame at ``stamp_ns`` (int nanoseconds); returns the
        filtered state (None while no usable estimate has arrived)."""
        if not estimate.ok:
            self.last_reason = estimate.reason
            return self._state
        self.last_reason = None
        prev, prev_stamp = self._state, self._stamp_ns
        self._stamp_ns = int(stamp_ns)
        if prev is None:
            self._state = estimate
            return self._state
        if prev_stamp is None or stamp_ns <= prev_stamp:
            return self._state  # a new time base; nothing to blend over
        dt_s = (stamp_ns - prev_stamp) * 1e-9
        tau = self.time_constant_s
        alpha = 1.0 if tau == 0.0 else -math.expm1(-dt_s / tau)

        def blend(a: float, b: float) -> float:
            return a + alpha * (b - a)

        self._state = replace(
            estimate,
            offset_k=blend(prev.offset_k, estimate.offset_k),
            gain=blend(prev.gain, estimate.gain),
            reference_k=blend(prev.reference_k, estimate.reference_k),
        )
        return self._state


# -- one frame set ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BalanceMeasurement:
    """What one frame set says about the balance.

    Attributes:
        estimate: the fit on calibrated, unbalanced temperatures (refused with the reason
            when too few points are shared).
        difference_k: median ``left - right`` over the shared points as displayed (full
            radiometry: calibration, balance and trims), NaN without shared points.
        shared: the shared points found.
    """

    estimate: BalanceEstimate
    difference_k: float
    shared: SharedTemperatures


def measure_balance(
    rig: Rig,
    tof: str,
    points_tof: npt.ArrayLike,
    left: str,
    right: str,
    raw_left: np.ndarray,
    raw_right: np.ndarray,
    radiometry: Mapping[str, Radiometry],
    **estimate_options: float,
) -> BalanceMeasurement:
    """The balance of one frame set: the imagers' raw images (H, W), their radiometry, and
    the TOF points (N, 3) of the same instant (TOF frame, metres)."""
    cal = {s: radiometry.get(s, Radiometry()) for s in (left, right)}
    t_l = cal[left].calibration.apply(raw_left)
    t_r = cal[right].calibration.apply(raw_right)
    shared = shared_temperatures(rig, tof, points_tof, left, right, t_l, t_r)
    estimate = estimate_balance(shared.t_left, shared.t_right, **estimate_options)
    if shared.n_points:
        # the rest of the chain (balance, trim) on the calibrated samples
        rest = {s: replace(r, gain=1.0, offset_k=0.0) for s, r in cal.items()}
        shown_l = rest[left].apply(shared.t_left)
        shown_r = rest[right].apply(shared.t_right)
        difference = float(np.median(shown_l - shown_r))
    else:
        difference = math.nan
    return BalanceMeasurement(estimate, difference, shared)
