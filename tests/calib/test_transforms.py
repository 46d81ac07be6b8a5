"""Rigid transforms: invert, compose, axis-angle round trips, validation, pose errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trifuse.calib.transforms import (
    check_rigid,
    invert,
    make_T,
    pose_error,
    rigidity_problem,
    rotation_angle_deg,
    rotation_from_euler_deg,
    rotation_from_rvec,
    rvec_from_rotation,
    transform_points,
)

RNG_SEED = 20240611


def random_T(rng: np.random.Generator) -> np.ndarray:
    rvec = rng.normal(size=3)
    rvec *= rng.uniform(0.0, np.pi) / np.linalg.norm(rvec)
    return make_T(rotation_from_rvec(rvec), rng.uniform(-2.0, 2.0, size=3))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(RNG_SEED)


# -- invert / compose / transform_points ---------------------------------------------------


def test_invert_is_the_inverse(rng: np.random.Generator) -> None:
    for _ in range(50):
        T = random_T(rng)
        # Entries are O(1) (translations up to 2 m): a few ulp of 2 is below 1e-14.
        np.testing.assert_allclose(invert(T) @ T, np.eye(4), rtol=0, atol=1e-14)
        np.testing.assert_allclose(T @ invert(T), np.eye(4), rtol=0, atol=1e-14)
        np.testing.assert_allclose(invert(invert(T)), T, rtol=0, atol=1e-14)
        np.testing.assert_allclose(invert(T), np.linalg.inv(T), rtol=0, atol=1e-14)
        assert rigidity_problem(invert(T)) is None


def test_compose_by_adjacent_frames(rng: np.random.Generator) -> None:
    T_a_b, T_b_c = random_T(rng), random_T(rng)
    T_a_c = T_a_b @ T_b_c
    P_c = rng.uniform(-5.0, 5.0, size=(100, 3))
    P_a = transform_points(T_a_b, transform_points(T_b_c, P_c))
    np.testing.assert_allclose(transform_points(T_a_c, P_c), P_a, rtol=0, atol=1e-13)
    np.testing.assert_allclose(invert(T_a_c), invert(T_b_c) @ invert(T_a_b), rtol=0, atol=1e-14)


def test_transform_points_known_values() -> None:
    # A quarter turn about z (x -> y) then a shift of 1 m along x.
    T = make_T(rotation_from_euler_deg(0.0, 0.0, 90.0), [1.0, 0.0, 0.0])
    out = transform_points(T, [[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    np.testing.assert_allclose(out, [[1.0, 1.0, 0.0], [1.0, 0.0, 2.0]], rtol=0, atol=1e-15)


def test_transform_points_keeps_shape_and_nan(rng: np.random.Generator) -> None:
    T = random_T(rng)
    P = rng.normal(size=(4, 5, 3))
    P[1, 2] = np.nan
    out = transform_points(T, P)
    assert out.shape == (4, 5, 3)
    assert np.all(np.isnan(out[1, 2]))
    assert np.isnan(out).sum() == 3


# -- axis-angle ------------------------------------------------------------------------------

AXES = [
    np.array([1.0, 0.0, 0.0]),
    np.array([0.0, 0.0, 1.0]),
    np.array([0.36, -0.48, 0.8]),  # unit, all components non-zero
    np.array([-2.0, 1.0, 2.0]) / 3.0,
]

# A well-conditioned conversion (angle from atan2 of the skew and symmetric parts) recovers
# R to a few ulp; 1e-12 on entries of size <= 1 leaves three orders of magnitude of slack.
ROUND_TRIP_TOL = 1e-12

ANGLES_OK = [0.0, 1e-6, 1e-3, 0.5, 1.0, 2.0, 3.0, np.pi]
# Ill-conditioned for an arccos-based conversion: near zero and near a half turn.
ANGLES_HARD = [1e-9, 1e-8, np.pi - 1e-3, np.pi - 1e-5, np.pi - 1e-6, np.pi - 1e-7]


def _check_rvec_round_trip(theta: float, axis: np.ndarray) -> None:
    R = rotation_from_rvec(axis * theta)
    assert rigidity_problem(make_T(R, np.zeros(3))) is None
    rvec = rvec_from_rotation(R)
    np.testing.assert_allclose(rotation_from_rvec(rvec), R, rtol=0, atol=ROUND_TRIP_TOL)
    # The angle is recovered to the same accuracy (within [0, pi], as it must be).
    assert np.linalg.norm(rvec) == pytest.approx(theta, rel=0, abs=ROUND_TRIP_TOL)
    if 0.0 < theta < np.pi:
        # Away from the half turn the vector itself is unique.
        np.testing.assert_allclose(rvec, axis * theta, rtol=0, atol=ROUND_TRIP_TOL)


@pytest.mark.parametrize("axis", AXES, ids=["x", "z", "oblique1", "oblique2"])
@pytest.mark.parametrize("theta", ANGLES_OK)
def test_rvec_round_trip(theta: float, axis: np.ndarray) -> None:
    _check_rvec_round_trip(theta, axis)


@pytest.mark.parametrize("theta", ANGLES_HARD)
def test_rvec_round_trip_ill_conditioned(theta: float) -> None:
    _check_rvec_round_trip(theta, AXES[2])


def test_rvec_at_half_turn_is_either_sign() -> None:
    axis = AXES[2]
    rvec = rvec_from_rotation(rotation_from_rvec(axis * np.pi))
    assert min(np.abs(rvec - axis * np.pi).max(), np.abs(rvec + axis * np.pi).max()) < 1e-12


def test_rvec_agrees_with_opencv(rng: np.random.Generator) -> None:
    for _ in range(50):
        rvec = rng.normal(size=3)
        rvec *= rng.uniform(0.01, 3.0) / np.linalg.norm(rvec)
        R_cv, _ = cv2.Rodrigues(rvec)
        np.testing.assert_allclose(rotation_from_rvec(rvec), R_cv, rtol=0, atol=1e-14)
        np.testing.assert_allclose(rvec_from_rotation(R_cv), rvec, rtol=0, atol=1e-12)


def test_euler_angles() -> None:
    R = rotation_from_euler_deg(10.0, -20.0, 30.0)
    assert rotation_angle_deg(rotation_from_euler_deg(0.0, 0.0, 30.0)) == pytest.approx(30.0)
    # Rz(yaw) @ Ry(pitch) @ Rx(roll), each a rotation about one axis.
    Rz = rotation_from_rvec([0.0, 0.0, np.radians(30.0)])
    Ry = rotation_from_rvec([0.0, np.radians(-20.0), 0.0])
    Rx = rotation_from_rvec([np.radians(10.0), 0.0, 0.0])
    np.testing.assert_allclose(R, Rz @ Ry @ Rx, rtol=0, atol=1e-15)


# -- check_rigid -----------------------------------------------------------------------------


def test_check_rigid_accepts_and_converts() -> None:
    T = check_rigid(np.eye(4).tolist())
    assert isinstance(T, np.ndarray)
    assert T.dtype == np.float64
    np.testing.assert_array_equal(T, np.eye(4))


def _with(**changes: object) -> np.ndarray:
    T = make_T(rotation_from_euler_deg(5.0, -3.0, 20.0), [0.1, -0.2, 0.3])
    for key, value in changes.items():
        if key == "scale":
            T[:3, :3] *= value
        elif key == "shear":
            T[0, 1] += value
        elif key == "reflect":
            T[:3, 0] *= -1.0
        elif key == "last_row":
            T[3] = value
        elif key == "nan":
            T[1, 3] = np.nan
    return T


@pytest.mark.parametrize(
    ("T", "match"),
    [
        (np.eye(3), r"expected shape \(4, 4\), got \(3, 3\)"),
        (np.eye(4)[:3], r"expected shape \(4, 4\), got \(3, 4\)"),
        ([["a"] * 4] * 4, "expected a 4x4 array of numbers"),
        (_with(nan=True), "contains NaN or infinity"),
        (_with(scale=1.01), r"rotation block is not orthonormal \(max \|R\^T R - I\| = 0\.0201\)"),
        (_with(shear=0.05), "rotation block is not orthonormal"),
        (_with(reflect=True), r"rotation block is a reflection \(det = -1\.000000\)"),
        (_with(last_row=[0.0, 0.0, 0.1, 1.0]), r"last row must be \[0, 0, 0, 1\]"),
        (_with(last_row=[0.0, 0.0, 0.0, 2.0]), r"last row must be \[0, 0, 0, 1\]"),
    ],
    ids=["3x3", "3x4", "strings", "nan", "scaled", "shear", "reflection", "row-z", "row-w"],
)
def test_check_rigid_errors_name_the_problem(T: object, match: str) -> None:
    with pytest.raises(ValueError, match=rf"^T_rig_x: not a rigid transform: {match}"):
        check_rigid(T, "T_rig_x")


def test_rigidity_tolerance() -> None:
    T = make_T(rotation_from_euler_deg(5.0, -3.0, 20.0), [0.1, -0.2, 0.3])
    T[:3, :3] *= 1.0 + 1e-8  # |R^T R - I| ~ 2e-8 < 1e-6
    assert rigidity_problem(T) is None


# -- pose_error --------------------------------------------------------------------------------


def test_pose_error_known_offsets(rng: np.random.Generator) -> None:
    T_true = random_T(rng)
    dR = rotation_from_rvec(np.array([0.36, -0.48, 0.8]) * np.radians(0.5))
    T_est = T_true.copy()
    T_est[:3, :3] = T_true[:3, :3] @ dR
    T_est[:3, 3] += [0.003, -0.004, 0.0]
    rot_deg, trans_m = pose_error(T_est, T_true)
    assert rot_deg == pytest.approx(0.5, rel=1e-9)
    assert trans_m == pytest.approx(0.005, rel=1e-9)
    # Symmetric in its arguments.
    assert pose_error(T_true, T_est) == pytest.approx((rot_deg, trans_m), rel=1e-9)


def test_pose_error_of_identical_poses_is_zero(rng: np.random.Generator) -> None:
    T = random_T(rng)
    rot_deg, trans_m = pose_error(T, T.copy())
    assert rot_deg == pytest.approx(0.0, abs=1e-6)
    assert trans_m == 0.0
