"""The colour span shared by both eyes, over time, and FLIR's level/span notation.

A span is ``(low, high)`` in kelvin, ``low < high``: the temperatures at the two ends of the
palette. Thermal cameras' menus call the same thing level (the centre, kelvin) and span (the
width, kelvin): :func:`span_from_level` and :func:`level_from_span` convert.

An automatic span taken from every frame's percentiles flickers as the scene's hottest
pixels come and go; :class:`SpanSmoother` low-passes it with a time constant measured on the
frames' own time stamps (nanoseconds), so a replay at any speed looks the same.

The span itself: fixed by the settings, or :func:`auto_span` over both eyes' temperature
images (:func:`resolve_span`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from trifuse.calib.numbers import check_finite, is_integer, is_integral
from trifuse.fusion.palettes import check_span

if TYPE_CHECKING:
    from trifuse.fusion.compose import DisplaySettings

__all__ = [
    "SpanSmoother",
    "auto_span",
    "level_from_span",
    "resolve_span",
    "span_from_level",
]


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
        if not is_integral(stamp_ns):
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


def auto_span(
    thermal_images: np.ndarray | Sequence[np.ndarray],
    low_pct: float = 1.0,
    high_pct: float = 99.0,
    *,
    step: int = 8,
    min_span_k: float = 1.0,
    default: tuple[float, float] | None = None,
) -> tuple[float, float]:
    """One palette span over several temperature images (both eyes): percentiles of the
    valid pixels of all of them together.

    Cheap: every ``step``-th pixel in each direction (1/64 of the pixels by default, about
    0.3 ms for two 1280 x 960 eyes). A span narrower than ``min_span_k`` (a uniform scene)
    is widened about its middle to ``min_span_k``, so noise is not stretched over the
    whole palette.

    Args:
        thermal_images: one array or a sequence of arrays of kelvin (any shape; 2-D
            images are subsampled in both directions); NaN and inf are ignored.
        low_pct, high_pct: percentiles, 0 <= low < high <= 100.
        step: subsampling step, positive.
        min_span_k: the narrowest span returned, positive.
        default: returned when no image has a finite pixel; if None, that is a ValueError.

    Returns:
        ``(low_k, high_k)`` with ``low < high``.
    """
    low_pct = check_finite(low_pct, "low_pct")
    high_pct = check_finite(high_pct, "high_pct")
    if not 0.0 <= low_pct < high_pct <= 100.0:
        raise ValueError(
            f"low_pct, high_pct: expected 0 <= low < high <= 100, got ({low_pct}, {high_pct})"
        )
    if not is_integer(step) or step < 1:
        raise ValueError(f"step: expected a positive integer, got {step!r}")
    if not check_finite(min_span_k, "min_span_k") > 0.0:
        raise ValueError(f"min_span_k: expected a positive number, got {min_span_k}")
    images = [thermal_images] if isinstance(thermal_images, np.ndarray) else list(thermal_images)
    samples = []
    for i, image in enumerate(images):
        a = np.asarray(image)
        if a.dtype.kind not in "fiu":
            raise ValueError(f"thermal_images[{i}]: expected numbers in kelvin, got {a.dtype}")
        sub = a[..., ::step, ::step] if a.ndim >= 2 else a.reshape(-1)[::step]
        samples.append(sub[np.isfinite(sub)])  # 1-D, no copy of the subsample itself
    values = np.concatenate(samples) if samples else np.empty(0)
    if values.size == 0:
        if default is not None:
            return check_span(default, "default")
        raise ValueError("thermal_images: expected at least one finite temperature, got none")
    low, high = (float(v) for v in np.percentile(values, [low_pct, high_pct]))
    if high - low < min_span_k:
        mid = 0.5 * (low + high)
        low, high = mid - 0.5 * min_span_k, mid + 0.5 * min_span_k
    return low, high


def resolve_span(
    settings: DisplaySettings, thermal_images: np.ndarray | Sequence[np.ndarray]
) -> tuple[float, float]:
    """The span to use for one stereo frame: ``settings.span_k``, or :func:`auto_span`
    over ``thermal_images`` (pass both eyes so they share it). An all-NaN frame gets the
    arbitrary span (273.15, 373.15): nothing is painted then anyway."""
    if settings.span_k is not None:
        return settings.span_k
    return auto_span(
        thermal_images,
        settings.auto_low_pct,
        settings.auto_high_pct,
        default=(273.15, 373.15),
    )
