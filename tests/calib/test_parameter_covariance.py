"""The rig file's joint covariance (calib.parameter_covariance): what a calibration writes,
its round trip, its bad forms, and how it moves a rig."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from trifuse.calib.errors import RigError
from trifuse.calib.parameter_covariance import (
    ParameterCovariance,
    bounding_covariance,
    split_name,
)
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import rig_from_yaml, rig_to_dict, rig_to_yaml
from trifuse.calib.transforms import rotation_from_rvec


def test_a_calibrated_rig_carries_its_covariance_and_reads_back_exactly(simulated: dict) -> None:
    rig = simulated["rig"]  # read from the file `trifuse calibrate` wrote
    cov = rig.covariance
    assert cov is not None
    assert set(cov.sensors) == set(rig.names)
    poses = {split_name(n)[0] for n in cov.names if split_name(n)[1] == "rx"}
    assert poses == set(rig.names) - {rig.reference}
    assert rig_from_yaml(rig_to_yaml(rig)) == rig
    C = cov.matrix()
    assert np.all(np.linalg.eigvalsh(C / np.outer(cov.sigma, cov.sigma)) > -1e-9)
    # at least the larger of the two estimates the uncertainty blocks report per parameter
    for name, sigma in zip(cov.names, cov.sigma, strict=True):
        sensor, param = split_name(name)
        unc = rig[sensor].uncertainty
        if param in ("fx", "fy", "cx", "cy"):
            assert sigma >= unc[param] * (1 - 1e-9), name
        elif param in ("tx", "ty", "tz"):
            assert sigma >= unc["translation_m"]["xyz".index(param[1])] * (1 - 1e-9), name
    # the two thermal imagers' rotations err together: each relative to the other is
    # known better than either is to the reference
    sub = cov.restricted(("thermal_left", "thermal_right"))
    d = np.zeros(len(sub.names))
    d[sub.names.index("thermal_left.ry")], d[sub.names.index("thermal_right.ry")] = 1, -1
    rel = np.sqrt(d @ sub.matrix() @ d)
    assert rel < sub.sigma[sub.names.index("thermal_left.ry")]


def test_the_bound_holds_both_estimates() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        A, B = rng.standard_normal((2, 6, 6))
        iid, cluster = A @ A.T, B @ B.T * rng.uniform(0.1, 3.0)
        S = bounding_covariance(iid, cluster)
        scale = np.abs(S).max()
        assert np.linalg.eigvalsh(S - iid).min() > -1e-9 * scale
        assert np.linalg.eigvalsh(S - cluster).min() > -1e-9 * scale
    iid = np.diag([4.0, 1.0])
    assert np.allclose(bounding_covariance(iid, 0.5 * iid), iid)  # iid already holds both


def test_restricted_and_sampled_covariances_are_the_same_distribution() -> None:
    rng = np.random.default_rng(5)
    A = rng.standard_normal((5, 5))
    names = ["b.rx", "b.ry", "c.fx", "c.k1", "b.tz"]
    cov = ParameterCovariance.from_matrix(names, A @ A.T)
    sub = cov.restricted(["b"])
    assert sub.names == ("b.rx", "b.ry", "b.tz")
    assert np.allclose(sub.matrix(), (A @ A.T)[np.ix_([0, 1, 4], [0, 1, 4])])
    draws = cov.sample(np.random.default_rng(6), 20000)
    # 20000 draws: each variance to about 1 % (sqrt(2 / n)); 5 % is 5 of those
    assert np.allclose(np.cov(draws.T), A @ A.T, rtol=0.05, atol=0.05 * np.abs(A @ A.T).max())
    zero = ParameterCovariance.from_matrix(["b.rx", "b.ry"], np.diag([1.0, 0.0]))
    assert zero.names == ("b.rx",)  # a parameter that was not estimated is left out


def test_perturbed_moves_poses_about_the_sensors_own_axes_and_adds_to_intrinsics(
    simulated: dict,
) -> None:
    rig = simulated["truth"]
    cov = ParameterCovariance.from_matrix(
        ["thermal_left.rz", "thermal_left.tx", "thermal_left.fx", "tof.k3", "tof.k6"],
        np.eye(5),
    )
    moved = rig.perturbed(cov, np.array([0.01, 0.002, 1.5, 0.003, -0.001]))
    before, after = rig["thermal_left"], moved["thermal_left"]
    assert np.allclose(
        after.T_rig_sensor[:3, :3], before.T_rig_sensor[:3, :3] @ rotation_from_rvec([0, 0, 0.01])
    )
    assert np.allclose(after.T_rig_sensor[:3, 3] - before.T_rig_sensor[:3, 3], [0.002, 0, 0])
    assert after.intrinsics.fx == before.intrinsics.fx + 1.5
    tof_d = moved["tof"].intrinsics.distortion
    assert len(tof_d) == 8 and tof_d[4] == rig["tof"].intrinsics.distortion[4] + 0.003
    assert tof_d[7] == -0.001
    assert moved.covariance is None and moved["ccd_left"] == rig["ccd_left"]
    with pytest.raises(ValueError, match="delta"):
        rig.perturbed(cov, np.zeros(4))


def test_with_sensor_keeps_the_covariance_only_while_the_geometry_stays(simulated: dict) -> None:
    rig = simulated["rig"]
    s = rig["thermal_left"]
    warmer = rig.with_sensor(replace(s, radiometry=Radiometry(balance_offset_k=0.5)))
    assert warmer.covariance == rig.covariance
    T = s.T_rig_sensor.copy()
    T[0, 3] += 0.001
    assert rig.with_sensor(replace(s, T_rig_sensor=T)).covariance is None


def _mutated(rig_dict: dict, path: str, value: object) -> dict:
    block = rig_dict["covariance"]
    if path == "row0":
        block["correlation_factor"][1] = [0.5]
    elif path == "reference":
        block["parameters"][0] = f"{rig_dict['reference']}.rx"
    elif path == "parameters":
        block["parameters"][0] = value
    else:
        block[path] = value
    return rig_dict


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        ("model", "other/1", "covariance.model"),
        ("sigma", [1.0], "covariance.sigma"),
        ("parameters", "nosuch.fx", "unknown sensor 'nosuch'"),
        ("parameters", "ccd_left.zoom", "parameter 'ccd_left.zoom'"),
        ("row0", None, r"correlation_factor\[1\]"),
        ("reference", None, "reference sensor's pose"),
    ],
)
def test_malformed_covariance_blocks_are_refused_by_name(
    simulated: dict, path: str, value: object, match: str
) -> None:
    import yaml

    data = _mutated(rig_to_dict(simulated["rig"]), path, value)
    with pytest.raises(RigError, match=match):
        rig_from_yaml(yaml.safe_dump(data))
