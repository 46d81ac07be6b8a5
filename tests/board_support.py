"""Synthetic board detections for the calibration tests (noisy corners of the simulated
head: :func:`noisy_corners`) and the polarity and ordering tests (tests/calib/test_polarity.py,
tests/calib/test_symmetric_board.py): exact projections of the simulated head's ground truth plus
seeded noise, their poses, the screening and the calibration's input shape, and hard-edged
synthetic board images."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import cv2
import numpy as np

from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.diagnosis import Screening, screen_sensors
from trifuse.calib.rig import Rig
from trifuse.calib.rig_calibration import SensorSpec
from trifuse.calib.transforms import make_T, transform_points

RIG = default_rig()

# Per-axis corner noise (px) of each modality, about what the detectors achieve.
NOISE = {"color": 0.08, "thermal": 0.06, "tof": 0.05}
VIEWS = 16


def noisy_corners(
    poses: Iterable[np.ndarray],
    rng: np.random.Generator,
    sensors: Iterable[str] | None = None,
    *,
    noise: Mapping[str, float] = NOISE,
    view_name: Callable[[int], str] = lambda i: f"{i + 1:04d}",
    moved: Mapping[str, np.ndarray] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """view -> sensor -> (N, 2) corners of the default head's ``sensors`` (all by default)
    seeing the calibration board at the ``T_rig_board`` ``poses`` (the TOF's frame): exact
    projections plus Gaussian noise (``noise``: px per axis, per modality); only whole boards
    at least 3 px inside the image. ``view_name``: the i-th pose's view name. ``moved``:
    sensor -> (4, 4) board-frame motion that sensor sees the board moved by (a camera running
    late)."""
    obs: dict[str, dict[str, np.ndarray]] = {}
    for i, T_rig_board in enumerate(poses):
        for s in sensors or RIG.names:
            T = T_rig_board @ moved[s] if moved and s in moved else T_rig_board
            uv = RIG[s].intrinsics.project(
                transform_points(RIG.T(s, "tof") @ T, CALIBRATION_BOARD.object_points())
            )
            w, h = RIG[s].image_size
            if np.isfinite(uv).all() and (uv > 3).all() and (uv < (w - 4, h - 4)).all():
                noisy = uv + rng.normal(0, noise[RIG[s].modality], uv.shape)
                obs.setdefault(view_name(i), {})[s] = noisy
    return obs


def scenario_corners(
    views: int = 30,
    seed: int = 0,
    sensors: list[str] | None = None,
    noise: dict[str, float] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Corners of the default head seeing the board at the calibration scenario's first
    ``views`` poses (its seed 1), noise seeded by ``seed`` (:data:`NOISE` unless given):
    view -> sensor -> (N, 2) pixels."""
    return noisy_corners(
        calibration_poses(views, seed=1, rig=RIG),
        np.random.default_rng(seed),
        sensors,
        noise=noise or NOISE,
    )


def corners_seen(
    board: Board,
    rig: Rig = RIG,
    views: int = VIEWS,
    seed: int = 0,
    poses: list[np.ndarray] | None = None,
    offsets: dict[str, dict[str, np.ndarray]] | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """sensor -> view -> (N, 2) noisy corners in canonical order, for the views where the
    board lies inside the sensor's image (3 px from the border). ``offsets[sensor][view]``
    moves the board points (3,) in the board frame before projecting (another sub-grid)."""
    rng = np.random.default_rng(seed)
    obs: dict[str, dict[str, np.ndarray]] = {}
    poses = poses if poses is not None else calibration_poses(views, 1, rig, board)
    for i, T_rig_board in enumerate(poses):
        view = f"{i + 1:04d}"
        for s in rig.names:
            obj = board.object_points() + (offsets or {}).get(s, {}).get(view, 0.0)
            pts = transform_points(np.linalg.inv(rig[s].T_rig_sensor) @ T_rig_board, obj)
            uv = rig[s].intrinsics.project(pts)
            w, h = rig[s].image_size
            if np.isfinite(uv).all() and (uv > 3).all() and (uv < (w - 4, h - 4)).all():
                sigma = NOISE[rig[s].modality]
                obs.setdefault(s, {})[view] = uv + rng.normal(0.0, sigma, uv.shape)
    return obs


def pnp_poses(
    obs: dict[str, dict[str, np.ndarray]], rig: Rig, board: Board
) -> dict[str, dict[str, np.ndarray]]:
    """sensor -> view -> T_sensor_board by PnP with the true intrinsics."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for s, per in obs.items():
        intr = rig[s].intrinsics
        for v, c in per.items():
            ok, rvec, tvec = cv2.solvePnP(board.object_points(), c, intr.K, intr.dist)
            assert ok
            out.setdefault(s, {})[v] = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
    return out


def mirror_sensor(obs: dict[str, dict[str, np.ndarray]], sensor: str, board: Board) -> None:
    """Replace ``sensor``'s corners in ``obs`` (in place) by what the detector makes of a
    mirrored image: x mirrored, rows relabelled so that the grid is right-handed again
    (calib.detect: "Mirrored images")."""
    w = RIG[sensor].image_size[0]
    for v, c in obs[sensor].items():
        G = c.reshape(board.rows, board.cols, 2).copy()
        G[..., 0] = w - 1 - G[..., 0]
        obs[sensor][v] = G[::-1].reshape(-1, 2)


def screen(obs: dict[str, dict[str, np.ndarray]], board: Board, rig: Rig = RIG) -> Screening:
    """:func:`calib.diagnosis.screen_sensors` of ``obs`` with the true intrinsics and PnP poses."""
    return screen_sensors(
        obs,
        {s: rig[s].modality for s in obs},
        {s: rig[s].image_size for s in obs},
        {s: rig[s].intrinsics for s in obs},
        pnp_poses(obs, rig, board),
        board,
    )


SPECS = {n: SensorSpec(n, RIG[n].modality, RIG[n].image_size) for n in RIG.names}


def as_views(obs: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, np.ndarray]]:
    """sensor -> view -> corners as the calibration takes them: view -> sensor -> corners."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for s, per in obs.items():
        for v, c in per.items():
            out.setdefault(v, {})[s] = c
    return out


def board_image(board: Board, T_cam_board: np.ndarray, intr: Intrinsics, size, black, white):
    """A synthetic (H, W) float32 image of the board: ``black`` and ``white`` values of the
    squares (the margin white, one square wide), ``(black + white) / 2`` around it."""
    w, h = size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = intr.unproject(np.stack([u, v], axis=-1))
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    n = R[:, 2]
    depth = (n @ t) / (rays @ n)
    X = (rays * depth[..., None] - t) @ R  # board frame
    s = board.square_size_m
    inside = (X[..., 0] > -2 * s) & (X[..., 0] < (board.cols + 1) * s)
    inside &= (X[..., 1] > -2 * s) & (X[..., 1] < (board.rows + 1) * s)
    squares = (
        (X[..., 0] >= -s) & (X[..., 0] < board.cols * s)
        & (X[..., 1] >= -s) & (X[..., 1] < board.rows * s)
    )  # fmt: skip
    img = np.full((h, w), (black + white) / 2.0)
    img[inside] = white
    img[squares & board.is_black(X[..., 0], X[..., 1])] = black
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)
