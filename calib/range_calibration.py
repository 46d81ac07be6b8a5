"""Fitting the TOF range correction to views of the board (pure: arrays in, model out).

For a view whose board pose in the TOF frame is known, every TOF pixel whose ray meets the
board's checkered area has a reference distance: where that ray meets the board plane
(:func:`board_samples`). Pixels near the board's outline are left out (mixed pixels mix
the board with what lies behind it). The residuals ``measured - reference`` of many views
are fitted by the model of :mod:`calib.range_correction` with iteratively reweighted least
squares (Tukey's biweight on a MAD scale: what is left of mixed pixels and flying pixels is
down-weighted to nothing), with light smoothness priors on the distance spline and the
offset grid, so that sparsely seen distances and pixels stay well defined
(:func:`fit_range_correction`). :func:`region_errors` compares the error before and after
per accuracy region of the TOF image (calib/tof.py), the method's figure 4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics, pixel_rays
from trifuse.calib.range_correction import (
    RangeCorrection,
    amplitude_log,
    bilinear_weights,
    bspline_basis,
    offset_grid_shape,
)
from trifuse.calib.robust import mad_sigma
from trifuse.calib.tof import region_map

REGION_NAMES = {
    1: "region 1 (centre 11x11)",
    2: "region 2",
    3: "region 3",
    4: "region 4 (border, not trusted)",
}
TRUSTED_REGIONS = (1, 2, 3)


@dataclass
class RangeSamples:
    """Board pixels of one or more views.

    Attributes (all (N,)):
        u, v: pixel column and row (int32).
        measured_m: the TOF's radial distance, metres.
        reference_m: where the pixel's ray meets the board plane, metres.
        amplitude: the TOF amplitude at the pixel.
        view: index of the view each sample comes from (int32).
    """

    u: np.ndarray
    v: np.ndarray
    measured_m: np.ndarray
    reference_m: np.ndarray
    amplitude: np.ndarray
    view: np.ndarray

    def __len__(self) -> int:
        return int(self.u.size)

    @classmethod
    def concat(cls, parts: list[RangeSamples]) -> RangeSamples:
        names = ("u", "v", "measured_m", "reference_m", "amplitude", "view")
        if not parts:
            return cls(
                *(np.empty(0, np.int32 if n in ("u", "v", "view") else np.float64) for n in names)
            )
        return cls(*(np.concatenate([getattr(p, n) for p in parts]) for n in names))

    def subset(self, keep: np.ndarray) -> RangeSamples:
        return RangeSamples(
            self.u[keep],
            self.v[keep],
            self.measured_m[keep],
            self.reference_m[keep],
            self.amplitude[keep],
            self.view[keep],
        )

    @property
    def error_m(self) -> np.ndarray:
        """``measured - reference`` (N,), metres."""
        return self.measured_m - self.reference_m


def board_samples(
    intrinsics: Intrinsics,
    image_size: tuple[int, int],
    T_tof_board: np.ndarray,
    board: Board,
    distance_m: np.ndarray,
    amplitude: np.ndarray,
    view: int = 0,
    *,
    margin_px: float = 2.0,
    max_incidence_deg: float = 70.0,
) -> RangeSamples:
    """The TOF pixels that see the board's checkered area, with their reference distances.

    Args:
        intrinsics, image_size: the TOF camera's (W, H).
        T_tof_board: (4, 4) board pose in the TOF frame, metres.
        board: the checkerboard (the checkered area is ``squares * square_size`` wide,
            starting one square before the first inner corner).
        distance_m: (H, W) measured radial distance, metres, NaN or <= 0 invalid.
        amplitude: (H, W) amplitude.
        view: index stored with every sample.
        margin_px: pixels whose ray meets the plane closer than this many TOF pixels (at
            that distance) to the checkered area's outline are left out (mixed pixels).
        max_incidence_deg: rays meeting the board more obliquely are left out.
    """
    w, h = image_size
    d = np.asarray(distance_m, np.float64)
    if d.shape != (h, w) or np.shape(amplitude) != (h, w):
        raise ValueError(
            f"distance and amplitude: expected ({h}, {w}) images, got {d.shape} and "
            f"{np.shape(amplitude)}"
        )
    rays = pixel_rays(intrinsics, w, h)
    R, t = T_tof_board[:3, :3], T_tof_board[:3, 3]
    n = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = rays @ n
        s = (n @ t) / cos  # ray length to the plane
        local = (rays * s[..., None] - t) @ R  # hit point in the board frame
    sq = board.square_size_m
    margin = margin_px * s / intrinsics.fx
    inside = (
        (local[..., 0] >= -sq + margin)
        & (local[..., 0] <= board.cols * sq - margin)
        & (local[..., 1] >= -sq + margin)
        & (local[..., 1] <= board.rows * sq - margin)
    )
    ok = inside & (s > 0) & (np.abs(cos) >= math.cos(math.radians(max_incidence_deg)))
    ok &= np.isfinite(d) & (d > 0)
    v, u = np.nonzero(ok)
    return RangeSamples(
        u.astype(np.int32),
        v.astype(np.int32),
        d[v, u],
        s[v, u],
        np.asarray(amplitude, np.float64)[v, u],
        np.full(u.size, view, np.int32),
    )


@dataclass(frozen=True)
class FitOptions:
    """Settings of :func:`fit_range_correction`.

    Attributes:
        distance_step_m: knot spacing of the distance spline (the wiggling's shortest
            period is ~1 m for a 30 MHz camera: 0.15 m resolves it).
        offset_step_px: spacing of the per-pixel offset nodes.
        amplitude_degree: degree of the amplitude polynomial (0: no amplitude term).
        smooth_distance: weight of the spline's second-difference prior, per metre.
        smooth_offset: weight of the offset grid's first-difference prior, per metre.
        iterations: reweighting passes after the first least-squares solve.
        tukey_c: Tukey biweight cut-off in MAD sigmas.
    """

    distance_step_m: float = 0.15
    offset_step_px: int = 8
    amplitude_degree: int = 2
    smooth_distance: float = 30.0
    smooth_offset: float = 3.0
    iterations: int = 5
    tukey_c: float = 4.685


def _design(
    samples: RangeSamples,
    start: float,
    step: float,
    n_spline: int,
    grid: tuple[int, int],
    opts: FitOptions,
    amp_ref: float,
    log_range: tuple[float, float],
) -> sp.csr_matrix:
    n = len(samples)
    si, sw = bspline_basis(samples.measured_m, start, step, n_spline)
    gi, gw = bilinear_weights(samples.u, samples.v, opts.offset_step_px, grid)
    L = amplitude_log(samples.amplitude, amp_ref, log_range)
    k = opts.amplitude_degree
    n_grid = grid[0] * grid[1]
    cols = [si[:, None] + np.arange(4)]
    vals = [sw]
    cols.append(n_spline + gi)
    vals.append(gw)
    if k:
        cols.append(np.broadcast_to(n_spline + n_grid + np.arange(k), (n, k)))
        vals.append(np.stack([L ** (j + 1) for j in range(k)], axis=1))
    c = np.concatenate(cols, axis=1)
    x = np.concatenate(vals, axis=1)
    rows = np.repeat(np.arange(n), c.shape[1])
    return sp.csr_matrix((x.ravel(), (rows, c.ravel())), shape=(n, n_spline + n_grid + k))


def _priors(n_spline: int, grid: tuple[int, int], k: int, opts: FitOptions, n_data: int):
    """Regularisation rows (sparse) of the smoothness priors and the gauge: the offset
    grid's mean is zero (the constant belongs to the distance term)."""
    rows: list[sp.spmatrix] = []
    n_grid = grid[0] * grid[1]
    total = n_spline + n_grid + k
    # spline: second differences
    D2 = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n_spline - 2, n_spline))
    rows.append(sp.hstack([opts.smooth_distance * D2, sp.csr_matrix((n_spline - 2, n_grid + k))]))
    # grid: first differences along rows and columns
    idx = np.arange(n_grid).reshape(grid)
    pairs = [(idx[:, :-1].ravel(), idx[:, 1:].ravel()), (idx[:-1, :].ravel(), idx[1:, :].ravel())]
    for a, b in pairs:
        m = a.size
        D = sp.csr_matrix(
            (np.r_[np.ones(m), -np.ones(m)], (np.r_[np.arange(m), np.arange(m)], np.r_[a, b])),
            shape=(m, n_grid),
        )
        rows.append(
            sp.hstack([sp.csr_matrix((m, n_spline)), opts.smooth_offset * D, sp.csr_matrix((m, k))])
        )
    gauge = np.zeros((1, total))
    gauge[0, n_spline : n_spline + n_grid] = math.sqrt(n_data) / n_grid
    rows.append(sp.csr_matrix(gauge))
    return sp.vstack(rows).tocsr()


def fit_range_correction(
    samples: RangeSamples, image_size: tuple[int, int], options: FitOptions | None = None
) -> RangeCorrection:
    """Fit the range correction to board samples of several views (robust, see module)."""
    opts = options or FitOptions()
    if len(samples) < 1000:
        raise ValueError(
            f"range calibration: only {len(samples)} board pixels with a valid distance "
            "(need 1000): capture more views with the board in the TOF's image"
        )
    w, h = image_size
    lo = float(np.percentile(samples.measured_m, 0.5))
    hi = float(np.percentile(samples.measured_m, 99.5))
    step = opts.distance_step_m
    start = round(math.floor(lo / step) * step, 6)
    intervals = max(1, math.ceil((hi - start) / step))
    n_spline = intervals + 3
    grid = offset_grid_shape(w, h, opts.offset_step_px)
    amp = samples.amplitude[samples.amplitude > 0]
    amp_ref = float(np.median(amp)) if amp.size else 1000.0
    log_range = (
        (
            float(np.percentile(np.log10(amp / amp_ref), 0.5)),
            float(np.percentile(np.log10(amp / amp_ref), 99.5)),
        )
        if amp.size
        else (-1.0, 1.0)
    )
    if not log_range[0] < log_range[1]:
        log_range = (log_range[0] - 0.5, log_range[1] + 0.5)
    k = opts.amplitude_degree
    A = _design(samples, start, step, n_spline, grid, opts, amp_ref, log_range)
    P = _priors(n_spline, grid, k, opts, len(samples))
    y = samples.error_m
    weights = np.ones(len(samples))
    x = np.zeros(A.shape[1])
    for it in range(opts.iterations + 1):
        Aw = sp.diags(weights) @ A
        N = (A.T @ Aw + P.T @ P).toarray()
        b = Aw.T @ y
        x = np.linalg.solve(N, b)
        r = y - A @ x
        sigma = mad_sigma(r) or 1e-6
        if it < opts.iterations:
            z = r / (opts.tukey_c * sigma)
            weights = np.where(np.abs(z) < 1, (1 - z * z) ** 2, 0.0)
    inlier = weights > 0
    model = RangeCorrection(
        image_size=(w, h),
        distance_start_m=start,
        distance_step_m=step,
        distance_coeffs_m=x[:n_spline],
        offset_step_px=opts.offset_step_px,
        offset_nodes_m=x[n_spline : n_spline + grid[0] * grid[1]].reshape(grid),
        amplitude_ref=amp_ref,
        amplitude_log_range=log_range,
        amplitude_coeffs_m=tuple(x[n_spline + grid[0] * grid[1] :]),
        fit={
            "views": int(np.unique(samples.view).size),
            "pixels": len(samples),
            "inliers": int(inlier.sum()),
            "residual_rms_mm": round(1000 * float(np.sqrt(np.mean(r[inlier] ** 2))), 2),
            "distance_range_m": [round(lo, 3), round(hi, 3)],
        },
    )
    return model


@dataclass(frozen=True)
class RegionError:
    """Distance error statistics over the samples of one accuracy region.

    Attributes:
        region: 1-4, or 0 for regions 1-3 together.
        pixels: samples counted (after the outlier cut).
        before_rms_mm, after_rms_mm: RMS of ``measured - reference`` without and with the
            correction, millimetres.
        before_mean_mm, after_mean_mm: the means (bias), millimetres.
    """

    region: int
    pixels: int
    before_rms_mm: float
    after_rms_mm: float
    before_mean_mm: float
    after_mean_mm: float

    @property
    def ratio(self) -> float:
        """How many times smaller the RMS error got."""
        return self.before_rms_mm / self.after_rms_mm if self.after_rms_mm > 0 else math.inf

    @property
    def name(self) -> str:
        return "regions 1-3" if self.region == 0 else REGION_NAMES[self.region]

    def to_dict(self) -> dict[str, float | int | str]:
        return {
            "region": self.region,
            "name": self.name,
            "pixels": self.pixels,
            "before_rms_mm": round(self.before_rms_mm, 2),
            "after_rms_mm": round(self.after_rms_mm, 2),
            "before_mean_mm": round(self.before_mean_mm, 2),
            "after_mean_mm": round(self.after_mean_mm, 2),
            "ratio": round(self.ratio, 2),
        }


def region_errors(
    samples: RangeSamples,
    model: RangeCorrection,
    image_size: tuple[int, int],
    outlier_m: float = 0.25,
) -> list[RegionError]:
    """Error before / after the correction per accuracy region (1-4) and for 1-3 (region 0).

    Samples whose error is beyond ``outlier_m`` either way, before or after (mixed and
    flying pixels the margin missed), are left out of both, so the two compare the same
    pixels.
    """
    before = samples.error_m
    after = before - model.error_at(samples.u, samples.v, samples.measured_m, samples.amplitude)
    keep = (np.abs(before) <= outlier_m) & (np.abs(after) <= outlier_m)
    regions = region_map(*image_size)[samples.v, samples.u]
    out = []
    for region in (1, 2, 3, 4, 0):
        sel = keep & (np.isin(regions, TRUSTED_REGIONS) if region == 0 else regions == region)
        if not sel.any():
            out.append(RegionError(region, 0, math.nan, math.nan, math.nan, math.nan))
            continue
        b, a = before[sel], after[sel]
        out.append(
            RegionError(
                region,
                int(sel.sum()),
                1000 * float(np.sqrt(np.mean(b * b))),
                1000 * float(np.sqrt(np.mean(a * a))),
                1000 * float(np.mean(b)),
                1000 * float(np.mean(a)),
            )
        )
    return out
