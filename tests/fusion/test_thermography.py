"""Object temperatures from apparent ones (fusion.thermography): the band's radiance against
an independent integration of Planck's law, the tables, the air's transmission, and the
measurement equation on surfaces whose true temperature is known: a low-emissivity surface
mirroring a cold sky, surfaces at 0.5-10 m in humid air read with their own distance and
with one distance for all."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.fusion.thermography import (
    BAND_M,
    BOLTZMANN_K,
    LIGHT_C,
    MATERIALS,
    PLANCK_H,
    ObjectParameters,
    apparent_temperature,
    band_tables,
    object_temperature,
    transmission,
)


def _planck_trapezoid(t_k: float, n: int = 200_001) -> float:
    """W(T) by the trapezoid rule on a fine grid: an independent integration."""
    lam = np.linspace(*BAND_M, n)
    x = PLANCK_H * LIGHT_C / (lam * BOLTZMANN_K * t_k)
    spectral = 2 * PLANCK_H * LIGHT_C**2 / lam**5 / np.expm1(x)
    return float(np.sum((spectral[1:] + spectral[:-1]) * np.diff(lam)) / 2)


@pytest.mark.parametrize("t_k", [200.0, 300.0, 500.0, 1100.0])
def test_band_radiance_is_planck_integrated_over_7_to_14_um(t_k: float) -> None:
    b = band_tables()
    assert b.exact(t_k) == pytest.approx(_planck_trapezoid(t_k), rel=1e-8)
    # at 300 K, 7-14 um holds 43 % of a black body's radiance (sigma T^4 / pi): the
    # tabulated fractions below 4200 and 2100 um K, 0.516 and 0.083
    if t_k == 300.0:
        total = 5.670374419e-8 * t_k**4 / np.pi
        assert 0.42 < b.exact(t_k) / total < 0.445


def test_the_tables_are_the_quadrature_both_ways_and_nan_outside() -> None:
    b = band_tables()
    t = np.linspace(150.5, 1199.5, 20_001)
    w = b.exact(t)
    assert np.max(np.abs(b.radiance(t) / w - 1)) < 1e-5
    assert np.max(np.abs(b.temperature(w) - t)) < 1e-4
    assert np.isnan(b.radiance([149.0, 1201.0, np.nan])).all()
    assert np.isnan(b.temperature([0.0, -1.0, np.nan, b.exact(1300.0)])).all()


def test_transmission_falls_with_distance_and_humidity() -> None:
    d = np.array([0.0, 0.5, 1.0, 3.0, 10.0, 30.0, 100.0, 1000.0])
    tau = transmission(d, 293.15, 50.0)
    assert tau[0] == 1.0 and np.all(np.diff(tau) < 0) and tau[-1] > 0
    assert 0.97 < tau[4] < 0.99 and 0.92 < tau[6] < 0.96  # 10 m and 100 m
    dry, humid = transmission(100.0, 293.15, 0.0), transmission(100.0, 293.15, 100.0)
    assert dry > humid
    assert transmission(100.0, 308.15, 80.0) < transmission(100.0, 283.15, 80.0)  # warmer: wetter


def test_a_half_emissivity_surface_mirroring_a_cold_sky_reads_its_true_temperature() -> None:
    """The issue's case: a 50 degrees C surface of emissivity 0.5 mirroring a -40 degrees C
    sky, 5 m away in air at 20 degrees C and 80 %. The imager reads about 16 degrees C
    (34 K low); the linear shortcut on kelvin reads about 72.5 (22 K high); the measurement
    equation gives the truth (to the tables' 1e-4 K)."""
    p = ObjectParameters(emissivity=0.5, reflected_k=233.15, air_k=293.15, humidity_pct=80.0)
    truth = 323.15
    seen = float(apparent_temperature(truth, 5.0, p))
    assert truth - seen > 30.0  # uncorrected
    shortcut = (seen - (1 - p.emissivity) * p.reflected_k) / p.emissivity
    assert shortcut - truth > 15.0
    assert float(object_temperature(seen, 5.0, p)) == pytest.approx(truth, abs=1e-3)


@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_every_material_of_the_table_comes_back(material: str) -> None:
    eps = MATERIALS[material]
    p = ObjectParameters(emissivity=eps, reflected_k=283.15, air_k=298.15, humidity_pct=60.0)
    truth = np.array([263.15, 310.15, 373.15, 773.15])
    seen = apparent_temperature(truth, 2.0, p)
    np.testing.assert_allclose(object_temperature(seen, 2.0, p), truth, atol=2e-3)


def test_each_pixels_own_distance_against_one_for_the_image() -> None:
    """Surfaces at 500 degrees C (emissivity 0.9) from 0.5 to 10 m in air at 20 degrees C and
    80 %, read with each pixel's distance: the truth everywhere (1e-3 K). Read with one
    distance for the image (3 m, as a camera does): 2.5 K high at 0.5 m and 3.5 K low at
    10 m. Where the TOF has no distance (NaN), the default is used."""
    p = ObjectParameters(emissivity=0.9, reflected_k=293.15, air_k=293.15, humidity_pct=80.0)
    distance = np.array([[0.5, 1.0, 2.0], [3.0, 6.0, 10.0]])
    truth = np.full(distance.shape, 773.15)
    seen = apparent_temperature(truth, distance, p)
    np.testing.assert_allclose(object_temperature(seen, distance, p), truth, atol=1e-3)
    one = object_temperature(seen, None, p)  # the default 3 m for every pixel
    error = one - truth
    assert error[0, 0] > 2.0 and error[1, 2] < -3.0 and abs(error[1, 0]) < 1e-3
    holes = distance.copy()
    holes[0, 0] = np.nan
    np.testing.assert_allclose(object_temperature(seen, holes, p)[0, 0], one[0, 0])


def test_readings_no_surface_explains_are_nan() -> None:
    """NaN in, NaN out; an apparent temperature below what the reflection alone gives (here
    a 0.1-emissivity surface mirroring 400 K read as 290 K): no surface temperature explains
    it (wrong parameters), NaN rather than a number."""
    p = ObjectParameters(emissivity=0.1, reflected_k=400.0)
    out = object_temperature(np.array([np.nan, 290.0]), 1.0, p)
    assert np.isnan(out).all()


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("emissivity", 0.0, "emissivity: expected 0.01 to 1, got 0"),
        ("emissivity", 1.2, "emissivity: expected 0.01 to 1, got 1.2"),
        ("emissivity", float("nan"), "emissivity: expected a finite number, got nan"),
        ("humidity_pct", -1.0, "humidity_pct: expected 0 to 100, got -1"),
        ("humidity_pct", 101.0, "humidity_pct: expected 0 to 100, got 101"),
        ("reflected_k", 20.0, "reflected_k: expected 150 to 1200, got 20"),
        ("default_distance_m", -2.0, "default_distance_m: expected 0 to 10000, got -2"),
    ],
)
def test_parameters_out_of_range_are_refused_with_what_was_expected(
    field: str, value: float, message: str
) -> None:
    with pytest.raises(ValueError, match=message.replace(".", r"\.")):
        ObjectParameters(**{field: value})
