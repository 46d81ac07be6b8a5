"""The radiometric model of one thermal imager: the rig file's per-sensor ``radiometry`` block.

Three stages, applied in this order to the imager's raw value (counts, or kelvin from a
camera that already converts):

1. the radiometric calibration, raw -> kelvin: ``T_cal = gain * raw + offset_k``;
2. the balance between the two thermal imagers (estimated automatically from the points
   both see, :mod:`fusion.balance`): ``T_bal = balance_gain * T_cal + balance_offset_k``;
3. the operator's trim: ``T = T_bal + manual_offset_k``.

So ``T = balance_gain * (gain * raw + offset_k) + balance_offset_k + manual_offset_k``, an
affine map ``scale * raw + shift`` evaluated in one vectorised pass (:meth:`Radiometry.apply`).

The balance is estimated on calibrated temperatures (stage 1 only, :attr:`Radiometry.
calibration`), so that a new estimate replaces the balance rather than stacking on it and
does not undo the operator's trim.

Rig-file block (all keys optional, defaults shown)::

    radiometry: {gain: 1.0, offset_k: 0.0, balance_gain: 1.0, balance_offset_k: 0.0,
                 manual_offset_k: 0.0}
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from trifuse.calib.numbers import check_finite

__all__ = ["RADIOMETRY_KEYS", "Radiometry"]

RADIOMETRY_KEYS: tuple[str, ...] = (
    "gain",
    "offset_k",
    "balance_gain",
    "balance_offset_k",
    "manual_offset_k",
)
MAX_TRIM_K = 50.0
"""Largest balance or manual offset, kelvin: two imagers of one model disagree by about
1.5 K, a trim of more than 50 K is a typing error."""
MAX_OFFSET_K = 10_000.0
"""Largest radiometric calibration offset, kelvin (raw counts to kelvin)."""
GAIN_RANGE = (1e-6, 1e3)
"""Gains (kelvin per raw unit; the balance's, unitless) outside it are not physical."""
_LIMITS = {
    "gain": GAIN_RANGE,
    "balance_gain": GAIN_RANGE,
    "offset_k": (-MAX_OFFSET_K, MAX_OFFSET_K),
    "balance_offset_k": (-MAX_TRIM_K, MAX_TRIM_K),
    "manual_offset_k": (-MAX_TRIM_K, MAX_TRIM_K),
}


def _check_field(name: str, value: Any, where: str) -> float:
    """``value`` as a float within its physical limits, or ValueError naming ``where.name``."""
    v = check_finite(value, f"{where}.{name}")
    low, high = _LIMITS[name]
    if not low <= v <= high:
        raise ValueError(f"{where}.{name}: expected a number in [{low:g}, {high:g}], got {v:g}")
    return v


@dataclass(frozen=True)
class Radiometry:
    """Raw value -> kelvin for one thermal imager (see the module docstring).

    Attributes:
        gain: radiometric calibration, kelvin per raw unit (in ``GAIN_RANGE``).
        offset_k: radiometric calibration, kelvin (at most ``MAX_OFFSET_K``).
        balance_gain: the automatic balance between the two imagers (in ``GAIN_RANGE``,
            unitless).
        balance_offset_k: the automatic balance, kelvin (at most ``MAX_TRIM_K``).
        manual_offset_k: the operator's trim, kelvin (at most ``MAX_TRIM_K``).

    Every field is a finite plain float (checked on construction; ValueError otherwise),
    so instances are hashable and compare by value.
    """

    gain: float = 1.0
    offset_k: float = 0.0
    balance_gain: float = 1.0
    balance_offset_k: float = 0.0
    manual_offset_k: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(
                self, f.name, _check_field(f.name, getattr(self, f.name), "Radiometry")
            )

    # -- the affine map -------------------------------------------------------------------

    @property
    def scale(self) -> float:
        """Kelvin per raw unit of the whole chain: ``balance_gain * gain``."""
        return self.balance_gain * self.gain

    @property
    def shift_k(self) -> float:
        """Kelvin at raw 0: ``balance_gain * offset_k + balance_offset_k + manual_offset_k``."""
        return self.balance_gain * self.offset_k + self.balance_offset_k + self.manual_offset_k

    @property
    def identity(self) -> bool:
        """True when the whole chain maps every value to itself (scale 1, shift 0), even if
        individual terms are not at their defaults (e.g. a balance offset cancelled by the
        trim)."""
        return self.scale == 1.0 and self.shift_k == 0.0

    @property
    def calibration(self) -> Radiometry:
        """Stage 1 only (no balance, no trim): what the balance is estimated on."""
        return Radiometry(gain=self.gain, offset_k=self.offset_k)

    def apply(self, raw: npt.ArrayLike, out: np.ndarray | None = None) -> np.ndarray:
        """Kelvin from raw values, vectorised, NaN stays NaN.

        Args:
            raw: any shape, e.g. an (H, W) image; any real dtype (float32 kelvin, uint16
                counts ...).
            out: optional preallocated float32 array of ``raw``'s shape, written in place
                (may be ``raw`` itself); per-frame code passes one so nothing is allocated.

        Returns:
            float32 kelvin of ``raw``'s shape. When the model is the :attr:`identity`, the
            input itself if it already is a float32 array (no copy; ``out`` is then not
            written), else its float32 conversion. Otherwise ``out`` (or a new array).

        Raises:
            ValueError: ``out`` is not a float32 array of ``raw``'s shape.
        """
        if self.identity:
            return np.asarray(raw, dtype=np.float32)
        x = np.asarray(raw)
        if out is None:
            out = np.empty(x.shape, dtype=np.float32)
        elif not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.shape != x.shape:
            got = (
                f"{out.dtype} array of shape {out.shape}"
                if isinstance(out, np.ndarray)
                else type(out).__name__
            )
            raise ValueError(f"out: expected a float32 array of shape {x.shape}, got {got}")
        np.multiply(x, np.float32(self.scale), out=out, casting="unsafe")
        np.add(out, np.float32(self.shift_k), out=out)
        return out

    # -- copies ---------------------------------------------------------------------------

    def with_balance(self, gain: float, offset_k: float) -> Radiometry:
        """A copy with the automatic balance replaced (``balance_gain``, ``balance_offset_k``)."""
        return replace(self, balance_gain=gain, balance_offset_k=offset_k)

    def with_manual(self, offset_k: float) -> Radiometry:
        """A copy with the operator's trim replaced (ValueError beyond ``MAX_TRIM_K``)."""
        return replace(self, manual_offset_k=offset_k)

    # -- the rig file's block -------------------------------------------------------------

    def to_dict(self) -> dict[str, float]:
        """The rig-file block: all five keys, plain floats."""
        return {k: float(getattr(self, k)) for k in RADIOMETRY_KEYS}

    @classmethod
    def from_dict(cls, data: Any, where: str = "radiometry") -> Radiometry:
        """Parse a rig-file block; missing keys take their defaults.

        Args:
            data: a mapping with any subset of :data:`RADIOMETRY_KEYS`.
            where: prefix of error messages, e.g. ``"sensor 'thermal_left': radiometry"``.

        Raises:
            ValueError: not a mapping; unknown keys (the message lists the allowed ones);
                a value that is not a real number (bools included), NaN or infinite; a
                ``gain`` or ``balance_gain`` <= 0. The message names the field.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"{where}: expected a mapping, got {type(data).__name__}")
        unknown = sorted((str(k) for k in data if k not in RADIOMETRY_KEYS), key=str)
        if unknown:
            raise ValueError(
                f"{where}: unknown key(s) {unknown} (allowed: {list(RADIOMETRY_KEYS)})"
            )
        return cls(**{k: _check_field(k, v, where) for k, v in data.items()})
