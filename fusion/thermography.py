"""Object temperatures from apparent ones: emissivity, reflected temperature and the air
between, per pixel (issue 35, items 1 and 2).

A thermal imager calibrated against a black body reports the *apparent* temperature: the
one a black body (emissivity 1) right in front of it would need to give the radiance it
received. What it received from a surface ``d`` metres away through air of transmission
``tau(d)`` is, in the 7-14 um band (the measurement equation thermal cameras use)::

    W(T_app) = tau eps W(T_obj) + tau (1 - eps) W(T_refl) + (1 - tau) W(T_air)

with ``W(T)`` the band radiance of a black body at ``T`` (Planck's law integrated over the
band), ``eps`` the surface's emissivity, ``T_refl`` the reflected apparent temperature (what
the surface mirrors: a cold sky, a hot furnace wall) and ``T_air`` the air's temperature.
Solved for ``W(T_obj)`` and inverted (:func:`object_temperature`). A shortcut on kelvin
(``T_obj = (T_app - (1 - eps) T_refl) / eps``) is wrong by kelvins: the radiance is far from
linear in temperature (:class:`BandRadiance`).

The air's transmission follows the two-term model thermal camera makers publish for short
paths (:func:`transmission`): water vapour from the air's temperature and relative
humidity, absorption growing with the square root of the distance. A camera applies one
distance to the whole image; trifuse has the TOF's distance at each pixel
(:func:`object_temperature` takes an array), and a default where the TOF has none.

Pure: arrays in, arrays out; kelvin, metres, percent for humidity.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "MATERIALS",
    "BandRadiance",
    "ObjectParameters",
    "apparent_temperature",
    "band_tables",
    "object_temperature",
    "transmission",
    "water_vapour",
]

PLANCK_H = 6.62607015e-34
"""Planck's constant, J s."""
LIGHT_C = 299_792_458.0
"""The speed of light, m/s."""
BOLTZMANN_K = 1.380649e-23
"""Boltzmann's constant, J/K."""
BAND_M = (7e-6, 14e-6)
"""The imagers' band, metres (long-wave infrared)."""

# the atmosphere's two-term model (the constants thermal camera makers publish with it)
_ATM_X = 1.9
_ATM_ALPHA = (0.006569, 0.01262)
_ATM_BETA = (-0.002276, -0.00667)


class BandRadiance:
    """Black-body radiance in the band, ``W(T)`` (W m^-2 sr^-1), and its inverse, on tables.

    ``W`` is Planck's spectral radiance integrated over :data:`BAND_M` by Gauss-Legendre
    quadrature (64 nodes: exact to 1e-12 relative for these smooth integrands). Two tables
    of ``size`` entries, both read by index arithmetic and linear interpolation (no search:
    about 1 ms for 110,000 pixels): ``W`` on a uniform grid of temperature from ``low_k`` to
    ``high_k``, and the temperature on a uniform grid of ``log W`` (the radiance spans four
    decades). Within 1e-4 K of the exact values both ways. Outside: NaN.
    """

    def __init__(self, low_k: float = 150.0, high_k: float = 1200.0, size: int = 16_384):
        self.low_k, self.high_k = low_k, high_k
        self._t_step = (high_k - low_k) / (size - 1)
        self._w = self.exact(np.linspace(low_k, high_k, size))
        self._log_lo, self._log_hi = math.log(self._w[0]), math.log(self._w[-1])
        self._log_step = (self._log_hi - self._log_lo) / (size - 1)
        log_w = np.linspace(self._log_lo, self._log_hi, size)
        # the temperature of each log W: the exact inverse by Newton on the quadrature
        t = np.interp(log_w, np.log(self._w), np.linspace(low_k, high_k, size))
        for _ in range(2):
            h = 1e-3
            f = np.log(self.exact(t)) - log_w
            df = (np.log(self.exact(t + h)) - np.log(self.exact(t - h))) / (2 * h)
            t = t - f / df
        self._t = t

    @staticmethod
    def exact(temperature_k: npt.ArrayLike) -> np.ndarray:
        """``W(T)`` by quadrature for any temperatures (kelvin, > 0), W m^-2 sr^-1."""
        t = np.asarray(temperature_k, dtype=np.float64)
        nodes, weights = np.polynomial.legendre.leggauss(64)
        lo, hi = BAND_M
        lam = 0.5 * (hi - lo) * nodes + 0.5 * (hi + lo)
        w = 0.5 * (hi - lo) * weights
        c1 = 2.0 * PLANCK_H * LIGHT_C**2 / lam**5
        c2 = PLANCK_H * LIGHT_C / (lam * BOLTZMANN_K)
        x = c2 / t[..., None]
        return np.sum(w * c1 / np.expm1(x), axis=-1)

    @staticmethod
    def _lookup(table: np.ndarray, position: np.ndarray) -> np.ndarray:
        """Linear interpolation of ``table`` at fractional indices (NaN outside)."""
        inside = (position >= 0) & (position <= len(table) - 1)
        p = np.where(inside, position, 0.0)
        i = np.minimum(p.astype(np.intp), len(table) - 2)
        f = p - i
        out = table[i] * (1.0 - f) + table[i + 1] * f
        return np.where(inside, out, np.nan)

    def radiance(self, temperature_k: npt.ArrayLike) -> np.ndarray:
        """``W(T)`` from the table (NaN outside it)."""
        t = np.asarray(temperature_k, dtype=np.float64)
        return self._lookup(self._w, (t - self.low_k) / self._t_step)

    def temperature(self, radiance: npt.ArrayLike) -> np.ndarray:
        """The temperature whose ``W`` is ``radiance`` (NaN outside the table or <= 0)."""
        w = np.asarray(radiance, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_w = np.log(w)
        return self._lookup(self._t, (log_w - self._log_lo) / self._log_step)


@functools.cache
def band_tables() -> BandRadiance:
    """The 7-14 um tables, 150-1200 K (-123 to 927 degrees C), made at the first use
    (about 0.4 s of CPU)."""
    return BandRadiance()


MATERIALS: dict[str, float] = {
    "matte paint": 0.95,
    "human skin": 0.98,
    "water": 0.96,
    "glass": 0.92,
    "concrete": 0.92,
    "oxidised steel": 0.8,
    "bare aluminium": 0.1,
}
"""Emissivities of common surfaces in the long-wave band (a short table for the operator:
a surface's own value, measured or from its maker, is better)."""


EMISSIVITY_RANGE = (0.01, 1.0)
"""Emissivities accepted (a surface below 0.01 reflects all but nothing of itself)."""
REFLECTED_RANGE_K = (150.0, 1200.0)
"""Reflected apparent temperatures accepted, kelvin (the band tables' range)."""


@dataclass(frozen=True)
class ObjectParameters:
    """What the measurement equation needs besides the apparent temperature.

    Attributes:
        emissivity: the surface's, 0.01-1.
        reflected_k: the reflected apparent temperature, kelvin (150-1200).
        air_k: the air's temperature, kelvin (200-350).
        humidity_pct: the air's relative humidity, percent (0-100).
        default_distance_m: the distance used where the TOF has none, metres (0-10 000).
    """

    emissivity: float = 1.0
    reflected_k: float = 293.15
    air_k: float = 293.15
    humidity_pct: float = 50.0
    default_distance_m: float = 3.0

    def __post_init__(self) -> None:
        for name, low, high in (
            ("emissivity", *EMISSIVITY_RANGE),
            ("reflected_k", *REFLECTED_RANGE_K),
            ("air_k", 200.0, 350.0),
            ("humidity_pct", 0.0, 100.0),
            ("default_distance_m", 0.0, 10_000.0),
        ):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)):
                raise ValueError(f"{name}: expected a finite number, got {value!r}")
            if not low <= value <= high:
                raise ValueError(f"{name}: expected {low:g} to {high:g}, got {value:g}")


def water_vapour(air_k: float, humidity_pct: float) -> float:
    """The air's water vapour content in the atmosphere model's units (grams per cubic
    metre, approximately: its saturation value at the air's temperature times the relative
    humidity)."""
    t = air_k - 273.15
    saturated = math.exp(1.5587 + 0.06939 * t - 0.00027816 * t**2 + 0.00000068455 * t**3)
    return humidity_pct / 100.0 * saturated


def transmission(distance_m: npt.ArrayLike, air_k: float, humidity_pct: float) -> np.ndarray:
    """The air's transmission over ``distance_m`` (metres, any shape; >= 0) in the band:
    ``X exp(-sqrt(d) (a1 + b1 sqrt(h))) + (1 - X) exp(-sqrt(d) (a2 + b2 sqrt(h)))``, ``h``
    the water vapour (:func:`water_vapour`). 1 at 0 m; about 0.98 at 10 m and 0.94 at 100 m in
    air at 20 degrees C and 50 %. Clipped to (0, 1]."""
    d = np.sqrt(np.maximum(np.asarray(distance_m, dtype=np.float64), 0.0))
    h = math.sqrt(water_vapour(air_k, humidity_pct))
    (a1, a2), (b1, b2) = _ATM_ALPHA, _ATM_BETA
    tau = _ATM_X * np.exp(-d * (a1 + b1 * h)) + (1.0 - _ATM_X) * np.exp(-d * (a2 + b2 * h))
    return np.clip(tau, 1e-6, 1.0)


def _distances(distance_m: npt.ArrayLike | None, params: ObjectParameters) -> np.ndarray:
    """The distances with the default where there is none (None, NaN or <= 0)."""
    if distance_m is None:
        return np.asarray(params.default_distance_m, dtype=np.float64)
    d = np.asarray(distance_m, dtype=np.float64)
    return np.where(np.isfinite(d) & (d > 0), d, params.default_distance_m)


def object_temperature(
    apparent_k: npt.ArrayLike,
    distance_m: npt.ArrayLike | None,
    params: ObjectParameters,
    emissivity: npt.ArrayLike | None = None,
    reflected_k: npt.ArrayLike | None = None,
    band: BandRadiance | None = None,
) -> np.ndarray:
    """The surfaces' temperatures (kelvin, the shape of ``apparent_k``) from the imager's
    apparent ones, by the measurement equation (module docstring).

    Args:
        apparent_k: apparent temperatures, kelvin, any shape; NaN where none.
        distance_m: each pixel's distance, metres, broadcastable to ``apparent_k`` (the
            TOF's); None, NaN or <= 0 take ``params.default_distance_m``.
        params: emissivity, reflected and air temperature, humidity.
        emissivity, reflected_k: per pixel (broadcastable to ``apparent_k``; regions of
            other surfaces, :func:`fusion.regions.surface_maps`) instead of ``params``'.
        band: the band's radiance tables (default :func:`band_tables`).

    Returns:
        kelvin; NaN where the apparent temperature is NaN or the received radiance is less
        than the reflection and the air alone would give (no surface temperature explains it:
        wrong parameters), or the result is outside the table.
    """
    b = band or band_tables()
    tau = transmission(_distances(distance_m, params), params.air_k, params.humidity_pct)
    eps = params.emissivity if emissivity is None else np.asarray(emissivity, np.float64)
    w_app = b.radiance(apparent_k)
    w_refl = b.radiance(params.reflected_k if reflected_k is None else reflected_k)
    w_air = float(b.radiance(params.air_k))
    w_obj = (w_app - tau * (1.0 - eps) * w_refl - (1.0 - tau) * w_air) / (tau * eps)
    return b.temperature(np.where(w_obj > 0, w_obj, np.nan))


def apparent_temperature(
    object_k: npt.ArrayLike,
    distance_m: npt.ArrayLike | None,
    params: ObjectParameters,
    band: BandRadiance | None = None,
    emissivity: npt.ArrayLike | None = None,
) -> np.ndarray:
    """The forward model: what an imager reads (kelvin) looking at surfaces of
    ``object_k`` through the air (the inverse of :func:`object_temperature`); ``emissivity``
    per surface (broadcastable to ``object_k``) instead of ``params``'."""
    b = band or band_tables()
    tau = transmission(_distances(distance_m, params), params.air_k, params.humidity_pct)
    eps = params.emissivity if emissivity is None else np.asarray(emissivity, np.float64)
    w = (
        tau * eps * b.radiance(object_k)
        + tau * (1.0 - eps) * float(b.radiance(params.reflected_k))
        + (1.0 - tau) * float(b.radiance(params.air_k))
    )
    return b.temperature(w)
