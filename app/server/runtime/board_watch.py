"""Live board detection (checkerboard, ChArUco, circle grid) on the console's newest frame set.

:class:`BoardWatch` searches every sensor of the pipeline's newest frame set for the board
and keeps the result as a :class:`BoardSighting`: the frames it looked at, each sensor's
corners (or why not), the board's pose in the rig frame and whether the board has held
still since the previous sighting. The Feeds panel draws the corners, the 3D scene shows
the pose and the calibration session's auto-capture takes steady, novel sightings.

How it keeps up (in the calibration scenario with a browser on the 2-core reference
machine, the 3D board followed a new board pose in the cloud 1.0-2.1 s late (median) and
up to 3.8 s before; now no later than the cloud (median), 0.4 s at worst: BENCHMARKS.md,
"Live board detection"):

- **Always the newest frame set, never a backlog.** A pass starts from whatever
  ``latest()`` returns at that moment; frame sets that arrive during a pass are not
  queued, the next pass takes the newest. Passes start as soon as a new frame set is
  there (polled every ``poll_s``), at most ``rate_hz`` times a second and, so that the
  watch leaves CPU to the rest of the console, after a pause as long as the previous
  pass (``duty``), but never longer than :data:`MAX_PAUSE_S`. A frame set whose images
  are the very objects the previous pass searched (a simulated head holding a pose, a
  paused replay) reuses their detections: such a pass costs next to nothing.
- **The pose first.** A second thread, the pose loop (:meth:`BoardWatch.pose_tick`),
  looks at each new picture's sensors in the order their detection is trusted for the pose
  (:data:`POSE_PREFERENCE`: colour, thermal, TOF) until one shows the board, and publishes
  its pose at once as :attr:`BoardWatch.latest_pose` (``pose_listeners`` are called, so
  the 3D scene moves the board then), even while a complete pass over an older picture is
  still searching the thermal imagers. The complete passes (:meth:`BoardWatch.tick`)
  search every sensor, two at a time in the same order, publishing the pose early too,
  and give the complete sighting as :attr:`BoardWatch.latest`. Both loops share their
  looks at each image (:class:`LookCache`): no image is searched twice.
- **Colour at half resolution first** (:func:`first_look`): a 1280 x 960 colour image is
  searched at 640 x 480 and the corners are then found at full resolution in a crop around
  the board (the same corners to 0.001 px as a full search, measured on 40 simulated
  images, in about half the time; a search that finds nothing, the costliest, in 0.5 s
  instead of 1.1-2.9 s). Only when the half-resolution search finds nothing is the whole
  image searched at full resolution (a board too small to find at half resolution): at
  most every :data:`FULL_SEARCH_PERIOD_S` per camera, after the pose is published, and
  not when the pose from another sensor puts the board (partly) outside the image
  (:func:`board_in_image`).
- While the last pass found the board nowhere, complete passes are ``idle_period_s``
  apart and the pose loop rests (a failed search costs the most).
- **Only while someone looks.** Given a ``demand`` (:mod:`app.server.runtime.demand`), both
  loops search only while it is wanted: in the console, while a Viser client is connected
  (the Calibration panel, the feeds' corners, the 3D board) or auto-capture is on. A
  search that failed the inspection room's every colour frame cost a quarter of a core.

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
import time
from collections import deque
from collections.abc import Callable, Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.board import Board
from trifuse.calib.detect import Detection
from trifuse.calib.polarity import detect_board_configured, orient_to_pose, override
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import invert, make_T, rotation_from_rvec

STEADY_PX = 2.0
"""A board is steady when no corner moved more than this many pixels (in any sensor that
saw it both times) since the previous sighting."""

POSE_PREFERENCE = ("color", "thermal", "tof")
"""Modalities in the order their detection is trusted for the board's pose."""

COARSE_MIN_WIDTH = 960
"""Colour images at least this wide are searched at half resolution first."""
COARSE_CROP_MARGIN = 2.0
"""The full-resolution crop around a board found at half resolution reaches this many
corner spacings (plus 8 px) beyond the outer corners: the outer squares, the board's
margin and a quiet zone for the detector."""
FULL_SEARCH_PERIOD_S = 10.0
"""A colour camera whose half-resolution search found nothing is searched at full
resolution at most this often (seconds)."""
MAX_PAUSE_S = 0.5
"""The pause after a pass (``duty``) is at most this long: on a busy machine a pass takes
longer, and a new picture must not wait for long (the 3D board would lag the cloud)."""

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
        steady: found in at least one sensor, and no sensor that found it in the previous
            sighting too saw a corner move more than :data:`STEADY_PX`.
        complete: every sensor was searched (False: the pose was published early).
    """

    frames: FrameSet
    detections: dict[str, Detection]
    T_rig_board: np.ndarray | None
    pose_sensor: str | None
    steady: bool
    complete: bool = True

    @property
    def found(self) -> list[str]:
        """Sensors whose image shows the board."""
        return [s for s, d in self.detections.items() if d.found]


@dataclass(frozen=True)
class PassTiming:
    """How long one pass of :class:`BoardWatch` took (seconds of wall time).

    Attributes:
        stamp_ns: time stamp of the frame set searched.
        pose_s: from the pass's start to the pose's publication (None: no pose).
        pass_s: from the pass's start to the complete sighting.
        pose_age_s: how much older the searched frames were than the newest frame set
            when the pose was published (what the 3D scene draws late by); None without
            a pose.
        reused: every detection was taken over from the previous pass (same images).
    """

    stamp_ns: int
    pose_s: float | None
    pass_s: float
    pose_age_s: float | None
    reused: bool


MIN_POSE_CORNERS = 6
"""A partial view (ChArUco) gives a pose from at least this many corners."""


def board_pose(rig: Rig, sensor: str, corners: np.ndarray, board: Board) -> np.ndarray | None:
    """(4, 4) ``T_rig_board`` from one sensor's corners (N, 2) pixels, NaN rows for corners
    not seen (a partial view: at least :data:`MIN_POSE_CORNERS`), by PnP with the rig's
    intrinsics; None when PnP fails or too few corners were seen."""
    intr = rig[sensor].intrinsics
    corners = np.asarray(corners, dtype=np.float64)
    seen = np.isfinite(corners).all(axis=1)
    if seen.sum() < min(MIN_POSE_CORNERS, len(corners)):
        return None
    ok, rvec, tvec = cv2.solvePnP(
        board.object_points()[seen].astype(np.float64),
        corners[seen].reshape(-1, 1, 2),
        intr.K,
        np.asarray(intr.distortion, dtype=np.float64),
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        return None
    return rig[sensor].T_rig_sensor @ make_T(rotation_from_rvec(rvec.ravel()), tvec.ravel())


def board_in_image(rig: Rig, sensor: str, T_rig_board: np.ndarray, board: Board) -> bool:
    """Whether every inner corner of the board at ``T_rig_board`` (4, 4) projects into
    ``sensor``'s image (in front of it, within its pixels), by the rig's calibration; of a
    board seen in part (ChArUco), whether at least :data:`MIN_POSE_CORNERS` do."""
    s = rig[sensor]
    T = invert(s.T_rig_sensor) @ np.asarray(T_rig_board, dtype=np.float64)
    P = board.object_points() @ T[:3, :3].T + T[:3, 3]
    uv = s.intrinsics.project(P)
    w, h = s.image_size
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    inside &= np.isfinite(uv).all(axis=1) & (P[:, 2] > 0)
    if board.partial_views:
        return int(inside.sum()) >= MIN_POSE_CORNERS
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


def _safe_look(
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


def _trusted(rig: Rig, names: list[str]) -> list[str]:
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
    names = _trusted(rig, [s for s in frames.frames if s in rig])
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
        return _safe_look(first, name, frames.frames[name].image, rig[name].modality)

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
            pose = board_pose(rig, name, det.corners, board)
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
            if det.found and (T := board_pose(rig, name, det.corners, board)) is not None:
                pose_sensor, pose = name, T
                break
    detections = orient_by_colour(detections, rig, board, pose, pose_sensor)
    moved = [
        _moved_px(det.corners, previous.detections[name].corners)
        for name, det in detections.items()
        if det.found
        and previous is not None
        and name in previous.detections
        and previous.detections[name].found
    ]
    steady = bool(moved) and max(moved) <= STEADY_PX
    ordered = {n: detections[n] for n in frames.frames if n in detections}
    return BoardSighting(frames, ordered, pose, pose_sensor, steady)


def _moved_px(now: np.ndarray, before: np.ndarray) -> float:
    """How far (pixels) the corners (N, 2) seen both times moved at most; inf when a partial
    view (NaN rows) shares no corner with the previous one."""
    d = np.linalg.norm(now - before, axis=1)
    d = d[np.isfinite(d)]
    return float(d.max()) if len(d) else math.inf


class _PoseLoop(Periodic):
    """The board watch's second thread: :meth:`BoardWatch.pose_tick` every ``poll_s``."""

    def __init__(self, watch: BoardWatch, poll_s: float) -> None:
        super().__init__("board-pose", poll_s, watch.demand)
        self.watch = watch

    def record_error(self, exc: BaseException, where: str | None = None) -> str:
        """Recorded as the watch's error."""
        return self.watch.record_error(exc, where or "pose loop")

    def tick(self) -> None:
        self.watch.pose_tick()


class BoardWatch(Periodic):
    """Detects the board in the newest frame set of ``latest()``, in two loops (threads)
    that share their looks at each image (:class:`LookCache`):

    - the pose loop (:meth:`pose_tick`): each new picture, the sensors in order of trust
      until one shows the board, then its pose is published (``latest_pose``): the 3D
      board follows the cloud without waiting for a complete pass;
    - the complete passes (:meth:`tick`): every sensor, the full :class:`BoardSighting`
      with steadiness (``latest``, ``on_sighting``: Feeds panel, auto-capture).

    Args:
        latest: returns the newest frame set (or None before the first).
        rig: sensor modalities, intrinsics and poses.
        board: the checkerboard to look for.
        rate_hz: at most this many passes (of each loop) start per second.
        on_sighting: called (in the watch's thread) with every complete sighting.
        idle_period_s: while the last pass found no board anywhere, complete passes are
            this far apart instead and the pose loop rests (a search that fails costs the
            most: about 1.2 s of CPU for a 1280 x 960 colour image against 0.1 s when the
            board is there).
        duty: a pass that took ``t`` seconds is followed by a pause of
            ``t * (1 / duty - 1)`` seconds, at most :data:`MAX_PAUSE_S` (each loop's share
            of its thread's time).
        poll_s: how often the loops look for a new frame set.
        detect: the detector (tests pass a stand-in).
        demand: search only while it is wanted (None: always).

    Attributes:
        latest: the newest complete sighting (Feeds panel, auto-capture).
        latest_pose: the sighting of the newest frames with the board's pose, partial or
            complete, or a complete one without (the 3D scene).
        pose_listeners: called (in a watch thread) with each new ``latest_pose``.
        timings: the last 600 complete passes' :class:`PassTiming`.
        pose_timings: the last 600 pose-loop passes' :class:`PassTiming` (``pass_s`` is
            the time to the pose).
        last_error: the newest failure of a pass or a pose listener, or None
            (:class:`~app.server.runtime.periodic.Periodic`).

    ``enabled`` may be set False to pause detection (nothing else changes).
    """

    def __init__(
        self,
        latest: Callable[[], FrameSet | None],
        rig: Rig,
        board: Board,
        rate_hz: float = 4.0,
        on_sighting: Callable[[BoardSighting], None] | None = None,
        idle_period_s: float = 3.0,
        duty: float = 0.5,
        poll_s: float = 0.05,
        detect: Detector = detect_board_configured,
        demand: Demand | None = None,
    ) -> None:
        super().__init__("board-watch", poll_s, demand)
        if not (rate_hz > 0 and 0 < duty <= 1 and poll_s > 0):
            raise ValueError(
                f"board watch: expected rate_hz > 0, 0 < duty <= 1 and poll_s > 0, got "
                f"rate_hz={rate_hz}, duty={duty}, poll_s={poll_s}"
            )
        self.min_period_s = 1.0 / rate_hz
        self.idle_period_s = idle_period_s
        self.duty = duty
        self.detect = detect
        self.latest_frames, self.rig, self.board = latest, rig, board
        self.on_sighting = on_sighting
        self.enabled = True
        self.latest: BoardSighting | None = None
        self.latest_pose: BoardSighting | None = None
        self.pose_listeners: list[Callable[[BoardSighting], None]] = []
        self.timings: deque[PassTiming] = deque(maxlen=600)
        self.pose_timings: deque[PassTiming] = deque(maxlen=600)
        self._looks = LookCache(board, detect)
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="board-detect")
        self._pose_loop = _PoseLoop(self, poll_s)
        self._searched: FrameSet | None = None
        self._last_pass = -math.inf
        self._next_start = -math.inf
        self._pose_next = -math.inf
        self._pose_images: tuple[np.ndarray, ...] | None = None
        self._full_due: dict[str, float] = {}
        self._pass_lock = threading.Lock()  # one complete pass at a time
        self._pose_lock = threading.Lock()  # one pose pass at a time
        self._publish_lock = threading.Lock()
        self._pose_at: tuple[float, float | None] | None = None  # (s into the pass, age)

    def start(self) -> BoardWatch:
        super().start()
        self._pose_loop.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._pose_loop.stop(timeout_s)
        super().stop(timeout_s)
        self._pool.shutdown(wait=False)

    def _age_s(self, frames: FrameSet) -> float | None:
        """How much older ``frames`` are than the newest frame set, seconds."""
        newest = self.latest_frames()
        return None if newest is None else (newest.stamp_ns - frames.stamp_ns) / 1e9

    def _publish_pose(self, s: BoardSighting) -> bool:
        """``s`` becomes ``latest_pose`` unless that is of newer frames already (the other
        loop was quicker); the listeners hear of it (their failures are theirs: the watch
        goes on). Returns whether ``s`` was taken."""
        with self._publish_lock:
            current = self.latest_pose
            if current is not None and s.frames.stamp_ns < current.frames.stamp_ns:
                return False
            self.latest_pose = s
        for listener in list(self.pose_listeners):
            try:
                listener(s)
            except Exception as exc:  # a listener's bug must not stop the detection
                self.record_error(exc, "pose listener")
        return True

    def _pause_after(self, started: float, done: float) -> float:
        """When the next pass of a loop may start after one from ``started`` to ``done``."""
        pause = min(MAX_PAUSE_S, (done - started) * (1 / self.duty - 1))
        return max(started + self.min_period_s, done + pause)

    def due(self, now: float) -> bool:
        """Whether a complete pass may start at ``now`` (monotonic seconds): the rate
        limit, the pause after the previous pass and, without a board lately, the idle
        period."""
        if now < self._next_start:
            return False
        idle = self.latest is not None and not self.latest.found
        return not (idle and now - self._last_pass < self.idle_period_s)

    # -- the pose loop -------------------------------------------------------------------

    def pose_tick(self) -> None:
        """One look of the pose loop: if the newest frame set shows a new picture (some
        image is not the very object looked at last time) and a pass is due, its sensors
        in order of trust until one shows the board; its pose is published. Rests while
        the last complete pass found the board nowhere."""
        with self._pose_lock:
            fs = self.latest_frames()
            last = self.latest
            if not self.enabled or fs is None or (last is not None and not last.found):
                return
            rig = self.rig
            names = _trusted(rig, [n for n in fs.frames if n in rig])
            images = tuple(fs.frames[n].image for n in names)
            seen = self._pose_images
            if seen is not None and len(seen) == len(images):
                if all(a is b for a, b in zip(seen, images, strict=True)):
                    return  # the same picture
            started = time.monotonic()
            if started < self._pose_next:
                return
            self._pose_images = images
            detections: dict[str, Detection] = {}
            found: BoardSighting | None = None
            for name in names:
                det, _ = _safe_look(self._looks, name, fs.frames[name].image, rig[name].modality)
                detections[name] = det
                if det.found and (T := board_pose(rig, name, det.corners, self.board)) is not None:
                    found = BoardSighting(fs, dict(detections), T, name, False, False)
                    break
            done = time.monotonic()
            self._pose_next = self._pause_after(started, done)
        if found is not None and self._publish_pose(found):
            age = self._age_s(fs)
            self.pose_timings.append(
                PassTiming(fs.stamp_ns, done - started, done - started, age, False)
            )

    # -- the complete passes -------------------------------------------------------------

    def tick(self) -> None:
        """One look: a complete pass over the newest frame set if it is new and due."""
        with self._pass_lock:
            fs = self.latest_frames()
            if not self.enabled or fs is None or fs is self._searched:
                return
            started = time.monotonic()
            if not self.due(started):
                return
            self._last_pass = started
            self._searched = fs
            allowed = {n for n in self.rig.names if started >= self._full_due.get(n, -math.inf)}
            previous = self.latest
            self._pose_at = None

            def early(p: BoardSighting) -> None:
                if self._publish_pose(p):
                    self._pose_at = (time.monotonic() - started, self._age_s(p.frames))

            s = sighting(  # an exception is recorded by Periodic; the watch keeps running
                fs,
                self.rig,
                self.board,
                previous,
                self._pool,
                on_pose=early,
                full_search=allowed,
                detect=self.detect,
                looker=self._looks,
            )
            done = time.monotonic()
            self._next_start = self._pause_after(started, done)
            for name in allowed:
                det = s.detections.get(name)
                if det is not None and det.reason is not None:
                    if "(half resolution)" not in det.reason:
                        self._full_due[name] = done + FULL_SEARCH_PERIOD_S
            self.latest = s
            took = done - started
            if self._publish_pose(s) and self._pose_at is None and s.T_rig_board is not None:
                self._pose_at = (took, self._age_s(fs))
            reused = previous is not None and all(
                previous.detections.get(n) is d for n, d in s.detections.items()
            )
            pose_s, age_s = self._pose_at if self._pose_at is not None else (None, None)
            self.timings.append(PassTiming(fs.stamp_ns, pose_s, took, age_s, reused))
        if self.on_sighting is not None:
            self.on_sighting(s)
