"""Numbers read from files and messages: one check of "a finite real number"."""

from __future__ import annotations

import math
import numbers
from typing import Any


def finite_float(value: Any) -> float | None:
    """``value`` as a float if it is a finite real number (int, float or a numpy scalar;
    not a bool), else None: also for NaN, infinity and integers beyond float's range."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float's range
        return None
    return number if math.isfinite(number) else None


def check_finite(value: Any, where: str, error: type[Exception] = ValueError) -> float:
    """``value`` as a float (:func:`finite_float`), else ``error`` naming ``where``:
    "expected a number" for anything else, "expected a finite number" for NaN, infinity
    and integers beyond float's range."""
    number = finite_float(value)
    if number is not None:
        return number
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise error(f"{where}: expected a number, got {value!r}")
    raise error(f"{where}: expected a finite number, got {value!r}")
