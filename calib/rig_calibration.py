"""Joint calibration of a multi-sensor rig from checkerboard corners.

Pipeline (the method's Zhang-based calibration, extended to the whole rig at once):

1. **Intrinsics per sensor** with Zhang's method (``cv2.calibrateCamera``: closed form
   start, then Levenberg-Marquardt with distortion; ``cv2.calibrateCameraExtended`` for
   the standard deviations when the joint pass does not refine the intrinsics). Sensors
   with too few views are left out and reported.
2. **Initial poses**: each sensor's pose relative to the reference from the views it shares
   with an already placed sensor (chordal mean of rotations, median of translations),
   walking the co-visibility graph outward from the reference; each board pose from a
   sensor that saw it.
3. **Joint refinement** of every sensor pose ``T_rig_sensor``, every board pose
   ``T_rig_board`` and (optionally) every sensor's intrinsics and distortion, minimising the
   reprojection error of all corners of all sensors at once (analytic sparse Jacobian;
   Levenberg-Marquardt with a Schur complement on the board poses, calib.schur_lm, so an
   iteration costs time linear in the number of views), first with a robust loss; then
   outlier corners and views are flagged, each sensor's residuals are weighted by its own
   noise level, and a final least-squares pass runs on the inliers.
4. **Uncertainty**: the covariance ``s^2 (J^T J)^-1`` of the final pass, and a
   cluster-robust (per image) one, give a 1-sigma for every parameter; ``J^T J`` is formed
   from the sparse Jacobian (n x n, never the dense m x n matrix).

BLAS runs on one thread throughout (threadpoolctl, for the duration of
:func:`calibrate_rig`): beside other busy processes, OpenBLAS's spinning threads cost far
more than they gain on these small products. OpenCV's own threads are left alone: one or
two made no difference to Zhang's stage, idle or beside two busy processes (measured).
Everything per corner is vectorised (numpy); Python loops run over sensors, views or
images only.

Inputs are plain arrays; nothing here reads files or prints. ``observations`` maps view
name -> sensor name -> (N, 2) float64 corners in canonical board order (calib.board).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import cv2
import numpy as np
import scipy.linalg
from scipy import sparse
from threadpoolctl import threadpool_limits

from calib.board import Board
from calib.camera import Intrinsics
from calib.diagnosis import fallback_reference, screen_sensors, zhang_failure
from calib.errors import CalibrationError
from calib.polarity import SensorPolarity
from calib.rig import Eye, Rig, Sensor
from calib.schur_lm import SchurResult, least_squares_schur
from calib.transforms import (
    invert,
    make_T,
    mean_rotation,
    rotation_from_rvec,
    rotations_from_rvecs,
    rvec_from_rotation,
)

Observations = Mapping[str, Mapping[str, np.ndarray]]
Progress = Callable[[str, float], None]

# Rayleigh: the median of |e| for 2-D Gaussian errors of per-axis sigma s is s*sqrt(2 ln 2).
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))

# BLAS threads of the whole calibration: the products are small (sparse, n x n with n of a
# few hundred, the screening's (n M, 3) x (3, 3 J)), so more threads gain little and, beside
# other busy processes, spinning OpenBLAS threads cost up to 10x (BENCHMARKS.md).
_BLAS_THREADS = 1


@dataclass(frozen=True)
class SensorSpec:
    """What must be known of a sensor before calibrating it."""

    name: str
    modality: str
    image_size: tuple[int, int]


@dataclass(frozen=True)
class CalibrationOptions:
    """Settings of :func:`calibrate_rig`.

    Attributes:
        reference: sensor whose frame is the rig frame; default the TOF camera if one was
            observed, else the first sensor by name.
        refine_intrinsics: refine intrinsics and distortion in the joint pass too.
        free_k3_modalities: modalities whose k3 is estimated (k3 = 0 for the others:
            a low-resolution sensor cannot separate it from k1, k2).
        loss_scale_px: scale of the robust (soft L1) loss of the first joint pass.
        corner_outlier_sigmas: a corner is an outlier beyond this many sigmas of its
            sensor's noise (per-axis sigma from the median error, Rayleigh statistics) ...
        corner_outlier_min_px: ... and beyond this error (detector biases of a tenth of a
            pixel are not outliers, however clean the rest is).
        view_outlier_factor: a view is an outlier for a sensor when its RMS error exceeds
            this factor times the median view RMS of that sensor ...
        view_outlier_min_px: ... and exceeds this absolute value.
        min_views: fewest views with the board for a sensor's intrinsics. Zhang's method
            runs from 3, but measured on simulated captures a thermal imager seen in 3-6 of
            16 views missed the calibration targets (0.1 deg, 1 mm to the other sensors:
            up to 0.17 deg, 1.7 mm) and met them from 8 (0.06 deg, 0.4 mm); a sensor with
            fewer is left out with the reason (too few views), not calibrated badly.
    """

    reference: str | None = None
    refine_intrinsics: bool = True
    free_k3_modalities: tuple[str, ...] = ("color",)
    loss_scale_px: float = 1.0
    corner_outlier_sigmas: float = 5.0
    corner_outlier_min_px: float = 0.3
    view_outlier_factor: float = 3.0
    view_outlier_min_px: float = 0.3
    min_views: int = 8


@dataclass
class ViewError:
    """Reprojection error of one sensor in one view (at the final solution)."""

    rms_px: float
    max_px: float
    outlier: bool = False
    reason: str | None = None


@dataclass
class SensorResult:
    """Calibration of one sensor.

    ``sigma`` holds 1-sigma uncertainties: ``fx fy cx cy`` (px), ``distortion`` (list),
    ``rotation_deg`` and ``translation_m`` (3 components each, of ``T_rig_sensor``'s
    rotation vector and translation; zero for the reference).
    """

    name: str
    modality: str
    image_size: tuple[int, int]
    intrinsics: Intrinsics
    T_rig_sensor: np.ndarray
    sigma: dict[str, Any]
    views_detected: int
    views_used: int
    rms_px: float
    worst_view: str | None


@dataclass
class Outlier:
    """An observation left out of the final solution, and why."""

    view: str
    sensor: str
    corner: int | None  # None: the whole view of that sensor
    error_px: float
    reason: str


@dataclass
class CalibrationResult:
    """Everything a calibration found; ``to_report()`` gives it as JSON-able data."""

    reference: str
    board: Board
    sensors: dict[str, SensorResult]
    views: dict[str, dict[str, ViewError]]
    board_poses: dict[str, np.ndarray]
    outliers: list[Outlier]
    excluded_sensors: dict[str, str]
    rms_px: float
    seconds: float
    eyes: dict[str, Eye] = field(default_factory=dict)
    polarity: dict[str, SensorPolarity] = field(default_factory=dict)
    """Per sensor: which squares read dark/cold or bright/hot, and how that was found."""
    notes: list[str] = field(default_factory=list)
    """What the calibration decided on its own (e.g. another reference), in sentences."""

    def rig(self) -> Rig:
        """The calibrated rig (sensors that were calibrated), with ``uncertainty`` blocks."""
        sensors = {}
        for name, s in self.sensors.items():
            unc = {k: v for k, v in s.sigma.items()}
            unc["rms_px"] = s.rms_px
            sensors[name] = Sensor(
                name, s.modality, s.image_size, s.intrinsics, s.T_rig_sensor.copy(), uncertainty=unc
            )  # type: ignore[arg-type]
        eyes = {n: e for n, e in self.eyes.items() if e.color in sensors and e.thermal in sensors}
        return Rig(sensors=sensors, reference=self.reference, eyes=eyes)

    def to_report(self) -> dict[str, Any]:
        """Plain data (lists, floats, strings) for ``report.json``."""
        sensors = {}
        for name, s in self.sensors.items():
            i = s.intrinsics
            sensors[name] = {
                "modality": s.modality,
                "image_size": list(s.image_size),
                "views_detected": s.views_detected,
                "views_used": s.views_used,
                "rms_px": s.rms_px,
                "worst_view": s.worst_view,
                "intrinsics": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
                "distortion": list(i.distortion),
                "T_rig_sensor": s.T_rig_sensor.tolist(),
                "sigma": s.sigma,
            }
        return {
            "format": "trifuse-calibration-report/1",
            "reference": self.reference,
            "board": self.board.to_dict(),
            "rms_px": self.rms_px,
            "seconds": self.seconds,
            "sensors": sensors,
            "excluded_sensors": dict(self.excluded_sensors),
            "polarity": {n: p.as_dict() for n, p in sorted(self.polarity.items())},
            "notes": list(self.notes),
            "views": {
                v: {
                    s: {
                        "rms_px": e.rms_px,
                        "max_px": e.max_px,
                        "outlier": e.outlier,
                        "reason": e.reason,
                    }
                    for s, e in per.items()
                }
                for v, per in self.views.items()
            },
            "outliers": [
                {
                    "view": o.view,
                    "sensor": o.sensor,
                    "corner": o.corner,
                    "error_px": o.error_px,
                    "reason": o.reason,
                }
                for o in self.outliers
            ],
            "board_poses": {v: T.tolist() for v, T in self.board_poses.items()},
        }


# -- projection with per-point parameters -------------------------------------------------


def _project(Q: np.ndarray, K4: np.ndarray, D8: np.ndarray) -> np.ndarray:
    """Project camera-frame points (M, 3) with per-point intrinsics (M, 4) fx fy cx cy and
    distortion (M, 8) k1 k2 p1 p2 k3 k4 k5 k6 (OpenCV's model, as calib.camera)."""
    x = Q[:, 0] / Q[:, 2]
    y = Q[:, 1] / Q[:, 2]
    k1, k2, p1, p2, k3, k4, k5, k6 = D8.T
    r2 = x * x + y * y
    rad = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K4[:, 0] * xd + K4[:, 2], K4[:, 1] * yd + K4[:, 3]], axis=1)


def _project_derivatives(
    Q: np.ndarray, K4: np.ndarray, D8: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Derivatives of :func:`_project` (analytic, same per-point parameters).

    Args:
        Q: (M, 3) camera-frame points (metres).
        K4: (M, 4) fx fy cx cy (px).
        D8: (M, 8) k1 k2 p1 p2 k3 k4 k5 k6.

    Returns:
        ``d(u, v)/dQ`` (M, 2, 3) in px per metre, ``d(u, v)/d(fx, fy, cx, cy)`` (M, 2, 4)
        and ``d(u, v)/d(k1 ... k6)`` (M, 2, 8) in px per unit coefficient.
    """
    iz = 1.0 / Q[:, 2]
    x = Q[:, 0] * iz
    y = Q[:, 1] * iz
    k1, k2, p1, p2, k3, k4, k5, k6 = D8.T
    fx, fy = K4[:, 0], K4[:, 1]
    r2 = x * x + y * y
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    b = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = a / b
    drad = ((k1 + r2 * (2 * k2 + 3 * r2 * k3)) * b - a * (k4 + r2 * (2 * k5 + 3 * r2 * k6))) / (
        b * b
    )  # d rad / d r2
    xy = x * y
    xd = x * rad + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
    # d(xd, yd)/d(x, y)
    dxx = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * xy * drad + 2 * p1 * x + 2 * p2 * y
    dyy = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    M = len(Q)
    # d(x, y)/dQ = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    dQ = np.empty((M, 2, 3))
    dQ[:, 0, 0] = fx * dxx * iz
    dQ[:, 0, 1] = fx * dxy * iz
    dQ[:, 0, 2] = -fx * (dxx * x + dxy * y) * iz
    dQ[:, 1, 0] = fy * dxy * iz
    dQ[:, 1, 1] = fy * dyy * iz
    dQ[:, 1, 2] = -fy * (dxy * x + dyy * y) * iz
    dK = np.zeros((M, 2, 4))
    dK[:, 0, 0] = xd
    dK[:, 1, 1] = yd
    dK[:, 0, 2] = 1.0
    dK[:, 1, 3] = 1.0
    dD = np.empty((M, 2, 8))
    powers = np.stack([r2, r2 * r2, r2 * r2 * r2], axis=1) / b[:, None]  # d rad / d k1 k2 k3
    dD[:, 0, [0, 1, 4]] = (fx * x)[:, None] * powers
    dD[:, 1, [0, 1, 4]] = (fy * y)[:, None] * powers
    dD[:, 0, [5, 6, 7]] = -(fx * x * rad)[:, None] * powers
    dD[:, 1, [5, 6, 7]] = -(fy * y * rad)[:, None] * powers
    dD[:, 0, 2] = fx * 2 * xy
    dD[:, 1, 2] = fy * (r2 + 2 * y * y)
    dD[:, 0, 3] = fx * (r2 + 2 * x * x)
    dD[:, 1, 3] = fy * 2 * xy
    return dQ, dK, dD


def _right_jacobians(rvecs: np.ndarray) -> np.ndarray:
    """Right Jacobians of SO(3) at axis-angle vectors (K, 3) (radians): (K, 3, 3).

    ``R(r + dr) = R(r) exp([J_r(r) dr]x)`` to first order, with
    ``J_r = I - (1 - cos t) / t^2 [r]x + (t - sin t) / t^3 [r]x^2``, t = |r| (Taylor
    series below 1e-4 rad, where the closed form loses digits).
    """
    r = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    t2 = np.sum(r * r, axis=1)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    c1 = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    c2 = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    S = np.zeros((len(r), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -r[:, 2], r[:, 1]
    S[:, 1, 0], S[:, 1, 2] = r[:, 2], -r[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -r[:, 1], r[:, 0]
    return np.eye(3)[None] - c1[:, None, None] * S + c2[:, None, None] * (S @ S)


# -- the problem --------------------------------------------------------------------------


@dataclass
class _Problem:
    """Observations flattened to points, and the parameter vector's layout."""

    sensors: list[str]  # index = sensor id; [0] is the reference
    views: list[str]
    s_idx: np.ndarray  # (M,) sensor id of each corner
    v_idx: np.ndarray  # (M,) view id
    c_idx: np.ndarray  # (M,) corner index on the board
    X: np.ndarray  # (M, 3) board points
    uv: np.ndarray  # (M, 2) observed pixels
    free_dist: dict[str, list[int]]  # sensor -> indices (into 8) of estimated coefficients
    refine_intrinsics: bool

    def __post_init__(self) -> None:
        n_s, n_v = len(self.sensors), len(self.views)
        self.off_sensor = 0
        self.off_board = 6 * (n_s - 1)
        self.off_intr = self.off_board + 6 * n_v
        self.intr_slices: dict[int, slice] = {}
        o = self.off_intr
        if self.refine_intrinsics:
            for k, s in enumerate(self.sensors):
                n = 4 + len(self.free_dist[s])
                self.intr_slices[k] = slice(o, o + n)
                o += n
        self.n_params = o

    def pack(
        self,
        T_rig_sensor: dict[str, np.ndarray],
        T_rig_board: dict[str, np.ndarray],
        intr: dict[str, Intrinsics],
    ) -> np.ndarray:
        x = np.zeros(self.n_params)
        for k, s in enumerate(self.sensors[1:]):
            T = T_rig_sensor[s]
            x[6 * k : 6 * k + 3] = rvec_from_rotation(T[:3, :3])
            x[6 * k + 3 : 6 * k + 6] = T[:3, 3]
        for k, v in enumerate(self.views):
            T = T_rig_board[v]
            o = self.off_board + 6 * k
            x[o : o + 3] = rvec_from_rotation(T[:3, :3])
            x[o + 3 : o + 6] = T[:3, 3]
        for k, sl in self.intr_slices.items():
            i = intr[self.sensors[k]]
            d = np.zeros(8)
            d[: len(i.distortion)] = i.distortion
            x[sl] = [i.fx, i.fy, i.cx, i.cy, *d[self.free_dist[self.sensors[k]]]]
        return x

    def unpack_intrinsics(
        self, x: np.ndarray, fixed: dict[str, Intrinsics]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(S, 4) and (S, 8) intrinsics/distortion arrays at ``x``."""
        K4 = np.zeros((len(self.sensors), 4))
        D8 = np.zeros((len(self.sensors), 8))
        for k, s in enumerate(self.sensors):
            i = fixed[s]
            K4[k] = (i.fx, i.fy, i.cx, i.cy)
            D8[k, : len(i.distortion)] = i.distortion
            if k in self.intr_slices:
                p = x[self.intr_slices[k]]
                K4[k] = p[:4]
                D8[k] = 0.0
                D8[k, self.free_dist[s]] = p[4:]
        return K4, D8

    def poses(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        n_s, n_v = len(self.sensors), len(self.views)
        sp = x[: self.off_board].reshape(n_s - 1, 6)
        bp = x[self.off_board : self.off_intr].reshape(n_v, 6)
        Rs = np.concatenate([np.eye(3)[None], rotations_from_rvecs(sp[:, :3])])
        ts = np.concatenate([np.zeros((1, 3)), sp[:, 3:]])
        return Rs, ts, rotations_from_rvecs(bp[:, :3]), bp[:, 3:]

    def project(self, x: np.ndarray, fixed: dict[str, Intrinsics]) -> np.ndarray:
        Rs, ts, Rb, tb = self.poses(x)
        K4, D8 = self.unpack_intrinsics(x, fixed)
        P = np.einsum("kij,kj->ki", Rb[self.v_idx], self.X) + tb[self.v_idx]
        Q = np.einsum("kji,kj->ki", Rs[self.s_idx], P - ts[self.s_idx])
        return _project(Q, K4[self.s_idx], D8[self.s_idx])

    def subset(self, keep: np.ndarray) -> _Problem:
        """The problem on the corners where ``keep`` (M,) is true, in the same order; views
        left without corners are dropped (and the board poses' layout with them)."""
        used = np.unique(self.v_idx[keep])
        remap = np.zeros(len(self.views), dtype=np.int64)
        remap[used] = np.arange(len(used))
        return _Problem(
            self.sensors,
            [self.views[i] for i in used],
            self.s_idx[keep],
            remap[self.v_idx[keep]],
            self.c_idx[keep],
            self.X[keep],
            self.uv[keep],
            self.free_dist,
            self.refine_intrinsics,
        )

    @cached_property
    def _jacobian_layout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
        """Sparsity of the residuals' Jacobian, built once per problem.

        Each corner's two rows touch its board pose (6 columns), its sensor's pose (6,
        none for the reference) and its sensor's intrinsics (4 + free distortion
        coefficients, when refined). :meth:`jacobian` computes the values in that block
        order; ``order`` sorts them into CSR order (``indices``, ``indptr``).

        Returns:
            ``(order, indices, indptr, points)``: (nnz,) permutation, (nnz,) int32 column
            of each CSR value, (2M + 1,) row pointers, and the corner indices of each
            sensor.
        """
        M = len(self.s_idx)
        points = [np.flatnonzero(self.s_idx == k) for k in range(len(self.sensors))]
        row2 = 2 * np.arange(M)[:, None, None] + np.arange(2)[None, :, None]  # (M, 2, 1)
        rows = [np.broadcast_to(row2, (M, 2, 6))]
        cols = [
            np.broadcast_to(
                self.off_board + 6 * self.v_idx[:, None, None] + np.arange(6), (M, 2, 6)
            )
        ]
        moving = np.flatnonzero(self.s_idx > 0)
        rows.append(np.broadcast_to(row2[moving], (len(moving), 2, 6)))
        cols.append(
            np.broadcast_to(
                6 * (self.s_idx[moving, None, None] - 1) + np.arange(6), (len(moving), 2, 6)
            )
        )
        for k, sl in self.intr_slices.items():
            n = sl.stop - sl.start
            rows.append(np.broadcast_to(row2[points[k]], (len(points[k]), 2, n)))
            cols.append(np.broadcast_to(sl.start + np.arange(n), (len(points[k]), 2, n)))
        r = np.concatenate([a.ravel() for a in rows])
        c = np.concatenate([a.ravel() for a in cols])
        order = np.lexsort((c, r))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=2 * M))])
        return order, c[order].astype(np.int32), indptr, points

    def jacobian(
        self, x: np.ndarray, fixed: dict[str, Intrinsics], weights: np.ndarray
    ) -> sparse.csr_matrix:
        """Analytic Jacobian of the weighted residuals ``(project(x) - uv) * weights``.

        Args:
            x: (n,) parameters (rotation vectors in radians, translations in metres,
                intrinsics in px, distortion coefficients).
            fixed: intrinsics of sensors whose intrinsics are not parameters.
            weights: (M,) weight of each corner (both of its rows), 1/px.

        Returns:
            (2M, n) CSR matrix, rows ``2m`` (u) and ``2m + 1`` (v) of corner m; about
            21 non-zeros per row (see :attr:`_jacobian_layout`).
        """
        order, indices, indptr, points = self._jacobian_layout
        n_s = len(self.sensors)
        s, v = self.s_idx, self.v_idx
        Rs, ts, Rb, tb = self.poses(x)
        K4, D8 = self.unpack_intrinsics(x, fixed)
        P = np.einsum("kij,kj->ki", Rb[v], self.X) + tb[v]
        Q = np.einsum("kji,kj->ki", Rs[s], P - ts[s])
        dQ, dK, dD = _project_derivatives(Q, K4[s], D8[s])
        w = weights[:, None, None]
        dQ *= w
        dP = np.einsum("kai,kji->kaj", dQ, Rs[s])  # d/dP = d/dQ R_s^T
        Jrb = _right_jacobians(x[self.off_board : self.off_intr].reshape(-1, 6)[:, :3])
        # P = R_b X + t_b: dP/dr_b = -R_b [X]x J_r(r_b), and c^T [X]x = (c x X)^T.
        dRb = -np.einsum(
            "kai,kij->kaj", np.cross(np.einsum("kai,kij->kaj", dP, Rb[v]), self.X[:, None]), Jrb[v]
        )
        blocks = [np.concatenate([dRb, dP], axis=2)]
        moving = s > 0
        if n_s > 1:
            # Q = R_s^T (P - t_s): dQ/dr_s = [Q]x J_r(r_s), dQ/dt_s = -R_s^T.
            Jrs = _right_jacobians(x[: self.off_board].reshape(-1, 6)[:, :3])
            dRs = np.einsum(
                "kai,kij->kaj", np.cross(dQ[moving], Q[moving, None]), Jrs[s[moving] - 1]
            )
            blocks.append(np.concatenate([dRs, -dP[moving]], axis=2))
        for k in self.intr_slices:
            m = points[k]
            free = self.free_dist[self.sensors[k]]
            blocks.append(np.concatenate([dK[m], dD[m][:, :, free]], axis=2) * w[m])
        data = np.concatenate([b.ravel() for b in blocks])[order]
        return sparse.csr_matrix(
            (data, indices, indptr), shape=(2 * len(s), self.n_params), copy=False
        )


def _build_problem(
    sensors: list[str],
    views: list[str],
    by_sensor: Mapping[str, Mapping[str, np.ndarray]],
    board: Board,
    free_dist: dict[str, list[int]],
    refine_intrinsics: bool,
) -> _Problem:
    """Every corner of every sensor's views, ordered by sensor, view (as ``views``: sorted)
    and corner.

    Args:
        sensors: sensor names, the reference first.
        views: every view any of them saw, sorted.
        by_sensor: sensor -> view -> (N, 2) corners, pixels.
        board: the checkerboard (N corners).
        free_dist: sensor -> indices (into k1 k2 p1 p2 k3 k4 k5 k6) of the estimated
            distortion coefficients.
        refine_intrinsics: intrinsics are parameters.
    """
    n = board.n_corners
    vpos = {v: i for i, v in enumerate(views)}
    s_idx, v_idx, uv = [], [], []
    for si, s in enumerate(sensors):
        names = sorted(by_sensor[s])
        if not names:
            continue
        s_idx.append(np.full(len(names) * n, si))
        v_idx.append(np.repeat([vpos[v] for v in names], n))
        uv.append(np.stack([by_sensor[s][v] for v in names]).reshape(-1, 2))
    s_all = np.concatenate(s_idx)
    c_idx = np.tile(np.arange(n), len(s_all) // n)
    return _Problem(
        list(sensors),
        list(views),
        s_all,
        np.concatenate(v_idx),
        c_idx,
        board.object_points()[c_idx],
        np.concatenate(uv).astype(np.float64),
        free_dist,
        refine_intrinsics,
    )


# -- initialisation -----------------------------------------------------------------------


def _intrinsics_per_sensor(
    obs: dict[str, dict[str, np.ndarray]],
    board: Board,
    spec: SensorSpec,
    free_k3: bool,
    with_std: bool = True,
) -> tuple[Intrinsics, dict[str, np.ndarray], np.ndarray]:
    """Zhang per sensor (OpenCV).

    Args:
        obs: view -> (N, 2) corners, pixels.
        board: the checkerboard.
        spec: the sensor's image size.
        free_k3: estimate k3 (else k3 = 0).
        with_std: also the standard deviations of the intrinsics
            (``cv2.calibrateCameraExtended``). They cost more than the calibration itself
            and grow with the cube of the views (OpenCV inverts the dense normal matrix of
            intrinsics and every view's pose: 0.8 s against 0.2 s at 150 views); the joint
            refinement's covariance replaces them when it refines the intrinsics.

    Returns:
        Intrinsics, view -> (4, 4) T_sensor_board (metres), and (9,) standard deviations of
        fx fy cx cy (px) k1 k2 p1 p2 k3 (NaN without ``with_std``).
    """
    views = sorted(obs)
    obj = [board.object_points().astype(np.float32) for _ in views]
    img = [obs[v].astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = 0 if free_k3 else cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if with_std:
        _rms, K, dist, rvecs, tvecs, std_intr, *_ = cv2.calibrateCameraExtended(
            obj, img, spec.image_size, None, None, flags=flags, criteria=crit
        )
    else:
        _rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            obj, img, spec.image_size, None, None, flags=flags, criteria=crit
        )
        std_intr = np.full(9, np.nan)
    d = dist.ravel()[:5]
    intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(float(c) for c in d))
    T = {
        v: make_T(rotation_from_rvec(r.ravel()), t.ravel())
        for v, r, t in zip(views, rvecs, tvecs, strict=True)
    }
    return intr, T, np.ravel(std_intr)


def _place_sensors(
    reference: str, sensors: list[str], T_s_board: dict[str, dict[str, np.ndarray]]
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """T_rig_sensor for every sensor reachable from ``reference`` through shared views."""
    placed = {reference: np.eye(4)}
    unplaced = {s: "never seen in the same view as an already placed sensor" for s in sensors}
    unplaced.pop(reference)
    progress = True
    while unplaced and progress:
        progress = False
        for s in sorted(unplaced):
            best = None
            for p in placed:
                shared = sorted(set(T_s_board[s]) & set(T_s_board[p]))
                if shared and (best is None or len(shared) > len(best[1])):
                    best = (p, shared)
            if best is None:
                continue
            p, shared = best
            T_p_s = [T_s_board[p][v] @ invert(T_s_board[s][v]) for v in shared]
            R = mean_rotation(np.stack([T[:3, :3] for T in T_p_s]))
            t = np.median(np.stack([T[:3, 3] for T in T_p_s]), axis=0)
            placed[s] = placed[p] @ make_T(R, t)
            del unplaced[s]
            progress = True
    return placed, unplaced


# -- the calibration ----------------------------------------------------------------------


def _check_observations(
    observations: Observations, board: Board, specs: Mapping[str, SensorSpec]
) -> dict[str, dict[str, np.ndarray]]:
    """Validate shapes; return sensor -> view -> corners."""
    by_sensor: dict[str, dict[str, np.ndarray]] = {}
    for view, per in observations.items():
        for sensor, corners in per.items():
            if sensor not in specs:
                raise CalibrationError(
                    f"view {view!r}: sensor {sensor!r} has no description (known: {sorted(specs)})"
                )
            c = np.asarray(corners, dtype=np.float64)
            if c.shape != (board.n_corners, 2):
                raise CalibrationError(
                    f"view {view!r}, sensor {sensor!r}: expected corners of "
                    f"shape ({board.n_corners}, 2), got {c.shape}"
                )
            if not np.all(np.isfinite(c)):
                raise CalibrationError(f"view {view!r}, sensor {sensor!r}: corners contain NaN")
            by_sensor.setdefault(sensor, {})[view] = c
    if not by_sensor:
        raise CalibrationError("the board was not detected in any image: nothing to calibrate")
    return by_sensor


def _choose_reference(
    options: CalibrationOptions, observed: list[str], specs: Mapping[str, SensorSpec]
) -> str:
    if options.reference is not None:
        if options.reference not in specs:
            raise CalibrationError(
                f"reference: unknown sensor {options.reference!r} (sensors: {sorted(specs)})"
            )
        if options.reference not in observed:
            raise CalibrationError(
                f"reference {options.reference!r}: the board was never detected in it"
            )
        return options.reference
    tofs = sorted(s for s in observed if specs[s].modality == "tof")
    return tofs[0] if tofs else sorted(observed)[0]


def calibrate_rig(
    observations: Observations,
    board: Board,
    specs: Mapping[str, SensorSpec],
    options: CalibrationOptions | None = None,
    progress: Progress | None = None,
    eyes: Mapping[str, Eye] | None = None,
) -> CalibrationResult:
    """Calibrate every observed sensor's intrinsics and pose, and every board pose.

    Args:
        observations: view -> sensor -> (N, 2) corners (canonical order, full board).
        board: the checkerboard.
        specs: modality and image size of every sensor that may appear.
        options: see :class:`CalibrationOptions`.
        progress: called with (stage description, fraction done in [0, 1]).
        eyes: eye pairs to carry into the calibrated rig.

    Raises:
        CalibrationError: nothing usable (no detections, the reference has too few views ...).
    """
    # BLAS on one thread throughout (threadpoolctl; numpy's, scipy's and OpenCV's own
    # OpenBLAS): every product here is small, and OpenBLAS's spinning threads cost more than
    # they gain. Measured on 40 views: 0.42 s idle, 0.87 s beside two busy processes; with
    # OpenBLAS's default 2 threads 0.56 s and 1.5 s.
    with threadpool_limits(limits=_BLAS_THREADS, user_api="blas"):
        return _calibrate_rig(observations, board, specs, options, progress, eyes)


def _calibrate_rig(
    observations: Observations,
    board: Board,
    specs: Mapping[str, SensorSpec],
    options: CalibrationOptions | None,
    progress: Progress | None,
    eyes: Mapping[str, Eye] | None,
) -> CalibrationResult:
    """:func:`calibrate_rig`'s work (same arguments), with BLAS limited by the caller."""
    opts = options or CalibrationOptions()
    t0 = time.perf_counter()
    report = progress or (lambda _stage, _frac: None)
    by_sensor = _check_observations(observations, board, specs)
    reference = _choose_reference(opts, sorted(by_sensor), specs)

    excluded: dict[str, str] = {}
    for s in sorted(by_sensor):
        if len(by_sensor[s]) < opts.min_views:
            excluded[s] = (
                f"board detected in {len(by_sensor[s])} view(s); at least "
                f"{opts.min_views} are needed for intrinsics: too few views (show it the "
                "board in more views)"
            )

    # 1. Intrinsics per sensor.
    intr: dict[str, Intrinsics] = {}
    T_s_board: dict[str, dict[str, np.ndarray]] = {}
    std_zhang: dict[str, np.ndarray] = {}
    candidates = [s for s in sorted(by_sensor) if s not in excluded]
    for k, s in enumerate(candidates):
        report(f"intrinsics of {s}", 0.4 * k / len(candidates))
        free_k3 = specs[s].modality in opts.free_k3_modalities
        try:
            intr[s], T_s_board[s], std_zhang[s] = _intrinsics_per_sensor(
                by_sensor[s], board, specs[s], free_k3, with_std=not opts.refine_intrinsics
            )
        except (cv2.error, ValueError) as exc:  # e.g. a negative focal length
            excluded[s] = zhang_failure(len(by_sensor[s]), exc)

    # 1b. Diagnosis (calib.diagnosis): physical intrinsics, and every sensor's board
    # ordering (thermal and TOF polarity) found from its poses' agreement with the others;
    # a sensor that cannot be reconciled is left out with the reason.
    report("board orientation per sensor", 0.38)
    screen = screen_sensors(
        {s: by_sensor[s] for s in intr},
        {s: specs[s].modality for s in intr},
        {s: specs[s].image_size for s in intr},
        intr,
        T_s_board,
        board,
    )
    excluded.update(screen.excluded)
    by_sensor = {**by_sensor, **screen.observations}
    T_s_board = screen.T_sensor_board
    candidates = [s for s in candidates if s not in excluded]
    notes = list(screen.notes)
    if reference in excluded:
        fallback = fallback_reference(
            reference, candidates, {s: specs[s].modality for s in specs}, screen.anchor
        )
        if fallback is None:
            raise CalibrationError(
                f"reference sensor {reference!r}: {excluded[reference]}; and no other sensor "
                "can be calibrated: "
                + "; ".join(f"{s}: {why}" for s, why in excluded.items() if s != reference)
            )
        notes.append(
            f"the reference {reference} is not calibrated ({excluded[reference]}): the rig "
            f"frame is {fallback}'s instead"
        )
        reference = fallback

    # 2. Initial poses.
    report("initial poses", 0.4)
    T_rig_sensor, unplaced = _place_sensors(reference, candidates, T_s_board)
    excluded.update(unplaced)
    sensors = [reference, *sorted(s for s in T_rig_sensor if s != reference)]
    views = sorted({v for s in sensors for v in by_sensor[s]})
    T_rig_board: dict[str, np.ndarray] = {}
    for v in views:
        seen = [s for s in sensors if v in by_sensor[s]]
        s = max(seen, key=lambda n: specs[n].image_size[0] * specs[n].image_size[1])
        T_rig_board[v] = T_rig_sensor[s] @ T_s_board[s][v]

    free_dist = {
        s: [0, 1, 2, 3] + ([4] if specs[s].modality in opts.free_k3_modalities else [])
        for s in sensors
    }

    def solve(prob: _Problem, x0: np.ndarray, weights: np.ndarray, loss: str) -> SchurResult:
        w_point = weights[prob.s_idx]
        w = np.repeat(w_point, 2)

        def fun(x: np.ndarray) -> np.ndarray:
            return (prob.project(x, intr) - prob.uv).ravel() * w

        return least_squares_schur(
            fun,
            lambda x: prob.jacobian(x, intr, w_point),
            x0,
            (prob.off_board, len(prob.views), 6),
            loss=loss,
            f_scale=opts.loss_scale_px,
            ftol=1e-12,
            xtol=1e-12,
            gtol=1e-10,
            max_nfev=100,
        )

    # 3a. Robust joint pass on everything.
    report("joint refinement (robust)", 0.5)
    prob = _build_problem(sensors, views, by_sensor, board, free_dist, opts.refine_intrinsics)
    x = solve(prob, prob.pack(T_rig_sensor, T_rig_board, intr), np.ones(len(sensors)), "soft_l1").x
    err = np.linalg.norm(prob.project(x, intr) - prob.uv, axis=1)

    # 3b. Outliers: corners beyond k sigma of their sensor; then views, judged by their
    # remaining corners (a view with many outlier corners is an outlier as a whole).
    sigma_s = np.array(
        [np.median(err[prob.s_idx == k]) / _RAYLEIGH_MEDIAN for k in range(len(sensors))]
    )
    limit = np.maximum(opts.corner_outlier_sigmas * sigma_s[prob.s_idx], opts.corner_outlier_min_px)
    bad_corner = err > limit
    outliers, in_bad_view = _flag_outliers(prob, err, bad_corner, limit, opts)
    inlier = ~bad_corner & ~in_bad_view

    # 3c. Final pass: inliers, each sensor weighted by its own noise level.
    report("joint refinement (inliers, weighted)", 0.75)
    Rs, ts, Rb, tb = prob.poses(x)
    K4, D8 = prob.unpack_intrinsics(x, intr)
    for k, s in enumerate(sensors):
        T_rig_sensor[s] = make_T(Rs[k], ts[k])
        intr[s] = Intrinsics(*K4[k], tuple(D8[k, :5]))
    for vi, v in enumerate(prob.views):
        T_rig_board[v] = make_T(Rb[vi], tb[vi])
    final = prob.subset(inlier)
    inlier_err, inlier_s = err[inlier], prob.s_idx[inlier]
    noise = np.array(
        [np.sqrt(np.mean(inlier_err[inlier_s == k] ** 2) / 2.0) for k in range(len(sensors))]
    )
    weights = 1.0 / np.maximum(noise, 1e-6)
    res = solve(final, final.pack(T_rig_sensor, T_rig_board, intr), weights, "linear")
    x = res.x

    # 4. Covariance of the parameters from the weighted Jacobian.
    report("uncertainty", 0.95)
    sig = _parameter_sigma(final, res.jac, res.fun)

    Rs, ts, Rb, tb = final.poses(x)
    K4, D8 = final.unpack_intrinsics(x, intr)
    for k, s in enumerate(sensors):
        T_rig_sensor[s] = make_T(Rs[k], ts[k])
        intr[s] = Intrinsics(*(float(v) for v in K4[k]), tuple(float(c) for c in D8[k, :5]))
    board_poses = {v: make_T(Rb[vi], tb[vi]) for vi, v in enumerate(final.views)}

    # Errors of every observation (outliers included) at the final solution.
    x_all = prob.pack(T_rig_sensor, {**T_rig_board, **board_poses}, intr)
    err_all = np.linalg.norm(prob.project(x_all, intr) - prob.uv, axis=1)
    outlier_views = {(o.view, o.sensor): o.reason for o in outliers if o.corner is None}
    n_s = len(sensors)
    image = prob.v_idx * n_s + prob.s_idx  # view-major: the report's order
    count, sum_sq, worst_px = _image_sums(image, err_all, len(prob.views) * n_s)
    views_out: dict[str, dict[str, ViewError]] = {}
    for i in np.flatnonzero(count):
        v, s = prob.views[i // n_s], sensors[i % n_s]
        views_out.setdefault(v, {})[s] = ViewError(
            float(np.sqrt(sum_sq[i] / count[i])),
            float(worst_px[i]),
            (v, s) in outlier_views,
            outlier_views.get((v, s)),
        )

    results: dict[str, SensorResult] = {}
    final_err = np.linalg.norm(final.project(x, intr) - final.uv, axis=1)
    for k, s in enumerate(sensors):
        sel = final.s_idx == k
        sensor_sigma = _sensor_sigma(final, k, sig, std_zhang[s], free_dist[s])
        per_view = {v: e.rms_px for v, d in views_out.items() for n, e in d.items() if n == s}
        worst = max(per_view, key=per_view.__getitem__) if per_view else None
        results[s] = SensorResult(
            s,
            specs[s].modality,
            specs[s].image_size,
            intr[s],
            T_rig_sensor[s],
            sensor_sigma,
            views_detected=len(by_sensor[s]),
            views_used=len({final.views[i] for i in np.unique(final.v_idx[sel])}),
            rms_px=float(np.sqrt(np.mean(final_err[sel] ** 2))),
            worst_view=worst,
        )
    report("done", 1.0)
    return CalibrationResult(
        reference=reference,
        board=board,
        sensors=results,
        views=views_out,
        board_poses=board_poses,
        outliers=outliers,
        excluded_sensors=excluded,
        rms_px=float(np.sqrt(np.mean(final_err**2))),
        seconds=time.perf_counter() - t0,
        eyes=dict(eyes or {}),
        polarity=screen.polarity,
        notes=notes,
    )


def _parameter_sigma(prob: _Problem, J: sparse.spmatrix | np.ndarray, r: np.ndarray) -> np.ndarray:
    """1-sigma of every parameter (units of ``x``): the larger of two covariance estimates.

    * ``s^2 (J^T J)^-1``: right when corner errors are independent;
    * the cluster-robust (sandwich) estimate ``B (sum_g J_g^T r_g r_g^T J_g) B`` with
      ``B = (J^T J)^-1`` and one cluster per (view, sensor) image: detector errors are
      correlated within an image (blur, lighting or heating gradients move neighbouring
      corners alike), which the first estimate ignores and this one measures.

    Args:
        prob: the problem ``J`` and ``r`` belong to.
        J: (2M, n) Jacobian of the weighted residuals, sparse (or dense); only the
            (n, n) ``J^T J`` and the (images, n) sparse per-image scores are formed.
        r: (2M,) weighted residuals at the solution.

    Returns:
        (n,) standard deviations.
    """
    J = sparse.csr_matrix(J)
    A = (J.T @ J).toarray()  # (n, n)
    # Invert the equilibrated matrix (unit diagonal): parameters in px, metres and radians
    # differ by orders of magnitude; scaling keeps the inverse accurate.
    diag = np.diag(A).copy()
    d = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
    As = A * d[:, None] * d[None, :]
    with threadpool_limits(limits=_BLAS_THREADS, user_api="blas"):
        try:
            inv = scipy.linalg.cho_solve(scipy.linalg.cho_factor(As), np.eye(len(As)))
        except np.linalg.LinAlgError:  # singular: some parameter is not determined
            inv = np.linalg.pinv(As, hermitian=True)
        bread = inv * d[:, None] * d[None, :]
        dof = max(1, J.shape[0] - J.shape[1])
        var_iid = np.diag(bread) * float(np.sum(r**2) / dof)
        cluster = np.repeat(prob.v_idx * len(prob.sensors) + prob.s_idx, 2)
        _, group = np.unique(cluster, return_inverse=True)
        g = int(group.max()) + 1
        C = sparse.csr_matrix((r, (group, np.arange(len(r)))), shape=(g, len(r)))
        scores = (C @ J).tocsr()  # (g, n): sum over the image's rows of r_i J_i
        SB = np.asarray(scores @ bread)  # (g, n)
        var_cluster = np.sum(SB * SB, axis=0) * (g / max(1, g - 1))
    var = np.maximum(var_iid, var_cluster)
    return np.sqrt(np.clip(var, 0.0, None))


def _image_sums(
    image: np.ndarray, err: np.ndarray, n_images: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per image: corners, sum of squared errors (px^2) and largest error (px; -inf when
    empty), from the (M,) image id and (M,) error of each corner."""
    count = np.bincount(image, minlength=n_images)
    sum_sq = np.bincount(image, weights=err * err, minlength=n_images)
    worst = np.full(n_images, -np.inf)
    np.maximum.at(worst, image, err)
    return count, sum_sq, worst


def _flag_outliers(
    prob: _Problem,
    err: np.ndarray,
    bad_corner: np.ndarray,
    limit: np.ndarray,
    opts: CalibrationOptions,
) -> tuple[list[Outlier], np.ndarray]:
    """Outlier views and corners, with the reason for each.

    Args:
        prob: the problem the corners belong to.
        err: (M,) error of each corner, px.
        bad_corner: (M,) whether each corner is beyond its limit.
        limit: (M,) each corner's limit, px.
        opts: the thresholds.

    Returns:
        The outliers (per sensor: its outlier views in view order, then the corners of
        other views), and (M,) whether each corner's view is an outlier for its sensor.
    """
    outliers: list[Outlier] = []
    n_v = len(prob.views)
    size = len(prob.sensors) * n_v
    image = prob.s_idx * n_v + prob.v_idx  # sensor-major
    count, sum_sq, _ = _image_sums(image, err, size)
    n_bad = np.bincount(image, weights=bad_corner, minlength=size).astype(int)
    good_count, good_sq, _ = _image_sums(image[~bad_corner], err[~bad_corner], size)
    bad_image = np.zeros(size, dtype=bool)
    for k, s in enumerate(prob.sensors):
        view_rms: dict[int, float] = {}
        for i in k * n_v + np.flatnonzero(count[k * n_v : (k + 1) * n_v]):
            v = prob.views[i - k * n_v]
            if n_bad[i] > 0.2 * count[i]:
                bad_image[i] = True
                outliers.append(
                    Outlier(
                        v,
                        s,
                        None,
                        float(np.sqrt(sum_sq[i] / count[i])),
                        (
                            f"{n_bad[i]} of {count[i]} corners are beyond "
                            f"{opts.corner_outlier_sigmas:g} sigma of {s}'s noise (or "
                            f"{opts.corner_outlier_min_px:g} px)"
                        ),
                    )
                )
            else:
                view_rms[int(i)] = float(np.sqrt(good_sq[i] / good_count[i]))
        if not view_rms:
            continue
        med = float(np.median(list(view_rms.values())))
        for i, r in view_rms.items():
            if r > opts.view_outlier_factor * med and r > opts.view_outlier_min_px:
                bad_image[i] = True
                outliers.append(
                    Outlier(
                        prob.views[i - k * n_v],
                        s,
                        None,
                        r,
                        (
                            f"view RMS {r:.2f} px is {r / med:.1f}x the median {med:.2f} px of "
                            f"{s}'s views"
                        ),
                    )
                )
    in_bad_view = bad_image[image]
    for m in np.flatnonzero(bad_corner & ~in_bad_view):  # the (few) outlier corners
        s = prob.sensors[prob.s_idx[m]]
        outliers.append(
            Outlier(
                prob.views[prob.v_idx[m]],
                s,
                int(prob.c_idx[m]),
                float(err[m]),
                (
                    f"error {err[m]:.2f} px > {limit[m]:.2f} px (the larger of "
                    f"{opts.corner_outlier_sigmas:g} sigma of {s}'s noise and "
                    f"{opts.corner_outlier_min_px:g} px)"
                ),
            )
        )
    return outliers, in_bad_view


def _sensor_sigma(
    prob: _Problem, k: int, sig: np.ndarray, std_zhang: np.ndarray, free: list[int]
) -> dict[str, Any]:
    """1-sigma of one sensor's parameters (from the joint covariance, or Zhang's)."""
    out: dict[str, Any] = {}
    if k in prob.intr_slices:
        p = sig[prob.intr_slices[k]]
        out.update(fx=float(p[0]), fy=float(p[1]), cx=float(p[2]), cy=float(p[3]))
        dist = [0.0] * 5
        for j, idx in enumerate(free):
            if idx < 5:
                dist[idx] = float(p[4 + j])
        out["distortion"] = dist
    else:
        out.update(
            fx=float(std_zhang[0]),
            fy=float(std_zhang[1]),
            cx=float(std_zhang[2]),
            cy=float(std_zhang[3]),
            distortion=[float(v) for v in std_zhang[4:9]],
        )
    if k == 0:
        out["rotation_deg"] = [0.0, 0.0, 0.0]
        out["translation_m"] = [0.0, 0.0, 0.0]
    else:
        p = sig[6 * (k - 1) : 6 * k]
        out["rotation_deg"] = [float(np.degrees(v)) for v in p[:3]]
        out["translation_m"] = [float(v) for v in p[3:]]
    return out
