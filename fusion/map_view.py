"""What a browser is sent of a :class:`~fusion.voxel_map.VoxelMap`: at most a given number
of points (level of detail: occupied voxels merged into cells of 2, 4, 8 ... voxels until
few enough remain), coloured by temperature or colour, hot spots above a threshold
highlighted.

A merged cell's point is the mean of its voxels' centres; its temperature is their mean and
its maximum the largest (so a hot spot survives any level), its colour their mean.

Frames and units: points in the map's world frame, metres; temperatures kelvin; colours
(N, 3) uint8 RGB.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from trifuse.fusion.agc import DEFAULT_MAX_GAIN, tone_map
from trifuse.fusion.cloud_colors import point_colors
from trifuse.fusion.palettes import PaletteName, palette
from trifuse.fusion.voxel_map import VoxelMap

MapColoring = Literal["temperature", "color"]
MapAgc = Literal["plateau", "linear"]
MAP_COLORINGS: tuple[MapColoring, ...] = ("temperature", "color")
UNKNOWN_RGB = (128, 128, 128)
"""Colour of a point with no reading of what it is coloured by."""
DIMMED = 0.25
"""Below the threshold, a point keeps this share of its brightness, greyed."""


@dataclass(frozen=True)
class MapCloud:
    """A map as shown.

    Attributes:
        points: (N, 3) float32 world, metres.
        colors: (N, 3) uint8 RGB.
        temp_mean, temp_max: (N,) float32 kelvin (NaN unseen).
        level: cells of ``2 ** level`` voxels a side (0: every occupied voxel).
        cell_m: the cell's edge, metres (a point size that closes the surface).
        occupied: occupied voxels in the map (before the level of detail).
        span_k: the temperature span coloured (None: colour mode or no temperature).
        above: points at or above the threshold (0 without one).
    """

    points: np.ndarray
    colors: np.ndarray
    temp_mean: np.ndarray
    temp_max: np.ndarray
    level: int
    cell_m: float
    occupied: int
    span_k: tuple[float, float] | None
    above: int


def merged(voxel_map: VoxelMap, max_points: int) -> tuple[dict[str, np.ndarray], int, int]:
    """The occupied voxels merged into cells of ``2 ** level`` voxels, the smallest level
    that leaves at most ``max_points`` cells.

    Returns:
        (``centre`` (N, 3), ``temp_mean``, ``temp_max`` (N,), ``rgb`` (N, 3) float with
        NaN, per cell; the level; the number of occupied voxels).
    """
    occ = voxel_map.occupied()
    n = int(occ.sum())
    centre = voxel_map["centre"][occ]
    tm, tx = voxel_map["temp_mean"][occ], voxel_map["temp_max"][occ]
    rgb = voxel_map["rgb"][occ]
    level = 0
    if n <= max_points:
        return {"centre": centre, "temp_mean": tm, "temp_max": tx, "rgb": rgb}, 0, n
    ijk = np.floor(centre / voxel_map.settings.voxel_m).astype(np.int64)
    while True:
        level += 1
        cell = ijk >> level  # floor division by 2 ** level, negative indices included
        cell -= cell.min(axis=0)
        span = cell.max(axis=0) + 1
        key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
        uniq, inverse = np.unique(key, return_inverse=True)
        if len(uniq) <= max_points or level >= 20:
            break
    k = len(uniq)
    count = np.bincount(inverse, minlength=k).astype(np.float64)
    out = {"centre": np.stack(
        [np.bincount(inverse, centre[:, a], minlength=k) / count for a in range(3)], axis=1
    ).astype(np.float32)}  # fmt: skip
    seen = np.isfinite(tm)
    total = np.bincount(inverse[seen], tm[seen].astype(np.float64), minlength=k)
    n_seen = np.bincount(inverse[seen], minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["temp_mean"] = (total / n_seen).astype(np.float32)
    top = np.full(k, -np.inf)
    np.maximum.at(top, inverse[seen], tx[seen].astype(np.float64))
    out["temp_max"] = np.where(np.isfinite(top), top, np.nan).astype(np.float32)
    has = np.isfinite(rgb).all(axis=1)
    n_rgb = np.bincount(inverse[has], minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["rgb"] = np.stack(
            [np.bincount(inverse[has], rgb[has, a], minlength=k) / n_rgb for a in range(3)],
            axis=1,
        )
    return out, level, n


def map_cloud(
    voxel_map: VoxelMap,
    by: MapColoring = "temperature",
    max_points: int = 300_000,
    span_k: tuple[float, float] | None = None,
    palette_name: PaletteName = "iron",
    threshold_k: float | None = None,
    agc: MapAgc = "plateau",
) -> MapCloud:
    """The map as a point cloud of at most ``max_points`` points (see the module
    docstring).

    Args:
        voxel_map: the map.
        by: colour by ``temperature`` (the mean, ``palette`` over ``span_k``) or by
            ``color`` (the colour cameras').
        max_points: the most points sent.
        span_k: the temperature span (None: the coldest to the hottest shown point under
            ``plateau``, the 1st to 99th percentile under ``linear``).
        palette_name: the palette of temperatures.
        threshold_k: points whose maximum temperature reaches it keep their colour, the
            others are dimmed to grey ("everything above 50 C"); None: no threshold.
        agc: ``plateau`` (the viewer's default, :mod:`fusion.agc`: the shown points'
            temperatures equalized, no kelvin wider than 12 palette steps, so a hot pipe
            does not turn the room one colour) or ``linear`` over the span.
    """
    if max_points < 1:
        raise ValueError(f"max_points: expected at least 1, got {max_points}")
    cells, level, occupied = merged(voxel_map, max_points)
    pts = cells["centre"].astype(np.float32)
    n = len(pts)
    span = None
    if by == "temperature":
        t = cells["temp_mean"]
        finite = t[np.isfinite(t)]
        if span_k is None and len(finite):
            lo, hi = (
                np.percentile(finite, [1, 99]) if agc == "linear" else (finite.min(), finite.max())
            )
            span_k = (float(lo), float(max(hi, lo + 0.5)))
        if span_k is None:
            colors = np.full((n, 3), UNKNOWN_RGB, np.uint8)
        elif agc == "linear":
            span = span_k
            colors = point_colors(pts, "temperature", t, span_k, palette_name, UNKNOWN_RGB)
        else:
            span = span_k
            tone = tone_map([t.reshape(-1, 1)], agc, span_k, max_gain=DEFAULT_MAX_GAIN)
            colors = palette(palette_name)[tone.index_of(t)]
            colors[~np.isfinite(t)] = UNKNOWN_RGB
    elif by == "color":
        rgb = cells["rgb"]
        known = np.isfinite(rgb).all(axis=1)
        colors = np.full((n, 3), UNKNOWN_RGB, np.uint8)
        colors[known] = np.clip(np.rint(rgb[known]), 0, 255).astype(np.uint8)
    else:
        raise ValueError(f"by: expected one of {MAP_COLORINGS}, got {by!r}")
    above = 0
    if threshold_k is not None:
        with np.errstate(invalid="ignore"):
            hot = cells["temp_max"] >= threshold_k
        above = int(hot.sum())
        grey = colors[~hot].mean(axis=1, keepdims=True) * DIMMED + 255 * 0.15 * (1 - DIMMED)
        colors[~hot] = np.clip(grey, 0, 255).astype(np.uint8)
    return MapCloud(
        points=pts,
        colors=colors,
        temp_mean=cells["temp_mean"].astype(np.float32),
        temp_max=cells["temp_max"].astype(np.float32),
        level=level,
        cell_m=voxel_map.settings.voxel_m * 2**level,
        occupied=occupied,
        span_k=span,
        above=above,
    )


def path_segments(voxel_map: VoxelMap, max_segments: int = 2000) -> np.ndarray:
    """The head's path as line segments (M, 2, 3) float32 (world, metres), thinned to at
    most ``max_segments``."""
    if len(voxel_map.path) < 2:
        return np.zeros((0, 2, 3), np.float32)
    pos = np.array([T[:3, 3] for _, T in voxel_map.path], dtype=np.float32)
    step = max(1, -(-(len(pos) - 1) // max_segments))
    pos = np.concatenate([pos[::step], pos[-1:]]) if (len(pos) - 1) % step else pos[::step]
    return np.stack([pos[:-1], pos[1:]], axis=1)
