"""Seeded thermal views of the heated board under real-world conditions, with their truth:
what the ``thermal-detect`` benchmark (app/devtools/bench_detect.py) and
tests/app/sources/test_thermal_conditions.py run the detectors on. The conditions themselves are
app.sources.sim.thermal_conditions."""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.render import HeadModel, Renderer
from trifuse.app.sources.sim.scenarios import (
    CALIBRATION_BOARD,
    board_solid,
    calibration_poses,
    hot_objects_beside_board,
    lab_background,
    partial_view_poses,
)
from trifuse.app.sources.sim.scene import Scene
from trifuse.app.sources.sim.thermal_conditions import (
    ThermalConditions,
    centre_excess_k,
    square_emissivities,
)
from trifuse.calib.board import Board
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import transform_points


@dataclass
class ThermalView:
    """One rendered thermal image under some conditions, with its truth.

    Attributes:
        key: (seed, pose index, sensor) identifying the view.
        sensor: the thermal imager (or colour camera: the scene conditions apply to it).
        image: (H, W) float32 kelvin, or uint16 counts (``raw_counts``); a colour
            camera's (H, W, 3) uint8 RGB.
        corners: (N, 2) exact projections of the board's inner corners, canonical order
            (NaN where not projectable).
        inside: (N,) whether each inner corner has at least half a local corner spacing
            of image around it (its neighbourhood, which locates it, is in view).
        in_image: (N,) whether each inner corner lies inside the image at all.
        T_rig_board: (4, 4) the board pose, metres.
    """

    key: tuple[int, int, str]
    sensor: str
    image: np.ndarray
    corners: np.ndarray
    inside: np.ndarray
    in_image: np.ndarray
    T_rig_board: np.ndarray

    @property
    def expected(self) -> bool:
        """Whether a correct detector should find the board: every inner corner with its
        neighbourhood in view."""
        return bool(self.inside.all())

    @property
    def cut(self) -> bool:
        """Whether some inner corner is outside the image (the board cannot be found
        whole; a detector must not return it)."""
        return not bool(self.in_image.all())


def corner_visibility(
    corners: np.ndarray,
    board: Board,
    width: int,
    height: int,
    board_pixels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per inner corner (N,): in the image at all, and with at least half its local
    corner spacing of image on every side (``corners`` (N, 2) canonical order, pixels).

    ``board_pixels``: (H, W) bool, where the pixel-centre ray hits the board (the render's
    truth); a corner whose neighbourhood (0.45 spacing around it) shows anything else,
    e.g. a hand in front of it, is not counted as in view."""
    G = corners.reshape(board.rows, board.cols, 2)
    finite = np.all(np.isfinite(G), axis=2)
    dx = np.linalg.norm(np.diff(G, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(G, axis=0), axis=2)
    sp = np.full(G.shape[:2], np.inf)
    sp[:, :-1] = np.fmin(sp[:, :-1], dx)
    sp[:, 1:] = np.fmin(sp[:, 1:], dx)
    sp[:-1, :] = np.fmin(sp[:-1, :], dy)
    sp[1:, :] = np.fmin(sp[1:, :], dy)
    with np.errstate(invalid="ignore"):
        u, v = G[..., 0], G[..., 1]
        edge = np.minimum.reduce([u + 0.5, width - 0.5 - u, v + 0.5, height - 0.5 - v])
        in_image = finite & (edge > 0)
        inside = in_image & (edge >= np.maximum(2.0, 0.5 * sp))
    if board_pixels is not None:
        ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        ring = np.concatenate([[[0.0, 0.0]], np.stack([np.cos(ang), np.sin(ang)], axis=1)])
        with np.errstate(invalid="ignore"):
            pts = G[:, :, None, :] + 0.45 * np.where(np.isfinite(sp), sp, 0)[..., None, None] * ring
        u = np.clip(np.rint(np.nan_to_num(pts[..., 0])), 0, width - 1).astype(int)
        v = np.clip(np.rint(np.nan_to_num(pts[..., 1])), 0, height - 1).astype(int)
        inside &= board_pixels[v, u].all(axis=2)
    return in_image.ravel(), inside.ravel()


def thermal_condition_views(
    conditions: ThermalConditions,
    poses_per_seed: int = 8,
    seeds: tuple[int, ...] = (0,),
    rig: Rig | None = None,
    sensors: tuple[str, ...] = ("thermal_left", "thermal_right"),
) -> Iterator[ThermalView]:
    """Render thermal views of the heated board under ``conditions`` (accurate quality).

    For every seed: ``poses_per_seed`` board poses aimed at the thermal imagers in turn
    (:func:`~app.sources.sim.scenarios.calibration_poses` on the thermal imagers, or
    :func:`~app.sources.sim.scenarios.partial_view_poses` with ``partial_view``), each
    seen by every imager of ``sensors``, in the calibration lab (plus the hot objects
    with ``hot_objects``). ``conditions.seed`` is replaced by each seed in turn; noise is
    seeded by (seed, pose, sensor). Pose i of a seed is view i of a session (cooling).
    """
    rig = rig or default_rig()
    board = CALIBRATION_BOARD
    background = lab_background()
    for seed in seeds:
        cond = replace(conditions, seed=seed)
        renderer = Renderer(rig, HeadModel(thermal_imager=cond.imager()))
        targets = Rig(
            sensors={n: rig[n] for n in sensors}, reference=sensors[0], eyes={}
        )  # poses aimed at the thermal imagers only (still in the rig frame)
        if cond.partial_view:
            poses = partial_view_poses(poses_per_seed, seed, targets, board)
        else:
            poses = calibration_poses(poses_per_seed, seed, targets, board)
        for i, T_rig_board in enumerate(poses):
            solid = board_solid(T_rig_board, board)
            scene_solids = [*background, solid]
            if cond.hot_objects:
                scene_solids += hot_objects_beside_board(T_rig_board, board, seed=seed * 1000 + i)
            scene = Scene(scene_solids)
            mat = solid.material
            bt = cond.board_thermal(
                board,
                scene.ambient_k,
                i,
                centre_excess_k(mat, board, scene.ambient_k),
                square_emissivities(mat, board),
            )
            if bt is not None:
                mat.thermal = bt  # type: ignore[attr-defined]
            for name in sensors:
                sensor = rig[name]
                rng = np.random.default_rng([seed, 17, i, zlib.crc32(name.encode())])
                T_rig_s = sensor.T_rig_sensor
                values, truth = renderer.render_raw(scene, name, T_rig_s)
                frame = renderer.develop(name, values, truth, 0, rng)
                T_s_b = np.linalg.inv(T_rig_s) @ T_rig_board
                uv = sensor.intrinsics.project(transform_points(T_s_b, board.object_points()))
                w, h = sensor.image_size
                in_image, inside = corner_visibility(
                    uv, board, w, h, truth.solid == len(background)
                )
                yield ThermalView(
                    (seed, i, name), name, frame.image, uv, inside, in_image, T_rig_board
                )
