"""How accurate a fused mapping is, against the exact mapping of a simulated scene.

The simulator knows, for every pixel of every sensor, the exact distance along the
pixel's ray to the surface it sees. From the target sensor's exact ranges the exact 3D
point of each target pixel follows, hence the exact source pixel; the source's exact ranges
say whether the source sees that point or something in front of it. A mapping under test
(TOF-based fusion, or a fixed homography) is compared with that, per distance band, away
from depth edges (where a pixel mixes two surfaces and no single answer is right).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from trifuse.calib.camera import Intrinsics, pixel_grid
from trifuse.calib.rig import Rig

BANDS_M: tuple[tuple[float, float], ...] = ((0.5, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0))


@lru_cache(maxsize=4)
def _pixel_xy(intrinsics: Intrinsics, width: int, height: int) -> np.ndarray:
    """(H, W, 2) undistorted normalised coordinates of every pixel centre (read-only;
    kept: a colour camera's take about 1 s, and a comparison asks for them per frame)."""
    xy = intrinsics.normalized(pixel_grid(width, height))
    xy.flags.writeable = False
    return xy


@dataclass
class ExactMapping:
    """Exact source pixel (H, W, 2) of each target pixel, the target pixels' depth (H, W)
    along the optical axis in metres, which points the source sees (H, W) bool, and which
    lie inside the TOF's field of view (H, W) bool: only those can be fused at all (a near
    object at the outer edge of a colour image can be outside the TOF's view)."""

    source_xy: np.ndarray
    depth_m: np.ndarray
    visible: np.ndarray
    in_tof_view: np.ndarray


def exact_mapping(
    rig: Rig,
    target: str,
    source: str,
    target_range_m: np.ndarray,
    source_range_m: np.ndarray,
    tof: str = "tof",
    tolerance_m: float = 0.01,
) -> ExactMapping:
    """The true mapping from ground-truth ranges (radial, metres, NaN = nothing seen)."""
    tgt, src = rig[target], rig[source]
    w, h = tgt.image_size
    xy = _pixel_xy(tgt.intrinsics, w, h)
    rays = np.concatenate([xy, np.ones((h, w, 1))], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)  # unit rays, as unproject gives
    P = rays * target_range_m[..., None]
    T = rig.T(source, target)
    Q = P @ T[:3, :3].T + T[:3, 3]
    xy = src.intrinsics.project(Q)
    sw, sh = src.image_size
    iu = np.clip(np.round(np.nan_to_num(xy[..., 0], nan=-1)), 0, sw - 1).astype(int)
    iv = np.clip(np.round(np.nan_to_num(xy[..., 1], nan=-1)), 0, sh - 1).astype(int)
    inside = (
        (xy[..., 0] >= -0.5)
        & (xy[..., 0] < sw - 0.5)
        & (xy[..., 1] >= -0.5)
        & (xy[..., 1] < sh - 0.5)
    )
    seen = source_range_m[iv, iu]
    visible = inside & (seen > np.linalg.norm(Q, axis=-1) * 0.99 - tolerance_m)
    T_tof = rig.T(tof, target)
    tof_xy = rig[tof].intrinsics.project(P @ T_tof[:3, :3].T + T_tof[:3, 3])
    tw, th = rig[tof].image_size
    in_tof = (
        (tof_xy[..., 0] >= 0)
        & (tof_xy[..., 0] <= tw - 1)
        & (tof_xy[..., 1] >= 0)
        & (tof_xy[..., 1] <= th - 1)
    )
    return ExactMapping(xy, P[..., 2], visible, in_tof)


def depth_edges(depth_m: np.ndarray, margin_px: int, rel: float = 0.03) -> np.ndarray:
    """Pixels within ``margin_px`` of a depth discontinuity (relative jump > ``rel``)."""
    d = np.nan_to_num(depth_m, nan=1e6)
    e = np.zeros(d.shape, np.uint8)
    jh = np.abs(np.diff(d, axis=1)) > rel * np.minimum(d[:, 1:], d[:, :-1])
    jv = np.abs(np.diff(d, axis=0)) > rel * np.minimum(d[1:], d[:-1])
    e[:, 1:] |= jh
    e[:, :-1] |= jh
    e[1:] |= jv
    e[:-1] |= jv
    k = 2 * margin_px + 1
    return cv2.dilate(e, np.ones((k, k), np.uint8)).astype(bool)


@dataclass
class BandError:
    """Mapping error in source pixels over the pixels of one distance band."""

    band_m: tuple[float, float]
    pixels: int
    median_px: float
    p95_px: float
    rms_px: float


def band_errors(
    map_xy: np.ndarray,
    exact: ExactMapping,
    mask: np.ndarray,
    bands: tuple[tuple[float, float], ...] = BANDS_M,
) -> list[BandError]:
    """Per band: |mapped - exact| (source pixels) over ``mask`` and the pixels that are
    exactly visible to the source and inside the TOF's view."""
    err = np.linalg.norm(map_xy - exact.source_xy, axis=-1)
    out = []
    for lo, hi in bands:
        sel = mask & exact.visible & exact.in_tof_view
        sel &= (exact.depth_m >= lo) & (exact.depth_m < hi)
        sel &= np.isfinite(err)
        e = err[sel]
        if e.size:
            out.append(
                BandError(
                    (lo, hi),
                    int(e.size),
                    float(np.median(e)),
                    float(np.percentile(e, 95)),
                    float(np.sqrt(np.mean(e**2))),
                )
            )
        else:
            out.append(BandError((lo, hi), 0, float("nan"), float("nan"), float("nan")))
    return out


def fixed_depth_mapping(rig: Rig, target: str, source: str, depth_m: float) -> np.ndarray:
    """The naive fusion: every target pixel assumed at one distance (a plane at
    ``depth_m``, fronto-parallel to the target: one homography, here with each lens's
    distortion handled exactly, which favours the baseline). (H, W, 2) source pixels."""
    tgt, src = rig[target], rig[source]
    w, h = tgt.image_size
    xy = _pixel_xy(tgt.intrinsics, w, h)
    P = np.concatenate([xy * depth_m, np.full((h, w, 1), depth_m)], axis=-1)
    T = rig.T(source, target)
    return src.intrinsics.project(P @ T[:3, :3].T + T[:3, 3])
