"""One sighting of the board: every sensor of a frame set searched, the pose, steadiness.

:func:`sighting` searches the sensors of a frame set in the order their detection is trusted
for the pose (:data:`POSE_PREFERENCE`: colour, thermal, TOF) and gives a
:class:`BoardSighting`: each sensor's corners (or why not), the board's pose in the rig frame
(:func:`calib.board_pose.board_pose_single`, from the most trusted sensor that found it)
and whether the board held still since the previous sighting (:class:`Motion`).
:class:`LookCache` shares the looks at each image between threads;
:class:`~app.server.runtime.board_watch.BoardWatch` decides when and on which threads the
searches run.

Stillness is judged in frame time, never per search: two looks at the board (two frame
sets) are compared by how far its corners moved and how far apart the frames' own time
stamps are (:func:`compare_looks`). A board is still when its corners moved at most
:data:`STEADY_PX` (the detector's noise) plus :data:`STILL_PX_PER_S` for each second of
frame time between the looks, counted up to :data:`STILL_WINDOW_S` (a pose change is never
still, however long the looks took); looks at different pictures less than
:data:`STILL_MIN_SPAN_S` apart tell nothing yet, and the very same pictures (a simulated
board holding its pose, a source repeating a frame) moved by nothing. A machine whose
searches take seconds therefore still decides: its two looks are far apart in frame time
and allowed the drift of that time, and the board watch compares each search with a look at
the newest frames as well (:meth:`~app.server.runtime.board_watch.BoardWatch.tick`).

Colour images of at least :data:`COARSE_MIN_WIDTH` pixels are searched at half resolution
first (:func:`first_look`), the corners then found at full resolution in a crop around the
board; a full-resolution search of the whole image only when the half-resolution one finds
nothing, and not where the pose from another sensor puts the board (partly) outside the
image (:func:`board_in_image`).

Which squares read hot or dark in a thermal or TOF image depends on the board
(calib.polarity): the images are searched with ``board.yaml``'s polarity keys when it sets
them, and otherwise each complete sighting puts every thermal and TOF detection in the
ordering that agrees with the board pose a colour camera found, through the rig in use
(:func:`orient_by_colour`), so that the Feeds panel, the steadiness and auto-capture see
the corners in the right order.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.app.sources.frames import FrameSet
from trifuse.calib.board import MIN_POSE_POINTS, Board
from trifuse.calib.board_ordering import orient_to_pose
from trifuse.calib.board_pose import board_pose_single
from trifuse.calib.detect import Detection
from trifuse.calib.polarity import detect_board_configured, override
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import invert

STEADY_PX = 2.0
"""The detector's noise: two looks at a board that did not move agree within this many
pixels (every corner, in every sensor that saw it both times)."""
STILL_PX_PER_S = 4.0
"""Beyond :data:`STEADY_PX`, a still board's corners may drift this many pixels per second of
frame time between two looks (a hand holding the board; 0.13 px per frame at 30 Hz)."""
STILL_WINDOW_S = 1.0
"""The drift allowed grows with frame time up to this many seconds and no further: looks
farther apart (a slow machine) allow :data:`STEADY_PX` + :data:`STILL_PX_PER_S` x this at
most, so a board moved to another pose never reads still."""
STILL_MIN_SPAN_S = 0.2
"""Looks at different pictures closer than this in frame time (seconds) do not tell whether
the board is still: a later frame must be looked at."""

POSE_PREFERENCE = ("color", "thermal", "tof")
"""Modalities in the order their detection is trusted for the board's pose."""

COARSE_MIN_WIDTH = 960
"""Colour images at least this wide are searched at half resolution first."""
COARSE_CROP_MARGIN = 2.0
"""The full-resolution crop around a board found at half resolution reaches this many
corner spacings (plus 8 px) beyond the outer corners: the outer squares, the board's
margin and a quiet zone for the detector."""

Detector = Callable[[np.ndarray, Board, str], Detection]


@dataclass(frozen=True, eq=False)
class BoardSighting:
    """One detection pass over a frame set.

    Attributes:
        frames: the frame set that was searched (what a capture of this sighting writes).
        detections: sensor -> :class:`~calib.detect.Detection` (corners (N, 2) px or a
            reason); a partial sighting has those of the sensors searched so far.
        T_rig_board: (4, 4) board pose in the rig frame, metres (from the most trusted
            sensor that found it, with the rig's intrinsics and pose), or None.
        pose_sensor: the sensor the pose comes from, or None.
        steady: the board was still (:attr:`motion`): found in at least one sensor, and
            compared with another look at it in frame time, within the drift allowed.
        complete: every sensor was searched (False: the pose was published early).
        motion: how far the board moved against the look it was compared with, in frame
            time (None: nothing to compare with, such as a first sighting).
    """

    frames: FrameSet
    detections: dict[str, Detection]
    T_rig_board: np.ndarray | None
    pose_sensor: str | None
    steady: bool
    complete: bool = True
    motion: Motion | None = None

    @property
    def found(self) -> list[str]:
        """Sensors whose image shows the board."""
        return [s for s, d in self.detections.items() if d.found]


def still_limit_px(span_s: float) -> float:
    """How far (pixels) a still board's corners may move between two looks ``span_s``
    seconds of frame time apart: :data:`STEADY_PX` + :data:`STILL_PX_PER_S` x the span,
    counted up to :data:`STILL_WINDOW_S`."""
    return STEADY_PX + STILL_PX_PER_S * min(max(span_s, 0.0), STILL_WINDOW_S)


@dataclass(frozen=True)
class Motion:
    """How far the board moved between two looks at it, in frame time.

    Attributes:
        moved_px: the largest corner displacement, pixels, in ``sensor`` (inf: the board
            was lost, or a partial view shares no corner with the other look).
        span_s: frame time between the two looks at ``sensor`` (its frames' stamps),
            seconds; 0 for the very same picture.
        sensor: the sensor compared (of several, the one that moved most for its span).
        same_picture: ``sensor``'s image is the very object looked at before (a
            simulated board holding its pose, a source repeating a frame): nothing moved.
    """

    moved_px: float
    span_s: float
    sensor: str
    same_picture: bool = False

    @property
    def limit_px(self) -> float:
        """How far the corners may move for :attr:`span_s` (:func:`still_limit_px`)."""
        return still_limit_px(self.span_s)

    @property
    def decided(self) -> bool:
        """Whether the looks tell: the same picture, or at least :data:`STILL_MIN_SPAN_S`
        apart."""
        return self.same_picture or self.span_s >= STILL_MIN_SPAN_S

    @property
    def still(self) -> bool:
        """Decided, and the corners moved no more than :attr:`limit_px`."""
        return self.decided and self.moved_px <= self.limit_px

    @property
    def speed_px_s(self) -> float:
        """Mean speed of the corners between the looks, pixels per second of frame time
        (inf: lost, or no time between them)."""
        if self.same_picture:
            return 0.0
        return self.moved_px / self.span_s if self.span_s > 0 else math.inf

    def describe(self) -> str:
        """One line for the operator, e.g. ``moving: 7.3 px in 1.20 s of frame time
        (6.1 px/s); still needs at most 6.0 px``."""
        if self.same_picture:
            return "still: the same picture as before"
        if not self.decided:
            return (
                f"waiting for frames: the looks at {self.sensor} are "
                f"{1000 * self.span_s:.0f} ms apart, {1000 * STILL_MIN_SPAN_S:.0f} ms tell"
            )
        word = "still" if self.still else "moving"
        if not math.isfinite(self.moved_px):
            return f"{word}: the board left {self.sensor}'s view"
        return (
            f"{word}: {self.moved_px:.1f} px in {self.span_s:.2f} s of frame time "
            f"({self.speed_px_s:.1f} px/s) in {self.sensor}; still needs at most "
            f"{self.limit_px:.1f} px"
        )


def compare_looks(
    before: FrameSet,
    before_detections: dict[str, Detection],
    now: FrameSet,
    now_detections: dict[str, Detection],
) -> Motion | None:
    """How the board moved from one look to another (:class:`Motion`), from every sensor
    that found it both times: the pictures' own time stamps, not when they were searched.

    A sensor whose image is the very object of the other look moved by nothing. Of the
    sensors whose looks tell (:attr:`Motion.decided`), the one that moved most for its
    span is returned; if none tells, the one whose looks are farthest apart. None when no
    sensor found the board both times.
    """
    compared: list[Motion] = []
    for name, det in now_detections.items():
        old = before_detections.get(name)
        if not det.found or old is None or not old.found:
            continue
        a, b = before.frames.get(name), now.frames.get(name)
        if a is None or b is None:
            continue
        if a.image is b.image:
            compared.append(Motion(0.0, abs(b.stamp_ns - a.stamp_ns) / 1e9, name, True))
            continue
        span_s = abs(b.stamp_ns - a.stamp_ns) / 1e9
        compared.append(Motion(_moved_px(det.corners, old.corners), span_s, name))
    if not compared:
        return None
    decided = [m for m in compared if m.decided]
    if not decided:
        return max(compared, key=lambda m: m.span_s)
    # the most moved for its span; of equals, a look at a new picture (it says more)
    return max(decided, key=lambda m: (m.moved_px / m.limit_px, not m.same_picture))


def board_in_image(rig: Rig, sensor: str, T_rig_board: np.ndarray, board: Board) -> bool:
    """Whether every inner corner of the board at ``T_rig_board`` (4, 4) projects into
    ``sensor``'s image (in front of it, within its pixels), by the rig's calibration; of a
    board seen in part (ChArUco), whether at least :data:`MIN_POSE_POINTS` do."""
    s = rig[sensor]
    T = invert(s.T_rig_sensor) @ np.asarray(T_rig_board, dtype=np.float64)
    P = board.object_points() @ T[:3, :3].T + T[:3, 3]
    uv = s.intrinsics.project(P)
    w, h = s.image_size
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    inside &= np.isfinite(uv).all(axis=1) & (P[:, 2] > 0)
    if board.partial_views:
        return int(inside.sum()) >= MIN_POSE_POINTS
    return bool(np.all(inside))


def orient_by_colour(
    detections: dict[str, Detection],
    rig: Rig,
    board: Board,
    T_rig_board: np.ndarray | None,
    pose_sensor: str | None,
) -> dict[str, Detection]:
    """Thermal and TOF detections in the ordering that agrees with a colour camera's.

    Which squares read hot or dark in a thermal or TOF image depends on the board
    (calib.polarity); unless ``board.yaml`` fixes it, each such detection is compared with
    where the board pose ``T_rig_board`` (4, 4), found by the colour camera ``pose_sensor``,
    puts the corners in that sensor's image through the rig, and is reversed (relabelled by
    the half turn, method suffixed ``-turned``) when the reversed ordering is the one that
    agrees. Without a colour camera's pose, or where the expected corners do not tell, the
    detections stay as they are. A ChArUco board's markers name every corner: its
    detections are never turned.
    """
    if T_rig_board is None or pose_sensor is None or rig[pose_sensor].modality != "color":
        return detections
    if board.pattern == "charuco":
        return detections
    out = dict(detections)
    for name, det in detections.items():
        m = rig[name].modality
        if not det.found or m not in ("thermal", "tof") or override(board, m) is not None:
            continue
        T_sensor_board = invert(rig[name].T_rig_sensor) @ T_rig_board
        got = orient_to_pose(det.corners, rig[name].intrinsics, T_sensor_board, board)
        if got is not None and got[1]:
            out[name] = Detection(got[0], None, f"{det.method}-turned")
    return out


def _corner_spacing(corners: np.ndarray, board: Board) -> float:
    """Median distance between neighbouring points (N, 2) of the board's grid (along a row
    and down a column; corners not seen, NaN rows, left out), pixels."""
    G = corners.reshape(board.rows, board.cols, 2)
    dx = np.linalg.norm(np.diff(G, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(G, axis=0), axis=2)
    d = np.concatenate([dx.ravel(), dy.ravel()])
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else 0.0


def first_look(
    image: np.ndarray, board: Board, modality: str, detect: Detector = detect_board_configured
) -> tuple[Detection, bool]:
    """Search one sensor image, colour images of at least :data:`COARSE_MIN_WIDTH` pixels
    at half resolution first.

    Returns:
        (detection, coarse): the detection in the original image's pixels (as
        ``detect`` gives it, its method suffixed ``-crop`` when the corners come from the
        full-resolution crop around a board found at half resolution), and whether only
        the half-resolution image was searched and showed no board (a full-resolution
        search might still find a small one).
    Raises:
        ValueError: what ``detect`` raises for an image it cannot search.
    """
    a = np.asarray(image)
    coarse_ok = modality == "color" and a.dtype == np.uint8 and a.ndim in (2, 3)
    if not coarse_ok or a.shape[1] < COARSE_MIN_WIDTH:
        return detect(a, board, modality), False
    h, w = a.shape[:2]
    small = cv2.resize(a, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    coarse = detect(small, board, modality)
    if not coarse.found:
        return Detection(None, f"{coarse.reason} (half resolution)", coarse.method), True
    # pixel centres: full = (half + 0.5) * 2 - 0.5 (docs/CONVENTIONS.md)
    G = (coarse.corners + 0.5) * 2.0 - 0.5
    margin = COARSE_CROP_MARGIN * _corner_spacing(G, board) + 8.0
    x0 = max(0, int(np.floor(np.nanmin(G[:, 0]) - margin)))
    x1 = min(w, int(np.ceil(np.nanmax(G[:, 0]) + margin)) + 1)
    y0 = max(0, int(np.floor(np.nanmin(G[:, 1]) - margin)))
    y1 = min(h, int(np.ceil(np.nanmax(G[:, 1]) + margin)) + 1)
    fine = detect(np.ascontiguousarray(a[y0:y1, x0:x1]), board, modality)
    if fine.found:
        corners = fine.corners + np.array([x0, y0], dtype=np.float64)
        return Detection(corners, None, f"{fine.method}-crop"), False
    return detect(a, board, modality), False  # the crop misled (rare): the whole image


Looker = Callable[[str, np.ndarray, str], tuple[Detection, bool]]
"""(sensor, image, modality) -> :func:`first_look`'s (detection, coarse)."""


def safe_look(
    looker: Looker, name: str, image: np.ndarray, modality: str
) -> tuple[Detection, bool]:
    """``looker``'s result, or a detection saying why a malformed image was not searched."""
    try:
        return looker(name, image, modality)
    except ValueError as exc:  # a malformed frame: say so, keep watching
        return Detection(None, f"cannot search this image: {exc}", None), False


class LookCache:
    """Per sensor, the newest image looked at and its :func:`first_look` result, shared by
    the threads that ask for it: a second request for the very same image object waits
    for the first one's result instead of searching again.

    Args:
        board: the checkerboard.
        detect: the detector.
    """

    def __init__(self, board: Board, detect: Detector = detect_board_configured) -> None:
        self.board, self.detect = board, detect
        self._lock = threading.Lock()
        self._entries: dict[str, tuple[np.ndarray, Future]] = {}

    def __call__(self, name: str, image: np.ndarray, modality: str) -> tuple[Detection, bool]:
        with self._lock:
            entry = self._entries.get(name)
            mine = entry is None or entry[0] is not image
            if mine:
                entry = (image, Future())
                self._entries[name] = entry
        fut = entry[1]  # type: ignore[index]
        if mine:
            try:
                fut.set_result(first_look(image, self.board, modality, self.detect))
            except BaseException as exc:  # the waiting threads get it too
                fut.set_exception(exc)
        return fut.result()


class _Now:
    """A finished :class:`~concurrent.futures.Future` look-alike (no pool)."""

    def __init__(self, fn: Callable[..., Detection], *args: object) -> None:
        self._value = fn(*args)

    def result(self) -> Detection:
        return self._value


def trusted(rig: Rig, names: list[str]) -> list[str]:
    """``names`` in the order of :data:`POSE_PREFERENCE` (stable within a modality)."""
    rank = {m: i for i, m in enumerate(POSE_PREFERENCE)}
    return sorted(names, key=lambda n: rank.get(rig[n].modality, len(rank)))


def sighting(
    frames: FrameSet,
    rig: Rig,
    board: Board,
    previous: BoardSighting | None = None,
    pool: ThreadPoolExecutor | None = None,
    *,
    on_pose: Callable[[BoardSighting], None] | None = None,
    full_search: Collection[str] | None = None,
    detect: Detector = detect_board_configured,
    looker: Looker | None = None,
) -> BoardSighting:
    """Detect the board in every frame of ``frames`` (sensors of ``rig`` only).

    An image that is the very object the previous sighting searched (a source repeating a
    frame) keeps its detection. The sensors are searched in the order of
    :data:`POSE_PREFERENCE` (in ``pool``'s threads if given); as soon as the most trusted
    sensor showing the board is known, ``on_pose`` gets a partial sighting with the pose.

    Args:
        full_search: colour cameras that may get a full-resolution search when the
            half-resolution one finds nothing (:func:`first_look`), unless the pose from
            another sensor puts the board (partly) outside their image; None: all.
        detect: the detector (:func:`calib.detect.detect_board`'s signature; default
            :func:`calib.polarity.detect_board_configured`: with the board file's polarity
            overrides).
        looker: does the first look at a sensor's image (default :func:`first_look` with
            ``detect``); :class:`LookCache` shares looks between threads.
    """
    names = trusted(rig, [s for s in frames.frames if s in rig])
    first = looker or (lambda name, image, modality: first_look(image, board, modality, detect))

    def reused(name: str) -> Detection | None:
        if previous is None or name not in previous.detections:
            return None
        seen = previous.frames.frames.get(name)
        if seen is not None and seen.image is frames.frames[name].image:  # the same image
            return previous.detections[name]
        return None

    def look(name: str) -> tuple[Detection, bool]:
        old = reused(name)
        if old is not None:
            return old, False
        return safe_look(first, name, frames.frames[name].image, rig[name].modality)

    def full(name: str) -> Detection:
        try:
            return detect(frames.frames[name].image, board, rig[name].modality)
        except ValueError as exc:
            return Detection(None, f"cannot search this image: {exc}", None)

    def submit(fn: Callable[..., object], name: str) -> Future | _Now:
        return pool.submit(fn, name) if pool is not None else _Now(fn, name)  # type: ignore

    looks = {n: submit(look, n) for n in names}
    detections: dict[str, Detection] = {}
    missed: list[str] = []  # colour cameras searched at half resolution only, in vain
    pose_sensor: str | None = None
    pose: np.ndarray | None = None
    published = False
    for name in names:  # in order of trust: the first found gives the pose
        det, coarse = looks[name].result()  # type: ignore[misc]
        detections[name] = det
        if coarse:
            missed.append(name)
        if pose_sensor is None and det.found:
            pose = board_pose_single(rig, name, det.corners, board)
            if pose is not None:
                pose_sensor = name
        if pose is not None and not published and on_pose is not None:
            if len(detections) < len(names):  # more to come: publish now
                on_pose(BoardSighting(frames, dict(detections), pose, pose_sensor, False, False))
                published = True
    # a full-resolution search only where the board may be (too small at half resolution):
    # not where the pose from another sensor puts it (partly) outside the image
    retries = {
        n: submit(full, n)
        for n in missed
        if (full_search is None or n in full_search)
        and (pose is None or board_in_image(rig, n, pose, board))
    }
    if retries and pose is not None and not published and on_pose is not None:
        on_pose(BoardSighting(frames, dict(detections), pose, pose_sensor, False, False))
    if retries:
        for name, fut in retries.items():
            detections[name] = fut.result()  # type: ignore[assignment]
        pose_sensor, pose = None, None
        for name in names:
            det = detections[name]
            if det.found and (T := board_pose_single(rig, name, det.corners, board)) is not None:
                pose_sensor, pose = name, T
                break
    detections = orient_by_colour(detections, rig, board, pose, pose_sensor)
    motion = None
    if previous is not None:
        motion = compare_looks(previous.frames, previous.detections, frames, detections)
    steady = motion is not None and motion.still
    ordered = {n: detections[n] for n in frames.frames if n in detections}
    return BoardSighting(frames, ordered, pose, pose_sensor, steady, motion=motion)


def _moved_px(now: np.ndarray, before: np.ndarray) -> float:
    """How far (pixels) the corners (N, 2) seen both times moved at most; inf when a partial
    view (NaN rows) shares no corner with the previous one."""
    d = np.linalg.norm(now - before, axis=1)
    d = d[np.isfinite(d)]
    return float(d.max()) if len(d) else math.inf
