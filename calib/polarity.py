"""Which way round each sensor sees the board's squares, found from the data.

A checkerboard with odd x even inner corners is asymmetric under a half turn only through
its square colours (calib.board). A colour camera sees the printed colours (black is dark),
but in a thermal image the squares' contrast depends on the board (painted squares on bare
aluminium read hot when heated and cold when cooled) and in a TOF amplitude image on the
inks' near-infrared reflectance. A detector that assumes the wrong polarity returns the
half-turned ordering: the corner list reversed (label ``i`` on corner ``N - 1 - i``), so
every board pose it yields is turned by a half turn about the board normal through the
board's centre (:func:`half_turn`).

The ordering is therefore decided by geometry. For a sensor ``s`` and an anchor ``a`` (a
colour camera when there is one) that saw the board in the same views, each view gives a
relative pose ``T_a_s = T_a_board @ inv(T_s_board)`` for the ordering as detected and
``T_a_board @ H @ inv(T_s_board)`` for its half turn (``H`` = :func:`half_turn`; reversing
the labels is a valid relabelling of the board, so one Zhang calibration serves both).
The right ordering's relative poses agree across views; the wrong one's scatter, because
the half turn is about a different axis in every view.

Agreement is measured where it matters and where the per-view poses are reliable: the
board's corners as the sensor saw them are moved into the anchor's frame through two
relative poses, and the angle between the two positions is taken as seen from the
anchor's centre (RMS over the corners, degrees). Per-view pose errors that are large for a
small board (its distance, its tilt) move corners nearly along the anchor's lines of sight
and hardly count; a half turn moves every corner across the board, about ``2 r / d``
radians for a corner ``r`` from the centre at distance ``d`` (what :attr:`OrderingCheck.
half_turn_deg` reports, several degrees at calibration distances).

A board that looks the same turned has no polarity to find: its views are ordered by the
same vote in calib.board_ordering (:func:`calib.board_ordering.order_views`).

Pure: arrays in, values out (calib.diagnosis applies the decisions in a calibration; the
console's live board watch uses :func:`calib.board_ordering.orient_to_pose`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.detect import THERMAL_BLACK_IS_HOT, Detection, detect_board
from trifuse.calib.transforms import make_T

AGREE_FRACTION_OF_HALF_TURN = 0.1
"""A view agrees with a consensus pose when its disagreement is below this fraction of what
a half turn would cause in that view (:attr:`OrderingCheck.half_turn_deg`). Measured on
simulated captures: the right ordering's views disagree by 0.01-0.15 deg, a half turn makes
13-60 deg; a board found one square off (a wrong board size) disagrees by about 0.16 of a
half turn and does not agree."""
MIN_AGREEING_FRACTION = 0.6
"""An ordering is consistent when at least this fraction of the shared views agree with
one relative pose (the rest may be stray detections)."""
MIN_SHARED_VIEWS = 3
"""Fewest views a sensor must share with an anchor for its ordering to be decided."""

TOF_BLACK_IS_DARK = True
"""What a detector assumes of TOF amplitude images: black squares dark (low near-infrared
reflectance)."""

AS_DETECTED, HALF_TURNED = 0, 1


# -- the half turn ---------------------------------------------------------------------------


def half_turn(board: Board) -> np.ndarray:
    """(4, 4) board-frame transform of a half turn about the board normal through the centre
    of its inner corners: it maps corner ``i`` onto corner ``N - 1 - i``.

    A pose ``T_s_board`` of corners labelled one way is ``T_s_board @ half_turn(board)`` for
    the same corners labelled the other way (the list reversed). Its own inverse.
    """
    cx = (board.cols - 1) * board.square_size_m
    cy = (board.rows - 1) * board.square_size_m
    return make_T(np.diag([-1.0, -1.0, 1.0]), (cx, cy, 0.0))


def reverse_corners(corners: np.ndarray) -> np.ndarray:
    """(N, 2) corners relabelled by the half turn: corner ``i`` becomes ``N - 1 - i``."""
    return np.ascontiguousarray(np.asarray(corners)[::-1])


# -- what the detector assumed, in words -------------------------------------------------------


def detected_as(board: Board, modality: str) -> bool:
    """Whether the detector took the board's black squares as hot (thermal) or dark (TOF,
    colour): the ``board.yaml`` override when set, else the detector's default."""
    if modality == "thermal":
        key = board.thermal_black_is_hot
        return THERMAL_BLACK_IS_HOT if key is None else key
    if modality == "tof":
        key = board.tof_black_is_dark
        return TOF_BLACK_IS_DARK if key is None else key
    return True


def override(board: Board, modality: str) -> bool | None:
    """The ``board.yaml`` polarity key of ``modality`` (None: found from the data)."""
    if modality == "thermal":
        return board.thermal_black_is_hot
    if modality == "tof":
        return board.tof_black_is_dark
    return None


def override_key(modality: str) -> str | None:
    """The name of ``modality``'s polarity key in ``board.yaml``."""
    return {"thermal": "thermal_black_is_hot", "tof": "tof_black_is_dark"}.get(modality)


def polarity_words(modality: str, black_is_hot_or_dark: bool) -> str:
    """``black squares hot`` / ``cold`` (thermal), ``dark`` / ``bright`` (colour, TOF)."""
    if modality == "thermal":
        return "black squares hot" if black_is_hot_or_dark else "black squares cold"
    return "black squares dark" if black_is_hot_or_dark else "black squares bright"


def detect_board_configured(image: np.ndarray, board: Board, modality: str) -> Detection:
    """:func:`calib.detect.detect_board` with the board's polarity overrides applied.

    Thermal images are searched with ``board.thermal_black_is_hot`` (the detector's
    default when None); TOF amplitude corners are reversed when ``board.tof_black_is_dark``
    is false (black squares bright in amplitude: the detector takes dark squares as black).
    Without overrides this is ``detect_board`` itself; the calibration finds the polarity.
    A ChArUco board or a circle grid has its points labelled by the pattern: never reversed.

    Args:
        image, board, modality: as :func:`calib.detect.detect_board`.
    """
    if modality == "thermal":
        hot = detected_as(board, modality)
        return detect_board(image, board, modality, thermal_black_is_hot=hot)
    det = detect_board(image, board, modality)
    turnable = board.pattern == "checkerboard"  # ChArUco, circles: no polarity to apply
    if modality == "tof" and det.found and turnable and not detected_as(board, modality):
        return Detection(reverse_corners(det.corners), None, det.method)
    return det


# -- agreement of relative poses -----------------------------------------------------------


def apply_T(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Points ``P`` (n, M, 3) mapped by per-view transforms ``T`` (n, 4, 4) or by one
    transform per hypothesis and view (J, n, 4, 4) -> (..., M, 3)."""
    return np.matmul(P, np.swapaxes(T[..., :3, :3], -1, -2)) + T[..., None, :3, 3]


# Elements per coordinate array of :func:`_angle_deg_each`'s chunks (about 1 MB): small
# enough to stay in cache through the dozen operations on them, which halved its time.
_CHUNK_ELEMENTS = 1 << 17


def _angle_deg_each(moved: np.ndarray, P: np.ndarray, T: np.ndarray) -> np.ndarray:
    """:func:`angle_deg` between every view's candidates and every transform's mapping.

    Args:
        moved: (n, K, M, 3) each view's corners moved by its K candidate transforms.
        P: (n, M, 3) each view's corners.
        T: (J, 4, 4) transforms tried on every view's corners.

    Returns:
        (J, n, K) degrees: ``angle_deg(moved[None], apply_T(T[:, None], P[None])[:, :, None])``
        without its (J, n, K, M, 3) intermediates: a chunk of transforms at a time, their
        mapped copies of all corners from one matrix product (n M, 3) x (3, 3 J), one
        (n, 1, M, J) array per coordinate, the angles formed coordinate by coordinate.
    """
    n, K, M = moved.shape[:3]
    J = len(T)
    out = np.empty((J, n, K))
    ax, ay, az = (np.ascontiguousarray(moved[..., i])[..., None] for i in range(3))
    flat = P.reshape(n * M, 3)
    chunk = max(1, _CHUNK_ELEMENTS // (n * K * M))
    for j0 in range(0, J, chunk):
        Tc = T[j0 : j0 + chunk]
        Jc = len(Tc)
        G = flat @ np.concatenate([Tc[:, i, :3] for i in range(3)]).T  # (n M, 3 Jc)
        bx, by, bz = (
            G[:, i * Jc : (i + 1) * Jc].reshape(n, 1, M, Jc) + Tc[:, i, 3] for i in range(3)
        )
        cross = ay * bz - az * by
        cross *= cross
        c = az * bx - ax * bz
        cross += c * c
        c = ax * by - ay * bx
        cross += c * c
        np.sqrt(cross, out=cross)
        dot = ax * bx + ay * by + az * bz
        ang = np.arctan2(cross, dot, out=cross)
        ang *= ang
        out[j0 : j0 + Jc] = np.degrees(np.sqrt(np.mean(ang, axis=2))).transpose(2, 0, 1)
    return out


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """RMS over the last-but-one axis of the angle (degrees) between vectors ``a`` and ``b``
    (..., M, 3) seen from the origin (arrays broadcast against each other)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    cross = np.sqrt(cx * cx + cy * cy + cz * cz)
    dot = ax * bx + ay * by + az * bz
    ang = np.arctan2(cross, dot)
    ang *= ang
    return np.degrees(np.sqrt(np.mean(ang, axis=-1)))


def _align(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(4, 4) rigid ``T`` that best maps points ``src`` onto ``dst`` (both (K, 3), metres),
    each pair weighted by ``1 / |dst|^2`` so that what is fitted is the angle seen from the
    origin of ``dst``'s frame (weighted Kabsch)."""
    w = 1.0 / np.maximum(np.einsum("ij,ij->i", dst, dst), 1e-12)
    w /= w.sum()
    cs, cd = w @ src, w @ dst
    M = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, cd - R @ cs)


@dataclass(frozen=True)
class _Vote:
    X: np.ndarray  # (4, 4) consensus T_anchor_sensor
    choice: np.ndarray  # (n,) ordering each view agrees best with
    error_deg: np.ndarray  # (n,) its disagreement with X
    agree: np.ndarray  # (n,) bool
    support: np.ndarray  # (n, K) how many views agree with each candidate taken as consensus

    @property
    def runner_up(self) -> int:
        """Most views agreeing with a candidate that is not ``X``'s (a view's orderings
        other than its choice): as many as ``X`` gets means the data cannot tell."""
        n, K = self.support.shape
        other = np.ones((n, K), dtype=bool)
        other[np.arange(n), self.choice] = False
        return int(self.support[other].max(initial=0))


def vote_poses(C: np.ndarray, P: np.ndarray, tol_deg: np.ndarray) -> _Vote:
    """The relative pose most views agree with.

    Args:
        C: (n, K, 4, 4) candidate ``T_anchor_sensor`` per view and ordering.
        P: (n, M, 3) board corners per view in the sensor frame, metres.
        tol_deg: (n,) how close a view must come to agree.

    Every candidate is tried as the consensus (a view may agree through any of its K
    orderings); the one most views agree with wins (ties: the smaller disagreements), then
    it is refined as the rigid transform that best maps the agreeing views' corners (sensor
    frame) onto where their candidates put them (anchor frame), in angle: far better
    determined than any one view's relative pose (a small board's tilt is not).
    """
    n, K = C.shape[:2]
    hyps = C.reshape(n * K, 4, 4)
    moved = apply_T(C, P[:, None])  # (n, K, M, 3)
    d = _angle_deg_each(moved, P, hyps)  # (J, n, K)
    e = d.min(axis=2)
    agree = e < tol_deg
    support = agree.sum(axis=1)
    score = support - np.where(agree, e / tol_deg, 0.0).sum(axis=1) / (n + 1)
    X = hyps[int(np.argmax(score))]
    for _ in range(3):
        d = angle_deg(moved, apply_T(X, P)[:, None])  # (n, K)
        choice = d.argmin(axis=1)
        e = d.min(axis=1)
        agree = e < tol_deg
        if not agree.any():
            break
        chosen = moved[np.arange(n), choice]  # (n, M, 3) anchor frame
        X = _align(P[agree].reshape(-1, 3), chosen[agree].reshape(-1, 3))
    d = angle_deg(moved, apply_T(X, P)[:, None])
    choice = d.argmin(axis=1)
    e = d.min(axis=1)
    return _Vote(X, choice, e, e < tol_deg, support.reshape(n, K))


@dataclass(frozen=True)
class OrderingCheck:
    """How one sensor's per-view board poses agree with an anchor's (:func:`check_ordering`).

    Attributes:
        anchor: the sensor compared with.
        views: the views both saw the board in.
        spread_deg: (as detected, half-turned): for each ordering of all views alike, the
            median disagreement (degrees, seen from the anchor) of the views' relative
            poses with the pose most of them agree with.
        agreeing: (as detected, half-turned): how many views agree with that pose.
        half_turn_deg: median over the views of the disagreement a half turn causes.
        ordering: ``AS_DETECTED`` (0) or ``HALF_TURNED`` (1) when exactly one ordering is
            consistent (at least :data:`MIN_AGREEING_FRACTION` of the views agree), else
            None (see ``consistent``).
        consistent: (as detected, half-turned) whether each ordering is consistent.
        turned_views: views whose detection agrees only when turned the other way from
            ``ordering`` (their polarity differs from the rest: a reflection of something
            hot, a board near room temperature ...).
        stray_views: views that agree with neither ordering.
        T_anchor_sensor: (4, 4) the consensus relative pose of ``ordering`` (or of the
            better-agreeing ordering when none or both are consistent), metres.
    """

    anchor: str
    views: tuple[str, ...]
    spread_deg: tuple[float, float]
    agreeing: tuple[int, int]
    half_turn_deg: float
    ordering: int | None
    consistent: tuple[bool, bool]
    turned_views: tuple[str, ...] = ()
    stray_views: tuple[str, ...] = ()
    T_anchor_sensor: np.ndarray = field(default_factory=lambda: np.eye(4), compare=False)

    @property
    def ratio(self) -> float:
        """Spread of the other ordering over that of the chosen (or better) one: how
        decisive the choice is (infinite when the chosen spread is 0)."""
        k = self.best
        mine, other = self.spread_deg[k], self.spread_deg[1 - k]
        return math.inf if mine <= 0 else other / mine

    @property
    def best(self) -> int:
        """The chosen ordering, or (undecided) the one with the smaller spread."""
        if self.ordering is not None:
            return self.ordering
        return AS_DETECTED if self.spread_deg[0] <= self.spread_deg[1] else HALF_TURNED


def check_ordering(
    anchor: str,
    T_anchor_board: Mapping[str, np.ndarray],
    T_sensor_board: Mapping[str, np.ndarray],
    board: Board,
) -> OrderingCheck:
    """Which ordering of a sensor's detections agrees with an anchor across shared views.

    Args:
        anchor: the anchor's name (for the result).
        T_anchor_board: view -> (4, 4) board pose in the anchor's frame (its own ordering,
            taken as right), metres.
        T_sensor_board: view -> (4, 4) board pose in the sensor's frame from its corners as
            detected, metres.
        board: the checkerboard.

    Raises:
        ValueError: fewer than two shared views (nothing to compare).
    """
    views = tuple(sorted(set(T_anchor_board) & set(T_sensor_board)))
    if len(views) < 2:
        raise ValueError(
            f"check_ordering: the sensor shares {len(views)} view(s) with {anchor!r}; at "
            "least 2 are needed to compare poses"
        )
    H = half_turn(board)
    A = np.stack([np.asarray(T_anchor_board[v], dtype=np.float64) for v in views])
    S = np.stack([np.asarray(T_sensor_board[v], dtype=np.float64) for v in views])
    S_inv = np.linalg.inv(S)
    C = np.stack([A @ S_inv, A @ H @ S_inv], axis=1)  # (n, 2, 4, 4) T_anchor_sensor
    P = apply_T(S, board.object_points()[None])  # (n, M, 3) corners in the sensor frame
    moved = apply_T(C, P[:, None])
    h = angle_deg(moved[:, 0], moved[:, 1])  # (n,) what a half turn does
    tol = AGREE_FRACTION_OF_HALF_TURN * h
    need = max(2, math.ceil(MIN_AGREEING_FRACTION * len(views)))
    alone = [vote_poses(C[:, [k]], P, tol) for k in (AS_DETECTED, HALF_TURNED)]
    spread = (float(np.median(alone[0].error_deg)), float(np.median(alone[1].error_deg)))
    agreeing = (int(alone[0].agree.sum()), int(alone[1].agree.sum()))
    consistent = (agreeing[0] >= need, agreeing[1] >= need)
    ordering = None
    if consistent[0] != consistent[1]:
        ordering = AS_DETECTED if consistent[0] else HALF_TURNED
    k = ordering if ordering is not None else int(spread[1] < spread[0])
    X = alone[k].X
    d = angle_deg(moved, apply_T(X, P)[:, None])  # (n, 2)
    turned = tuple(v for i, v in enumerate(views) if d[i, k] >= tol[i] and d[i, 1 - k] < tol[i])
    stray = tuple(v for i, v in enumerate(views) if d[i, k] >= tol[i] and d[i, 1 - k] >= tol[i])
    return OrderingCheck(
        anchor,
        views,
        spread,
        agreeing,
        float(np.median(h)),
        ordering,
        consistent,
        turned if ordering is not None else (),
        stray,
        X,
    )


# -- the findings of a calibration ------------------------------------------------------------


@dataclass(frozen=True)
class SensorPolarity:
    """What was found about one sensor's board polarity (report and console).

    Attributes:
        sensor, modality: the sensor.
        black_is: whether the black squares read hot (thermal) or dark (colour, TOF) in it,
            as finally used; None when it could not be decided.
        turned: the detections were relabelled by a half turn (the detector's assumption,
            :func:`detected_as`, was wrong for this board).
        decided_by: ``"colour"`` (printed colours: colour cameras), ``"data"`` (agreement
            of the poses with ``anchor``), ``"board.yaml"`` (the override, checked against
            the data when possible), ``"assumed"`` (no colour camera: the anchor's own
            ordering is taken as detected), or ``"undecided"``.
        anchor: the sensor its poses were compared with (None: none).
        check: the comparison (None when there was none).
        turned_views: views relabelled alone (their polarity differed from the sensor's).
        reversed_views: every view whose corner list was reversed (relabelled by the half
            turn) before the calibration.
        problem: why the sensor cannot be calibrated, or None.
    """

    sensor: str
    modality: str
    black_is: bool | None
    turned: bool
    decided_by: str
    anchor: str | None = None
    check: OrderingCheck | None = None
    turned_views: tuple[str, ...] = ()
    reversed_views: tuple[str, ...] = ()
    problem: str | None = None

    @property
    def words(self) -> str:
        """``black squares hot`` ..., or ``not decided``."""
        if self.black_is is None:
            return "not decided"
        return polarity_words(self.modality, self.black_is)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready content of the report's ``polarity`` entry (docs/FORMATS.md)."""
        c = self.check
        return {
            "modality": self.modality,
            "polarity": self.words,
            "black_is_hot" if self.modality == "thermal" else "black_is_dark": self.black_is,
            "turned": self.turned,
            "decided_by": self.decided_by,
            "anchor": self.anchor,
            "views_compared": len(c.views) if c else 0,
            "spread_deg": (
                {"as_detected": c.spread_deg[0], "half_turned": c.spread_deg[1]} if c else None
            ),
            "agreeing_views": (
                {"as_detected": c.agreeing[0], "half_turned": c.agreeing[1]} if c else None
            ),
            "half_turn_deg": c.half_turn_deg if c else None,
            "ratio": (c.ratio if math.isfinite(c.ratio) else None) if c else None,
            "turned_views": list(self.turned_views),
            "stray_views": list(c.stray_views) if c else [],
            "problem": self.problem,
        }
