"""Exact synthetic views of any calibration target (tests of ChArUco and circle grids).

A pinhole camera (no distortion) looks at a board (calib.board.Board) through a pose; a
pixel on an edge is the mean of ``supersample`` x ``supersample`` rays intersected with the
board plane and classified by :meth:`Board.is_black`, so edges are area-sampled and the
ground truth (the board's points projected) is exact. Seeded noise.
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.transforms import make_T


def look_at_pose(
    board: Board,
    distance_m: float,
    tilt_deg: tuple[float, float],
    shift_m: tuple[float, float] = (0.0, 0.0),
    roll_deg: float = 0.0,
) -> np.ndarray:
    """(4, 4) ``T_cam_board``: the board's centre ``distance_m`` ahead of the camera, moved
    ``shift_m`` (x right, y down, metres) and turned by ``tilt_deg`` (about x, about y) and
    ``roll_deg`` (about the optical axis)."""
    x0, y0, x1, y1 = board.extent_m()
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    ax, ay = np.radians(tilt_deg)
    rz = np.radians(roll_deg)
    Rx = cv2.Rodrigues(np.array([ax, 0.0, 0.0]))[0]
    Ry = cv2.Rodrigues(np.array([0.0, ay, 0.0]))[0]
    Rz = cv2.Rodrigues(np.array([0.0, 0.0, rz]))[0]
    R = Rz @ Ry @ Rx
    t = np.array([shift_m[0], shift_m[1], distance_m]) - R @ centre
    return make_T(R, t)


def _classify(
    board: Board,
    K_inv: np.ndarray,
    T_cam_board: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    margin_m: float,
) -> np.ndarray:
    """Class of the board at image points (u, v): 0 a mark, 1 the board's white, 2 the
    background (off the board or behind the camera)."""
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ K_inv.T
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    C = -R.T @ t  # camera centre in the board frame
    d = rays @ R  # ray directions in the board frame
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -C[2] / d[..., 2]
    X = C[0] + lam * d[..., 0]
    Y = C[1] + lam * d[..., 1]
    x0, y0, x1, y1 = board.extent_m()
    on_board = (lam > 0) & (X >= x0 - margin_m) & (X < x1 + margin_m)
    on_board &= (Y >= y0 - margin_m) & (Y < y1 + margin_m)
    patterned = on_board & (X >= x0) & (X < x1) & (Y >= y0) & (Y < y1)
    marks = np.zeros(u.shape, dtype=bool)
    marks[patterned] = board.is_black(X[patterned], Y[patterned])
    if board.inverted:  # the margin of an inverted print is black too
        marks |= on_board & ~patterned
    return np.where(marks, 0, np.where(on_board, 1, 2))


def render(
    board: Board,
    K: np.ndarray,
    T_cam_board: np.ndarray,
    size: tuple[int, int],
    *,
    rng: np.random.Generator,
    margin_m: float = 0.02,
    supersample: int = 8,
    noise: float = 2.0,
    black: float = 30.0,
    white: float = 220.0,
    background: float = 120.0,
) -> np.ndarray:
    """(H, W) float64 image of ``board`` (its marks ``black``, the rest of the board within
    ``margin_m`` of its patterned area ``white``, elsewhere ``background``), plus Gaussian
    noise of sigma ``noise``. Pixel centres at integer coordinates. Pixels whose four
    corners see the same class are uniform; the others are the mean of ``supersample`` x
    ``supersample`` rays (features smaller than a pixel may be missed)."""
    w, h = size
    K_inv = np.linalg.inv(K)
    values = np.array([black, white, background])
    cu, cv = np.meshgrid(np.arange(w + 1) - 0.5, np.arange(h + 1) - 0.5)
    c = _classify(board, K_inv, T_cam_board, cu, cv, margin_m)
    corners = np.stack([c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
    img = values[corners[0]].astype(np.float64)
    mixed = np.flatnonzero(np.any(corners != corners[0], axis=0))
    if len(mixed):
        ss = supersample
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        ou, ov = np.meshgrid(offs, offs)
        pu = (mixed % w)[:, None] + ou.ravel()[None, :]
        pv = (mixed // w)[:, None] + ov.ravel()[None, :]
        sub = values[_classify(board, K_inv, T_cam_board, pu, pv, margin_m)]
        img.ravel()[mixed] = sub.mean(axis=1)
    return img + rng.normal(0.0, noise, img.shape)


def truth_points(board: Board, K: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """(N, 2) the board's points projected, pixels."""
    P = board.object_points() @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    uv = P @ K.T
    return uv[:, :2] / uv[:, 2:]


def to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
