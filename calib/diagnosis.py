"""Before the joint calibration: can each sensor's detections be reconciled with the others?

Run between the per-sensor intrinsics (Zhang) and the placement of the sensors
(calib.rig_calibration). For every sensor:

1. **Physical intrinsics**: positive focal lengths (Zhang's failures are caught before
   this), the principal point inside the image, about square pixels, a plausible field of
   view and a sane RMS of Zhang's fit (:func:`intrinsics_problem`).
2. **Board ordering** (calib.polarity): colour cameras see the printed colours; every
   thermal imager's and TOF camera's ordering is chosen by the agreement of its per-view
   relative poses with an anchor (the colour camera most other sensors agree with; without
   colour cameras the sensor with the most views), chaining through sensors already decided
   for a sensor that shares too few views with the anchor. A ``board.yaml`` polarity key
   replaces the search for its modality and is only checked. A board that looks the same
   turned (``Board.orderings`` > 1) has no polarity to find: each view's ordering is
   decided across the sensors instead (calib.board_ordering.order_views). A ChArUco board or an
   asymmetric circle grid has neither: its markers or layout fix the order.

A sensor that fails is excluded with a sentence naming what disagrees and the likely cause,
and the others go on; the optimiser is never left to find out. Pure: arrays in, values out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.board_ordering import BoardOrdering, order_views
from trifuse.calib.camera import Intrinsics
from trifuse.calib.polarity import (
    AS_DETECTED,
    HALF_TURNED,
    MIN_AGREEING_FRACTION,
    MIN_SHARED_VIEWS,
    OrderingCheck,
    SensorPolarity,
    check_ordering,
    detected_as,
    half_turn,
    override,
    override_key,
    polarity_words,
    reverse_corners,
)

MAX_ZHANG_RMS_PX = 2.0
MAX_ZHANG_RMS_DIAGONAL = 0.005
"""Zhang's fit of one sensor's corners must have an RMS error of at most the larger of
``MAX_ZHANG_RMS_PX`` pixels and ``MAX_ZHANG_RMS_DIAGONAL`` of the image's diagonal: beyond
it the corners fit no single camera (corners astray, images from different cameras). The
share of the diagonal keeps the rule from refusing real colour cameras that OpenCV
calibrates (a ZED 2i at 1280 x 720: Zhang RMS 2.05 px, OpenCV's 1.59 px, on a board found
in 69 views; a 12 MP camera's corners scatter more pixels than a thermal core's)."""
MAX_ASPECT_DEVIATION = 0.2
"""|fy / fx - 1| at most this: the imagers have about square pixels."""
FIELD_OF_VIEW_DEG = (2.0, 170.0)
"""Plausible horizontal field of view of a sensor, degrees."""

LIKELY_ZHANG = (
    "likely too few or too similar views, a wrong board size in board.yaml, or corners astray"
)
LIKELY_DISAGREEMENT = (
    "likely a mirrored image, a wrong board size in board.yaml, a polarity that changes from "
    "view to view, or images from another camera"
)


@dataclass
class Screening:
    """What :func:`screen_sensors` found and decided.

    Attributes:
        observations: sensor -> view -> (N, 2) corners, pixels, relabelled where the
            ordering was turned (canonical board order for every usable sensor).
        T_sensor_board: sensor -> view -> (4, 4) board pose in the sensor's frame for those
            corners, metres.
        polarity: sensor -> :class:`~calib.polarity.SensorPolarity`, every screened sensor.
        excluded: sensor -> why it cannot be calibrated.
        anchor: the sensor the orderings were compared with (None: no usable sensor).
        notes: sentences for the report (e.g. no colour camera).
        ordering: a board that looks the same turned: every view's ordering, decided
            across sensors instead of the polarity (None for other boards).
    """

    observations: dict[str, dict[str, np.ndarray]]
    T_sensor_board: dict[str, dict[str, np.ndarray]]
    polarity: dict[str, SensorPolarity]
    excluded: dict[str, str]
    anchor: str | None
    notes: list[str] = field(default_factory=list)
    ordering: BoardOrdering | None = None


def zhang_failure(n_views: int, exc: Exception) -> str:
    """The exclusion reason of a sensor whose Zhang calibration raised ``exc``."""
    what = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return (
        f"Zhang's method found no physical camera in its {n_views} view(s) ({what}); {LIKELY_ZHANG}"
    )


def zhang_rms_px(
    corners: Mapping[str, np.ndarray],
    intrinsics: Intrinsics,
    T_sensor_board: Mapping[str, np.ndarray],
    board: Board,
) -> float:
    """RMS reprojection error (pixels) of Zhang's solution over a sensor's views.

    Args:
        corners: view -> (N, 2) detected corners, pixels (NaN rows: not seen).
        intrinsics: Zhang's intrinsics.
        T_sensor_board: view -> (4, 4) Zhang's board pose, metres.
        board: the checkerboard.
    """
    obj = board.object_points()
    errs = []
    for v, c in corners.items():
        T = T_sensor_board[v]
        uv = intrinsics.project(obj @ T[:3, :3].T + T[:3, 3])
        seen = np.isfinite(c[:, 0])  # all but on a partial view (NaN rows: not seen)
        errs.append(np.sum((uv[seen] - c[seen]) ** 2, axis=1))
    e = np.concatenate(errs)
    return float(np.sqrt(np.mean(e))) if np.all(np.isfinite(e)) else math.inf


def intrinsics_problem(
    intrinsics: Intrinsics, image_size: tuple[int, int], rms_px: float, n_views: int
) -> str | None:
    """Why Zhang's intrinsics of a sensor are not physical, or None.

    Args:
        intrinsics: Zhang's result (focal lengths are positive by construction).
        image_size: (width, height) pixels.
        rms_px: RMS error of Zhang's fit (:func:`zhang_rms_px`).
        n_views: views it was computed from.
    """
    w, h = image_size
    i = intrinsics
    found = []
    if not (-0.5 <= i.cx <= w - 0.5 and -0.5 <= i.cy <= h - 0.5):
        found.append(f"principal point ({i.cx:.1f}, {i.cy:.1f}) outside the {w}x{h} image")
    if abs(i.fy / i.fx - 1.0) > MAX_ASPECT_DEVIATION:
        found.append(f"fx = {i.fx:.1f} and fy = {i.fy:.1f} px differ by {abs(i.fy / i.fx - 1):.0%}")
    fov = math.degrees(2.0 * math.atan2(w / 2.0, i.fx))
    lo, hi = FIELD_OF_VIEW_DEG
    if not lo <= fov <= hi:
        found.append(f"a horizontal field of view of {fov:.1f}° (fx = {i.fx:.1f} px)")
    most = max(MAX_ZHANG_RMS_PX, MAX_ZHANG_RMS_DIAGONAL * math.hypot(w, h))
    if not rms_px <= most:
        found.append(f"an RMS error of {rms_px:.2f} px, more than {most:.3g} px")
    if not found:
        return None
    return (
        f"Zhang's intrinsics from its {n_views} views are not physical: {'; '.join(found)}; "
        f"{LIKELY_ZHANG}"
    )


def _spreads(c: OrderingCheck) -> str:
    return (
        f"spread {c.spread_deg[0]:.2f}° as detected, {c.spread_deg[1]:.2f}° half-turned, over "
        f"the {len(c.views)} views shared with {c.anchor}; a half turn makes "
        f"{c.half_turn_deg:.1f}°"
    )


def _disagreement(c: OrderingCheck) -> str:
    need = max(2, math.ceil(MIN_AGREEING_FRACTION * len(c.views)))
    return (
        f"its board poses disagree with {c.anchor}'s with either ordering of its corners "
        f"({_spreads(c)}; at most {max(c.agreeing)} of {len(c.views)} views agree, {need} "
        f"needed): {LIKELY_DISAGREEMENT}"
    )


def _decide(
    sensor: str, modality: str, board: Board, c: OrderingCheck
) -> tuple[SensorPolarity, str | None]:
    """The polarity of a thermal or TOF sensor from its comparison with an anchor, and the
    problem that excludes it (or None)."""
    key = override_key(modality)
    fixed = override(board, modality)
    assumed = detected_as(board, modality)
    word = "hot" if modality == "thermal" else "dark"
    if fixed is not None:
        if c.consistent[AS_DETECTED]:
            return SensorPolarity(sensor, modality, fixed, False, "board.yaml", c.anchor, c), None
        if c.consistent[HALF_TURNED]:
            problem = (
                f"wrong polarity after all: board.yaml says {key}: {str(fixed).lower()}, but "
                f"its board poses agree with {c.anchor}'s only with the other ordering "
                f"({_spreads(c)}): it sees {polarity_words(modality, not fixed)}; remove "
                f"{key} from board.yaml (the polarity is then found from the data) or set it "
                f"to {str(not fixed).lower()}"
            )
        else:
            problem = _disagreement(c)
        return SensorPolarity(sensor, modality, None, False, "board.yaml", c.anchor, c), problem
    if c.ordering is None:
        if all(c.consistent):
            problem = (
                f"cannot tell which squares read {word} in it: both orderings of its corners "
                f"agree with {c.anchor}'s ({_spreads(c)}): the board was held at too similar "
                f"poses (tilt and move it differently between views), or set {key} in "
                "board.yaml"
            )
        else:
            problem = _disagreement(c)
        return SensorPolarity(sensor, modality, None, False, "undecided", c.anchor, c), problem
    turned = c.ordering == HALF_TURNED
    black = assumed != turned
    return (
        SensorPolarity(
            sensor, modality, black, turned, "data", c.anchor, c, turned_views=c.turned_views
        ),
        None,
    )


def screen_sensors(
    observations: Mapping[str, Mapping[str, np.ndarray]],
    modalities: Mapping[str, str],
    image_sizes: Mapping[str, tuple[int, int]],
    intrinsics: Mapping[str, Intrinsics],
    T_sensor_board: Mapping[str, Mapping[str, np.ndarray]],
    board: Board,
) -> Screening:
    """Check every sensor that has Zhang intrinsics and decide its board ordering.

    Args:
        observations: sensor -> view -> (N, 2) corners as detected (thermal with
            ``board.thermal_black_is_hot`` or the detector's default, TOF likewise:
            :func:`calib.polarity.detected_as`), pixels.
        modalities: sensor -> ``color`` / ``thermal`` / ``tof``.
        image_sizes: sensor -> (width, height), pixels.
        intrinsics: sensor -> Zhang's intrinsics (sensors without are not screened).
        T_sensor_board: sensor -> view -> (4, 4) Zhang's board pose, metres.
        board: the checkerboard (its polarity keys are overrides).

    Returns:
        A :class:`Screening`: every usable sensor's corners and poses in canonical order,
        the polarity found per sensor, and the excluded sensors with their reasons.
    """
    H = half_turn(board)
    obs = {s: dict(observations[s]) for s in intrinsics}
    poses = {s: dict(T_sensor_board[s]) for s in intrinsics}
    excluded: dict[str, str] = {}
    found: dict[str, SensorPolarity] = {}
    notes: list[str] = []
    for s in sorted(intrinsics):
        rms = zhang_rms_px(obs[s], intrinsics[s], poses[s], board)
        problem = intrinsics_problem(intrinsics[s], image_sizes[s], rms, len(obs[s]))
        if problem is not None:
            excluded[s] = problem
    usable = [s for s in sorted(intrinsics) if s not in excluded]
    if not usable:
        return Screening(obs, poses, found, excluded, None, notes)
    if board.pattern != "checkerboard" and board.orderings == 1:  # markers or layout fix it
        anchor = sorted(usable, key=lambda s: (modalities[s] != "color", -len(poses[s]), s))[0]
        return Screening(obs, poses, found, excluded, anchor, notes)
    if board.orderings > 1:  # no polarity to find: each view's ordering instead
        o = order_views(
            {s: obs[s] for s in usable}, {s: poses[s] for s in usable}, modalities, board
        )
        excluded.update(o.excluded)
        return Screening(o.observations, o.T_sensor_board, found, excluded, o.anchor, o.notes, o)

    def shared(a: str, b: str) -> int:
        return len(set(poses[a]) & set(poses[b]))

    # check_ordering(a, b) of the current poses, computed once: the anchor's support is
    # counted with the comparisons that then decide the other sensors (a sensor's entries
    # are dropped once it is decided: its poses may have been turned).
    checks: dict[tuple[str, str], OrderingCheck] = {}

    def check(a: str, b: str) -> OrderingCheck:
        if (a, b) not in checks:
            checks[a, b] = check_ordering(a, poses[a], poses[b], board)
        return checks[a, b]

    def agrees(a: str, b: str) -> bool:
        if shared(a, b) < MIN_SHARED_VIEWS:
            return False
        return any(check(a, b).consistent)

    colours = [s for s in usable if modalities[s] == "color"]
    if colours:
        support = {c: sum(agrees(c, s) for s in usable if s != c) for c in colours}
        anchor = sorted(colours, key=lambda c: (-support[c], -len(poses[c]), c))[0]
        found[anchor] = SensorPolarity(anchor, "color", True, False, "colour")
    else:
        anchor = sorted(usable, key=lambda s: (-len(poses[s]), s))[0]
        m = modalities[anchor]
        fixed = override(board, m)
        how = "board.yaml" if fixed is not None else "assumed"
        found[anchor] = SensorPolarity(anchor, m, detected_as(board, m), False, how)
        if fixed is None:
            notes.append(
                f"no colour camera: the board's orderings are relative to {anchor}'s as "
                f"detected (assumed {polarity_words(m, detected_as(board, m))}; set "
                f"{override_key(m)} in board.yaml if it is the other way)"
            )
    decided = [anchor]
    pending = sorted(
        (s for s in usable if s != anchor),
        key=lambda s: (modalities[s] != "color", -len(poses[s]), s),
    )
    progress = True
    while pending and progress:
        progress = False
        for s in list(pending):
            partners = [p for p in decided if shared(p, s) >= MIN_SHARED_VIEWS]
            if not partners:
                continue
            p = anchor if anchor in partners else max(partners, key=lambda q: shared(q, s))
            c = check(p, s)
            pending.remove(s)
            progress = True
            m = modalities[s]
            if m == "color":
                result = SensorPolarity(s, m, True, False, "colour", p, c)
                problem = None
                if not c.consistent[AS_DETECTED]:
                    problem = _disagreement(c)
                    if c.consistent[HALF_TURNED]:
                        problem = (
                            f"its corners agree with {p}'s only half-turned ({_spreads(c)}): a "
                            "colour camera sees black squares dark, unless its image (or "
                            f"{p}'s) is inverted"
                        )
            else:
                result, problem = _decide(s, m, board, c)
            if problem is not None:
                excluded[s] = problem
                found[s] = SensorPolarity(
                    s, m, result.black_is, False, result.decided_by, p, c, problem=problem
                )
                continue
            flip = set(c.views if result.turned else ()) ^ set(result.turned_views)
            if result.turned:
                flip |= set(poses[s]) - set(c.views)
            for v in flip:
                obs[s][v] = reverse_corners(obs[s][v])
                poses[s][v] = poses[s][v] @ H
            for key in [k for k in checks if s in k]:
                del checks[key]
            found[s] = SensorPolarity(
                s,
                m,
                result.black_is,
                result.turned,
                result.decided_by,
                p,
                c,
                result.turned_views,
                tuple(sorted(flip)),
            )
            decided.append(s)
    for s in pending:
        m = modalities[s]
        most = max((shared(p, s) for p in decided), default=0)
        fixed = override(board, m)
        if m == "color" or fixed is not None:
            how = "colour" if m == "color" else "board.yaml"
            black = True if m == "color" else fixed
            found[s] = SensorPolarity(s, m, black, False, how)
            notes.append(
                f"{s}: its ordering was not checked against another sensor (it shares at most "
                f"{most} view(s) with one; {MIN_SHARED_VIEWS} needed)"
            )
            continue
        key = override_key(m)
        word = "hot" if m == "thermal" else "dark"
        problem = (
            f"cannot tell which squares read {word} in it: it shares at most {most} view(s) "
            f"with a sensor whose ordering is known ({MIN_SHARED_VIEWS} needed); capture views "
            f"that it and {anchor} both see, or set {key} in board.yaml"
        )
        excluded[s] = problem
        found[s] = SensorPolarity(s, m, None, False, "undecided", problem=problem)
    for s in excluded:
        obs.pop(s, None)
        poses.pop(s, None)
    return Screening(obs, poses, found, excluded, anchor, notes)


def fallback_reference(
    reference: str, usable: list[str], modalities: Mapping[str, str], anchor: str | None
) -> str | None:
    """Another reference when ``reference`` cannot be calibrated: a TOF camera, else the
    anchor, else the first usable sensor by name; None when none is usable."""
    if reference in usable:
        return reference
    tofs = sorted(s for s in usable if modalities[s] == "tof")
    if tofs:
        return tofs[0]
    if anchor is not None and anchor in usable:
        return anchor
    return sorted(usable)[0] if usable else None
