"""What each TOF point looks like to the other sensors: its temperature from the thermal
imagers and its colour from the colour cameras, where the sensor sees the point and not
something in front of it (the method's Eq. 4 the other way round: for the 3D map, the
values travel to the points rather than to a camera's pixels).

Occlusion: the frame's points are splatted into a z-buffer of each sensor with cells about
the size of one TOF pixel there (:class:`SensorSampler`); a point is seen when it is no
further than ``rel`` behind the nearest point of its cell and the cells around it. The
sample is bilinear at the point's projection.

Frames: points (N, 3) in the TOF frame, metres; temperatures kelvin; colours RGB 0-255
(float, NaN where unseen).
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np

from trifuse.calib.rig import Rig
from trifuse.fusion.geometry import Projector32

_KERNEL = np.ones((3, 3), np.uint8)


class SensorSampler:
    """Samples one sensor's image at the TOF points it sees (see the module docstring).

    Args:
        rig: the rig (intrinsics and poses).
        sensor: the sensor sampled.
        tof: the TOF sensor whose points are given.
        rel: a point is occluded when it lies more than this fraction of its depth behind
            the nearest point around its pixel.
    """

    def __init__(self, rig: Rig, sensor: str, tof: str, rel: float = 0.03) -> None:
        self.sensor = rig[sensor]
        self._project = Projector32(self.sensor.intrinsics, rig.T(sensor, tof))
        self.rel = rel
        # One cell ~ one TOF pixel as the sensor sees it (TOF and sensor angular pitch).
        self.cell = max(1, round(self.sensor.intrinsics.fx / rig[tof].intrinsics.fx))
        w, h = self.sensor.image_size
        self.shape = (-(-h // self.cell), -(-w // self.cell))
        self._z = np.empty(self.shape[0] * self.shape[1], dtype=np.float32)

    def project(self, points_tof: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The points (N, 3) that land inside the image, before occlusion: their pixels
        (M, 2) float32, their rows (M,) in ``points_tof`` and their depths (M,) along the
        sensor's axis (metres) (:class:`fusion.geometry.Projector32`)."""
        uv, rows, z = self._project(points_tof)
        w, h = self.sensor.image_size
        ok = (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < h - 0.5)
        return uv[ok], rows[ok], z[ok]

    def visible_pixels(self, points_tof: np.ndarray) -> np.ndarray:
        """(N, 2) float32 pixel of each point in the sensor; NaN where the point is
        invalid, outside the image or hidden behind another point."""
        uv, idx, z = self.project(points_tof)
        inv = 1.0 / self.cell  # uv > -0.5: truncation is the floor
        cu = ((uv[:, 0] + 0.5) * inv).astype(np.intp)
        cv = ((uv[:, 1] + 0.5) * inv).astype(np.intp)
        cell = cv * self.shape[1] + cu
        self._z.fill(np.inf)
        np.minimum.at(self._z, cell, z)
        near = cv2.erode(self._z.reshape(self.shape), _KERNEL)
        seen = z <= near.ravel()[cell] * (1.0 + self.rel)
        out = np.full((len(points_tof), 2), np.nan, dtype=np.float32)
        out[idx[seen]] = uv[seen]
        return out

    def sample(self, points_tof: np.ndarray, image: np.ndarray) -> np.ndarray:
        """Bilinear samples of ``image`` ((H, W) or (H, W, C)) at the points the sensor
        sees: (N,) or (N, C) float32, NaN elsewhere."""
        uv = self.visible_pixels(points_tof)
        channels = 1 if image.ndim == 2 else image.shape[2]
        seen = np.isfinite(uv[:, 0])
        out = np.full((len(uv), channels), np.nan, dtype=np.float32)
        if seen.any():
            got = cv2.remap(
                image,
                uv[seen].reshape(-1, 1, 2),
                None,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            out[seen] = got.reshape(-1, channels)  # uint8 colour interpolates in OpenCV
        return out[:, 0] if channels == 1 else out


class PointAttributes:
    """Temperature and colour of each TOF point from the rig's sensors that see it (the
    mean where several do).

    Args:
        rig: the rig.
        tof: its TOF sensor.
        sensors: the thermal imagers and colour cameras sampled (default: every thermal
            imager, for the widest view and so that the two units' offsets average out,
            and the first eye's colour camera: the second camera sees the same surfaces
            and would cost as much again, BENCHMARKS.md "Thermal 3D map").
    """

    def __init__(self, rig: Rig, tof: str, sensors: list[str] | None = None) -> None:
        if sensors is None:
            sensors = [n for n, s in rig.sensors.items() if s.modality == "thermal"]
            if rig.eyes:
                sensors.append(next(iter(rig.eyes.values())).color)
        bad = [n for n in sensors if rig[n].modality not in ("thermal", "color")]
        if bad:
            raise ValueError(f"sensors: expected thermal imagers and colour cameras, got {bad}")
        self.samplers = {name: SensorSampler(rig, name, tof) for name in sensors}
        self.modality = {name: rig[name].modality for name in self.samplers}

    def sample(
        self, points_tof: np.ndarray, images: Mapping[str, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per point (N,) temperature (kelvin, NaN unseen) and (N, 3) colour (RGB 0-255,
        NaN unseen) from ``images``: sensor name -> thermal image in kelvin (H, W) or
        colour image (H, W, 3) uint8 RGB. Sensors missing from ``images`` are skipped."""
        pts = np.asarray(points_tof, dtype=np.float32).reshape(-1, 3)
        n = len(pts)
        sums = {"thermal": np.zeros(n, np.float32), "color": np.zeros((n, 3), np.float32)}
        counts = {"thermal": np.zeros(n, np.float32), "color": np.zeros(n, np.float32)}
        for name, sampler in self.samplers.items():
            image = images.get(name)
            if image is None:
                continue
            kind = self.modality[name]
            v = sampler.sample(pts, np.asarray(image))
            ok = np.isfinite(v) if v.ndim == 1 else np.isfinite(v[:, 0])
            sums[kind] += np.where(ok if v.ndim == 1 else ok[:, None], v, 0.0)
            counts[kind] += ok
        with np.errstate(invalid="ignore", divide="ignore"):
            temperature = sums["thermal"] / counts["thermal"]
            colour = sums["color"] / counts["color"][:, None]
        return temperature, colour
