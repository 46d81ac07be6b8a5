"""Measurement regions (fusion.regions): which pixels a spot, box or polygon covers, what it
reads (extremes, mean, where), regions of their own surface in the measurement equation,
and regions refused with the reason (outside the image, a wrong shape, a value out of
range)."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.fusion.regions import Region, line_profile, read_region, surface_maps
from trifuse.fusion.thermography import ObjectParameters, apparent_temperature, object_temperature


def test_a_box_covers_the_pixels_whose_centres_it_holds_ends_included() -> None:
    m = Region("b", "left", "box", ((4.0, 2.0), (1.0, 5.0))).mask(10, 8)
    ys, xs = np.nonzero(m)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (1, 4, 2, 5) and m.sum() == 16
    half = Region("h", "left", "box", ((1.5, 2.5), (3.5, 3.4))).mask(10, 8)
    assert np.argwhere(half).tolist() == [[3, 2], [3, 3]]


def test_a_polygon_covers_its_inside_and_a_spot_one_pixel() -> None:
    tri = Region("t", "right", "polygon", ((0, 0), (8, 0), (0, 8))).mask(10, 10)
    assert tri[1, 1] and tri[0, 8] and not tri[8, 8]
    spot = Region("s", "left", "spot", ((3.4, 6.6),)).mask(10, 10)
    assert np.argwhere(spot).tolist() == [[7, 3]]


def test_reading_a_region_gives_extremes_mean_and_where() -> None:
    t = np.full((6, 8), 300.0)
    t[2, 3], t[4, 5] = 350.0, 280.0
    t[0, 0] = np.nan  # no temperature there: not counted
    r = read_region(Region("all", "left", "box", ((0, 0), (7, 5))), t)
    assert (r.pixels, r.max_k, r.min_k, r.max_at, r.min_at) == (47, 350.0, 280.0, (3, 2), (5, 4))
    assert r.mean_k == pytest.approx((45 * 300.0 + 350 + 280) / 47)
    empty = read_region(Region("none", "left", "box", ((0, 0), (0, 0))), t)
    assert empty.pixels == 0 and empty.max_k is None and empty.as_dict()["mean_k"] is None


def test_a_region_of_its_own_surface_reads_its_true_temperature() -> None:
    """Two surfaces in one picture at 4 m: matte paint (0.95) at 60 degrees C everywhere but
    a bare aluminium plate (0.1) at 60 degrees C mirroring a 20 degrees C room in a box.
    With the global emissivity only, the plate reads 25 degrees C; with its region's
    emissivity, both read 60 within 0.01 K."""
    h, w = 40, 60
    truth = np.full((h, w), 333.15)
    paint = ObjectParameters(emissivity=0.95, reflected_k=293.15, humidity_pct=60.0)
    plate = Region("plate", "left", "box", ((20, 10), (39, 29)), emissivity=0.1)
    seen = apparent_temperature(truth, 4.0, paint)
    inside = plate.mask(w, h)
    seen[inside] = apparent_temperature(
        truth[inside], 4.0, ObjectParameters(0.1, 293.15, 293.15, 60.0)
    )
    wrong = object_temperature(seen, 4.0, paint)
    assert np.all(truth[inside] - wrong[inside] > 30.0)  # 298.2 K: 35 K low
    eps, refl = surface_maps([plate], "left", w, h, paint.emissivity, paint.reflected_k)
    assert eps[inside].tolist() == [0.1] * inside.sum() and np.all(eps[~inside] == 0.95)
    assert np.all(refl == 293.15)
    right = object_temperature(seen, 4.0, paint, emissivity=eps, reflected_k=refl)
    np.testing.assert_allclose(right, truth, atol=0.01)
    other_eye = surface_maps([plate], "right", w, h, 0.95, 293.15)[0]
    assert np.all(other_eye == 0.95)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"shape": "box", "points": ((1, 1),)}, "a box takes 2 points, got 1"),
        ({"shape": "polygon", "points": ((1, 1), (2, 2))}, "a polygon takes 3 points, got 2"),
        ({"shape": "circle", "points": ((1, 1),)}, "shape: expected spot, box or polygon"),
        (
            {"shape": "spot", "points": ((1, float("nan")),)},
            "expected points \\(x, y\\) of finite numbers",
        ),
        ({"shape": "spot", "points": ((1, 1),), "emissivity": 1.5}, "emissivity: expected 0.01"),
        ({"shape": "spot", "points": ((1, 1),), "eye": "middle"}, "eye: expected left or right"),
    ],
)
def test_a_wrong_region_is_refused_with_the_reason(kwargs: dict, message: str) -> None:
    args = {"name": "r", "eye": "left", **kwargs}
    with pytest.raises(ValueError, match=message):
        Region(**args)


def test_a_region_outside_the_image_is_refused() -> None:
    with pytest.raises(ValueError, match=r"r: outside the 10x8 image"):
        Region("r", "left", "box", ((20, 20), (30, 30))).mask(10, 8)
    with pytest.raises(ValueError, match="outside"):
        Region("r", "left", "spot", ((-1, 3),)).mask(10, 8)


def test_a_line_profile_samples_every_pixel_along_the_segment() -> None:
    """A ramp of 1 K a column: the profile along a row reads it back, one sample a pixel,
    half-pixel positions interpolated; NaN beyond the picture."""
    t = np.tile(300.0 + np.arange(20, dtype=np.float64), (10, 1))
    d, v = line_profile(t, (2.0, 4.0), (12.0, 4.0))
    assert len(d) == 11 and d[0] == 0.0 and d[-1] == pytest.approx(10.0)
    np.testing.assert_allclose(v, 302.0 + np.arange(11), atol=1e-3)
    _, half = line_profile(t, (2.5, 4.0), (3.5, 4.0))
    np.testing.assert_allclose(half, [302.5, 303.5], atol=1e-3)
    _, out = line_profile(t, (18.0, 4.0), (25.0, 4.0))
    assert np.isfinite(out[:2]).all() and np.isnan(out[-1])
