"""How a calibration is judged (:mod:`calib.verdict`): its figures as linear functions of
the sensors' parameters (1-sigma from the covariance of :mod:`calib.rig_uncertainty`), their
grades, and the advice: what more views would do.

**Advice** is derived from the information matrix, not from the number of views: candidate
board poses of a few kinds (tilted about the vertical axis, tilted about the horizontal
axis, in the image corners, nearer, farther; :data:`calib.verdict.KINDS`) are placed in
front of the sensor, projected into every sensor that would see the whole board with the
current estimates, and their Jacobian is added to the information of the sensors' parameters
(the board pose eliminated). Views are added one at a time, each time the one that lowers
the worst sigma / target ratio most, until every target is met or :data:`MAX_MORE_VIEWS`
views have been added: the advice names how many views that took and of which kinds.
Predicted sigmas scale the current ones by the change of the independent-errors estimate, so
the cluster-robust inflation carries over.

Pure: arrays in, values out.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg

from trifuse.calib.board import Board
from trifuse.calib.rig import Eye
from trifuse.calib.rig_compare import FOCAL_TARGET, POSE_TARGET
from trifuse.calib.rig_problem import CornerProblem
from trifuse.calib.rig_uncertainty import RigCovariance
from trifuse.calib.sensor_result import SensorResult
from trifuse.calib.transforms import invert, make_T, rotations_from_rvecs, rvec_from_rotation
from trifuse.calib.verdict import (
    DISAGREEMENT,
    GOOD,
    MAX_MORE_VIEWS,
    POOR,
    POOR_FACTOR,
    SIGMA_SHARE,
    USABLE,
    Figure,
    RigVerdict,
    Verdict,
)

_ROTATION_AXES = ("horizontal", "vertical", "optical")
_TRANSLATION_AXES = ("sideways", "vertical", "depth")
_MIN_SPACING_PX = 8.0  # corners nearer than this in the image: the detector fails
_MARGIN = 0.03  # share of the image kept free around a candidate board


# -- figures as linear functions of the sensors' parameters ---------------------------------


@dataclass
class FigureSpec:
    """A figure as rows of a Jacobian on the kept parameters (RigCovariance.columns):
    ``sigma`` combines the rows' variances (``norm``: their sum, ``max``: the largest),
    times ``unit_scale``. ``fallback``: the sigma when there are no rows (intrinsics held
    fixed: Zhang's own sigma, not predicted)."""

    what: str
    unit: str
    target: float | None
    rows: np.ndarray | None  # (k, p)
    combine: str
    unit_scale: float
    axis_names: tuple[str, str, str] | None = None
    fallback: float | None = None

    def variances(self, cov: np.ndarray) -> np.ndarray:
        """(k,) variances of the rows under ``cov`` (none without rows)."""
        rows = self.rows if self.rows is not None else np.zeros((0, len(cov)))
        return np.einsum("ij,jk,ik->i", rows, cov, rows)

    def combined(self, var: np.ndarray) -> float:
        v = float(np.sum(var)) if self.combine == "norm" else float(np.max(var))
        return float(np.sqrt(max(v, 0.0))) * self.unit_scale

    def figure(self, c: RigCovariance) -> tuple[Figure, float]:
        """The figure now, and its independent-errors sigma alone (0 without rows: not
        predicted)."""
        if self.rows is None:
            return Figure(self.what, float(self.fallback or 0.0), self.unit, self.target), 0.0
        v_iid, v_cl = self.variances(c.iid), self.variances(c.cluster)
        sigma = max(self.combined(v_iid), self.combined(v_cl))
        axes = None
        if self.axis_names is not None:
            axes = tuple(float(a) for a in np.sqrt(np.maximum(v_iid, v_cl)) * self.unit_scale)
        fig = Figure(self.what, sigma, self.unit, self.target, axes, self.axis_names)  # type: ignore[arg-type]
        return fig, self.combined(v_iid)


def _T_rig(prob: CornerProblem, x: np.ndarray, sensor: str) -> np.ndarray:
    k = prob.sensors.index(sensor)
    if k == 0:
        return np.eye(4)
    p = x[6 * (k - 1) : 6 * k]
    return make_T(rotations_from_rvecs(p[:3])[0], p[3:])


def _pose_rows(c: RigCovariance, a: str, b: str) -> np.ndarray:
    """(6, p): derivatives of the error of ``T_a_b`` (rotation vector of ``R(x) R0^T`` in
    radians, translation change in metres, both in frame a) by the kept parameters
    (central differences over the two sensors' pose parameters)."""
    prob, x0 = c.problem, c.x
    T0 = invert(_T_rig(prob, x0, a)) @ _T_rig(prob, x0, b)
    rows = np.zeros((6, len(c.columns)))
    h = 1e-6
    for s in (a, b):
        k = prob.sensors.index(s)
        if k == 0:
            continue
        for j in range(6 * (k - 1), 6 * k):
            d = []
            for sign in (1.0, -1.0):
                x = x0.copy()
                x[j] += sign * h
                T = invert(_T_rig(prob, x, a)) @ _T_rig(prob, x, b)
                d.append(np.r_[rvec_from_rotation(T[:3, :3] @ T0[:3, :3].T), T[:3, 3] - T0[:3, 3]])
            rows[:, c.column(j)] += (d[0] - d[1]) / (2 * h)
    return rows


def pose_specs(
    c: RigCovariance, a: str, b: str, modalities: Mapping[str, str], kind: str
) -> list[FigureSpec]:
    rows = _pose_rows(c, a, b)
    rot_t = max(POSE_TARGET[modalities[a]][0], POSE_TARGET[modalities[b]][0]) * SIGMA_SHARE
    tr_t = max(POSE_TARGET[modalities[a]][1], POSE_TARGET[modalities[b]][1]) * SIGMA_SHARE
    rot_what = "rotation" if kind == "pair" else f"rotation to {a}"
    tr_what = "baseline" if kind == "pair" else f"translation to {a}"
    return [
        FigureSpec(rot_what, "°", rot_t, rows[:3], "norm", float(np.degrees(1.0)), _ROTATION_AXES),
        FigureSpec(tr_what, "mm", 1000 * tr_t, rows[3:], "norm", 1000.0, _TRANSLATION_AXES),
    ]


def sensor_specs(
    c: RigCovariance, s: SensorResult, reference: str, modalities: Mapping[str, str]
) -> list[FigureSpec]:
    prob = c.problem
    k = prob.sensors.index(s.name)
    i = s.intrinsics
    focal_t = 100 * FOCAL_TARGET[s.modality] * SIGMA_SHARE
    if k in prob.intr_slices:
        start = prob.intr_slices[k].start
        p = len(c.columns)
        focal = np.zeros((2, p))
        focal[0, c.column(start)] = 100.0 / i.fx
        focal[1, c.column(start + 1)] = 100.0 / i.fy
        centre = np.zeros((2, p))
        centre[0, c.column(start + 2)] = 1.0
        centre[1, c.column(start + 3)] = 1.0
        specs = [
            FigureSpec("focal length", "%", focal_t, focal, "max", 1.0),
            FigureSpec("principal point", "px", None, centre, "max", 1.0),
        ]
    else:  # intrinsics held fixed: Zhang's own sigma, not predicted
        sg = s.sigma
        rel = 100 * max(sg["fx"] / i.fx, sg["fy"] / i.fy)
        specs = [
            FigureSpec("focal length", "%", focal_t, None, "max", 1.0, fallback=rel),
            FigureSpec(
                "principal point", "px", None, None, "max", 1.0, fallback=max(sg["cx"], sg["cy"])
            ),
        ]
    if s.name != reference:
        specs += pose_specs(c, reference, s.name, modalities, "sensor")
    return specs


# -- candidate views: what more views would do ----------------------------------------------


@dataclass(frozen=True)
class _Candidate:
    """A view the advice may suggest: its kind, the sensor the board is placed in front
    of, the board pose ``T_rig_board`` (4, 4) and the (p, p) information it would add."""

    kind: str
    sensor: str
    T_rig_board: np.ndarray
    information: np.ndarray


def _rot(axis: int, deg: float) -> np.ndarray:
    r = np.zeros(3)
    r[axis] = np.radians(deg)
    return rotations_from_rvecs(r)[0]


def _inside(uv: np.ndarray, size: tuple[int, int], margin_px: float = 1.0) -> bool:
    w, h = size
    return bool(
        np.all(np.isfinite(uv))
        and np.all(uv >= margin_px)
        and np.all(uv[:, 0] <= w - 1 - margin_px)
        and np.all(uv[:, 1] <= h - 1 - margin_px)
    )


def _candidates(s: SensorResult, board: Board, distance_m: float) -> list[tuple[str, np.ndarray]]:
    """(kind, T_sensor_board) of candidate views in front of sensor ``s``."""
    obj = board.object_points()
    centre_b = 0.5 * (obj.min(axis=0) + obj.max(axis=0))
    extent = obj.max(axis=0) - obj.min(axis=0)
    intr, (w, h) = s.intrinsics, s.image_size
    margin = _MARGIN * min(w, h)

    def fill(frac: float) -> float:  # distance at which the board spans frac of the image
        return max(extent[0] * intr.fx / (frac * w), extent[1] * intr.fy / (frac * h))

    def place(R: np.ndarray, pixel: tuple[float, float], z: float) -> np.ndarray | None:
        ray = intr.normalized(np.array(pixel, dtype=np.float64))
        for _ in range(25):
            T = make_T(R, np.r_[ray * z, z] - R @ centre_b)
            if _inside(intr.project(obj @ T[:3, :3].T + T[:3, 3]), (w, h), margin):
                return T
            z *= 1.1
        return None

    steps = np.linalg.norm(np.diff(obj, axis=0), axis=1)
    spacing = float(np.min(steps[steps > 0]))  # neighbouring corners, metres
    far_limit = spacing * min(intr.fx, intr.fy) / _MIN_SPACING_PX
    pp = (intr.cx, intr.cy)
    out: list[tuple[str, np.ndarray | None]] = []
    z_tilt = max(distance_m, fill(0.7))
    for a in (25.0, -25.0, 45.0, -45.0):
        out.append(("tilt_vertical", place(_rot(1, a), pp, z_tilt)))
        out.append(("tilt_horizontal", place(_rot(0, a), pp, z_tilt)))
    z_c = max(distance_m, fill(0.45))
    hw, hh = extent[0] * intr.fx / (2 * z_c), extent[1] * intr.fy / (2 * z_c)
    for u in (margin + hw, w - 1 - margin - hw):
        for v in (margin + hh, h - 1 - margin - hh):
            out.append(("corners", place(np.eye(3), (u, v), z_c)))
    tilts = [_rot(0, 15.0), _rot(0, -15.0), _rot(1, 15.0), _rot(1, -15.0)]
    z_near = fill(0.85)
    if z_near < 0.8 * distance_m:
        out += [("nearer", place(R, pp, z_near)) for R in tilts]
    z_far = min(1.7 * distance_m, far_limit)
    if z_far > 1.2 * distance_m:
        out += [("farther", place(R, pp, z_far)) for R in tilts]
    return [(k, T) for k, T in out if T is not None]


def _candidate_information(
    c: RigCovariance,
    sensors: Mapping[str, SensorResult],
    board: Board,
    subject: str,
) -> list[_Candidate]:
    """Every candidate view in front of ``subject``, with the information it would add
    (:func:`pose_information`)."""
    cands = _candidates(sensors[subject], board, _median_distance(c, subject, board))
    poses = [sensors[subject].T_rig_sensor @ T for _, T in cands]
    infos = pose_information(c, sensors, board, poses)
    return [
        _Candidate(kind, subject, T, info)
        for (kind, _), T, info in zip(cands, poses, infos, strict=True)
        if info is not None
    ]


def pose_information(
    c: RigCovariance,
    sensors: Mapping[str, SensorResult],
    board: Board,
    poses: list[np.ndarray],
) -> list[np.ndarray | None]:
    """The (p, p) information each board pose ``T_rig_board`` (4, 4) of ``poses`` would
    add to the kept parameters (its own board pose eliminated), from every sensor that
    would see the whole board with the current estimates (None: no sensor would). One
    Jacobian for all of them."""
    prob = c.problem
    obj = board.object_points()
    n = len(obj)
    kept, s_idx, v_idx, uv = [], [], [], []
    for i, T_rig_board in enumerate(poses):
        seen = []
        for k, name in enumerate(prob.sensors):
            s = sensors[name]
            T_s = invert(s.T_rig_sensor) @ T_rig_board
            p = s.intrinsics.project(obj @ T_s[:3, :3].T + T_s[:3, 3])
            if _inside(p, s.image_size):
                seen.append((k, p))
        if not seen:
            continue
        for k, p in seen:
            s_idx.append(np.full(n, k))
            v_idx.append(np.full(n, len(kept)))
            uv.append(p)
        kept.append(i)
    out: list[np.ndarray | None] = [None] * len(poses)
    if not kept:
        return out
    s_all = np.concatenate(s_idx)
    hyp = CornerProblem(
        prob.sensors,
        [f"next{i}" for i in range(len(kept))],
        s_all,
        np.concatenate(v_idx),
        np.tile(np.arange(n), len(s_all) // n),
        np.tile(obj, (len(s_all) // n, 1)),
        np.concatenate(uv),
        prob.free_dist,
        prob.refine_intrinsics,
    )
    board_x = np.concatenate(
        [np.r_[rvec_from_rotation(poses[i][:3, :3]), poses[i][:3, 3]] for i in kept]
    )
    x = np.r_[c.x[: prob.off_board], board_x, c.x[prob.off_intr :]]
    J = hyp.jacobian(x, c.fixed, c.weights[hyp.s_idx])
    keep = np.r_[np.arange(hyp.off_board), np.arange(hyp.off_intr, hyp.n_params)]
    J_keep, J_board = J[:, keep].tocsr(), J[:, hyp.off_board : hyp.off_intr].tocsr()
    rows = np.r_[0, np.cumsum(np.bincount(hyp.v_idx, minlength=len(kept)))] * 2
    for j, i in enumerate(kept):
        Js = J_keep[rows[j] : rows[j + 1]].toarray()
        Jb = J_board[rows[j] : rows[j + 1], 6 * j : 6 * j + 6].toarray()
        W = Js.T @ Jb
        out[i] = Js.T @ Js - W @ np.linalg.pinv(Jb.T @ Jb, hermitian=True) @ W.T
    return out


def _row_variances(information: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(k,) diagonal of ``rows inv(information) rows^T`` (rows (k, p)), through a
    Cholesky factor of the equilibrated matrix (pseudo-inverse if singular)."""
    d = np.sqrt(np.clip(np.diag(information), 1e-300, None))
    As = information / d[:, None] / d[None, :]
    Rs = rows / d[None, :]
    try:
        X = scipy.linalg.cho_solve(scipy.linalg.cho_factor(As), Rs.T)
    except np.linalg.LinAlgError:
        X = np.linalg.pinv(As, hermitian=True) @ Rs.T
    return np.einsum("ij,ji->i", Rs, X)


def predictor(
    c: RigCovariance, specs: list[FigureSpec], now: list[Figure], iid_now: list[float]
) -> Callable[[np.ndarray], list[Figure]]:
    """The judged figures of ``specs`` (``now``: their current figures, ``iid_now`` their
    independent-errors sigmas) predicted under another (p, p) information of the kept
    parameters: each current sigma times the ratio of its independent-errors sigma under
    that information and now (:func:`_more_views` says why); figures without a Jacobian
    keep their sigma."""
    judged = [
        (spec, fig, base)
        for spec, fig, base in zip(specs, now, iid_now, strict=True)
        if spec.target is not None and base > 0
    ]
    fixed = [f for f, base in zip(now, iid_now, strict=True) if f.target is not None and base <= 0]
    rows = np.concatenate([spec.rows for spec, _, _ in judged]) if judged else None
    ends = np.cumsum([len(spec.rows) for spec, _, _ in judged])

    def predict(information: np.ndarray) -> list[Figure]:
        out = list(fixed)
        if rows is not None:
            var = np.split(_row_variances(information, rows) * c.scale, ends[:-1])
            for (spec, fig, base), v in zip(judged, var, strict=True):
                out.append(replace(fig, sigma=fig.sigma * spec.combined(v) / base, axes=None))
        return out

    return predict


def _more_views(
    c: RigCovariance,
    specs: list[FigureSpec],
    now: list[Figure],
    iid_now: list[float],
    candidates: list[_Candidate],
) -> tuple[int | None, list[_Candidate], Figure | None]:
    """Greedy: add the candidate view that lowers the worst sigma / target ratio most,
    until every judged sigma meets its target or :data:`MAX_MORE_VIEWS` were added.

    A figure's predicted sigma is its current one times the ratio of its independent-errors
    sigma with and without the views: the cluster-robust excess is carried along whole
    (a model in which it fades with the views' leverage predicted sigmas 1-4.5 times too
    small on simulated captures; this one within a factor of two either way). Figures
    without a Jacobian keep their sigma. Returns (views added, None if that did not
    suffice; the views chosen, in order; the judged figure with the worst ratio at the
    end, with its predicted sigma).
    """
    predict = predictor(c, specs, now, iid_now)

    def worst(information: np.ndarray) -> Figure | None:
        return max(predict(information), key=lambda f: f.ratio, default=None)

    info = c.information.copy()
    reached = worst(info)
    picks: list[_Candidate] = []
    while reached is not None and reached.ratio > 1.0 and len(picks) < MAX_MORE_VIEWS:
        scored = [(worst(info + cand.information), k) for k, cand in enumerate(candidates)]
        best = min(scored, key=lambda fk: fk[0].ratio, default=None)
        if best is None or best[0].ratio > reached.ratio * (1 - 1e-4):
            break  # no candidate helps
        reached, k = best
        info += candidates[k].information
        picks.append(candidates[k])
    done = reached is None or reached.ratio <= 1.0
    return (len(picks) if done else None), picks, reached


def _grade(figures: list[Figure]) -> str:
    worst = max((f.ratio for f in figures if f.target is not None), default=0.0)
    if worst <= 1.0:
        return GOOD
    return POOR if worst > POOR_FACTOR else USABLE


def _median_distance(c: RigCovariance, sensor: str, board: Board) -> float:
    """Median distance (m) from ``sensor`` to the centre of the board over its views."""
    prob = c.problem
    k = prob.sensors.index(sensor)
    views = np.unique(prob.v_idx[prob.s_idx == k])
    obj = board.object_points()
    centre = 0.5 * (obj.min(axis=0) + obj.max(axis=0))
    _Rs, _ts, Rb, tb = prob.poses(c.x)
    T_s = _T_rig(prob, c.x, sensor)
    P = np.einsum("vij,j->vi", Rb[views], centre) + tb[views]
    Q = (P - T_s[:3, 3]) @ T_s[:3, :3]
    return float(np.median(np.linalg.norm(Q, axis=1)))


class _Judge:
    """Verdicts of one calibration; candidate views' information computed once per
    sensor they are placed in front of."""

    def __init__(self, c: RigCovariance, sensors: Mapping[str, SensorResult], board: Board) -> None:
        self.c, self.sensors, self.board = c, sensors, board
        self.modalities = {n: s.modality for n, s in sensors.items()}
        self._cache: dict[str, list[_Candidate]] = {}

    def candidates(self, subjects: tuple[str, ...]) -> list[_Candidate]:
        out = []
        for s in dict.fromkeys(subjects):
            if s not in self._cache:
                self._cache[s] = _candidate_information(self.c, self.sensors, self.board, s)
            out += self._cache[s]
        return out

    def disagreement(self, names: tuple[str, ...]) -> str | None:
        """Why one of ``names`` disagrees with the other sensors (:data:`DISAGREEMENT`)."""
        factor, margin = DISAGREEMENT
        for name in names:
            s = self.sensors[name]
            alone = s.zhang_rms_px
            if alone is None or len(self.sensors) < 2:
                continue
            if s.rms_px > factor * alone and s.rms_px > alone + margin:
                return (
                    f"{name}'s corners fit one camera alone (RMS {alone:.2f} px) but not the "
                    f"other sensors' in the same views ({s.rms_px:.2f} px): likely the "
                    "sensors moved relative to each other between views, or did not capture "
                    "at the same moment; fix the mount or synchronise the captures, then "
                    "capture again"
                )
        return None

    def verdict(
        self,
        label: str,
        names: tuple[str, ...],
        specs: list[FigureSpec],
        subjects: tuple[str, ...],
        baseline: tuple[float, float] | None = None,
    ) -> Verdict:
        """The verdict on ``specs`` of the sensor or pair ``names``; candidate views are
        placed in front of each of ``subjects``."""
        current = [spec.figure(self.c) for spec in specs]
        figures = [f for f, _ in current]
        grade = _grade(figures)
        disagreement = self.disagreement(names) if grade != GOOD else None
        more, picks, predicted = 0, [], None
        if disagreement is not None:
            more = None  # more views will not mend it
        elif grade != GOOD:
            iid_now = [k for _, k in current]
            more, picks, predicted = _more_views(
                self.c, specs, figures, iid_now, self.candidates(subjects)
            )
        by_kind = Counter(p.kind for p in picks).most_common(2)
        views = tuple(
            (k, tuple(dict.fromkeys(p.sensor for p in picks if p.kind == k)), n) for k, n in by_kind
        )
        length, sig_len = baseline if baseline is not None else (None, None)
        return Verdict(
            label,
            names,
            grade,
            tuple(figures),
            more,
            views,
            predicted,
            length,
            sig_len,
            tuple(p.T_rig_board for p in picks),
            disagreement,
        )

    def sensor(self, s: SensorResult, reference: str) -> Verdict:
        specs = sensor_specs(self.c, s, reference, self.modalities)
        subjects = (s.name,) if s.name == reference else (s.name, reference)
        return self.verdict(s.name, (s.name,), specs, subjects)

    def pair(self, what: str, a: str, b: str) -> Verdict:
        c = self.c
        specs = pose_specs(c, a, b, self.modalities, "pair")
        t = (invert(self.sensors[a].T_rig_sensor) @ self.sensors[b].T_rig_sensor)[:3, 3]
        length = float(np.linalg.norm(t))
        row = (t / length if length > 0 else np.zeros(3)) @ _pose_rows(c, a, b)[3:]
        sig_len = float(np.sqrt(max(row @ c.iid @ row, row @ c.cluster @ row, 0.0)))
        label = f"{what} ({a} – {b})"
        return self.verdict(label, (a, b), specs, (a, b), (1000 * length, 1000 * sig_len))


def judge_rig(
    cov: RigCovariance,
    sensors: Mapping[str, SensorResult],
    reference: str,
    eyes: Mapping[str, Eye],
    board: Board,
) -> RigVerdict:
    """Verdicts on every calibrated sensor and on the eye and stereo pairs.

    Args:
        cov: the calibration's joint covariance (calib.rig_uncertainty.rig_covariance).
        sensors: the calibrated sensors (intrinsics, ``T_rig_sensor``, sigma).
        reference: the rig's reference sensor.
        eyes: eye name -> (colour, thermal); pairs with an uncalibrated sensor are skipped.
        board: the board (candidate views are of it).
    """
    judge = _Judge(cov, sensors, board)
    out = {name: judge.sensor(s, reference) for name, s in sensors.items()}
    calibrated = {
        n: e for n, e in sorted(eyes.items()) if e.color in sensors and e.thermal in sensors
    }
    pairs = [judge.pair(f"{n} eye", e.color, e.thermal) for n, e in calibrated.items()]
    if len(calibrated) >= 2:
        a, b = (e.color for e in list(calibrated.values())[:2])
        pairs.append(judge.pair("stereo", a, b))
    return RigVerdict(out, pairs)
