"""The rotation vocabulary of calib.transforms: quaternions (x, y, z, w), roll-pitch-yaw in
radians (URDF) and degrees, rotation about an axis, shortest-arc interpolation and the
angle of a rotation, checked against closed forms and against each other."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trifuse.calib.transforms import (
    quaternion_from_rotation,
    rotation_about,
    rotation_angle_deg,
    rotation_from_euler_deg,
    rotation_from_quaternion,
    rotation_from_rpy,
    rotation_from_rvec,
    rotations_from_rvecs,
    slerp_rotation,
)

RNG_SEED = 31


def random_rotations(n: int) -> np.ndarray:
    """(n, 3, 3) rotations, angles up to a half turn about random axes (seeded)."""
    rng = np.random.default_rng(RNG_SEED)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return rotations_from_rvecs(axes * rng.uniform(0.0, math.pi, (n, 1)))


def test_quaternion_of_a_quarter_turn_about_z() -> None:
    q = quaternion_from_rotation(rotation_from_euler_deg(0.0, 0.0, 90.0))
    h = math.sqrt(0.5)
    assert q == pytest.approx((0.0, 0.0, h, h), abs=1e-15)
    assert all(isinstance(v, float) for v in q)


def test_quaternions_have_a_non_negative_w_and_come_back() -> None:
    for R in random_rotations(200):
        q = np.array(quaternion_from_rotation(R))
        assert q[3] >= 0.0
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
        np.testing.assert_allclose(rotation_from_quaternion(q), R, rtol=0, atol=1e-15)
        # Either sign and any length name the same rotation.
        np.testing.assert_allclose(rotation_from_quaternion(-3.0 * q), R, rtol=0, atol=1e-15)


def test_a_zero_quaternion_is_refused() -> None:
    with pytest.raises(ValueError):
        rotation_from_quaternion([0.0, 0.0, 0.0, 0.0])


def test_rpy_in_radians_is_the_euler_order_in_degrees() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for roll, pitch, yaw in rng.uniform(-180.0, 180.0, (100, 3)):
        R = rotation_from_rpy(*np.radians([roll, pitch, yaw]))
        np.testing.assert_allclose(R, rotation_from_euler_deg(roll, pitch, yaw), atol=1e-15)


def test_rotation_about_an_axis_of_any_length() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(50):
        axis, angle = rng.normal(size=3), rng.uniform(-math.pi, math.pi)
        R = rotation_about(5.0 * axis, angle)
        unit = axis / np.linalg.norm(axis)
        np.testing.assert_allclose(R, rotation_from_rvec(unit * angle), rtol=0, atol=1e-15)
        np.testing.assert_allclose(R @ unit, unit, atol=1e-15)  # the axis stays
        np.testing.assert_allclose(rotation_about(axis, -angle), R.T, atol=1e-15)


def test_slerp_goes_along_the_shortest_arc() -> None:
    for R0, R1 in zip(random_rotations(20), random_rotations(21)[1:], strict=True):
        np.testing.assert_allclose(slerp_rotation(R0, R1, 0.0), R0, atol=1e-15)
        np.testing.assert_allclose(slerp_rotation(R0, R1, 1.0), R1, atol=1e-14)
        total = rotation_angle_deg(R0.T @ R1)
        for s in (0.25, 0.5):
            Rs = slerp_rotation(R0, R1, s)
            assert rotation_angle_deg(R0.T @ Rs) == pytest.approx(s * total, abs=1e-9)
            assert rotation_angle_deg(Rs.T @ R1) == pytest.approx((1 - s) * total, abs=1e-9)
    # 179 degrees one way is the short way round (not 181 the other).
    B = rotation_from_euler_deg(0.0, 179.0, 0.0)
    assert rotation_angle_deg(slerp_rotation(np.eye(3), B, 0.5)) == pytest.approx(89.5, abs=1e-9)


def test_the_angle_stays_accurate_where_arccos_of_the_trace_does_not() -> None:
    for deg in (1e-6, 1e-3, 0.5, 30.0, 90.0, 179.999999):
        R = rotation_from_euler_deg(0.0, 0.0, deg)
        assert rotation_angle_deg(R) == pytest.approx(deg, rel=1e-9)
    # arccos((trace - 1) / 2) loses half the digits near 0: at 1e-6 degrees it is off by
    # over 1 %, which is why every angle goes through rotation_angle_deg.
    R = rotation_from_euler_deg(0.0, 0.0, 1e-6)
    c = (np.trace(R) - 1.0) / 2.0
    assert abs(math.degrees(math.acos(min(1.0, c))) - 1e-6) > 1e-8
