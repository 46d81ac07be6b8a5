"""Recent frame rates: one sliding window for every rate the console shows.

Every rate the operator reads (each sensor's delivered rate in the Source panel, the
stream's rate in the Source panel, the status route and the viewer) counts events over the
last :data:`RATE_WINDOW_S` seconds, never a lifetime average.

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
from collections.abc import Callable
from dataclasses import dataclass

RATE_WINDOW_S = 3.0
"""Rates are counted over this much of the recent past (seconds)."""
MIN_SPAN_S = 0.2
"""Shortest time a rate is divided by, right after the first event (seconds)."""


def window_rate(times: deque[float], first_s: float | None, end_s: float, window_s: float) -> float:
    """Events per second in ``(end_s - window_s, end_s]``.

    Args:
        times: event times (seconds, non-decreasing), at least those of the window.
        first_s: time of the very first event (None: none yet).
        end_s: the window's end, seconds on the clock of ``times``.
        window_s: the window's length, seconds.

    Returns:
        The count divided by the window, or by the time since the first event when that is
        shorter (at least :data:`MIN_SPAN_S`); 0.0 before the first event.
    """
    if first_s is None or end_s < first_s:
        return 0.0
    n = sum(1 for t in times if end_s - window_s < t <= end_s)
    return n / min(window_s, max(end_s - first_s, MIN_SPAN_S))


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
        if not (isinstance(window_s, int | float) and math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s: expected a positive number of seconds, got {window_s!r}")
        self.window_s = float(window_s)
        self._clock, self._wall_ns = clock, wall_ns
        self._lock = threading.Lock()
        self._all: deque[float] = deque()
        self._new: deque[float] = deque()
        self._first: float | None = None
        self._cached: tuple[int, RatesSnapshot] | None = None

    def tick(self, new: bool) -> None:
        """Count one published frame; ``new``: a new picture (not a repeat)."""
        with self._lock:  # the clock is read under the lock: events arrive in time order
            now = self._clock()
            if self._first is None:
                self._first = now
            self._all.append(now)
            if new:
                self._new.append(now)
            keep = now - self.window_s - 2.0  # a snapshot may still ask for the last second
            for q in (self._all, self._new):
                while q and q[0] < keep:
                    q.popleft()

    def snapshot(self) -> RatesSnapshot:
        """The rates over the window ending at the last whole second of the clock.

        Readers within the same second get the same (cached) snapshot. A stalled stream
        reads 0 once the window has passed."""
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
                stream_fps=window_rate(self._all, self._first, end, self.window_s),
                new_fps=window_rate(self._new, self._first, end, self.window_s),
            )
            self._cached = (second, snap)
            return snap
