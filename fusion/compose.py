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
``registration``
    the registration uncertainty: each pixel's registration sigma (how far, 1-sigma, in
    colour pixels, the thermal value drawn there may land from where it belongs:
    :mod:`fusion.registration`) as a colour map over the colour image, blended like
    ``blend`` (``opacity``), on a fixed scale of 0 to 2 colour pixels (clipped above:
    :mod:`fusion.registration_overlay`). The sigma is estimated on the fusion's coarse
    grid, off the picture's path (the console every 2 s: :attr:`fusion.stereo.StereoFusion.
    registration`); pixels without an estimate (none yet, no TOF depth, a depth edge) show
    the colour image. Only the console draws it (:data:`CONSOLE_ONLY_MODES`).

Rules common to all modes:

- Pixels without a reading (NaN) always show the colour image, unchanged (also in the
  greyscale background of ``isotherm``: colour there says "no thermal reading").
- "Painted" pixels are those that show thermal information: every pixel with a reading in
  ``blend`` (opacity > 0), ``edges`` and ``thermal``; the selected ones in ``threshold``
  and ``isotherm``; the ones inside the rectangle in ``pip``; those with a sigma estimate
  in ``registration`` (shown in the colour map, not the palette); none in ``color``.
- Fallback marking (``mark_fallback``): painted fallback pixels are veiled, their colour
  moved :data:`FALLBACK_DESATURATION` of the way to its own grey (luma) and
  :data:`FALLBACK_FADE` of the way to mid-grey: muted, a little less contrast, hue and
  brightness still readable. Decision: the temperature shown at a fallback pixel is a real
  reading (only its registration is approximate), so its palette colour must stay readable,
  and the mark must not draw the eye more than the scene does (issue 19: the diagonal hatch
  it replaces did). The veil changes a pixel by a small fraction of its value (a bound in
  ``tests/fusion/test_agc.py``); a uniform grey at the veil's fixed point (mid-grey) does not
  change. Only painted pixels are marked: the colour image itself does not depend on depth.
  Pixels without a thermal view keep the plain colour image (above); the viewer's legend
  names both.
What is drawn is set here (:class:`DisplaySettings`, :func:`pip_box`); the modes are
drawn by :class:`fusion.composer.Composer` (one eye, preallocated buffers), over one span
shared by both eyes (:func:`fusion.span.resolve_span`); the stereo pair is put together
by :mod:`fusion.stereo_pair`, and :mod:`fusion.cloud_colors` colours point clouds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

from trifuse.calib.numbers import check_finite, is_integer
from trifuse.fusion.agc import (
    AGC_MODES,
    DEFAULT_MAX_GAIN,
    DEFAULT_PLATEAU,
    AgcMode,
    check_max_gain,
    check_plateau,
)
from trifuse.fusion.palettes import PALETTE_NAMES, PaletteName, _check_rgb, check_span

__all__ = [
    "BACKGROUNDS",
    "CONSOLE_ONLY_MODES",
    "DIRECTIONS",
    "DISPLAY_MODES",
    "DisplayMode",
    "DisplaySettings",
    "IsothermBackground",
    "ThresholdDirection",
    "describe_array",
    "pip_box",
]

DisplayMode = Literal[
    "color", "blend", "edges", "thermal", "threshold", "isotherm", "pip", "registration"
]
"""A display mode (the module's docstring describes each)."""
#: The display modes, in the order of :data:`DisplayMode`.
DISPLAY_MODES: tuple[DisplayMode, ...] = get_args(DisplayMode)
#: Modes only the console draws: they show what its background work estimates
#: (``registration``); ``trifuse fuse`` and ``record --video-mode`` do not offer them.
CONSOLE_ONLY_MODES: tuple[DisplayMode, ...] = ("registration",)
ThresholdDirection = Literal["above", "below", "inside"]
"""Which temperatures the ``threshold`` mode paints, relative to its interval."""
DIRECTIONS: tuple[ThresholdDirection, ...] = get_args(ThresholdDirection)
IsothermBackground = Literal["color", "grey"]
"""The background of the ``isotherm`` mode."""
BACKGROUNDS: tuple[IsothermBackground, ...] = get_args(IsothermBackground)

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
    if is_integer(value) or isinstance(value, float | np.floating):
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
    if is_integer(value) or isinstance(value, float | np.floating):
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
        opacity: ``blend`` mode, 0 (colour only) .. 1 (thermal only); ``registration``
            mode likewise, the colour map for the palette.
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


def describe_array(a: object) -> str:
    """``a`` for an error message: its dtype and shape, or its type."""
    if isinstance(a, np.ndarray):
        return f"{a.dtype} array of shape {a.shape}"
    return type(a).__name__
