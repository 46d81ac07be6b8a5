"""Live board detection (checkerboard, ChArUco, circle grid) on the console's newest frame set.

:class:`BoardWatch` searches every sensor of the pipeline's newest frame set for the board
and keeps the result as a :class:`BoardSighting`: the frames it looked at, each sensor's
corners (or why not), the board's pose in the rig frame and whether the board has held
still since the previous sighting. The Feeds panel draws the corners, the 3D scene shows
the pose and the calibration session's auto-capture takes steady, novel sightings. How one
frame set is searched (:class:`BoardSighting`, :func:`first_look`, :class:`LookCache` ...)
is in :mod:`app.server.runtime.board_sighting`; this module decides when and on which
threads.

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
- **Stillness in frame time.** A complete sighting is compared with the previous one by
  the frames' time stamps (:class:`~app.server.runtime.board_sighting.Motion`), and,
  when that does not show the board still (the previous one was of another pose, or
  too close in time), with a second look at the newest frame set
  (:meth:`BoardWatch.second_look`): the same picture again costs nothing, another one a
  look at the most trusted sensor that found the board. A machine whose passes take
  seconds (the board moved on between two passes) thus still finds the board still
  while it is, and auto-capture takes it.
- **Little search without a board.** While the last complete pass found the board
  nowhere, the pose loop rests and complete passes are ``idle_full_period_s`` apart: a
  failed search costs the most (in the inspection room, about 2.6 s of CPU for the five
  sensors of the simulated head: each thermal imager 0.9 s, the TOF 0.3 s, each colour
  camera 0.2 s at half resolution; every 3 s that was most of a core). In between, every
  ``idle_period_s``, a glance at the colour cameras at half resolution (shared with the
  next pass, :class:`LookCache`): a board brought into their view starts a complete pass
  at once. A board only the thermal imagers or the TOF see (a dark room) is found by the
  next complete pass. A rig without colour cameras gets complete passes every
  ``idle_period_s``, as nothing is cheaper to glance at.
- **Only while someone looks.** Given a ``demand`` (:mod:`app.server.runtime.demand`), both
  loops search only while it is wanted: in the console, while a Viser client is connected
  (the Calibration panel, the feeds' corners, the 3D board) or auto-capture is on. A
  search that failed the inspection room's every colour frame cost a quarter of a core.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from trifuse.app.server.runtime.board_sighting import (
    STILL_MIN_SPAN_S,
    BoardSighting,
    Detector,
    LookCache,
    Motion,
    compare_looks,
    safe_look,
    sighting,
    trusted,
)
from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.detection_cache import detect_remembered
from trifuse.calib.board import Board
from trifuse.calib.board_pose import board_pose_single
from trifuse.calib.detect import Detection
from trifuse.calib.rig import Rig

FULL_SEARCH_PERIOD_S = 10.0
"""A colour camera whose half-resolution search found nothing is searched at full
resolution at most this often (seconds)."""
MAX_PAUSE_S = 0.5
"""The pause after a pass (``duty``) is at most this long: on a busy machine a pass takes
longer, and a new picture must not wait for long (the 3D board would lag the cloud)."""


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
        idle_period_s: while the last complete pass found no board anywhere, the colour
            cameras are glanced at (half resolution) this often; a glance that finds the
            board starts a complete pass (module docstring).
        idle_full_period_s: while the last complete pass found no board anywhere,
            complete passes are this far apart (``idle_period_s`` for a rig without
            colour cameras).
        duty: a pass that took ``t`` seconds is followed by a pause of
            ``t * (1 / duty - 1)`` seconds, at most :data:`MAX_PAUSE_S` (each loop's share
            of its thread's time).
        poll_s: how often the loops look for a new frame set.
        detect: the detector (default: :func:`calib.polarity.detect_board_configured`
            with its results kept in memory, :mod:`app.storage.detection_cache`; tests pass
            a stand-in).
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
        idle_full_period_s: float = 15.0,
        duty: float = 0.5,
        poll_s: float = 0.05,
        detect: Detector = detect_remembered,
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
        self.idle_full_period_s = idle_full_period_s
        self._last_glance = -math.inf
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

    def idle(self) -> bool:
        """Whether the last complete pass found the board nowhere."""
        return self.latest is not None and not self.latest.found

    def due(self, now: float) -> bool:
        """Whether a complete pass may start at ``now`` (monotonic seconds): the rate
        limit, the pause after the previous pass and, without a board lately, the idle
        period of complete passes (a glance may start one sooner: :meth:`tick`)."""
        if now < self._next_start:
            return False
        period = self.idle_full_period_s if self.rig.by_modality("color") else self.idle_period_s
        return not (self.idle() and now - self._last_pass < period)

    def glance(self, fs: FrameSet, now: float) -> bool:
        """While idle, at most every ``idle_period_s``: whether a colour camera of ``fs``
        shows the board at half resolution (:func:`first_look`, kept in the shared
        :class:`LookCache` for the pass it starts)."""
        names = self.rig.by_modality("color")  # the rig in use: the console may change it
        if not names or now - self._last_glance < self.idle_period_s:
            return False
        self._last_glance = now
        for name in names:
            frame = fs.frames.get(name)
            if frame is not None and safe_look(self._looks, name, frame.image, "color")[0].found:
                return True
        return False

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
            names = trusted(rig, [n for n in fs.frames if n in rig])
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
                det, _ = safe_look(self._looks, name, fs.frames[name].image, rig[name].modality)
                detections[name] = det
                if (
                    det.found
                    and (T := board_pose_single(rig, name, det.corners, self.board)) is not None
                ):
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

    def second_look(self, s: BoardSighting) -> BoardSighting:
        """``s`` judged still or moving against the newest frame set as well (module
        docstring): sensors whose image there is the very one ``s`` searched moved by
        nothing; the most trusted sensor that found the board whose image is new is
        looked at (shared with the pose loop: often looked at already), if its frame is
        at least :data:`~app.server.runtime.board_sighting.STILL_MIN_SPAN_S` later. A
        board that sensor no longer finds (at full resolution) has moved. Returns ``s``
        itself when the newest frames tell nothing more, else ``s`` with the new
        :class:`Motion` and ``steady``. The very same images tell nothing while another
        sensor's image is new and not looked at: the searched set may straddle a jump
        of the board (a simulated pose change: the colour cameras' new pose with the
        slower sensors' frames of the pose before), which a second look at those same
        images would take for a still board."""
        newest = self.latest_frames()
        if newest is None or newest is s.frames:
            return s
        rig = self.rig
        names = trusted(rig, [n for n in s.found if n in newest.frames and n in rig])
        now: dict[str, Detection] = {}
        lost: Motion | None = None
        looked = changed = told = False  # told: a new image was compared (or lost the board)
        for name in names:
            old, new = s.frames.frames[name], newest.frames[name]
            if new.image is old.image:
                now[name] = s.detections[name]
                continue
            changed = True
            span_s = abs(new.stamp_ns - old.stamp_ns) / 1e9
            if looked or span_s < STILL_MIN_SPAN_S:
                continue
            looked = True
            det, coarse = safe_look(self._looks, name, new.image, rig[name].modality)
            if not det.found:
                if not coarse:  # (half resolution only: too small to tell)
                    lost, told = Motion(math.inf, span_s, name), True
                continue
            if rig[name].modality != "color" and self.board.pattern != "charuco":
                det = _nearer_ordering(det, s.detections[name].corners)
            now[name], told = det, True
        if changed and not told:  # only the unchanged images to compare: they tell nothing
            return s
        motion = compare_looks(s.frames, s.detections, newest, now)
        if lost is not None and (motion is None or motion.still):
            motion = lost
        if motion is None or not motion.decided:
            return s
        return dataclasses.replace(s, steady=motion.still, motion=motion)

    def tick(self) -> None:
        """One look: a complete pass over the newest frame set if it is new and due."""
        with self._pass_lock:
            fs = self.latest_frames()
            if not self.enabled or fs is None or fs is self._searched:
                return
            started = time.monotonic()
            if not self.due(started):
                if not (started >= self._next_start and self.idle() and self.glance(fs, started)):
                    return
                started = time.monotonic()  # the board is back in view: a pass now
            self._last_pass = self._last_glance = started  # a pass glances too
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
            if s.found and not s.steady:
                s = self.second_look(s)
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


def _nearer_ordering(det: Detection, before: np.ndarray) -> Detection:
    """``det`` or its corners in the reversed order (the half turn a thermal or TOF
    detection may come in before it is put in the colour camera's ordering), whichever
    lies nearer ``before`` (N, 2) pixels."""
    turned = det.corners[::-1]
    a = np.nanmax(np.linalg.norm(det.corners - before, axis=1))
    b = np.nanmax(np.linalg.norm(turned - before, axis=1))
    return Detection(turned.copy(), None, det.method) if b < a else det
