"""The video stream's rate controller: one per viewer, driven by its acknowledgements.

Pure: no I/O and no clock of its own; every call passes the time ``t`` (seconds, any
monotonic origin). The sender reports each frame it sends (:meth:`RateController.on_sent`)
and each acknowledgement (:meth:`RateController.on_ack`); from these the controller knows
each frame's round trip (send -> ack), the frames and bytes in flight and the throughput
the viewer received over the last second. It answers what to send next
(:meth:`RateController.target`: bitrate, ladder level, frame rate) and whether a frame may
go now (:meth:`RateController.can_send`: fewer than :attr:`RateController.window` frames
unacknowledged, and not sooner than the level's frame period).

Each acknowledgement gives a delay sample: the frame's one-way delay when the viewer says
when the frame arrived (``recv_s``, its own clock: the offset between the clocks is
unknown but constant, so only the rise above the recent minimum counts), else its round
trip. The one-way delay leaves out what happens after the frame arrived (the viewer
decoding on a busy CPU, the acknowledgement's way back, the server's loop reading it late),
which would otherwise read as a queue on a machine that is merely busy.

Congestion is :data:`HIGH_IN_A_ROW` delays in a row well above the recent minimum (a queue
builds on the link; a resent packet or the viewer's hiccup delays fewer frames), or a
frame unacknowledged for much longer than the minimum round trip (the link stalled), or a
full window with a quarter of what was sent delivered or less (the link cannot carry it),
or the viewer falling behind its shared encoder (:meth:`RateController.on_dropped`: its
frames waiting to be sent were dropped): the bitrate steps down at once, multiplicatively
(to :data:`DECREASE` of itself, or of what the link carried, whichever is lower: for a
queue the rate of the acknowledgements that showed it, else the last second's throughput;
never the encoder's output of a still scene, which is below the target), at most once per
round trip (a step waits for the acknowledgement of a frame sent after the previous one).
A step taken for a stall or a short window is undone when the acknowledgements that end it
show that the frames had arrived without a queue (their one-way delays low: the
acknowledgements, not the frames, were late), as TCP undoes a spurious timeout. A clear
link (the last delay near the minimum, room in the window) raises it additively,
:data:`INCREASE_BPS_PER_S`, from :data:`HOLD_AFTER_DECREASE_S` after a decrease.
The bitrate stays between :data:`MIN_BPS` and the preset's cap. With preset ``auto`` the
level follows the bitrate down the ladder at once and back up with hysteresis
(:data:`UP_MARGIN`, :data:`UP_HOLD_S`). Frames are paced at the level's frame rate by a
token bucket that holds :data:`BURST_FRAMES` (a source's frames come unevenly: a strict
minimum gap would skip some that the rate allows).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from trifuse.app.recording.h264 import MIN_BPS, Level
from trifuse.app.server.runtime.video_presets import LEVEL_BY_NAME, LEVELS, check_preset

WINDOW = 4
"""Frames in flight (sent, not yet acknowledged): 30 frames/s over a 100 ms round trip."""
DECREASE = 0.7
"""A congestion step multiplies the bitrate by this (or sets it to this times the
delivered throughput, if lower)."""
INCREASE_BPS_PER_S = 500_000
"""A clear link raises the bitrate by this much per second."""
HOLD_AFTER_DECREASE_S = 1.5
"""No increase for this long after a decrease."""
QUEUE_DELAY_S = 0.08
"""Delays more than ``max(QUEUE_DELAY_S, min_rtt / 2)`` above their minimum are high."""
HIGH_IN_A_ROW = 3
"""This many high delays in a row, none falling, are congestion: a queue on the link
delays every frame more than or as much as the one before. A packet that TCP resends
delays the frames behind it too, but they arrive together, so their delays fall
frame by frame (each left later): a falling delay starts the count again."""
FALL_S = 0.010
"""A delay shorter than the one before by more than this is falling."""
STALL_S = 0.5
"""A frame unacknowledged for ``max(STALL_S, 3 min_rtt)`` is congestion (the link stalled)."""
SHORT_SHARE = 0.25
"""With the window full, a throughput below this share of what was sent is congestion."""
MIN_RTT_WINDOW_S = 10.0
"""The minimum round trip is the least of the last this many seconds."""
THROUGHPUT_WINDOW_S = 1.0
"""The delivered throughput is measured over this many seconds of acknowledgements."""
UP_MARGIN = 1.25
"""``auto`` moves up a level when the bitrate exceeds the current level's cap this much."""
UP_HOLD_S = 4.0
"""... and it has been on the current level this long (each change costs an IDR)."""
BURST_FRAMES = 2.0
"""The pacing bucket holds this many frames: after a gap, two frames may go back to back."""
PACE_SLACK = 0.1
"""A frame may go when the bucket holds ``1 - PACE_SLACK`` frames (timer jitter)."""


@dataclass(frozen=True)
class Target:
    """What to encode next: ``bitrate_bps`` (bit/s), the ladder ``level``, ``fps``
    (frames/s: the level's)."""

    bitrate_bps: int
    level: Level
    fps: int


@dataclass
class _InFlight:
    nbytes: int
    t_sent: float


@dataclass
class _Undo:
    """A step down for a stall or a short window, to undo if it proves spurious."""

    bitrate_bps: float  # before the step
    level: Level  # likewise
    last_seq: int  # the newest frame sent when it was taken


class RateController:
    """One viewer's bitrate and level (see the module doc).

    Args:
        preset: ``auto`` or a level's name (:data:`app.server.runtime.video_presets.PRESETS`;
            ValueError otherwise).
        window: the most frames in flight.
    """

    def __init__(self, preset: str = "auto", window: int = WINDOW) -> None:
        if window < 1:
            raise ValueError(f"the window must be at least one frame, got {window}")
        self.window = window
        self._in_flight: dict[int, _InFlight] = {}
        self._rtts: deque[tuple[float, float]] = deque()  # (t_ack, rtt), last MIN_RTT_WINDOW_S
        self._delays: deque[tuple[float, float]] = deque()  # (t_ack, delay), likewise
        self._one_way: bool | None = None  # delays are one-way (the viewer's recv_s)
        self._last_delay: float | None = None
        self._undo: _Undo | None = None
        self._credit = BURST_FRAMES  # the pacing bucket, frames
        self._credit_t: float | None = None
        self._acked: deque[tuple[float, int]] = deque()  # (t_ack, nbytes), last second
        self._sent: deque[tuple[float, int]] = deque()  # (t_sent, nbytes), last second
        self._first_sent_t: float | None = None
        self._last_seq = 0
        self._decrease_seq = 0  # a decrease waits for the ack of a frame sent after this
        self._decrease_t = float("-inf")
        self._update_t: float | None = None
        self._level_t = float("-inf")
        self.last_rtt_s: float | None = None
        self._high_run = 0  # delays in a row above the limit
        self.congestion_events = 0
        self.undone_events = 0
        """Steps down undone: the acknowledgements, not the frames, were late."""
        self.last_congestion: str | None = None
        """Why the last step down was taken: ``queue``, ``stall``, ``short`` or ``late``
        (module doc)."""
        self.set_preset(preset)

    # -- the sender's reports ---------------------------------------------------------------

    def set_preset(self, preset: str) -> None:
        """Change the preset: the bitrate starts again at its cap (``auto``: the top of the
        ladder), capped from now on."""
        self.preset = check_preset(preset)
        self.cap_bps = LEVELS[0].max_bps if preset == "auto" else LEVEL_BY_NAME[preset].max_bps
        self.bitrate_bps = float(self.cap_bps)
        self.level = LEVELS[0] if preset == "auto" else LEVEL_BY_NAME[preset]
        self._level_t = float("-inf")

    def on_sent(self, seq: int, nbytes: int, t: float) -> None:
        """Frame ``seq`` (increasing) of ``nbytes`` went out at ``t``."""
        self._credit = self._credit_at(t) - 1.0
        self._credit_t = t
        self._in_flight[seq] = _InFlight(nbytes, t)
        self._sent.append((t, nbytes))
        if self._first_sent_t is None:
            self._first_sent_t = t
        self._last_seq = max(self._last_seq, seq)

    def on_ack(self, seq: int, t: float, recv_s: float | None = None) -> None:
        """The viewer acknowledged frame ``seq`` at ``t``; acknowledges every older frame too
        (a viewer may skip an ack). Unknown or repeated ``seq``: ignored. ``recv_s``: when
        the frame reached the viewer, seconds on the viewer's own clock (any origin, the
        same for every ack of the viewer), if it says."""
        frame = self._in_flight.get(seq)
        if frame is None:
            return
        for old in [s for s in self._in_flight if s <= seq]:
            f = self._in_flight.pop(old)
            self._acked.append((t, f.nbytes))
        rtt = max(t - frame.t_sent, 0.0)
        self.last_rtt_s = rtt
        self._rtts.append((t, rtt))
        if self._one_way is None:
            self._one_way = recv_s is not None
        delay = None
        if self._one_way == (recv_s is not None):  # a viewer that changes its mind: rtt only
            delay = rtt if recv_s is None else recv_s - frame.t_sent
            self._delays.append((t, delay))
        self._trim(t)
        if delay is not None:
            self._on_delay(seq, delay, t)

    def on_dropped(self, t: float) -> None:
        """The viewer fell behind the encoder it shares with others: the frames waiting to
        be sent to it were dropped at ``t`` (it waits for the next key frame). Congestion
        (``late``): the bitrate steps down, at most once per :data:`STALL_S`."""
        if t - self._decrease_t > STALL_S:
            self._decrease(t, "late")

    def reset_in_flight(self) -> None:
        """Forget the frames in flight (the viewer asked for a fresh start)."""
        self._in_flight.clear()

    # -- what to send -----------------------------------------------------------------------

    @property
    def in_flight(self) -> int:
        """Frames sent and not acknowledged."""
        return len(self._in_flight)

    @property
    def bytes_in_flight(self) -> int:
        return sum(f.nbytes for f in self._in_flight.values())

    @property
    def min_rtt_s(self) -> float:
        """The least round trip of the last :data:`MIN_RTT_WINDOW_S` (0 before any)."""
        return min((r for _, r in self._rtts), default=0.0)

    @property
    def queue_delay_s(self) -> float | None:
        """The last delay sample above the least of the last :data:`MIN_RTT_WINDOW_S`
        (seconds; None before any)."""
        if self._last_delay is None:
            return None
        return self._last_delay - self._base_delay()

    def delivered_bps(self, t: float) -> float:
        """Bits acknowledged over the last :data:`THROUGHPUT_WINDOW_S` (or since the first
        frame went, if that is less), per second."""
        return self._rate_bps(self._acked, t)

    def sent_bps(self, t: float) -> float:
        """Bits sent over the same time, per second (what the encoder made: below the
        target when the scene needs less)."""
        return self._rate_bps(self._sent, t)

    def _rate_bps(self, log: deque[tuple[float, int]], t: float) -> float:
        self._trim(t)
        first = self._first_sent_t if self._first_sent_t is not None else t
        span = min(THROUGHPUT_WINDOW_S, t - first)
        return sum(n for _, n in log) * 8 / span if span > 0 else 0.0

    def can_send(self, t: float) -> bool:
        """Whether a frame may go at ``t``: the window has room and the level's frame
        period has passed since the last frame (a little early is allowed: jitter)."""
        return self.wait_s(t) == 0.0

    def wait_s(self, t: float) -> float | None:
        """Seconds until a frame may go (0: now); None while the window is full (an
        acknowledgement must come first)."""
        if len(self._in_flight) >= self.window:
            return None
        return max(0.0, (1.0 - PACE_SLACK - self._credit_at(t)) / self.level.fps)

    def _credit_at(self, t: float) -> float:
        """The pacing bucket at ``t``: frames that may go at the level's frame rate."""
        if self._credit_t is None:
            return BURST_FRAMES
        return min(BURST_FRAMES, self._credit + (t - self._credit_t) * self.level.fps)

    def target(self, t: float) -> Target:
        """The bitrate, level and frame rate to encode at ``t``; updates the bitrate (a
        stalled link steps it down, a clear one up)."""
        self._check_stall(t)
        last = self._update_t if self._update_t is not None else t
        self._update_t = t
        dt = max(t - last, 0.0)
        if t - self._decrease_t >= HOLD_AFTER_DECREASE_S and dt > 0 and self._clear():
            self.bitrate_bps = min(float(self.cap_bps), self.bitrate_bps + INCREASE_BPS_PER_S * dt)
        self._set_level(t)
        return Target(int(self.bitrate_bps), self.level, self.level.fps)

    # -- inside -----------------------------------------------------------------------------

    def _on_delay(self, seq: int, delay: float, t: float) -> None:
        """One delay sample (frame ``seq``, acknowledged at ``t``): the queue rule, and the
        verdict on a pending step down (:class:`_Undo`)."""
        high = delay - self._base_delay() > self._queue_limit_s()
        falling = self._last_delay is not None and delay < self._last_delay - FALL_S
        self._last_delay = delay
        undo = self._undo
        if undo is not None and self._one_way:
            if seq > undo.last_seq or high:
                self._undo = None  # a frame sent after the step, or the link was late
            elif undo.bitrate_bps > self.bitrate_bps:
                self.bitrate_bps, self.level = undo.bitrate_bps, undo.level  # it was in time
                self._undo = None
                self.undone_events += 1
        self._high_run = self._high_run + 1 if high and not falling else 0
        if self._high_run >= HIGH_IN_A_ROW and seq > self._decrease_seq:
            self._decrease(t, "queue")

    def _set_level(self, t: float) -> None:
        """The preset's level, or ``auto``'s: down at once to the lowest level whose cap
        covers the bitrate, up only past :data:`UP_MARGIN` times the current cap and
        :data:`UP_HOLD_S` after the last change."""
        if self.preset != "auto":
            return
        b = self.bitrate_bps
        fits = [lv for lv in LEVELS if lv.max_bps >= b] or [LEVELS[0]]
        best = fits[-1]  # the lowest level whose cap covers b
        current = self.level
        down = best.max_bps < current.max_bps
        up = (
            best.max_bps > current.max_bps
            and b > current.max_bps * UP_MARGIN
            and t - self._level_t >= UP_HOLD_S
        )
        if down or up:
            self.level, self._level_t = best, t

    def _queue_limit_s(self) -> float:
        """A delay more than this above :meth:`_base_delay` is high (seconds)."""
        return max(QUEUE_DELAY_S, self.min_rtt_s / 2)

    def _base_delay(self) -> float:
        """The least delay sample of the last :data:`MIN_RTT_WINDOW_S`."""
        return min((d for _, d in self._delays), default=0.0)

    def _clear(self) -> bool:
        """The link shows no queue: the last delay near the minimum, room in the window."""
        d = self._last_delay
        return (
            d is not None
            and d - self._base_delay() <= self._queue_limit_s()
            and self.in_flight < self.window
        )

    def _check_stall(self, t: float) -> None:
        if not self._in_flight:
            return
        oldest = min(f.t_sent for f in self._in_flight.values())
        stall = max(STALL_S, 3 * self.min_rtt_s)
        stalled = t - oldest > stall
        # a full window and a quarter of what was sent delivered: the link cannot carry
        # it (also where a standing queue has raised the minimum round trip)
        short = (
            len(self._in_flight) >= self.window
            and t - self._decrease_t > max(STALL_S, self.min_rtt_s)
            and self.delivered_bps(t) < SHORT_SHARE * self.sent_bps(t)
        )
        if (stalled and t - self._decrease_t > stall) or short:
            undo = self._undo or _Undo(self.bitrate_bps, self.level, self._last_seq)
            self._decrease(t, "stall" if stalled else "short")
            self._undo = _Undo(undo.bitrate_bps, undo.level, self._last_seq)

    def _queue_rate_bps(self) -> float:
        """What the link carried over the last :data:`HIGH_IN_A_ROW` acknowledgements (bit/s;
        0 when they came at once): while a queue stands, acknowledgements come as fast as
        the link delivers, which the last second's throughput, from before the queue,
        overstates."""
        recent = list(self._acked)[-HIGH_IN_A_ROW:]
        span = recent[-1][0] - recent[0][0] if len(recent) > 1 else 0.0
        return sum(n for _, n in recent[1:]) * 8 / span if span > 0 else 0.0

    def _decrease(self, t: float, reason: str) -> None:
        delivered = self.delivered_bps(t)
        if reason == "queue" and self._queue_rate_bps() > 0:
            # while the queue stands, acks come at the link's rate: the last second's
            # throughput is the encoder's (a still scene needs less than the target)
            delivered = self._queue_rate_bps()
        new = DECREASE * self.bitrate_bps
        if delivered > 0:
            new = min(new, DECREASE * delivered)
        self.bitrate_bps = max(float(MIN_BPS), new)
        self._decrease_seq = self._last_seq
        self._decrease_t = t
        self._update_t = t
        self.congestion_events += 1
        self.last_congestion = reason
        self._set_level(t)

    def _trim(self, t: float) -> None:
        while self._rtts and self._rtts[0][0] < t - MIN_RTT_WINDOW_S:
            self._rtts.popleft()
        while self._delays and self._delays[0][0] < t - MIN_RTT_WINDOW_S:
            self._delays.popleft()
        while self._acked and self._acked[0][0] < t - THROUGHPUT_WINDOW_S:
            self._acked.popleft()
        while self._sent and self._sent[0][0] < t - THROUGHPUT_WINDOW_S:
            self._sent.popleft()
