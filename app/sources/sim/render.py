"""Ray-casting renderer of the simulated head: colour, thermal and TOF images.

Each sensor's pixel rays (with lens distortion) are cast into the scene in numpy, each
solid only within its screen box (its hull's projection). Pixels on silhouettes and
pattern edges are supersampled (n x n sub-rays) so edges are anti-aliased the way a real
sensor integrates light over its pixel, and TOF pixels on depth edges become mixed pixels
(the live quality, for the console and recordings, skips this in colour and thermal).
Then each modality's physics:

* colour: Lambert shading, vignetting, shot and read noise, gamma, uint8 RGB;
* thermal: emitted plus reflected radiance (``eps T^4 + (1 - eps) T_amb^4``) averaged over
  the pixel, optics blur, per-imager gain/offset, NETD noise, float32 kelvin;
* TOF: radial distance and amplitude (``rho cos(theta) / d^2``), the systematic range
  error of :mod:`tof_error`, noise growing as the amplitude falls, NaN where the true
  distance is beyond range or the amplitude too low.

Ground truth comes with every image: the exact radial distance along each pixel-centre
ray and the index of the solid it hits.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.scene import Scene, apply_affine
from trifuse.app.sources.sim.tof_error import RangeErrorModel
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig, Sensor

if TYPE_CHECKING:
    from trifuse.app.sources.sim.thermal_conditions import ImagerThermal

_CHUNK = 1 << 20  # samples traced at once in the supersampling pass


@dataclass
class HeadModel:
    """Sensor physics of the simulated head (everything but geometry, which is the rig)."""

    color_exposure: float = 1.0
    color_read_noise: float = 0.004  # linear units (1.0 = full scale)
    color_shot_noise: float = 0.0004  # variance per unit signal
    thermal_netd_k: float = 0.08
    thermal_blur_sigma_px: float = 0.7
    thermal_offset_k: dict[str, float] = field(
        default_factory=lambda: {"thermal_left": 0.75, "thermal_right": -0.75}
    )
    thermal_gain: dict[str, float] = field(default_factory=dict)
    tof_amplitude_scale: float = 20000.0
    tof_min_amplitude: float = 60.0
    tof_max_range_m: float = 10.0
    tof_noise_m: float = 0.0015  # 1-sigma at amplitude tof_noise_ref
    tof_noise_ref: float = 10000.0
    range_error: RangeErrorModel = field(default_factory=RangeErrorModel)
    supersample: dict[str, int] = field(
        default_factory=lambda: {"color": 6, "thermal": 8, "tof": 4}
    )
    thermal_imager: ImagerThermal | None = None
    """Vignetting/narcissus, fixed-pattern stripes, raw counts
    (app.sources.sim.thermal_conditions); None: off."""


@dataclass
class SensorTruth:
    """Exact per-pixel ground truth of one rendered image.

    Attributes:
        range_m: (H, W) float32 radial distance along the pixel-centre ray, NaN on a miss.
        solid: (H, W) int16 index of the hit solid in ``scene.solids``, -1 on a miss.
    """

    range_m: np.ndarray
    solid: np.ndarray


class _RayGrid:
    """Cached rays of one sensor: unit directions at pixel centres, camera frame.

    ``margin`` extra pixels on every side extend the image beyond the sensor's own (a
    live render that is warped to a nearby head pose later needs them): pixel (0, 0) of
    the grid is the sensor's pixel (-margin, -margin). ``coarse``: undistort a large
    image's rays exactly on a coarse grid only (:data:`COARSE_STEP_PX`), for live renders.
    """

    def __init__(self, sensor: Sensor, margin: int = 0, coarse: bool = False) -> None:
        w, h = sensor.image_size
        w, h = w + 2 * margin, h + 2 * margin
        intr = sensor.intrinsics
        us = np.arange(-1 - margin, w + 1 - margin, dtype=np.float64)
        vs = np.arange(-1 - margin, h + 1 - margin, dtype=np.float64)
        # Normalised undistorted coordinates with a one-pixel margin (for interpolation).
        if coarse and w * h >= _COARSE_MIN_PIXELS:
            self.xy = _coarse_normalized(intr, us, vs)
        else:
            u, v = np.meshgrid(us, vs)
            self.xy = intr.normalized(np.stack([u, v], axis=-1)).astype(np.float32)
        if np.isnan(self.xy).any():
            raise ValueError(
                f"sensor {sensor.name!r}: distortion is not invertible inside the "
                + ("image" if not margin else f"image and a margin of {margin} px")
                + "; cannot render it"
            )
        xy = self.xy[1:-1, 1:-1]
        d = np.empty((h, w, 3), dtype=np.float32)
        d[..., :2] = xy
        d[..., 2] = 1.0
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        self.dirs = d
        self.width, self.height = w, h
        # Per pixel column (row): the range of normalised x (y) its rays and sub-rays (up
        # to half a pixel away) cover; the screen box of a solid follows from these.
        x, y = self.xy[..., 0].astype(np.float64), self.xy[..., 1].astype(np.float64)
        cmin, cmax = x.min(axis=0), x.max(axis=0)  # (w + 2,) grid columns -1 .. w
        rmin, rmax = y.min(axis=1), y.max(axis=1)
        self.col_x = (
            np.minimum(np.minimum(cmin[:-2], cmin[1:-1]), cmin[2:]),
            np.maximum(np.maximum(cmax[:-2], cmax[1:-1]), cmax[2:]),
        )
        self.row_y = (
            np.minimum(np.minimum(rmin[:-2], rmin[1:-1]), rmin[2:]),
            np.maximum(np.maximum(rmax[:-2], rmax[1:-1]), rmax[2:]),
        )
        for a in (self.xy, self.dirs, *self.col_x, *self.row_y):
            a.flags.writeable = False  # shared by every renderer of this camera

    def sub_dirs(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit directions (N, 3) at fractional pixel positions (bilinear in xy)."""
        n = len(u)
        rows = -(-n // 1024)  # remap wants maps under 32767 rows: lay them out 1024 wide
        maps = np.zeros((2, rows * 1024), dtype=np.float32)
        maps[0, :n] = u + 1.0
        maps[1, :n] = v + 1.0
        xy = cv2.remap(
            self.xy,
            maps[0].reshape(rows, 1024),
            maps[1].reshape(rows, 1024),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(-1, 2)[:n]
        d = np.empty((len(xy), 3), dtype=np.float32)
        d[:, :2] = xy
        d[:, 2] = 1.0
        d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        return d


GRIDS_KEPT = 8
"""Ray grids kept for the process (a colour camera's takes about 1 s to build and 25 MB):
renderers of cameras with the same intrinsics, image size, margin and quality share one."""
_grids: OrderedDict[tuple, _RayGrid] = OrderedDict()
_grids_lock = threading.Lock()


def _ray_grid(sensor: Sensor, margin: int, coarse: bool) -> _RayGrid:
    """The (shared, read-only) ray grid of ``sensor`` with ``margin``, built once."""
    key = (sensor.intrinsics, tuple(sensor.image_size), margin, coarse)
    with _grids_lock:
        grid = _grids.get(key)
        if grid is not None:
            _grids.move_to_end(key)
            return grid
    grid = _RayGrid(sensor, margin, coarse)
    with _grids_lock:
        _grids[key] = grid
        while len(_grids) > GRIDS_KEPT:
            _grids.popitem(last=False)
    return grid


COARSE_STEP_PX = 8
"""Spacing of the pixels whose rays a live renderer undistorts exactly in an image of at
least 2^18 pixels, bilinear in between: 1/10 of the time of a colour camera's grid, rays
within 0.003 px of the exact ones (smaller images are cheap: all exact)."""
_COARSE_MIN_PIXELS = 1 << 18


def _coarse_normalized(intr: Intrinsics, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """(len(vs), len(us), 2) float32 undistorted normalised coordinates of the pixel grid
    ``us`` x ``vs``: exact every :data:`COARSE_STEP_PX` pixels and at the last ones,
    bilinear in between (NaN where the distortion is not invertible)."""
    # A uniform lattice (past the last pixel if need be): every pixel sits at a multiple
    # of 1/8 between two lattice points, which remap's 1/32-pixel positions hold exactly.
    cu = us[0] + COARSE_STEP_PX * np.arange(-(-(len(us) - 1) // COARSE_STEP_PX) + 1)
    cv = vs[0] + COARSE_STEP_PX * np.arange(-(-(len(vs) - 1) // COARSE_STEP_PX) + 1)
    xy = intr.normalized(np.stack(np.meshgrid(cu, cv), axis=-1)).astype(np.float32)
    if np.isnan(xy).any():  # not invertible just outside the image: undistort every pixel
        return intr.normalized(np.stack(np.meshgrid(us, vs), axis=-1)).astype(np.float32)
    map_u, map_v = np.meshgrid(
        ((us - us[0]) / COARSE_STEP_PX).astype(np.float32),
        ((vs - vs[0]) / COARSE_STEP_PX).astype(np.float32),
    )
    return cv2.remap(xy, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


_NEAR_M = 1e-4  # hull points are clipped to z >= this in front of the camera


def _screen_boxes(
    scene: Scene, grid: _RayGrid, T_sensor_world: np.ndarray
) -> list[tuple[int, int, int, int] | None]:
    """Per solid, the pixel rectangle (u0, u1, v0, v1) of ``grid`` its pixels (and their
    sub-rays) can hit, or None if it is not in view.

    Each solid's hull points (a convex polytope around it) are clipped to the half-space in
    front of the camera and projected to undistorted normalised coordinates; the solid's
    image lies in their bounding rectangle there, and the pixel columns and rows whose rays
    reach into that rectangle bound it in the image (exact with any lens distortion the
    ray grid can represent, since the grid's own undistorted rays decide).
    """
    w, h = grid.width, grid.height
    R, t = T_sensor_world[:3, :3], T_sensor_world[:3, 3]
    boxes: list[tuple[int, int, int, int] | None] = []
    for solid in scene.solids:
        P = solid.hull_points() @ R.T + t
        z = P[:, 2]
        front = z >= _NEAR_M
        if not front.any():
            boxes.append(None)
            continue
        pts = [P[front]]
        if not front.all():
            # Where the segments between points in front and points behind cross the
            # near plane: with the points in front, they span the clipped hull.
            a, b = P[front], P[~front]
            s = (_NEAR_M - a[:, None, 2]) / (b[None, :, 2] - a[:, None, 2])
            pts.append(
                (a[:, None, :] + s[..., None] * (b[None, :, :] - a[:, None, :])).reshape(-1, 3)
            )
        Q = np.concatenate(pts)
        x = Q[:, 0] / np.maximum(Q[:, 2], _NEAR_M)
        y = Q[:, 1] / np.maximum(Q[:, 2], _NEAR_M)
        x0, x1, y0, y1 = x.min(), x.max(), y.min(), y.max()
        cols = np.flatnonzero((grid.col_x[1] >= x0) & (grid.col_x[0] <= x1))
        rows = np.flatnonzero((grid.row_y[1] >= y0) & (grid.row_y[0] <= y1))
        if not len(cols) or not len(rows):
            boxes.append(None)
            continue
        boxes.append(
            (int(cols[0]), int(min(w, cols[-1] + 1)), int(rows[0]), int(min(h, rows[-1] + 1)))
        )
    return boxes


LIVE_SUPERSAMPLE = {"color": 1, "thermal": 1}
"""Sub-rays per pixel side in the live quality (1: none), by modality; others keep the
model's. The TOF keeps its 4 x 4: its mixed pixels on depth edges are a real artefact the
fusion must handle, and they cost 8 ms a frame; colour and thermal edges alias instead."""


@lru_cache(maxsize=16)
def vignetting(width: int, height: int, margin: int = 0) -> np.ndarray:
    """(H + 2 margin, W + 2 margin) float32 relative illumination of a colour camera's
    pixels, ``1 - 0.08 r^2`` (r = 1 at the middle of each image edge); read-only."""
    yy, xx = np.mgrid[-margin : height + margin, -margin : width + margin].astype(np.float32)
    r2 = ((xx - width / 2) / (width / 2)) ** 2 + ((yy - height / 2) / (height / 2)) ** 2
    out = 1 - 0.08 * r2
    out.flags.writeable = False
    return out


class Renderer:
    """Renders any subset of a rig's sensors from a scene, with ground truth.

    Args:
        rig: the head's sensors (geometry).
        model: the sensor physics (default :class:`HeadModel`).
        live: the live (demo) quality: no edge supersampling in colour and thermal
            (their edges alias; :data:`LIVE_SUPERSAMPLE`), shading in float32 and a colour
            camera's rays undistorted on a coarse grid: about 4x faster for a colour
            image; away from edges the values and the ground truth are those of the
            accurate quality (the default, for calibration captures and tests of
            accuracy). :mod:`app.sources.sim.live` gives such renders fresh noise per
            frame.
    """

    def __init__(self, rig: Rig, model: HeadModel | None = None, *, live: bool = False) -> None:
        self.rig = rig
        self.model = model or HeadModel()
        self.live = live
        self._grids: dict[tuple[str, int], _RayGrid] = {}

    def prepare(self, sensors: list[str] | None = None) -> None:
        """Build the ray grids of ``sensors`` (default: all) now; the first render of a
        sensor does it otherwise (about 1 s for an accurate colour camera)."""
        for name in sensors or self.rig.names:
            self._grid(name)

    def _grid(self, name: str, margin: int = 0) -> _RayGrid:
        key = (name, margin)
        if key not in self._grids:
            self._grids[key] = _ray_grid(self.rig[name], margin, self.live)
        return self._grids[key]

    # -- tracing ------------------------------------------------------------------------

    def _trace_grid(self, scene, origin, dirs, boxes):
        h, w = dirs.shape[:2]
        t_min = np.full((h, w), np.inf, dtype=np.float32)
        ids = np.full((h, w), -1, dtype=np.int16)
        for k, (solid, box) in enumerate(zip(scene.solids, boxes, strict=True)):
            if box is None:
                continue
            u0, u1, v0, v1 = box
            t = solid.intersect(origin, dirs[v0:v1, u0:u1])
            tm = t_min[v0:v1, u0:u1]
            closer = t < tm
            tm[closer] = t[closer]
            ids[v0:v1, u0:u1][closer] = k
        return t_min, ids

    def _trace_list(self, scene, origin, dirs, u, v, boxes, full):
        t_min = np.full(len(dirs), np.inf, dtype=np.float32)
        ids = np.full(len(dirs), -1, dtype=np.int16)
        for k, (solid, box) in enumerate(zip(scene.solids, boxes, strict=True)):
            if box is None:
                continue
            u0, u1, v0, v1 = box
            if box == full:
                t = solid.intersect(origin, dirs)
                closer = t < t_min
                t_min[closer] = t[closer]
                ids[closer] = k
                continue
            sel = np.flatnonzero((u >= u0 - 1) & (u < u1) & (v >= v0 - 1) & (v < v1))
            if not len(sel):
                continue
            t = solid.intersect(origin, dirs[sel])
            closer = t < t_min[sel]
            t_min[sel[closer]] = t[closer]
            ids[sel[closer]] = k
        return t_min, ids

    # -- shading: per-sample quantities of each modality ---------------------------------

    def _shade(
        self,
        scene: Scene,
        modality: str,
        origin: np.ndarray,
        dirs: np.ndarray,
        t: np.ndarray,
        ids: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-sample values (N, C) and edge keys (N,) for flat arrays of samples.

        Channels: colour linear RGB (3); thermal: the fourth power of the apparent
        temperature an ideal imager reads (1; :meth:`Scene.surface_apparent_k`: a proxy of
        radiance that the supersampling averages, exact away from edges);
        TOF amplitude-weighted distance and amplitude (2). float64, float32 when live.
        """
        dtype = np.float32 if self.live else np.float64
        n = len(t)
        channels = {"color": 3, "thermal": 1, "tof": 2}[modality]
        light = -np.asarray(scene.light_dir_world, dtype=np.float64)
        light /= np.linalg.norm(light)
        light = light.astype(dtype)
        o = origin.astype(dtype)
        # The samples sorted by solid (stably: index order within each solid), so that
        # each solid works on contiguous slices: one gather and one scatter in all.
        order = np.argsort(ids, kind="stable")
        starts = np.concatenate(
            ([0], np.cumsum(np.bincount(ids + 1, minlength=len(scene.solids) + 1)))
        )
        dirs_s = dirs[order].astype(dtype, copy=False)
        t_s = t[order].astype(dtype, copy=False)
        out_s = np.zeros((n, channels), dtype=dtype)
        keys_s = np.zeros(n, dtype=np.int32)
        if modality == "thermal":  # a miss sees the surroundings (a cold room, a sky)
            miss = (
                scene.ambient_k**4 * 0.9
                if scene.atmosphere is None
                else scene.miss_apparent_k() ** 4
            )
            out_s[: starts[1], 0] = miss
        for k, solid in enumerate(scene.solids):
            a, b = int(starts[k + 1]), int(starts[k + 2])
            if a == b:
                continue
            d = dirs_s[a:b]
            dist = t_s[a:b]
            p = o + dist[:, None] * d
            normals, st = solid.surface(p)
            cos = np.einsum("ij,ij->i", normals, d)
            normals[cos > 0] *= -1.0
            cos = np.abs(cos)
            mat = solid.material
            keys_s[a:b] = mat.edge_key(st)
            if modality == "color":
                lambert = np.clip(normals @ light, 0.0, None)
                out_s[a:b] = mat.albedo(st) * (0.35 + 0.75 * lambert)[:, None]
            elif modality == "thermal":
                eps, temp = mat.emissivity_at(st), mat.temperature(st)
                if scene.atmosphere is None:  # the proxy itself (Scene.surface_apparent_k)
                    out_s[a:b, 0] = eps * temp**4 + (1.0 - eps) * scene.ambient_k**4
                else:
                    out_s[a:b, 0] = scene.surface_apparent_k(eps, temp, dist) ** 4
            else:
                amp = (
                    self.model.tof_amplitude_scale
                    * mat.nir(st)
                    * cos
                    / np.maximum(dist * dist, 1e-6)
                )
                out_s[a:b, 0] = amp * dist
                out_s[a:b, 1] = amp
        out = np.empty_like(out_s)
        out[order] = out_s
        keys = ids.astype(np.int32) * 64
        if not self.live:  # the edge keys decide where to supersample
            keys[order] += keys_s
        return out, keys

    def render_raw(
        self, scene: Scene, name: str, T_world_sensor: np.ndarray, margin: int = 0
    ) -> tuple[np.ndarray, SensorTruth]:
        """Pixel-integrated scene values (H, W, C) of sensor ``name`` at ``T_world_sensor``
        (4, 4), before the sensor model, plus the exact truth (H, W).

        Channels as :meth:`_shade`. ``margin`` pixels more on every side (H + 2 margin, W +
        2 margin; the truth likewise). Edges are supersampled (when live, see
        :data:`LIVE_SUPERSAMPLE`).
        """
        sensor = self.rig[name]
        grid = self._grid(name, margin)
        h, w = grid.height, grid.width
        R = T_world_sensor[:3, :3]
        origin = T_world_sensor[:3, 3].astype(np.float64)
        T_sensor_world = np.linalg.inv(T_world_sensor)
        boxes = _screen_boxes(scene, grid, T_sensor_world)
        dirs = apply_affine(R, grid.dirs)
        t, ids = self._trace_grid(scene, origin, dirs, boxes)
        values, keys = self._shade(
            scene, sensor.modality, origin, dirs.reshape(-1, 3), t.ravel(), ids.ravel()
        )
        values = values.reshape(h, w, -1)
        truth = SensorTruth(
            range_m=np.where(np.isfinite(t), t, np.nan).astype(np.float32), solid=ids
        )
        ns = self.model.supersample[sensor.modality]
        if self.live:
            ns = LIVE_SUPERSAMPLE.get(sensor.modality, ns)
        if ns <= 1:
            return values, truth

        # Supersample pixels where the solid or the surface pattern changes.
        keys = keys.reshape(h, w)
        edge = np.zeros((h, w), dtype=bool)
        dh = keys[:, 1:] != keys[:, :-1]
        dv = keys[1:, :] != keys[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        ev, eu = np.nonzero(edge)
        if len(eu):
            offs = (np.arange(ns) + 0.5) / ns - 0.5
            ou, ov = (a.ravel() for a in np.meshgrid(offs, offs))
            per_chunk = max(1, _CHUNK // (ns * ns))
            for start in range(0, len(eu), per_chunk):
                pu = eu[start : start + per_chunk]
                pv = ev[start : start + per_chunk]
                su = (pu[:, None] + ou[None, :]).ravel()
                sv = (pv[:, None] + ov[None, :]).ravel()
                sd = apply_affine(R, grid.sub_dirs(su, sv))
                st_, sid = self._trace_list(scene, origin, sd, su, sv, boxes, (0, w, 0, h))
                sval, _ = self._shade(scene, sensor.modality, origin, sd, st_, sid)
                values[pv, pu] = sval.reshape(len(pu), ns * ns, -1).mean(axis=1)
        return values, truth

    # -- per-modality sensor models ------------------------------------------------------

    def _color(self, values: np.ndarray, sensor: Sensor, rng: np.random.Generator):
        m = self.model
        h, w = values.shape[:2]
        lin = values.astype(np.float32) * (m.color_exposure * vignetting(w, h))[..., None]
        sigma = np.sqrt(m.color_read_noise**2 + m.color_shot_noise * np.clip(lin, 0, None))
        lin += sigma * rng.standard_normal(lin.shape, dtype=np.float32)
        np.clip(lin, 0.0, 1.0, out=lin)
        return (255.0 * lin ** (1 / 2.2) + 0.5).astype(np.uint8)

    def _thermal(self, values: np.ndarray, sensor: Sensor, rng: np.random.Generator):
        m = self.model
        temp = np.power(values[..., 0], 0.25).astype(np.float32)
        if m.thermal_blur_sigma_px > 0:
            temp = cv2.GaussianBlur(
                temp, (0, 0), m.thermal_blur_sigma_px, borderType=cv2.BORDER_REPLICATE
            )
        gain = m.thermal_gain.get(sensor.name, 1.0)
        offset = m.thermal_offset_k.get(sensor.name, 0.0)
        temp = gain * temp + offset
        temp += m.thermal_netd_k * rng.standard_normal(temp.shape, dtype=np.float32)
        if m.thermal_imager is not None:
            return m.thermal_imager.apply(temp, sensor.name)
        return temp.astype(np.float32)

    def tof_readings(
        self, values: np.ndarray, range_m: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """The TOF's sensor model: amplitude and measured radial distance (H, W) float32
        (NaN where invalid) from raw ``values`` (H, W, 2) (:meth:`render_raw`) and the
        exact ``range_m`` (H, W) of the pixel-centre rays, with noise from ``rng``."""
        m = self.model
        amp = values[..., 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            dist = values[..., 0] / amp
        err = m.range_error.error_m(np.nan_to_num(dist), amp)
        sigma = m.tof_noise_m * np.sqrt(m.tof_noise_ref / np.maximum(amp, 1.0))
        measured = dist + err + sigma * rng.standard_normal(dist.shape)
        invalid = ~(range_m <= m.tof_max_range_m) | ~(amp >= m.tof_min_amplitude)
        measured[invalid] = np.nan
        amp_noisy = amp + np.sqrt(np.maximum(amp, 0.0)) * rng.standard_normal(amp.shape)
        return (np.clip(amp_noisy, 0.0, 65535.0).astype(np.float32), measured.astype(np.float32))

    def develop(
        self,
        name: str,
        values: np.ndarray,
        truth: SensorTruth,
        stamp_ns: int,
        rng: np.random.Generator,
    ) -> Frame:
        """The frame sensor ``name`` delivers from its raw values (:meth:`render_raw`,
        no margin): the modality's sensor model with noise drawn from ``rng``."""
        sensor = self.rig[name]
        if sensor.modality == "color":
            return Frame(name, stamp_ns, self._color(values, sensor, rng))
        if sensor.modality == "thermal":
            return Frame(name, stamp_ns, self._thermal(values, sensor, rng))
        amp, dist = self.tof_readings(values, truth.range_m, rng)
        return Frame(name, stamp_ns, amp, distance_m=dist)

    # -- public -------------------------------------------------------------------------

    def render(
        self,
        scene: Scene,
        T_world_rig: np.ndarray,
        stamp_ns: int,
        rng: np.random.Generator,
        sensors: list[str] | None = None,
    ) -> tuple[FrameSet, dict[str, SensorTruth]]:
        """Render the named sensors (default: all) with the rig at ``T_world_rig``.

        Returns the frame set (images as a real head would deliver them) and the exact
        ground truth per sensor.
        """
        frames: dict[str, Frame] = {}
        truths: dict[str, SensorTruth] = {}
        for name in sensors or self.rig.names:
            T_world_sensor = T_world_rig @ self.rig[name].T_rig_sensor
            values, truth = self.render_raw(scene, name, T_world_sensor)
            frames[name] = self.develop(name, values, truth, stamp_ns, rng)
            truths[name] = truth
        return FrameSet(stamp_ns, frames), truths
