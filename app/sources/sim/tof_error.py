"""Systematic range error of the simulated TOF camera, after the SR4000's behaviour.

The measured radial distance is ``d_true + error_m(d, amplitude) + noise``, where the
systematic error is the sum of

* a constant bias and a distance-dependent periodic "wiggling" term (harmonics of the
  modulation frequency),
* a per-pixel offset: a smooth bowl growing with the distance from the image centre, a
  steep rise in the border (region 4, unreliable) and a fixed-pattern per-pixel part,
* an amplitude-dependent term (weak returns read long, saturating ones short).

With the defaults the error is about 40 mm RMS over regions 1-3 at 0.6-4 m, like the
uncalibrated camera in the method (41 mm on the optical axis, 46 mm at the edge of
region 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class RangeErrorModel:
    """Ground-truth systematic range error of a TOF camera, metres.

    Attributes:
        width, height: TOF image size in pixels.
        bias_m: constant offset.
        wiggle: (amplitude m, period m, phase rad) of each periodic term in distance.
        radial_m: offset at the image corner of the smooth bowl ``radial_m * r^2``
            (r = 0 at the centre, 1 at the corner).
        border_m: extra offset reached at the outermost pixels of region 4.
        pixel_sigma_m: standard deviation of the fixed per-pixel offset pattern.
        amplitude_m: scale of the amplitude term ``amplitude_m * log10(ref / A)``.
        amplitude_ref: amplitude at which the amplitude term is zero.
        seed: seed of the fixed per-pixel pattern (a property of the camera unit).
    """

    width: int = 176
    height: int = 144
    bias_m: float = 0.031
    wiggle: tuple[tuple[float, float, float], ...] = ((0.026, 1.875, 0.6), (0.008, 0.9375, 2.1))
    radial_m: float = 0.028
    border_m: float = 0.07
    pixel_sigma_m: float = 0.005
    amplitude_m: float = 0.008
    amplitude_ref: float = 3000.0
    seed: int = 4000

    @cached_property
    def pixel_offset_m(self) -> np.ndarray:
        """(height, width) float64 per-pixel offset in metres (bowl + border + pattern)."""
        u = (np.arange(self.width) - (self.width - 1) / 2) / (self.width / 2)
        v = (np.arange(self.height) - (self.height - 1) / 2) / (self.height / 2)
        uu, vv = np.meshgrid(u, v)
        r2 = (uu * uu + vv * vv) / 2.0
        box = np.maximum(np.abs(uu), np.abs(vv))
        border = np.clip((box - 0.8) / 0.2, 0.0, 1.0) ** 2
        pattern = np.random.default_rng(self.seed).normal(0.0, self.pixel_sigma_m, r2.shape)
        return self.radial_m * r2 + self.border_m * border + pattern

    def wiggle_m(self, distance_m: np.ndarray) -> np.ndarray:
        """Distance-dependent part (bias + wiggling) for distances in metres."""
        d = np.asarray(distance_m, dtype=np.float64)
        out = np.full(d.shape, self.bias_m)
        for amp, period, phase in self.wiggle:
            out += amp * np.sin(2 * np.pi * d / period + phase)
        return out

    def amplitude_term_m(self, amplitude: np.ndarray) -> np.ndarray:
        a = np.maximum(np.asarray(amplitude, dtype=np.float64), 1.0)
        return self.amplitude_m * np.clip(np.log10(self.amplitude_ref / a), -1.0, 2.0)

    def error_m(self, distance_m: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
        """Systematic error (height, width) for a full image of distances and amplitudes."""
        return self.wiggle_m(distance_m) + self.pixel_offset_m + self.amplitude_term_m(amplitude)
