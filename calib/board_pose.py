"""The board's pose in the rig frame from the corners every sensor found, for a known rig.

One sensor: PnP with the rig's intrinsics (:func:`board_pose_single`). Several sensors:
that pose from the sensor with the finest angular resolution, then refined by
Gauss-Newton on the reprojection error of all sensors' corners together
(:func:`board_pose`): the 1280 x 960 colour cameras pin the board's distance far better
than the 176 x 144 TOF alone, given the rig's extrinsics.

Frames: ``T_rig_board`` (4, 4) maps board-frame points (metres, board plane z = 0) into
the rig frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_rvec, rvec_from_rotation


@dataclass(frozen=True)
class BoardPose:
    """A board pose and how well it explains the corners.

    Attributes:
        T_rig_board: (4, 4) float64, metres.
        rms_px: per sensor, RMS reprojection error of its corners in its own pixels.
        sensors: the sensors whose corners were used.
    """

    T_rig_board: np.ndarray
    rms_px: dict[str, float]
    sensors: tuple[str, ...]


def board_pose_single(
    rig: Rig, sensor: str, corners: np.ndarray, board: Board
) -> np.ndarray | None:
    """(4, 4) ``T_rig_board`` from one sensor's corners (N, 2) pixels (PnP with the rig's
    intrinsics; NaN rows, corners a partial view did not see, left out); None when PnP
    fails or too few corners were seen (:meth:`calib.board.Board.pose_problem`)."""
    intr = rig[sensor].intrinsics
    uv = np.asarray(corners, np.float64).reshape(-1, 2)
    seen = np.isfinite(uv).all(axis=1)  # all but on a partial view (NaN rows: not seen)
    if board.pose_problem(seen) is not None:
        return None
    ok, rvec, tvec = cv2.solvePnP(
        board.object_points()[seen],
        uv[seen].reshape(-1, 1, 2),
        intr.K,
        np.asarray(intr.distortion, dtype=np.float64),
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        return None
    return rig[sensor].T_rig_sensor @ make_T(rotation_from_rvec(rvec.ravel()), tvec.ravel())


def _residuals(
    rig: Rig, corners: Mapping[str, np.ndarray], obj: np.ndarray, T_rig_board: np.ndarray
) -> dict[str, np.ndarray]:
    """Per sensor (M, 2) projected minus detected corners, pixels, of the corners seen
    (rows of ``corners`` that are not NaN)."""
    out = {}
    for name, uv in corners.items():
        seen = np.isfinite(uv).all(axis=1)
        T = np.linalg.inv(rig[name].T_rig_sensor) @ T_rig_board
        out[name] = rig[name].intrinsics.project(obj[seen] @ T[:3, :3].T + T[:3, 3]) - uv[seen]
    return out


def board_pose(
    rig: Rig, corners: Mapping[str, np.ndarray], board: Board, iterations: int = 10
) -> BoardPose | None:
    """The board pose that best explains every sensor's corners together.

    Args:
        rig: intrinsics and ``T_rig_sensor`` of every sensor named in ``corners``.
        corners: sensor -> (cols * rows, 2) detected corners, pixels, canonical order
            (NaN rows: corners a partial view did not see).
        board: the checkerboard.
        iterations: Gauss-Newton steps at most (it converges in 3-4).

    Returns None when no sensor's PnP succeeds. Sensors are weighted alike per pixel, so
    the finer cameras dominate, as their smaller angular noise deserves.
    """
    names = [n for n in corners if n in rig]
    if not names:
        return None
    # Start from the finest sensor (most pixels per radian).
    names.sort(key=lambda n: -rig[n].intrinsics.fx)
    T0 = None
    for name in names:
        T0 = board_pose_single(rig, name, corners[name], board)
        if T0 is not None:
            break
    if T0 is None:
        return None
    obj = board.object_points()
    used = {n: np.asarray(corners[n], np.float64).reshape(-1, 2) for n in names}
    rvec = rvec_from_rotation(T0[:3, :3])
    t = T0[:3, 3].copy()

    def stacked(rv: np.ndarray, tv: np.ndarray) -> np.ndarray:
        res = _residuals(rig, used, obj, make_T(rotation_from_rvec(rv), tv))
        return np.concatenate([r.ravel() for r in res.values()])

    r = stacked(rvec, t)
    for _ in range(iterations):
        if not np.all(np.isfinite(r)):
            break
        J = np.empty((r.size, 6))
        h = 1e-6
        for k in range(6):  # numeric Jacobian: six evaluations of a few hundred points
            dr, dt = np.zeros(3), np.zeros(3)
            (dr if k < 3 else dt)[k % 3] = h
            J[:, k] = (stacked(rvec + dr, t + dt) - r) / h
        step, *_ = np.linalg.lstsq(J, -r, rcond=None)
        rvec_new, t_new = rvec + step[:3], t + step[3:]
        r_new = stacked(rvec_new, t_new)
        if not np.all(np.isfinite(r_new)) or r_new @ r_new > r @ r:
            break
        rvec, t, r = rvec_new, t_new, r_new
        if np.max(np.abs(step)) < 1e-10:
            break
    T = make_T(rotation_from_rvec(rvec), t)
    res = _residuals(rig, used, obj, T)
    rms = {n: float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) for n, e in res.items()}
    return BoardPose(T, rms, tuple(names))
