"""Ray-casting renderer of the simulated head: colour, thermal and TOF images.

Each sensor's pixel rays (with lens distortion) are cast into the scene in numpy. Pixels
on silhouettes and pattern edges are supersampled (n x n sub-rays) so edges are
anti-aliased the way a real sensor integrates light over its pixel, and TOF pixels on depth
edges become mixed pixels. Then each modality's physics:

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

from dataclasses import dataclass, field

import cv2
import numpy as np

from app.sources.frames import Frame, FrameSet
from app.sources.sim.scene import Scene, apply_affine
from app.sources.sim.tof_error import RangeErrorModel
from calib.rig import Rig, Sensor

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
    """Cached rays of one sensor: unit directions at pixel centres, camera frame."""

    def __init__(self, sensor: Sensor) -> None:
        w, h = sensor.image_size
        intr = sensor.intrinsics
        u, v = np.meshgrid(
            np.arange(-1, w + 1, dtype=np.float64), np.arange(-1, h + 1, dtype=np.float64)
        )
        # Normalised undistorted coordinates with a one-pixel margin (for interpolation).
        self.xy = intr.normalized(np.stack([u, v], axis=-1)).astype(np.float32)
        if np.isnan(self.xy).any():
            raise ValueError(
                f"sensor {sensor.name!r}: distortion is not invertible inside the "
                "image; cannot render it"
            )
        xy = self.xy[1:-1, 1:-1]
        d = np.empty((h, w, 3), dtype=np.float32)
        d[..., :2] = xy
        d[..., 2] = 1.0
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        self.dirs = d
        self.width, self.height = w, h

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


def _screen_boxes(
    scene: Scene, sensor: Sensor, T_sensor_world: np.ndarray
) -> list[tuple[int, int, int, int] | None]:
    """Per solid, the pixel rectangle (u0, u1, v0, v1) it can cover, or None if unseen."""
    w, h = sensor.image_size
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    boxes: list[tuple[int, int, int, int] | None] = []
    for solid in scene.solids:
        c, r = solid.bounding_sphere()
        c_cam = T_sensor_world[:3, :3] @ c + T_sensor_world[:3, 3]
        if c_cam[2] - r <= 0.05 * r + 0.02:
            boxes.append((0, w, 0, h) if c_cam[2] + r > 0 else None)
            continue
        uv = sensor.intrinsics.project(c_cam + r * corners)
        mu, mv = 0.03 * w + 3, 0.03 * h + 3
        u0 = int(max(0, np.floor(uv[:, 0].min() - mu)))
        u1 = int(min(w, np.ceil(uv[:, 0].max() + mu)))
        v0 = int(max(0, np.floor(uv[:, 1].min() - mv)))
        v1 = int(min(h, np.ceil(uv[:, 1].max() + mv)))
        boxes.append((u0, u1, v0, v1) if u0 < u1 and v0 < v1 else None)
    return boxes


class Renderer:
    """Renders any subset of a rig's sensors from a scene, with ground truth."""

    def __init__(self, rig: Rig, model: HeadModel | None = None) -> None:
        self.rig = rig
        self.model = model or HeadModel()
        self._grids: dict[str, _RayGrid] = {}

    def _grid(self, name: str) -> _RayGrid:
        if name not in self._grids:
            self._grids[name] = _RayGrid(self.rig[name])
        return self._grids[name]

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

        Channels: colour linear RGB (3); thermal radiance proxy T^4 (1);
        TOF amplitude-weighted distance and amplitude (2).
        """
        n = len(t)
        channels = {"color": 3, "thermal": 1, "tof": 2}[modality]
        out = np.zeros((n, channels), dtype=np.float64)
        keys = ids.astype(np.int32) * 64
        if modality == "thermal":
            out[:, 0] = scene.ambient_k**4 * 0.9  # a miss sees the cold sky of the room
        light = -np.asarray(scene.light_dir_world, dtype=np.float64)
        light /= np.linalg.norm(light)
        for k, solid in enumerate(scene.solids):
            sel = np.flatnonzero(ids == k)
            if not len(sel):
                continue
            d = dirs[sel].astype(np.float64)
            p = origin + t[sel, None].astype(np.float64) * d
            normals, st = solid.surface(p)
            cos = np.einsum("ij,ij->i", normals, d)
            normals[cos > 0] *= -1.0
            cos = np.abs(cos)
            mat = solid.material
            keys[sel] += mat.edge_key(st)
            if modality == "color":
                lambert = np.clip(normals @ light, 0.0, None)
                out[sel] = mat.albedo(st) * (0.35 + 0.75 * lambert)[:, None]
            elif modality == "thermal":
                eps = mat.emissivity_at(st)
                temp = mat.temperature(st)
                out[sel, 0] = eps * temp**4 + (1.0 - eps) * scene.ambient_k**4
            else:
                dist = t[sel].astype(np.float64)
                amp = (
                    self.model.tof_amplitude_scale
                    * mat.nir(st)
                    * cos
                    / np.maximum(dist * dist, 1e-6)
                )
                out[sel, 0] = amp * dist
                out[sel, 1] = amp
        return out, keys

    def _render_raw(self, scene: Scene, name: str, T_world_sensor: np.ndarray):
        """Pixel-integrated values (H, W, C) plus truth for one sensor."""
        sensor = self.rig[name]
        grid = self._grid(name)
        h, w = grid.height, grid.width
        R = T_world_sensor[:3, :3]
        origin = T_world_sensor[:3, 3].astype(np.float64)
        T_sensor_world = np.linalg.inv(T_world_sensor)
        boxes = _screen_boxes(scene, sensor, T_sensor_world)
        dirs = apply_affine(R, grid.dirs)
        t, ids = self._trace_grid(scene, origin, dirs, boxes)
        values, keys = self._shade(
            scene, sensor.modality, origin, dirs.reshape(-1, 3), t.ravel(), ids.ravel()
        )
        values = values.reshape(h, w, -1)
        keys = keys.reshape(h, w)

        # Supersample pixels where the solid or the surface pattern changes.
        edge = np.zeros((h, w), dtype=bool)
        dh = keys[:, 1:] != keys[:, :-1]
        dv = keys[1:, :] != keys[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        ns = self.model.supersample[sensor.modality]
        ev, eu = np.nonzero(edge)
        if len(eu) and ns > 1:
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
        truth = SensorTruth(
            range_m=np.where(np.isfinite(t), t, np.nan).astype(np.float32), solid=ids
        )
        return values, truth

    # -- per-modality sensor models ------------------------------------------------------

    def _color(self, values: np.ndarray, sensor: Sensor, rng: np.random.Generator):
        m = self.model
        h, w = values.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
        lin = values.astype(np.float32) * (m.color_exposure * (1 - 0.08 * r2))[..., None]
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
        return temp.astype(np.float32)

    def _tof(self, values: np.ndarray, truth: SensorTruth, rng: np.random.Generator):
        m = self.model
        amp = values[..., 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            dist = values[..., 0] / amp
        err = m.range_error.error_m(np.nan_to_num(dist), amp)
        sigma = m.tof_noise_m * np.sqrt(m.tof_noise_ref / np.maximum(amp, 1.0))
        measured = dist + err + sigma * rng.standard_normal(dist.shape)
        invalid = ~(truth.range_m <= m.tof_max_range_m) | ~(amp >= m.tof_min_amplitude)
        measured[invalid] = np.nan
        amp_noisy = amp + np.sqrt(np.maximum(amp, 0.0)) * rng.standard_normal(amp.shape)
        return (np.clip(amp_noisy, 0.0, 65535.0).astype(np.float32), measured.astype(np.float32))

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
            sensor = self.rig[name]
            T_world_sensor = T_world_rig @ sensor.T_rig_sensor
            values, truth = self._render_raw(scene, name, T_world_sensor)
            if sensor.modality == "color":
                frames[name] = Frame(name, stamp_ns, self._color(values, sensor, rng))
            elif sensor.modality == "thermal":
                frames[name] = Frame(name, stamp_ns, self._thermal(values, sensor, rng))
            else:
                amp, dist = self._tof(values, truth, rng)
                frames[name] = Frame(name, stamp_ns, amp, distance_m=dist)
            truths[name] = truth
        return FrameSet(stamp_ns, frames), truths
