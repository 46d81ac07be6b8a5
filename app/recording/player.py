"""The replay machinery shared by recordings and ROS 2 bags.

:class:`MessageReplay` is a :class:`~app.sources.base.FrameSource` over an MCAP file
(:class:`~app.recording.mcapindex.McapIndex`): messages in log-time order are routed to a
sensor and a kind (colour, thermal, TOF distance, TOF amplitude) by the subclass, decoded
into the program's arrays, the two TOF streams paired into one frame, and delivered in real
time (or as fast as possible) with rate, pause, seek and loop.

Timeline: ``start_ns``, ``end_ns``, ``position_ns`` and :meth:`MessageReplay.seek` use the
messages' log time, which pacing follows too. A frame's ``stamp_ns`` is its acquisition
time: for trifuse recordings the same number, for ROS 2 bags the message header's stamp.

Bad messages are skipped, not fatal: a frame message that does not decode, or whose image
has another size than the rig gives its sensor (checked from its header, before its pixels
are decoded: :mod:`app.recording.images`), is left out and counted per sensor and reason
(:attr:`MessageReplay.skipped`, and :meth:`MessageReplay.stats` for the console's sensor
health); the replay goes on. Damage to the file itself (a truncated or corrupted chunk)
ends the replay (:class:`~app.recording.errors.RecordingDamaged`).

Keeping time (``keep_time``, the console's replay): a consumer slower than the recording
does not slow the replay's clock. When a frame's time has passed and a newer frame of the same
sensor and kind is due too (the file is read ahead to its wall-clock time), the older one is
dropped before its image is decoded, and counted (:attr:`MessageReplay.dropped`). The
consumer gets the newest frames at the recording's pace; only a stall longer than
:data:`KEEP_TIME_MAX_LAG_S` (or a look-ahead of :data:`LOOKAHEAD_MESSAGES`) slows the clock. The two
colour images of an instant are decoded at once, the second in a worker thread.
Without it (``trifuse fuse``, ``map``, ``record``, tests of pacing), every frame is
delivered.

Thread use: one thread iterates :meth:`MessageReplay.frames`; :meth:`pause`,
:meth:`resume`, :meth:`seek` and the ``rate`` setter may be called from any thread and take
effect before the next frame is delivered.
"""

from __future__ import annotations

import logging
import math
import numbers
import threading
import time
from abc import abstractmethod
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Message

from trifuse.app.errors import describe_error
from trifuse.app.recording.errors import ImageSizeError, RecordingDamaged, RecordingError
from trifuse.app.recording.mcapindex import McapDamage, McapIndex
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame
from trifuse.calib.numbers import is_real
from trifuse.calib.rig import Rig

log = logging.getLogger(__name__)

FRAME_KINDS = ("color", "thermal", "tof_distance", "tof_amplitude")
MAX_LAG_S = 0.25
"""A real-time replay that falls further behind than this re-anchors its clock (plays on
from where it is, slower) instead of delivering a burst of late frames."""
KEEP_TIME_MAX_LAG_S = 2.0
"""A time-keeping replay re-anchors its clock only when this far behind (a stall, a machine
that froze): short of it the frames the consumer had no time for are dropped instead."""
LOOKAHEAD_MESSAGES = 512
"""The most messages a time-keeping replay reads ahead to find the newest due frames (about
4 s of a full-rate recording of the simulated head)."""
SAME_INSTANT_NS = 10_000_000
"""Frames within this log time of each other are one instant to a time-keeping replay (kept
or dropped together)."""
PAIR_WINDOW_NS = 50_000_000
"""A TOF half (distance or amplitude) whose partner has not come within this log time is
delivered alone."""
MAX_SKIP_REASONS = 8
"""Distinct reasons counted per sensor in :attr:`MessageReplay.skipped`; further ones are
counted under :data:`OTHER_REASONS`."""
OTHER_REASONS = "other problems"


@dataclass(frozen=True)
class Route:
    """Where one channel's messages go.

    Attributes:
        sensor: the sensor id.
        kind: ``color``, ``thermal``, ``tof_distance``, ``tof_amplitude``, or another
            (non-frame) kind the subclass handles itself (``calibration``, ``camera_info``).
        decode: ``(message, size=None)`` -> (stamp_ns, array); ``size`` is the (width,
            height) the rig gives the sensor (None: unknown), which an image must have
            (:class:`~app.recording.errors.ImageSizeError` before its pixels are decoded);
            raises on a malformed message.
    """

    sensor: str
    kind: str
    decode: Callable[..., tuple[int, np.ndarray]]


@dataclass
class _Skips:
    """One sensor's skipped messages (see :attr:`MessageReplay.skipped`)."""

    reasons: dict[str, int] = field(default_factory=dict)
    since_delivered: int = 0
    last_s: float | None = None  # time.monotonic()
    last_reason: str = ""


@dataclass
class _TofHalf:
    stamp_ns: int
    log_ns: int
    parts: dict[str, np.ndarray] = field(default_factory=dict)


Skips = dict[str, dict[str, int]]
"""sensor -> reason -> messages skipped (:attr:`MessageReplay.skipped`)."""


def add_skips(into: Skips, more: Skips, sign: int = 1) -> None:
    """Add (``sign`` -1: subtract) the counts ``more`` to ``into``; zeros are dropped."""
    for sensor, reasons in more.items():
        mine = into.setdefault(sensor, {})
        for reason, n in reasons.items():
            mine[reason] = mine.get(reason, 0) + sign * n
            if not mine[reason]:
                del mine[reason]
        if not mine:
            del into[sensor]


def skips_between(before: Skips | None, after: Skips) -> Skips:
    """The messages skipped from the snapshot ``before`` (None: counting never began, so
    nothing) to ``after`` (:attr:`MessageReplay.skipped` taken at two moments)."""
    if before is None:
        return {}
    out = {s: dict(r) for s, r in after.items()}
    add_skips(out, before, -1)
    return out


def skips_text(skips: Skips) -> list[str]:
    """One line per sensor and reason: ``3 messages of ccd_left skipped: JPEG of
    30000x30000 pixels, the rig says 1280x960``."""
    return [
        f"{n} message{'s' * (n != 1)} of {sensor} skipped: {reason}"
        for sensor, reasons in skips.items()
        for reason, n in reasons.items()
    ]


class _Lookahead:
    """A cursor over a file's messages that can read ahead of the one being handled.

    ``next()`` gives the messages read ahead first, then the cursor's; damage met while
    reading ahead is raised when the messages before it have been taken.
    """

    def __init__(self, cursor: Iterator[Message]) -> None:
        self.cursor = cursor
        self.ahead: deque[Message] = deque()
        self.decoding: dict[int, tuple[Message, Future[tuple[int, np.ndarray]]]] = {}
        """id of a message read ahead -> (it, its decoding started in a worker)."""
        self._damage: McapDamage | None = None
        self._ended = False

    def __iter__(self) -> _Lookahead:
        return self

    def __next__(self) -> Message:
        if self.ahead:
            return self.ahead.popleft()
        if self._damage is not None:
            damage, self._damage = self._damage, None
            raise damage
        return next(self.cursor)

    def _read_to(self, log_ns: int) -> None:
        """Read ahead until a message after ``log_ns`` (or the end, damage, or
        :data:`LOOKAHEAD_MESSAGES`)."""
        while not self._ended and self._damage is None and len(self.ahead) < LOOKAHEAD_MESSAGES:
            if self.ahead and self.ahead[-1].log_time > log_ns:
                break
            try:
                self.ahead.append(next(self.cursor))
            except StopIteration:
                self._ended = True
            except McapDamage as exc:
                self._damage = exc

    def newer_due(self, channel_id: int, now_ns: int) -> bool:
        """Whether a later message of ``channel_id`` with log time at most ``now_ns`` is in
        the file, reading ahead to find it."""
        self._read_to(now_ns)
        return any(m.channel_id == channel_id and m.log_time <= now_ns for m in self.ahead)

    def same_instant(self, log_ns: int) -> list[Message]:
        """The next messages within :data:`SAME_INSTANT_NS` after ``log_ns``, read ahead."""
        self._read_to(log_ns + SAME_INSTANT_NS)
        return [m for m in self.ahead if m.log_time <= log_ns + SAME_INSTANT_NS]


class MessageReplay(FrameSource):
    """Base of :class:`~app.recording.reader.ReplaySource` and
    :class:`~app.recording.ros2.Ros2BagSource` (see the module docstring).

    Args:
        path: the MCAP file.
        rate: playback speed (2.0 = twice as fast); real time only.
        loop: start again from the beginning at the end.
        realtime: pace frames by their log times (sleeping); False = as fast as possible.
        on_damage: ``"raise"`` (default): ``frames()`` raises
            :class:`~app.recording.errors.RecordingDamaged` at the point of damage, after
            delivering every frame before it; ``"stop"``: log a warning there and end the
            stream. Either way :attr:`damage` holds the exception.
        pair_tolerance_s: TOF distance and amplitude messages whose stamps differ by at
            most this much form one frame.
        clock, sleep: the wall clock that paces ``realtime`` (seconds) and how to wait on
            it; None: ``time.monotonic`` and a wait that pause, seek and rate changes cut
            short (tests pass a simulated clock).
        keep_time: with ``realtime``, drop the frames a slower consumer has no time for
            rather than slowing the clock (see the module docstring).

    Attributes:
        sensors: the sensors of the source (the rig's or the topic map's), including any
            the file has no frames of (``FrameSet.missing`` then reports them).
        rig: the rig, when the file (or the caller) gives one.
        frame_sizes: sensor -> (width, height) every frame of it must have (from the rig:
            :meth:`expect`); a sensor not in it may have any size up to
            :data:`calib.rig.MAX_IMAGE_PIXELS`.
        damage: the damage met by the last iteration, else None.
        skipped: sensor -> reason -> messages skipped (see the module docstring), over
            every iteration since the source was opened.
        dropped: sensor -> frames dropped to keep time (``keep_time``), likewise.
        notes: non-fatal problems found when opening (damaged summary, missing topics).
    """

    source_kind = "replay"

    def __init__(
        self,
        path: str | Path,
        *,
        rate: float = 1.0,
        loop: bool = False,
        realtime: bool = True,
        on_damage: str = "raise",
        pair_tolerance_s: float = 0.001,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], object] | None = None,
        keep_time: bool = False,
    ) -> None:
        if on_damage not in ("raise", "stop"):
            raise RecordingError(f"on_damage: expected 'raise' or 'stop', got {on_damage!r}")
        self.path = Path(path)
        self._cond = threading.Condition()
        self._clock = clock or time.monotonic
        self._sleep = sleep or self._cond.wait  # called holding the lock
        self._rate = self._check_rate(rate)
        self.loop = bool(loop)
        self.realtime = bool(realtime)
        self.keep_time = bool(keep_time)
        self.on_damage = on_damage
        self.pair_tolerance_ns = round(pair_tolerance_s * 1e9)
        self.damage: RecordingDamaged | None = None
        self._paused = False
        self._pending_seek: int | None = None
        self._anchor: tuple[int, float] | None = None  # (log ns, monotonic s)
        # keep_time: (log ns of an instant, the "now" it was judged at, the anchor then)
        self._judged: tuple[int, int, tuple[int, float]] | None = None
        self._routes: dict[int, Route | None] = {}
        self._tof_parts: dict[str, set[str]] = {}
        self.frame_sizes: dict[str, tuple[int, int]] = {}
        self._skips: dict[str, _Skips] = {}
        self._dropped: dict[str, int] = {}
        self._pair_decoder: ThreadPoolExecutor | None = None  # keep_time: the stereo pair's second
        self.index = McapIndex.open(self.path)
        self.notes: list[str] = list(self.index.notes)
        start = self.index.start_ns
        self._position = 0 if start is None else start
        self.sensors: list[str] = []
        try:
            self._opened()
        except BaseException:
            self.index.close()
            raise

    # -- subclass hooks -------------------------------------------------------------------

    def _opened(self) -> None:
        """The end of ``__init__``, the file open (:attr:`index`): a subclass reads what it
        needs of it here (rig, sensors); if this raises, the file is closed."""
        return None

    @abstractmethod
    def _route(self, channel: Channel) -> Route | None:
        """How to handle a channel's messages (None: ignore them)."""

    def _side_message(self, route: Route, message: Message) -> None:
        """A message of a non-frame kind (calibration, camera info); ignored by default."""
        return None

    # -- what frames must be, and what was skipped --------------------------------------

    def expect(self, rig: Rig | None) -> None:
        """Check every frame against ``rig``'s image sizes from now on (None: against
        nothing but the largest size a rig may describe)."""
        self.frame_sizes = {} if rig is None else {n: rig[n].image_size for n in rig.names}

    @property
    def skipped(self) -> Skips:
        """sensor -> reason -> messages skipped (a copy)."""
        with self._cond:
            return {s: dict(k.reasons) for s, k in self._skips.items()}

    @property
    def dropped(self) -> dict[str, int]:
        """sensor -> frames dropped to keep time (``keep_time``; a copy)."""
        with self._cond:
            return dict(self._dropped)

    def stats(self) -> dict[str, Any]:
        """``{"rejected_by_sensor": {sensor: {"since_accepted", "last_rejected_s",
        "last_error"}}}``: per sensor, the messages skipped since its last frame delivered,
        when the latest was skipped (``time.monotonic()``) and why (the push ingest's
        shape, which the console's sensor health reads)."""
        with self._cond:
            return {
                "rejected_by_sensor": {
                    s: {
                        "since_accepted": k.since_delivered,
                        "last_rejected_s": k.last_s,
                        "last_error": k.last_reason,
                    }
                    for s, k in self._skips.items()
                }
            }

    def _skip(self, sensor: str, exc: Exception) -> None:
        """Count a message of ``sensor`` that was left out, and why."""
        if isinstance(exc, ImageSizeError):
            reason = str(exc)
        else:
            reason = f"cannot be decoded ({describe_error(exc)})"
            reason = reason if len(reason) <= 200 else reason[:199] + "…"
        with self._cond:
            k = self._skips.setdefault(sensor, _Skips())
            key = reason
            if key not in k.reasons and len(k.reasons) >= MAX_SKIP_REASONS:
                key = OTHER_REASONS
            k.reasons[key] = k.reasons.get(key, 0) + 1
            k.since_delivered += 1
            k.last_s = time.monotonic()
            k.last_reason = reason

    def _delivered(self, sensor: str) -> None:
        k = self._skips.get(sensor)
        if k is not None and k.since_delivered:
            with self._cond:
                k.since_delivered = 0

    # -- time line ------------------------------------------------------------------------

    @property
    def start_ns(self) -> int:
        """Log time of the first message (0 for an empty file)."""
        s = self.index.start_ns
        return 0 if s is None else s

    @property
    def end_ns(self) -> int:
        """Log time of the last message in the file's index (for a truncated file: the last
        complete chunk)."""
        e = self.index.end_ns
        return 0 if e is None else e

    @property
    def duration_s(self) -> float:
        """Seconds from the first to the last message."""
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def position_ns(self) -> int:
        """Log time of the last frame delivered (or where a seek will continue)."""
        with self._cond:
            return self._pending_seek if self._pending_seek is not None else self._position

    @property
    def rate(self) -> float:
        return self._rate

    @rate.setter
    def rate(self, value: float) -> None:
        value = self._check_rate(value)
        with self._cond:
            self._rate = value
            self._anchor = None  # re-anchor at the next frame
            self._cond.notify_all()

    @staticmethod
    def _check_rate(value: float) -> float:
        if not is_real(value):
            raise RecordingError(f"rate: expected a positive number, got {value!r}")
        if not math.isfinite(value) or value <= 0:
            raise RecordingError(f"rate: expected a positive finite number, got {value!r}")
        return float(value)

    @property
    def paused(self) -> bool:
        return self._paused

    def pause(self) -> None:
        """Hold the stream: ``frames()`` blocks before its next frame until :meth:`resume`."""
        with self._cond:
            self._paused = True
            self._cond.notify_all()

    def resume(self) -> None:
        """Continue after :meth:`pause`, from where it stopped (the pause is not caught up)."""
        with self._cond:
            self._paused = False
            self._anchor = None
            self._cond.notify_all()

    def seek(self, position: float) -> int:
        """Continue from ``position``: an ``int`` is a log time in nanoseconds, a ``float``
        a fraction of the duration (0.0 = start, 1.0 = end). Clamped to the recording;
        returns the target log time. Takes effect before the next frame (or at the start of
        the next ``frames()``)."""
        if not is_real(position):
            raise RecordingError(
                f"seek: expected a log time in ns (int) or a fraction (float), got {position!r}"
            )
        if isinstance(position, numbers.Integral):
            target = int(position)
        else:
            f = float(position)
            if not (math.isfinite(f) and 0.0 <= f <= 1.0):
                raise RecordingError(
                    f"seek: a float is a fraction of the duration, expected 0.0..1.0, got {f}"
                )
            target = self.start_ns + round(f * (self.end_ns - self.start_ns))
        target = min(max(target, self.start_ns), self.end_ns)
        with self._cond:
            self._pending_seek = target
            self._cond.notify_all()
        return target

    # -- iteration ------------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        """Frames in log-time order from the start (or the pending seek target); see the
        class docstring for damage, pacing and looping, the module's for skipping."""
        self.damage = None
        with self._cond:
            start = self._pending_seek if self._pending_seek is not None else self.start_ns
            self._pending_seek = None
            self._position = start
            self._anchor = None
        delivered = 0
        pass_delivered = 0
        pending: dict[str, _TofHalf] = {}
        cursor = _Lookahead(self.index.messages(start))
        while True:
            with self._cond:
                target = self._pending_seek
                self._pending_seek = None
            if target is not None:
                pending.clear()
                cursor = _Lookahead(self.index.messages(target))
                with self._cond:
                    self._position = target
                    self._anchor = (target, self._clock())
                pass_delivered = 1  # a seek counts as progress for the loop guard
            damage: tuple[str, int | None, int | None] | None = None
            try:
                msg: Message | None = next(cursor)
            except StopIteration:
                msg = None
            except McapDamage as exc:  # only its facts leave this block (not its frames)
                msg, damage = None, (exc.reason, exc.offset, exc.stamp_ns)
            if damage is not None:
                cursor = _Lookahead(iter(()))  # the chunks read so far go
                for s, h in sorted(pending.items(), key=lambda kv: kv[1].log_ns):
                    frame, _due = self._tof_frame(s, h)
                    delivered += 1
                    self._delivered(s)
                    yield frame
                pending.clear()
                self._damaged(*damage, delivered)
                return
            if msg is None:
                ready = [self._tof_frame(s, h) for s, h in pending.items()]
                pending.clear()
                ready.sort(key=lambda fr: fr[1])
                for frame, due in ready:
                    if self._wait(due):
                        delivered += 1
                        self._delivered(frame.sensor)
                        yield frame
                if self.loop and pass_delivered and self._pending_seek is None:
                    pass_delivered = 0
                    cursor = _Lookahead(self.index.messages(self.start_ns))
                    with self._cond:
                        self._position = self.start_ns
                        self._anchor = None
                    continue
                if self._pending_seek is not None:
                    continue
                return
            route = self._route_of(msg.channel_id)
            if route is None:
                continue
            if route.kind not in FRAME_KINDS:
                try:
                    self._side_message(route, msg)
                except Exception as exc:
                    log.warning(
                        "%s: ignoring a malformed %s message: %s", self.path, route.kind, exc
                    )
                continue
            if self.keep_time and self._superseded(msg, cursor):
                cursor.decoding.pop(id(msg), None)  # a decoding started for it goes too
                parts = self._tof_parts.get(route.sensor, {"tof_distance"})
                if route.kind != "tof_amplitude" or "tof_distance" not in parts:
                    with self._cond:  # a TOF frame is counted once, by its distance half
                        self._dropped[route.sensor] = self._dropped.get(route.sensor, 0) + 1
                continue
            try:
                stamp, data = self._decode(route, msg, cursor)
            except Exception as exc:
                self._skip(route.sensor, exc)
                continue
            for frame, due in self._collect(route, stamp, data, msg.log_time, pending):
                if not self._wait(due):
                    break  # a seek came: drop what was decoded before it
                delivered += 1
                pass_delivered += 1
                self._delivered(frame.sensor)
                yield frame

    def _route_of(self, channel_id: int) -> Route | None:
        if channel_id not in self._routes:
            channel = self.index.channels[channel_id]
            self._routes[channel_id] = self._route(channel)
        return self._routes[channel_id]

    def _collect(
        self,
        route: Route,
        stamp: int,
        data: np.ndarray,
        log_ns: int,
        pending: dict[str, _TofHalf],
    ) -> list[tuple[Frame, int]]:
        """Frames ready after this message: itself, or a completed (or abandoned) TOF pair."""
        out: list[tuple[Frame, int]] = []
        for s in [s for s, h in pending.items() if log_ns - h.log_ns > PAIR_WINDOW_NS]:
            out.append(self._tof_frame(s, pending.pop(s)))
        if route.kind in ("color", "thermal"):
            out.append((Frame(route.sensor, stamp, data), log_ns))
            return out
        half = pending.get(route.sensor)
        if half is not None and (
            abs(half.stamp_ns - stamp) > self.pair_tolerance_ns or route.kind in half.parts
        ):
            out.append(self._tof_frame(route.sensor, pending.pop(route.sensor)))
            half = None
        if half is None:
            half = pending[route.sensor] = _TofHalf(stamp, log_ns)
        half.parts[route.kind] = data
        half.log_ns = max(half.log_ns, log_ns)
        expected = self._tof_parts.get(route.sensor, {"tof_distance", "tof_amplitude"})
        if expected <= half.parts.keys():
            out.append(self._tof_frame(route.sensor, pending.pop(route.sensor)))
        return out

    @staticmethod
    def _tof_frame(sensor: str, half: _TofHalf) -> tuple[Frame, int]:
        distance = half.parts.get("tof_distance")
        amplitude = half.parts.get("tof_amplitude")
        if amplitude is None:
            assert distance is not None
            amplitude = np.full(distance.shape, np.nan, np.float32)
        return Frame(sensor, half.stamp_ns, amplitude, distance), half.log_ns

    def _decode(self, route: Route, msg: Message, cursor: _Lookahead) -> tuple[int, np.ndarray]:
        """``route.decode`` of ``msg``. Keeping time, a colour image's decoding starts the
        decoding of the other colour images of its instant in a worker thread (the stereo
        pair decodes on two cores); a message whose decoding was started so is waited for."""
        started = cursor.decoding.pop(id(msg), None)
        if started is not None and started[0] is msg:
            return started[1].result()
        if self.keep_time and route.kind == "color":
            for other in cursor.same_instant(msg.log_time):
                r = self._route_of(other.channel_id)
                if r is not None and r.kind == "color" and id(other) not in cursor.decoding:
                    if self._pair_decoder is None:
                        self._pair_decoder = ThreadPoolExecutor(
                            1, thread_name_prefix="replay-decode"
                        )
                    job = self._pair_decoder.submit(r.decode, other, self.frame_sizes.get(r.sensor))
                    cursor.decoding[id(other)] = (other, job)
        return route.decode(msg, self.frame_sizes.get(route.sensor))

    def _superseded(self, msg: Message, cursor: _Lookahead) -> bool:
        """Whether ``msg``'s time has passed (real time) and a newer message of its channel
        is due too (``keep_time``). The messages of one instant (within
        :data:`SAME_INSTANT_NS` of the first of them) are judged at the same moment: the
        two cameras of a stereo pair are kept or dropped together."""
        with self._cond:
            if not self.realtime or self._paused or self._anchor is None:
                return False
            judged = self._judged
            if (
                judged is None
                or judged[2] is not self._anchor  # a seek, resume or new rate since
                or not 0 <= msg.log_time - judged[0] <= SAME_INSTANT_NS
            ):
                anchor_ns, anchor_s = self._anchor
                now_ns = anchor_ns + round((self._clock() - anchor_s) * self._rate * 1e9)
                judged = self._judged = (msg.log_time, now_ns, self._anchor)
        now_ns = judged[1]
        return msg.log_time < now_ns and cursor.newer_due(msg.channel_id, now_ns)

    def _wait(self, due_ns: int) -> bool:
        """Block until a frame of log time ``due_ns`` is due, then count it as delivered
        (``position_ns``); False if a seek came first. The position moves under the same
        lock as :meth:`pause` reads and sets: once ``pause()`` returns, it stays put."""
        with self._cond:
            while True:
                if self._pending_seek is not None:
                    return False
                if self._paused:
                    self._cond.wait()
                    continue
                if self.realtime:
                    now = self._clock()
                    if self._anchor is None:
                        self._anchor = (due_ns, now)
                    anchor_ns, anchor_s = self._anchor
                    due_s = anchor_s + (due_ns - anchor_ns) / 1e9 / self._rate
                    if now < due_s:
                        self._sleep(due_s - now)
                        continue
                    if now - due_s > (KEEP_TIME_MAX_LAG_S if self.keep_time else MAX_LAG_S):
                        self._anchor = (due_ns, now)
                self._position = max(self._position, due_ns)
                return True

    def _damaged(
        self, reason: str, offset: int | None, stamp_ns: int | None, delivered: int
    ) -> None:
        exc = RecordingDamaged(
            self.path,
            reason,
            offset=offset,
            stamp_ns=stamp_ns,
            start_ns=self.start_ns,
            frames_delivered=delivered,
        )
        self.damage = exc
        if self.on_damage == "raise":
            raise exc
        log.warning("%s", exc)

    def close(self) -> None:
        if self._pair_decoder is not None:
            self._pair_decoder.shutdown(wait=True, cancel_futures=True)
        self.index.close()
