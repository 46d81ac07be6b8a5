"""The simulated head renders exact geometry and the sensor errors it claims to inject."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.app.sources.sim.render import HeadModel, Renderer
from trifuse.app.sources.sim.scenarios import (
    CALIBRATION_BOARD,
    board_solid,
    calibration_poses,
    lab_background,
)
from trifuse.app.sources.sim.scene import Material, Quad, Scene
from trifuse.app.sources.sim.tof_error import RangeErrorModel
from trifuse.calib.tof import region_map
from trifuse.calib.transforms import make_T, rotation_from_euler_deg, transform_points
from trifuse.fusion.geometry import tof_points, tof_rays

RIG = default_rig()
NO_RANGE_ERROR = RangeErrorModel(
    bias_m=0.0, wiggle=(), radial_m=0.0, border_m=0.0, pixel_sigma_m=0.0, amplitude_m=0.0
)


def _wall_scene(
    distance_m: float, yaw_deg: float = 20.0, nir: float = 0.5, temperature_k: float = 300.0
) -> tuple[Scene, np.ndarray]:
    """A large flat wall facing the head; returns the scene and its pose."""
    T = make_T(rotation_from_euler_deg(0.0, yaw_deg, 0.0), (0.0, 0.0, distance_m))
    wall = Quad(
        "wall", Material((0.5, 0.5, 0.5), temperature_k, 1.0, nir), T, (-20.0, 20.0, -20.0, 20.0)
    )
    return Scene([wall], ambient_k=temperature_k), T


def _detect(gray: np.ndarray) -> np.ndarray | None:
    """Classic detector + cornerSubPix with a window from the corner spacing, (N, 2)."""
    ok, corners = cv2.findChessboardCorners(
        gray,
        CALIBRATION_BOARD.pattern_size,
        flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE,
    )
    if not ok:
        return None
    c = corners.reshape(-1, 2).astype(np.float32)
    grid = c.reshape(CALIBRATION_BOARD.rows, CALIBRATION_BOARD.cols, 2)
    spacing = float(np.min(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    half = int(np.clip(0.4 * spacing, 2, 11))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    return cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (half, half), (-1, -1), crit).reshape(-1, 2)


@pytest.mark.slow  # renders and searches calibration views: about 8 s
def test_color_corners_match_ground_truth_projection() -> None:
    """OpenCV finds the board corners within 0.1 px RMS of the exact projection."""
    renderer = Renderer(RIG)
    rng = np.random.default_rng(7)
    board_pts = CALIBRATION_BOARD.object_points()
    errors = []
    # Views 2, 3, 4, 5 of the sequence target the two colour cameras and two other sensors.
    for T_rig_board in calibration_poses(8, seed=3, rig=RIG)[1:7]:
        scene = Scene([*lab_background(), board_solid(T_rig_board)])
        frames, _ = renderer.render(scene, np.eye(4), 0, rng, ["ccd_left", "ccd_right"])
        for name in ("ccd_left", "ccd_right"):
            found = _detect(cv2.cvtColor(frames[name].image, cv2.COLOR_RGB2GRAY))
            if found is None:
                continue
            truth = RIG[name].intrinsics.project(
                transform_points(RIG.T(name, "tof") @ T_rig_board, board_pts)
            )
            # Geometry only: pair each detection with the nearest true corner.
            dist = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=-1)
            nearest = dist.argmin(axis=1)
            assert len(set(nearest.tolist())) == len(truth), "corners matched twice"
            errors.append(dist[np.arange(len(found)), nearest])
    assert len(errors) >= 6, f"board detected in only {len(errors)} colour images"
    rms = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    assert rms < 0.1, f"corner RMS {rms:.3f} px"


def test_tof_points_of_a_plane_lie_on_it_within_the_noise() -> None:
    model = HeadModel(range_error=NO_RANGE_ERROR)
    scene, T_world_wall = _wall_scene(2.0)
    frames, truth = Renderer(RIG, model).render(
        scene, np.eye(4), 0, np.random.default_rng(1), ["tof"]
    )
    tof = frames["tof"]
    intr = RIG["tof"].intrinsics
    points = tof_points(tof.distance_m, tof_rays(intr, 176, 144))
    valid = np.isfinite(points[..., 0])
    assert valid.mean() > 0.95
    n = T_world_wall[:3, 2]
    along = points[valid] @ n - n @ T_world_wall[:3, 3]  # signed distance to the plane
    rays = tof_rays(intr, 176, 144)[valid]
    along_ray = along / (rays @ n)  # convert to distance along the ray
    sigma = model.tof_noise_m * np.sqrt(model.tof_noise_ref / tof.image[valid])
    z = along_ray / sigma
    assert abs(float(np.mean(z))) < 0.05  # no bias: 25k samples, 1/sqrt(N) ~ 0.006
    assert 0.95 < float(np.std(z)) < 1.05
    # The exact range in the ground truth lies on the plane to float32 precision.
    exact = tof_points(truth["tof"].range_m, tof_rays(intr, 176, 144))[valid]
    assert np.max(np.abs(exact @ n - n @ T_world_wall[:3, 3])) < 1e-5


def test_injected_range_error_has_the_stated_size() -> None:
    """About 40 mm RMS in regions 1-3 over 0.6-4 m, worse in the border (region 4)."""
    model = HeadModel()
    regions = region_map(176, 144)
    renderer = Renderer(RIG, model)
    err = {r: [] for r in (1, 2, 3, 4)}
    for distance in np.linspace(0.6, 4.0, 12):
        scene, _ = _wall_scene(float(distance), yaw_deg=0.0)
        frames, truth = renderer.render(scene, np.eye(4), 0, np.random.default_rng(2), ["tof"])
        measured = frames["tof"].distance_m
        # The systematic part follows the model exactly; the rest is the injected noise.
        expected = model.range_error.error_m(truth["tof"].range_m, frames["tof"].image)
        residual = measured - truth["tof"].range_m - expected
        sigma = model.tof_noise_m * np.sqrt(model.tof_noise_ref / frames["tof"].image)
        ok = np.isfinite(residual)
        assert np.std(residual[ok] / sigma[ok]) == pytest.approx(1.0, abs=0.05)
        for r in err:
            sel = ok & (regions == r)
            err[r].append((measured - truth["tof"].range_m)[sel])
    rms = {r: float(np.sqrt(np.mean(np.concatenate(e) ** 2))) for r, e in err.items()}
    inner = float(np.sqrt(np.mean(np.concatenate(err[1] + err[2] + err[3]) ** 2)))
    assert 0.035 < inner < 0.048, rms
    assert rms[1] < rms[3] < rms[4]
    assert rms[4] > 1.5 * inner


def test_tof_invalid_beyond_range_and_at_low_amplitude() -> None:
    renderer = Renderer(RIG)
    far, _ = _wall_scene(12.0, yaw_deg=0.0, nir=1.0)
    frames, _ = renderer.render(far, np.eye(4), 0, np.random.default_rng(3), ["tof"])
    assert np.isnan(frames["tof"].distance_m).all()
    dark, _ = _wall_scene(3.0, yaw_deg=0.0, nir=0.001)
    frames, _ = renderer.render(dark, np.eye(4), 0, np.random.default_rng(3), ["tof"])
    assert np.isnan(frames["tof"].distance_m).all()
    empty = Scene(
        [
            Quad(
                "tiny",
                Material((1, 1, 1), 300.0),
                make_T(np.eye(3), (0, 0, 2)),
                (-0.01, 0.01, -0.01, 0.01),
            )
        ]
    )
    frames, truth = renderer.render(empty, np.eye(4), 0, np.random.default_rng(3), ["tof"])
    miss = truth["tof"].solid == -1
    assert miss.mean() > 0.99 and np.isnan(frames["tof"].distance_m[miss]).all()


def test_thermal_noise_offset_and_units() -> None:
    """A uniform 300 K wall: 0.08 K NETD, and the two imagers 1.5 K apart by default."""
    scene, _ = _wall_scene(3.0, temperature_k=300.0)
    frames, _ = Renderer(RIG).render(
        scene, np.eye(4), 0, np.random.default_rng(4), ["thermal_left", "thermal_right"]
    )
    left, right = frames["thermal_left"].image, frames["thermal_right"].image
    assert left.dtype == np.float32 and left.shape == (288, 382)
    assert np.median(left) == pytest.approx(300.75, abs=0.01)
    assert np.median(right) == pytest.approx(299.25, abs=0.01)
    assert float(np.std(left)) == pytest.approx(0.08, rel=0.03)


def test_calibration_poses_cover_every_sensor_to_its_corners() -> None:
    poses = calibration_poses(30, seed=1, rig=RIG)
    s, m = CALIBRATION_BOARD.square_size_m, 0.04
    cols, rows = CALIBRATION_BOARD.cols, CALIBRATION_BOARD.rows
    plate = np.array(
        [
            [-s - m, -s - m, 0],
            [cols * s + m, -s - m, 0],
            [cols * s + m, rows * s + m, 0],
            [-s - m, rows * s + m, 0],
        ]
    )
    for name in RIG.names:
        w, h = RIG[name].image_size
        reached = set()
        for T_rig_board in poses:
            P = transform_points(RIG.T(name, "tof") @ T_rig_board, plate)
            distance = float(np.linalg.norm(T_rig_board[:3, 3]))
            assert 0.45 < distance < 4.6
            tilt = np.degrees(np.arccos(abs((T_rig_board[:3, 2] @ T_rig_board[:3, 3]) / distance)))
            assert tilt < 60.0
            uv = RIG[name].intrinsics.project(P)
            if not (np.isfinite(uv).all() and (uv >= 0).all() and (uv < (w, h)).all()):
                continue
            for corner_uv in uv:
                cu = 0 if corner_uv[0] < 0.15 * w else (2 if corner_uv[0] > 0.85 * w else 1)
                cv = 0 if corner_uv[1] < 0.15 * h else (2 if corner_uv[1] > 0.85 * h else 1)
                reached.add((cu, cv))
        assert {(0, 0), (2, 0), (0, 2), (2, 2)} <= reached, f"{name}: corners {reached}"


def test_inspection_scene_has_parallax_range_and_a_person() -> None:
    scenario = InspectionScenario(seed=0)
    frames, truth = scenario.render(0.0, ["tof", "thermal_left"])
    r = truth["tof"].range_m
    assert np.nanmin(r) < 0.65 and np.nanmax(r) > 7.0
    names = [s.name for s in scenario.scene.solids]
    head = truth["thermal_left"].solid == names.index("person_head")
    assert head.sum() > 50
    # A 37 C head reads about 310 K (+0.75 K imager offset), away from its blurred rim.
    inner = cv2.erode(head.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.median(frames["thermal_left"].image[inner]) == pytest.approx(310.9, abs=0.5)
    moved = scenario.T_world_rig(7.5)
    assert np.degrees(np.arccos(moved[0, 0])) == pytest.approx(20.0, abs=0.01)


# -- the live (demo) quality ------------------------------------------------------------------

LIVE_T_S = 4.0  # a moment of the inspection scenario: the head turns at 2.8 deg/s
LIVE_SENSORS = ("ccd_left", "thermal_left", "tof")


@pytest.fixture(scope="module")
def live_and_accurate() -> tuple[InspectionScenario, InspectionScenario]:
    return InspectionScenario(seed=0, live=True), InspectionScenario(seed=0)


def _interior(solid: np.ndarray, size: int = 3) -> np.ndarray:
    """Pixels whose size x size neighbourhood shows one solid (away from silhouettes)."""
    ids = (solid.astype(np.int32) + 2).astype(np.float32)
    k = np.ones((size, size), np.uint8)
    return cv2.erode(ids, k) == cv2.dilate(ids, k)


def test_live_render_is_the_accurate_one_away_from_edges(live_and_accurate) -> None:
    """Without edge supersampling, the live quality's pixel values are the accurate render's
    wherever supersampling does not reach (one solid around the pixel), to a tenth of the
    colour read noise (0.004 linear), and its ground truth is the accurate one."""
    live, acc = live_and_accurate
    T = live.T_world_rig(LIVE_T_S)
    for name in LIVE_SENSORS:
        Ts = T @ RIG[name].T_rig_sensor
        v_live, t_live = live.renderer.render_raw(live.scene, name, Ts)
        v_acc, t_acc = acc.renderer.render_raw(acc.scene, name, Ts)
        assert v_live.dtype == np.float32 and v_live.shape == v_acc.shape
        interior = _interior(t_acc.solid)
        assert interior.mean() > 0.85  # most of the picture
        if RIG[name].modality == "color":
            # Rays undistorted on a coarse grid (within 0.003 px): a few pixels on creases
            # (a box's edge, where a tiny change of ray picks another face) may differ.
            diff = np.abs(v_live - v_acc).max(axis=-1)[interior]
            assert (diff > 4e-4).mean() < 1e-5 and diff.mean() < 1e-5
            assert (t_live.solid == t_acc.solid).mean() > 0.9999
            same = np.isfinite(t_acc.range_m)
            rel = np.abs(t_live.range_m[same] - t_acc.range_m[same]) / t_acc.range_m[same]
            assert np.median(rel) < 1e-5
        else:  # exact rays: float32 shading against float64
            rel = np.abs(v_live - v_acc) / np.maximum(np.abs(v_acc), 1e-12)
            assert rel[interior].max() < 1e-4
            np.testing.assert_array_equal(t_live.solid, t_acc.solid)
            np.testing.assert_array_equal(t_live.range_m, t_acc.range_m)


def test_live_frames_sizes_types_and_fresh_noise(live_and_accurate) -> None:
    """Live frames are what the sensors deliver; each frame from one render gets its own
    noise, of the model's size; the same seed gives the same frame."""
    live, _ = live_and_accurate
    frames, truth = live.render(LIVE_T_S)
    for name in RIG.names:
        w, h = RIG[name].image_size
        f = frames[name]
        assert f.stamp_ns == round(LIVE_T_S * 1e9)
        if RIG[name].modality == "color":
            assert f.image.dtype == np.uint8 and f.image.shape == (h, w, 3)
        else:
            assert f.image.dtype == np.float32 and f.image.shape == (h, w)
        if RIG[name].modality == "tof":
            assert f.distance_m is not None and f.distance_m.dtype == np.float32
            assert f.distance_m.shape == (h, w)
        assert truth[name].solid.shape == (h, w)

    model = live.renderer.model
    clean = live.render_clean(LIVE_T_S, list(LIVE_SENSORS))
    # TOF: NaN exactly where the true distance is beyond range or the return too weak.
    amp = clean["tof"].planes["values"][..., 1]
    valid = (truth["tof"].range_m <= model.tof_max_range_m) & (amp >= model.tof_min_amplitude)
    assert frames["tof"].distance_m is not None and 0.5 < valid.mean() < 1.0
    np.testing.assert_array_equal(np.isnan(frames["tof"].distance_m), ~valid)
    dev = live.developer
    assert dev is not None
    a = dev.frame(clean["ccd_left"], 0, np.random.default_rng(1))
    b = dev.frame(clean["ccd_left"], 0, np.random.default_rng(2))
    again = dev.frame(clean["ccd_left"], 0, np.random.default_rng(1))
    np.testing.assert_array_equal(a.image, again.image)
    assert (a.image != b.image).mean() > 0.5
    # Residual against the clean picture, in units of the per-pixel sigma: a standard
    # normal deviate, rounded to whole levels (adds 1/12 level^2: under 2 % of the variance
    # where sigma >= 2 levels). Mid-tones only: the model clips at 0 and 255.
    mean, sigma = clean["ccd_left"].planes["mean"], clean["ccd_left"].planes["sigma"]
    mid = (mean > 20) & (mean < 235) & (sigma >= 2.0)
    z = (a.image.astype(np.float32) - mean)[mid] / sigma[mid]
    assert abs(z.mean()) < 0.02 and 0.97 < z.std() < 1.03
    t1 = dev.frame(clean["thermal_left"], 0, np.random.default_rng(1)).image
    t2 = dev.frame(clean["thermal_left"], 0, np.random.default_rng(2)).image
    # Two draws of NETD noise differ with sigma sqrt(2) NETD (110 000 pixels: +-1 %).
    assert np.std(t1 - t2) / np.sqrt(2) == pytest.approx(model.thermal_netd_k, rel=0.03)
    d1 = dev.frame(clean["tof"], 0, np.random.default_rng(1)).distance_m
    d2 = dev.frame(clean["tof"], 0, np.random.default_rng(2)).distance_m
    assert d1 is not None and d2 is not None
    np.testing.assert_array_equal(np.isnan(d1), np.isnan(d2))
    assert np.nanstd(d1 - d2) > 0


def test_live_colour_noise_agrees_with_the_accurate_model(live_and_accurate) -> None:
    """Live colour frames and accurate ones of the same moment differ by noise only: no
    bias (the first-order gamma shortcut is off by under 0.1 level at mid-tones) and the
    spread of two independent draws, sqrt(2) sigma."""
    live, acc = live_and_accurate
    T = live.T_world_rig(LIVE_T_S) @ RIG["ccd_left"].T_rig_sensor
    values, truth = acc.renderer.render_raw(acc.scene, "ccd_left", T)
    accurate = acc.renderer.develop("ccd_left", values, truth, 0, np.random.default_rng(3))
    clean = live.render_clean(LIVE_T_S, ["ccd_left"])["ccd_left"]
    assert live.developer is not None
    frame = live.developer.frame(clean, 0, np.random.default_rng(4))
    mean, sigma = clean.planes["mean"], clean.planes["sigma"]
    mid = _interior(truth.solid)[..., None] & (mean > 20) & (mean < 235) & (sigma >= 2.0)
    diff = frame.image.astype(np.float32)[mid] - accurate.image.astype(np.float32)[mid]
    assert abs(diff.mean()) < 0.1
    assert diff.std() / np.sqrt(2 * np.mean(sigma[mid] ** 2)) == pytest.approx(1.0, abs=0.05)


def test_rotation_warp_map_is_the_exact_projection() -> None:
    """The turn's map, exact on a grid every 8 px and bilinear between, is within its own
    interpolation bound of projecting every pixel: (8^2 / 8) x the map's largest second
    difference, plus float32 arithmetic on pixel coordinates (bilinear: four products and
    three sums, at most 4 ulp of the largest coordinate)."""
    from trifuse.app.sources.sim.live import RotationWarp

    R = rotation_from_euler_deg(0.05, 0.3, 0.02)
    for name in LIVE_SENSORS:
        s = RIG[name]
        w, h = s.image_size
        got = RotationWarp(s).update(R, 5)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        rays = np.concatenate(
            [s.intrinsics.normalized(np.stack([u, v], -1)), np.ones((h, w, 1))], -1
        )
        exact = s.intrinsics.project(rays @ R.T) + 5
        second = max(
            np.abs(np.diff(exact, 2, axis=0)).max(), np.abs(np.diff(exact, 2, axis=1)).max()
        )
        bound = 8.0 * second + 4 * np.finfo(np.float32).eps * np.abs(exact).max()
        assert np.abs(got - exact).max() <= bound, name
        assert np.abs(exact - 5 - np.stack([u, v], -1)).max() > 1.0  # it does turn


def test_a_turned_frame_is_the_render_at_its_own_pose(live_and_accurate) -> None:
    """A picture rendered at t = 4.0 s (with a margin) and turned to the head's orientation
    at 4.1 s shows what a render at 4.1 s shows: no shift left (the colour camera, 5.4 cm
    off the turning axis, moves 0.26 mm: 0.35 px / distance in m of parallax, under 0.25 px
    for the room at 1.5-8 m) where the unturned picture is off by the turn (0.28 deg)."""
    model = HeadModel(color_read_noise=0.0, color_shot_noise=0.0)
    sc = InspectionScenario(seed=0, live=True, model=model)
    assert sc.developer is not None
    t0, t1 = LIVE_T_S, LIVE_T_S + 0.1
    name = "ccd_left"
    src = sc.render_clean(t0, [name], {name: 12})[name]
    ref = sc.render_clean(t1, [name])[name]
    T1 = sc.T_world_rig(t1) @ RIG[name].T_rig_sensor
    rng = np.random.default_rng(0)
    turned = sc.developer.frame(src, 0, rng, T1).image
    unturned = sc.developer.frame(src, 0, rng).image
    target = sc.developer.frame(ref, 0, rng).image
    gray = [
        cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float32) for x in (turned, unturned, target)
    ]
    window = cv2.createHanningWindow(gray[0].shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(gray[0], gray[2], window)
    assert abs(dx) < 0.25 and abs(dy) < 0.25
    turn = np.radians(sc.pan_deg * (np.sin(2 * np.pi * t1 / 30) - np.sin(2 * np.pi * t0 / 30)))
    (dx, _), _ = cv2.phaseCorrelate(gray[1], gray[2], window)
    assert abs(dx) == pytest.approx(RIG[name].intrinsics.fx * np.tan(turn), rel=0.1)
    # Pixel by pixel, away from silhouettes: the same picture up to rounding to levels.
    inner = _interior(ref.truth.solid, 5)
    assert np.abs(turned.astype(np.int16) - target)[inner].mean() < 0.5
