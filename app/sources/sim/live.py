"""Many frames from one live render: fresh sensor noise per frame, turned to nearby poses.

A live render (:class:`~app.sources.sim.render.Renderer` with ``live=True``) costs about a
tenth of a second for a colour image; a simulated head at 30 Hz cannot render every frame.
:class:`LiveDeveloper` therefore splits a sensor model in two:

* :meth:`LiveDeveloper.clean`, once per render: the noise-free picture the sensor would
  deliver (colour: vignetting, exposure and gamma, plus the noise's standard deviation per
  pixel in the same 0-255 units; thermal: temperature with the optics blur and the
  imager's gain and offset; TOF: the pixel-integrated distance and amplitude);
* :meth:`LiveDeveloper.frame`, once per frame (a few milliseconds): fresh noise on that
  picture, optionally after turning it to the sensor's orientation at the frame's own
  time (:class:`RotationWarp`), so a reused render moves smoothly and does not look
  frozen.

The noise follows :class:`~app.sources.sim.render.HeadModel` like the accurate sensor
model, with two shortcuts. Colour noise is added in the gamma-encoded domain, its
standard deviation carried through the gamma curve to first order (the accurate model adds
it to linear intensity before the curve; they differ visibly only in near-black pixels),
and its normal deviates come from a bank of ``(H + 64) x (W + 64)`` numbers drawn once per
image size, read at a random offset and sign per frame (8450 different fields; two frames'
noise is one field shifted, which only a correlation of the noise itself finds). The TOF's
systematic range error is applied per frame, in the sensor's pixel grid, exactly as the
accurate model does.

Turning a picture to another orientation ignores the sensor's translation: the head of the
inspection scenario pans about the rig origin, so a sensor 5.4 cm from it moves 0.4 mm
while the head turns 0.42 degrees (0.1 s of its fastest pan, the most a recording with
poses at 5 Hz turns a picture): a parallax under 1 px at 0.6 m, 0.2 px at 3 m. Pixels that
come from beyond the rendered picture repeat its border: render with a margin
(:meth:`~app.sources.sim.render.Renderer.render_raw`) wide enough for the turn.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.render import Renderer, SensorTruth, vignetting
from trifuse.calib.rig import Sensor

NOISE_BANK_PAD = 64
"""Extra rows and columns of the colour noise bank: the offsets a frame can read it at."""
WARP_STEP_PX = 8
"""Pixel spacing of the coarse grid on which :class:`RotationWarp` computes its map."""
_GAMMA = 1 / 2.2


@dataclass
class CleanImage:
    """One sensor's noise-free picture from one live render.

    Attributes:
        sensor: the sensor's name.
        modality: ``color``, ``thermal`` or ``tof``.
        margin: pixels beyond the sensor's image on every side (arrays are (H + 2 margin,
            W + 2 margin)).
        T_world_sensor: (4, 4) the sensor's pose the picture was rendered at.
        planes: float32 arrays. colour: ``mean`` (.., 3) gamma-encoded RGB 0-255 and
            ``sigma`` (.., 3) the noise's standard deviation in those units; thermal:
            ``temperature`` kelvin (blurred, gain and offset applied); TOF: ``values``
            (.., 2) pixel-integrated (amplitude x distance, amplitude) and ``range`` the
            exact radial distance of the pixel-centre ray (m, NaN on a miss).
        truth: the render's exact ground truth (with the margin).
    """

    sensor: str
    modality: str
    margin: int
    T_world_sensor: np.ndarray
    planes: dict[str, np.ndarray]
    truth: SensorTruth


class RotationWarp:
    """Where each pixel of a sensor's image looks in a picture of the same sensor rendered
    at another orientation (same position): the map for ``cv2.remap``.

    The map is exact on a grid every :data:`WARP_STEP_PX` pixels (undistort, rotate,
    distort) and bilinear in between (the map of a small turn is smooth: the error is far
    below a thousandth of a pixel for the turns this module makes).
    """

    def __init__(self, sensor: Sensor) -> None:
        w, h = sensor.image_size
        self.sensor = sensor
        # A uniform grid, past the last pixel if need be: every pixel then sits at a
        # multiple of 1/8 between grid points, which remap's 1/32-pixel positions hold.
        us = WARP_STEP_PX * np.arange(-(-(w - 1) // WARP_STEP_PX) + 1, dtype=np.float64)
        vs = WARP_STEP_PX * np.arange(-(-(h - 1) // WARP_STEP_PX) + 1, dtype=np.float64)
        uu, vv = np.meshgrid(us, vs)
        xy = sensor.intrinsics.normalized(np.stack([uu, vv], axis=-1))
        self._rays = np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=-1)  # (hc, wc, 3)
        # Fractional grid index of every pixel, to spread the coarse map.
        self._fine_u, self._fine_v = np.meshgrid(
            (np.arange(w) / WARP_STEP_PX).astype(np.float32),
            (np.arange(h) / WARP_STEP_PX).astype(np.float32),
        )
        self.map = np.empty((h, w, 2), dtype=np.float32)

    def update(self, R_src_dst: np.ndarray, margin: int) -> np.ndarray:
        """The map (H, W, 2) float32: for each pixel of the image at orientation ``dst``,
        its position in the picture at ``src`` that has ``margin`` extra pixels on every
        side; ``R_src_dst`` (3, 3) turns directions from the dst into the src camera frame.
        Overwrites (and returns) :attr:`map`."""
        rays = self._rays @ np.asarray(R_src_dst, dtype=np.float64).T
        uv = self.sensor.intrinsics.project(rays)
        coarse = np.nan_to_num(uv + margin, nan=-1e4).astype(np.float32)
        cv2.remap(
            coarse,
            self._fine_u,
            self._fine_v,
            cv2.INTER_LINEAR,
            dst=self.map,
            borderMode=cv2.BORDER_REPLICATE,
        )
        return self.map


class LiveDeveloper:
    """Frames with fresh noise from the clean pictures of live renders (module docstring).

    Args:
        renderer: the renderer whose rig and :class:`~app.sources.sim.render.HeadModel`
            the pictures follow.
        noise_seed: seed of the colour noise bank.

    Thread-safe: frames of different sensors may be made at the same time.
    """

    def __init__(self, renderer: Renderer, noise_seed: int = 0) -> None:
        self.renderer = renderer
        self.rig = renderer.rig
        self.model = renderer.model
        self.noise_seed = noise_seed
        self._banks: dict[tuple[int, int], np.ndarray] = {}
        self._warps: dict[str, RotationWarp] = {}
        self._lock = threading.Lock()

    # -- once per render ------------------------------------------------------------------

    def clean(
        self,
        name: str,
        values: np.ndarray,
        truth: SensorTruth,
        T_world_sensor: np.ndarray,
        margin: int = 0,
    ) -> CleanImage:
        """The noise-free picture of sensor ``name`` from its raw render ``values`` (H + 2
        margin, W + 2 margin, C) (:meth:`~app.sources.sim.render.Renderer.render_raw`)."""
        sensor = self.rig[name]
        m = self.model
        planes: dict[str, np.ndarray] = {}
        if sensor.modality == "color":
            w, h = sensor.image_size
            lin = (
                values.astype(np.float32) * (m.color_exposure * vignetting(w, h, margin))[..., None]
            )
            sigma = np.sqrt(m.color_read_noise**2 + m.color_shot_noise * np.clip(lin, 0, None))
            np.clip(lin, 0.0, 1.0, out=lin)
            planes["mean"] = 255.0 * lin**_GAMMA
            # d(255 lin^g)/d lin, taken no closer to 0 than one sigma (it grows without
            # bound there, where the accurate model's clipped noise is one-sided anyway).
            slope = (255.0 * _GAMMA) * np.maximum(lin, sigma) ** (_GAMMA - 1.0)
            planes["sigma"] = (slope * sigma).astype(np.float32)
        elif sensor.modality == "thermal":
            temp = np.power(values[..., 0], 0.25).astype(np.float32)
            if m.thermal_blur_sigma_px > 0:
                temp = cv2.GaussianBlur(
                    temp, (0, 0), m.thermal_blur_sigma_px, borderType=cv2.BORDER_REPLICATE
                )
            gain = m.thermal_gain.get(name, 1.0)
            offset = m.thermal_offset_k.get(name, 0.0)
            planes["temperature"] = (gain * temp + offset).astype(np.float32)
        else:
            planes["values"] = np.ascontiguousarray(values, dtype=np.float32)
            planes["range"] = truth.range_m.astype(np.float32)
        return CleanImage(
            name, sensor.modality, margin, np.array(T_world_sensor, dtype=np.float64), planes, truth
        )

    # -- once per frame ---------------------------------------------------------------------

    def frame(
        self,
        clean: CleanImage,
        stamp_ns: int,
        rng: np.random.Generator,
        T_world_sensor: np.ndarray | None = None,
    ) -> Frame:
        """A frame of ``clean``'s sensor stamped ``stamp_ns`` with fresh noise from ``rng``;
        with ``T_world_sensor`` (4, 4), the picture is first turned to that orientation
        (its rotation relative to the render's; the translation is ignored)."""
        sensor = self.rig[clean.sensor]
        R_src_dst = None
        if T_world_sensor is not None:
            R = clean.T_world_sensor[:3, :3].T @ np.asarray(T_world_sensor)[:3, :3]
            if not np.allclose(R, np.eye(3), rtol=0.0, atol=1e-12):
                R_src_dst = R
        if R_src_dst is None:
            return self._frame(clean, sensor, stamp_ns, rng, None)
        with self._lock:  # the sensor's map is shared
            warp_map = self._warp(clean.sensor).update(R_src_dst, clean.margin)
            return self._frame(clean, sensor, stamp_ns, rng, warp_map)

    def _frame(
        self,
        clean: CleanImage,
        sensor: Sensor,
        stamp_ns: int,
        rng: np.random.Generator,
        warp_map: np.ndarray | None,
    ) -> Frame:
        w, h = sensor.image_size
        mg = clean.margin

        def view(plane: str, nearest: bool = False) -> np.ndarray:
            a = clean.planes[plane]
            if warp_map is None:
                return a[mg : mg + h, mg : mg + w]
            interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
            return cv2.remap(a, warp_map, None, interp, borderMode=cv2.BORDER_REPLICATE)

        if clean.modality == "color":
            return Frame(clean.sensor, stamp_ns, self._color(view("mean"), view("sigma"), rng))
        if clean.modality == "thermal":
            noise = rng.standard_normal((h, w), dtype=np.float32)
            noise *= np.float32(self.model.thermal_netd_k)
            noise += view("temperature")
            return Frame(clean.sensor, stamp_ns, noise)
        values = np.ascontiguousarray(view("values", nearest=True))
        range_m = view("range", nearest=True)
        amp, dist = self.renderer.tof_readings(values, range_m, rng)
        return Frame(clean.sensor, stamp_ns, amp, distance_m=dist)

    def _color(self, mean: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """uint8 RGB: ``mean + sigma * N`` rounded and saturated, N from the noise bank."""
        h, w = mean.shape[:2]
        bank = self._bank(h, w)
        dy, dx = (int(x) for x in rng.integers(0, NOISE_BANK_PAD + 1, size=2))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        noise = cv2.multiply(sigma, bank[dy : dy + h, dx : dx + w], scale=sign)
        return cv2.add(mean, noise, dtype=cv2.CV_8U)

    def _bank(self, h: int, w: int) -> np.ndarray:
        bank = self._banks.get((h, w))
        if bank is None:
            rng = np.random.default_rng([self.noise_seed, h, w])
            shape = (h + NOISE_BANK_PAD, w + NOISE_BANK_PAD, 3)
            bank = rng.standard_normal(shape, dtype=np.float32)
            bank.flags.writeable = False
            self._banks[(h, w)] = bank
        return bank

    def _warp(self, name: str) -> RotationWarp:
        warp = self._warps.get(name)
        if warp is None:
            warp = self._warps[name] = RotationWarp(self.rig[name])
        return warp
