"""Rigid transforms as 4x4 float64 arrays named ``T_dst_src``, and the one place for rotations.

``T_dst_src`` maps points from frame ``src`` into frame ``dst``; transforms compose by
adjacent frames, ``T_a_c = T_a_b @ T_b_c``.

Rotations are (3, 3) float64 matrices; the other forms they take, each written once here:
axis-angle vectors (radians, OpenCV's ``rvec``), roll-pitch-yaw (fixed axes,
``Rz(yaw) @ Ry(pitch) @ Rx(roll)``: degrees for the simulator and tests, radians for URDF),
unit quaternions ``(x, y, z, w)`` (ROS, Foxglove, MCAP), the angle of a rotation, the
shortest-arc interpolation between two and the mean of many.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

RIGID_TOL = 1e-6


def rigidity_problem(T: npt.ArrayLike, tol: float = RIGID_TOL) -> str | None:
    """Return why ``T`` is not a rigid 4x4 transform, or None if it is.

    Args:
        T: candidate transform, anything convertible to a float array.
        tol: tolerance on orthonormality, determinant and the last row.
    """
    try:
        A = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        return "expected a 4x4 array of numbers"
    except OverflowError:  # an integer beyond float's range
        return "contains a number too large for a float"
    if A.shape != (4, 4):
        return f"expected shape (4, 4), got {A.shape}"
    if not np.all(np.isfinite(A)):
        return "contains NaN or infinity"
    if not np.allclose(A[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        return f"last row must be [0, 0, 0, 1], got {A[3].tolist()}"
    R = A[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # entries near 1e308 overflow
        ortho = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if not ortho <= tol:  # NaN too
        return f"rotation block is not orthonormal (max |R^T R - I| = {ortho:.3g})"
    det = float(np.linalg.det(R))
    if det < 0:
        return f"rotation block is a reflection (det = {det:.6f})"
    return None


def check_rigid(T: npt.ArrayLike, name: str = "T") -> np.ndarray:
    """Return ``T`` as a (4, 4) float64 array, or raise ValueError naming ``name``."""
    problem = rigidity_problem(T)
    if problem is not None:
        raise ValueError(f"{name}: not a rigid transform: {problem}")
    return np.array(T, dtype=np.float64)


def make_T(R: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """Build a (4, 4) transform from a (3, 3) rotation and a (3,) translation in metres."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform: ``T_src_dst`` from ``T_dst_src``."""
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


def transform_points(T_dst_src: np.ndarray, points_src: np.ndarray) -> np.ndarray:
    """Map points ``(..., 3)`` in frame src into frame dst; NaN stays NaN."""
    P = np.asarray(points_src, dtype=np.float64)
    return P @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]


def rotation_from_rvec(rvec: npt.ArrayLike) -> np.ndarray:
    """(3, 3) rotation matrix from an axis-angle vector (radians), Rodrigues' formula."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def rotation_about(axis: npt.ArrayLike, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about ``axis`` (3,) (any non-zero length; the
    turn is right-handed about it), Rodrigues' formula."""
    a = np.asarray(axis, dtype=np.float64)
    k = a / np.linalg.norm(a)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def rvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) in radians of a (3, 3) rotation matrix.

    The angle comes from ``atan2`` of the skew and symmetric parts, which stays accurate
    near 0 and near a half turn (``arccos`` of the trace does not).
    """
    R = np.asarray(R, dtype=np.float64)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])  # 2 sin(t) k
    s = float(np.linalg.norm(w)) / 2.0
    c = (float(np.trace(R)) - 1.0) / 2.0
    theta = float(np.arctan2(s, c))
    if s == 0.0 and c > 0:
        return np.zeros(3)
    if c > -0.9:
        return w * (theta / (2.0 * s))
    # Near a half turn: (R + R^T) / 2 - cos(t) I = (1 - cos(t)) k k^T.
    B = (R + R.T) / 2.0 - c * np.eye(3)
    i = int(np.argmax(np.diag(B)))
    k = B[:, i] / np.sqrt(B[i, i] * (1.0 - c))
    k /= np.linalg.norm(k)
    if k @ w < 0:
        k = -k
    return k * theta


def rotation_from_euler_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``, angles in degrees."""
    rx, ry, rz = np.radians([roll, pitch, yaw])
    Rx = np.array([[1, 0, 0], [0, np.cos(rx), -np.sin(rx)], [0, np.sin(rx), np.cos(rx)]])
    Ry = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
    Rz = np.array([[np.cos(rz), -np.sin(rz), 0], [np.sin(rz), np.cos(rz), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


_GIMBAL_EPS = 1e-12
"""``cos(pitch)`` below which :func:`rpy_from_rotation` folds yaw into roll (the two axes
coincide)."""


def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) rotation of URDF's ``rpy``: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``, radians.

    Fixed axes: roll about the parent's x, then pitch about its y, then yaw about its z
    (the order of :func:`rotation_from_euler_deg`, in radians).
    """
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """URDF's ``(roll, pitch, yaw)`` in radians of a (3, 3) rotation (inverse of
    :func:`rotation_from_rpy`), with pitch in [-pi/2, pi/2].

    Pitch comes from ``atan2``, accurate everywhere. At gimbal lock (pitch = +-90 degrees)
    roll and yaw turn about the same axis and only their difference (or sum) is defined:
    yaw is set to 0 there. Roll is always taken from what is left once yaw and pitch are
    undone, ``(Rz(yaw) Ry(pitch))^T R``, so an imprecise yaw near the lock is absorbed by
    roll and ``rotation_from_rpy(*rpy_from_rotation(R))`` reproduces ``R`` to about 1e-16.
    """
    R = np.asarray(R, dtype=np.float64)
    cos_pitch = math.hypot(float(R[0, 0]), float(R[1, 0]))
    pitch = math.atan2(-float(R[2, 0]), cos_pitch)
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0])) if cos_pitch > _GIMBAL_EPS else 0.0
    rest = rotation_from_rpy(0.0, pitch, yaw).T @ R  # = Rx(roll)
    roll = math.atan2(float(rest[2, 1]), float(rest[1, 1]))
    return roll, pitch, yaw


def quaternion_from_rotation(R: np.ndarray) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` unit quaternion of a (3, 3) rotation matrix, ``w >= 0`` (of the two
    quaternions of a rotation, the one with the non-negative scalar part)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return float(x), float(y), float(z), float(w)


def rotation_from_quaternion(q: npt.ArrayLike) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion ``(x, y, z, w)`` (scaled to unit length first;
    ``q`` and ``-q`` give the same rotation). Raises ValueError for a zero quaternion."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def slerp_rotation(R0: np.ndarray, R1: np.ndarray, s: float) -> np.ndarray:
    """(3, 3) rotation a fraction ``s`` (0..1) of the way from ``R0`` to ``R1`` along the
    shortest arc (spherical linear interpolation): ``R0 @ exp(s * log(R0^T R1))``."""
    from scipy.spatial.transform import Rotation

    r0 = Rotation.from_matrix(R0)
    step = (r0.inv() * Rotation.from_matrix(R1)).as_rotvec()
    return (r0 * Rotation.from_rotvec(s * step)).as_matrix()


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (e.g. of ``R_est.T @ R_true``)."""
    return float(np.degrees(np.linalg.norm(rvec_from_rotation(R))))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two transforms."""
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


def rotations_from_rvecs(rvecs: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rotation matrices from (K, 3) axis-angle vectors (radians), vectorised."""
    r = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(r, axis=1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = r / safe[:, None]
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s = np.where(small, 0.0, np.sin(theta))[:, None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(theta))[:, None, None]
    return np.eye(3)[None] + s * K + c * (K @ K)


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (K, 3, 3): the rotation nearest to their sum."""
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
