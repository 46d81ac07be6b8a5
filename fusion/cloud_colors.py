"""Colours of a point cloud for the 3D view (:func:`point_colors`): sampled colour, or
a palette over temperature or distance."""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import numpy.typing as npt

from trifuse.fusion.compose import describe_array as _describe
from trifuse.fusion.palettes import PaletteName, palette_colors
from trifuse.fusion.span import auto_span

CloudColoring = Literal["color", "temperature", "depth"]
"""What colours a point cloud (:func:`point_colors`)."""
CLOUD_COLORINGS: tuple[CloudColoring, ...] = get_args(CloudColoring)


def point_colors(
    points: npt.ArrayLike,
    by: CloudColoring = "color",
    values: npt.ArrayLike | None = None,
    span: tuple[float, float] | None = None,
    palette: PaletteName = "iron",
    nan_color: tuple[int, int, int] = (128, 128, 128),
) -> np.ndarray:
    """Colours of a point cloud for the 3D view: (N, 3) uint8 RGB.

    Args:
        points: (N, 3) points in metres (NaN rows allowed).
        by: ``"color"``: ``values`` are (N, 3) uint8 RGB (e.g. sampled from the colour
            image), returned as a copy; ``"temperature"``: ``values`` are (N,) kelvin,
            coloured with ``palette`` over ``span``; ``"depth"``: the distance of each
            point from the origin of its frame (radial, as the TOF measures; ``values``
            must be None), coloured with ``palette`` over ``span`` in metres.
        span: ``(low, high)`` for "temperature" / "depth"; None: the 1st to 99th
            percentile of the finite values (:func:`auto_span` without subsampling).
        palette: palette name.
        nan_color: RGB of points with no value (NaN temperature, NaN point).

    Raises:
        ValueError: bad shapes, an unknown ``by``, or ``span=None`` with no finite value.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {p.shape}")
    n = p.shape[0]
    if by == "color":
        if values is None:
            raise ValueError("values: expected (N, 3) uint8 RGB for by='color', got None")
        c = np.asarray(values)
        if c.dtype != np.uint8 or c.shape != (n, 3):
            raise ValueError(f"values: expected uint8 ({n}, 3) RGB, got {_describe(c)}")
        return c.copy()
    if by == "temperature":
        if values is None:
            raise ValueError("values: expected (N,) kelvin for by='temperature', got None")
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (n,):
            raise ValueError(f"values: expected shape ({n},) in kelvin, got {v.shape}")
        v = np.where(np.isfinite(p).all(axis=1), v, np.nan)
    elif by == "depth":
        if values is not None:
            raise ValueError("values: expected None for by='depth' (computed from points)")
        v = np.linalg.norm(p, axis=1)
    else:
        *first, last = (repr(c) for c in CLOUD_COLORINGS)
        raise ValueError(f"by: expected {', '.join(first)} or {last}, got {by!r}")
    if span is None:
        span = auto_span(v, step=1, min_span_k=1e-3)
    return palette_colors(v, span, palette, nan_color)
