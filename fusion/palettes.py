"""Thermal palettes: 256-entry RGB tables and their fast application to kelvin images.

The palettes are the ones an operator of FLIR or Fluke imagers expects by name. Each table
is built here from a handful of control points (position in [0, 1], RGB), interpolated
linearly in RGB; the control points are ours, chosen so that:

- ``white_hot`` / ``black_hot`` are exact grey ramps (0 -> 255 and 255 -> 0);
- ``iron`` (ironbow), ``lava`` and ``arctic`` have a non-decreasing luminance
  (Rec. 601 luma) from the cold end to the hot end, so that "brighter is hotter" holds for
  them as it does for the grey ramps; because luma is linear in RGB, it is enough that the
  control points' luma increases;
- ``rainbow`` is a hue sweep violet -> blue -> cyan -> green -> yellow -> orange -> red for
  the most distinguishable small differences (not monotone in luminance, on purpose).

A temperature image (H, W) float kelvin becomes an index image (H, W) uint8 with
``index = round(255 * (T - low) / (high - low))`` saturated to [0, 255]
(:func:`temperature_index`, one ``cv2.addWeighted``), and the index image becomes colour
with ``cv2.applyColorMap(index, userColor=lut)`` (:func:`apply_palette`). OpenCV's docs speak
of colormaps in BGR, but with a user table ``applyColorMap`` is a plain per-channel look-up:
the channels of the output are the channels of the table in the same order (checked on
OpenCV 5.0), so an RGB table gives RGB and no conversion is needed. Both calls write into
preallocated buffers (``out=``), which matters at 1280 x 960 (see FIELD-NOTES.md).

Non-finite temperatures (NaN = no reading) get an unspecified index; mask them, as
:class:`fusion.composer.Composer` does, or pass ``nan_color`` to :func:`apply_palette`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal, get_args

import cv2
import numpy as np
import numpy.typing as npt

from trifuse.calib.numbers import is_integer

__all__ = [
    "CONTROL_POINTS",
    "PALETTE_NAMES",
    "PaletteName",
    "apply_palette",
    "check_span",
    "palette",
    "palette_bar",
    "palette_colors",
    "palette_lut",
    "temperature_index",
]

PaletteName = Literal["iron", "rainbow", "white_hot", "black_hot", "arctic", "lava"]
"""A palette's name, in the order a user interface lists them."""
#: The palette names, in the order of :data:`PaletteName`.
PALETTE_NAMES: tuple[PaletteName, ...] = get_args(PaletteName)

#: Control points of every palette: (position in [0, 1], (R, G, B)). Position 0 is the cold
#: end of the span, 1 the hot end; the first and last points are the table's first and last
#: entries exactly.
CONTROL_POINTS: dict[PaletteName, tuple[tuple[float, tuple[int, int, int]], ...]] = {
    # black -> indigo -> purple -> red -> orange -> yellow -> near white (luma 0 .. 252)
    "iron": (
        (0.00, (0, 0, 0)),
        (0.15, (40, 0, 110)),
        (0.35, (140, 0, 150)),
        (0.55, (220, 60, 20)),
        (0.75, (250, 140, 0)),
        (0.90, (255, 220, 40)),
        (1.00, (255, 255, 230)),
    ),
    # a hue sweep, cold violet to hot red
    "rainbow": (
        (0.00, (40, 0, 90)),
        (0.15, (0, 0, 230)),
        (0.35, (0, 200, 255)),
        (0.50, (0, 220, 80)),
        (0.65, (240, 240, 0)),
        (0.82, (255, 110, 0)),
        (1.00, (230, 0, 0)),
    ),
    "white_hot": ((0.0, (0, 0, 0)), (1.0, (255, 255, 255))),
    "black_hot": ((0.0, (255, 255, 255)), (1.0, (0, 0, 0))),
    # cold in blues (navy -> light steel blue), warm in golds (tan -> orange -> pale yellow)
    "arctic": (
        (0.00, (0, 5, 40)),
        (0.30, (20, 70, 170)),
        (0.50, (110, 150, 200)),
        (0.55, (170, 140, 110)),
        (0.75, (240, 160, 40)),
        (1.00, (255, 245, 170)),
    ),
    # black -> dark teal -> dark red -> red -> orange -> yellow -> white
    "lava": (
        (0.00, (0, 0, 0)),
        (0.20, (0, 60, 80)),
        (0.35, (150, 10, 20)),
        (0.50, (220, 30, 0)),
        (0.70, (255, 130, 0)),
        (0.88, (255, 230, 60)),
        (1.00, (255, 255, 255)),
    ),
}


def _build(points: Sequence[tuple[float, tuple[int, int, int]]]) -> np.ndarray:
    pos = np.array([p for p, _ in points], dtype=np.float64)
    rgb = np.array([c for _, c in points], dtype=np.float64)
    x = np.linspace(0.0, 1.0, 256)
    table = np.stack([np.interp(x, pos, rgb[:, k]) for k in range(3)], axis=1)
    table = np.clip(np.rint(table), 0, 255).astype(np.uint8)
    table.flags.writeable = False
    return table


_TABLES: dict[str, np.ndarray] = {name: _build(CONTROL_POINTS[name]) for name in PALETTE_NAMES}
# OpenCV's shape for a user colormap: (256, 1, 3) CV_8UC3, contiguous.
_LUTS: dict[str, np.ndarray] = {}
for _name, _table in _TABLES.items():
    _lut = np.ascontiguousarray(_table.reshape(256, 1, 3))
    _lut.flags.writeable = False
    _LUTS[_name] = _lut


def _check_name(name: object) -> str:
    if not isinstance(name, str) or name not in _TABLES:
        raise ValueError(f"palette: expected one of {', '.join(PALETTE_NAMES)}, got {name!r}")
    return name


def palette(name: str) -> np.ndarray:
    """The (256, 3) uint8 RGB table of palette ``name`` (read-only); entry 0 is the cold end.

    Raises:
        ValueError: unknown name.
    """
    return _TABLES[_check_name(name)]


def palette_lut(name: str) -> np.ndarray:
    """The same table shaped (256, 1, 3) for ``cv2.applyColorMap(src, userColor=...)``."""
    return _LUTS[_check_name(name)]


def check_span(span: object, name: str = "span") -> tuple[float, float]:
    """Validate a temperature span ``(low_k, high_k)``: two finite floats, low < high.

    Returns:
        ``(low_k, high_k)`` as plain floats.

    Raises:
        ValueError: naming ``name``, what was expected and what arrived.
    """
    try:
        low, high = (float(v) for v in span)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: expected (low_k, high_k), two finite numbers, got {span!r}"
        ) from None
    if not (math.isfinite(low) and math.isfinite(high)) or not low < high:
        raise ValueError(f"{name}: expected finite low_k < high_k, got ({low}, {high})")
    return low, high


def _check_image(a: np.ndarray, name: str) -> None:
    if not isinstance(a, np.ndarray) or a.dtype not in (np.float32, np.float64) or a.ndim != 2:
        got = (
            f"{a.dtype} array of shape {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
        )
        raise ValueError(f"{name}: expected a (H, W) float32 or float64 array in kelvin, got {got}")


def _check_out(out: np.ndarray, shape: tuple[int, ...], name: str) -> None:
    if not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != shape:
        got = (
            f"{out.dtype} array of shape {out.shape}"
            if isinstance(out, np.ndarray)
            else type(out).__name__
        )
        raise ValueError(f"{name}: expected a uint8 array of shape {shape}, got {got}")
    pixel_strides = (1,) if out.ndim == 2 else (3, 1)
    if out.strides[1:] != pixel_strides:
        raise ValueError(f"{name}: expected rows of contiguous pixels (a row slice is fine)")


def temperature_index(
    thermal_k: np.ndarray, span: tuple[float, float], out: np.ndarray | None = None
) -> np.ndarray:
    """Palette index of every pixel: ``round(255 * (T - low) / (high - low))`` in [0, 255].

    ``low`` maps to 0 and ``high`` to 255; colder and hotter pixels saturate. One
    ``cv2.addWeighted`` (about 0.35 ms at 1280 x 960).

    Args:
        thermal_k: (H, W) float32/float64 temperatures in kelvin.
        span: ``(low_k, high_k)``.
        out: (H, W) uint8 buffer to write into (a view with strided rows is fine);
            allocated if None.

    Returns:
        ``out``: (H, W) uint8. Non-finite temperatures give an unspecified index.
    """
    _check_image(thermal_k, "thermal_k")
    low, high = check_span(span)
    if out is None:
        out = np.empty(thermal_k.shape, np.uint8)
    else:
        _check_out(out, thermal_k.shape, "out")
    _index_into(thermal_k, low, high, out)
    return out


def _index_into(thermal_k: np.ndarray, low: float, high: float, out: np.ndarray) -> None:
    """Unchecked :func:`temperature_index` (``out`` is written, never reallocated)."""
    scale = 255.0 / (high - low)
    cv2.addWeighted(thermal_k, scale, thermal_k, 0.0, -low * scale, dst=out, dtype=cv2.CV_8U)


def _colormap_into(index: np.ndarray, name: str, out: np.ndarray) -> None:
    """Unchecked palette look-up of a uint8 index image into ``out`` (H, W, 3)."""
    cv2.applyColorMap(index, _LUTS[name], dst=out)


def apply_palette(
    thermal_k: np.ndarray,
    span: tuple[float, float],
    name: str = "iron",
    out: np.ndarray | None = None,
    index_out: np.ndarray | None = None,
    nan_color: tuple[int, int, int] | None = None,
) -> np.ndarray:
    """Colour a temperature image with a palette: RGB (H, W, 3) uint8.

    About 1.2 ms at 1280 x 960 with preallocated ``out`` and ``index_out``.

    Args:
        thermal_k: (H, W) float32/float64 kelvin.
        span: ``(low_k, high_k)``: low gets the palette's first entry, high its last.
        name: one of :data:`PALETTE_NAMES`.
        out: (H, W, 3) uint8 buffer for the result; allocated if None.
        index_out: (H, W) uint8 scratch buffer for the index image; allocated if None.
        nan_color: if given, non-finite pixels get this RGB colour (costs a mask, which
            is allocated); otherwise their colour is unspecified.

    Returns:
        ``out``.
    """
    name = _check_name(name)
    index = temperature_index(thermal_k, span, index_out)
    h, w = thermal_k.shape
    if out is None:
        out = np.empty((h, w, 3), np.uint8)
    else:
        _check_out(out, (h, w, 3), "out")
    _colormap_into(index, name, out)
    if nan_color is not None:
        out[~np.isfinite(thermal_k)] = _check_rgb(nan_color, "nan_color")
    return out


def _check_rgb(color: object, name: str) -> tuple[int, int, int]:
    try:
        values = tuple(color)  # type: ignore[call-overload]
    except TypeError:
        values = ()
    if len(values) != 3 or not all(is_integer(v) and 0 <= v <= 255 for v in values):
        raise ValueError(f"{name}: expected an (R, G, B) triple of integers 0-255, got {color!r}")
    return (int(values[0]), int(values[1]), int(values[2]))


def palette_colors(
    values: npt.ArrayLike,
    span: tuple[float, float],
    name: str = "iron",
    nan_color: tuple[int, int, int] = (128, 128, 128),
) -> np.ndarray:
    """Palette colours of arbitrary values (e.g. per point): (..., 3) uint8 RGB.

    Same mapping as :func:`temperature_index` (numpy, for small arrays such as a point
    cloud; allocates). Non-finite values get ``nan_color``.
    """
    table = palette(name)
    low, high = check_span(span)
    nan_rgb = _check_rgb(nan_color, "nan_color")
    v = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(v)
    with np.errstate(invalid="ignore"):
        idx = np.rint((np.where(finite, v, low) - low) * (255.0 / (high - low)))
    idx = np.clip(idx, 0, 255).astype(np.intp)
    colors = table[idx]
    colors[~finite] = nan_rgb
    return colors


def palette_bar(name: str, width: int, height: int, orientation: str | None = None) -> np.ndarray:
    """A legend image of palette ``name``: (height, width, 3) uint8 RGB.

    Args:
        name: one of :data:`PALETTE_NAMES`.
        width, height: size in pixels.
        orientation: ``"horizontal"`` (cold at the left, hot at the right) or
            ``"vertical"`` (hot at the top, as beside a thermal image); default vertical if
            ``height > width``, else horizontal.

    The first and last pixel along the bar are the palette's first and last entries.
    """
    table = palette(name)
    for n, v in (("width", width), ("height", height)):
        if not is_integer(v) or v <= 0:
            raise ValueError(f"{n}: expected a positive integer, got {v!r}")
    if orientation is None:
        orientation = "vertical" if height > width else "horizontal"
    if orientation not in ("horizontal", "vertical"):
        raise ValueError(
            f"orientation: expected 'horizontal', 'vertical' or None, got {orientation!r}"
        )
    length = int(width) if orientation == "horizontal" else int(height)
    idx = np.rint(np.linspace(0.0, 255.0, length)).astype(np.intp) if length > 1 else np.array([0])
    line = table[idx]  # (length, 3)
    if orientation == "horizontal":
        return np.ascontiguousarray(np.broadcast_to(line[None, :, :], (height, width, 3)))
    return np.ascontiguousarray(np.broadcast_to(line[::-1, None, :], (height, width, 3)))
