"""The TOF point cloud of the console's 3D scene, coloured: by the colour camera, by
temperature (the thermal imager through its radiometry, in the pipeline's palette over its
span) or by radial distance; for a slow link, decimated on the TOF's pixel grid
(:func:`decimate_cloud`: every s-th pixel of every s-th row, so the cloud keeps the
sensor's regular structure)."""

from __future__ import annotations

import numpy as np

from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.rig import Sensor
from trifuse.fusion.palettes import PALETTE_NAMES
from trifuse.fusion.span import auto_span, resolve_span

DEPTH_PALETTE = "rainbow" if "rainbow" in PALETTE_NAMES else PALETTE_NAMES[0]
NAN_GREY = (128, 128, 128)
C_TO_K = 273.15


def temperature_span(
    pipeline: FusionPipeline, thermal_images: list[np.ndarray]
) -> tuple[float, float] | None:
    """The pipeline's span (kelvin): fixed in its settings, else the last fused frame's
    span, else the automatic span over ``thermal_images`` (None without any)."""
    settings = pipeline.settings
    if settings.span_k is not None:
        return settings.span_k
    span = pipeline.fusion.span_k
    if span is not None:
        return span
    return resolve_span(settings, thermal_images) if thermal_images else None


def thermal_k(pipeline: FusionPipeline, fs: FrameSet, sensor: str) -> np.ndarray | None:
    """The imager's temperatures (H, W) kelvin in frame set ``fs`` through its radiometry
    (calibration, balance, trim) as the fused picture shows them, or None."""
    frame = fs.frames.get(sensor)
    if frame is None:
        return None
    r = pipeline.radiometry.get(sensor)
    image = np.asarray(frame.image, dtype=np.float32)
    return image if r is None else r.apply(image)


def coloured_cloud(
    pipeline: FusionPipeline, fs: FrameSet, mode: str
) -> tuple[np.ndarray, np.ndarray, str, tuple[float, float] | None]:
    """The pipeline's TOF points coloured by ``mode`` (``color``, ``temperature``,
    ``depth``: :data:`fusion.cloud_colors.CLOUD_COLORINGS`) with frame set ``fs``.

    Returns:
        (points (N, 3) metres in the in-use rig's TOF frame, colours (N, 3) uint8 RGB
        (:data:`NAN_GREY` where the colouring sensor is missing), the legend, the span
        coloured (kelvin or metres; None for ``color``)).
    """
    fusion, rig = pipeline.fusion, pipeline.rig
    points = fusion.points
    n = len(points)
    eye_name = fusion.eyes[0]
    eye = rig.eyes[eye_name]
    grey = np.full((n, 3), NAN_GREY, np.uint8)
    if mode == "color":
        frame = fs.frames.get(eye.color)
        if frame is None:
            return points, grey, f"colour camera {eye.color} missing", None
        pts, rgb = fusion.point_cloud({eye_name: frame.image}, {}, "color")
        return pts, rgb, f"from {eye.color}", None
    if mode == "temperature":
        thermals = {
            e: t
            for e in fusion.eyes
            if (t := thermal_k(pipeline, fs, rig.eyes[e].thermal)) is not None
        }
        span = temperature_span(pipeline, list(thermals.values()))
        if eye_name not in thermals or span is None:
            return points, grey, f"thermal imager {eye.thermal} missing", span
        palette = pipeline.settings.palette
        pts, rgb = fusion.point_cloud(
            {}, {eye_name: thermals[eye_name]}, "temperature", span, palette
        )
        legend = (
            f"from {eye.thermal}, {span[0] - C_TO_K:.1f} to {span[1] - C_TO_K:.1f} °C ({palette})"
        )
        return pts, rgb, legend, span
    r = np.linalg.norm(np.asarray(points, dtype=np.float64), axis=1)
    span = auto_span(r, step=1, min_span_k=0.01, default=(0.0, 1.0))
    pts, rgb = fusion.point_cloud({}, {}, "depth", span, DEPTH_PALETTE)
    legend = f"radial distance {span[0]:.2f} to {span[1]:.2f} m ({DEPTH_PALETTE})"
    return pts, rgb, legend, span


def grid_stride(image_size: tuple[int, int], max_points: int) -> int:
    """The smallest stride ``s`` (pixels, >= 1) for which every ``s``-th pixel of every
    ``s``-th row of an image of ``image_size`` (W, H) are at most ``max_points``, i.e.
    ``ceil(W / s) * ceil(H / s) <= max_points`` (176 x 144 and 6400: 2, 6336 pixels)."""
    w, h = image_size
    if max_points < 1:
        raise ValueError(f"max_points: expected at least 1, got {max_points}")
    s = 1
    while -(-w // s) * -(-h // s) > max_points:
        s += 1
    return s


def decimate_cloud(
    points: np.ndarray, colors: np.ndarray, tof: Sensor, stride: int
) -> tuple[np.ndarray, np.ndarray]:
    """The points of the TOF pixels in every ``stride``-th column of every ``stride``-th
    row (columns and rows 0, s, 2s, ...), and their colours.

    Args:
        points: (N, 3) float metres in the TOF's frame, one per valid TOF pixel (the
            invalid ones left out, so the grid position is recovered by projecting each
            point back through ``tof``'s intrinsics: it lands on its pixel's centre).
        colors: (N, 3) uint8 RGB, one per point.
        tof: the TOF sensor the points were measured with.
        stride: keep one pixel in ``stride`` in each direction (1: all).
    Returns:
        (M, 3) points and (M, 3) colours, M <= ``ceil(W / stride) * ceil(H / stride)``,
        in their order in ``points``.
    """
    if stride <= 1 or len(points) == 0:
        return points, colors
    uv = tof.intrinsics.project(np.asarray(points, dtype=np.float64))
    with np.errstate(invalid="ignore"):
        col = np.rint(uv[:, 0])
        row = np.rint(uv[:, 1])
        keep = (np.fmod(col, stride) == 0) & (np.fmod(row, stride) == 0)
    return points[keep], colors[keep]
