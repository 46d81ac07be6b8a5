"""How far a thermal value can land from the colour pixel that sees its point: the
registration uncertainty of the fusion, per pixel, at the depth the TOF measured.

The fusion (:mod:`fusion.mapping`) gives each colour pixel ``q`` a depth ``z(q)`` from the
TOF and takes the thermal value at ``F(q) = project_t(T_t_c z(q) ray_c(q))``. Three things
move ``F(q)`` away from the thermal pixel that truly sees ``q``'s point:

- **calibration**: the intrinsics and poses of the colour camera, the thermal imager and
  the TOF (their joint covariance, :mod:`calib.parameter_covariance`). A parameter error
  moves the TOF's point (its ray, its pose), the colour pixel's ray and the thermal
  projection; ``z(q)`` follows the surface the TOF measured, locally the plane through
  the point with the normal of the measured depth;
- **range**: the TOF's radial distance error, 1-sigma per accuracy region
  (:class:`RangeError`, from the rig's range correction);
- **footprint**: a TOF pixel is several colour pixels wide, and the fusion gives each
  coarse cell the nearest depth among the TOF points covering it; on a slanted surface that
  depth is off by up to the depth's change across the covered window (a bias towards the
  camera and a spread; :func:`_footprint_part`). Its share is their root mean square.

Each is propagated to first order (derivatives by central differences of the same chain
the fusion computes) to a 2 x 2 covariance of ``F(q)`` in thermal pixels, and brought to
colour pixels through the local map between the two images on the measured surface,
``A = (dF/dq)^-1``: a thermal value misplaced by ``dF`` lands ``A dF`` colour pixels from
where it belongs. The reported sigma of a pixel is the semi-major axis of its 1-sigma
ellipse, colour pixels. It is computed on the fusion's coarse grid (one value per
``scale`` x ``scale`` colour pixels, every ``stride``-th cell); cells without TOF depth,
not seen by the thermal imager or on a depth edge have none (NaN).

Pure: rig, covariance and depth in, arrays out.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from trifuse.calib.camera import Intrinsics, pixel_grid
from trifuse.calib.parameter_covariance import (
    DISTORTION_PARAMETERS,
    INTRINSIC_PARAMETERS,
    POSE_PARAMETERS,
    ParameterCovariance,
    split_name,
)
from trifuse.calib.rig import Rig, moved_intrinsics
from trifuse.calib.rig_problem import BLAS_THREADS, project_derivatives
from trifuse.calib.tof import region_map
from trifuse.calib.transforms import invert, rotation_from_rvec
from trifuse.fusion.geometry import in_image
from trifuse.fusion.mapping import splat_radius

UNCORRECTED_RANGE_SIGMA_M = 0.041  # the method's TOF distance error before range calibration
PARTS = ("calibration", "range", "footprint")
ALL_INTRINSICS = INTRINSIC_PARAMETERS + DISTORTION_PARAMETERS


@dataclass(frozen=True)
class RangeError:
    """1-sigma of the TOF's radial distance per accuracy region (calib.tof), metres.

    Attributes:
        sigma_m: region (1-4) -> 1-sigma, metres.
        source: where the figures come from, in words.
    """

    sigma_m: Mapping[int, float]
    source: str

    def per_pixel(self, width: int, height: int) -> np.ndarray:
        """(height, width) float64 1-sigma of each TOF pixel, metres."""
        lut = np.array([0.0] + [float(self.sigma_m[r]) for r in (1, 2, 3, 4)])
        return lut[region_map(width, height)]


def range_error(rig: Rig, tof: str) -> RangeError:
    """The TOF's distance error model of ``rig``: the range correction's held-out RMS per
    region when the rig has them, else its overall held-out (or fit) RMS, else the method's
    41 mm of an uncorrected TOF."""
    rc = rig[tof].range_correction
    fit = rc.fit if rc is not None else {}
    regions = fit.get("holdout_region_rms_mm") or {}
    if all(regions.get(str(r)) is not None for r in (1, 2, 3, 4)):
        sig = {r: float(regions[str(r)]) / 1000 for r in (1, 2, 3, 4)}
        return RangeError(sig, "range correction, held-out RMS per region")
    overall = (fit.get("holdout_rms_mm") or {}).get("after") or fit.get("residual_rms_mm")
    if rc is not None and overall is not None:
        return RangeError(dict.fromkeys((1, 2, 3, 4), float(overall) / 1000), "range correction")
    return RangeError(
        dict.fromkeys((1, 2, 3, 4), UNCORRECTED_RANGE_SIGMA_M), "no range correction: 41 mm"
    )


@dataclass(frozen=True, eq=False)
class RegistrationSigma:
    """The registration uncertainty of one eye over the fusion's coarse grid.

    Attributes:
        color, thermal, tof: the sensors.
        cell_px: colour pixels per cell side (the mapping's scale times ``stride``).
        centres: (h, w, 2) float64 colour pixel (u, v) at which each value holds.
        sigma_px: (h, w) float64 semi-major axis of the 1-sigma ellipse, colour pixels; NaN
            where there is no estimate.
        covariance: (h, w, 2, 2) float64 the full covariance, colour pixels squared (NaN
            likewise).
        parts: ``calibration``, ``range``, ``footprint`` -> (h, w, 2, 2) each one's share.
        thermal_to_color: (h, w, 2, 2) float64 ``A``: a thermal value misplaced by ``dF``
            thermal pixels lands ``A dF`` colour pixels from where it belongs (NaN likewise).
        range_source: where the range error came from (:class:`RangeError`).
    """

    color: str
    thermal: str
    tof: str
    cell_px: int
    centres: np.ndarray
    sigma_px: np.ndarray
    covariance: np.ndarray
    parts: dict[str, np.ndarray]
    thermal_to_color: np.ndarray
    range_source: str

    def summary(self) -> dict[str, float | None]:
        """``{"median_px", "p95_px", "cells"}`` over the cells with an estimate."""
        s = self.sigma_px[np.isfinite(self.sigma_px)]
        if s.size == 0:
            return {"median_px": None, "p95_px": None, "cells": 0}
        return {
            "median_px": float(np.median(s)),
            "p95_px": float(np.percentile(s, 95)),
            "cells": int(s.size),
        }


def major_sigma(cov: np.ndarray) -> np.ndarray:
    """(...) semi-major axis of 2 x 2 covariances (..., 2, 2): sqrt of the larger eigenvalue."""
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    half_tr = 0.5 * (a + c)
    return np.sqrt(half_tr + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0)))


# -- the chain ----------------------------------------------------------------------------


@dataclass
class _Geometry:
    """What the chain needs of the rig: the three sensors' intrinsics and two poses."""

    tof: Intrinsics
    color: Intrinsics
    thermal: Intrinsics
    T_c_tof: np.ndarray
    T_t_c: np.ndarray

    @classmethod
    def of(cls, rig: Rig, color: str, thermal: str, tof: str) -> _Geometry:
        return cls(
            rig[tof].intrinsics,
            rig[color].intrinsics,
            rig[thermal].intrinsics,
            rig.T(color, tof),
            rig.T(thermal, color),
        )


def _rays(intr: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """(N, 3) rays with z = 1 through pixels (N, 2)."""
    xy = intr.normalized(pixels)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


class _Chain:
    """``F(q)`` for fixed TOF measurements (u, v, d) and colour pixels q, under any geometry.

    The TOF point ``d unit(ray_tof(u, v))`` goes into the colour frame; the colour pixel's
    ray meets the plane through it with the measured surface's normal; that point is
    projected into the thermal imager.
    """

    def __init__(
        self, g: _Geometry, q: np.ndarray, uv: np.ndarray, d: np.ndarray, n: np.ndarray
    ) -> None:
        self.g, self.q, self.uv, self.d, self.n = g, q, uv, d, n
        r = _rays(g.tof, uv)
        self.tof_dir = r / np.linalg.norm(r, axis=1, keepdims=True)
        self.color_ray = _rays(g.color, q)

    def __call__(
        self,
        T_c_tof: np.ndarray | None = None,
        T_t_c: np.ndarray | None = None,
        thermal: Intrinsics | None = None,
        tof_dir: np.ndarray | None = None,
        color_ray: np.ndarray | None = None,
        d_offset: np.ndarray | float = 0.0,
    ) -> np.ndarray:
        """(N, 2) thermal pixels F(q); any argument given replaces the nominal one (the
        poses, the thermal intrinsics, the TOF's unit rays and the colour rays with z = 1),
        and the TOF's distances are moved by ``d_offset`` metres."""
        g = self.g
        T_c_tof = g.T_c_tof if T_c_tof is None else T_c_tof
        T_t_c = g.T_t_c if T_t_c is None else T_t_c
        tof_dir = self.tof_dir if tof_dir is None else tof_dir
        ray = self.color_ray if color_ray is None else color_ray
        X = ((self.d + d_offset)[:, None] * tof_dir) @ T_c_tof[:3, :3].T + T_c_tof[:3, 3]
        z = np.sum(self.n * X, axis=1) / np.sum(self.n * ray, axis=1)
        P = (z[:, None] * ray) @ T_t_c[:3, :3].T + T_t_c[:3, 3]
        return (thermal or g.thermal).project(P)


def _ray_derivatives(intr: Intrinsics, pixels: np.ndarray) -> np.ndarray:
    """(N, 3, 12) derivative of the rays with z = 1 through fixed pixels (N, 2) with respect
    to ``fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6``: the pixel stays, so the normalised point
    moves by ``-(dp/dxy)^-1 dp/dparam``."""
    xy = intr.normalized(pixels)
    Q = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    K4 = np.broadcast_to([intr.fx, intr.fy, intr.cx, intr.cy], (len(xy), 4))
    D8 = np.zeros((len(xy), 8))
    D8[:, : len(intr.distortion)] = intr.distortion
    dQ, dK, dD = project_derivatives(Q, K4, D8)
    dxy = -np.linalg.solve(dQ[:, :, :2], np.concatenate([dK, dD], axis=2))  # (N, 2, 12)
    return np.concatenate([dxy, np.zeros((len(xy), 1, 12))], axis=1)


def _surface(z: np.ndarray, rays: np.ndarray, edge_rel: float) -> tuple[np.ndarray, np.ndarray]:
    """Normals (h, w, 3) of the surface ``z * rays`` (colour frame) and a mask of cells on a
    depth edge or next to a cell without depth (h, w)."""
    X = z[..., None] * rays
    with np.errstate(invalid="ignore"):
        Xu = np.gradient(X, axis=1)
        Xv = np.gradient(X, axis=0)
        n = np.cross(Xu, Xv)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        bad = ~np.isfinite(z)
        zp = np.pad(z, 1, mode="edge")
        for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            nb = zp[1 + dv : 1 + dv + z.shape[0], 1 + du : 1 + du + z.shape[1]]
            bad |= ~np.isfinite(nb) | (np.abs(nb - z) > edge_rel * np.minimum(nb, z))
    return n, bad


def registration_sigma(
    rig: Rig,
    covariance: ParameterCovariance | None,
    color: str,
    thermal: str,
    tof: str,
    coarse_z: np.ndarray,
    coarse_ok: np.ndarray,
    scale: int,
    range_err: RangeError,
    stride: int = 1,
    edge_rel: float = 0.05,
) -> RegistrationSigma:
    """The registration uncertainty of one eye (module docstring).

    Args:
        rig: the rig the fusion uses.
        covariance: the joint covariance of its parameters (``rig.covariance``); None
            leaves the calibration's share out (its part is zero).
        color, thermal, tof: the eye's colour camera and thermal imager, and the TOF.
        coarse_z: (hc, wc) depth of the fusion's coarse cells along the colour camera's
            axis, metres (:meth:`fusion.mapping.ViewMapping.coarse_cells`).
        coarse_ok: (hc, wc) bool, the cell's depth is the TOF's and the thermal imager sees
            its point.
        scale: colour pixels per cell side.
        range_err: the TOF's distance error (:func:`range_error`).
        stride: evaluate every ``stride``-th cell in each direction.
        edge_rel: neighbouring depths differing by more than this fraction are an edge.
    """
    if stride < 1 or scale < 1:
        raise ValueError(f"stride, scale: expected integers >= 1, got {stride}, {scale}")
    z = np.where(coarse_ok, coarse_z, np.nan).astype(np.float64)
    hc, wc = z.shape
    centres = pixel_grid(wc, hc).astype(np.float64) * scale + (scale - 1) / 2.0
    cs = rig[color]
    rays = np.concatenate([cs.intrinsics.normalized(centres), np.ones((hc, wc, 1))], axis=-1)
    normals, bad = _surface(z, rays, edge_rel)
    with np.errstate(invalid="ignore"):
        gx, gy = np.gradient(z, axis=1), np.gradient(z, axis=0)  # metres per cell
    spacing = cs.intrinsics.fx / scale / rig[tof].intrinsics.fx  # cells per TOF pixel
    radius = splat_radius(spacing)
    z, centres, normals, bad, gx, gy = (
        a[::stride, ::stride] for a in (z, centres, normals, bad, gx, gy)
    )
    rays = rays[::stride, ::stride]
    h, w = z.shape
    good = ~bad.reshape(-1)
    X_c = z.reshape(-1)[good, None] * rays.reshape(-1, 3)[good]
    parts, A = _point_covariances(
        rig,
        covariance,
        (color, thermal, tof),
        centres.reshape(-1, 2)[good],
        X_c,
        normals.reshape(-1, 3)[good],
        gx.reshape(-1)[good],
        gy.reshape(-1)[good],
        (spacing, radius),
        range_err,
    )

    def grid(a: np.ndarray) -> np.ndarray:
        out = np.full((h * w, 2, 2), np.nan)
        out[good] = a
        return out.reshape(h, w, 2, 2)

    parts_out = {name: grid(c) for name, c in parts.items()}
    cov_out = sum(parts_out.values())
    return RegistrationSigma(
        color,
        thermal,
        tof,
        scale * stride,
        centres,
        major_sigma(cov_out),
        cov_out,
        parts_out,
        grid(A),
        range_err.source,
    )


def _point_covariances(
    rig: Rig,
    covariance: ParameterCovariance | None,
    sensors: tuple[str, str, str],
    q: np.ndarray,
    X_c: np.ndarray,
    n: np.ndarray,
    gx: np.ndarray,
    gy: np.ndarray,
    footprint: tuple[float, int],
    range_err: RangeError,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Each share's covariance at N colour pixels, colour pixels squared, and ``A``.

    Args:
        rig, covariance: as :func:`registration_sigma`.
        sensors: (colour, thermal, TOF).
        q: (N, 2) colour pixels; X_c: (N, 3) their points, colour frame, metres; n: (N, 3)
            the surface's unit normals there.
        gx, gy: (N,) the depth's change per cell, metres; footprint: (TOF pixels' spacing
            in cells, the splat radius in cells).
        range_err: the TOF's distance error.

    Returns:
        share -> (N, 2, 2) and (N, 2, 2) ``A``; NaN where the point has no TOF pixel.

    BLAS runs on one thread: the products are (N, 3) by (3, 3), which more threads do not
    speed up, and beside a busy fusion spinning BLAS threads cost 10x and more.
    """
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        color, thermal, tof = sensors
        N = len(q)
        parts = {p: np.full((N, 2, 2), np.nan) for p in PARTS}
        A_out = np.full((N, 2, 2), np.nan)
        T_tof_c = rig.T(tof, color)
        X_tof = X_c @ T_tof_c[:3, :3].T + T_tof_c[:3, 3]
        uv = rig[tof].intrinsics.project(X_tof)
        ok = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
        if ok.size == 0:
            return parts, A_out
        d = np.linalg.norm(X_tof[ok], axis=1)
        chain = _Chain(_Geometry.of(rig, color, thermal, tof), q[ok], uv[ok], d, n[ok])
        found = {
            "calibration": _calibration_part(chain, rig, covariance, sensors),
            "range": _range_part(chain, rig, tof, range_err),
            "footprint": _footprint_part(chain, gx[ok], gy[ok], *footprint),
        }
        A = np.linalg.inv(_dF_dq(chain))  # colour px per thermal px
        A_out[ok] = A
        for name, c in found.items():
            parts[name][ok] = A @ c @ A.transpose(0, 2, 1)
        return parts, A_out


def _outer(D: np.ndarray) -> np.ndarray:
    """(N, 2, 2) sum over k of D[:, k] D[:, k]^T for D (N, K, 2)."""
    return np.einsum("nki,nkj->nij", D, D)


def _central(f: Callable[[float], np.ndarray], h: float) -> np.ndarray:
    return (f(h) - f(-h)) / (2 * h)


def _calibration_part(
    chain: _Chain, rig: Rig, cov: ParameterCovariance | None, sensors: tuple[str, str, str]
) -> np.ndarray:
    """Each parameter's derivative of F(q) by central differences (rays moved along their
    analytic derivatives), times the covariance's factor."""
    N = len(chain.q)
    if cov is None or not set(sensors) & set(cov.sensors):
        return np.zeros((N, 2, 2))
    color, thermal, tof = sensors
    sub = cov.restricted(sensors)
    g = chain.g
    rays_of = {
        color: (chain.color_ray, _ray_derivatives(g.color, chain.q), "color_ray"),
        tof: (chain.tof_dir, _ray_derivatives(g.tof, chain.uv), "tof_dir"),
    }
    poses = {n: rig[n].T_rig_sensor for n in sensors}
    J = np.empty((N, 2, len(sub.names)))
    for j, name in enumerate(sub.names):
        sensor, param = split_name(name)
        if param in POSE_PARAMETERS:
            k = POSE_PARAMETERS.index(param)

            def at(e: float, sensor: str = sensor, k: int = k) -> np.ndarray:
                T = poses[sensor].copy()
                if k < 3:
                    T[:3, :3] = T[:3, :3] @ rotation_from_rvec(e * np.eye(3)[k])
                else:
                    T[:3, 3] += e * np.eye(3)[k - 3]
                P = {**poses, sensor: T}
                return chain(T_c_tof=invert(P[color]) @ P[tof], T_t_c=invert(P[thermal]) @ P[color])

        elif sensor == thermal:

            def at(e: float, param: str = param) -> np.ndarray:
                return chain(thermal=moved_intrinsics(g.thermal, {param: e}))

        else:
            i = ALL_INTRINSICS.index(param)
            ray, dray, arg = rays_of[sensor]

            def at(e: float, i: int = i, ray=ray, dray=dray, arg=arg) -> np.ndarray:
                r = ray + e * dray[:, :, i]
                if arg == "tof_dir":  # stays a unit vector
                    r = r / np.linalg.norm(r, axis=1, keepdims=True)
                return chain(**{arg: r})

        J[:, :, j] = _central(at, float(sub.sigma[j]) * 1e-2)
    M = J @ (sub.factor * sub.sigma[:, None])  # (N, 2, p): Cov = M M^T
    return M @ M.transpose(0, 2, 1)


def _range_part(chain: _Chain, rig: Rig, tof: str, err: RangeError) -> np.ndarray:
    s = rig[tof]
    per_pixel = err.per_pixel(s.width, s.height)
    iu = np.clip(np.rint(chain.uv[:, 0]).astype(int), 0, s.width - 1)
    iv = np.clip(np.rint(chain.uv[:, 1]).astype(int), 0, s.height - 1)
    D = _central(lambda e: chain(d_offset=e), 1e-3) * per_pixel[iv, iu][:, None]
    return _outer(D[:, None, :])


def _footprint_part(
    chain: _Chain, gx: np.ndarray, gy: np.ndarray, spacing: float, radius: int
) -> np.ndarray:
    """The depth the fusion holds over a cell: the nearest of the TOF points covering it.

    Args:
        chain: the nominal chain of the N cells.
        gx, gy: (N,) the depth's change per cell along x and y, metres.
        spacing: TOF pixels' spacing in cells; radius: cells each point covers around its
            own (:func:`fusion.mapping.splat_radius`).

    Along each axis the nearest covering point lies uniformly within one spacing of the
    window's near edge, ``radius + 1/2`` cells away: the depth is off by
    ``-(|gx| + |gy|) b`` plus noise of variance ``(gx^2 + gy^2) s^2 / 12``, with
    ``s = min(spacing, 2 radius + 1)`` and ``b = radius + 1/2 - s / 2``.
    """
    s = min(spacing, 2 * radius + 1.0)
    b = radius + 0.5 - s / 2
    dz_rms = np.sqrt((np.abs(gx) + np.abs(gy)) ** 2 * b * b + (gx * gx + gy * gy) * s * s / 12)
    g = chain.g
    depth = _nominal_depth(chain)

    def at(e: float) -> np.ndarray:
        return g.thermal.project(_to_thermal(g, (depth + e)[:, None] * chain.color_ray))

    D = _central(at, 1e-3) * dz_rms[:, None]
    return _outer(D[:, None, :])


def _nominal_depth(chain: _Chain) -> np.ndarray:
    g = chain.g
    X = (chain.d[:, None] * chain.tof_dir) @ g.T_c_tof[:3, :3].T + g.T_c_tof[:3, 3]
    return np.sum(chain.n * X, axis=1) / np.sum(chain.n * chain.color_ray, axis=1)


def _to_thermal(g: _Geometry, P_c: np.ndarray) -> np.ndarray:
    return P_c @ g.T_t_c[:3, :3].T + g.T_t_c[:3, 3]


def _dF_dq(chain: _Chain) -> np.ndarray:
    """(N, 2, 2) dF/dq on the measured surface (the plane through each point), thermal px
    per colour px."""
    g = chain.g
    depth_plane = np.sum(chain.n * chain.color_ray, axis=1) * _nominal_depth(chain)
    out = np.empty((len(chain.q), 2, 2))
    for k in range(2):
        cols = []
        for h in (1.0, -1.0):
            q = chain.q.copy()
            q[:, k] += h
            ray = _rays(g.color, q)
            z = depth_plane / np.sum(chain.n * ray, axis=1)
            cols.append(g.thermal.project(_to_thermal(g, z[:, None] * ray)))
        out[:, :, k] = (cols[0] - cols[1]) / 2.0
    return out


def _wall(
    rig: Rig, color: str, thermal: str, tof: str, distance_m: np.ndarray, cell_px: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of a wall facing the colour camera at each distance, one per ``cell_px``
    colour pixels, that the thermal imager and the TOF see.

    Returns:
        q (M, 2) colour pixels, P (M, 3) their points (colour frame, metres) and which
        distance (M,) each is at.
    """
    d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
    if d.size == 0 or not np.all(np.isfinite(d) & (d > 0)):
        raise ValueError("distance_m: expected finite distances > 0")
    cs = rig[color]
    hc, wc = -(-cs.height // cell_px), -(-cs.width // cell_px)
    centres = (pixel_grid(wc, hc).astype(np.float64) * cell_px + (cell_px - 1) / 2.0).reshape(-1, 2)
    rays = np.concatenate([cs.intrinsics.normalized(centres), np.ones((len(centres), 1))], 1)
    P = (d[:, None, None] * rays[None]).reshape(-1, 3)
    ok = np.ones(len(P), bool)
    for other in (thermal, tof):
        T = rig.T(other, color)
        ok &= in_image(
            rig[other].intrinsics.project(P @ T[:3, :3].T + T[:3, 3]), *rig[other].image_size
        )
    which = np.repeat(np.arange(d.size), len(centres))
    return np.tile(centres, (d.size, 1))[ok], P[ok], which[ok]


@dataclass(frozen=True, eq=False)
class SigmaCurve:
    """Registration sigma of one eye against distance, for a wall facing its colour camera.

    Attributes:
        distance_m: (N,) the wall's depth along the colour camera's axis, metres.
        median_px: part (``calibration``, ``range``, ``footprint``) and ``total`` -> (N,)
            median over the pixels that see the wall in all three sensors, colour pixels
            (NaN where none does).
        p95_px: ``total`` -> (N,) its 95th percentile.
    """

    distance_m: np.ndarray
    median_px: dict[str, np.ndarray]
    p95_px: dict[str, np.ndarray]


def sigma_vs_distance(
    rig: Rig,
    color: str,
    thermal: str,
    tof: str,
    distance_m: np.ndarray,
    range_err: RangeError | None = None,
    cell_px: int = 32,
) -> SigmaCurve:
    """:func:`registration_sigma` of a flat wall facing the colour camera at each distance
    (no footprint share: the depth does not change across a TOF pixel), over a grid of one
    value per ``cell_px`` colour pixels, for the Precision panel's curves.

    Args:
        rig: the rig (its ``covariance`` is used when it has one).
        color, thermal, tof: the eye's sensors and the TOF.
        distance_m: (N,) depths, metres, > 0.
        range_err: the TOF's distance error; default the rig's (:func:`range_error`).
        cell_px: colour pixels between values.
    """
    d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
    err = range_err or range_error(rig, tof)
    q, P, which = _wall(rig, color, thermal, tof, d, cell_px)
    zeros = np.zeros(len(q))
    normal = np.broadcast_to([0.0, 0.0, 1.0], (len(q), 3))
    parts, _ = _point_covariances(
        rig,
        rig.covariance,
        (color, thermal, tof),
        q,
        P,
        normal,
        zeros,
        zeros,
        (1.0, 0),
        err,
    )
    median = {p: np.full(d.size, np.nan) for p in (*PARTS, "total")}
    p95 = {"total": np.full(d.size, np.nan)}
    sig = {p: major_sigma(c) for p, c in parts.items()}
    sig["total"] = major_sigma(sum(parts.values()))
    for i in range(d.size):
        for p, s_p in sig.items():
            at = s_p[which == i]
            at = at[np.isfinite(at)]
            if at.size:
                median[p][i] = np.median(at)
                if p == "total":
                    p95[p][i] = np.percentile(at, 95)
    return SigmaCurve(d, median, p95)


@dataclass(frozen=True, eq=False)
class MappingDifference:
    """How far two calibrations' fusions put the same thermal value apart, one eye, against
    distance (a wall facing the colour camera, seen by the TOF).

    Attributes:
        distance_m: (N,) the wall's depth along the colour camera's axis, metres.
        median_px, p95_px, max_px: (N,) over the colour pixels that see the wall in all
            three sensors, colour pixels (NaN where none does).
    """

    distance_m: np.ndarray
    median_px: np.ndarray
    p95_px: np.ndarray
    max_px: np.ndarray

    def worst(self) -> tuple[float, float]:
        """(largest median over the distances, the distance where it is), px and metres."""
        i = int(np.nanargmax(self.median_px))
        return float(self.median_px[i]), float(self.distance_m[i])


def mapping_difference(
    rig_a: Rig,
    rig_b: Rig,
    color: str,
    thermal: str,
    tof: str,
    distance_m: np.ndarray,
    cell_px: int = 32,
) -> MappingDifference:
    """The difference of two calibrations' fused mappings (cross-validation, mrcal's idea in
    the operator's units).

    The TOF measures a wall facing ``rig_a``'s colour camera; each rig fuses those very
    measurements (its own TOF rays and pose, colour rays, thermal projection), and the two
    thermal pixels found for the same colour pixel are compared, brought to colour pixels
    through ``rig_a``'s local map (:func:`registration_sigma`'s ``A``). Exact, not
    linearised.

    Args:
        rig_a, rig_b: two calibrations of the same head (same sensor names).
        color, thermal, tof: the eye's sensors and the TOF.
        distance_m: (N,) depths, metres, > 0.
        cell_px: colour pixels between the compared pixels.
    """
    d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
    q, P, at = _wall(rig_a, color, thermal, tof, d, cell_px)
    T_tof_c = rig_a.T(tof, color)
    X_tof = P @ T_tof_c[:3, :3].T + T_tof_c[:3, 3]
    median, p95, top = (np.full(d.size, np.nan) for _ in range(3))
    if len(q):
        with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
            n = np.broadcast_to([0.0, 0.0, 1.0], (len(q), 3))
            dist = np.linalg.norm(X_tof, axis=1)
            chain = _Chain(
                _Geometry.of(rig_a, color, thermal, tof),
                q,
                rig_a[tof].intrinsics.project(X_tof),
                dist,
                n,
            )
            b = _Geometry.of(rig_b, color, thermal, tof)
            tof_dir = _rays(b.tof, chain.uv)
            F_b = chain(
                T_c_tof=b.T_c_tof,
                T_t_c=b.T_t_c,
                thermal=b.thermal,
                tof_dir=tof_dir / np.linalg.norm(tof_dir, axis=1, keepdims=True),
                color_ray=_rays(b.color, chain.q),
            )
            A = np.linalg.inv(_dF_dq(chain))
            gap = np.linalg.norm(np.einsum("nij,nj->ni", A, F_b - chain()), axis=1)
        for i in range(d.size):
            g = gap[(at == i) & np.isfinite(gap)]
            if g.size:
                median[i], p95[i], top[i] = np.median(g), np.percentile(g, 95), g.max()
    return MappingDifference(d, median, p95, top)
