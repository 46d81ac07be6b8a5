"""The calibration scenario of the simulated head, and the board views it is made of.

``calibration``: the head stands still (world = rig frame) and the heated board is held at
poses that cover every sensor's image, corners included, 0.6-4 m away, tilted up to 45
degrees, in a lab with a warm radiator and a cold window behind it. Like an operator who
waits for the console's beep, the board can wait at a pose until it is captured
(:class:`CaptureHold`: the console's auto-capture asks it to, so that a slow machine still
gets every pose). The inspection room
and its scenario are in :mod:`app.sources.sim.inspection` (the survey in
:mod:`app.sources.sim.survey`); the lab and the inspection room are built with :func:`room`
and :func:`quad`.
"""

from __future__ import annotations

import bisect
import hashlib
import math
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from trifuse.app.sources.frames import FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.render import HeadModel, Renderer, SensorTruth
from trifuse.app.sources.sim.scene import (
    Board,
    BoardMaterial,
    Box,
    Cylinder,
    Material,
    Quad,
    Scene,
    Solid,
    Sphere,
)
from trifuse.calib.board import aruco_dictionary
from trifuse.calib.rig import Rig, Sensor, rig_to_yaml
from trifuse.calib.transforms import make_T, rotation_about, rotation_from_euler_deg

CALIBRATION_BOARD = Board(cols=9, rows=6, square_size_m=0.06)
BOARD_MARGIN_M = 0.04  # bare aluminium around the patterned area
BOARD_PLATE_K = 296.0  # plate temperature before heating


def plate_extent_m(board: Board) -> tuple[float, float, float, float]:
    """The board plate ``(x0, x1, y0, y1)`` in the board frame, metres (a
    :class:`~app.sources.sim.scene.Quad`'s extent): the patterned area
    (``board.extent_m()``) and :data:`BOARD_MARGIN_M` of bare
    plate around it."""
    x0, y0, x1, y1 = board.extent_m()
    m = BOARD_MARGIN_M
    return (x0 - m, x1 + m, y0 - m, y1 + m)


def pattern_centre_m(board: Board) -> np.ndarray:
    """(3,) the middle of the board's patterned area in the board frame, metres (where the
    poses aim the board)."""
    x0, y0, x1, y1 = board.extent_m()
    return np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])


def quad(name: str, centre, rpy_deg, half_w: float, half_h: float, mat: Material) -> Quad:
    T = make_T(rotation_from_euler_deg(*rpy_deg), centre)
    return Quad(name, mat, T, (-half_w, half_w, -half_h, half_h))


def room(
    x: float, y_floor: float, y_ceil: float, z_front: float, z_back: float, wall_k: float
) -> list[Solid]:
    """Six walls of a box-shaped room; walls warmer towards the ceiling."""
    wall = Material(
        (0.62, 0.6, 0.55),
        wall_k,
        0.93,
        0.55,
        pattern=(0.45, 0.12),
        temperature_gradient_k_per_m=-0.4,
    )
    floor = Material((0.38, 0.33, 0.28), wall_k - 1.0, 0.95, 0.35, pattern=(0.6, 0.3))
    ceil = Material((0.85, 0.85, 0.85), wall_k + 0.8, 0.9, 0.7)
    zc, zh = (z_front + z_back) / 2, (z_back - z_front) / 2
    yc, yh = (y_floor + y_ceil) / 2, (y_floor - y_ceil) / 2
    return [
        quad("wall_back", (0, yc, z_back), (0, 0, 0), x, yh, wall),
        quad("wall_front", (0, yc, z_front), (0, 180, 0), x, yh, wall),
        quad("wall_left", (-x, yc, zc), (0, 90, 0), zh, yh, wall),
        quad("wall_right", (x, yc, zc), (0, -90, 0), zh, yh, wall),
        quad("floor", (0, y_floor, zc), (90, 0, 0), x, zh, floor),
        quad("ceiling", (0, y_ceil, zc), (-90, 0, 0), x, zh, ceil),
    ]


@dataclass(frozen=True)
class BoardFinish:
    """What the board's two kinds of squares are made of and how warm the plate is.

    The default is the simulated head's board: black matte foil (emissivity 0.95, NIR
    reflectance 0.06) on bare aluminium (0.12, 0.75), heated by ``heating_k`` kelvin (a
    negative value cools it). The colours (black squares dark in colour) never change;
    which squares read hot or dark in thermal and TOF images does.
    """

    heating_k: float = 22.0
    black_emissivity: float = 0.95
    white_emissivity: float = 0.12
    black_nir: float = 0.06
    white_nir: float = 0.75


THERMAL_FINISHES: dict[str, dict[str, float]] = {
    "heated": {},
    "cooled": {"heating_k": -25.0},
    "white-hot": {"black_emissivity": 0.12, "white_emissivity": 0.95},
}
"""Thermal variants of the board: ``heated`` (black squares hot), ``cooled`` (the same board
25 K colder at most: black squares cold), ``white-hot`` (heated, the high-emissivity paint on
the white squares: white squares hot)."""

TOF_FINISHES: dict[str, dict[str, float]] = {
    "dark": {},
    "bright": {"black_nir": 0.8, "white_nir": 0.2},
}
"""TOF amplitude variants: ``dark`` (black squares dark), ``bright`` (a black ink that
reflects the near infrared over a duller white: black squares bright)."""


def board_finish(thermal: str = "heated", tof: str = "dark") -> BoardFinish:
    """The :class:`BoardFinish` of a thermal and a TOF variant (names above)."""
    for what, name, table in (("thermal", thermal, THERMAL_FINISHES), ("tof", tof, TOF_FINISHES)):
        if name not in table:
            raise ValueError(f"{what} board variant: expected one of {sorted(table)}, got {name!r}")
    return BoardFinish(**{**THERMAL_FINISHES[thermal], **TOF_FINISHES[tof]})


def board_solid(
    T_world_board: np.ndarray,
    board: Board = CALIBRATION_BOARD,
    heating_k: float = 22.0,
    finish: BoardFinish | None = None,
) -> Quad:
    """The heated board as a quad in its own frame (calib.board), margin included: its
    pattern (checkerboard, ChArUco, circle grid) where the board's ``is_black`` says.

    ``finish`` (default: the simulated head's board heated by ``heating_k``) sets the
    squares' emissivities and NIR reflectances and the heating (it replaces ``heating_k``).
    """
    extent = plate_extent_m(board)
    x0, y0, x1, y1 = board.extent_m()
    f = finish if finish is not None else BoardFinish(heating_k=heating_k)
    mat = BoardMaterial(
        (0.8, 0.8, 0.78),
        BOARD_PLATE_K,
        board=board,
        heating_k=f.heating_k,
        hot_spot_xy_m=(0.3 * (x1 - x0), 0.2 * (y1 - y0)),
        black_emissivity=f.black_emissivity,
        white_emissivity=f.white_emissivity,
        black_nir=f.black_nir,
        white_nir=f.white_nir,
    )
    return Quad("board", mat, T_world_board, extent)


def lab_background() -> list[Solid]:
    """The calibration lab: walls, a warm radiator and a cold window (thermal clutter)."""
    solids = room(3.0, 1.2, -1.6, -2.0, 6.0, 294.0)
    solids.append(
        Box(
            "radiator",
            Material((0.9, 0.9, 0.88), 328.0, 0.92, 0.6),
            make_T(np.eye(3), (1.6, 0.5, 5.9)),
            (0.7, 0.35, 0.06),
        )
    )
    solids.append(
        quad(
            "window",
            (-1.4, -0.2, 5.98),
            (0, 0, 0),
            0.8,
            0.6,
            Material((0.55, 0.7, 0.85), 284.0, 0.9, 0.2),
        )
    )
    return solids


@dataclass
class CalibrationView:
    """One simulated capture of the board.

    Attributes:
        name: view folder name, "0001", ...
        T_rig_board: (4, 4) exact board pose in the rig frame, metres.
        frames: the images of every sensor of the rig.
        truth: exact per-pixel ground truth per sensor.
    """

    name: str
    T_rig_board: np.ndarray
    frames: FrameSet
    truth: dict[str, SensorTruth]


_TARGETS = [
    (0.16, 0.16),
    (0.84, 0.84),
    (0.84, 0.16),
    (0.16, 0.84),
    (0.5, 0.5),
    (0.5, 0.14),
    (0.86, 0.5),
    (0.5, 0.86),
    (0.14, 0.5),
]


def _plate_corners(board: Board) -> np.ndarray:
    x0, x1, y0, y1 = plate_extent_m(board)
    return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)


def calibration_poses(
    views: int, seed: int, rig: Rig, board: Board = CALIBRATION_BOARD
) -> list[np.ndarray]:
    """Board poses ``T_rig_board`` (4, 4) covering every sensor's image.

    View i targets sensor ``i mod n`` and one of nine image positions (corners first);
    the board is placed so it lies wholly inside that sensor's image at a distance drawn
    from 0.6-4 m (0.6-1.8 m for a TOF camera, whose board image gets small quickly; a
    ChArUco board no farther than that sensor reads its markers, at least to 1 m:
    :func:`_readable_within_m`), with a random tilt up to 45 degrees and roll up to 15
    degrees.
    """
    if views < 1:
        raise ValueError(f"views: expected at least 1, got {views}")
    rng = np.random.default_rng(seed)
    names = rig.names
    centre_b = pattern_centre_m(board)
    corners_b = _plate_corners(board)
    poses = []
    for i in range(views):
        sensor = rig[names[i % len(names)]]
        target = np.array(_TARGETS[(i // len(names)) % len(_TARGETS)])
        far = _readable_within_m(sensor, board, 1.8 if sensor.modality == "tof" else 4.0)
        distance = rng.uniform(0.6, far)
        tilt = np.radians(rng.uniform(0.0, 45.0))
        tilt_dir = rng.uniform(0.0, 2 * np.pi)
        roll = rng.uniform(-15.0, 15.0)
        w, h = sensor.image_size
        pose = None
        for _attempt in range(200):
            px = target * (w - 1, h - 1)
            ray = sensor.intrinsics.unproject(px)
            # Board frame: z along the viewing ray (the board faces the camera), x ~ right.
            z = ray
            x = np.cross((0.0, 1.0, 0.0), z)
            x /= np.linalg.norm(x)
            y = np.cross(z, x)
            R_face = np.stack([x, y, z], axis=1)
            axis = np.array([np.cos(tilt_dir), np.sin(tilt_dir), 0.0])
            R_tilt = rotation_about(axis, tilt)
            R = R_face @ R_tilt @ rotation_from_euler_deg(0.0, 0.0, roll)
            t = distance * ray - R @ centre_b
            T_s_b = make_T(R, t)
            uv = sensor.intrinsics.project((R @ corners_b.T).T + t)
            margin = 0.02 * np.array([w, h])
            if np.all(np.isfinite(uv)) and np.all(uv >= margin) and np.all(uv <= (w, h) - margin):
                pose = sensor.T_rig_sensor @ T_s_b
                break
            # Not inside: pull towards the image centre, then back off.
            target = 0.5 + 0.9 * (target - 0.5)
            if _attempt % 10 == 9:
                distance *= 1.08
        if pose is None:
            raise RuntimeError(f"could not place the board for view {i + 1} in {sensor.name}")
        poses.append(pose)
    return poses


MARKER_CELL_PX = 2.5
"""A ChArUco board's views aimed at a sensor keep its marker cells (bits) at least this
many pixels wide (where the sensor still has room for the board, from 1 m)."""


def _readable_within_m(sensor: Sensor, board: Board, far_m: float) -> float:
    """How far (metres) a view aimed at ``sensor`` may put ``board``: ``far_m``, for a
    ChArUco board no farther than its marker cells are :data:`MARKER_CELL_PX` wide, but
    not under 1 m (the TOF camera then sees markers it cannot read: it says so)."""
    if board.pattern != "charuco":
        return far_m
    cells = int(aruco_dictionary(board.dictionary).markerSize) + 2  # type: ignore[arg-type]
    cell_m = float(board.marker_size_m) / cells  # type: ignore[arg-type]
    return min(far_m, max(1.0, sensor.intrinsics.fx * cell_m / MARKER_CELL_PX))


PARTIAL_EVERY = 3
"""Every third view of a board that may be seen in part (ChArUco) leaves the image."""
PARTIAL_OVERHANG = (0.1, 0.4)
"""What fraction of the patterned area's image those views put beyond the border."""


def calibration_views(
    views: int,
    seed: int,
    rig: Rig | None = None,
    model: HeadModel | None = None,
    board: Board = CALIBRATION_BOARD,
    finish: BoardFinish | None = None,
    sensor_views: Mapping[str, int] | None = None,
) -> Iterator[CalibrationView]:
    """Render the calibration scenario lazily, one view (all sensors) at a time.

    Args:
        views, seed: how many views, and the seed of the poses and the noise.
        rig: the head (default: the simulated head's ground truth).
        model: the sensor models.
        board: the board (its poses follow its size); a board whose views may show part
            of it (ChArUco: ``board.partial_views``) is pushed over an image border in
            every :data:`PARTIAL_EVERY`-th view (:func:`partial_view_poses`), so that
            the image corners get covered.
        finish: what the marks are made of and how warm (default: the heated board).
        sensor_views: sensor -> N: that sensor's image is kept in N views only, views
            that show it the whole board where there are enough (spread evenly over the
            session: :func:`kept_views`); the others' are all kept.
    """
    rig = rig or default_rig()
    renderer = Renderer(rig, model)
    background = lab_background()
    rng = np.random.default_rng([seed, 1])
    poses = calibration_poses(views, seed, rig, board)
    if board.partial_views:
        partial = partial_view_poses(views, seed, rig, board, PARTIAL_OVERHANG)
        for i in range(PARTIAL_EVERY - 1, views, PARTIAL_EVERY):
            poses[i] = partial[i]
    keep = {}
    for name, n in (sensor_views or {}).items():
        inside = [i for i, T in enumerate(poses) if board_inside(rig[name], T, board)]
        pool = inside if len(inside) >= n else list(range(views))
        keep[name] = frozenset(pool[k] for k in kept_views(len(pool), n))
    for i, T_rig_board in enumerate(poses):
        scene = Scene([*background, board_solid(T_rig_board, board, finish=finish)])
        stamp_ns = int(i * 2e9)
        frames, truth = renderer.render(scene, np.eye(4), stamp_ns, rng)
        dropped = [s for s, k in keep.items() if i not in k]
        if dropped:
            frames = FrameSet(
                frames.stamp_ns, {n: f for n, f in frames.frames.items() if n not in dropped}
            )
            truth = {n: t for n, t in truth.items() if n not in dropped}
        yield CalibrationView(f"{i + 1:04d}", T_rig_board, frames, truth)


def board_inside(
    sensor: Sensor, T_rig_board: np.ndarray, board: Board, margin: float = 0.05
) -> bool:
    """Whether the whole board plate at ``T_rig_board`` (4, 4, rig frame) lies in front of
    ``sensor`` and inside its image, at least ``margin`` x the image size from the border."""
    T = np.linalg.inv(sensor.T_rig_sensor) @ T_rig_board
    P = _plate_corners(board) @ T[:3, :3].T + T[:3, 3]
    if not np.all(P[:, 2] > 0):
        return False
    uv = sensor.intrinsics.project(P)
    size = np.array(sensor.image_size, dtype=np.float64)
    inside = np.all(uv >= margin * size) and np.all(uv <= (1 - margin) * size)
    return bool(np.all(np.isfinite(uv)) and inside)


def kept_views(views: int, n: int) -> frozenset[int]:
    """Indices (0-based) of ``n`` of ``views`` views spread evenly over them, first and last
    included (all of them when ``n >= views``)."""
    if n < 0:
        raise ValueError(f"views kept: expected a number >= 0, got {n}")
    if n >= views:
        return frozenset(range(views))
    if n == 1:
        return frozenset({0})
    return frozenset(round(k * (views - 1) / (n - 1)) for k in range(n))


CAPTURE_WAIT_S = 30.0
"""How much longer than its hold (seconds of stream time) the simulated board waits at a
pose for a capture at most (:class:`CaptureHold`)."""


class CaptureHold:
    """The simulated board waits at a pose until it is captured, at most ``max_hold_s``.

    The simulated head asks :meth:`scenario_time` which scenario time its frame stamped
    ``stamp_ns`` shows (:class:`~app.sources.simulated.SimulatedHeadSource`). Without
    :attr:`waiting`, that is the stream's own time, ``(stamp_ns - start_ns) / 1e9``: each
    pose is shown for ``hold_s`` seconds. While :attr:`waiting` is set (the console does
    while auto-capture is on) and the pose shown has not been released (:meth:`release`,
    which the console calls when it captured a view of the pose or found nothing to take
    there), the scenario time stands still at the last moment of that pose instead of
    moving on to the next one, until the pose has been shown for ``max_hold_s`` seconds;
    then, or once released, the scenario time goes on from the end of that pose (the next
    pose follows at once). Poses are those the head shows: scenario time ``t`` shows pose
    ``round(t / hold_s) mod n_poses`` (one rendering per pose, ``render_hz = 1 / hold_s``).

    Stamps asked for again or out of order get the scenario time they were given (a
    history of the changes is kept); a new stream (another ``start_ns``) starts afresh,
    keeping what was released.

    Args:
        hold_s: seconds each pose is held without waiting.
        n_poses: how many poses the board cycles through.
        max_hold_s: the longest a pose is shown while waiting (at least ``hold_s``),
            seconds of stream time.

    Attributes:
        waiting: whether to wait at poses not released yet (set by the console).

    Thread-safe.
    """

    def __init__(self, hold_s: float, n_poses: int, max_hold_s: float) -> None:
        if not (hold_s > 0 and n_poses >= 1 and max_hold_s >= hold_s):
            raise ValueError(
                "capture hold: expected hold_s > 0, n_poses >= 1 and max_hold_s >= hold_s, "
                f"got hold_s={hold_s}, n_poses={n_poses}, max_hold_s={max_hold_s}"
            )
        self.hold_s, self.n_poses, self.max_hold_s = float(hold_s), n_poses, float(max_hold_s)
        self.waiting = False
        self._lock = threading.Lock()
        self._released: set[int] = set()
        self._restart(None)

    def _restart(self, start_ns: int | None) -> None:
        self._start_ns = start_ns
        self._shift = 0.0  # scenario time = stream time - shift (while not frozen)
        self._frozen: float | None = None  # the scenario time standing still
        self._last_s = -math.inf  # the latest stream time asked for
        self._last_t = 0.0  # the scenario time given for it
        self._pose = 0  # the pose shown since stream time _since
        self._since = 0.0
        # (stream time, shift, frozen) from which on the mapping holds: for stamps asked
        # for again or out of order
        self._changes: list[tuple[float, float, float | None]] = [(-math.inf, 0.0, None)]

    def __getstate__(self) -> dict[str, Any]:  # a scenario may be pickled to a process
        state = dict(self.__dict__)
        del state["_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def pose_at(self, t_s: float) -> int:
        """The pose the head shows at scenario time ``t_s`` (seconds)."""
        loop_s = self.n_poses * self.hold_s
        return round((t_s % loop_s) / self.hold_s) % self.n_poses

    def _holding(self, s: float) -> bool:
        return (
            self.waiting and self._pose not in self._released and s - self._since < self.max_hold_s
        )

    def _past(self, s: float) -> float:
        """The scenario time given for stream time ``s`` before the latest one."""
        i = bisect.bisect_right(self._changes, s, key=lambda c: c[0]) - 1
        _, shift, frozen = self._changes[max(i, 0)]
        return frozen if frozen is not None else s - shift

    def _change(self, s: float) -> None:
        self._changes.append((s, self._shift, self._frozen))
        if len(self._changes) > 4096:
            del self._changes[1:1025]

    def scenario_time(self, stamp_ns: int, start_ns: int) -> float:
        """The scenario time (seconds) the frame stamped ``stamp_ns`` of a stream started
        at ``start_ns`` shows (class docstring)."""
        with self._lock:
            if start_ns != self._start_ns:
                self._restart(start_ns)
            s = (stamp_ns - start_ns) / 1e9
            if s < self._last_s:
                return self._past(s)
            self._last_s = s
            if self._frozen is not None:
                if self._holding(s):
                    return self._frozen
                # on from the end of the held pose: the next one at once
                end = (round(self._frozen / self.hold_s) + 0.5 + 1e-6) * self.hold_s
                self._shift, self._frozen = s - end, None
                self._change(s)
            t = s - self._shift
            pose = self.pose_at(t)
            if pose != self._pose:
                if self._holding(s):
                    self._frozen = self._last_t
                    self._change(s)
                    return self._frozen
                self._pose, self._since = pose, s
            self._last_t = t
            return t

    def release(self, stamp_ns: int) -> int | None:
        """The pose shown at ``stamp_ns`` (a frame of the current stream) needs no more
        waiting: it was captured, or there is nothing to take there. Returns that pose
        (None before any stream)."""
        with self._lock:
            if self._start_ns is None:
                return None
            s = (stamp_ns - self._start_ns) / 1e9
            if s < self._last_s:
                t = self._past(s)
            else:
                t = self._frozen if self._frozen is not None else s - self._shift
            pose = self.pose_at(t)
            self._released.add(pose)
            return pose

    def status(self) -> str | None:
        """What the board is waiting for, for the operator (None: it is not waiting)."""
        with self._lock:
            if self._frozen is None:
                return None
            there = self._last_s - self._since
            return (
                f"the simulated board waits at pose {self._pose + 1} of {self.n_poses} for "
                f"a capture ({there:.0f} s there, at most {self.max_hold_s:.0f} s)"
            )


class CalibrationScenario:
    """The calibration session as a live scene: the head stands still and the heated
    ``board`` (any pattern) is held at each of ``n_poses`` poses (:func:`calibration_poses`;
    a ChArUco board leaves the image in every :data:`PARTIAL_EVERY`-th) for ``hold_s``
    seconds, then jumps to the next; the sequence loops every ``loop_s`` seconds. While
    :attr:`capture_hold` is ``waiting``, a pose not captured yet is held up to
    ``capture_wait_s`` seconds longer (:class:`CaptureHold`).

    For :class:`~app.sources.simulated.SimulatedHeadSource` use ``render_hz = 1 / hold_s``
    and ``loop_s = loop_s``: one rendering per board pose (``scene_key`` tells the source
    which times show the same scene, :meth:`scenario_time` which time a frame shows).
    """

    def __init__(
        self,
        rig: Rig | None = None,
        model: HeadModel | None = None,
        n_poses: int = 40,
        hold_s: float = 3.0,
        seed: int = 1,
        board: Board = CALIBRATION_BOARD,
        capture_wait_s: float = CAPTURE_WAIT_S,
    ) -> None:
        if not hold_s > 0:
            raise ValueError(f"hold_s: expected a positive number of seconds, got {hold_s}")
        if not capture_wait_s >= 0:
            raise ValueError(f"capture_wait_s: expected seconds >= 0, got {capture_wait_s}")
        self.rig = rig or default_rig()
        self.renderer = Renderer(self.rig, model)
        self.model = model
        self.board = board
        self.poses = calibration_poses(n_poses, seed, self.rig, board)
        if board.partial_views:  # as in calibration_views: some poses leave the image
            partial = partial_view_poses(n_poses, seed, self.rig, board, PARTIAL_OVERHANG)
            for i in range(PARTIAL_EVERY - 1, n_poses, PARTIAL_EVERY):
                self.poses[i] = partial[i]
        self.background = lab_background()
        self.n_poses, self.hold_s, self.seed = n_poses, float(hold_s), seed
        self.loop_s = n_poses * self.hold_s
        self.capture_hold = CaptureHold(self.hold_s, n_poses, self.hold_s + capture_wait_s)
        """Waits at poses not captured yet while the console's auto-capture is on."""

    def cache_key(self) -> str:
        """What identifies this scenario's pictures (for the simulated head's disk cache)."""
        rig = hashlib.sha256(rig_to_yaml(self.rig).encode()).hexdigest()[:16]
        key = f"poses={self.n_poses} hold={self.hold_s} seed={self.seed} rig={rig} {self.model!r}"
        return key if self.board == CALIBRATION_BOARD else f"{key} board={self.board!r}"

    def pose_index(self, t_s: float) -> int:
        """Which board pose is held at scenario time ``t_s`` (seconds)."""
        return int(np.floor(t_s / self.hold_s)) % self.n_poses

    def scene_key(self, t_s: float) -> int:
        """Times with equal keys show the same scene (the same board pose)."""
        return self.pose_index(t_s)

    def scenario_time(self, stamp_ns: int, start_ns: int) -> float:
        """The scenario time (seconds) a frame stamped ``stamp_ns`` of a stream started at
        ``start_ns`` shows: :meth:`CaptureHold.scenario_time`."""
        return self.capture_hold.scenario_time(stamp_ns, start_ns)

    def T_world_rig(self, t_s: float) -> np.ndarray:
        """The head does not move: the world frame is the rig frame."""
        return np.eye(4)

    def T_rig_board(self, t_s: float) -> np.ndarray:
        """(4, 4) exact board pose in the rig frame at ``t_s``, metres."""
        return self.poses[self.pose_index(t_s)]

    def render(
        self, t_s: float, sensors: list[str] | None = None
    ) -> tuple[FrameSet, dict[str, SensorTruth]]:
        """Frames and exact ground truth at ``t_s``; noise is seeded by (seed, pose)."""
        i = self.pose_index(t_s)
        rng = np.random.default_rng([self.seed, 2, i])
        scene = Scene([*self.background, board_solid(self.poses[i], self.board)])
        return self.renderer.render(scene, np.eye(4), round(t_s * 1e9), rng, sensors)


# -- hard thermal views (issue 15: app.sources.sim.thermal_conditions) ----------------------


def _facing_pose(
    sensor: Sensor, px: np.ndarray, distance: float, R_extra: np.ndarray, centre_b: np.ndarray
) -> np.ndarray:
    """``T_sensor_board`` (4, 4) with the board's inner-corner centre ``centre_b`` at
    ``distance`` (m) along the ray of pixel ``px`` (2,), facing the camera, then turned by
    ``R_extra`` (3, 3) about that centre."""
    ray = sensor.intrinsics.unproject(px)
    z = ray / np.linalg.norm(ray)
    x = np.cross((0.0, 1.0, 0.0), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1) @ R_extra
    return make_T(R, distance * z - R @ centre_b)


def partial_view_poses(
    views: int,
    seed: int,
    rig: Rig,
    board: Board = CALIBRATION_BOARD,
    overhang: tuple[float, float] = (-0.1, 0.45),
) -> list[np.ndarray]:
    """Board poses ``T_rig_board`` (4, 4) that put the board across the image border.

    View i is aimed at sensor ``i mod n`` of ``rig``: the board (0.8-3 m away, tilted up
    to 35 degrees, rolled up to 15) is pushed over one edge or corner of that image
    (seeded) so that a fraction drawn from ``overhang`` (default -0.1: wholly inside, outer
    squares at the border, to 0.45) of its patterned area's image lies beyond it. Whether
    every inner corner is still in view is for the caller to work out from the exact
    projection.
    """
    if views < 1:
        raise ValueError(f"views: expected at least 1, got {views}")
    rng = np.random.default_rng([seed, 18])
    names = rig.names
    centre_b = pattern_centre_m(board)
    x0, y0, x1, y1 = board.extent_m()
    outline_b = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
    sides = [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (-1, 1), (1, 1)]
    poses = []
    for i in range(views):
        sensor = rig[names[i % len(names)]]
        w, h = sensor.image_size
        distance = rng.uniform(0.8, 3.0)
        tilt = np.radians(rng.uniform(0.0, 35.0))
        tilt_dir = rng.uniform(0.0, 2 * np.pi)
        R_extra = rotation_about(np.array([np.cos(tilt_dir), np.sin(tilt_dir), 0.0]), tilt)
        R_extra = R_extra @ rotation_from_euler_deg(0.0, 0.0, rng.uniform(-15.0, 15.0))
        side = sides[int(rng.integers(len(sides)))]
        over = rng.uniform(*overhang)
        along = rng.uniform(0.25, 0.75)
        centre_px = np.array([(w - 1) / 2, (h - 1) / 2])
        T0 = _facing_pose(sensor, centre_px, distance, R_extra, centre_b)
        uv = sensor.intrinsics.project((T0[:3, :3] @ outline_b.T).T + T0[:3, 3])
        size = uv.max(axis=0) - uv.min(axis=0)
        target = np.empty(2)
        for k, (d, extent) in enumerate(zip(side, (w, h), strict=True)):
            if d < 0:
                target[k] = (0.5 - over) * size[k]
            elif d > 0:
                target[k] = extent - 1 - (0.5 - over) * size[k]
            else:
                target[k] = along * (extent - 1)
        T_s_b = _facing_pose(sensor, target, distance, R_extra, centre_b)
        poses.append(sensor.T_rig_sensor @ T_s_b)
    return poses


HOT_PIPE_K = 333.15
"""The hot pipe beside the board: 60 C."""


def hot_objects_beside_board(
    T_rig_board: np.ndarray, board: Board = CALIBRATION_BOARD, seed: int = 0
) -> list[Solid]:
    """Hot clutter around the board at ``T_rig_board`` (4, 4): a vertical 60 C pipe beside
    it (5-25 cm from the plate, on a seeded side) and the person holding it (a 33 C body
    behind the board, sticking out on the other side, a 37 C head above it, 34 C hands on
    the plate's edges in front). Hands and pipe may hide parts of the board: what is
    visible comes from the render's truth. Names: ``hot_pipe``, ``person_body``, ``person_head``,
    ``hand_left``, ``hand_right``."""
    rng = np.random.default_rng([seed, 19])
    x_lo, x_hi, y_lo, y_hi = plate_extent_m(board)
    cy = 0.5 * (y_lo + y_hi)
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    pipe_r = rng.uniform(0.03, 0.05)
    gap = rng.uniform(0.05, 0.25) + pipe_r
    pipe_x = x_hi + gap if side > 0 else x_lo - gap

    def world(p: tuple[float, float, float]) -> np.ndarray:
        return T_rig_board[:3, :3] @ np.asarray(p, dtype=np.float64) + T_rig_board[:3, 3]

    pipe = Cylinder(
        "hot_pipe",
        Material((0.5, 0.5, 0.52), HOT_PIPE_K, 0.9, 0.5),
        make_T(np.eye(3), world((pipe_x, cy, rng.uniform(-0.1, 0.3)))),
        pipe_r,
        (-1.2, 1.2),
    )
    # The person stands behind the board (world-vertical body, head on top), far enough
    # along the board's normal that no part of them comes through a tilted board.
    normal = T_rig_board[:3, 2]  # board +z: away from the camera
    body_r, top, bottom = 0.2, -0.75, 1.0  # head top and feet, metres from board height
    lean = abs(normal[1])
    depth = 0.1 + max(abs(top), bottom) * lean + body_r * np.sqrt(max(0.0, 1 - lean**2))
    body_x = 0.5 * (x_lo + x_hi) - side * rng.uniform(0.1, 0.3) * (x_hi - x_lo)
    base = world((body_x, cy, 0.0)) + depth * normal
    body = Cylinder(
        "person_body",
        Material((0.2, 0.28, 0.5), 306.0, 0.95, 0.4, pattern=(0.12, 0.15)),
        make_T(np.eye(3), base),
        body_r,
        (-0.5, bottom),
    )
    head = Sphere(
        "person_head",
        Material((0.76, 0.57, 0.45), 310.15, 0.98, 0.45),
        tuple(base + np.array([0.0, -0.62, 0.0])),
        0.11,
    )
    skin = Material((0.76, 0.57, 0.45), 307.0, 0.98, 0.45)
    hands = [
        Sphere(name, skin, tuple(world((x, cy + rng.uniform(-0.1, 0.1), -0.04))), 0.045)
        for name, x in (("hand_left", x_lo), ("hand_right", x_hi))
    ]
    return [pipe, body, head, *hands]
