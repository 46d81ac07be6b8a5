"""Intrinsics: project/unproject round trips, agreement with OpenCV, validation, scaling."""

from __future__ import annotations

import dataclasses
import math
import re
import warnings

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trifuse.calib.camera import (
    MAX_DISTORTION_TERM,
    MAX_RAY_RADIUS,
    PHYSICAL_FOV_DEG,
    Intrinsics,
    corner_radius,
    physical_problem,
    pixel_grid,
)
from trifuse.fusion.geometry import Projector32

# Deterministic property tests: same examples every run.
PROPERTY = settings(derandomize=True, database=None, deadline=None, max_examples=150)

# Distortion ranges "like the default head's" (tof, ccd and thermal sit inside them).
K1 = (-0.25, 0.1)
K2 = (-0.05, 0.15)
P12 = (-1e-3, 1e-3)
K3 = (-0.01, 0.01)
K456 = (-0.01, 0.01)
# Inside this normalised radius every distortion above is monotonic (d r_d / d r > 0.5),
# i.e. the field of view of a real lens with such coefficients (about +-35 degrees).
R_MAX = 0.7
# ... and r_d(R_MAX) > 0.59 for all of them, so distorted radii below this are invertible.
RD_MAX = 0.55


def _floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@st.composite
def intrinsics(draw: st.DrawFn, n_coeffs: int | None = None) -> Intrinsics:
    n = draw(st.sampled_from((4, 5, 8))) if n_coeffs is None else n_coeffs
    fx = draw(_floats(100.0, 2000.0))
    fy = fx * draw(_floats(0.95, 1.05))
    cx = draw(_floats(0.3, 0.7)) * 2.0 * fx * R_MAX
    cy = draw(_floats(0.3, 0.7)) * 2.0 * fy * R_MAX
    dist = [draw(_floats(*K1)), draw(_floats(*K2)), draw(_floats(*P12)), draw(_floats(*P12))]
    if n >= 5:
        dist.append(draw(_floats(*K3)))
    if n == 8:
        dist += [draw(_floats(*K456)) for _ in range(3)]
    return Intrinsics(fx, fy, cx, cy, tuple(dist))


@st.composite
def points_in_fov(draw: st.DrawFn) -> np.ndarray:
    """(N, 3) points in front of the camera whose normalised radius is at most R_MAX."""
    n = draw(st.integers(1, 20))
    rows = []
    for _ in range(n):
        r = draw(_floats(0.0, R_MAX))
        phi = draw(_floats(0.0, 2.0 * math.pi))
        z = draw(_floats(0.05, 50.0))
        rows.append([r * math.cos(phi) * z, r * math.sin(phi) * z, z])
    return np.array(rows)


@st.composite
def pixels_in_fov(draw: st.DrawFn, intr: Intrinsics) -> np.ndarray:
    """(N, 2) pixels whose distorted normalised radius is at most RD_MAX."""
    n = draw(st.integers(1, 20))
    rows = []
    for _ in range(n):
        r = draw(_floats(0.0, RD_MAX))
        phi = draw(_floats(0.0, 2.0 * math.pi))
        rows.append([intr.fx * r * math.cos(phi) + intr.cx, intr.fy * r * math.sin(phi) + intr.cy])
    return np.array(rows)


def cv2_project(intr: Intrinsics, points: np.ndarray) -> np.ndarray:
    """OpenCV's projection of camera-frame points, reshaped from (N, 1, 2) to (N, 2)."""
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), intr.K, intr.dist)
    return uv.reshape(-1, 2)


# -- round trips -----------------------------------------------------------------------


@PROPERTY
@given(intr=intrinsics(), points=points_in_fov())
def test_unproject_of_project_is_the_unit_ray(intr: Intrinsics, points: np.ndarray) -> None:
    rays = intr.unproject(intr.project(points))
    expected = points / np.linalg.norm(points, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, expected, rtol=0, atol=1e-9)


@PROPERTY
@given(data=st.data(), intr=intrinsics())
def test_project_of_unproject_is_the_pixel(data: st.DataObject, intr: Intrinsics) -> None:
    uv = data.draw(pixels_in_fov(intr))
    rays = intr.unproject(uv)
    assert np.all(np.isfinite(rays))
    assert np.all(rays[:, 2] > 0)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(intr.project(rays), uv, rtol=0, atol=1e-6)


@pytest.mark.parametrize("n_coeffs", [4, 5, 8])
@PROPERTY
@given(data=st.data(), points=points_in_fov())
def test_project_agrees_with_opencv(n_coeffs: int, data: st.DataObject, points: np.ndarray) -> None:
    intr = data.draw(intrinsics(n_coeffs))
    assert len(intr.distortion) == n_coeffs
    np.testing.assert_allclose(intr.project(points), cv2_project(intr, points), rtol=0, atol=1e-9)


@pytest.mark.parametrize("n_coeffs", [4, 5, 8])
@PROPERTY
@given(data=st.data(), points=points_in_fov())
def test_round_trip_per_coefficient_count(
    n_coeffs: int, data: st.DataObject, points: np.ndarray
) -> None:
    intr = data.draw(intrinsics(n_coeffs))
    rays = intr.unproject(intr.project(points))
    expected = points / np.linalg.norm(points, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, expected, rtol=0, atol=1e-9)


def test_project_keeps_leading_shape() -> None:
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0, (-0.1, 0.01, 0.0, 0.0, 0.0))
    grid = pixel_grid(4, 3)
    assert grid.shape == (3, 4, 2)
    np.testing.assert_array_equal(grid[2, 3], [3.0, 2.0])
    rays = intr.unproject(grid)
    assert rays.shape == (3, 4, 3)
    np.testing.assert_allclose(intr.project(rays), grid, rtol=0, atol=1e-6)


def test_principal_point_is_the_optical_axis() -> None:
    intr = Intrinsics(800.0, 810.0, 319.5, 239.5, (-0.2, 0.1, 1e-3, -1e-3, 0.01))
    np.testing.assert_array_equal(intr.project([0.0, 0.0, 3.0]), [319.5, 239.5])
    np.testing.assert_allclose(intr.unproject([319.5, 239.5]), [0.0, 0.0, 1.0], atol=1e-15)


# -- points that do not project ----------------------------------------------------------


@pytest.mark.parametrize("z", [0.0, -1e-9, -1.0, -100.0])
def test_points_on_or_behind_the_camera_are_nan(z: float) -> None:
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0, (-0.1, 0.01, 0.0, 0.0, 0.0))
    uv = intr.project([[0.1, -0.2, z], [0.0, 0.0, 1.0]])
    assert np.all(np.isnan(uv[0]))
    assert np.all(np.isfinite(uv[1]))


@pytest.mark.parametrize("z", [1e-17, -1e-17, 1e-9])
@pytest.mark.parametrize("dist", [(0.0,) * 5, (-0.19, 0.09, -0.0005, 0.0003, 0.0)])
def test_points_on_the_image_plane_up_to_rounding_are_nan(z: float, dist: tuple) -> None:
    # A point at z = 0 after a rigid round trip comes back with z of about 1e-17: its
    # normalised radius (1e16) is no ray any lens sees, and the distortion polynomial
    # overflows to pixels like (5.7e86, -1.1e87) (issue 14).
    intr = Intrinsics(399.6, 399.9, 189.4, 145.1, dist)
    assert np.isnan(intr.project([0.1, -0.2, z])).all()


def test_grazing_but_real_rays_still_project() -> None:
    # 89.9 degrees off axis (normalised radius 573, inside MAX_RAY_RADIUS): far outside any
    # image, but a pixel, not NaN, without distortion.
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0)
    r = np.tan(np.radians(89.9))
    assert r < MAX_RAY_RADIUS
    np.testing.assert_allclose(intr.project([r, 0.0, 1.0]), [320.0 + 500.0 * r, 240.0])
    assert np.isnan(intr.project([1.01 * MAX_RAY_RADIUS, 0.0, 1.0])).all()


def test_points_beyond_the_fold_of_the_distortion_are_nan() -> None:
    # k1 = -0.4: r_d = r (1 - 0.4 r^2) folds at r = 0.913; a point at r = 1.5 would land
    # back inside the image at r_d = 0.15.
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0, (-0.4, 0.0, 0.0, 0.0, 0.0))
    uv = intr.project([[0.5, 0.0, 1.0], [1.5, 0.0, 1.0]])
    assert np.isfinite(uv[0]).all()
    assert np.isnan(uv[1]).all()


def test_nan_points_project_to_nan() -> None:
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0)
    uv = intr.project([[np.nan, 0.0, 1.0], [0.0, 0.0, np.nan]])
    assert np.all(np.isnan(uv))


def test_project_rejects_wrong_last_dimension() -> None:
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0)
    with pytest.raises(ValueError, match=r"points: expected shape \(\.\.\., 3\), got \(4, 2\)"):
        intr.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"pixels: expected shape \(\.\.\., 2\), got \(4, 3\)"):
        intr.unproject(np.zeros((4, 3)))


# -- validation ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"fx": -500.0}, "focal length must be positive"),
        ({"fy": -1.0}, "focal length must be positive"),
        ({"fx": 0.0}, "focal length must be positive"),
        ({"fx": float("nan")}, "fx: expected a finite number"),
        ({"cy": float("inf")}, "cy: expected a finite number"),
        ({"cx": "320"}, "cx: expected a number"),
        ({"fx": True}, "fx: expected a number"),
        ({"distortion": (0.1, 0.0, 0.0)}, "distortion: expected 4, 5, 8 coefficients.*got 3"),
        ({"distortion": (0.0,) * 6}, "distortion: expected 4, 5, 8 coefficients.*got 6"),
        ({"distortion": (0.0,) * 9}, "distortion: expected 4, 5, 8 coefficients.*got 9"),
        ({"distortion": ()}, "distortion: expected 4, 5, 8 coefficients.*got 0"),
        ({"distortion": (0.1, float("nan"), 0.0, 0.0)}, "distortion: expected finite numbers"),
    ],
)
def test_intrinsics_validation(kwargs: dict, match: str) -> None:
    args = {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        Intrinsics(**args)


def test_intrinsics_are_hashable_and_comparable() -> None:
    a = Intrinsics(500, 501, 320, 240, [0.1, 0.0, 0.0, 0.0])
    b = Intrinsics(500.0, 501.0, 320.0, 240.0, (0.1, 0.0, 0.0, 0.0))
    assert a == b
    assert hash(a) == hash(b)
    assert isinstance(a.fx, float)
    assert a.distortion == (0.1, 0.0, 0.0, 0.0)
    np.testing.assert_array_equal(a.K, [[500.0, 0.0, 320.0], [0.0, 501.0, 240.0], [0, 0, 1]])


# -- scaling -----------------------------------------------------------------------------


@PROPERTY
@given(intr=intrinsics(), points=points_in_fov(), factor=_floats(0.1, 4.0))
def test_scaled_moves_pixel_centres_consistently(
    intr: Intrinsics, points: np.ndarray, factor: float
) -> None:
    uv = intr.project(points)
    uv_scaled = intr.scaled(factor).project(points)
    # The scaled camera sees the same point at factor * (u + 0.5) - 0.5; both sides are
    # O(factor * 3000 px), so a few ulp of that is well below 1e-9 px.
    np.testing.assert_allclose(uv_scaled, factor * (uv + 0.5) - 0.5, rtol=0, atol=1e-9)


def test_scaled_by_two_and_half() -> None:
    intr = Intrinsics(500.0, 400.0, 319.5, 239.5, (-0.1, 0.01, 0.0, 0.0, 0.0))
    half = intr.scaled(0.5)
    assert (half.fx, half.fy, half.cx, half.cy) == (250.0, 200.0, 159.5, 119.5)
    assert half.distortion == intr.distortion
    assert intr.scaled(2.0).scaled(0.5) == intr
    with pytest.raises(ValueError, match="focal length must be positive"):
        intr.scaled(-1.0)


# -- physical bounds ---------------------------------------------------------------------


def _at_fov(fov_deg: float, side: int) -> float:
    """The focal length (px) that gives ``fov_deg`` across ``side`` pixels."""
    return side / (2.0 * math.tan(math.radians(fov_deg) / 2.0))


TERM_POWERS = (2, 4, 1, 1, 6, 2, 4, 6)  # of the corner radius, k1 k2 p1 p2 k3 k4 k5 k6


def _reach(side: int, f: float) -> float:
    """How far the principal point may lie from the image centre (pixels): 1.5 image sizes
    (one outside the image), or 30 degrees off the axis."""
    return max(1.5 * side, f * math.tan(math.radians(30.0)))


@pytest.mark.parametrize("size", [(8, 8), (640, 480)])
@pytest.mark.parametrize("fov_deg", PHYSICAL_FOV_DEG)
@pytest.mark.parametrize("centre", ["middle", "edge before", "edge beyond"])
@pytest.mark.parametrize(
    "signs",
    [
        (0,) * 5,
        (1, 0, 0, 0, 0),
        (-1, 0, 0, 0, 0),
        (0, 0, 0, 0, -1),
        (0, 0, 1, -1, 1),
        (1,) * 8,
        (1, -1) * 4,
    ],
    ids=["none", "k1+", "k1-", "k3-", "p1p2k3", "all+", "alternating"],
)
def test_a_camera_at_the_edge_of_every_bound_still_sees_without_overflow(
    size: tuple[int, int], fov_deg: float, centre: str, signs: tuple[int, ...]
) -> None:
    """At the edges of the bounds (field of view 0.1 or 179 degrees, the principal point
    an image size outside the image or, for the telephoto, 30 degrees off its centre's
    direction, every chosen distortion term 1e6 at the image's corner: k3 from 1e-11 for
    the widest to 3e23 for the telephoto) pixels unproject to rays that project back to
    them, with no overflow warning, also in the fusion's float32 (which loses up to a tenth
    of a pixel there), and so do points up to 80 degrees off the axis; beyond the
    distortion's fold the rays are NaN, as for any camera. (Beyond the bounds, k1 = 1e300
    overflows, and fx = 1e300 puts every point 1e299 pixels away: no spot reading.)"""
    w, h = size
    fx, fy = _at_fov(fov_deg, w), _at_fov(fov_deg, h)
    side = {"middle": 0.0, "edge before": -1.0, "edge beyond": 1.0}[centre] * (1 - 1e-12)
    cx, cy = ((n - 1) / 2 + side * _reach(n, f) for n, f in ((w, fx), (h, fy)))
    pinhole = Intrinsics(fx, fy, cx, cy)
    r = corner_radius(pinhole, size)
    edge = MAX_DISTORTION_TERM * (1 - 1e-9)  # (a rounding below the bound)
    distortion = tuple(s * edge / r**p for s, p in zip(signs, TERM_POWERS, strict=False))
    intr = dataclasses.replace(pinhole, distortion=distortion)
    assert physical_problem(intr, size) is None
    u, v = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    angle = np.radians(np.linspace(0.0, 80.0, 9))
    off_axis = np.stack([np.sin(angle), np.zeros_like(angle), np.cos(angle)], axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rays = intr.unproject(pixels)
        back = intr.project(rays)
        seen = np.isfinite(back).all(axis=1)  # NaN rays, and rays within the fold's margin
        # (to 1e-5 px: a 0.1-degree lens has fx = 3.7e5 px, and tangential terms of 1e6 at
        # its corner cost Newton a few digits; every other case is within 2e-8 px)
        np.testing.assert_allclose(back[seen], pixels[seen], atol=1e-5)
        if seen.any():  # (cv2.transform of no points is None)
            uv32, rows, _ = Projector32(intr, np.eye(4))(100.0 * rays[seen])
            assert len(rows) == seen.sum() and np.isfinite(uv32).all()
            np.testing.assert_allclose(uv32, back[seen], atol=0.1)
        far = intr.project(off_axis)
        far32, rows32, _ = Projector32(intr, np.eye(4))(10.0 * off_axis)
        assert np.isfinite(far32).all()
        np.testing.assert_array_equal(rows32, np.flatnonzero(np.isfinite(far).all(axis=1)))
    if centre == "middle":
        assert seen[len(pixels) // 2]  # the principal point's own pixel
    if not any(signs):
        assert seen.all()
        # float32 to its resolution at these pixel values (1/64 px where the principal
        # point lies 2e5 px away, as a 0.1-degree lens 30 degrees off may have it)
        resolution = float(np.spacing(np.float32(max(abs(cx), abs(cy), w, h))))
        np.testing.assert_allclose(uv32, pixels, atol=max(1e-3, 4 * resolution))


def test_the_physical_bounds_name_the_parameter_and_the_bound() -> None:
    size = (640, 480)
    good = Intrinsics(_at_fov(60.0, 640), _at_fov(48.0, 480), 319.5, 239.5)
    assert physical_problem(good, size) is None
    for change, parameter, reason in [
        ({"fx": 1e300}, "fx", r"1e\+300 px gives a field of view of 3\.667e-296 degrees across"),
        ({"fy": _at_fov(179.5, 480)}, "fy", r"of 179\.5 degrees across the 480-pixel height"),
        ({"fx": _at_fov(0.09, 640)}, "fx", r"of 0\.09 degrees .* \(fx from 2\.793 to 3\.667e\+05"),
        ({"cx": -641.0}, "cx", r"-641 px; expected -640\.5 to 1279\.5 px \(at most 1 image width "),
        ({"cy": 960.0}, "cy", r"960 px; expected -480\.5 to 959\.5 px .* or 30 degrees off the"),
        # a telephoto's principal point may lie farther: 30 degrees off
        (
            {"fx": 1e5, "cx": 319.5 + 57736.0},
            "cx",
            r"58055\.5 px; expected -57415\.5 to 58054\.5 px",
        ),
        (
            {"distortion": (0.0, 0.0, 0.0, 0.0, -7e6)},
            "k3",
            r"k3 = -7e\+06 makes a term of 1\.05e\+06 at the image's farthest corner \(normalised "
            r"radius 0\.7291\); expected at most 1e\+06 \(\|k3\| at most 6\.658e\+06\)",
        ),
        (
            {"distortion": (0.0, 0.0, 3e6, 0.0, 0.0)},
            "p1",
            r"p1 = 3e\+06 makes a term of 2\.19e\+06",
        ),
        ({"distortion": (0.0,) * 7 + (1e300,)}, "k6", r"k6 = 1e\+300 makes a term of 1\.5e\+299"),
    ]:
        problem = physical_problem(dataclasses.replace(good, **change), size)
        assert problem is not None and problem[0] == parameter, change
        assert re.search(reason, problem[1]), problem
