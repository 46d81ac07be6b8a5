"""The OpenCV 5 multiview baseline: recovers a synthetic rig, OpenCV's conventions pinned.

Observations are synthesised without rendering: board corners projected through the
simulated head's exact cameras (``default_rig``) for random board poses that every sensor
sees whole, plus seeded Gaussian pixel noise.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import CalibrationError
from trifuse.calib.opencv_baseline import BaselineResult, calibrate_multiview_opencv
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.transforms import (
    invert,
    make_T,
    pose_error,
    rotation_from_euler_deg,
    rotation_from_rvec,
    transform_points,
)

BOARD = Board(9, 6, 0.06)
SEED = 20240612
EDGE_PX = 3.0  # keep every corner this far inside the image


def board_poses_and_observations(
    rig: Rig,
    n_views: int,
    seed: int,
    noise_px: float = 0.0,
    board: Board = BOARD,
    distance_m: tuple[float, float] = (0.6, 1.6),
    max_tilt_deg: float = 45.0,
) -> tuple[list[np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """Random ``T_rig_board`` poses in front of all sensors and their corner observations.

    A pose is kept only if every sensor sees all corners at least ``EDGE_PX`` inside its
    image. Noise is drawn after a pose is accepted, so it never decides acceptance.
    """
    rng = np.random.default_rng(seed)
    obj = board.object_points()
    centre = obj.mean(axis=0)
    poses: list[np.ndarray] = []
    observations: dict[str, dict[str, np.ndarray]] = {}
    while len(poses) < n_views:
        d = rng.uniform(*distance_m)
        axis = np.array([*rng.normal(size=2), 0.0])
        axis /= np.linalg.norm(axis)
        tilt = np.radians(rng.uniform(0.0, max_tilt_deg))
        R = rotation_from_rvec(axis * tilt) @ rotation_from_euler_deg(
            0.0, 0.0, rng.uniform(-20.0, 20.0)
        )
        c = np.array([rng.uniform(-0.45, 0.45) * d, rng.uniform(-0.35, 0.35) * d, d])
        T_rig_board = make_T(R, c - R @ centre)
        exact = {}
        for name, s in rig.sensors.items():
            uv = s.intrinsics.project(transform_points(invert(s.T_rig_sensor) @ T_rig_board, obj))
            w, h = s.image_size
            inside = np.all(np.isfinite(uv)) and np.all(
                (uv >= EDGE_PX) & (uv <= (w - 1 - EDGE_PX, h - 1 - EDGE_PX))
            )
            if not inside:
                break
            exact[name] = uv
        else:
            poses.append(T_rig_board)
            observations[f"{len(poses):04d}"] = {
                name: uv + rng.normal(0.0, noise_px, uv.shape) for name, uv in exact.items()
            }
    return poses, observations


def image_sizes(rig: Rig) -> dict[str, tuple[int, int]]:
    return {name: s.image_size for name, s in rig.sensors.items()}


def assert_recovers(
    result: BaselineResult, rig: Rig, rot_deg: float, trans_m: float, fx_rel: float
) -> None:
    for name, s in rig.sensors.items():
        rot, trans = pose_error(result.T_rig_sensor[name], s.T_rig_sensor)
        fx = result.intrinsics[name].fx
        assert rot < rot_deg, f"{name}: rotation error {rot:.3g} deg"
        assert trans < trans_m, f"{name}: translation error {trans:.3g} m"
        assert abs(fx / s.intrinsics.fx - 1) < fx_rel, f"{name}: fx {fx} vs {s.intrinsics.fx}"


@pytest.fixture(scope="module")
def rig() -> Rig:
    return default_rig()


@pytest.fixture(scope="module")
def exact_data(rig: Rig) -> tuple[list[np.ndarray], dict[str, dict[str, np.ndarray]]]:
    return board_poses_and_observations(rig, 25, SEED)


# -- accuracy -----------------------------------------------------------------------------------


def test_exact_projections_recover_the_rig(rig: Rig, exact_data) -> None:
    _, observations = exact_data
    result = calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof")
    assert set(result.T_rig_sensor) == set(rig.names)
    np.testing.assert_array_equal(result.T_rig_sensor["tof"], np.eye(4))
    # Only float32 rounding of the image points (about 4e-5 px at 1280 px) remains.
    assert_recovers(result, rig, rot_deg=1e-3, trans_m=1e-5, fx_rel=1e-4)
    for name, s in rig.sensors.items():
        got = result.intrinsics[name]
        assert len(got.distortion) == 5
        np.testing.assert_allclose((got.cx, got.cy), (s.intrinsics.cx, s.intrinsics.cy), atol=1e-3)
        np.testing.assert_allclose(got.distortion, s.intrinsics.distortion, atol=1e-4)
    assert result.rms_px < 1e-4
    assert all(v < 1e-4 for v in result.rms_px_by_sensor.values())
    assert result.seconds > 0


def test_noisy_projections_within_derived_tolerances(rig: Rig) -> None:
    sigma = 0.1
    poses, observations = board_poses_and_observations(rig, 30, SEED + 1, noise_px=sigma)
    result = calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof")

    # Derivation of the tolerances. The pose stage fits 6 parameters per sensor to
    # 30 views x 54 corners: its own noise (about sigma / f / sqrt(1620) rad, 1e-3 deg for
    # the TOF) is negligible. What moves the poses is the error of stage 1's intrinsics,
    # which the poses cannot absorb:
    # * a principal-point error dc (px) turns a camera's view of every board by dc / f rad,
    #   so sensor s's rotation relative to the reference errs by
    #   sd_rot = sqrt(sum over both cameras of (sd_cx / fx)^2 + (sd_cy / fy)^2);
    # * a relative focal-length error e = d_fx / fx scales the depth of every board that
    #   camera sees by e, so the relative translation errs by about e * z_mean (z_mean the
    #   mean board depth): sd_t = sqrt((z_mean e_ref)^2 + (z_mean e_s)^2 + (|t_s| sd_rot)^2),
    #   the last term being the lever arm of the rotation error.
    # sd_fx, sd_fy, sd_cx, sd_cy are the linearised standard deviations that
    # cv2.calibrateCameraExtended reports for the same views (they scale with the residual,
    # i.e. with sigma: about 0.5 px for the principal points here, so sd_rot is about
    # 0.25 deg, dominated by the TOF's f = 165 px). We allow 5 sd, and 5 sd_fx / fx for fx.
    obj = BOARD.object_points()
    sd = {}
    for name, s in rig.sensors.items():
        corners = [obs[name].astype(np.float32) for obs in observations.values()]
        out = cv2.calibrateCameraExtended(
            [obj.astype(np.float32)] * len(corners), corners, s.image_size, None, None
        )
        sd_fx, sd_fy, sd_cx, sd_cy = np.asarray(out[5]).ravel()[:4]
        i = s.intrinsics
        sd[name] = {
            "angle2": (sd_cx / i.fx) ** 2 + (sd_cy / i.fy) ** 2,
            "e": max(sd_fx / i.fx, sd_fy / i.fy),
        }
    T_ref_rig = invert(rig["tof"].T_rig_sensor)
    z_mean = float(np.mean([transform_points(T_ref_rig @ T, obj)[:, 2].mean() for T in poses]))

    for name, s in rig.sensors.items():
        assert abs(result.intrinsics[name].fx / s.intrinsics.fx - 1) < 5 * sd[name]["e"], name
        if name == "tof":
            continue
        sd_rot = np.sqrt(sd["tof"]["angle2"] + sd[name]["angle2"])
        lever = np.linalg.norm(s.T_rig_sensor[:3, 3])
        sd_t = np.sqrt((z_mean * sd["tof"]["e"]) ** 2 + (z_mean * sd[name]["e"]) ** 2)
        sd_t = np.hypot(sd_t, lever * sd_rot)
        rot, trans = pose_error(result.T_rig_sensor[name], s.T_rig_sensor)
        assert rot < 5 * np.degrees(sd_rot), f"{name}: {rot:.3g} deg, sd {np.degrees(sd_rot):.3g}"
        assert trans < 5 * sd_t, f"{name}: {trans * 1e3:.3g} mm, sd {sd_t * 1e3:.3g} mm"
        # Sanity: the derived bounds are not vacuous.
        assert 5 * np.degrees(sd_rot) < 2.0 and 5 * sd_t < 0.03
    # RMS of the 2-D corner error: sigma * sqrt(2) less the few fitted degrees of freedom.
    assert 0.9 * sigma * np.sqrt(2) < result.rms_px < 1.05 * sigma * np.sqrt(2)


# -- conventions ---------------------------------------------------------------------------------


def _pinhole_pair_rig(t_x: float) -> Rig:
    """Two identical pinhole cameras; ``cam_b`` sits ``t_x`` metres along the reference's +x."""
    intr = Intrinsics(800.0, 800.0, 399.5, 299.5, (-0.05, 0.01, 0.0, 0.0, 0.0))
    sensors = {
        "cam_b": Sensor("cam_b", "color", (800, 600), intr, make_T(np.eye(3), (t_x, 0.0, 0.0))),
        "ref": Sensor("ref", "color", (800, 600), intr, np.eye(4)),
    }
    return Rig(sensors=sensors, reference="ref")


@pytest.mark.parametrize("t_x", [0.1, -0.1])
def test_direction_convention_pure_x_translation(t_x: float) -> None:
    # cam_b listed first: the reference must still become OpenCV's camera 0.
    rig = _pinhole_pair_rig(t_x)
    _, observations = board_poses_and_observations(rig, 15, SEED + 2, distance_m=(0.8, 1.5))
    result = calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "ref")
    T = result.T_rig_sensor["cam_b"]
    np.testing.assert_allclose(T[:3, 3], (t_x, 0.0, 0.0), atol=1e-5)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-6)
    np.testing.assert_array_equal(result.T_rig_sensor["ref"], np.eye(4))


def test_missing_observations(rig: Rig) -> None:
    """Sensors absent from some views, the reference too; one sensor linked only via others."""
    _, full = board_poses_and_observations(rig, 30, SEED + 3)
    rng = np.random.default_rng(SEED + 4)
    observations: dict[str, dict[str, np.ndarray]] = {}
    for i, (view, obs) in enumerate(full.items()):
        keep = {name: uv for name, uv in obs.items() if rng.random() > 0.3}
        if i < 10:
            # thermal_right only ever appears without the reference (linked via ccd_right).
            keep.pop("tof", None)
            keep["ccd_right"] = obs["ccd_right"]
            keep["thermal_right"] = obs["thermal_right"]
        else:
            keep.pop("thermal_right", None)
            keep["tof"] = obs["tof"]
        observations[view] = keep
    seen = {n: sum(n in o for o in observations.values()) for n in rig.names}
    assert min(seen.values()) >= 3 and max(seen.values()) < 30
    assert not any("tof" in o and "thermal_right" in o for o in observations.values())

    result = calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof")
    assert_recovers(result, rig, rot_deg=1e-3, trans_m=1e-5, fx_rel=1e-4)


def test_four_distortion_coefficients(rig: Rig, exact_data) -> None:
    _, observations = exact_data
    result = calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof", 4)
    assert all(len(i.distortion) == 4 for i in result.intrinsics.values())
    assert_recovers(result, rig, rot_deg=1e-3, trans_m=1e-5, fx_rel=1e-4)


# -- unusable input ----------------------------------------------------------------------------


def test_sensor_with_too_few_views(rig: Rig, exact_data) -> None:
    _, full = exact_data
    observations = {v: dict(o) for v, o in full.items()}
    for i, obs in enumerate(observations.values()):
        if i >= 2:
            obs.pop("thermal_left")
    with pytest.raises(CalibrationError, match=r"at least 3 views.*'thermal_left' in 2"):
        calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof")


def test_sensor_never_seen_with_the_others(rig: Rig, exact_data) -> None:
    _, full = exact_data
    observations = {}
    for i, (v, o) in enumerate(full.items()):
        if i < 5:
            observations[v] = {"thermal_left": o["thermal_left"]}
        else:
            observations[v] = {n: uv for n, uv in o.items() if n != "thermal_left"}
    with pytest.raises(CalibrationError, match=r"\['thermal_left'\] never see the board together"):
        calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof")


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda o, s: o["0001"].update(tof=o["0001"]["tof"][:-1]), r"expected shape \(54, 2\)"),
        (lambda o, s: o["0001"]["tof"].__setitem__((0, 0), np.nan), "NaN"),
        (lambda o, s: s.pop("ccd_left"), "no image size for sensor 'ccd_left'"),
        (lambda o, s: s.update(tof=(176,)), r"image_sizes\['tof'\]"),
    ],
)
def test_malformed_input(rig: Rig, exact_data, mutate, message: str) -> None:
    _, full = exact_data
    observations = {v: {n: uv.copy() for n, uv in o.items()} for v, o in full.items()}
    sizes = image_sizes(rig)
    mutate(observations, sizes)
    with pytest.raises(ValueError, match=message):
        calibrate_multiview_opencv(observations, BOARD, sizes, "tof")


def test_bad_reference_and_coefficients(rig: Rig, exact_data) -> None:
    _, observations = exact_data
    with pytest.raises(ValueError, match="reference: sensor 'lidar'"):
        calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "lidar")
    with pytest.raises(ValueError, match="dist_coeffs"):
        calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof", 6)


def test_empty_views_are_ignored(rig: Rig, exact_data) -> None:
    _, full = exact_data
    observations = {"0000_empty": {}, **full, "9999_empty": {}}
    result = calibrate_multiview_opencv(observations, BOARD, image_sizes(rig), "tof")
    assert_recovers(result, rig, rot_deg=1e-3, trans_m=1e-5, fx_rel=1e-4)
