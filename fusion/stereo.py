"""The operator's fused stereo pair: both eyes' thermal-on-colour pictures, side by side.

Per TOF frame, the TOF points are computed once (along the rays of one shared
:class:`fusion.mapping.TofGrid`) and each eye's mapping is recomputed from them
(:meth:`StereoFusion.update_depth`); per frame, each eye's thermal image is warped into its
colour camera's pixels, one colour span and one AGC table (:mod:`fusion.agc`) are chosen
for both eyes, and both pictures are composed straight into the halves of one preallocated
side-by-side buffer (left | right) ready for encoding.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

import cv2
import numpy as np

from trifuse.calib.rig import Rig
from trifuse.fusion.agc import ToneMap, ToneMapper, gain_span
from trifuse.fusion.cloud_colors import CloudColoring, point_colors
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.composer import Composer
from trifuse.fusion.mapping import EyeFusion, MappingOptions, TofGrid
from trifuse.fusion.palettes import PaletteName
from trifuse.fusion.registration_overlay import SigmaOverlay
from trifuse.fusion.span import SpanSmoother, resolve_span
from trifuse.fusion.stereo_pair import anaglyph, stereo_halves

EYE_ORDER = ("left", "right")
SPAN_SETTLED_K = 0.02
"""A smoothed span within this of its target is settled (far below one palette step)."""


EyeMap = Callable[[Callable[[Any], Any], Iterable[Any]], Iterable[Any]]
"""``map``'s shape: how :class:`StereoFusion` runs a step over the eyes (the mapping update,
the warp, the composition; the spot meter's capture), results in the eyes' order."""


class StereoFusion:
    """Fusion of a rig's two eyes (``left``/``right`` in ``rig.eyes``) into one frame.

    Attributes:
        tof: the name of the rig's TOF sensor, whose frames drive the mappings.
        grid: its rays, shared by every eye's mappings.
        fusion: eye -> its :class:`fusion.mapping.EyeFusion` (colour <- thermal, and back).
        span_k: the (low, high) span of the last frame, kelvin, shared by both eyes (an
            automatic one under ``plateau``/``dde`` at least ``255 / settings.max_gain``
            wide: :func:`fusion.agc.gain_span`).
        tone: the last frame's AGC mapping (``settings.agc`` over both eyes, smoothed over
            time by :attr:`tone_mapper`), shared by both eyes; its ``ticks_k`` label the
            viewer's colour scale.
        registration: eye -> its registration sigma ready to draw (the ``registration``
            display mode), or None before an estimate; set by :meth:`set_registration`.
        registration_version: counts :meth:`set_registration`'s calls (a picture drawn
            before a new estimate is not the same picture).
    """

    def __init__(
        self, rig: Rig, options: MappingOptions | None = None, eyes: tuple[str, ...] = EYE_ORDER
    ) -> None:
        missing = [e for e in eyes if e not in rig.eyes]
        if missing:
            raise ValueError(f"rig has no eye(s) {missing} (eyes: {sorted(rig.eyes)})")
        self.rig = rig
        self.eyes = eyes
        self.options = options or MappingOptions()
        self.grid = TofGrid(rig)
        self.tof = self.grid.tof
        self.fusion = {e: EyeFusion(rig, e, self.options, self.grid) for e in eyes}
        sizes = {rig[rig.eyes[e].color].image_size for e in eyes}
        if len(sizes) != 1:
            raise ValueError(f"the eyes' colour cameras differ in size ({sorted(sizes)})")
        w, h = sizes.pop()
        self.size = (w, h)
        self.composers = {e: Composer(w, h) for e in eyes}
        self.thermal_on_color = {e: np.empty((h, w), np.float32) for e in eyes}
        self.frame = np.zeros((h, w * len(eyes), 3), np.uint8)
        self.span_k: tuple[float, float] | None = None
        self.span_smoother = SpanSmoother()
        self.tone_mapper = ToneMapper()
        self.tone: ToneMap | None = None
        self._span_target: tuple[float, float] | None = None
        self._reverse_fresh: set[str] = set()
        tof = rig[self.tof]
        self.range_correction = tof.range_correction
        self._corrected = np.empty(tof.image_size[::-1], np.float32)
        self.distance_m: np.ndarray | None = None
        self._aside: tuple[dict[str, EyeFusion], np.ndarray] | None = None  # map_aside's
        self.registration: dict[str, SigmaOverlay | None] = dict.fromkeys(eyes)
        self.registration_version = 0
        # per eye: where its overlay is drawn, for which (overlay, coarse depth) it was made
        self._registration_mask = {e: np.zeros((h, w), np.uint8) for e in eyes}
        self._registration_made: dict[str, tuple[SigmaOverlay, np.ndarray] | None] = dict.fromkeys(
            eyes
        )
        self.map_eyes: EyeMap = map
        """How the eyes' own steps run (:meth:`update_depth`'s mapping update,
        :meth:`compose`'s warp and composition): ``map``, one after the other; the console
        gives a map that runs them on both cores (each eye has its own mapping, buffers,
        composer and half of the frame: the results are the same)."""

    @property
    def points(self) -> np.ndarray:
        """The last TOF frame's valid points (N, 3) float32, TOF frame, metres."""
        return self._points

    @property
    def ready(self) -> bool:
        return all(f.forward.ready for f in self.fusion.values())

    def update_depth(self, distance_m: np.ndarray, amplitude: np.ndarray | None = None) -> None:
        """A new TOF frame: recompute every eye's colour <- thermal mapping.

        Args:
            distance_m: (H, W) radial distances of the TOF, metres, NaN invalid.
            amplitude: (H, W) its amplitude image, for the amplitude term of the rig's
                range correction (without it, that term is left out).
        The rig's range correction (``range_correction`` of the TOF), if it has one, is
        applied first; :attr:`distance_m` is the corrected image.
        """
        self.distance_m, self._points = self._map(
            distance_m, amplitude, self.fusion, self._corrected, self.map_eyes
        )
        self._reverse_fresh.clear()

    def set_registration(self, eye: str, overlay: SigmaOverlay | None) -> None:
        """The registration sigma of ``eye`` the ``registration`` mode draws from the next
        picture on (None: none). May be called from any thread: an overlay is never
        changed once made, and the pictures take it whole."""
        if eye not in self.registration:
            raise ValueError(f"eye: expected one of {list(self.eyes)}, got {eye!r}")
        self.registration[eye] = overlay
        self.registration_version += 1

    def map_aside(
        self, distance_m: np.ndarray, amplitude: np.ndarray | None = None
    ) -> Callable[[], None]:
        """:meth:`update_depth` into a second set of mappings, not the ones in use; returns
        the function that puts them in use (and the previous ones aside for the next call).

        May run in another thread while :meth:`compose` and every reader of the mappings
        use the current ones (the console maps each TOF frame in a worker thread and goes on
        composing with the last depth meanwhile); the returned function must be called
        where the mappings are read (the fusion thread), between two pictures. One call at a
        time. The eyes are mapped one after the other (``map``). The mappings put in use
        are those :meth:`update_depth` makes of the same frame.
        """
        if self._aside is None:
            aside = {e: EyeFusion(self.rig, e, self.options, self.grid) for e in self.eyes}
            self._aside = (aside, np.empty_like(self._corrected))
        eyes, corrected = self._aside
        distance, points = self._map(distance_m, amplitude, eyes, corrected, map)

        def use() -> None:
            self._aside = (self.fusion, self._corrected)
            self.fusion, self._corrected = eyes, corrected
            self.distance_m, self._points = distance, points
            self._reverse_fresh.clear()

        return use

    def _map(
        self,
        distance_m: np.ndarray,
        amplitude: np.ndarray | None,
        eyes: Mapping[str, EyeFusion],
        corrected: np.ndarray,
        map_eyes: EyeMap,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Range correction (into ``corrected``), the frame's points and each eye's forward
        mapping updated from them; returns (the corrected distances, the points)."""
        if self.range_correction is not None:
            distance_m = self.range_correction.apply(distance_m, amplitude, out=corrected)
        points = self.grid.points(distance_m, self.options.edge_rel)
        list(map_eyes(lambda f: f.forward.update_points(points), eyes.values()))
        return distance_m, points

    def compose(
        self,
        colors: Mapping[str, np.ndarray],
        thermals: Mapping[str, np.ndarray],
        settings: DisplaySettings,
        stamp_ns: int | None = None,
    ) -> np.ndarray:
        """The side-by-side frame (H, n_eyes * W, 3) uint8 RGB for one instant.

        Args:
            colors: eye -> colour image (H, W, 3) uint8 RGB of its colour camera.
            thermals: eye -> thermal image (h, w) float32 kelvin of its thermal imager.
            settings: display mode, palette, span ...
            stamp_ns: the frame's time: with it, an automatic span and the AGC table are
                smoothed over time (``settings.span_smoothing_s``); without it, each frame
                gets its own.
        Returns the internal frame buffer (overwritten by the next call).
        """
        if not self.ready:
            raise RuntimeError("StereoFusion.compose: no TOF frame yet (call update_depth)")

        def warp(e: str) -> None:
            self.fusion[e].forward.warp(thermals[e], out=self.thermal_on_color[e])

        list(self.map_eyes(warp, self.eyes))
        span = resolve_span(settings, [self.thermal_on_color[e] for e in self.eyes])
        if settings.span_k is None and settings.agc != "linear":
            span = gain_span(span, settings.max_gain)  # a flat scene: not stretched
        self._span_target = span
        if settings.span_k is None and stamp_ns is not None:
            self.span_smoother.time_constant_s = settings.span_smoothing_s
            span = self.span_smoother.update(span, stamp_ns)
        else:
            self.span_smoother.reset()
        self.span_k = span
        self.tone = self.tone_mapper.update(
            [self.thermal_on_color[e] for e in self.eyes],
            settings.agc,
            span,
            settings.plateau,
            settings.span_smoothing_s,
            stamp_ns,
            settings.max_gain,
        )
        halves = stereo_halves(self.frame) if len(self.eyes) == 2 else (self.frame,)

        def compose(eye_half: tuple[str, np.ndarray]) -> None:
            e, half = eye_half
            mask = self._registration_drawn(e) if settings.mode == "registration" else None
            self.composers[e].compose(
                colors[e],
                self.thermal_on_color[e],
                self.fusion[e].forward.fallback,
                settings,
                self.span_k,
                out=half,
                tone=self.tone,
                registration=self.registration[e],
                registration_mask=mask,
            )

        list(self.map_eyes(compose, zip(self.eyes, halves, strict=True)))
        return self.frame

    def _registration_drawn(self, eye: str) -> np.ndarray | None:
        """Where the eye's registration overlay is drawn with the depth in use (made again
        when the overlay or the depth changed: :meth:`SigmaOverlay.mask_into
        <fusion.registration_overlay.SigmaOverlay.mask_into>`), or None without one."""
        overlay = self.registration[eye]
        if overlay is None:
            return None
        z, _ = self.fusion[eye].forward.coarse_depth()
        made = self._registration_made[eye]
        if made is None or made[0] is not overlay or made[1] is not z:
            overlay.mask_into(z, out=self._registration_mask[eye])
            self._registration_made[eye] = (overlay, z)
        return self._registration_mask[eye]

    @property
    def span_settled(self) -> bool:
        """Whether the span and the AGC table shown are the last frame's own (not still
        gliding towards them)."""
        target, span = self._span_target, self.span_k
        if target is None or span is None:
            return True
        if not self.tone_mapper.settled:
            return False
        return max(abs(target[0] - span[0]), abs(target[1] - span[1])) < SPAN_SETTLED_K

    def anaglyph(self, out: np.ndarray | None = None) -> np.ndarray:
        """Red-cyan anaglyph of the last composed pair."""
        left, right = stereo_halves(self.frame)
        return anaglyph(left, right, out)

    def color_in_thermal_view(self, eye: str, color: np.ndarray) -> np.ndarray:
        """The reverse direction: the eye's colour image drawn into its thermal imager's
        pixels (h, w, 3) uint8, black where the colour camera does not see the point.
        The eye's reverse mapping is built on first use and updated from the last TOF
        frame's points when it lags behind them."""
        f = self.fusion[eye]
        if eye not in self._reverse_fresh:
            f.reverse.update_points(self._points)
            self._reverse_fresh.add(eye)
        return f.reverse.warp(color, fill=0)

    def point_cloud(
        self,
        colors: Mapping[str, np.ndarray],
        thermals: Mapping[str, np.ndarray],
        by: CloudColoring = "color",
        span: tuple[float, float] | None = None,
        palette: PaletteName = "iron",
        eye: str | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The last TOF frame's points (N, 3) float32 (TOF frame, metres) and their colours
        (N, 3) uint8 RGB for the 3D view: ``by`` "color" (sampled from the eye's colour
        camera), "temperature" (its thermal imager, in ``palette`` over ``span``) or
        "depth" (radial distance). Points a camera does not see get grey."""
        if not self.ready:
            raise RuntimeError("StereoFusion.point_cloud: no TOF frame yet")
        e = eye or self.eyes[0]
        pts = self._points
        if by == "color":
            sensor = self.rig.eyes[e].color
            rgb = sample_image(self.rig, sensor, self.tof, pts, colors[e], 128)
            return pts, point_colors(pts, "color", rgb.astype(np.uint8))
        if by == "temperature":
            sensor = self.rig.eyes[e].thermal
            t = sample_image(self.rig, sensor, self.tof, pts, thermals[e], np.nan)
            return pts, point_colors(pts, "temperature", t, span, palette)
        return pts, point_colors(pts, by, None, span, palette)


def sample_image(
    rig: Rig, sensor: str, tof: str, points_tof: np.ndarray, image: np.ndarray, fill: float
) -> np.ndarray:
    """Bilinear samples (N,) or (N, C) of ``image`` where ``points_tof`` project in
    ``sensor``; ``fill`` outside its image."""
    T = rig.T(sensor, tof)
    uv = rig[sensor].intrinsics.project(points_tof @ T[:3, :3].T + T[:3, 3])
    uv = np.nan_to_num(uv, nan=-1e4).astype(np.float32).reshape(-1, 1, 2)
    channels = 1 if image.ndim == 2 else image.shape[2]
    out = cv2.remap(
        image,
        uv,
        None,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(fill,) * channels,
    )
    return (
        out.reshape(len(points_tof), -1).squeeze(-1)
        if channels == 1
        else out.reshape(len(points_tof), channels)
    )
