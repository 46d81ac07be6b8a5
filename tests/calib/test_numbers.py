"""calib/numbers.py: the type predicates every input check uses, on the values that make
them differ (bools, numpy scalars, NaN/inf, integers beyond float's range, strings)."""

from __future__ import annotations

import math
import numbers
from decimal import Decimal
from fractions import Fraction

import numpy as np
import pytest

from trifuse.calib.numbers import (
    check_finite,
    finite_float,
    is_int,
    is_int_or_float,
    is_integer,
    is_integral,
    is_real,
)


class _Registered:
    """An integer type that is neither int nor numpy's, registered as numbers.Integral
    (as sympy's and gmpy2's are)."""

    def __init__(self, v: int) -> None:
        self.v = v

    def __repr__(self) -> str:
        return f"_Registered({self.v})"


numbers.Integral.register(_Registered)

BIG = 10**400  # an int beyond float's range

# value -> (is_int, is_integer, is_integral, is_int_or_float, is_real)
CASES: list[tuple[object, tuple[bool, bool, bool, bool, bool]]] = [
    (True, (False, False, False, False, False)),
    (False, (False, False, False, False, False)),
    (np.bool_(True), (False, False, False, False, False)),
    (0, (True, True, True, True, True)),
    (-7, (True, True, True, True, True)),
    (BIG, (True, True, True, True, True)),
    (np.int64(3), (False, True, True, False, True)),
    (np.uint8(255), (False, True, True, False, True)),
    (np.int32(-1), (False, True, True, False, True)),
    (_Registered(2), (False, False, True, False, True)),
    (1.0, (False, False, False, True, True)),
    (math.nan, (False, False, False, True, True)),
    (math.inf, (False, False, False, True, True)),
    (-math.inf, (False, False, False, True, True)),
    (np.float64(2.5), (False, False, False, True, True)),  # a float subclass
    (np.float32(2.5), (False, False, False, False, True)),
    (np.float16(math.nan), (False, False, False, False, True)),
    (Fraction(1, 2), (False, False, False, False, True)),
    (Decimal("1.5"), (False, False, False, False, False)),
    (1 + 2j, (False, False, False, False, False)),
    ("3", (False, False, False, False, False)),
    ("nan", (False, False, False, False, False)),
    (None, (False, False, False, False, False)),
    ([1], (False, False, False, False, False)),
    (np.array(3), (False, False, False, False, False)),  # a 0-d array is not a scalar
]
PREDICATES = (is_int, is_integer, is_integral, is_int_or_float, is_real)


@pytest.mark.parametrize(("value", "expected"), CASES, ids=[repr(v) for v, _ in CASES])
def test_each_predicate_accepts_exactly_its_type_set(value: object, expected: tuple) -> None:
    got = tuple(p(value) for p in PREDICATES)
    assert got == expected, dict(zip([p.__name__ for p in PREDICATES], got, strict=True))


def test_each_predicate_is_what_its_sites_wrote_by_hand() -> None:
    """The predicates equal the hand-written expressions they replaced, on every case."""
    hand = (
        lambda v: not (isinstance(v, bool) or not isinstance(v, int)),
        lambda v: not (isinstance(v, bool) or not isinstance(v, int | np.integer)),
        lambda v: not (isinstance(v, bool) or not isinstance(v, numbers.Integral)),
        lambda v: isinstance(v, int | float) and not isinstance(v, bool),
        lambda v: not (isinstance(v, bool) or not isinstance(v, numbers.Real)),
    )
    for value, _ in CASES:
        for predicate, written in zip(PREDICATES, hand, strict=True):
            assert predicate(value) is written(value), (predicate.__name__, value)


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (3, 3.0),
        (-2.5, -2.5),
        (np.int64(4), 4.0),
        (np.float32(0.5), 0.5),
        (Fraction(1, 4), 0.25),
        (10**300, 1e300),
        (True, None),
        (np.bool_(False), None),
        (math.nan, None),
        (math.inf, None),
        (np.float64(-math.inf), None),
        (BIG, None),
        ("1.0", None),
        (None, None),
    ],
)
def test_finite_float(value: object, expected: float | None) -> None:
    got = finite_float(value)
    assert got == expected
    assert got is None or type(got) is float


def test_check_finite_names_the_place_and_the_kind_of_failure() -> None:
    assert check_finite(np.int64(2), "n") == 2.0
    for value in (True, "1", None, 1j):
        with pytest.raises(ValueError, match=r"^x\.y: expected a number, got "):
            check_finite(value, "x.y")
    for value in (math.nan, -math.inf, BIG):
        with pytest.raises(ValueError, match=r"^x\.y: expected a finite number, got "):
            check_finite(value, "x.y")

    class Wrong(ValueError):
        pass

    with pytest.raises(Wrong, match=r"^z: expected a number, got False$"):
        check_finite(False, "z", Wrong)
