"""The colour span shared by both eyes, over time, and FLIR's level/span notation.

A span is ``(low, high)`` in kelvin, ``low < high``: the temperatures at the two ends of the
palette. Thermal cameras' menus call the same thing level (the centre, kelvin) and span (the
width, kelvin): :func:`span_from_level` and :func:`level_from_span` convert.

An automatic span taken from every frame's percentiles flickers as the scene's hottest
pixels come and go; :class:`SpanSmoother` low-passes it with a time constant measured on the
frames' own time stamps (nanoseconds), so a replay at any speed looks the same.
"""

from __future__ import annotations

import math
import numbers

from trifuse.calib.numbers import check_finite

__all__ = ["SpanSmoother", "level_from_span", "span_from_level"]


def _check_span(low: float, high: float, name: str = "span") -> tuple[float, float]:
    lo, hi = check_finite(low, f"{name} low"), check_finite(high, f"{name} high")
    if not lo < hi:
        raise ValueError(f"{name}: expected low < high (kelvin), got ({lo}, {hi})")
    return lo, hi


def span_from_level(level_k: float, span_k: float) -> tuple[float, float]:
    """``(low, high)`` kelvin from a level (the centre, kelvin) and a span (the width,
    kelvin, > 0). Raises ValueError for a span <= 0 or non-finite values."""
    level = check_finite(level_k, "level_k")
    span = check_finite(span_k, "span_k")
    if span <= 0.0:
        raise ValueError(f"span_k: expected a width > 0 kelvin, got {span_k!r}")
    return level - span / 2.0, level + span / 2.0


def level_from_span(low: float, high: float) -> tuple[float, float]:
    """``(level, span)`` kelvin: the centre and the width of ``(low, high)``. Raises
    ValueError unless ``low < high`` (both finite)."""
    lo, hi = _check_span(low, high)
    return (lo + hi) / 2.0, hi - lo


class SpanSmoother:
    """Exponential smoothing of a ``(low, high)`` span over frame time.

    Each end moves ``alpha = 1 - exp(-dt / time_constant_s)`` of the way to the new value,
    ``dt`` being the time since the previous update (from the frames' ``stamp_ns``). The
    first update, and any update whose time stamp is not later than the previous one (a
    replay that looped or was sought back), snaps to the given span: a jump in time is a new
    start, not a huge or negative step. ``time_constant_s`` 0 disables the smoothing.
    """

    def __init__(self, time_constant_s: float = 1.0) -> None:
        tau = check_finite(time_constant_s, "time_constant_s")
        if tau < 0.0:
            raise ValueError(f"time_constant_s: expected >= 0 seconds, got {time_constant_s!r}")
        self.time_constant_s = tau
        self._span: tuple[float, float] | None = None
        self._stamp_ns: int | None = None

    @property
    def span(self) -> tuple[float, float] | None:
        """The current smoothed span (kelvin), None before the first update."""
        return self._span

    def reset(self) -> None:
        """Forget the state: the next update snaps."""
        self._span = None
        self._stamp_ns = None

    def update(self, span: tuple[float, float], stamp_ns: int) -> tuple[float, float]:
        """Feed one frame's span ``(low, high)`` kelvin at ``stamp_ns`` (int nanoseconds);
        returns the smoothed span.

        Raises:
            ValueError: ``span`` is not two finite numbers with low < high, or ``stamp_ns``
                is not an integer.
        """
        try:
            low, high = span
        except (TypeError, ValueError):
            raise ValueError(f"span: expected (low, high) kelvin, got {span!r}") from None
        lo, hi = _check_span(low, high)
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, numbers.Integral):
            raise ValueError(f"stamp_ns: expected an integer (nanoseconds), got {stamp_ns!r}")
        stamp_ns = int(stamp_ns)
        prev, prev_stamp = self._span, self._stamp_ns
        self._stamp_ns = stamp_ns
        if prev is None or prev_stamp is None or stamp_ns <= prev_stamp:
            self._span = (lo, hi)
            return self._span
        if self.time_constant_s == 0.0:
            alpha = 1.0
        else:
            alpha = -math.expm1(-(stamp_ns - prev_stamp) * 1e-9 / self.time_constant_s)
        self._span = (prev[0] + alpha * (lo - prev[0]), prev[1] + alpha * (hi - prev[1]))
        return self._span
