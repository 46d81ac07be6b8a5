"""Fusion geometry: TOF rays and points, projection into the other sensors, the whole chain."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.camera import Intrinsics, pixel_grid
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.transforms import make_T, transform_points
from trifuse.fusion.geometry import (
    in_image,
    monotonic_radius,
    project_to_sensor,
    tof_points,
    tof_rays,
    tof_sensor_name,
    tof_to_sensor_pixels,
)

RIG = default_rig()
TOF = RIG["tof"]
W, H = TOF.width, TOF.height  # 176 x 144
RAYS = tof_rays(TOF.intrinsics, W, H)
OTHERS = ["ccd_left", "ccd_right", "thermal_left", "thermal_right"]

# Undistortion stops at a residual of 1e-13 in normalised coordinates, i.e. about 2e-11 px
# at the TOF's 166 px focal length; 1e-9 px leaves a factor of 50.
PX_TOL = 1e-9


def cv2_project(points: np.ndarray, T: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Independent projection: OpenCV with the rotation as a Rodrigues vector, (N, 2)."""
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, T[:3, 3], intr.K, intr.dist)
    return uv.reshape(-1, 2)


def tilted_plane() -> tuple[np.ndarray, float]:
    """Unit normal n and offset c of the plane n . P = c through (0, 0, 2 m), tilted
    20 degrees about x and 10 degrees about y (TOF frame)."""
    a, b = np.radians(20.0), np.radians(10.0)
    n = np.array([np.sin(b), -np.sin(a) * np.cos(b), np.cos(a) * np.cos(b)])
    return n, float(n @ [0.0, 0.0, 2.0])


def plane_distances(rays: np.ndarray) -> np.ndarray:
    """Exact radial distance along each ray to the tilted plane: d = c / (n . r)."""
    n, c = tilted_plane()
    return c / (rays @ n)


# -- rays ------------------------------------------------------------------------------------------


def test_rays_are_unit_and_forward() -> None:
    assert RAYS.shape == (H, W, 3)
    assert RAYS.dtype == np.float64
    assert np.all(np.isfinite(RAYS))
    np.testing.assert_allclose(np.linalg.norm(RAYS, axis=-1), 1.0, rtol=0, atol=1e-15)
    assert np.all(RAYS[..., 2] > 0)


def test_rays_pass_through_the_pixel_centres() -> None:
    uv = cv2_project(RAYS.reshape(-1, 3), np.eye(4), TOF.intrinsics)
    np.testing.assert_allclose(uv.reshape(H, W, 2), pixel_grid(W, H), rtol=0, atol=PX_TOL)


def test_ray_at_the_principal_point_is_the_axis() -> None:
    rays = tof_rays(Intrinsics(100.0, 100.0, 2.0, 1.0, (-0.1, 0.02, 0.001, 0.0)), 5, 3)
    np.testing.assert_allclose(rays[1, 2], [0.0, 0.0, 1.0], rtol=0, atol=1e-15)
    # Without distortion the ray through (u, v) is ((u - cx) / f, (v - cy) / f, 1) normalised.
    rays = tof_rays(Intrinsics(100.0, 50.0, 2.0, 1.0), 5, 3)
    expected = np.array([2.0 / 100.0, 1.0 / 50.0, 1.0])
    np.testing.assert_allclose(rays[2, 4], expected / np.linalg.norm(expected), atol=1e-15)


def test_rays_beyond_the_distortion_fold_are_nan() -> None:
    # k1 = -0.5 folds at r = sqrt(2/3): distorted radii beyond 0.544 have no preimage.
    rays = tof_rays(Intrinsics(100.0, 100.0, 50.0, 50.0, (-0.5, 0.0, 0.0, 0.0)), 200, 101)
    assert np.all(np.isfinite(rays[50, 50:100]))  # distorted radius <= 0.49
    assert np.all(np.isnan(rays[50, 110:]))  # distorted radius >= 0.6
    assert np.all(np.isnan(rays[0, 199]))


@pytest.mark.parametrize(("width", "height"), [(0, 10), (10, -1), (10.0, 10), (True, 10)])
def test_rays_reject_bad_sizes(width: object, height: object) -> None:
    with pytest.raises(ValueError, match="expected a positive integer"):
        tof_rays(TOF.intrinsics, width, height)  # type: ignore[arg-type]


# -- points ----------------------------------------------------------------------------------------


def test_points_of_a_tilted_plane_lie_on_the_plane() -> None:
    n, c = tilted_plane()
    d = plane_distances(RAYS)
    assert 1.5 < d.min() < d.max() < 3.5  # all inside the TOF's range
    P = tof_points(d, RAYS)
    assert P.shape == (H, W, 3)
    # |P| < 3.5 m: rounding is a few ulp of 3.5, far below 1e-9 m.
    np.testing.assert_allclose(P @ n - c, 0.0, rtol=0, atol=1e-9)
    # The distance is radial: |P| = d, so off-axis points have z < d.
    np.testing.assert_allclose(np.linalg.norm(P, axis=-1), d, rtol=1e-15, atol=0)
    assert np.all(P[0, 0, 2] < d[0, 0] - 0.1)


def test_points_from_float32_distances() -> None:
    d32 = plane_distances(RAYS).astype(np.float32)
    P = tof_points(d32, RAYS)
    assert P.dtype == np.float64
    np.testing.assert_array_equal(P, d32.astype(np.float64)[..., None] * RAYS)


def test_invalid_distances_give_nan_points_never_the_origin() -> None:
    d = plane_distances(RAYS)
    bad = {
        (0, 0): 0.0,
        (1, 1): np.nan,
        (2, 2): 12.0,
        (3, 3): -1.0,
        (4, 4): np.inf,
        (5, 5): -np.inf,
        (6, 6): 0.05,
        (7, 7): 10.0 + 1e-9,
    }
    for (v, u), value in bad.items():
        d[v, u] = value
    d[8, 8], d[9, 9] = 0.1, 10.0  # the range is inclusive
    P = tof_points(d, RAYS)
    nan_rows = np.isnan(P).any(axis=-1)
    assert nan_rows.sum() == len(bad)
    assert all(np.isnan(P[v, u]).all() for v, u in bad)
    assert not np.any(np.all(P == 0.0, axis=-1))
    np.testing.assert_allclose(np.linalg.norm(P[8, 8]), 0.1, rtol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(P[9, 9]), 10.0, rtol=1e-15)


def test_custom_range_and_nan_rays() -> None:
    rays = RAYS[:2, :3].copy()
    rays[1, 2] = np.nan
    d = np.array([[0.3, 0.6, 2.0], [2.5, 1.0, 1.0]])
    P = tof_points(d, rays, min_range_m=0.5, max_range_m=2.0)
    valid = ~np.isnan(P).any(axis=-1)
    np.testing.assert_array_equal(valid, [[False, True, True], [False, True, False]])


@pytest.mark.parametrize(
    ("d_shape", "rays_shape", "match"),
    [
        (
            (10, 10),
            (H, W, 3),
            r"distance_m: expected shape \(144, 176\) to match rays "
            r"\(144, 176, 3\), got \(10, 10\)",
        ),
        ((W, H), (H, W, 3), r"expected shape \(144, 176\) .* got \(176, 144\)"),
        ((H, W, 1), (H, W, 3), r"expected shape \(144, 176\) .* got \(144, 176, 1\)"),
        ((H, W), (H, W, 2), r"rays: expected shape \(\.\.\., 3\), got \(144, 176, 2\)"),
        ((H, W), (H, W), r"rays: expected shape \(\.\.\., 3\), got \(144, 176\)"),
    ],
)
def test_points_reject_mismatched_shapes(d_shape: tuple, rays_shape: tuple, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        tof_points(np.ones(d_shape), np.ones(rays_shape))


@pytest.mark.parametrize(("lo", "hi"), [(2.0, 1.0), (-0.1, 1.0), (0.1, np.inf), (np.nan, 1.0)])
def test_points_reject_a_bad_range(lo: float, hi: float) -> None:
    with pytest.raises(ValueError, match="expected finite 0 <= min_range_m < max_range_m"):
        tof_points(np.ones((H, W)), RAYS, min_range_m=lo, max_range_m=hi)


# -- projection into the other sensors -------------------------------------------------------------


def plane_points_with_holes() -> np.ndarray:
    d = plane_distances(RAYS)
    d[::7, ::5] = np.nan
    d[3, :] = 0.0
    return tof_points(d, RAYS)


@pytest.mark.parametrize("sensor", OTHERS)
def test_projection_agrees_with_opencv(sensor: str) -> None:
    P = plane_points_with_holes()
    uv = project_to_sensor(P, RIG, sensor)
    assert uv.shape == (H, W, 2)
    holes = np.isnan(P).any(axis=-1)
    np.testing.assert_array_equal(np.isnan(uv).any(axis=-1), holes)
    expected = cv2_project(P[~holes], RIG.T(sensor, "tof"), RIG[sensor].intrinsics)
    # |u| < 2000 px: the two evaluation orders differ by a few ulp of that (< 1e-12 px).
    np.testing.assert_allclose(uv[~holes], expected, rtol=0, atol=PX_TOL)
    # Sanity: the TOF's plane fills most of each image's overlap with it.
    inside = in_image(uv, RIG[sensor].width, RIG[sensor].height)
    assert inside.sum() > 0.5 * (~holes).sum()


@pytest.mark.parametrize("sensor", OTHERS)
def test_projection_equals_transform_then_intrinsics(sensor: str) -> None:
    P = plane_points_with_holes()
    P_sensor = transform_points(RIG.T(sensor, "tof"), P)
    expected = RIG[sensor].intrinsics.project(P_sensor)
    np.testing.assert_array_equal(project_to_sensor(P, RIG, sensor), expected)


def test_projection_into_the_tof_itself_gives_back_the_pixel_grid() -> None:
    P = tof_points(plane_distances(RAYS), RAYS)
    np.testing.assert_allclose(project_to_sensor(P, RIG, "tof"), pixel_grid(W, H), atol=PX_TOL)


@pytest.mark.parametrize("sensor", OTHERS)
def test_points_behind_the_sensor_are_nan(sensor: str) -> None:
    T_tof_sensor = RIG.T("tof", sensor)
    in_sensor = np.array([[0.1, 0.0, -0.5], [0.1, -0.2, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -2.0]])
    uv = project_to_sensor(transform_points(T_tof_sensor, in_sensor), RIG, sensor)
    assert np.isnan(uv[[0, 1, 3]]).all()
    assert np.isfinite(uv[2]).all()
    assert np.isnan(project_to_sensor([0.0, 0.0, -1.0], RIG, sensor)).all()


def test_nan_in_nan_out_any_shape() -> None:
    uv = project_to_sensor(np.full((2, 3, 4, 3), np.nan), RIG, "ccd_left")
    assert uv.shape == (2, 3, 4, 2)
    assert np.isnan(uv).all()
    with pytest.raises(ValueError, match=r"points_tof: expected shape \(\.\.\., 3\), got \(5, 2\)"):
        project_to_sensor(np.zeros((5, 2)), RIG, "ccd_left")


# -- a toy rig, by hand ----------------------------------------------------------------------------


def toy_rig(baseline_m: float, cam: Intrinsics, tof: Intrinsics | None = None) -> Rig:
    """TOF at the origin and a camera ``baseline_m`` to its right (+x), no rotation."""
    tof_intr = tof or Intrinsics(100.0, 100.0, 50.0, 50.0)
    sensors = {
        "tof": Sensor("tof", "tof", (101, 101), tof_intr, np.eye(4)),
        "cam": Sensor("cam", "color", (640, 480), cam, make_T(np.eye(3), [baseline_m, 0.0, 0.0])),
    }
    return Rig(sensors=sensors, reference="tof")


@pytest.mark.parametrize("d", [0.5, 2.0, 7.5])
def test_point_on_the_tof_axis_in_a_sideways_camera(d: float) -> None:
    # The camera sits b to the right of the TOF: T_cam_tof = [I | (-b, 0, 0)], so the
    # on-axis point (0, 0, d) is at (-b, 0, d) in the camera: u = cx - fx b / d, v = cy.
    b, cam = 0.12, Intrinsics(200.0, 210.0, 320.0, 240.0)
    rig = toy_rig(b, cam)
    uv = tof_to_sensor_pixels(np.full((101, 101), d), rig, "cam")
    np.testing.assert_allclose(uv[50, 50], [320.0 - 200.0 * b / d, 240.0], rtol=0, atol=PX_TOL)


def test_whole_toy_image_by_hand() -> None:
    # TOF pixel (u, v): x = (u - 50) / 100, y = (v - 50) / 100, n = sqrt(x^2 + y^2 + 1),
    # P_tof = d (x, y, 1) / n, P_cam = (d x / n - b, d y / n, d / n), hence
    # u' = cx + fx (x - b n / d) and v' = cy + fy y: parallax b n / d, vertical unchanged.
    b, d, cam = 0.12, 1.6, Intrinsics(200.0, 210.0, 320.0, 240.0)
    distance = np.full((101, 101), d)
    uv = tof_to_sensor_pixels(distance, toy_rig(b, cam), "cam")
    grid = pixel_grid(101, 101)
    x = (grid[..., 0] - 50.0) / 100.0
    y = (grid[..., 1] - 50.0) / 100.0
    n = np.sqrt(x * x + y * y + 1.0)
    expected = np.stack([320.0 + 200.0 * (x - b * n / d), 240.0 + 210.0 * y], axis=-1)
    np.testing.assert_allclose(uv, expected, rtol=0, atol=PX_TOL)


def test_points_beyond_the_fold_of_the_sensor_distortion_are_nan() -> None:
    # k1 = -0.5 folds at r = sqrt(2/3) = 0.816: a point at r = 1.2 would be drawn at the
    # distorted radius 1.2 (1 - 0.72) = 0.336, well inside the image, by the bare model.
    cam = Intrinsics(200.0, 200.0, 320.0, 240.0, (-0.5, 0.0, 0.0, 0.0))
    rig = toy_rig(0.0, cam)
    # At r = 1.66 the radial factor is negative: the point is drawn mirrored through the
    # centre, and calib's unproject even returns it as the ray of that pixel.
    P = np.array([[1.2, 0.0, 1.0], [0.5, 0.0, 1.0], [-1.66, 0.0, 1.0], [0.0, 0.82, 1.0]])
    bare = cam.distort(P[:, :2] / P[:, 2:]) * 200.0 + (320.0, 240.0)  # the polynomial alone
    assert in_image(bare[0], 640, 480)
    assert in_image(bare[2], 640, 480)
    uv = project_to_sensor(P, rig, "cam")
    assert np.isnan(uv[[0, 2, 3]]).all()
    np.testing.assert_array_equal(uv[1], cam.project(P[1]))


@pytest.mark.parametrize(
    ("dist", "r_fold"),
    [
        ((-0.5, 0.0, 0.0, 0.0), np.sqrt(2.0 / 3.0)),  # d/dr r (1 + k1 r^2) = 0
        ((-0.5, 0.1, 0.0, 0.0), 1.0),  # 1 - 1.5 r^2 + 0.5 r^4 = 0 at r^2 = 1 (and 2)
        ((-1e-4, 0.0, 0.0, 0.0, 0.0), 1.0 / np.sqrt(3e-4)),  # far out: the geometric grid
        # rational, r_d = r / (1 + k4 r^2):
        ((0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0), 1.0 / np.sqrt(0.5)),
    ],
)
def test_monotonic_radius_finds_the_first_fold(dist: tuple, r_fold: float) -> None:
    r = monotonic_radius(Intrinsics(100.0, 100.0, 50.0, 50.0, dist))
    # Conservative by at most two grid steps (1e-3 below r = 2, 0.43 % of r beyond).
    assert r_fold - 2 * max(1e-3, 0.0043 * r_fold) <= r <= r_fold


def test_monotonic_radius_of_the_default_head_is_unbounded() -> None:
    for name in RIG.names:
        assert monotonic_radius(RIG[name].intrinsics) == np.inf
    assert monotonic_radius(Intrinsics(100.0, 100.0, 50.0, 50.0)) == np.inf


# -- the whole chain and its arguments -------------------------------------------------------------


def test_chain_equals_its_steps() -> None:
    d = plane_distances(RAYS).astype(np.float32)
    d[10:20, 30:40] = np.nan
    steps = project_to_sensor(tof_points(d, RAYS), RIG, "thermal_left")
    np.testing.assert_array_equal(tof_to_sensor_pixels(d, RIG, "thermal_left"), steps)
    np.testing.assert_array_equal(tof_to_sensor_pixels(d, RIG, "thermal_left", "tof", RAYS), steps)
    assert np.isnan(steps[10:20, 30:40]).all()


def test_chain_rejects_a_distance_image_of_the_wrong_size() -> None:
    with pytest.raises(ValueError, match=r"expected shape \(144, 176\) .* got \(288, 382\)"):
        tof_to_sensor_pixels(np.ones((288, 382)), RIG, "thermal_left")


def test_tof_sensor_name() -> None:
    assert tof_sensor_name(RIG) == "tof"
    assert tof_sensor_name(RIG, "tof") == "tof"
    with pytest.raises(KeyError, match="no sensor 'depth' in the rig"):
        tof_sensor_name(RIG, "depth")
    with pytest.raises(KeyError, match="no sensor 'ccd_middle' in the rig"):
        project_to_sensor(np.zeros(3), RIG, "ccd_middle")


def test_tof_must_be_named_unless_there_is_exactly_one() -> None:
    cam = Intrinsics(200.0, 200.0, 320.0, 240.0)
    no_tof = Rig(
        sensors={"cam": Sensor("cam", "color", (640, 480), cam, np.eye(4))}, reference="cam"
    )
    with pytest.raises(ValueError, match=r"exactly one sensor of modality 'tof'.*got \[\]"):
        project_to_sensor(np.zeros(3), no_tof, "cam")
    rig = toy_rig(0.1, cam)
    rig.sensors["tof2"] = Sensor("tof2", "tof", (101, 101), cam, make_T(np.eye(3), [0.2, 0, 0]))
    with pytest.raises(ValueError, match=r"got \['tof', 'tof2'\]; name the TOF sensor"):
        tof_to_sensor_pixels(np.ones((101, 101)), rig, "cam")
    # Named explicitly, either works: tof2 sits 10 cm right of the camera.
    uv = project_to_sensor([0.0, 0.0, 2.0], rig, "cam", tof="tof2")
    np.testing.assert_allclose(uv, [320.0 + 200.0 * 0.1 / 2.0, 240.0], rtol=0, atol=PX_TOL)


# -- in_image --------------------------------------------------------------------------------------


def test_in_image_boundaries() -> None:
    eps = 1e-9
    pixels = np.array(
        [
            [-0.5, -0.5],
            [9.5 - eps, 4.5 - eps],
            [0.0, 0.0],
            [9.0, 4.0],
            [-0.5 - eps, 0.0],
            [0.0, -0.5 - eps],
            [9.5, 0.0],
            [0.0, 4.5],
            [np.nan, 1.0],
            [1.0, np.inf],
        ]
    )
    inside = in_image(pixels, 10, 5)
    np.testing.assert_array_equal(inside, [True] * 4 + [False] * 6)
    assert in_image(pixels.reshape(2, 5, 2), 10, 5).shape == (2, 5)
    with pytest.raises(ValueError, match=r"pixels: expected shape \(\.\.\., 2\), got \(3,\)"):
        in_image(np.zeros(3), 10, 5)
    with pytest.raises(ValueError, match="width: expected a positive integer, got 0"):
        in_image(pixels, 0, 5)


@pytest.mark.parametrize("sensor", OTHERS)
def test_the_float32_projector_agrees_with_project_to_sensor(sensor: str) -> None:
    """Projector32 (the thermal map's per-frame projection) against the float64 chain:
    the same points kept (in front, inside the distortion's fold), the same pixels to
    float32 precision."""
    from trifuse.fusion.geometry import Projector32

    rng = np.random.default_rng(21)
    pts = rng.uniform((-6.0, -4.0, -2.0), (6.0, 4.0, 9.0), size=(20_000, 3))
    pts[:50] = np.nan
    want = project_to_sensor(pts, RIG, sensor)
    uv, rows, z = Projector32(RIG[sensor].intrinsics, RIG.T(sensor, "tof"))(pts)
    P = transform_points(RIG.T(sensor, "tof"), pts)
    expected = np.flatnonzero(np.isfinite(want[:, 0]) & (P[:, 2] > 0.05))
    np.testing.assert_array_equal(rows, expected)
    # a few thousandths of a pixel in the image; float32's 7 digits far outside it
    np.testing.assert_allclose(uv, want[rows], rtol=1e-5, atol=5e-3)
    w, h = RIG[sensor].image_size
    inside = in_image(want[rows], w, h)
    assert inside.sum() > 1000
    np.testing.assert_allclose(uv[inside], want[rows][inside], atol=5e-3)
    np.testing.assert_allclose(z, P[rows, 2], rtol=1e-5)
