"""Joint calibration of a multi-sensor rig from checkerboard corners.

Pipeline (the method's Zhang-based calibration, extended to the whole rig at once):

1. **Intrinsics per sensor** with Zhang's method (``cv2.calibrateCameraExtended``: closed
   form start, then Levenberg-Marquardt with distortion). Sensors with too few views are
   left out and reported.
2. **Initial poses**: each sensor's pose relative to the reference from the views it shares
   with an already placed sensor (chordal mean of rotations, median of translations),
   walking the co-visibility graph outward from the reference; each board pose from a
   sensor that saw it.
3. **Joint refinement** of every sensor pose ``T_rig_sensor``, every board pose
   ``T_rig_board`` and (optionally) every sensor's intrinsics and distortion, minimising the
   reprojection error of all corners of all sensors at once (``scipy.optimize.least_squares``,
   sparse Jacobian), first with a robust loss; then outlier corners and views are flagged,
   each sensor's residuals are weighted by its own noise level, and a final least-squares
   pass runs on the inliers.
4. **Uncertainty**: the covariance ``s^2 (J^T J)^-1`` of the final pass gives a 1-sigma for
   every parameter.

Inputs are plain arrays; nothing here reads files or prints. ``observations`` maps view
name -> sensor name -> (N, 2) float64 corners in canonical board order (calib.board).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from calib.board import Board
from calib.camera import Intrinsics
from calib.errors import CalibrationError
from calib.rig import Eye, Rig, Sensor
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
        min_views: fewest views with the board for a sensor's intrinsics.
    """

    reference: str | None = None
    refine_intrinsics: bool = True
    free_k3_modalities: tuple[str, ...] = ("color",)
    loss_scale_px: float = 1.0
    corner_outlier_sigmas: float = 5.0
    corner_outlier_min_px: float = 0.3
    view_outlier_factor: float = 3.0
    view_outlier_min_px: float = 0.3
    min_views: int = 3


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

    def column_groups(self) -> list[list[tuple[int, np.ndarray]]]:
        """Columns that touch disjoint rows, grouped for finite differences.

        Each group lists (column, rows of the residual vector it affects); the columns
        of one group are perturbed together (one sensor's or view's parameters never
        share rows with another's).
        """
        M = len(self.s_idx)
        point_rows = np.stack([2 * np.arange(M), 2 * np.arange(M) + 1], axis=1)
        rows_s = [point_rows[self.s_idx == k].ravel() for k in range(len(self.sensors))]
        rows_v = [point_rows[self.v_idx == k].ravel() for k in range(len(self.views))]
        groups: list[list[tuple[int, np.ndarray]]] = []
        for j in range(6):
            groups.append([(6 * (k - 1) + j, rows_s[k]) for k in range(1, len(self.sensors))])
            groups.append([(self.off_board + 6 * k + j, rows_v[k]) for k in range(len(self.views))])
        width = max((sl.stop - sl.start for sl in self.intr_slices.values()), default=0)
        for j in range(width):
            groups.append(
                [
                    (sl.start + j, rows_s[k])
                    for k, sl in self.intr_slices.items()
                    if sl.start + j < sl.stop
                ]
            )
        return [g for g in groups if g]

    def jacobian(
        self,
        fun: Callable[[np.ndarray], np.ndarray],
        x: np.ndarray,
        groups: list[list[tuple[int, np.ndarray]]],
    ) -> np.ndarray:
        """Dense Jacobian of ``fun`` at ``x`` by grouped central differences."""
        J = np.zeros((2 * len(self.s_idx), len(x)))
        for group in groups:
            cols = np.array([c for c, _ in group])
            h = 1e-6 * np.maximum(1.0, np.abs(x[cols]))
            xp, xm = x.copy(), x.copy()
            xp[cols] += h
            xm[cols] -= h
            diff = fun(xp) - fun(xm)
            for (c, rows), hc in zip(group, h, strict=True):
                J[rows, c] = diff[rows] / (2.0 * hc)
        return J


# -- initialisation -----------------------------------------------------------------------


def _intrinsics_per_sensor(
    obs: dict[str, dict[str, np.ndarray]], board: Board, spec: SensorSpec, free_k3: bool
) -> tuple[Intrinsics, dict[str, np.ndarray], np.ndarray]:
    """Zhang per sensor: intrinsics, T_sensor_board per view, std devs of the intrinsics."""
    views = sorted(obs)
    obj = [board.object_points().astype(np.float32) for _ in views]
    img = [obs[v].astype(np.float32).reshape(-1, 1, 2) for v in views]
    flags = 0 if free_k3 else cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    _rms, K, dist, rvecs, tvecs, std_intr, *_ = cv2.calibrateCameraExtended(
        obj, img, spec.image_size, None, None, flags=flags, criteria=crit
    )
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
                f"{opts.min_views} are needed for intrinsics"
            )
    if reference in excluded:
        raise CalibrationError(f"reference sensor {reference!r}: {excluded[reference]}")

    # 1. Intrinsics per sensor.
    intr: dict[str, Intrinsics] = {}
    T_s_board: dict[str, dict[str, np.ndarray]] = {}
    std_zhang: dict[str, np.ndarray] = {}
    candidates = [s for s in sorted(by_sensor) if s not in excluded]
    for k, s in enumerate(candidates):
        report(f"intrinsics of {s}", 0.4 * k / len(candidates))
        free_k3 = specs[s].modality in opts.free_k3_modalities
        intr[s], T_s_board[s], std_zhang[s] = _intrinsics_per_sensor(
            by_sensor[s], board, specs[s], free_k3
        )

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

    def build(keep: set[tuple[str, str, int]] | None) -> _Problem:
        s_idx, v_idx, c_idx, X, uv = [], [], [], [], []
        obj = board.object_points()
        for si, s in enumerate(sensors):
            for v in sorted(by_sensor[s]):
                corners = np.arange(board.n_corners)
                if keep is not None:
                    corners = np.array([c for c in corners if (v, s, int(c)) in keep], int)
                if not len(corners):
                    continue
                s_idx.append(np.full(len(corners), si))
                v_idx.append(np.full(len(corners), v))
                c_idx.append(corners)
                X.append(obj[corners])
                uv.append(by_sensor[s][v][corners])
        vnames = np.concatenate(v_idx)
        used_views = [v for v in views if v in set(vnames.tolist())]
        vpos = {v: i for i, v in enumerate(used_views)}
        return _Problem(
            sensors,
            used_views,
            np.concatenate(s_idx),
            np.array([vpos[v] for v in vnames]),
            np.concatenate(c_idx),
            np.concatenate(X),
            np.concatenate(uv),
            free_dist,
            opts.refine_intrinsics,
        )

    def solve(prob: _Problem, x0: np.ndarray, weights: np.ndarray, loss: str):
        w = np.repeat(weights[prob.s_idx], 2)
        groups = prob.column_groups()

        def fun(x: np.ndarray) -> np.ndarray:
            return (prob.project(x, intr) - prob.uv).ravel() * w

        return least_squares(
            fun,
            x0,
            jac=lambda x: prob.jacobian(fun, x, groups),
            method="trf",
            tr_solver="exact",
            x_scale="jac",
            loss=loss,
            f_scale=opts.loss_scale_px,
            ftol=1e-12,
            xtol=1e-12,
            gtol=1e-10,
            max_nfev=100,
        )

    # 3a. Robust joint pass on everything.
    report("joint refinement (robust)", 0.5)
    prob = build(None)
    x = solve(prob, prob.pack(T_rig_sensor, T_rig_board, intr), np.ones(len(sensors)), "soft_l1").x
    err = np.linalg.norm(prob.project(x, intr) - prob.uv, axis=1)

    # 3b. Outliers: corners beyond k sigma of their sensor; then views, judged by their
    # remaining corners (a view with many outlier corners is an outlier as a whole).
    sigma_s = np.array(
        [np.median(err[prob.s_idx == k]) / _RAYLEIGH_MEDIAN for k in range(len(sensors))]
    )
    limit = np.maximum(opts.corner_outlier_sigmas * sigma_s[prob.s_idx], opts.corner_outlier_min_px)
    bad_corner = err > limit
    outliers, bad_views = _flag_outliers(prob, err, bad_corner, limit, opts)
    keep = {
        (prob.views[prob.v_idx[m]], sensors[prob.s_idx[m]], int(prob.c_idx[m]))
        for m in range(len(err))
        if not bad_corner[m]
        and (prob.views[prob.v_idx[m]], sensors[prob.s_idx[m]]) not in bad_views
    }

    # 3c. Final pass: inliers, each sensor weighted by its own noise level.
    report("joint refinement (inliers, weighted)", 0.75)
    Rs, ts, Rb, tb = prob.poses(x)
    K4, D8 = prob.unpack_intrinsics(x, intr)
    for k, s in enumerate(sensors):
        T_rig_sensor[s] = make_T(Rs[k], ts[k])
        intr[s] = Intrinsics(*K4[k], tuple(D8[k, :5]))
    for vi, v in enumerate(prob.views):
        T_rig_board[v] = make_T(Rb[vi], tb[vi])
    final = build(keep)
    inlier_err = err[
        [
            (prob.views[prob.v_idx[m]], sensors[prob.s_idx[m]], int(prob.c_idx[m])) in keep
            for m in range(len(err))
        ]
    ]
    inlier_s = prob.s_idx[
        [
            (prob.views[prob.v_idx[m]], sensors[prob.s_idx[m]], int(prob.c_idx[m])) in keep
            for m in range(len(err))
        ]
    ]
    noise = np.array(
        [np.sqrt(np.mean(inlier_err[inlier_s == k] ** 2) / 2.0) for k in range(len(sensors))]
    )
    weights = 1.0 / np.maximum(noise, 1e-6)
    res = solve(final, final.pack(T_rig_sensor, T_rig_board, intr), weights, "linear")
    x = res.x

    # 4. Covariance of the parameters from the weighted Jacobian.
    report("uncertainty", 0.95)
    sig = _parameter_sigma(final, np.asarray(res.jac), res.fun)

    Rs, ts, Rb, tb = final.poses(x)
    K4, D8 = final.unpack_intrinsics(x, intr)
    for k, s in enumerate(sensors):
        T_rig_sensor[s] = make_T(Rs[k], ts[k])
        intr[s] = Intrinsics(*(float(v) for v in K4[k]), tuple(float(c) for c in D8[k, :5]))
    board_poses = {v: make_T(Rb[vi], tb[vi]) for vi, v in enumerate(final.views)}

    # Errors of every observation (outliers included) at the final solution.
    all_prob = build(None)
    x_all = all_prob.pack(T_rig_sensor, {**T_rig_board, **board_poses}, intr)
    err_all = np.linalg.norm(all_prob.project(x_all, intr) - all_prob.uv, axis=1)
    outlier_views = {(o.view, o.sensor): o.reason for o in outliers if o.corner is None}
    views_out: dict[str, dict[str, ViewError]] = {}
    for vi, v in enumerate(all_prob.views):
        for k, s in enumerate(sensors):
            sel = (all_prob.s_idx == k) & (all_prob.v_idx == vi)
            if sel.any():
                e = err_all[sel]
                views_out.setdefault(v, {})[s] = ViewError(
                    float(np.sqrt(np.mean(e**2))),
                    float(e.max()),
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
    )


def _parameter_sigma(prob: _Problem, J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """1-sigma of every parameter: the larger of two covariance estimates.

    * ``s^2 (J^T J)^-1``: right when corner errors are independent;
    * the cluster-robust (sandwich) estimate ``B (sum_g J_g^T r_g r_g^T J_g) B`` with
      ``B = (J^T J)^-1`` and one cluster per (view, sensor) image: detector errors are
      correlated within an image (blur, lighting or heating gradients move neighbouring
      corners alike), which the first estimate ignores and this one measures.
    """
    bread = np.linalg.pinv(J.T @ J)
    dof = max(1, J.shape[0] - J.shape[1])
    cov_iid = bread * float(np.sum(r**2) / dof)
    cluster = np.repeat(prob.v_idx * len(prob.sensors) + prob.s_idx, 2)
    order = np.argsort(cluster, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(cluster[order]) != 0])
    scores = np.add.reduceat(J[order] * r[order, None], starts, axis=0)  # (groups, n)
    g = len(starts)
    cov_cluster = bread @ (scores.T @ scores) @ bread * (g / max(1, g - 1))
    var = np.maximum(np.diag(cov_iid), np.diag(cov_cluster))
    return np.sqrt(np.clip(var, 0.0, None))


def _flag_outliers(
    prob: _Problem,
    err: np.ndarray,
    bad_corner: np.ndarray,
    limit: np.ndarray,
    opts: CalibrationOptions,
) -> tuple[list[Outlier], set[tuple[str, str]]]:
    """Outlier views and corners, with the reason for each."""
    outliers: list[Outlier] = []
    bad_views: set[tuple[str, str]] = set()
    view_rms: dict[tuple[int, int], float] = {}
    for k, s in enumerate(prob.sensors):
        for vi, v in enumerate(prob.views):
            sel = (prob.s_idx == k) & (prob.v_idx == vi)
            if not sel.any():
                continue
            n_bad = int(bad_corner[sel].sum())
            if n_bad > 0.2 * sel.sum():
                bad_views.add((v, s))
                outliers.append(
                    Outlier(
                        v,
                        s,
                        None,
                        float(np.sqrt(np.mean(err[sel] ** 2))),
                        (
                            f"{n_bad} of {int(sel.sum())} corners are beyond "
                            f"{opts.corner_outlier_sigmas:g} sigma of {s}'s noise (or "
                            f"{opts.corner_outlier_min_px:g} px)"
                        ),
                    )
                )
            else:
                view_rms[(k, vi)] = float(np.sqrt(np.mean(err[sel & ~bad_corner] ** 2)))
        rms = [r for (kk, _), r in view_rms.items() if kk == k]
        if not rms:
            continue
        med = float(np.median(rms))
        for (kk, vi), r in view_rms.items():
            if kk == k and r > opts.view_outlier_factor * med and r > opts.view_outlier_min_px:
                bad_views.add((prob.views[vi], s))
                outliers.append(
                    Outlier(
                        prob.views[vi],
                        s,
                        None,
                        r,
                        (
                            f"view RMS {r:.2f} px is {r / med:.1f}x the median {med:.2f} px of "
                            f"{s}'s views"
                        ),
                    )
                )
    for m in np.flatnonzero(bad_corner):
        v, s = prob.views[prob.v_idx[m]], prob.sensors[prob.s_idx[m]]
        if (v, s) not in bad_views:
            outliers.append(
                Outlier(
                    v,
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
    return outliers, bad_views


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
