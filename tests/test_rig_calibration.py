"""The joint rig calibration on synthetic corners: exact projections plus seeded noise."""

from __future__ import annotations

import numpy as np
import pytest

from app.sources.sim.head import default_rig
from app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from calib.errors import CalibrationError
from calib.rig_calibration import CalibrationOptions, SensorSpec, calibrate_rig
from calib.transforms import rvec_from_rotation, transform_points

RIG = default_rig()
SPECS = {n: SensorSpec(n, RIG[n].modality, RIG[n].image_size) for n in RIG.names}
# Per-axis corner noise (px) of each modality, about what the detectors achieve.
NOISE = {"color": 0.08, "thermal": 0.06, "tof": 0.05}


def synthetic(
    views: int = 30,
    seed: int = 0,
    sensors: list[str] | None = None,
    noise: dict[str, float] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Corners of the default head seeing the board at the calibration scenario's poses."""
    rng = np.random.default_rng(seed)
    obs: dict[str, dict[str, np.ndarray]] = {}
    for i, T_rig_board in enumerate(calibration_poses(views, seed=1, rig=RIG)):
        for s in sensors or RIG.names:
            pts = transform_points(RIG.T(s, "tof") @ T_rig_board, CALIBRATION_BOARD.object_points())
            uv = RIG[s].intrinsics.project(pts)
            w, h = RIG[s].image_size
            if np.isfinite(uv).all() and (uv > 3).all() and (uv < (w - 4, h - 4)).all():
                sigma = (noise or NOISE)[RIG[s].modality]
                obs.setdefault(f"{i + 1:04d}", {})[s] = uv + rng.normal(0, sigma, uv.shape)
    return obs


def _param_errors(name: str, result, reference: str = "tof"):
    """Errors of T_ref_sensor's rotation vector (deg) and translation (m), per component."""
    T_true = RIG.T(reference, name)
    T_est = result.sensors[name].T_rig_sensor
    rot = np.degrees(rvec_from_rotation(T_est[:3, :3]) - rvec_from_rotation(T_true[:3, :3]))
    return rot, T_est[:3, 3] - T_true[:3, 3]


@pytest.fixture(scope="module")
def full():
    return calibrate_rig(synthetic(), CALIBRATION_BOARD, SPECS)


def test_recovers_every_sensor_within_three_sigma(full) -> None:
    assert full.reference == "tof"
    assert not full.outliers
    for name in RIG.names:
        s, truth = full.sensors[name], RIG[name].intrinsics
        for k in ("fx", "fy", "cx", "cy"):
            err = getattr(s.intrinsics, k) - getattr(truth, k)
            assert abs(err) < 3 * s.sigma[k] + 1e-9, (name, k, err, s.sigma[k])
        if name == "tof":
            continue
        rot, trans = _param_errors(name, full)
        assert np.all(np.abs(rot) < 3 * np.array(s.sigma["rotation_deg"])), (name, rot)
        assert np.all(np.abs(trans) < 3 * np.array(s.sigma["translation_m"])), (name, trans)
        # And the issue's absolute targets (the noise here is the detectors' level).
        assert np.linalg.norm(rot) < 0.1 and np.linalg.norm(trans) < 0.001


def test_rms_matches_the_injected_noise(full) -> None:
    # RMS of 2-D errors = sqrt(2) * per-axis sigma, less the fitted degrees of freedom.
    for name, s in full.sensors.items():
        expected = np.sqrt(2) * NOISE[s.modality]
        assert s.rms_px == pytest.approx(expected, rel=0.1), name


def test_report_shape(full) -> None:
    report = full.to_report()
    for name in RIG.names:
        entry = report["sensors"][name]
        assert set(entry["intrinsics"]) == {"fx", "fy", "cx", "cy"}
        assert np.asarray(entry["T_rig_sensor"]).shape == (4, 4)
        assert {"fx", "fy", "cx", "cy", "rotation_deg", "translation_m"} <= set(entry["sigma"])
    some_view = next(iter(report["views"]))
    assert {"rms_px", "outlier"} <= set(next(iter(report["views"][some_view].values())))
    rig = full.rig()
    assert rig.reference == "tof" and rig["ccd_left"].uncertainty["fx"] > 0


@pytest.mark.parametrize(
    ("sensors", "reference"),
    [(["ccd_left", "ccd_right"], "ccd_left"), (["ccd_right", "thermal_right"], None)],
)
def test_subsets_of_sensors(sensors: list[str], reference: str | None) -> None:
    obs = synthetic(sensors=sensors, seed=3)
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS, CalibrationOptions(reference=reference))
    ref = reference or sorted(sensors)[0]  # no TOF: the first sensor by name
    assert result.reference == ref and sorted(result.sensors) == sorted(sensors)
    other = next(s for s in sensors if s != ref)
    T_est = result.sensors[other].T_rig_sensor
    rot, trans = _param_errors(other, result, reference=ref)
    sig = result.sensors[other].sigma
    assert np.all(np.abs(rot) < 3 * np.array(sig["rotation_deg"]))
    assert np.all(np.abs(trans) < 3 * np.array(sig["translation_m"]))
    assert np.allclose(result.sensors[ref].T_rig_sensor, np.eye(4))
    assert T_est.shape == (4, 4)


def test_outlier_view_and_corners_are_flagged_and_left_out() -> None:
    obs = synthetic(seed=5)
    rng = np.random.default_rng(11)
    obs["0007"]["thermal_left"] = obs["0007"]["thermal_left"] + rng.normal(0, 1.5, (54, 2))
    obs["0012"]["ccd_right"][20] += (4.0, -3.0)  # one mis-detected corner
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS)
    view_out = {(o.view, o.sensor) for o in result.outliers if o.corner is None}
    corner_out = {(o.view, o.sensor, o.corner) for o in result.outliers if o.corner is not None}
    assert ("0007", "thermal_left") in view_out
    assert result.views["0007"]["thermal_left"].outlier
    assert "corners are beyond 5 sigma" in result.views["0007"]["thermal_left"].reason
    assert ("0012", "ccd_right", 20) in corner_out
    assert len(view_out) == 1 and len(corner_out) <= 2
    rot, trans = _param_errors("thermal_left", result)
    assert np.linalg.norm(rot) < 0.1 and np.linalg.norm(trans) < 0.001
    assert result.sensors["thermal_left"].worst_view == "0007"


def test_bad_input_gives_clear_errors() -> None:
    with pytest.raises(CalibrationError, match="not detected in any image"):
        calibrate_rig({}, CALIBRATION_BOARD, SPECS)
    one = {"0001": synthetic(views=1)["0001"]}
    with pytest.raises(CalibrationError, match=r"reference sensor 'tof': .*1 view"):
        calibrate_rig(one, CALIBRATION_BOARD, SPECS)
    obs = synthetic(views=6)
    with pytest.raises(CalibrationError, match="unknown sensor 'lidar'"):
        calibrate_rig(obs, CALIBRATION_BOARD, SPECS, CalibrationOptions(reference="lidar"))
    obs["0001"]["tof"] = obs["0001"]["tof"][:10]
    with pytest.raises(CalibrationError, match=r"expected corners of shape \(54, 2\)"):
        calibrate_rig(obs, CALIBRATION_BOARD, SPECS)


def test_sensor_with_too_few_views_is_left_out_and_said() -> None:
    obs = synthetic(views=12, seed=2)
    seen = [v for v in obs if "thermal_right" in obs[v]]
    for v in seen[2:]:
        del obs[v]["thermal_right"]
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS)
    assert "thermal_right" not in result.sensors
    assert "2 view(s)" in result.excluded_sensors["thermal_right"]
