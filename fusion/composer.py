"""One eye's display picture: :class:`Composer` draws the display modes of
:mod:`fusion.compose` (which describes them and their common rules) from the eye's colour
image and its thermal image on the colour pixels.

:class:`Composer` preallocates every full-frame buffer once; :meth:`Composer.compose`
allocates no full-frame array in the steady state (OpenCV calls with ``dst=``, numpy with
``out=``). The colour range is one span shared by both eyes: a fixed ``span_k`` or
:func:`fusion.span.auto_span` over both eyes' images (:func:`fusion.span.resolve_span`).
Within it, palette colour follows the frame's AGC mapping (:mod:`fusion.agc`, ``settings.agc``): a
:class:`fusion.agc.ToneMap` computed over both eyes and handed to ``compose`` for each eye
(:class:`fusion.stereo.StereoFusion` does); without one, ``compose`` maps linearly over the
span.
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.calib.numbers import is_integer
from trifuse.fusion.agc import PaletteIndexer, ToneMap
from trifuse.fusion.compose import (
    EDGE_BOX_PX,
    EDGE_GAIN,
    FALLBACK_DESATURATION,
    FALLBACK_FADE,
    DisplaySettings,
    pip_box,
)
from trifuse.fusion.compose import describe_array as _describe
from trifuse.fusion.palettes import _colormap_into, check_span
from trifuse.fusion.registration_overlay import SigmaOverlay
from trifuse.fusion.span import resolve_span


class Composer:
    """Composes display pictures of one eye of a fixed size, with preallocated buffers.

    Use one per eye (or one for both, called in turn: ``compose`` is not re-entrant).

    Args:
        width, height: the colour image size in pixels.
    """

    def __init__(self, width: int, height: int) -> None:
        for n, v in (("width", width), ("height", height)):
            if not is_integer(v) or v <= 0:
                raise ValueError(f"{n}: expected a positive integer, got {v!r}")
        self.width = int(width)
        self.height = int(height)
        h, w = self.height, self.width
        self._index = np.zeros((h, w), np.uint8)  # palette indices; also the grey image
        self._pal = np.zeros((h, w, 3), np.uint8)  # palette image
        self._rgb = np.zeros((h, w, 3), np.uint8)  # scratch: detail (edges) or solid colour
        self._solid_rgb: tuple[int, int, int] | None = None  # what _rgb holds, if solid
        self._out = np.zeros((h, w, 3), np.uint8)  # the result when no ``out`` is given
        self._nan = np.zeros((h, w), bool)
        self._valid = np.zeros((h, w), bool)
        self._paint = np.zeros((h, w), np.uint8)
        self._mask = np.zeros((h, w), np.uint8)
        self._mask2 = np.zeros((h, w), np.uint8)
        self._indexer = PaletteIndexer(w, h)
        # The fallback veil as one colour transform: RGB -> (1 - d - f) RGB + d Y + 128 f
        d, f = FALLBACK_DESATURATION, FALLBACK_FADE
        luma = np.array([0.299, 0.587, 0.114])  # cv2.COLOR_RGB2GRAY's weights
        self._veil = np.hstack([(1.0 - d - f) * np.eye(3) + d * luma, np.full((3, 1), 128.0 * f)])

    # -- checks ------------------------------------------------------------------------------

    def _check_inputs(
        self,
        color: np.ndarray,
        thermal_k: np.ndarray,
        fallback: np.ndarray | None,
        out: np.ndarray | None,
    ) -> np.ndarray:
        h, w = self.height, self.width
        rgb_shape = (h, w, 3)
        if not isinstance(color, np.ndarray) or color.dtype != np.uint8 or color.shape != rgb_shape:
            raise ValueError(f"color: expected uint8 ({h}, {w}, 3) RGB, got {_describe(color)}")
        if (
            not isinstance(thermal_k, np.ndarray)
            or thermal_k.dtype not in (np.float32, np.float64)
            or thermal_k.shape != (h, w)
        ):
            raise ValueError(
                f"thermal_k: expected float32 (or float64) ({h}, {w}) kelvin, "
                f"got {_describe(thermal_k)}"
            )
        if fallback is not None and (
            not isinstance(fallback, np.ndarray)
            or fallback.dtype != np.bool_
            or fallback.shape != (h, w)
        ):
            raise ValueError(
                f"fallback: expected bool ({h}, {w}) or None, got {_describe(fallback)}"
            )
        if out is None:
            return self._out
        if not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (h, w, 3):
            raise ValueError(f"out: expected uint8 ({h}, {w}, 3), got {_describe(out)}")
        if out.strides[1:] != (3, 1):
            raise ValueError("out: expected rows of contiguous RGB pixels (a column slice is fine)")
        if np.may_share_memory(out, color) or np.may_share_memory(out, thermal_k):
            raise ValueError("out: must not overlap color or thermal_k")
        return out

    # -- building blocks -----------------------------------------------------------------------

    def _palette(
        self,
        thermal: np.ndarray,
        tone: ToneMap,
        name: str,
        dst: np.ndarray,
        sl: tuple[slice, slice],
    ) -> None:
        self._indexer.index_into(thermal, tone, self._index, sl)
        _colormap_into(self._index[sl], name, dst[sl])

    def _mark(
        self,
        out: np.ndarray,
        fallback: np.ndarray,
        paint: np.ndarray | None,
        box: tuple[int, int, int, int],
        fallback_box: tuple[int, int, int, int],
    ) -> None:
        """Veil the fallback pixels inside ``box`` (x0, y0, x1, y1), within ``paint``
        (a 0/255 or bool-as-uint8 mask, None = all) if given: ``(1 - d - f) * c + d * Y +
        f * 128`` (``d`` FALLBACK_DESATURATION, ``f`` FALLBACK_FADE, ``Y`` the pixel's
        luma, not rounded). Work is limited to the intersection with ``fallback_box``, the
        bounding box of the fallback pixels. Uses ``_pal`` and ``_mask2`` as scratch."""
        x0, y0 = max(box[0], fallback_box[0]), max(box[1], fallback_box[1])
        x1, y1 = min(box[2], fallback_box[2]), min(box[3], fallback_box[3])
        if x0 >= x1 or y0 >= y1:
            return
        sl = (slice(y0, y1), slice(x0, x1))
        base = fallback[sl].view(np.uint8)
        if paint is not None:
            base = cv2.bitwise_and(base, paint[sl], dst=self._mask2[sl])
        o = out[sl]
        cv2.copyTo(cv2.transform(o, self._veil, dst=self._pal[sl]), base, dst=o)

    def _restore_nan(self, out: np.ndarray, color: np.ndarray, sl: tuple[slice, slice]) -> bool:
        """Colour back on NaN pixels (within ``sl``); ``self._nan[sl]`` holds the NaN mask."""
        nan = self._nan[sl]
        if nan.any():
            cv2.copyTo(color[sl], nan.view(np.uint8), dst=out[sl])
            return True
        return False

    def _solid(self, rgb: tuple[int, int, int]) -> np.ndarray:
        if self._solid_rgb != rgb:
            self._rgb[...] = rgb
            self._solid_rgb = rgb
        return self._rgb

    # -- the modes ---------------------------------------------------------------------------

    def compose(
        self,
        color: np.ndarray,
        thermal_k: np.ndarray,
        fallback: np.ndarray | None,
        settings: DisplaySettings,
        span: tuple[float, float] | None = None,
        out: np.ndarray | None = None,
        tone: ToneMap | None = None,
        registration: SigmaOverlay | None = None,
        registration_mask: np.ndarray | None = None,
    ) -> np.ndarray:
        """One eye's display picture.

        Args:
            color: (H, W, 3) uint8 RGB.
            thermal_k: (H, W) float32/float64 kelvin, NaN = no reading.
            fallback: (H, W) bool, True where the mapping used a fallback depth; or None.
            settings: what to show.
            span: ``(low_k, high_k)`` of the palette; None: ``settings.span_k`` or, if
                that is None, :func:`auto_span` of this eye alone (pass the span from
                :func:`resolve_span` over both eyes so they match).
            out: (H, W, 3) uint8 to write into (a half of a side-by-side buffer from
                :func:`stereo_halves` is fine; must not overlap the inputs). None: an
                internal buffer, overwritten by the next call.
            tone: the frame's AGC mapping from kelvin to palette index
                (:class:`fusion.agc.ToneMap`, computed over both eyes so that they match);
                it brings its own span (``span`` is then ignored). None: linear over
                ``span``, whatever ``settings.agc`` says.
            registration: the eye's registration sigma at its colour pixels, for the
                ``registration`` mode (None: no estimate yet, the colour image).
            registration_mask: (H, W) uint8, non-zero where the sigma is drawn
                (:meth:`fusion.registration_overlay.SigmaOverlay.mask_into`: where the
                depth still is the estimate's); None: wherever it has an estimate.

        Returns:
            ``out`` (or the internal buffer): (H, W, 3) uint8 RGB.
        """
        if not isinstance(settings, DisplaySettings):
            raise ValueError(f"settings: expected DisplaySettings, got {type(settings).__name__}")
        out = self._check_inputs(color, thermal_k, fallback, out)
        if tone is None:
            span = resolve_span(settings, thermal_k) if span is None else check_span(span)
            tone = ToneMap.linear(span)
        elif not isinstance(tone, ToneMap):
            raise ValueError(f"tone: expected a ToneMap or None, got {type(tone).__name__}")
        mode = settings.mode
        full = (slice(None), slice(None))
        if mode == "color" or (mode == "blend" and settings.opacity == 0.0):
            np.copyto(out, color)
            return out
        if mode == "registration":
            return self._registration(
                color, thermal_k, settings.opacity, registration, registration_mask, out
            )
        fb_box = (0, 0, 0, 0)
        if settings.mark_fallback and fallback is not None:
            x, y, bw, bh = cv2.boundingRect(fallback.view(np.uint8))
            fb_box = (x, y, x + bw, y + bh)
        mark = fb_box[2] > fb_box[0]
        frame = (0, 0, self.width, self.height)
        name = settings.palette

        if mode in ("blend", "thermal", "edges"):
            direct = (
                mode == "thermal"
                or (mode == "blend" and settings.opacity == 1.0)
                or (mode == "edges" and settings.edge_strength == 0.0)
            )
            self._palette(thermal_k, tone, name, out if direct else self._pal, full)
            if not direct and mode == "blend":
                a = settings.opacity
                cv2.addWeighted(self._pal, a, color, 1.0 - a, 0.0, dst=out)
            elif not direct:
                self._emboss(color, settings.edge_strength, out)
            if mark:
                self._mark(out, fallback, None, frame, fb_box)  # NaN pixels are restored below
            np.isnan(thermal_k, out=self._nan)
            self._restore_nan(out, color, full)
            return out

        if mode == "pip":
            x0, y0, x1, y1 = pip_box(settings, self.width, self.height)
            np.copyto(out, color)
            sl = (slice(y0, y1), slice(x0, x1))
            self._palette(thermal_k, tone, name, self._pal, sl)
            valid = np.isfinite(thermal_k[sl], out=self._valid[sl]).view(np.uint8)
            cv2.copyTo(self._pal[sl], valid, dst=out[sl])
            if mark:
                self._mark(out, fallback, self._valid.view(np.uint8), (x0, y0, x1, y1), fb_box)
            return out

        # threshold and isotherm: a selection mask (0/255); NaN compares false
        paint = self._paint
        if mode == "threshold":
            low, high = settings.threshold_k  # type: ignore[misc]
            direction = settings.threshold_direction
        else:
            low, high = settings.isotherm_k
            direction = "inside"
        if direction == "above":
            cv2.compare(thermal_k, high, cv2.CMP_GT, dst=paint)
        elif direction == "below":
            cv2.compare(thermal_k, low, cv2.CMP_LT, dst=paint)
        else:
            cv2.compare(thermal_k, low, cv2.CMP_GE, dst=paint)
            cv2.compare(thermal_k, high, cv2.CMP_LE, dst=self._mask)
            cv2.bitwise_and(paint, self._mask, dst=paint)

        if mode == "isotherm" and settings.isotherm_background == "grey":
            cv2.cvtColor(color, cv2.COLOR_RGB2GRAY, dst=self._index)
            cv2.cvtColor(self._index, cv2.COLOR_GRAY2RGB, dst=out)
            np.isnan(thermal_k, out=self._nan)
            self._restore_nan(out, color, full)
        else:
            np.copyto(out, color)
        if mode == "isotherm" and settings.isotherm_color is not None:
            source = self._solid(settings.isotherm_color)
        else:
            self._palette(thermal_k, tone, name, self._pal, full)
            source = self._pal
        cv2.copyTo(source, paint, dst=out)
        if mark:
            self._mark(out, fallback, paint, frame, fb_box)
        return out

    def _registration(
        self,
        color: np.ndarray,
        thermal_k: np.ndarray,
        opacity: float,
        overlay: SigmaOverlay | None,
        drawn: np.ndarray | None,
        out: np.ndarray,
    ) -> np.ndarray:
        """The colour image with ``opacity * sigma colour + (1 - opacity) * colour`` where
        ``drawn`` (default: the overlay's cells with an estimate) and the thermal image has
        a reading."""
        np.copyto(out, color)
        if overlay is None or opacity == 0.0:
            return out
        drawn = overlay.mask if drawn is None else drawn
        if overlay.rgb.shape != color.shape or drawn.shape != color.shape[:2]:
            raise ValueError(
                f"registration: expected an overlay and mask of {self.width}x{self.height} "
                f"pixels, got {overlay.rgb.shape[1]}x{overlay.rgb.shape[0]} and "
                f"{_describe(drawn)}"
            )
        cv2.addWeighted(overlay.rgb, opacity, color, 1.0 - opacity, 0.0, dst=self._pal)
        valid = np.isfinite(thermal_k, out=self._valid).view(np.uint8)
        cv2.bitwise_and(drawn, valid, dst=self._mask)
        cv2.copyTo(self._pal, self._mask, dst=out)
        return out

    def _emboss(self, color: np.ndarray, strength: float, out: np.ndarray) -> None:
        """out = palette + gain * (Y - box(Y)) on every channel (saturating)."""
        grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY, dst=self._index)
        low = cv2.blur(grey, (EDGE_BOX_PX, EDGE_BOX_PX), dst=self._mask)
        k = EDGE_GAIN * strength
        # detail + 128 in uint8 (saturating), then to three channels
        cv2.addWeighted(grey, k, low, -k, 128.0, dst=self._mask2, dtype=cv2.CV_8U)
        self._solid_rgb = None
        cv2.cvtColor(self._mask2, cv2.COLOR_GRAY2RGB, dst=self._rgb)
        cv2.addWeighted(self._pal, 1.0, self._rgb, 1.0, -128.0, dst=out)
