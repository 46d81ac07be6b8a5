"""Where to hold the board next: the one board pose that would lower the calibration's
uncertainty most, as its verdicts (:mod:`calib.verdict`) judge it.

**What is judged.** Every judged figure of the calibration's verdicts: each sensor's focal
length and pose to the reference, each eye's and the stereo pair's relative pose, as
1-sigma / target ratios (a ratio of 1 is a sigma at half its accuracy target). Figures of a
sensor whose views disagree with the others' (a moved mount: more views do not help) are
left out. When every ratio is at most 1, every sensor's sigma meets its target and there is
nothing to suggest (:func:`suggest_next_pose` returns None).

**Candidates.** Board poses in front of each sensor of the worst figure (the sensor, or the
sensor and its reference, or the pair): the board's centre at nine places across the image
(its thirds), at four distances (the board spanning 30-85 % of the image), square-on or
tilted by 20-40 degrees about the camera's vertical or horizontal axis or both
(:data:`TILTS_DEG`). A candidate is feasible when the board's outline (its checkered area)
and every inner corner lie inside the image of every sensor of the worst figure (the
corners with a margin of :data:`MARGIN` of the image: the operator sees where the whole
board goes), its corners are at least :data:`MIN_SPACING_PX` apart there (closer ones the
detector misses), and the board is turned at most :data:`MAX_OBLIQUE_DEG` from the line of
sight.

**Choice.** Each feasible candidate's information (the Jacobian of its corners in every
sensor that would see the whole board, its own board pose eliminated:
:func:`calib.verdict_judge.pose_information`) is added to the calibration's, and the figures are
predicted as the verdicts predict them (:func:`calib.verdict_judge.predictor`). The candidate with
the lowest worst ratio wins; candidates within :data:`TIE` of it are told apart by the sum of
the squared ratios above 1 (the view that also helps the other figures).

**Sensors not calibrated yet** (seen in too few views) have no sigma to lower; given their
nominal calibration (``newcomers``), the candidates are narrowed to those that show them
the board too, while there are such.

Frames: ``T_rig_board`` (4, 4) maps board points (metres; origin at the first inner corner,
+z away from the cameras) into the rig frame; camera frames x right, y down, z forward.

Pure: arrays in, values out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from trifuse.calib.board import Board
from trifuse.calib.rig_problem import BLAS_THREADS
from trifuse.calib.rig_result import CalibrationResult
from trifuse.calib.rig_uncertainty import RigCovariance
from trifuse.calib.sensor_result import SensorResult
from trifuse.calib.transforms import invert, make_T, rotations_from_rvecs
from trifuse.calib.verdict import Figure, RigVerdict
from trifuse.calib.verdict_judge import (
    FigureSpec,
    pose_information,
    pose_specs,
    predictor,
    sensor_specs,
)

FILLS = (0.3, 0.45, 0.65, 0.85)
"""Candidate distances: the board spans this share of the image (the larger of width and
height)."""
PLACES = (0.2, 0.5, 0.8)
"""Candidate positions of the board's centre across the image, shares of width and height."""
TILTS_DEG = (
    (0.0, 0.0),
    (20.0, 0.0),
    (-20.0, 0.0),
    (40.0, 0.0),
    (-40.0, 0.0),
    (0.0, 20.0),
    (0.0, -20.0),
    (0.0, 40.0),
    (0.0, -40.0),
    (25.0, 25.0),
    (25.0, -25.0),
    (-25.0, 25.0),
    (-25.0, -25.0),
)
"""Candidate tilts, degrees about the camera's vertical (y) and horizontal (x) axes."""
MARGIN = 0.03
"""Share of the image's smaller side kept free around a candidate's inner corners."""
MIN_SPACING_PX = 8.0
"""Neighbouring corners closer than this in an image: the detector misses the board."""
MAX_OBLIQUE_DEG = 55.0
"""Largest angle between the board's normal and the line of sight to its centre."""
TIE = 0.005
"""Candidates whose worst ratio is within this share of the best are told apart by the
other figures."""
TURN_WORDS_DEG = 10.0
"""A tilt from this angle on is put in words ("turn the left edge away")."""


@dataclass(frozen=True)
class NextPose:
    """The suggested board pose.

    Attributes:
        T_rig_board: (4, 4) the pose, rig frame, metres.
        subject: the sensor the words and the distance refer to (a colour camera among
            those that see it when there is one).
        sensors: the sensors of the worst figure, which must all see the board.
        newcomers: sensors not calibrated yet that see the board there too (by their
            nominal calibration; see :func:`suggest_next_pose`).
        outline_px: sensor -> (4, 2) pixels of the board's checkered area's corners (its
            inner corners' bounding box widened by one square: top-left, top-right,
            bottom-right, bottom-left in the board frame) in every sensor that would see
            all its inner corners.
        worst_now: the judged figure with the worst sigma / target ratio now.
        worst_after: the worst judged figure predicted with this view added.
        distance_m: from ``subject`` to the board's centre, metres.
        centre_px: the board's centre in ``subject``'s image, pixels.
        tilt_deg: (about the vertical axis, about the horizontal axis) in ``subject``'s
            frame, degrees: positive about the vertical axis, the left edge is farther;
            positive about the horizontal axis, the top edge is farther.
        image_size: ``subject``'s (width, height), pixels.
    """

    T_rig_board: np.ndarray
    subject: str
    sensors: tuple[str, ...]
    outline_px: dict[str, np.ndarray]
    worst_now: Figure
    worst_after: Figure
    distance_m: float
    centre_px: tuple[float, float]
    tilt_deg: tuple[float, float]
    image_size: tuple[int, int]
    newcomers: tuple[str, ...] = ()

    @property
    def region(self) -> str:
        """Where in ``subject``'s image: ``lower-right corner``, ``top edge``, ``centre``."""
        w, h = self.image_size
        col = min(2, max(0, int(3 * self.centre_px[0] / w)))
        row = min(2, max(0, int(3 * self.centre_px[1] / h)))
        if row == 1 and col == 1:
            return "centre"
        if row == 1:
            return ("left", "", "right")[col] + " edge"
        if col == 1:
            return ("top", "", "bottom")[row] + " edge"
        return f"{('upper', '', 'lower')[row]}-{('left', '', 'right')[col]} corner"

    @property
    def turn(self) -> str:
        """The tilt in words: ``turn the left edge away 30°, the top edge away 20°`` or
        ``square-on``."""
        about_v, about_h = self.tilt_deg
        parts = []
        if abs(about_v) >= TURN_WORDS_DEG:
            parts.append(f"the {'left' if about_v > 0 else 'right'} edge away {abs(about_v):.0f}°")
        if abs(about_h) >= TURN_WORDS_DEG:
            parts.append(f"the {'top' if about_h > 0 else 'bottom'} edge away {abs(about_h):.0f}°")
        return "turn " + ", ".join(parts) if parts else "square-on"

    def words(self, current: np.ndarray | None = None, sensors: dict | None = None) -> str:
        """What the operator should do, e.g. ``move closer (0.9 m), turn the left edge away
        30°, lower-right corner of ccd_left``.

        Args:
            current: (4, 4) ``T_rig_board`` where the board is now (a live sighting), or
                None: the distance is then said as it is.
            sensors: sensor name -> object with ``T_rig_sensor`` (4, 4) (a Rig's sensors
                or a calibration's), needed with ``current``.
        """
        far = f"{self.distance_m:.1f} m"
        if current is not None and sensors is not None and self.subject in sensors:
            T = invert(sensors[self.subject].T_rig_sensor) @ np.asarray(current, dtype=float)
            now = float(np.linalg.norm(T[:3, 3]))
            if self.distance_m < 0.85 * now:
                far = f"move closer ({far})"
            elif self.distance_m > 1.15 * now:
                far = f"move back ({far})"
            else:
                far = f"this distance ({far})"
        else:
            far = f"at {far}"
        return f"{far}, {self.turn}, {self.region} of {self.subject}"

    def as_dict(self) -> dict:
        return {
            "T_rig_board": self.T_rig_board.tolist(),
            "subject": self.subject,
            "sensors": list(self.sensors),
            "outline_px": {s: p.tolist() for s, p in self.outline_px.items()},
            "worst_now": self.worst_now.as_dict(),
            "worst_after": self.worst_after.as_dict(),
            "distance_m": self.distance_m,
            "region": self.region,
            "tilt_deg": list(self.tilt_deg),
            "words": self.words(),
        }


def outline_points(board: Board) -> np.ndarray:
    """(4, 3) the board's checkered area's corners in the board frame, metres: the inner
    corners' bounding box widened by one square (top-left, top-right, bottom-right,
    bottom-left)."""
    obj = board.object_points()
    lo, hi = obj.min(axis=0) - board.square_size_m, obj.max(axis=0) + board.square_size_m
    return np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]])


def _rot(about_v_deg: float, about_h_deg: float) -> np.ndarray:
    """Rotation about the camera's vertical (y) then horizontal (x) axis, degrees."""
    Ry = rotations_from_rvecs(np.array([0.0, np.radians(about_v_deg), 0.0]))[0]
    Rx = rotations_from_rvecs(np.array([np.radians(about_h_deg), 0.0, 0.0]))[0]
    return Ry @ Rx


def candidate_poses(s: SensorResult, board: Board) -> list[np.ndarray]:
    """(4, 4) ``T_rig_board`` of the candidate poses in front of sensor ``s`` (not yet
    checked for feasibility): :data:`PLACES` x :data:`FILLS` x :data:`TILTS_DEG`."""
    obj = board.object_points()
    centre = 0.5 * (obj.min(axis=0) + obj.max(axis=0))
    extent = obj.max(axis=0) - obj.min(axis=0) + 2 * board.square_size_m
    intr, (w, h) = s.intrinsics, s.image_size
    out = []
    for fill in FILLS:
        z = max(extent[0] * intr.fx / (fill * w), extent[1] * intr.fy / (fill * h))
        for fu in PLACES:
            for fv in PLACES:
                ray = intr.normalized(np.array([fu * (w - 1), fv * (h - 1)]))
                for about_v, about_h in TILTS_DEG:
                    R = _rot(about_v, about_h)
                    T = make_T(R, np.r_[ray * z, z] - R @ centre)
                    out.append(s.T_rig_sensor @ T)
    return out


def feasible(T_rig_board: np.ndarray, sensors: Sequence[SensorResult], board: Board) -> bool:
    """Whether every sensor of ``sensors`` would find the board at ``T_rig_board`` (4, 4):
    its outline inside its image, inner corners with :data:`MARGIN` too, at least
    :data:`MIN_SPACING_PX` apart, the board at most :data:`MAX_OBLIQUE_DEG` off the line
    of sight."""
    obj, outline = board.object_points(), outline_points(board)
    for s in sensors:
        T = invert(s.T_rig_sensor) @ T_rig_board
        P = obj @ T[:3, :3].T + T[:3, 3]
        uv = s.intrinsics.project(P)
        edge = s.intrinsics.project(outline @ T[:3, :3].T + T[:3, 3])
        w, h = s.image_size
        m = MARGIN * min(w, h)
        if not (
            np.all(np.isfinite(uv))
            and np.all(uv >= m)
            and np.all(uv[:, 0] <= w - 1 - m)
            and np.all(uv[:, 1] <= h - 1 - m)
            and np.all(np.isfinite(edge))
            and np.all(edge >= 0)
            and np.all(edge <= (w - 1, h - 1))
        ):
            return False
        grid = uv.reshape(board.rows, board.cols, 2)
        spacing = min(
            float(np.min(np.linalg.norm(np.diff(grid, axis=1), axis=2))),
            float(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=2))),
        )
        if spacing < MIN_SPACING_PX:
            return False
        sight = P.mean(axis=0)
        cos = abs(T[:3, 2] @ sight) / np.linalg.norm(sight)
        if cos < np.cos(np.radians(MAX_OBLIQUE_DEG)):
            return False
    return True


def judged_specs(
    result: CalibrationResult, c: RigCovariance, v: RigVerdict
) -> list[tuple[tuple[str, ...], FigureSpec]]:
    """(sensors that must see a view for it to help, figure spec) of every figure the
    verdicts ``v`` of ``result`` judge (``c``: its covariance), but those of verdicts whose
    views disagree."""
    modalities = {n: s.modality for n, s in result.sensors.items()}
    out = []
    for name, s in result.sensors.items():
        if v.sensors[name].disagreement is not None:
            continue
        for spec in sensor_specs(c, s, result.reference, modalities):
            with_ref = spec.unit in ("°", "mm") and name != result.reference
            out.append(((name, result.reference) if with_ref else (name,), spec))
    for pair in v.pairs:
        if pair.disagreement is None:
            a, b = pair.sensors
            out += [((a, b), spec) for spec in pose_specs(c, a, b, modalities, "pair")]
    return [(who, spec) for who, spec in out if spec.target is not None]


def suggest_next_pose(
    result: CalibrationResult,
    candidates: Sequence[np.ndarray] | None = None,
    newcomers: Mapping[str, Any] | None = None,
) -> NextPose | None:
    """The board pose that would lower the worst sigma / target ratio of ``result``'s
    verdicts most (see the module doc), or None when every judged sigma meets its target
    (or no candidate lowers it: the verdict's advice then says what to do).

    Args:
        result: a calibration with its covariance and verdicts (calib.rig_calibration).
        candidates: (4, 4) ``T_rig_board`` poses to choose from (e.g. poses a user could
            reach); default: :func:`candidate_poses` in front of each sensor of the worst
            figure. Either way only poses every such sensor would see are kept.
        newcomers: sensors not calibrated yet (too few views), by name, with their
            nominal ``intrinsics``, ``image_size`` and ``T_rig_sensor`` (a Rig's sensors):
            while some candidate suits them too, only such candidates are kept, so that
            the next view also shows them the board.

    Raises:
        ValueError: ``result`` has no covariance or verdicts.
    """
    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):  # small products only
        return _suggest(result, candidates, dict(newcomers or {}))


def _suggest(
    result: CalibrationResult,
    candidates: Sequence[np.ndarray] | None,
    newcomers: dict[str, Any],
) -> NextPose | None:
    """:func:`suggest_next_pose`'s work (same arguments), BLAS limited by the caller."""
    c, v = result.covariance, result.verdict
    if c is None or v is None:
        raise ValueError(
            "suggest_next_pose: expected a calibration with its covariance and verdicts, "
            "got one without"
        )
    judged = judged_specs(result, c, v)
    if not judged:
        return None
    specs = [spec for _, spec in judged]
    now = [spec.figure(c) for spec in specs]
    figures = [f for f, _ in now]
    k_worst = int(np.argmax([f.ratio for f in figures]))
    worst_now = figures[k_worst]
    if worst_now.ratio <= 1.0:
        return None
    must = judged[k_worst][0]
    board, sensors = result.board, result.sensors
    if candidates is None:
        candidates = [T for s in must for T in candidate_poses(sensors[s], board)]
    poses = [np.asarray(T, dtype=np.float64) for T in candidates]
    poses = [T for T in poses if feasible(T, [sensors[s] for s in must], board)]
    new = {n: s for n, s in newcomers.items() if n not in sensors}
    shown = [T for T in poses if new and feasible(T, list(new.values()), board)]
    poses = shown or poses
    infos = pose_information(c, sensors, board, poses)
    predict = predictor(c, specs, figures, [b for _, b in now])
    scored = []
    for T, info in zip(poses, infos, strict=True):
        if info is None:
            continue
        after = predict(c.information + info)
        worst = max(after, key=lambda f: f.ratio)
        excess = sum(max(0.0, f.ratio - 1.0) ** 2 for f in after)
        scored.append((worst, excess, T))
    if not scored:
        return None
    best = min(w.ratio for w, _, _ in scored)
    if best >= worst_now.ratio * (1 - 1e-4):
        return None  # no candidate helps
    worst_after, _, T = min(
        (s for s in scored if s[0].ratio <= best * (1 + TIE)), key=lambda s: s[1]
    )
    nxt = describe(T, result.sensors, board, must, worst_now, worst_after)
    return replace(nxt, newcomers=tuple(new) if shown else ())


def describe(
    T_rig_board: np.ndarray,
    sensors: dict[str, SensorResult],
    board: Board,
    must: tuple[str, ...],
    worst_now: Figure,
    worst_after: Figure,
) -> NextPose:
    """The :class:`NextPose` of ``T_rig_board`` (4, 4): its outline in every sensor that
    sees all inner corners, and its place, distance and tilt in the subject sensor's frame:
    a colour camera among ``must`` or among those whose image holds the whole outline,
    else the first of ``must``."""
    outline = outline_points(board)
    obj = board.object_points()
    seen: dict[str, np.ndarray] = {}
    for name, s in sensors.items():
        T = invert(s.T_rig_sensor) @ T_rig_board
        uv = s.intrinsics.project(obj @ T[:3, :3].T + T[:3, 3])
        w, h = s.image_size
        if np.all(np.isfinite(uv)) and np.all((uv >= 0) & (uv <= (w - 1, h - 1))):
            seen[name] = s.intrinsics.project(outline @ T[:3, :3].T + T[:3, 3])
    whole = [n for n in must if n in seen]  # the outline lies in these (feasible())
    for n, uv in seen.items():
        w, h = sensors[n].image_size
        if (
            n not in whole
            and np.all(np.isfinite(uv))
            and np.all((uv >= 0) & (uv <= (w - 1, h - 1)))
        ):
            whole.append(n)  # its outline too lies in the image
    colour = [n for n in whole if sensors[n].modality == "color"]
    subject = colour[0] if colour else (whole or list(must))[0]
    s = sensors[subject]
    T = invert(s.T_rig_sensor) @ T_rig_board
    centre = T[:3, :3] @ (0.5 * (obj.min(axis=0) + obj.max(axis=0))) + T[:3, 3]
    n = T[:3, 2]  # the board's normal (+z away from the camera)
    about_v = float(np.degrees(np.arctan2(n[0], n[2])))
    about_h = float(np.degrees(np.arctan2(n[1], n[2])))
    uv = s.intrinsics.project(centre)
    return NextPose(
        np.asarray(T_rig_board, dtype=np.float64).copy(),
        subject,
        tuple(must),
        seen,
        worst_now,
        worst_after,
        float(np.linalg.norm(centre)),
        (float(uv[0]), float(uv[1])),
        (about_v, about_h),
        s.image_size,
    )
