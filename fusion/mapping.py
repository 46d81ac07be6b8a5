"""Parallax-free mapping between two sensors of the rig through TOF depth (the method's
data fusion, section 4): for every pixel of a *target* sensor (e.g. a colour camera), the
pixel of a *source* sensor (e.g. a thermal imager) that sees the same 3D point.

On each new TOF frame (:meth:`ViewMapping.update`):

1. the TOF points (method Eq. 1-3) are projected into the target sensor and splatted into a
   z-buffer at ``1/scale`` of its resolution (the TOF has ~8x fewer pixels per degree than a
   colour camera: the coarse grid matches what the depth can resolve); small holes are
   filled from neighbours, the rest gets a fallback depth and is marked;
2. for each coarse cell, the 3D point (the cell's depth along each pixel's own ray) is
   projected into the source sensor (Eq. 4), and the source's own z-buffer decides whether
   the source sees that point or something in front of it (occlusion);
3. the coarse map is brought to full resolution: bilinear inside surfaces, nearest at depth
   edges (so foreground and background never blend).

The TOF's rays are computed once (:class:`TofGrid`) and shared by every mapping fed the same
TOF frames; a frame's points are computed once too (:meth:`TofGrid.points`) and handed to
each mapping (:meth:`ViewMapping.update_points`), as :class:`fusion.stereo.StereoFusion` does.

Per frame, :meth:`ViewMapping.warp` is one ``cv2.remap`` of the source image into the
target's pixels; invisible pixels come out NaN (or a given fill value), never the
occluder's value.

Frames: ``T_dst_src`` 4x4; depth ``z`` along the target's optical axis, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.calib.camera import pixel_grid
from trifuse.calib.rig import Rig, Sensor
from trifuse.fusion.geometry import tof_rays, tof_sensor_name


@dataclass(frozen=True)
class MappingOptions:
    """Settings of a :class:`ViewMapping`.

    Attributes:
        scale: the target's z-buffer is ``1/scale`` of its resolution (>= 1).
        fallback_depth_m: depth used where the TOF has none; None = the median depth of
            the current TOF frame (the scene's typical distance), else 3 m.
        occlusion_rel: a source pixel whose z-buffer is nearer than the point by more than
            ``occlusion_rel * z + occlusion_abs_m`` is occluding it.
        occlusion_abs_m: see ``occlusion_rel``.
        edge_rel: neighbouring coarse depths differing by more than this fraction form a
            depth edge (nearest-neighbour upsampling there).
        fill_iterations: 3x3 passes that fill z-buffer holes from valid neighbours.
        smooth_middle: on smooth surfaces (neighbouring depths within ``edge_rel``) a
            z-buffer cell takes the middle of its neighbourhood's depths, not the nearest
            (:meth:`DepthView.render`): no bias towards the camera on slanted surfaces. Off
            for the fusion, whose registration sigma models the nearest
            (:mod:`fusion.registration`); on for the drift check (:mod:`fusion.drift_align`).
    """

    scale: int = 4
    fallback_depth_m: float | None = None
    occlusion_rel: float = 0.03
    occlusion_abs_m: float = 0.05
    edge_rel: float = 0.05
    fill_iterations: int = 2
    smooth_middle: bool = False


def splat_radius(spacing: float) -> int:
    """Cells around its own that a TOF point covers in a z-buffer whose cells are
    ``spacing`` to a TOF pixel (the ratio of angular resolutions): enough to close the gaps."""
    return max(0, int(np.ceil(spacing / 2.0 - 0.25)))


class DepthView:
    """A z-buffer of TOF points in one sensor, at ``1/scale`` of its resolution."""

    def __init__(
        self, rig: Rig, sensor: str, tof: str, scale: int, smooth_rel: float | None = None
    ) -> None:
        if scale < 1:
            raise ValueError(f"scale: expected an integer >= 1, got {scale}")
        self.smooth_rel = smooth_rel
        self.sensor: Sensor = rig[sensor]
        self.scale = scale
        w, h = self.sensor.image_size
        self.shape = (-(-h // scale), -(-w // scale))
        self.T_sensor_tof = rig.T(sensor, tof).astype(np.float32)
        tof_s = rig[tof]
        # Footprint of one TOF pixel in coarse cells: ratio of angular resolutions.
        self.radius = splat_radius((self.sensor.intrinsics.fx / scale) / tof_s.intrinsics.fx)
        self.z = np.full(self.shape, np.inf, dtype=np.float32)
        r = self.radius
        self._padded = np.empty((self.shape[0] + 2 * r, self.shape[1] + 2 * r), np.float32)
        if smooth_rel is not None:
            self._near = np.empty_like(self._padded)
            self._far = np.empty_like(self._padded)
        self._footprint = np.ones((2 * r + 1, 2 * r + 1), np.uint8)

    def render(self, points_tof: np.ndarray) -> np.ndarray:
        """Splat valid TOF points (N, 3) into the z-buffer; returns it (inf = empty).

        Each point covers the cells within ``radius`` of its own; a cell keeps the nearest
        depth covering it. Done as the nearest depth per cell (on a grid padded by
        ``radius``, so points just outside still cover the border) followed by a minimum
        over each cell's ``(2 radius + 1)^2`` neighbours (``cv2.erode``): the same minimum.
        With ``smooth_rel`` (None: off), where those neighbours are all filled and lie within
        ``smooth_rel`` of one another (a smooth surface, no depth edge), the cell takes the
        middle of their range instead: on a slanted surface the minimum is nearer than the
        surface by the slope times the radius (a board at 45 degrees 0.6 m away read 0.7 %
        near, and a stereo pair 120 mm apart saw a 0.1 degree turn that was not there); the
        middle of a plane's range is the plane itself.
        """
        R, t = self.T_sensor_tof[:3, :3], self.T_sensor_tof[:3, 3]
        P = points_tof @ R.T + t
        z = P[:, 2]
        front = z > 0.05
        # NaN on or behind the image plane and beyond the fold of the distortion (a point
        # there would land on a wrong pixel inside the image): not splatted
        uv = self.sensor.intrinsics.project(P[front]).astype(np.float32)
        seen = np.isfinite(uv).all(axis=1)
        uv, z = uv[seen], z[front][seen]
        s = self.scale
        cu = np.floor((uv[:, 0] + 0.5) / s).astype(np.int32)
        cv = np.floor((uv[:, 1] + 0.5) / s).astype(np.int32)
        hc, wc = self.shape
        r = self.radius
        pad = self._padded
        pad.fill(np.inf)
        ok = (cu >= -r) & (cu < wc + r) & (cv >= -r) & (cv < hc + r)
        np.minimum.at(pad.ravel(), (cv[ok] + r) * (wc + 2 * r) + (cu[ok] + r), z[ok])
        if r and self.smooth_rel is None:
            cv2.erode(pad, self._footprint, dst=pad)
        elif r:
            near, far = self._near, self._far
            cv2.erode(pad, self._footprint, dst=near)
            np.copyto(far, pad)
            far[far == np.inf] = np.float32(1e9)  # an empty neighbour: not smooth
            cv2.dilate(far, self._footprint, dst=far)
            smooth = far - near <= self.smooth_rel * near
            np.add(near, far, out=far)
            far *= np.float32(0.5)
            np.copyto(near, far, where=smooth)
            pad = near
        np.copyto(self.z, pad[r : r + hc, r : r + wc])
        return self.z


class TofGrid:
    """A rig's TOF sensor and the unit ray of each of its pixels: computed once, shared by
    every mapping fed the same TOF frames (both eyes, both directions).

    Attributes:
        tof: the TOF sensor's name (default the rig's only sensor of modality "tof").
        rays: (H, W, 3) float32 unit rays through the TOF's pixel centres, TOF frame
            (:func:`fusion.geometry.tof_rays`).
    """

    def __init__(self, rig: Rig, tof: str | None = None) -> None:
        self.tof = tof_sensor_name(rig, tof)
        s = rig[self.tof]
        self.rays = tof_rays(s.intrinsics, *s.image_size).astype(np.float32)

    def points(
        self, distance_m: np.ndarray, edge_rel: float, max_range_m: float = 10.0
    ) -> np.ndarray:
        """Valid TOF points (N, 3) float32 in the TOF frame, metres.

        Args:
            distance_m: (H, W) radial distances of the TOF, metres, NaN invalid.
            edge_rel: a pixel between two neighbours differing from it by more than this
                fraction is a flying pixel (:func:`mixed_pixels`) and left out.
            max_range_m: farther distances are left out (as are those <= 0.1 m).
        """
        d = np.asarray(distance_m, dtype=np.float32)
        if d.shape != self.rays.shape[:2]:
            raise ValueError(
                f"distance_m: expected shape {self.rays.shape[:2]} (the TOF image), got {d.shape}"
            )
        ok = np.isfinite(d) & (d > 0.1) & (d <= max_range_m)
        ok &= ~mixed_pixels(d, edge_rel)
        return self.rays[ok] * d[ok, None]


class ViewMapping:
    """Where each pixel of ``target`` finds the same 3D point in ``source``.

    Attributes after :meth:`update` (all (H, W) at the target's full resolution):
        map_x, map_y: float32 source pixel coordinates (-1e4 where not visible);
        fallback: bool, depth came from the fallback distance (no TOF depth);
    and, computed on request, ``depth_m`` and ``visible`` (properties).
    """

    def __init__(
        self,
        rig: Rig,
        target: str,
        source: str,
        tof: str | None = None,
        options: MappingOptions | None = None,
        grid: TofGrid | None = None,
    ) -> None:
        """``grid``: the TOF's rays, shared with the other mappings of the same TOF frames
        (built from ``tof`` if None; if both are given, they must name the same sensor)."""
        self.options = options or MappingOptions()
        if grid is None:
            grid = TofGrid(rig, tof)
        elif tof is not None and tof != grid.tof:
            raise ValueError(f"tof: {tof!r} is not the grid's TOF sensor {grid.tof!r}")
        self.grid = grid
        self.tof = grid.tof
        self.target, self.source = rig[target], rig[source]
        s = self.options.scale
        smooth = self.options.edge_rel if self.options.smooth_middle else None
        self.target_depth = DepthView(rig, target, self.tof, s, smooth)
        # The source's z-buffer decides occlusion; its cells as fine as a target cell.
        src_scale = max(1, round(s * self.source.intrinsics.fx / self.target.intrinsics.fx))
        self.source_depth = DepthView(rig, source, self.tof, src_scale, smooth)
        w, h = self.target.image_size
        hc, wc = self.target_depth.shape
        # Rays of the coarse cells' centre pixels, rotated into the source frame.
        centres = pixel_grid(wc, hc) * s + (s - 1) / 2.0
        xy = self.target.intrinsics.normalized(centres)
        rays = np.concatenate([xy, np.ones((hc, wc, 1))], axis=-1)
        T_src_tgt = rig.T(source, target)
        self.rays_src = (rays @ T_src_tgt[:3, :3].T).astype(np.float32)
        self.t_src_tgt = T_src_tgt[:3, 3].astype(np.float32)
        self.size = (w, h)
        self.map_x = np.empty((h, w), np.float32)
        self.map_y = np.empty((h, w), np.float32)
        self._near_x = np.empty((h, w), np.float32)
        self._near_y = np.empty((h, w), np.float32)
        self._edge_full = np.empty((h, w), np.uint8)
        self.fallback = np.zeros((h, w), bool)
        self.ready = False

    # -- per TOF frame --------------------------------------------------------------------

    def points(self, distance_m: np.ndarray, max_range_m: float = 10.0) -> np.ndarray:
        """Valid TOF points (N, 3) float32 in the TOF frame, metres, from a distance image
        (:meth:`TofGrid.points` with this mapping's ``edge_rel``)."""
        return self.grid.points(distance_m, self.options.edge_rel, max_range_m)

    def update(self, distance_m: np.ndarray) -> None:
        """Recompute the mapping from a TOF radial distance image (H, W) metres, NaN invalid."""
        self.update_points(self.points(distance_m))

    def update_points(self, points_tof: np.ndarray) -> None:
        """Recompute the mapping from valid TOF points (N, 3), TOF frame, metres."""
        opts = self.options
        z = self.target_depth.render(points_tof).copy()
        _fill_holes(z, opts.fill_iterations)
        missing = ~np.isfinite(z)
        valid_z = z[~missing]
        if opts.fallback_depth_m is not None:
            fallback = opts.fallback_depth_m
        else:
            fallback = float(np.median(valid_z)) if valid_z.size else 3.0
        z[missing] = fallback

        # Coarse 3D points in the source frame, their source pixels, occlusion.
        Q = self.rays_src * z[..., None] + self.t_src_tgt
        uv = self.source.intrinsics.project(Q).astype(np.float32)
        src_z = self.source_depth.render(points_tof)
        _fill_holes(src_z, opts.fill_iterations)
        w, h = self.source.image_size
        s2 = self.source_depth.scale
        inside = (
            (uv[..., 0] >= -0.5)
            & (uv[..., 0] < w - 0.5)
            & (uv[..., 1] >= -0.5)
            & (uv[..., 1] < h - 0.5)
        )
        iu = np.clip(
            np.floor((np.nan_to_num(uv[..., 0]) + 0.5) / s2), 0, src_z.shape[1] - 1
        ).astype(np.int32)
        iv = np.clip(
            np.floor((np.nan_to_num(uv[..., 1]) + 0.5) / s2), 0, src_z.shape[0] - 1
        ).astype(np.int32)
        nearest = src_z[iv, iu]
        occluded = nearest < Q[..., 2] * (1 - opts.occlusion_rel) - opts.occlusion_abs_m
        visible = inside & ~occluded
        coarse_x = np.where(visible, uv[..., 0], -1e4).astype(np.float32)
        coarse_y = np.where(visible, uv[..., 1], -1e4).astype(np.float32)

        # Depth edges: neighbouring cells differing by more than edge_rel.
        edge = np.zeros(z.shape, np.uint8)
        dz_h = np.abs(np.diff(z, axis=1)) > opts.edge_rel * np.minimum(z[:, 1:], z[:, :-1])
        dz_v = np.abs(np.diff(z, axis=0)) > opts.edge_rel * np.minimum(z[1:], z[:-1])
        edge[:, 1:] |= dz_h
        edge[:, :-1] |= dz_h
        edge[1:] |= dz_v
        edge[:-1] |= dz_v
        edge |= ~visible  # never interpolate towards an invisible cell

        self._upsample(coarse_x, coarse_y, edge, z, missing, visible)
        self.ready = True

    def _upsample(
        self,
        cx: np.ndarray,
        cy: np.ndarray,
        edge: np.ndarray,
        z: np.ndarray,
        missing: np.ndarray,
        visible: np.ndarray,
    ) -> None:
        """Coarse maps and masks to full resolution (bilinear, nearest at edges)."""
        w, h = self.size
        # cv2.resize samples the coarse grid at (x + 0.5) / s - 0.5: the cells' centres
        # (exactly so when the image size is a multiple of the scale, as 1280 x 960 is).
        cv2.resize(cx, (w, h), dst=self.map_x, interpolation=cv2.INTER_LINEAR)
        cv2.resize(cy, (w, h), dst=self.map_y, interpolation=cv2.INTER_LINEAR)
        near = cv2.INTER_NEAREST
        cv2.resize(cx, (w, h), dst=self._near_x, interpolation=near)
        cv2.resize(cy, (w, h), dst=self._near_y, interpolation=near)
        cv2.resize(
            cv2.dilate(edge, np.ones((3, 3), np.uint8)),
            (w, h),
            dst=self._edge_full,
            interpolation=near,
        )
        cv2.copyTo(self._near_x, self._edge_full, self.map_x)  # nearest on the edges
        cv2.copyTo(self._near_y, self._edge_full, self.map_y)
        cv2.resize(
            missing.view(np.uint8), (w, h), dst=self.fallback.view(np.uint8), interpolation=near
        )
        self._coarse_z, self._coarse_visible, self._coarse_missing = z, visible, missing
        self._coarse_x, self._coarse_y = cx, cy

    def coarse_depth(self) -> tuple[np.ndarray, np.ndarray]:
        """The coarse cells behind the mapping, (hc, wc) each: z float32 metres along the
        target's axis (fallback included) and bool, the depth is the fallback; new arrays
        at each update, never written afterwards. :attr:`depth_m` and :attr:`fallback` are
        them brought to full resolution (``cv2.INTER_NEAREST``)."""
        return self._coarse_z, self._coarse_missing

    def coarse_cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The coarse cells' depth z (hc, wc) float32 metres along the target's axis, whether
        it is the TOF's and the source sees its point (hc, wc) bool, and the source pixel
        (hc, wc, 2) float32 of each cell's centre (-1e4 where not seen); cell (i, j) is
        centred on target pixel ``(j s + (s - 1) / 2, i s + (s - 1) / 2)``, s the scale.
        New arrays at each update, never written afterwards."""
        ok = self._coarse_visible & ~self._coarse_missing
        return self._coarse_z, ok, np.stack([self._coarse_x, self._coarse_y], axis=-1)

    @property
    def depth_m(self) -> np.ndarray:
        """(H, W) float32 depth of each target pixel, metres (fallback included)."""
        return cv2.resize(self._coarse_z, self.size, interpolation=cv2.INTER_NEAREST)

    @property
    def visible(self) -> np.ndarray:
        """(H, W) bool: the source sees the point (inside its image, not occluded)."""
        v = self._coarse_visible.view(np.uint8)
        return cv2.resize(v, self.size, interpolation=cv2.INTER_NEAREST).view(bool)

    # -- per frame ------------------------------------------------------------------------

    def warp(
        self, source_image: np.ndarray, out: np.ndarray | None = None, fill: float = np.nan
    ) -> np.ndarray:
        """The source image resampled at the target's pixels (bilinear); ``fill`` where the
        source does not see the point. Needs :meth:`update` first."""
        if not self.ready:
            raise RuntimeError("ViewMapping.warp: no TOF frame yet (call update first)")
        w, h = self.source.image_size
        if source_image.shape[:2] != (h, w):
            raise ValueError(
                f"source image: expected {w}x{h} ({self.source.name}), got "
                f"{source_image.shape[1]}x{source_image.shape[0]}"
            )
        border = fill if source_image.ndim == 2 else (fill,) * source_image.shape[2]
        return cv2.remap(
            source_image,
            self.map_x,
            self.map_y,
            cv2.INTER_LINEAR,
            dst=out,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=border,
        )


def mixed_pixels(distance_m: np.ndarray, rel: float) -> np.ndarray:
    """TOF "flying pixels": (H, W) bool where a pixel's distance lies strictly between two
    neighbours' that differ from it by more than ``rel`` of it (a pixel straddling a depth
    edge averages the two surfaces and belongs to neither)."""
    d = np.where(np.isfinite(distance_m), distance_m, np.nan).astype(np.float32)
    pad = np.pad(d, 1, mode="edge")
    nb = np.stack([pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]])
    t = rel * d
    with np.errstate(invalid="ignore"):
        nearer = np.any(nb < d - t, axis=0)
        farther = np.any(nb > d + t, axis=0)
    return nearer & farther


def _fill_holes(z: np.ndarray, iterations: int) -> None:
    """Fill empty (inf) cells next to valid ones with the farthest depth around them, in
    place. Gaps between splats vanish; next to a depth edge an empty cell is background the
    TOF could not see (disocclusion), so the far side is the right guess. Large holes stay.
    """
    kernel = np.ones((3, 3), np.uint8)
    work = np.empty_like(z)
    for _ in range(iterations):
        empty = ~np.isfinite(z)
        if not empty.any():
            return
        np.copyto(work, z)
        work[empty] = 0.0
        grown = cv2.dilate(work, kernel, borderType=cv2.BORDER_REPLICATE)
        np.copyto(z, grown, where=empty & (grown > 0))


class EyeFusion:
    """Thermal onto colour for one eye of the rig, and colour onto thermal on request.

    Attributes:
        forward: the colour camera's pixels <- the thermal imager's (target colour, source
            thermal), what the picture is composed from.
        grid: the TOF rays it shares with the other mappings of the same TOF frames.
    """

    def __init__(
        self,
        rig: Rig,
        eye: str,
        options: MappingOptions | None = None,
        grid: TofGrid | None = None,
    ) -> None:
        if eye not in rig.eyes:
            raise KeyError(f"no eye {eye!r} in the rig (eyes: {sorted(rig.eyes)})")
        self.rig = rig
        self.eye = rig.eyes[eye]
        self.options = options or MappingOptions()
        self.grid = grid if grid is not None else TofGrid(rig)
        self.forward = ViewMapping(
            rig, self.eye.color, self.eye.thermal, options=self.options, grid=self.grid
        )
        self._reverse: ViewMapping | None = None

    @property
    def reverse(self) -> ViewMapping:
        """The thermal imager's pixels <- the colour camera's (target thermal, source
        colour, z-buffer at full resolution), built on first use; the caller updates it
        (:meth:`ViewMapping.update_points`), it does not follow :attr:`forward`."""
        if self._reverse is None:
            opts = self.options
            rev = MappingOptions(
                scale=1,
                fallback_depth_m=opts.fallback_depth_m,
                occlusion_rel=opts.occlusion_rel,
                occlusion_abs_m=opts.occlusion_abs_m,
                edge_rel=opts.edge_rel,
            )
            self._reverse = ViewMapping(
                self.rig, self.eye.thermal, self.eye.color, options=rev, grid=self.grid
            )
        return self._reverse
