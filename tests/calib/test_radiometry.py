"""The thermal imagers' radiometric model (calib.radiometry): the maths of the three stages,
no-copy identity and preallocated output, NaN, and the rig-file block's round trip and
error messages."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trifuse.calib.radiometry import RADIOMETRY_KEYS, Radiometry

FULL = Radiometry(
    gain=1.1, offset_k=-2.0, balance_gain=0.98, balance_offset_k=0.3, manual_offset_k=-0.1
)


def expected(r: Radiometry, raw: np.ndarray) -> np.ndarray:
    """The documented formula, in float64."""
    raw64 = raw.astype(np.float64)
    return r.balance_gain * (r.gain * raw64 + r.offset_k) + r.balance_offset_k + r.manual_offset_k


def test_apply_is_the_documented_formula() -> None:
    rng = np.random.default_rng(0)
    raw = rng.uniform(250.0, 400.0, (288, 382)).astype(np.float32)
    t = FULL.apply(raw)
    assert t.dtype == np.float32 and t.shape == raw.shape
    # float32 at 400 K resolves 3e-5 K; two rounded operations stay well below 1e-4 K.
    np.testing.assert_allclose(t, expected(FULL, raw), rtol=0, atol=1e-4)
    assert FULL.scale == pytest.approx(0.98 * 1.1)
    assert FULL.shift_k == pytest.approx(0.98 * -2.0 + 0.3 - 0.1)


def test_apply_converts_raw_counts() -> None:
    counts = np.array([[0, 1000], [29315, 65535]], dtype=np.uint16)
    r = Radiometry(gain=0.01, offset_k=0.0)
    t = r.apply(counts)
    assert t.dtype == np.float32
    np.testing.assert_allclose(t, [[0.0, 10.0], [293.15, 655.35]], rtol=1e-6)


def test_identity_returns_the_input_itself() -> None:
    raw = np.full((4, 5), 300.0, np.float32)
    assert Radiometry().identity
    assert Radiometry().apply(raw) is raw
    out = np.zeros_like(raw)
    assert Radiometry().apply(raw, out=out) is raw  # no copy, even with a buffer
    assert not out.any()
    # The whole chain counts, not each term: a balance offset cancelled by the trim.
    cancelled = Radiometry(balance_offset_k=0.5, manual_offset_k=-0.5)
    assert cancelled.identity and cancelled.apply(raw) is raw
    assert not FULL.identity
    # A non-float32 input is converted (the result is always float32).
    as64 = Radiometry().apply(raw.astype(np.float64))
    assert as64.dtype == np.float32


def test_apply_writes_into_out_without_allocating() -> None:
    rng = np.random.default_rng(1)
    raw = rng.uniform(280.0, 320.0, (6, 7)).astype(np.float32)
    out = np.empty_like(raw)
    result = FULL.apply(raw, out=out)
    assert result is out
    np.testing.assert_allclose(out, expected(FULL, raw), atol=1e-4)
    # In place on the input itself.
    copy = raw.copy()
    assert FULL.apply(copy, out=copy) is copy
    np.testing.assert_allclose(copy, expected(FULL, raw), atol=1e-4)


@pytest.mark.parametrize(
    ("out", "message"),
    [
        (np.empty((6, 7), np.float64), "float64 array of shape (6, 7)"),
        (np.empty((7, 6), np.float32), "float32 array of shape (7, 6)"),
        ([0.0], "got list"),
    ],
)
def test_apply_rejects_a_wrong_out_buffer(out: object, message: str) -> None:
    with pytest.raises(ValueError, match=r"out: expected a float32 array of shape \(6, 7\)") as e:
        FULL.apply(np.zeros((6, 7), np.float32), out=out)  # type: ignore[arg-type]
    assert message in str(e.value)


def test_nan_stays_nan() -> None:
    raw = np.array([300.0, np.nan, 310.0], np.float32)
    t = FULL.apply(raw)
    assert np.isnan(t[1]) and np.isfinite(t[[0, 2]]).all()


def test_dict_round_trip() -> None:
    d = FULL.to_dict()
    assert list(d) == list(RADIOMETRY_KEYS)
    assert all(type(v) is float for v in d.values())
    assert Radiometry.from_dict(d) == FULL
    assert Radiometry.from_dict(d).to_dict() == d
    assert Radiometry.from_dict({}) == Radiometry()
    # Any subset; ints are numbers too.
    assert Radiometry.from_dict({"manual_offset_k": 1}) == Radiometry(manual_offset_k=1.0)
    assert Radiometry.from_dict({"gain": np.float32(0.5)}).gain == 0.5


def test_copies() -> None:
    balanced = FULL.with_balance(1.02, -0.7)
    assert (balanced.balance_gain, balanced.balance_offset_k) == (1.02, -0.7)
    assert (balanced.gain, balanced.offset_k, balanced.manual_offset_k) == (1.1, -2.0, -0.1)
    assert FULL.balance_gain == 0.98  # unchanged
    trimmed = FULL.with_manual(0.25)
    assert trimmed.manual_offset_k == 0.25 and trimmed.balance_offset_k == 0.3
    assert FULL.calibration == Radiometry(gain=1.1, offset_k=-2.0)
    assert hash(FULL) == hash(Radiometry.from_dict(FULL.to_dict()))


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ([1.0], "radiometry: expected a mapping, got list"),
        (None, "radiometry: expected a mapping, got NoneType"),
        (
            {"gain": 1.0, "ofset_k": 0.0},
            "radiometry: unknown key(s) ['ofset_k'] (allowed: ['gain', 'offset_k', "
            "'balance_gain', 'balance_offset_k', 'manual_offset_k'])",
        ),
        ({"offset_k": "1.5"}, "radiometry.offset_k: expected a number, got '1.5'"),
        ({"manual_offset_k": True}, "radiometry.manual_offset_k: expected a number, got True"),
        ({"balance_offset_k": None}, "radiometry.balance_offset_k: expected a number, got None"),
        ({"offset_k": math.nan}, "radiometry.offset_k: expected a finite number, got nan"),
        ({"manual_offset_k": math.inf}, "expected a finite number, got inf"),
        ({"gain": 0.0}, "radiometry.gain: expected a number in [1e-06, 1000], got 0"),
        ({"gain": -1}, "radiometry.gain: expected a number in [1e-06, 1000], got -1"),
        ({"balance_gain": 0}, "radiometry.balance_gain: expected a number in [1e-06, 1000]"),
        # physical bounds: a 1e308 K offset overflowed a float32 cast in the fusion
        ({"manual_offset_k": 1e308}, "manual_offset_k: expected a number in [-50, 50], got 1e+308"),
        ({"balance_offset_k": -51}, "balance_offset_k: expected a number in [-50, 50]"),
        ({"offset_k": 2e4}, "radiometry.offset_k: expected a number in [-10000, 10000]"),
        ({"gain": 1e5}, "radiometry.gain: expected a number in [1e-06, 1000]"),
    ],
)
def test_from_dict_names_the_bad_field(data: object, message: str) -> None:
    with pytest.raises(ValueError) as e:
        Radiometry.from_dict(data)
    assert message in str(e.value)


def test_from_dict_prefixes_the_location() -> None:
    with pytest.raises(ValueError, match=r"^sensor 'thermal_left': radiometry\.gain: "):
        Radiometry.from_dict({"gain": -2.0}, where="sensor 'thermal_left': radiometry")


def test_constructor_validates_too() -> None:
    with pytest.raises(ValueError, match=r"Radiometry\.balance_gain: expected a number in"):
        Radiometry(balance_gain=0.0)
    with pytest.raises(ValueError, match=r"Radiometry\.offset_k: expected a finite number"):
        Radiometry(offset_k=math.nan)
    # Copies are checked as well.
    with pytest.raises(ValueError, match=r"Radiometry\.balance_gain: expected a number in"):
        FULL.with_balance(-1.0, 0.0)
    with pytest.raises(ValueError, match=r"Radiometry\.manual_offset_k: expected a finite"):
        FULL.with_manual(math.inf)
