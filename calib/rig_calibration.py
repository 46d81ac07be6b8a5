"""Joint calibration of a multi-sensor rig from checkerboard corners.

Pipeline (the method's Zhang-based calibration, extended to the whole rig at once):

1. **Intrinsics per sensor** with Zhang's method (``cv2.calibrateCamera``: closed form
   start, then Levenberg-Marquardt with distortion; ``cv2.calibrateCameraExtended`` for
   the standard deviations when the joint pass does not refine the intrinsics). Every
   sensor with Zhang's 3 views is calibrated (a stricter ``min_views`` leaves out those
   with fewer, with the reason).
2. **Initial poses**: each sensor's pose relative to the reference from the views it shares
   with an already placed sensor (chordal mean of rotations, median of translations),
   walking the co-visibility graph outward from the reference; each board pose from a
   sensor that saw it. A sensor that shares no view with any placed one is calibrated
   alone, on its own views (intrinsics with their sigma and verdict; its pose unknown:
   ``CalibrationResult.intrinsics_only``).
3. **Joint refinement** of every sensor pose ``T_rig_sensor``, every board pose
   ``T_rig_board`` and (optionally) every sensor's intrinsics and distortion, minimising the
   reprojection error of all corners of all sensors at once (analytic sparse Jacobian;
   Levenberg-Marquardt with a Schur complement on the board poses, calib.schur_lm, so an
   iteration costs time linear in the number of views), first with a robust loss; then
   outlier corners and views are flagged, each sensor's residuals are weighted by its own
   noise level, and a final least-squares pass runs on the inliers.
4. **Uncertainty**: the covariance ``s^2 (J^T J)^-1`` of the final pass, and a
   cluster-robust (per image, small-sample corrected) one, give a 1-sigma for every
   parameter; ``J^T J`` is formed from the sparse Jacobian (n x n, never the dense m x n
   matrix).
5. **Verdicts** (:mod:`calib.verdict`): per sensor and per eye and stereo pair, the
   1-sigmas of focal lengths and relative poses against the targets, and which views
   would lower them.

BLAS runs on one thread throughout (threadpoolctl, for the duration of
:func:`calibrate_rig`): beside other busy processes, OpenBLAS's spinning threads cost far
more than they gain on these small products. OpenCV's own threads are left alone: one or
two made no difference to Zhang's stage, idle or beside two busy processes (measured).
Everything per corner is vectorised (numpy); Python loops run over sensors, views or
images only.

The least-squares problem and its Jacobian are in :mod:`calib.rig_problem`, the
uncertainties in :mod:`calib.rig_uncertainty`, the verdicts in :mod:`calib.verdict`, the
result in :mod:`calib.rig_result`.
Inputs are plain arrays; nothing here reads files or prints. ``observations`` maps view
name -> sensor name -> (N, 2) float64 corners in canonical board order (calib.board); a
board with partial views (ChArUco) has NaN rows for the corners a view did not see.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.diagnosis import (
    fallback_reference,
    intrinsics_problem,
    screen_sensors,
    zhang_failure,
    zhang_rms_px,
)
from trifuse.calib.errors import CalibrationError
from trifuse.calib.numbers import is_int
from trifuse.calib.polarity import SensorPolarity
from trifuse.calib.rig import Eye
from trifuse.calib.rig_problem import BLAS_THREADS, CornerProblem, build_problem
from trifuse.calib.rig_result import CalibrationResult, CornerResiduals, Outlier, ViewError
from trifuse.calib.rig_uncertainty import covariance_estimates, rig_covariance, sensor_sigma
from trifuse.calib.schur_lm import SchurResult, least_squares_schur
from trifuse.calib.sensor_result import SensorResult
from trifuse.calib.transforms import invert, make_T, mean_rotation, rotation_from_rvec
from trifuse.calib.verdict import ZHANG_MIN_VIEWS, Verdict
from trifuse.calib.verdict_judge import judge_rig

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
        refine_intrinsics: refine intrinsics and distortion in the joint pass too (but a
            sensor whose views disagree with the others' keeps its own: :func:`_disagreeing`).
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
        min_views: fewest views with the board for a sensor to be calibrated. The default
            is Zhang's minimum (:data:`ZHANG_MIN_VIEWS`): a sensor seen in few views is
            calibrated, and its verdict (calib.verdict) says how well from its own
            uncertainty and what to capture next. A larger value is a strict mode: sensors
            with fewer views are left out with the reason.
    """

    reference: str | None = None
    refine_intrinsics: bool = True
    free_k3_modalities: tuple[str, ...] = ("color",)
    loss_scale_px: float = 1.0
    corner_outlier_sigmas: float = 5.0
    corner_outlier_min_px: float = 0.3
    view_outlier_factor: float = 3.0
    view_outlier_min_px: float = 0.3
    min_views: int = ZHANG_MIN_VIEWS

    def __post_init__(self) -> None:
        if not is_int(self.min_views) or self.min_views < ZHANG_MIN_VIEWS:
            raise CalibrationError(
                f"min_views: expected an integer of at least {ZHANG_MIN_VIEWS} (Zhang's "
                f"method needs {ZHANG_MIN_VIEWS} views of the board), got {self.min_views!r}"
            )


# The guard on the joint refinement of intrinsics (:func:`_disagreeing`), in sigmas of the
# sensor's own (Zhang) estimate: the joint sigma is no yardstick, it grows with the very
# residuals a disagreeing sensor inflates (cam_1 below: 50 px against 12 px alone). On
# caliscope's four webcams, whose cam_1 runs about a frame late, cam_1's fx moved 14 sigma,
# its cx 26 (fx 770 -> 939 px), with its RMS 10x its own (2.06 against 0.21 px); the other
# three moved at most 3.4 sigma with their RMS 1.8-4x their own; on the simulator's consistent
# views (8-30) at most 3 sigma and 1.04x.
GUARD_SIGMAS = 6.0
GUARD_RMS_RATIO = 3.0


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
        obs: view -> (N, 2) corners, pixels (NaN rows: not seen, on a partial view).
        board: the board.
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
    seen = [np.isfinite(obs[v][:, 0]) for v in views]  # all True but on partial views
    obj = [board.object_points()[m].astype(np.float32) for m in seen]
    img = [obs[v][m].astype(np.float32).reshape(-1, 1, 2) for v, m in zip(views, seen, strict=True)]
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
    """T_rig_sensor for every sensor reachable from ``reference`` through shared views, and
    why each other one is not placed."""
    placed = {reference: np.eye(4)}
    unplaced = dict.fromkeys(sensors, _unlinked(reference))
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


def _unlinked_sensors(reference: str, views: Mapping[str, set[str]]) -> list[str]:
    """The sensors (of ``views``: sensor -> its views) that no chain of shared views links to
    ``reference``, by name."""
    linked, todo = {reference}, [reference]
    while todo:
        a = todo.pop()
        for b in views:
            if b not in linked and views[a] & views[b]:
                linked.add(b)
                todo.append(b)
    return sorted(s for s in views if s not in linked)


def _unlinked(reference: str) -> str:
    """Why a sensor that no shared view links to ``reference`` has no pose."""
    return (
        f"shares no view with {reference} or any sensor placed from it: its pose to the rig "
        f"is unknown; capture views in which it and {reference} both see the board"
    )


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
            if not board.partial_views and not np.all(np.isfinite(c)):
                raise CalibrationError(f"view {view!r}, sensor {sensor!r}: corners contain NaN")
            if board.partial_views:  # NaN rows: corners not seen
                seen = np.all(np.isfinite(c), axis=1)
                if not seen.all():  # a row with one NaN coordinate is unseen as a whole
                    c = np.where(seen[:, None], c, np.nan)
                why = board.pose_problem(seen)
                if why is not None:
                    raise CalibrationError(f"view {view!r}, sensor {sensor!r}: {why}")
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
    judge: bool = True,
) -> CalibrationResult:
    """Calibrate every observed sensor's intrinsics and pose, and every board pose.

    Args:
        observations: view -> sensor -> (N, 2) corners (canonical order, full board; on
            a board with partial views, NaN rows for corners not seen, and at least
            :data:`calib.board.MIN_POSE_POINTS` not on one line).
        board: the checkerboard.
        specs: modality and image size of every sensor that may appear.
        options: see :class:`CalibrationOptions`.
        progress: called with (stage description, fraction done in [0, 1]).
        eyes: eye pairs to carry into the calibrated rig.
        judge: give the verdicts (``verdict``; a third of the time on 15 views: the advice
            tries candidate views); without, ``verdict`` is None (the cross-validation's
            halves need only the rig and its covariance).

    Raises:
        CalibrationError: nothing usable (no detections, the reference has too few views ...).
    """
    # BLAS on one thread throughout (threadpoolctl; numpy's, scipy's and OpenCV's own
    # OpenBLAS): every product here is small, and OpenBLAS's spinning threads cost more than
    # they gain. Measured on 40 views: 0.42 s idle, 0.87 s beside two busy processes; with
    # OpenBLAS's default 2 threads 0.56 s and 1.5 s.
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        return _calibrate_rig(observations, board, specs, options, progress, eyes, judge)


def _calibrate_rig(
    observations: Observations,
    board: Board,
    specs: Mapping[str, SensorSpec],
    options: CalibrationOptions | None,
    progress: Progress | None,
    eyes: Mapping[str, Eye] | None,
    judge: bool = True,
) -> CalibrationResult:
    """:func:`calibrate_rig`'s work (same arguments), with BLAS limited by the caller."""
    opts = options or CalibrationOptions()
    t0 = time.perf_counter()
    report = progress or (lambda _stage, _frac: None)
    by_sensor = _check_observations(observations, board, specs)
    reference = _choose_reference(opts, sorted(by_sensor), specs)

    excluded: dict[str, str] = {}
    for s in sorted(by_sensor):
        why = too_few_views(len(by_sensor[s]), opts.min_views)
        if why is not None:
            excluded[s] = why

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
    # A sensor that no chain of shared views links to the reference is left to be
    # calibrated alone (below): no view orders its corners against the reference's nor
    # places it. Only its intrinsics are screened here.
    report("board orientation per sensor", 0.38)
    lone = (
        _unlinked_sensors(reference, {s: set(by_sensor[s]) for s in intr})
        if reference in intr
        else []
    )
    for s in lone:
        rms = zhang_rms_px(by_sensor[s], intr[s], T_s_board[s], board)
        problem = intrinsics_problem(intr[s], specs[s].image_size, rms, len(by_sensor[s]))
        if problem is not None:
            excluded[s] = problem
    screened = [s for s in intr if s not in lone]
    screen = screen_sensors(
        {s: by_sensor[s] for s in screened},
        {s: specs[s].modality for s in screened},
        {s: specs[s].image_size for s in screened},
        {s: intr[s] for s in screened},
        {s: T_s_board[s] for s in screened},
        board,
    )
    excluded.update(screen.excluded)
    by_sensor = {**by_sensor, **screen.observations}
    T_s_board = screen.T_sensor_board
    candidates = [s for s in candidates if s not in excluded and s not in lone]
    alone_rms = {s: zhang_rms_px(by_sensor[s], intr[s], T_s_board[s], board) for s in candidates}
    notes = list(screen.notes)
    if reference in excluded:
        modalities = {s: specs[s].modality for s in specs}
        fallback = fallback_reference(reference, candidates, modalities, screen.anchor)
        if fallback is None and (unlinked := [s for s in lone if s not in excluded]):
            # Only sensors no view links to it are left: the rig frame is one of theirs,
            # calibrated from their views; the others keep their reasons.
            other = fallback_reference(reference, unlinked, modalities, None)
            rest = {
                v: {s: c for s, c in per.items() if s in unlinked}
                for v, per in observations.items()
            }
            result = _calibrate_rig(
                {v: per for v, per in rest.items() if per},
                board,
                specs,
                replace(opts, reference=other),
                progress,
                eyes,
                judge,
            )
            result.excluded_sensors = {**excluded, **result.excluded_sensors}
            result.notes.insert(
                0,
                f"the reference {reference} is not calibrated ({excluded[reference]}): the "
                f"rig frame is {other}'s instead",
            )
            return result
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
    unplaced.update({s: _unlinked(reference) for s in lone if s not in excluded})
    alone, alone_verdicts, alone_polarity, not_alone = _calibrate_alone(
        unplaced, by_sensor, board, specs, opts
    )
    excluded.update(not_alone)
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

    def solve(prob: CornerProblem, x0: np.ndarray, weights: np.ndarray, loss: str) -> SchurResult:
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

    # 3-4. Joint refinement; then the guard (:func:`_disagreeing`): a sensor whose intrinsics
    # the joint fit moved far beyond their uncertainty while fitting its views several times
    # worse than alone (the worst such sensor) keeps its own intrinsics, the others take theirs
    # from the joint refinement without its views, and the poses are refined again from the
    # start with every intrinsic fixed.
    own = dict(intr)
    start = (dict(T_rig_sensor), dict(T_rig_board))
    kept_own: dict[str, str] = {}
    while True:
        intr = {**own}
        T_rig_sensor, T_rig_board = dict(start[0]), dict(start[1])
        refine = opts.refine_intrinsics and not kept_own
        # 3a. Robust joint pass on everything.
        report("joint refinement (robust)", 0.5)
        prob = build_problem(sensors, views, by_sensor, board, free_dist, refine)
        x = solve(
            prob, prob.pack(T_rig_sensor, T_rig_board, intr), np.ones(len(sensors)), "soft_l1"
        ).x
        err = np.linalg.norm(prob.project(x, intr) - prob.uv, axis=1)

        # 3b. Outliers: corners beyond k sigma of their sensor; then views, judged by their
        # remaining corners (a view with many outlier corners is an outlier as a whole).
        sigma_s = np.array(
            [np.median(err[prob.s_idx == k]) / _RAYLEIGH_MEDIAN for k in range(len(sensors))]
        )
        limit = np.maximum(
            opts.corner_outlier_sigmas * sigma_s[prob.s_idx], opts.corner_outlier_min_px
        )
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
        report("uncertainty", 0.9)
        est = covariance_estimates(final, res.jac, res.fun)
        sig = est.sigma()

        Rs, ts, Rb, tb = final.poses(x)
        K4, D8 = final.unpack_intrinsics(x, intr)
        for k, s in enumerate(sensors):
            T_rig_sensor[s] = make_T(Rs[k], ts[k])
            intr[s] = Intrinsics(*(float(v) for v in K4[k]), tuple(float(c) for c in D8[k, :5]))
        board_poses = {v: make_T(Rb[vi], tb[vi]) for vi, v in enumerate(final.views)}

        if not refine:
            break
        joint_rms = {
            s: float(np.sqrt(np.mean(sq)))
            for k, s in enumerate(sensors)
            if (sq := np.sum((final.project(x, intr) - final.uv)[final.s_idx == k] ** 2, 1)).size
        }
        worst = _disagreeing(
            {s: own[s] for s in sensors},
            intr,
            joint_rms,
            alone_rms,
            lambda s: _intrinsics_per_sensor(
                by_sensor[s], board, specs[s], specs[s].modality in opts.free_k3_modalities
            )[2],
        )
        if worst is None:
            break
        s, why, std = worst
        kept_own[s] = why
        std_zhang[s] = std
        notes.append(f"{s} keeps the intrinsics of its own views: {why}")
        # The others' intrinsics: the joint refinement without its views (with them, the
        # others' absorb what its own cannot: caliscope's cam_2 fx went -8 %).
        rest = {v: {n: c for n, c in per.items() if n != s} for v, per in observations.items()}
        try:
            sub = _calibrate_rig(
                {v: per for v, per in rest.items() if per},
                board,
                specs,
                replace(opts, reference=None if s == reference else reference),
                None,
                None,
            ).sensors
        except CalibrationError:
            sub = {}  # the others keep their own too
        for n, r in sub.items():
            if n in own:
                own[n] = r.intrinsics
                sig_n = [r.sigma[k] for k in ("fx", "fy", "cx", "cy")] + r.sigma["distortion"]
                std_zhang[n] = np.array(sig_n, dtype=float)

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
        sigma = sensor_sigma(final, k, sig, std_zhang[s], free_dist[s])
        per_view = {v: e.rms_px for v, d in views_out.items() for n, e in d.items() if n == s}
        worst = max(per_view, key=per_view.__getitem__) if per_view else None
        results[s] = SensorResult(
            s,
            specs[s].modality,
            specs[s].image_size,
            intr[s],
            T_rig_sensor[s],
            sigma,
            views_detected=len(by_sensor[s]),
            views_used=len({final.views[i] for i in np.unique(final.v_idx[sel])}),
            rms_px=float(np.sqrt(np.mean(final_err[sel] ** 2))),
            worst_view=worst,
            zhang_rms_px=alone_rms[s],
            intrinsics_source=_source(s, kept_own, opts.refine_intrinsics),
        )
    # 5. Verdicts from the covariance (calib.verdict).
    report("verdicts", 0.95)
    cov = rig_covariance(final, est, x, intr, weights)
    verdict = (
        replace(
            judge_rig(cov, results, reference, dict(eyes or {}), board),
            intrinsics_only=alone_verdicts,
        )
        if judge
        else None
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
        polarity={**alone_polarity, **screen.polarity},  # the latter found with the others
        ordering=screen.ordering,
        notes=notes,
        covariance=cov,
        verdict=verdict,
        min_views=opts.min_views,
        intrinsics_only=alone,
        corners=CornerResiduals(
            list(prob.views),
            list(sensors),
            prob.v_idx,
            prob.s_idx,
            prob.c_idx,
            prob.uv,
            prob.uv - prob.project(x_all, intr),
            inlier,
        ),
    )


def _calibrate_alone(
    unplaced: Mapping[str, str],
    by_sensor: Mapping[str, dict[str, np.ndarray]],
    board: Board,
    specs: Mapping[str, SensorSpec],
    opts: CalibrationOptions,
) -> tuple[dict[str, SensorResult], dict[str, Verdict], dict[str, SensorPolarity], dict[str, str]]:
    """Each sensor not linked to the rig (``unplaced``: sensor -> why), calibrated on its
    own views as a capture of it alone would be (its own reference: the same joint
    refinement, outliers, sigmas and verdict); its pose is unknown.

    Returns:
        sensor -> its result (``pose_unknown`` set, ``T_rig_sensor`` NaN, no pose sigma),
        sensor -> its verdict (intrinsics judged, ``pose_unknown`` set), sensor -> its board
        polarity as found alone (a sensor sharing views with other unplaced ones has it from
        the screening with them too), and sensor -> why for any that cannot be calibrated alone
        either.
    """
    results: dict[str, SensorResult] = {}
    verdicts: dict[str, Verdict] = {}
    polarity: dict[str, SensorPolarity] = {}
    failed: dict[str, str] = {}
    for s, why in sorted(unplaced.items()):
        try:
            sub = _calibrate_rig(
                {v: {s: c} for v, c in by_sensor[s].items()},
                board,
                specs,
                replace(opts, reference=s),
                None,
                None,
            )
        except CalibrationError as exc:
            failed[s] = f"{why}; calibrated alone, it fails: {exc}"
            continue
        r = sub.sensors[s]
        pose = ("rotation_deg", "translation_m")
        results[s] = replace(
            r,
            T_rig_sensor=np.full((4, 4), np.nan),
            sigma={k: v for k, v in r.sigma.items() if k not in pose},
            intrinsics_source="own views, calibrated alone",
            pose_unknown=why,
        )
        if sub.verdict is not None:
            verdicts[s] = replace(sub.verdict.sensors[s], pose_unknown=why)
        polarity.update(sub.polarity)
    return results, verdicts, polarity, failed


def too_few_views(n_views: int, min_views: int = ZHANG_MIN_VIEWS) -> str | None:
    """Why a sensor seen in ``n_views`` views is not calibrated, or None: fewer than
    Zhang's minimum, or fewer than a stricter ``min_views``."""
    if n_views < ZHANG_MIN_VIEWS:
        return (
            f"board detected in {n_views} view(s); Zhang's method needs at least "
            f"{ZHANG_MIN_VIEWS} for intrinsics: too few views (show it the board in "
            f"{ZHANG_MIN_VIEWS - n_views} more)"
        )
    if n_views < min_views:
        return (
            f"board detected in {n_views} view(s); the strict minimum asked for is "
            f"{min_views} views (min views {min_views}): too few views (show it the board "
            f"in {min_views - n_views} more, or lower the minimum)"
        )
    return None


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
    prob: CornerProblem,
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


def _disagreeing(
    own: Mapping[str, Intrinsics],
    joint: Mapping[str, Intrinsics],
    joint_rms: Mapping[str, float],
    alone_rms: Mapping[str, float],
    own_std: Callable[[str], np.ndarray],
) -> tuple[str, str, np.ndarray] | None:
    """The sensor whose views disagree most with the others', if one does.

    A sensor disagrees when its joint RMS exceeds :data:`GUARD_RMS_RATIO` times its RMS alone
    and one of fx fy cx cy moved from its own estimate by more than :data:`GUARD_SIGMAS`
    times that estimate's 1-sigma.

    Args:
        own: sensor -> its own (Zhang) intrinsics, for the sensors refined jointly.
        joint: sensor -> the joint refinement's intrinsics.
        joint_rms, alone_rms: sensor -> RMS reprojection error jointly / alone, px.
        own_std: sensor -> (9,) Zhang's 1-sigma of fx fy cx cy k1 k2 p1 p2 k3 (called only
            for the sensors whose RMS grew: it costs a calibration).

    Returns:
        (sensor, the reason in words, its own (9,) 1-sigma), or None.
    """
    worst: tuple[float, str, str, np.ndarray] | None = None
    for s in own:
        ratio = joint_rms[s] / max(alone_rms[s], 1e-9)
        if ratio <= GUARD_RMS_RATIO:
            continue
        std = own_std(s)
        a = np.array([own[s].fx, own[s].fy, own[s].cx, own[s].cy])
        b = np.array([joint[s].fx, joint[s].fy, joint[s].cx, joint[s].cy])
        z = np.abs(b - a) / std[:4]
        j = int(np.argmax(z))
        if z[j] > GUARD_SIGMAS and (worst is None or z[j] > worst[0]):
            name = ("fx", "fy", "cx", "cy")[j]
            why = (
                f"the joint refinement moved its {name} {z[j]:.0f}σ ({a[j]:.1f} -> {b[j]:.1f} "
                f"px) and its RMS to {ratio:.0f}x its own ({joint_rms[s]:.2f} against "
                f"{alone_rms[s]:.2f} px): its views disagree with the others'"
            )
            worst = (float(z[j]), s, why, std)
    return None if worst is None else worst[1:]


def _source(sensor: str, kept_own: Mapping[str, str], refined: bool) -> str:
    """Where ``sensor``'s intrinsics come from, in words (the report's intrinsics_source)."""
    if sensor in kept_own:
        return f"own views ({kept_own[sensor]})"
    if not refined:
        return "own views"
    if kept_own:
        return "joint refinement without " + ", ".join(f"{n}'s views" for n in kept_own)
    return "joint refinement"
