"""Progress of a long command (``trifuse record --source sim``): the time left from the rate
measured as the work goes, on one line redrawn in place on a terminal, as a few plain lines
in a pipe or a log.

The work is counted in planned units (e.g. the seconds each step should take on the
reference machine), so that steps of unequal cost weigh what they cost; the rate of those
units per wall second is measured over the last :data:`RATE_WINDOW_S` seconds, so that the
estimate follows a machine that gets busier or quieter while the job runs.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Callable
from typing import TextIO

RATE_WINDOW_S = 60.0
"""Wall seconds of the recent past whose rate of work gives the time left."""
LINE_GAP_S = 5.0
"""In a pipe: at least this many seconds between two progress lines (but the last)."""
FIRST_LINE_S = 10.0
"""In a pipe: the first line after this many seconds (the time left measured by then),
unless the work has reached its first tenth before."""
QUIET_S = 120.0
"""In a pipe: a line at least this often, even between two tenths of the work."""
REDRAW_S = 0.25
"""On a terminal: the line is redrawn at most this often (but the last)."""


def span(seconds: float) -> str:
    """A duration for people: ``42 s``, ``3.5 min`` or ``2.1 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


class RateMeter:
    """The time left of ``total`` units of work, from the rate measured over the last
    ``window_s`` seconds (all of it while the job is younger).

    Args:
        total: units of work in all (> 0).
        start_s: the clock's time when the work began (nothing done).
        window_s: seconds of the recent past the rate is measured over.
    """

    def __init__(self, total: float, start_s: float, window_s: float = RATE_WINDOW_S) -> None:
        self.total = float(total)
        self.window_s = window_s
        self._samples: deque[tuple[float, float]] = deque([(start_s, 0.0)])

    def add(self, now_s: float, done: float) -> None:
        """``done`` units of work were done at ``now_s`` (the clock's seconds)."""
        samples = self._samples
        samples.append((now_s, float(done)))
        # keep one sample at or before the window's start: the rate is measured from it
        while len(samples) > 2 and samples[1][0] <= now_s - self.window_s:
            samples.popleft()

    @property
    def done(self) -> float:
        """Units of work done at the latest sample."""
        return self._samples[-1][1]

    def rate(self) -> float | None:
        """Units of work per second over the window, or None before it can be measured."""
        (t0, d0), (t1, d1) = self._samples[0], self._samples[-1]
        if t1 <= t0 or d1 <= d0:
            return None
        return (d1 - d0) / (t1 - t0)

    def remaining_s(self) -> float | None:
        """Seconds left at the measured rate: 0 when all is done, None before a rate."""
        left = self.total - self.done
        if left <= 0:
            return 0.0
        rate = self.rate()
        return None if rate is None else left / rate


class ProgressLine:
    """Shows a job's progress: ``LABEL, elapsed 3.5 min, ETA 7.2 min``.

    On a terminal the line is redrawn in place (a carriage return) at most every
    :data:`REDRAW_S` seconds and ended by :meth:`close`. Elsewhere (a pipe, a log file)
    a line is printed after :data:`FIRST_LINE_S` seconds, then each time the work enters a
    new tenth or after :data:`QUIET_S` seconds without a line, but never within
    :data:`LINE_GAP_S` seconds of the last; the last step's line always.

    Args:
        total: units of work in all (:class:`RateMeter`).
        stream: where the lines go (default: stdout).
        clock: seconds, monotonic (default: ``time.monotonic``); the job starts now.
        tty: whether ``stream`` is a terminal (default: ``stream.isatty()``).
    """

    def __init__(
        self,
        total: float,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
        tty: bool | None = None,
    ) -> None:
        self.stream = sys.stdout if stream is None else stream
        self.clock = clock
        self.tty = self.stream.isatty() if tty is None else tty
        self.start_s = clock()
        self.meter = RateMeter(total, self.start_s)
        self.lines = 0
        """Lines printed (a pipe) or redraws (a terminal)."""
        self._last_s: float | None = None
        self._tenth = 0
        self._width = 0  # of the line on the terminal, to blank what a shorter one leaves

    def update(self, done: float, label: str) -> None:
        """``done`` units of the work are done; ``label`` says where it is (e.g.
        ``[812/1944] t = 15.20 s of 36 s``)."""
        now = self.clock()
        self.meter.add(now, done)
        total = self.meter.total
        last = done >= total
        tenth = min(10, int(10 * done / total)) if total > 0 else 10
        first = self._last_s is None
        since = now - (self.start_s if first else self._last_s)
        if self.tty:
            show = last or first or since >= REDRAW_S
        else:
            due = tenth > self._tenth or since >= (FIRST_LINE_S if first else QUIET_S)
            show = last or (since >= LINE_GAP_S and due)
        if not show:
            return
        self._last_s, self._tenth = now, tenth
        self.lines += 1
        self._write(f"{label}, {self.text(now)}")

    def text(self, now: float | None = None) -> str:
        """``elapsed 3.5 min, ETA 7.2 min`` (``ETA unknown`` before a rate is measured)."""
        elapsed = (self.clock() if now is None else now) - self.start_s
        left = self.meter.remaining_s()
        return f"elapsed {span(elapsed)}, ETA {'unknown' if left is None else span(left)}"

    def _write(self, line: str) -> None:
        if self.tty:
            pad = " " * max(0, self._width - len(line))
            self._width = len(line)
            print(f"\r{line}{pad}", end="", file=self.stream, flush=True)
        else:
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        """End the redrawn line (a terminal), so that what follows starts on its own."""
        if self.tty and self._width:
            print(file=self.stream, flush=True)
            self._width = 0
