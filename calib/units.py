"""The 16-bit integer forms of readings in files and messages (docs/FORMATS.md).

| reading | in memory (docs/CONVENTIONS.md) | 16-bit form | 0 means |
| --- | --- | --- | --- |
| thermal temperature | float32 kelvin, NaN = no reading | centi-kelvin | no reading |
| TOF radial distance | float32 metres, NaN = invalid | millimetres | invalid |
| TOF amplitude | float32, arbitrary units | the value, rounded | (a value) |

Encoding rounds to the nearest count (NaN -> 0); decoding divides in float64 and rounds
once to float32, which for every 16-bit count is the same float32 as ``counts * scale``
with the per-count scales below (the form messages state their scale in). Only ``app/``
calls these, where it reads or writes; everything in between works in SI units.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = [
    "COUNTS_PER_K",
    "COUNTS_PER_M",
    "KELVIN_PER_COUNT",
    "METRES_PER_COUNT",
    "UINT16_MAX",
    "encode_amplitude",
    "encode_distance",
    "encode_thermal",
    "kelvin_from_counts",
    "metres_from_counts",
]

UINT16_MAX = 65535
COUNTS_PER_K = 100.0
"""Counts per kelvin of a 16-bit thermal reading (centi-kelvin)."""
COUNTS_PER_M = 1000.0
"""Counts per metre of a 16-bit TOF distance (millimetres)."""
KELVIN_PER_COUNT = 1.0 / COUNTS_PER_K
"""The scale of a 16-bit thermal reading, ``kelvin = counts * scale`` (0.01)."""
METRES_PER_COUNT = 1.0 / COUNTS_PER_M
"""The scale of a 16-bit TOF distance, ``metres = counts * scale`` (0.001)."""


def _to_uint16(values: npt.ArrayLike, counts_per_unit: float) -> np.ndarray:
    """``round(values * counts_per_unit)`` clipped to 0..65535 as uint16; NaN -> 0."""
    v = np.asarray(values, dtype=np.float64) * counts_per_unit
    v = np.where(np.isfinite(v), v, 0.0)
    return np.clip(np.rint(v), 0, UINT16_MAX).astype(np.uint16)


def encode_thermal(temperature_k: npt.ArrayLike) -> np.ndarray:
    """Kelvin (H, W) -> uint16 centi-kelvin (H, W): rounded, clipped to 0..655.35 K, NaN -> 0."""
    return _to_uint16(temperature_k, COUNTS_PER_K)


def encode_amplitude(amplitude: npt.ArrayLike) -> np.ndarray:
    """TOF amplitude (H, W) -> uint16 (H, W): rounded, clipped to 0..65535, NaN -> 0."""
    return _to_uint16(amplitude, 1.0)


def encode_distance(distance_m: npt.ArrayLike) -> np.ndarray:
    """Radial distance in metres (H, W) -> uint16 millimetres (H, W), 0 = invalid.

    NaN, negative and zero distances become 0; distances beyond 65.535 m, which 16 bits
    cannot hold, also become 0 (invalid) rather than being clipped to a wrong range.
    """
    mm = np.asarray(distance_m, dtype=np.float64) * COUNTS_PER_M
    valid = np.isfinite(mm) & (mm > 0) & (mm <= UINT16_MAX + 0.5)
    out = np.zeros(mm.shape, dtype=np.uint16)
    out[valid] = np.clip(np.rint(mm[valid]), 0, UINT16_MAX).astype(np.uint16)
    return out


def _from_counts(counts: np.ndarray, counts_per_unit: float) -> np.ndarray:
    """``counts / counts_per_unit`` (H, W) float32 (float64 division, one rounding), NaN
    where the count is 0."""
    values = (counts / counts_per_unit).astype(np.float32)
    values[counts == 0] = np.nan
    return values


def kelvin_from_counts(counts: np.ndarray) -> np.ndarray:
    """16-bit centi-kelvin (H, W) -> float32 kelvin (H, W), NaN where 0 (no reading)."""
    return _from_counts(counts, COUNTS_PER_K)


def metres_from_counts(counts: np.ndarray) -> np.ndarray:
    """16-bit millimetres (H, W) -> float32 metres (H, W), NaN where 0 (invalid)."""
    return _from_counts(counts, COUNTS_PER_M)
