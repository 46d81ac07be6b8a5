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

A board that looks the same turned (even x even or odd x odd inner corners, or square:
``Board.orderings`` > 1) has no polarity to find, but its detections come in any of its
orderings, image by image. :func:`order_views` gives each view one ordering for all the
sensors that saw it by the same vote, with one candidate per turn (:func:`grid_turns`) of
every view's corners.

Pure: arrays in, values out (calib.diagnosis applies the decisions in a calibration; the
console's live board watch uses :func:`orient_to_pose`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
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
ORIENT_MAX_RATIO = 0.5
"""Live orientation (:func:`orient_to_pose`): an ordering is taken when its RMS pixel error
against the expected corners is below this fraction of the other's."""

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


def _apply(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Points ``P`` (n, M, 3) mapped by per-view transforms ``T`` (n, 4, 4) or by one
    transform per hypothesis and view (J, n, 4, 4) -> (..., M, 3)."""
    return np.matmul(P, np.swapaxes(T[..., :3, :3], -1, -2)) + T[..., None, :3, 3]


# Elements per coordinate array of :func:`_angle_deg_each`'s chunks (about 1 MB): small
# enough to stay in cache through the dozen operations on them, which halved its time.
_CHUNK_ELEMENTS = 1 << 17


def _angle_deg_each(moved: np.ndarray, P: np.ndarray, T: np.ndarray) -> np.ndarray:
    """:func:`_angle_deg` between every view's candidates and every transform's mapping.

    Args:
        moved: (n, K, M, 3) each view's corners moved by its K candidate transforms.
        P: (n, M, 3) each view's corners.
        T: (J, 4, 4) transforms tried on every view's corners.

    Returns:
        (J, n, K) degrees: ``_angle_deg(moved[None], _apply(T[:, None], P[None])[:, :, None])``
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


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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


def _vote(C: np.ndarray, P: np.ndarray, tol_deg: np.ndarray) -> _Vote:
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
    moved = _apply(C, P[:, None])  # (n, K, M, 3)
    d = _angle_deg_each(moved, P, hyps)  # (J, n, K)
    e = d.min(axis=2)
    agree = e < tol_deg
    support = agree.sum(axis=1)
    score = support - np.where(agree, e / tol_deg, 0.0).sum(axis=1) / (n + 1)
    X = hyps[int(np.argmax(score))]
    for _ in range(3):
        d = _angle_deg(moved, _apply(X, P)[:, None])  # (n, K)
        choice = d.argmin(axis=1)
        e = d.min(axis=1)
        agree = e < tol_deg
        if not agree.any():
            break
        chosen = moved[np.arange(n), choice]  # (n, M, 3) anchor frame
        X = _align(P[agree].reshape(-1, 3), chosen[agree].reshape(-1, 3))
    d = _angle_deg(moved, _apply(X, P)[:, None])
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
    P = _apply(S, board.object_points()[None])  # (n, M, 3) corners in the sensor frame
    moved = _apply(C, P[:, None])
    h = _angle_deg(moved[:, 0], moved[:, 1])  # (n,) what a half turn does
    tol = AGREE_FRACTION_OF_HALF_TURN * h
    need = max(2, math.ceil(MIN_AGREEING_FRACTION * len(views)))
    alone = [_vote(C[:, [k]], P, tol) for k in (AS_DETECTED, HALF_TURNED)]
    spread = (float(np.median(alone[0].error_deg)), float(np.median(alone[1].error_deg)))
    agreeing = (int(alone[0].agree.sum()), int(alone[1].agree.sum()))
    consistent = (agreeing[0] >= need, agreeing[1] >= need)
    ordering = None
    if consistent[0] != consistent[1]:
        ordering = AS_DETECTED if consistent[0] else HALF_TURNED
    k = ordering if ordering is not None else int(spread[1] < spread[0])
    X = alone[k].X
    d = _angle_deg(moved, _apply(X, P)[:, None])  # (n, 2)
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


# -- boards that look the same turned (calib.board.Board.orderings > 1) ---------------------


def grid_turns(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """The turns about the board normal through the centre of its inner corners that map
    the grid of corners onto itself: 0 and 180 degrees, and 90 and 270 on a square board.

    Returns:
        ``G`` (K, 4, 4) board-frame transforms (``G[0]`` the identity, ``G[K // 2]`` the
        :func:`half_turn`) and ``perm`` (K, N) corner indices: corners ``c`` relabelled by
        turn ``k`` are ``c[perm[k]]`` and their pose is ``T_sensor_board @ G[k]``
        (``G[k]`` maps corner ``i`` onto corner ``perm[k][i]``).
    """
    s = board.square_size_m
    centre = np.array([(board.cols - 1) * s / 2.0, (board.rows - 1) * s / 2.0, 0.0])
    obj = board.object_points()
    cos_sin = ((1, 0), (0, 1), (-1, 0), (0, -1)) if board.cols == board.rows else ((1, 0), (-1, 0))
    Gs, perms = [], []
    for c, sn in cos_sin:
        R = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        G = make_T(R, centre - R @ centre)
        col_row = np.rint(_apply(G, obj)[:, :2] / s).astype(np.int64)
        Gs.append(G)
        perms.append(col_row[:, 1] * board.cols + col_row[:, 0])
    return np.stack(Gs), np.stack(perms)


@dataclass(frozen=True)
class SensorOrdering:
    """How one sensor's detections of a board that looks the same turned were given the
    views' common orderings (:func:`order_views`).

    Attributes:
        sensor: the sensor.
        compared_with: the sensors (already ordered) whose board poses it was compared
            with, one per view: the anchor where it saw the board, else the first ordered
            sensor that did.
        views: the views compared (seen by it and by one of ``compared_with``).
        agreeing: how many of them agree with the consensus relative pose (in one of
            their orderings).
        runner_up: most views agreeing with any other relative pose a turn away; as many
            as ``agreeing`` means the data cannot tell.
        turn_deg: median over the views of the disagreement the smallest turn causes.
        spread_deg: median disagreement of the agreeing views with the consensus.
        turned: view -> degrees (90, 180, 270) its corners were turned by (views kept as
            detected are not listed).
        left_out: view -> why its corners were left out of the joint pass.
        problem: why the sensor cannot be placed with the others, or None.
        T_anchor_sensor: (4, 4) consensus relative pose to the anchor, metres (identity
            for the anchor and for an undecided sensor).
    """

    sensor: str
    compared_with: tuple[str, ...] = ()
    views: tuple[str, ...] = ()
    agreeing: int = 0
    runner_up: int = 0
    turn_deg: float = math.nan
    spread_deg: float = math.nan
    turned: Mapping[str, int] = field(default_factory=dict)
    left_out: Mapping[str, str] = field(default_factory=dict)
    problem: str | None = None
    T_anchor_sensor: np.ndarray = field(default_factory=lambda: np.eye(4), compare=False)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready content of the report's ``board_ordering.sensors.<s>``."""

        def number(x: float) -> float | None:
            return x if math.isfinite(x) else None

        return {
            "compared_with": list(self.compared_with),
            "views_compared": len(self.views),
            "agreeing_views": self.agreeing,
            "runner_up_views": self.runner_up,
            "turn_deg": number(self.turn_deg),
            "spread_deg": number(self.spread_deg),
            "turned_views": dict(self.turned),
            "left_out": dict(self.left_out),
            "problem": self.problem,
        }


@dataclass
class BoardOrdering:
    """Every view's ordering of a board that looks the same turned (:func:`order_views`).

    Attributes:
        board: the board.
        anchor: the sensor whose detections keep their ordering (None: no sensor).
        sensors: sensor -> :class:`SensorOrdering`, every sensor given.
        observations: sensor -> view -> (N, 2) corners, pixels, turned into the ordering
            the view's other sensors use; left-out views and excluded sensors removed.
        T_sensor_board: sensor -> view -> (4, 4) board pose for those corners, metres.
        excluded: sensor -> why it cannot be placed with the others.
        notes: sentences for the report.
    """

    board: Board
    anchor: str | None
    sensors: dict[str, SensorOrdering]
    observations: dict[str, dict[str, np.ndarray]]
    T_sensor_board: dict[str, dict[str, np.ndarray]]
    excluded: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready content of the report's ``board_ordering`` (docs/FORMATS.md)."""
        return {
            "orderings": self.board.orderings,
            "anchor": self.anchor,
            "sensors": {s: o.as_dict() for s, o in sorted(self.sensors.items())},
        }


def _views_text(views: list[str] | tuple[str, ...]) -> str:
    return ", ".join(views) if len(views) <= 12 else f"{', '.join(views[:12])} ..."


def _turn_words(board: Board) -> str:
    what = "a quarter turn" if board.orderings == 4 else "a half turn"
    return f"the {board.cols}x{board.rows} board looks the same after {what}"


def _order_sensor(
    sensor: str,
    links: Mapping[str, str],
    poses: Mapping[str, Mapping[str, np.ndarray]],
    T_anchor: Mapping[str, np.ndarray],
    board: Board,
    G: np.ndarray,
) -> tuple[SensorOrdering, np.ndarray | None]:
    """Decide each linked view's ordering of ``sensor`` (:func:`order_views`).

    Args:
        links: view -> the already ordered sensor it is compared with in that view.
        poses: sensor -> view -> T_sensor_board, those of ordered sensors in their views'
            common ordering.
        T_anchor: ordered sensor -> (4, 4) T_anchor_sensor.
        board, G: the board and its :func:`grid_turns`.

    Returns:
        The sensor's :class:`SensorOrdering` (``turned`` and ``left_out`` filled, or a
        ``problem``) and (n,) the turn index per linked view (-1: left out), or None.
    """
    K = len(G)
    views = sorted(links)
    partners = tuple(dict.fromkeys(links[v] for v in views))
    A = np.stack([T_anchor[links[v]] @ poses[links[v]][v] for v in views])  # T_anchor_board
    S = np.stack([poses[sensor][v] for v in views])
    # Candidate T_anchor_sensor per view and turn: the sensor's corners turned by G[k] have
    # the pose S @ G[k], so T_anchor_sensor = A @ inv(S @ G[k]).
    C = A[:, None] @ np.linalg.inv(S[:, None] @ G[None])  # (n, K, 4, 4)
    P = _apply(S, board.object_points()[None])  # (n, M, 3) corners in the sensor frame
    moved = _apply(C, P[:, None])
    turn = np.min([_angle_deg(moved[:, 0], moved[:, k]) for k in range(1, K)], axis=0)
    vote = _vote(C, P, AGREE_FRACTION_OF_HALF_TURN * turn)
    agreeing = int(vote.agree.sum())
    need = max(2, math.ceil(MIN_AGREEING_FRACTION * len(views)))
    result = SensorOrdering(
        sensor,
        partners,
        tuple(views),
        agreeing,
        vote.runner_up,
        float(np.median(turn)),
        float(np.median(vote.error_deg[vote.agree])) if agreeing else math.nan,
    )
    names = " and ".join(partners)
    seen = f"its {len(views)} view(s) shared with {names} ({_views_text(views)})"
    if agreeing < need:
        problem = (
            f"its board poses agree with {names}'s in none of the board's {K} orderings: of "
            f"{seen}, at most {agreeing} agree with one relative pose ({need} needed): likely "
            "a wrong board size in board.yaml, a mirrored image or images from another camera"
        )
        return replace(result, problem=problem), None
    if vote.runner_up >= agreeing:
        problem = (
            f"cannot tell which way round it sees the board relative to {names} "
            f"({_turn_words(board)}): {seen} agree as well with a relative pose a turn away "
            f"({vote.runner_up} views) as with the best one ({agreeing}): the board was held "
            "at about the same place and tilt in them (only nearer, farther or turned in "
            "its plane); move and tilt it between views"
        )
        return replace(result, problem=problem), None
    ks = np.where(vote.agree, vote.choice, -1)
    angles = 360 // K
    turned = {v: int(k) * angles for v, k in zip(views, ks, strict=True) if k > 0}
    left_out = {
        v: (
            f"{sensor}'s board pose agrees with {links[v]}'s in none of the board's {K} "
            f"orderings ({vote.error_deg[i]:.1f}° off the consensus, a turn makes "
            f"{turn[i]:.1f}°)"
        )
        for i, v in enumerate(views)
        if ks[i] < 0
    }
    return replace(result, turned=turned, left_out=left_out, T_anchor_sensor=vote.X), ks


def order_views(
    observations: Mapping[str, Mapping[str, np.ndarray]],
    T_sensor_board: Mapping[str, Mapping[str, np.ndarray]],
    modalities: Mapping[str, str],
    board: Board,
) -> BoardOrdering:
    """Give every view of a board that looks the same turned one ordering for all sensors.

    A detector labels such a board (:attr:`calib.board.Board.orderings` > 1) in any of its
    orderings, independently per image. Each sensor's intrinsics do not care (Zhang's
    per-view poses absorb the labels), but a view's corners must be labelled alike in all
    the sensors that saw it. The anchor (a colour camera when there is one, the sensor
    sharing the most views with the others) keeps its labels; then, sensor by sensor
    (the one sharing the most views with those already ordered first), each view's
    candidate relative poses to the anchor, one per turn of its corners, are put to the
    vote of :func:`_vote`: the consensus most views agree with decides every view's turn,
    as the polarity's does (module docstring). A view agreeing in none of the turns is
    left out for that sensor (named, with its disagreement); a sensor sharing fewer than
    two views with the others, or whose views agree as well with a second relative pose
    (the board held at one place: the turn is about the same axis in every view), cannot
    be ordered and is excluded with the views and sensors that made it so, as is one that
    shares no view with the anchor's sensors (it could not be placed with them anyway).

    Args:
        observations: sensor -> view -> (N, 2) corners as detected, pixels.
        T_sensor_board: sensor -> view -> (4, 4) Zhang's board pose for them, metres.
        modalities: sensor -> ``color`` / ``thermal`` / ``tof``.
        board: the board.
    """
    G, perm = grid_turns(board)
    obs = {s: dict(observations[s]) for s in T_sensor_board}
    poses = {s: dict(T_sensor_board[s]) for s in T_sensor_board}
    found: dict[str, SensorOrdering] = {}
    if not poses:
        return BoardOrdering(board, None, found, obs, poses)

    def shared(s: str) -> int:
        return sum(len(set(poses[s]) & set(poses[o])) for o in poses if o != s)

    anchor = min(poses, key=lambda s: (modalities[s] != "color", -shared(s), s))
    found[anchor] = SensorOrdering(anchor)
    T_anchor = {anchor: np.eye(4)}
    ordered = [anchor]

    def links(s: str) -> dict[str, str]:
        """view -> the first ordered sensor (the anchor first) that saw it too."""
        out = {}
        for v in poses[s]:
            o = next((o for o in ordered if v in poses[o]), None)
            if o is not None:
                out[v] = o
        return out

    pending = set(poses) - {anchor}
    tried: dict[str, tuple[int, SensorOrdering]] = {}
    progress = True
    while progress:
        progress = False
        for s in sorted(pending, key=lambda s: (-len(links(s)), modalities[s] != "color", s)):
            L = links(s)
            if len(L) < 2 or tried.get(s, (-1, None))[0] == len(L):
                continue
            result, ks = _order_sensor(s, L, poses, T_anchor, board, G)
            tried[s] = (len(L), result)
            if ks is None:
                continue
            for v, k in zip(sorted(L), ks, strict=True):
                if k < 0:
                    del obs[s][v], poses[s][v]
                elif k > 0:
                    obs[s][v] = np.ascontiguousarray(obs[s][v][perm[k]])
                    poses[s][v] = poses[s][v] @ G[k]
            found[s] = result
            T_anchor[s] = result.T_anchor_sensor
            ordered.append(s)
            pending.discard(s)
            progress = True
            break
    excluded: dict[str, str] = {}
    notes = [
        f"{_turn_words(board)}: each view's corners were put in one ordering for all sensors "
        f"by the agreement of the sensors' board poses, relative to {anchor}'s"
    ]
    for s in sorted(pending):
        L = links(s)
        if s in tried:
            found[s] = tried[s][1]
        elif L:
            ((v, o),) = L.items()
            found[s] = SensorOrdering(
                s,
                (o,),
                (v,),
                problem=(
                    f"cannot tell which way round it sees the board relative to the others "
                    f"({_turn_words(board)}): it shares only view {v} with {o} (and no "
                    "other view with a sensor already ordered); one view fits every "
                    f"ordering: capture views that it and {o} both see"
                ),
            )
        else:
            found[s] = SensorOrdering(
                s,
                problem=(
                    f"it shares no view with {anchor} or the sensors ordered with it "
                    f"({_turn_words(board)}: each view's ordering is decided against them); "
                    f"capture views that it and {anchor} both see"
                ),
            )
        excluded[s] = found[s].problem or ""
        del obs[s], poses[s]
    for s in ordered:
        if found[s].left_out:
            notes.append(
                f"{s}: view(s) {_views_text(sorted(found[s].left_out))} left out of the joint "
                f"pass: its board pose there agrees with the others' in none of the orderings"
            )
    return BoardOrdering(board, anchor, found, obs, poses, excluded, notes)


# -- live: one sighting against an expected pose ---------------------------------------------


def orient_to_pose(
    corners: np.ndarray,
    intrinsics: Intrinsics,
    T_sensor_board: np.ndarray,
    board: Board,
) -> tuple[np.ndarray, bool] | None:
    """The ordering of one detection that agrees with an expected board pose: the
    detection as it is or turned (a half turn; quarter turns too on a square board).

    Args:
        corners: (N, 2) detected corners, pixels.
        intrinsics: the sensor's intrinsics.
        T_sensor_board: (4, 4) where the board is expected in the sensor's frame (e.g. from
            a colour camera's detection through the rig), metres.
        board: the checkerboard.

    Returns:
        (corners in the agreeing order, whether they were turned), or None when the
        expected corners do not tell (behind the camera, or no ordering is clearly
        closer: the RMS error of one must be below :data:`ORIENT_MAX_RATIO` of every
        other's).
    """
    P = board.object_points() @ T_sensor_board[:3, :3].T + T_sensor_board[:3, 3]
    if not np.all(P[:, 2] > 0):
        return None
    expected = intrinsics.project(P)
    if not np.all(np.isfinite(expected)):
        return None
    c = np.asarray(corners, dtype=np.float64)
    _, perm = grid_turns(board)
    e = np.sqrt(np.mean(np.sum((c[perm] - expected) ** 2, axis=2), axis=1))  # (K,)
    k = int(np.argmin(e))
    if e[k] > ORIENT_MAX_RATIO * np.delete(e, k).min():
        return None
    return (np.ascontiguousarray(c[perm[k]]), True) if k else (c, False)
