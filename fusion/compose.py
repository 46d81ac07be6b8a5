"""Display composition: one eye's colour image and reprojected thermal image into a picture.

Input per eye, at the colour camera's resolution (from ``fusion.mapping``):

- ``color``: (H, W, 3) uint8 RGB;
- ``thermal_k``: (H, W) float32 (or float64) kelvin on the colour pixels, NaN where the
  thermal imager does not see the point (outside its field of view, occluded);
- ``fallback``: (H, W) bool, True where the depth behind the mapping is a fallback
  distance (the TOF had no valid depth there), or None.

Display modes (:data:`DISPLAY_MODES`, :class:`DisplaySettings`):

``color``
    the colour image only.
``blend``
    ``opacity * palette + (1 - opacity) * colour``; opacity 0 is the colour image exactly,
    1 the palette image exactly.
``edges``
    MSX-like: the palette image with the colour image's detail embossed on it. The detail is
    the high-pass of the luminance, ``Y - box5x5(Y)``, signed, scaled by
    ``2 * edge_strength`` and added to every channel (saturating).
``thermal``
    the palette image only.
``threshold``
    the palette where the temperature is ``above`` the interval (T > high), ``below`` it
    (T < low) or ``inside`` it (low <= T <= high), the colour image elsewhere: the three
    directions partition the pixels with a reading. A single temperature T is the
    interval (T, T).
``isotherm``
    the colour image (``isotherm_background="color"``) or its greyscale (``"grey"``), with
    the pixels inside the interval (low <= T <= high) in ``isotherm_color`` (or, if None,
    their palette colour).
``pip``
    picture-in-picture: inside a rectangle (centred by default, :func:`pip_box`) the
    palette image of the same pixels (the thermal picture is registered to the colour
    image, so the inset lines up with the scene around it), the colour image outside.

Rules common to all modes:

- Pixels without a reading (NaN) always show the colour image, unchanged (also in the
  greyscale background of ``isotherm``: colour there says "no thermal reading").
- "Painted" pixels are those that show thermal information: every pixel with a reading in
  ``blend`` (opacity > 0), ``edges`` and ``thermal``; the selected ones in ``threshold``
  and ``isotherm``; the ones inside the rectangle in ``pip``; none in ``color``.
- Fallback marking (``mark_fallback``): painted fallback pixels are veiled, their colour
  moved :data:`FALLBACK_DESATURATION` of the way to its own grey (luma) and
  :data:`FALLBACK_FADE` of the way to mid-grey: muted, a little less contrast, hue and
  brightness still readable. Decision: the temperature shown at a fallback pixel is a real
  reading (only its registration is approximate), so its palette colour must stay readable,
  and the mark must not draw the eye more than the scene does (issue 19: the diagonal hatch
  it replaces did). The veil changes a pixel by a small fraction of its value (a bound in
  ``tests/test_agc.py``); a uniform grey at the veil's fixed point (mid-grey) does not
  change. Only painted pixels are marked: the colour image itself does not depend on depth.
  Pixels without a thermal view keep the plain colour image (above); the viewer's legend
  names both.

:class:`Composer` preallocates every full-frame buffer once; :meth:`Composer.compose`
allocates no full-frame array in the steady state (OpenCV calls with ``dst=``, numpy with
``out=``). The colour range is one span shared by both eyes: a fixed ``span_k`` or
:func:`auto_span` over both eyes' images (:func:`resolve_span`). Within it, palette colour
follows the frame's AGC mapping (:mod:`fusion.agc`, ``settings.agc``): a
:class:`fusion.agc.ToneMap` computed over both eyes and handed to ``compose`` for each eye
(:class:`fusion.stereo.StereoFusion` does); without one, ``compose`` maps linearly over the
span.

The stereo pair: :func:`side_by_side` (left | right), :func:`stereo_halves` (compose each
eye straight into its half), :func:`anaglyph` (red-cyan). :func:`point_colors` colours a
point cloud for the 3D view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, get_args

import cv2
import numpy as np
import numpy.typing as npt

from trifuse.calib.numbers import check_finite
from trifuse.fusion.agc import (
    AGC_MODES,
    DEFAULT_MAX_GAIN,
    DEFAULT_PLATEAU,
    AgcMode,
    PaletteIndexer,
    ToneMap,
    check_max_gain,
    check_plateau,
)
from trifuse.fusion.palettes import (
    PALETTE_NAMES,
    PaletteName,
    _check_rgb,
    _colormap_into,
    check_span,
    palette_colors,
)

__all__ = [
    "BACKGROUNDS",
    "CLOUD_COLORINGS",
    "DIRECTIONS",
    "DISPLAY_MODES",
    "CloudColoring",
    "Composer",
    "DisplayMode",
    "DisplaySettings",
    "IsothermBackground",
    "ThresholdDirection",
    "anaglyph",
    "auto_span",
    "pip_box",
    "point_colors",
    "resolve_span",
    "side_by_side",
    "stereo_halves",
]

DisplayMode = Literal["color", "blend", "edges", "thermal", "threshold", "isotherm", "pip"]
"""A display mode (the module's docstring describes each)."""
#: The display modes, in the order of :data:`DisplayMode`.
DISPLAY_MODES: tuple[DisplayMode, ...] = get_args(DisplayMode)
ThresholdDirection = Literal["above", "below", "inside"]
"""Which temperatures the ``threshold`` mode paints, relative to its interval."""
DIRECTIONS: tuple[ThresholdDirection, ...] = get_args(ThresholdDirection)
IsothermBackground = Literal["color", "grey"]
"""The background of the ``isotherm`` mode."""
BACKGROUNDS: tuple[IsothermBackground, ...] = get_args(IsothermBackground)
CloudColoring = Literal["color", "temperature", "depth"]
"""What colours a point cloud (:func:`point_colors`)."""
CLOUD_COLORINGS: tuple[CloudColoring, ...] = get_args(CloudColoring)

#: Fallback veil: the share of the way to a pixel's own grey (luma), and to mid-grey.
FALLBACK_DESATURATION = 0.35
FALLBACK_FADE = 0.05
#: Gain of the embossed detail at ``edge_strength`` 1.
EDGE_GAIN = 2.0
#: Box size of the low-pass subtracted from the luminance in ``edges`` mode.
EDGE_BOX_PX = 5
MAX_EDGE_STRENGTH = 10.0


KELVIN_RANGE = (0.0, 10_000.0)
"""Temperatures a setting may name, kelvin (absolute zero to far beyond any LWIR imager)."""
MIN_SPAN_K = 0.01
"""Narrowest colour span, kelvin (an eighth of the imagers' NETD)."""
MIN_SMOOTHING_S = 0.01
"""Shortest span smoothing time constant besides 0 (none), seconds."""


def _in_kelvin_range(interval: tuple[float, float], name: str) -> tuple[float, float]:
    low, high = KELVIN_RANGE
    if not (low <= interval[0] and interval[1] <= high):
        raise ValueError(
            f"{name}: expected temperatures in [{low:g}, {high:g}] K, "
            f"got ({interval[0]:g}, {interval[1]:g})"
        )
    return interval


def _temperature_span(value: object, name: str) -> tuple[float, float]:
    """A colour span: ``check_span``, within ``KELVIN_RANGE``, at least ``MIN_SPAN_K`` wide."""
    span = _in_kelvin_range(check_span(value, name), name)
    if span[1] - span[0] < MIN_SPAN_K - 1e-9:  # the limit itself, written in decimal, passes
        raise ValueError(
            f"{name}: expected a span at least {MIN_SPAN_K:g} K wide, "
            f"got ({span[0]:g}, {span[1]:g})"
        )
    return span


def _interval(value: object, name: str) -> tuple[float, float]:
    """(low, high) with low <= high; a single number T is (T, T)."""
    if isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool):
        t = check_finite(value, name)
        return t, t
    try:
        items = tuple(value)  # type: ignore[call-overload]
    except TypeError:
        items = ()
    if len(items) != 2:
        raise ValueError(f"{name}: expected (low_k, high_k) or one temperature, got {value!r}")
    low, high = check_finite(items[0], name), check_finite(items[1], name)
    if low > high:
        raise ValueError(f"{name}: expected low_k <= high_k, got ({low}, {high})")
    return low, high


def _pair_in(value: object, name: str, lo: float, hi: float, open_low: bool) -> tuple[float, float]:
    """A number or a pair of numbers in [lo, hi] (or (lo, hi] if open_low)."""
    if isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool):
        items: tuple[Any, ...] = (value, value)
    else:
        try:
            items = tuple(value)  # type: ignore[call-overload]
        except TypeError:
            items = ()
    if len(items) != 2:
        raise ValueError(f"{name}: expected a number or a pair of numbers, got {value!r}")
    out = (check_finite(items[0], name), check_finite(items[1], name))
    for v in out:
        if v > hi or v < lo or (open_low and v == lo):
            bound = f"({lo}, {hi}]" if open_low else f"[{lo}, {hi}]"
            raise ValueError(f"{name}: expected values in {bound}, got {value!r}")
    return out


@dataclass(frozen=True)
class DisplaySettings:
    """How to show one stereo frame; validated on construction (``ValueError``).

    Attributes:
        mode: one of :data:`DISPLAY_MODES`.
        palette: one of ``fusion.palettes.PALETTE_NAMES``.
        opacity: ``blend`` mode, 0 (colour only) .. 1 (thermal only).
        span_k: ``(low_k, high_k)`` for the palette, low < high; None = automatic
            (:func:`auto_span` with ``auto_low_pct``/``auto_high_pct`` over both eyes).
        auto_low_pct, auto_high_pct: percentiles of the automatic span, 0 <= low < high <= 100.
        threshold_k: ``(low_k, high_k)`` (low <= high) or one temperature for ``threshold``.
        threshold_direction: ``"above"`` (T > high), ``"below"`` (T < low) or ``"inside"``
            (low <= T <= high).
        isotherm_k: ``(low_k, high_k)`` (low <= high) highlighted in ``isotherm`` mode.
        isotherm_color: (R, G, B) of the highlight, or None for the palette colour.
        isotherm_background: ``"color"`` or ``"grey"``.
        edge_strength: ``edges`` mode, 0 (no detail) .. 10; 1 is a natural look.
        pip_center: (x, y) centre of the ``pip`` rectangle as fractions of width and height.
        pip_size: (width, height) of the rectangle as fractions in (0, 1] (one number: both).
        mark_fallback: veil (mute) the painted pixels whose depth came from the fallback.
        span_smoothing_s: time constant (seconds, >= 0) of the automatic span's smoothing
            over frame time, so that colours do not flicker; 0 = none. The AGC table is
            smoothed with the same time constant.
        agc: how temperatures within the span become palette positions, one of
            ``fusion.agc.AGC_MODES``: ``"plateau"`` (plateau equalization over both eyes),
            ``"linear"`` (proportional to temperature) or ``"dde"`` (plateau-equalized base
            plus amplified local detail); see :mod:`fusion.agc`. With a manual ``span_k``,
            equalization works within it.
        plateau: ``plateau``/``dde``: the largest share of the pixels one 0.1 K bin counts
            with, in [1e-4, 1]; 1 is plain histogram equalization.
        max_gain: ``plateau``/``dde``: the steepest the table may be, palette steps per
            kelvin, in [1, 1000] (a thermal camera's "max gain": a flat scene is not
            stretched into noise); an automatic span is at least ``255 / max_gain`` wide
            under these modes (:func:`fusion.agc.gain_span`).

    Numbers in lists are normalised to tuples of floats, so settings compare and hash.
    """

    mode: DisplayMode = "blend"
    palette: PaletteName = "iron"
    opacity: float = 0.6
    span_k: tuple[float, float] | None = None
    auto_low_pct: float = 1.0
    auto_high_pct: float = 99.0
    threshold_k: tuple[float, float] | float = (313.15, 313.15)
    threshold_direction: ThresholdDirection = "above"
    isotherm_k: tuple[float, float] = (303.15, 313.15)
    isotherm_color: tuple[int, int, int] | None = None
    isotherm_background: IsothermBackground = "grey"
    edge_strength: float = 1.0
    pip_center: tuple[float, float] = (0.5, 0.5)
    pip_size: tuple[float, float] | float = (0.5, 0.5)
    mark_fallback: bool = True
    span_smoothing_s: float = 1.0
    agc: AgcMode = "plateau"
    plateau: float = DEFAULT_PLATEAU
    max_gain: float = DEFAULT_MAX_GAIN

    def __post_init__(self) -> None:
        def put(name: str, value: object) -> None:
            object.__setattr__(self, name, value)

        if self.mode not in DISPLAY_MODES:
            raise ValueError(f"mode: expected one of {', '.join(DISPLAY_MODES)}, got {self.mode!r}")
        if self.palette not in PALETTE_NAMES:
            raise ValueError(
                f"palette: expected one of {', '.join(PALETTE_NAMES)}, got {self.palette!r}"
            )
        opacity = check_finite(self.opacity, "opacity")
        if not 0.0 <= opacity <= 1.0:
            raise ValueError(f"opacity: expected a number in [0, 1], got {opacity}")
        put("opacity", opacity)
        if self.span_k is not None:
            put("span_k", _temperature_span(self.span_k, "span_k"))
        low_pct = check_finite(self.auto_low_pct, "auto_low_pct")
        high_pct = check_finite(self.auto_high_pct, "auto_high_pct")
        if not 0.0 <= low_pct < high_pct <= 100.0:
            raise ValueError(
                "auto_low_pct, auto_high_pct: expected 0 <= low < high <= 100, "
                f"got ({low_pct}, {high_pct})"
            )
        put("auto_low_pct", low_pct)
        put("auto_high_pct", high_pct)
        put(
            "threshold_k",
            _in_kelvin_range(_interval(self.threshold_k, "threshold_k"), "threshold_k"),
        )
        if self.threshold_direction not in DIRECTIONS:
            raise ValueError(
                f"threshold_direction: expected one of {', '.join(DIRECTIONS)}, "
                f"got {self.threshold_direction!r}"
            )
        put("isotherm_k", _in_kelvin_range(_interval(self.isotherm_k, "isotherm_k"), "isotherm_k"))
        if self.isotherm_color is not None:
            put("isotherm_color", _check_rgb(self.isotherm_color, "isotherm_color"))
        if self.isotherm_background not in BACKGROUNDS:
            raise ValueError(
                f"isotherm_background: expected one of {', '.join(BACKGROUNDS)}, "
                f"got {self.isotherm_background!r}"
            )
        strength = check_finite(self.edge_strength, "edge_strength")
        if not 0.0 <= strength <= MAX_EDGE_STRENGTH:
            raise ValueError(
                f"edge_strength: expected a number in [0, {MAX_EDGE_STRENGTH}], got {strength}"
            )
        put("edge_strength", strength)
        put("pip_center", _pair_in(self.pip_center, "pip_center", 0.0, 1.0, open_low=False))
        put("pip_size", _pair_in(self.pip_size, "pip_size", 0.0, 1.0, open_low=True))
        if not isinstance(self.mark_fallback, bool | np.bool_):
            raise ValueError(f"mark_fallback: expected True or False, got {self.mark_fallback!r}")
        put("mark_fallback", bool(self.mark_fallback))
        smoothing = check_finite(self.span_smoothing_s, "span_smoothing_s")
        if not (smoothing == 0.0 or MIN_SMOOTHING_S <= smoothing <= 60.0):
            raise ValueError(
                f"span_smoothing_s: expected 0 (none) or seconds in [{MIN_SMOOTHING_S:g}, 60], "
                f"got {smoothing:g}"
            )
        put("span_smoothing_s", smoothing)
        if self.agc not in AGC_MODES:
            raise ValueError(f"agc: expected one of {', '.join(AGC_MODES)}, got {self.agc!r}")
        put("plateau", check_plateau(self.plateau))
        put("max_gain", check_max_gain(self.max_gain))


def pip_box(settings: DisplaySettings, width: int, height: int) -> tuple[int, int, int, int]:
    """The ``pip`` rectangle in pixels: ``(x0, y0, x1, y1)``, end-exclusive.

    Its size is ``round(pip_size * (width, height))`` (at least 1 px); it is centred on
    ``pip_center * (width, height)`` and shifted to lie wholly inside the image.
    """
    sw, sh = settings.pip_size  # type: ignore[misc]
    cx, cy = settings.pip_center
    w = min(width, max(1, round(sw * width)))
    h = min(height, max(1, round(sh * height)))
    x0 = min(max(round(cx * width - w / 2), 0), width - w)
    y0 = min(max(round(cy * height - h / 2), 0), height - h)
    return x0, y0, x0 + w, y0 + h


def auto_span(
    thermal_images: np.ndarray | Sequence[np.ndarray],
    low_pct: float = 1.0,
    high_pct: float = 99.0,
    *,
    step: int = 8,
    min_span_k: float = 1.0,
    default: tuple[float, float] | None = None,
) -> tuple[float, float]:
    """One palette span over several temperature images (both eyes): percentiles of the
    valid pixels of all of them together.

    Cheap: every ``step``-th pixel in each direction (1/64 of the pixels by default, about
    0.3 ms for two 1280 x 960 eyes). A span narrower than ``min_span_k`` (a uniform scene)
    is widened about its middle to ``min_span_k``, so noise is not stretched over the
    whole palette.

    Args:
        thermal_images: one array or a sequence of arrays of kelvin (any shape; 2-D
            images are subsampled in both directions); NaN and inf are ignored.
        low_pct, high_pct: percentiles, 0 <= low < high <= 100.
        step: subsampling step, positive.
        min_span_k: the narrowest span returned, positive.
        default: returned when no image has a finite pixel; if None, that is a ValueError.

    Returns:
        ``(low_k, high_k)`` with ``low < high``.
    """
    low_pct = check_finite(low_pct, "low_pct")
    high_pct = check_finite(high_pct, "high_pct")
    if not 0.0 <= low_pct < high_pct <= 100.0:
        raise ValueError(
            f"low_pct, high_pct: expected 0 <= low < high <= 100, got ({low_pct}, {high_pct})"
        )
    if isinstance(step, bool) or not isinstance(step, int | np.integer) or step < 1:
        raise ValueError(f"step: expected a positive integer, got {step!r}")
    if not check_finite(min_span_k, "min_span_k") > 0.0:
        raise ValueError(f"min_span_k: expected a positive number, got {min_span_k}")
    images = [thermal_images] if isinstance(thermal_images, np.ndarray) else list(thermal_images)
    samples = []
    for i, image in enumerate(images):
        a = np.asarray(image)
        if a.dtype.kind not in "fiu":
            raise ValueError(f"thermal_images[{i}]: expected numbers in kelvin, got {a.dtype}")
        sub = a[..., ::step, ::step] if a.ndim >= 2 else a.reshape(-1)[::step]
        samples.append(sub[np.isfinite(sub)])  # 1-D, no copy of the subsample itself
    values = np.concatenate(samples) if samples else np.empty(0)
    if values.size == 0:
        if default is not None:
            return check_span(default, "default")
        raise ValueError("thermal_images: expected at least one finite temperature, got none")
    low, high = (float(v) for v in np.percentile(values, [low_pct, high_pct]))
    if high - low < min_span_k:
        mid = 0.5 * (low + high)
        low, high = mid - 0.5 * min_span_k, mid + 0.5 * min_span_k
    return low, high


def resolve_span(
    settings: DisplaySettings, thermal_images: np.ndarray | Sequence[np.ndarray]
) -> tuple[float, float]:
    """The span to use for one stereo frame: ``settings.span_k``, or :func:`auto_span`
    over ``thermal_images`` (pass both eyes so they share it). An all-NaN frame gets the
    arbitrary span (273.15, 373.15): nothing is painted then anyway."""
    if settings.span_k is not None:
        return settings.span_k
    return auto_span(
        thermal_images,
        settings.auto_low_pct,
        settings.auto_high_pct,
        default=(273.15, 373.15),
    )


def _describe(a: object) -> str:
    if isinstance(a, np.ndarray):
        return f"{a.dtype} array of shape {a.shape}"
    return type(a).__name__


class Composer:
    """Composes display pictures of one eye of a fixed size, with preallocated buffers.

    Use one per eye (or one for both, called in turn: ``compose`` is not re-entrant).

    Args:
        width, height: the colour image size in pixels.
    """

    def __init__(self, width: int, height: int) -> None:
        for n, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v <= 0:
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
        luma). Work is limited to the intersection with ``fallback_box``, the bounding box
        of the fallback pixels. Uses ``_pal`` and ``_mask`` as scratch."""
        x0, y0 = max(box[0], fallback_box[0]), max(box[1], fallback_box[1])
        x1, y1 = min(box[2], fallback_box[2]), min(box[3], fallback_box[3])
        if x0 >= x1 or y0 >= y1:
            return
        sl = (slice(y0, y1), slice(x0, x1))
        base = fallback[sl].view(np.uint8)
        if paint is not None:
            base = cv2.bitwise_and(base, paint[sl], dst=self._mask2[sl])
        o = out[sl]
        grey = cv2.cvtColor(o, cv2.COLOR_RGB2GRAY, dst=self._mask[sl])
        veil = cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB, dst=self._pal[sl])
        d, f = FALLBACK_DESATURATION, FALLBACK_FADE
        cv2.addWeighted(o, 1.0 - d - f, veil, d, 128.0 * f, dst=veil)
        cv2.copyTo(veil, base, dst=o)

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


# -- the stereo pair -----------------------------------------------------------------------------


def _check_pair(left: np.ndarray, right: np.ndarray) -> tuple[int, int]:
    for name, a in (("left", left), ("right", right)):
        if not isinstance(a, np.ndarray) or a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"{name}: expected a uint8 (H, W, 3) image, got {_describe(a)}")
    if left.shape != right.shape:
        raise ValueError(f"right: expected the shape of left {left.shape}, got {right.shape}")
    return left.shape[0], left.shape[1]


def stereo_halves(sbs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The left and right (H, W, 3) views of a side-by-side (H, 2W, 3) buffer, to compose
    each eye straight into its half (``Composer.compose(..., out=half)``)."""
    if not isinstance(sbs, np.ndarray) or sbs.dtype != np.uint8 or sbs.ndim != 3:
        raise ValueError(f"sbs: expected a uint8 (H, 2W, 3) image, got {_describe(sbs)}")
    if sbs.shape[2] != 3 or sbs.shape[1] % 2:
        raise ValueError(f"sbs: expected shape (H, 2W, 3) with an even width, got {sbs.shape}")
    w = sbs.shape[1] // 2
    return sbs[:, :w], sbs[:, w:]


def side_by_side(left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The stereo pair side by side, left | right: (H, 2W, 3) uint8.

    Args:
        left, right: (H, W, 3) uint8 of the same shape.
        out: (H, 2W, 3) uint8 buffer; allocated if None (pass one per frame).
    """
    h, w = _check_pair(left, right)
    if out is None:
        out = np.empty((h, 2 * w, 3), np.uint8)
    elif not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (h, 2 * w, 3):
        raise ValueError(f"out: expected uint8 ({h}, {2 * w}, 3), got {_describe(out)}")
    lo, ro = stereo_halves(out)
    np.copyto(lo, left)
    np.copyto(ro, right)
    return out


def anaglyph(
    left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None, method: str = "color"
) -> np.ndarray:
    """Red-cyan anaglyph of the pair: (H, W, 3) uint8 RGB (red lens on the left eye).

    Args:
        left, right: (H, W, 3) uint8 RGB of the same shape.
        out: (H, W, 3) uint8 buffer; allocated if None; must not overlap the inputs.
        method: ``"color"``: red from the left image, green and blue from the right;
            ``"grey"``: red = the left's luminance, green = blue = the right's (less
            retinal rivalry, no colour; allocates two grey images).
    """
    h, w = _check_pair(left, right)
    if out is None:
        out = np.empty((h, w, 3), np.uint8)
    elif not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (h, w, 3):
        raise ValueError(f"out: expected uint8 ({h}, {w}, 3), got {_describe(out)}")
    if np.may_share_memory(out, left) or np.may_share_memory(out, right):
        raise ValueError("out: must not overlap left or right")
    if method == "color":
        cv2.mixChannels([left, right], [out], [0, 0, 4, 1, 5, 2])
    elif method == "grey":
        gl = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
        gr = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
        cv2.mixChannels([gl, gr], [out], [0, 0, 1, 1, 1, 2])
    else:
        raise ValueError(f"method: expected 'color' or 'grey', got {method!r}")
    return out


# -- the 3D view ---------------------------------------------------------------------------------


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
