"""Every view's ordering of a board that looks the same turned, found from the data.

A board that looks the same turned (even x even or odd x odd inner corners, or square:
``Board.orderings`` > 1) has no polarity to find, but its detections come in any of its
orderings, image by image. :func:`order_views` gives each view one ordering for all the
sensors that saw it by the same vote as the polarity's (calib.polarity, whose module
docstring describes it), with one candidate per turn (:func:`grid_turns`) of every view's
corners. :func:`orient_to_pose` orders one live detection against an expected board pose
(the console's live board watch).

Pure: arrays in, values out (calib.diagnosis applies the decisions in a calibration).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.polarity import (
    AGREE_FRACTION_OF_HALF_TURN,
    MIN_AGREEING_FRACTION,
    angle_deg,
    apply_T,
    vote_poses,
)
from trifuse.calib.transforms import make_T

ORIENT_MAX_RATIO = 0.5
"""Live orientation (:func:`orient_to_pose`): an ordering is taken when its RMS pixel error
against the expected corners is below this fraction of the other's."""


def grid_turns(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """The turns about the board normal through the centre of its inner corners that map
    the grid of corners onto itself: 0 and 180 degrees, and 90 and 270 on a square board.

    Returns:
        ``G`` (K, 4, 4) board-frame transforms (``G[0]`` the identity, ``G[K // 2]`` the
        :func:`calib.polarity.half_turn`) and ``perm`` (K, N) corner indices: corners ``c``
        relabelled by turn ``k`` are ``c[perm[k]]`` and their pose is ``T_sensor_board @
        G[k]`` (``G[k]`` maps corner ``i`` onto corner ``perm[k][i]``).
    """
    s = board.square_size_m
    centre = np.array([(board.cols - 1) * s / 2.0, (board.rows - 1) * s / 2.0, 0.0])
    obj = board.object_points()
    cos_sin = ((1, 0), (0, 1), (-1, 0), (0, -1)) if board.cols == board.rows else ((1, 0), (-1, 0))
    Gs, perms = [], []
    for c, sn in cos_sin:
        R = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        G = make_T(R, centre - R @ centre)
        col_row = np.rint(apply_T(G, obj)[:, :2] / s).astype(np.int64)
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
    P = apply_T(S, board.object_points()[None])  # (n, M, 3) corners in the sensor frame
    moved = apply_T(C, P[:, None])
    turn = np.min([angle_deg(moved[:, 0], moved[:, k]) for k in range(1, K)], axis=0)
    vote = vote_poses(C, P, AGREE_FRACTION_OF_HALF_TURN * turn)
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
    sharing the most views with the others) keeps its labels; then, sensor by sensor (the
    one sharing the most views with those already ordered first), each view's candidate
    relative poses to the anchor, one per turn of its corners, are put to the vote of
    :func:`calib.polarity.vote_poses`: the consensus most views agree with decides every
    view's turn, as the polarity's does (calib.polarity's module docstring). A view agreeing
    in none of the turns is left out for that sensor (named, with its disagreement); a
    sensor sharing fewer than two views with the others, or whose views agree as well with a
    second relative pose (the board held at one place: the turn is about the same axis in
    every view), cannot be ordered and is excluded with the views and sensors that made it
    so, as is one that shares no view with the anchor's sensors (it could not be placed with
    them anyway).

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
