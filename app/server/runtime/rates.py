"""Recent frame rates: one sliding window for every rate the console shows.

Every rate the operator reads (each sensor's delivered rate in the Source panel, the
stream's rate in the Source panel, the status route and the viewer, each video viewer's
frame rate) counts events over the recent past in a :class:`RateWindow`, never a lifetime
average.

:class:`StreamRates` measures the fused stream: frames published per second and, among
them, new pictures per second (the pipeline publishes the previous JPEG again when its
inputs have not changed, e.g. while the simulated head shows one rendered pose). Its
figures are taken at whole seconds (:meth:`StreamRates.snapshot`): whoever reads them
within the same second (the viewer through a frame's metadata, the Source panel, the
status route) gets the very same numbers, so two displays read at the same moment agree.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from trifuse.calib.numbers import is_int_or_float

RATE_WINDOW_S = 3.0
"""Rates are counted over this much of the recent past (seconds)."""
MIN_SPAN_S = 0.2
"""Shortest time a rate is divided by, right after the first event (seconds)."""
LATE_READ_S = 2.0
"""Events are kept this long beyond the window, for a rate read at an earlier end than the
newest event (:meth:`StreamRates.snapshot` reads at the last whole second)."""


class RateWindow:
    """Events per second over a sliding window, counted per key (thread-safe).

    The keys are what is counted: each sensor's frames (the Source panel), the stream's
    published frames and new pictures (:class:`StreamRates`), a viewer's frames sent
    (:class:`~trifuse.app.server.runtime.video_stats.VideoViewerStats`).

    Args:
        window_s: the window's length, seconds (ValueError unless positive and finite).
        from_first: divide by the time since the key's first event while that is shorter
            than the window (at least :data:`MIN_SPAN_S`); False: always by the window
            (a rate that ramps up over the first window).
        clock: monotonic seconds, read when a call gives no time (injectable for tests).

    Attributes:
        last_s: the time of the newest event (any key), seconds on ``clock``; None before.
    """

    def __init__(
        self,
        window_s: float = RATE_WINDOW_S,
        from_first: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (is_int_or_float(window_s) and math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s: expected a positive number of seconds, got {window_s!r}")
        self.window_s = float(window_s)
        self.from_first = from_first
        self._clock = clock
        self._lock = threading.Lock()
        self._times: dict[str, deque[float]] = {}
        self._first: dict[str, float] = {}
        self.last_s: float | None = None

    def tick(self, key: str, now_s: float | None = None) -> float:
        """Count one event of ``key`` at ``now_s`` seconds (default: the clock, read under
        the lock so that events arrive in time order); returns the time used."""
        with self._lock:
            now = self._clock() if now_s is None else now_s
            times = self._times.get(key)
            if times is None:
                times = self._times[key] = deque()
                self._first[key] = now
            times.append(now)
            keep = now - self.window_s - LATE_READ_S
            while times[0] < keep:
                times.popleft()
            self.last_s = now
            return now

    def rate(self, key: str, end_s: float | None = None, since: str | None = None) -> float:
        """Events of ``key`` per second in the window ``(end_s - window_s, end_s]``.

        Args:
            key: what is counted.
            end_s: the window's end, seconds on the clock (default: now).
            since: the key whose first event starts the time a young rate is divided by
                (default: ``key`` itself; ignored without ``from_first``).

        Returns:
            The count divided by the window or, with ``from_first``, by the time since the
            first event when that is shorter (at least :data:`MIN_SPAN_S`); 0.0 before the
            first event.
        """
        with self._lock:
            end = self._clock() if end_s is None else end_s
            return self._rate(key, end, key if since is None else since)

    def rates_hz(
        self, keys: Iterable[str] | None = None, now_s: float | None = None
    ) -> dict[str, float]:
        """``{key: events per second}`` at ``now_s`` (default: now) for ``keys`` and every
        key seen (0.0 for a key without events)."""
        with self._lock:
            now = self._clock() if now_s is None else now_s
            names = list(keys) if keys is not None else []
            names += [k for k in self._times if k not in names]
            return {k: self._rate(k, now, k) for k in names}

    def _rate(self, key: str, end_s: float, since: str) -> float:
        first = self._first.get(since)
        times = self._times.get(key, ())
        if first is None or end_s < first:
            return 0.0
        n = sum(1 for t in times if end_s - self.window_s < t <= end_s)
        if not self.from_first:
            return n / self.window_s
        return n / min(self.window_s, max(end_s - first, MIN_SPAN_S))


@dataclass(frozen=True)
class RatesSnapshot:
    """The stream's rates over the window that ends at ``at_ns``.

    Attributes:
        at_ns: wall-clock time (ns since the epoch) of the window's end, a whole second of
            the meter's clock: equal snapshots have equal ``at_ns``.
        window_s: the window's length, seconds.
        stream_fps: frames published to the stream per second (new or repeated pictures).
        new_fps: of these, new pictures (fused, not a repeat of the previous one) per second.
    """

    at_ns: int
    window_s: float
    stream_fps: float
    new_fps: float

    @property
    def repeat_fps(self) -> float:
        """Frames per second that repeat the previous picture (its input did not change)."""
        return max(self.stream_fps - self.new_fps, 0.0)

    def as_dict(self) -> dict[str, float | int]:
        """JSON-able, rates rounded to 0.01 frames per second."""
        return {
            "at_ns": self.at_ns,
            "window_s": self.window_s,
            "stream_fps": round(self.stream_fps, 2),
            "new_fps": round(self.new_fps, 2),
        }


class StreamRates:
    """Published frames and new pictures per second, over a sliding window (thread-safe).

    Args:
        window_s: the window's length, seconds.
        clock: monotonic seconds (injectable for tests).
        wall_ns: wall-clock nanoseconds (injectable for tests).
    """

    def __init__(
        self,
        window_s: float = RATE_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.window = RateWindow(window_s, clock=clock)
        self.window_s = self.window.window_s
        self._clock, self._wall_ns = clock, wall_ns
        self._lock = threading.Lock()
        self._cached: tuple[int, RatesSnapshot] | None = None

    def tick(self, new: bool) -> None:
        """Count one published frame; ``new``: a new picture (not a repeat)."""
        with self._lock:  # both counts at the same time, in time order
            now = self.window.tick("all")
            if new:
                self.window.tick("new", now)

    def snapshot(self) -> RatesSnapshot:
        """The rates over the window ending at the last whole second of the clock.

        Readers within the same second get the same (cached) snapshot. A stalled stream
        reads 0 once the window has passed; a young one divides by the time since its
        first frame."""
        with self._lock:
            now = self._clock()
            second = math.floor(now)
            cached = self._cached
            if cached is not None and cached[0] == second:
                return cached[1]
            end = float(second)
            snap = RatesSnapshot(
                at_ns=self._wall_ns() - round((now - end) * 1e9),
                window_s=self.window_s,
                stream_fps=self.window.rate("all", end),
                new_fps=self.window.rate("new", end, since="all"),
            )
            self._cached = (second, snap)
            return snap
