"""Numbers read from files, messages and arguments: one vocabulary of type predicates.

A bool is an ``int`` in Python, so every "is this a number?" question must refuse it
explicitly; these predicates do, and nothing else should write ``isinstance(x, bool)``
unless "must be true or false" is the question. Each predicate names one exact type set
(they differ on purpose; pick the one the input can carry):

- :func:`is_int`: a Python ``int`` (what JSON and YAML parsers give); numpy integers refused.
- :func:`is_integer`: an ``int`` or a numpy integer.
- :func:`is_integral`: any ``numbers.Integral`` (also other registered integer types).
- :func:`is_int_or_float`: a Python ``int`` or ``float`` (``np.float64`` is a float
  subclass, so accepted); other numpy scalars and ``Fraction`` refused.
- :func:`is_real`: any ``numbers.Real`` (numpy integers and floats, ``Fraction``).

None of them looks at the value: NaN, infinity and integers beyond float's range pass
:func:`is_real` / :func:`is_int_or_float`; :func:`finite_float` and :func:`check_finite`
also ask for a finite value. Each is a ``TypeGuard``, not a ``TypeIs``: False does not
mean "not an int" (a bool is one).
"""

from __future__ import annotations

import math
import numbers
from typing import Any, TypeGuard

import numpy as np


def is_int(value: Any) -> TypeGuard[int]:
    """True for a Python ``int`` that is not a bool; numpy integers are refused."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_integer(value: Any) -> TypeGuard[int | np.integer]:
    """True for a Python ``int`` or a numpy integer (``np.int64``, ``np.uint8``, ...), not a
    bool (nor ``np.bool_``)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def is_integral(value: Any) -> TypeGuard[numbers.Integral]:
    """True for any ``numbers.Integral`` (int, numpy integers, other registered integer
    types), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_int_or_float(value: Any) -> TypeGuard[int | float]:
    """True for a Python ``int`` or ``float`` (``np.float64`` is a float subclass: accepted),
    not a bool; other numpy scalars (``np.int64``, ``np.float32``) are refused."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def is_real(value: Any) -> TypeGuard[numbers.Real]:
    """True for any ``numbers.Real`` (int, float, numpy integers and floats, ``Fraction``),
    not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def finite_float(value: Any) -> float | None:
    """``value`` as a float if it is a finite real number (:func:`is_real`), else None: also
    for NaN, infinity and integers beyond float's range."""
    if not is_real(value):
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
    if not is_real(value):
        raise error(f"{where}: expected a number, got {value!r}")
    raise error(f"{where}: expected a finite number, got {value!r}")
