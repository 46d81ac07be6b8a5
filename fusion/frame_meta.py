"""The metadata of one fused picture (:class:`FrameMeta`), built once per picture by
:meth:`fusion.stereo_step.StereoStep.meta`.

The console sends it with each frame (:meth:`FrameMeta.as_json`, the JSON the viewer
overlays: time stamp, display mode, colour scale, missing sensors, hot and cold spots,
sensors' health; in the ``registration`` mode the legend of its colour map); ``trifuse
fuse`` writes its stamps into ``frames.csv``. For the viewer's colour scale it carries the
palette and the span the picture was coloured with
(:class:`ColourScale`: ``palette``, ``palette_rgb``, ``span_k``, ``span_auto``, the AGC
mode ``agc`` and ``palette_ticks_k``, the temperature at evenly spaced palette positions;
null when the picture shows no palette colour). Pure: no I/O.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from trifuse.fusion.agc import ToneMap
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.palettes import palette

PALETTE_TICKS = 9
"""The colour scale's ticks: palette positions 0, 1/8, ..., 1 (first entry to last)."""
_SCALE_KEYS = ("palette", "palette_rgb", "span_k", "span_auto", "agc", "palette_ticks_k")


def shows_palette(settings: DisplaySettings) -> bool:
    """Whether a picture made with ``settings`` shows palette colours (so the viewer shows
    a colour scale): not in ``color`` mode, not in ``registration`` (its colour map has a
    scale of its own: :attr:`FrameMeta.registration`), not in ``blend`` at opacity 0, not
    in ``isotherm`` with a fixed highlight colour."""
    if settings.mode in ("color", "registration"):
        return False
    if settings.mode == "blend" and settings.opacity == 0.0:
        return False
    return not (settings.mode == "isotherm" and settings.isotherm_color is not None)


@functools.cache
def palette_hex(name: str) -> str:
    """Palette ``name``'s 256 RGB entries, cold end first, as one string of 1536 hex digits
    (``"000000..."``: two per channel), for the viewer's colour scale."""
    return palette(name).tobytes().hex()


@dataclass(frozen=True)
class ColourScale:
    """What the viewer's colour scale needs: the palette's name, the span ``(low, high)``
    kelvin (the palette's first entry is ``low``, its last ``high``), whether the span
    follows the picture (``span_auto``) or is the operator's, the AGC mode of the picture's
    mapping (``agc``; "linear" without a table), the temperatures (kelvin) at
    :data:`PALETTE_TICKS` evenly spaced palette positions from the first entry to the last
    (non-linear under equalization), and ``mark_fallback`` (the legend of the marking)."""

    palette: str
    span_k: tuple[float, float]
    span_auto: bool
    agc: str
    palette_ticks_k: tuple[float, ...]
    mark_fallback: bool

    @classmethod
    def of(
        cls,
        settings: DisplaySettings,
        span_k: tuple[float, float] | None,
        tone: ToneMap | None = None,
    ) -> ColourScale | None:
        """The scale of a picture made with ``settings`` over ``span_k`` (kelvin) through
        ``tone`` (None: linear over the span); None when the picture shows no palette
        colour or there is no span."""
        if span_k is None or not shows_palette(settings):
            return None
        tone = tone or ToneMap.linear(span_k)
        return cls(
            settings.palette,
            (float(span_k[0]), float(span_k[1])),
            settings.span_k is None,
            tone.mode,
            tuple(round(t, 3) for t in tone.ticks_k(PALETTE_TICKS)),
            settings.mark_fallback,
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "palette": self.palette,
            "palette_rgb": palette_hex(self.palette),
            "span_k": list(self.span_k),
            "span_auto": self.span_auto,
            "agc": self.agc,
            "palette_ticks_k": list(self.palette_ticks_k),
            "mark_fallback": self.mark_fallback,
        }


def scale_meta(
    settings: DisplaySettings, span_k: tuple[float, float] | None, tone: ToneMap | None = None
) -> dict[str, Any]:
    """The colour scale's JSON (:class:`ColourScale`): ``palette``, ``palette_rgb``
    (:func:`palette_hex`), ``span_k`` ([low, high] kelvin), ``span_auto``, ``agc``,
    ``palette_ticks_k`` and ``mark_fallback``; all None when the picture shows no palette
    colour or there is no span."""
    scale = ColourScale.of(settings, span_k, tone)
    if scale is None:
        return {**dict.fromkeys(_SCALE_KEYS), "mark_fallback": None}
    return scale.as_json()


@dataclass(frozen=True)
class FrameMeta:
    """The metadata of one fused picture.

    Attributes:
        stamp_ns: the frame set's stamp.
        tof_stamp_ns: the stamp of the TOF frame behind the mapping (None: none yet).
        mode: the display mode shown (``color`` for the colour images before any depth).
        scale: the colour scale, None when the picture shows no palette colour.
        missing: the set's missing sensors, sorted.
        spots: the hot and cold spot of each eye (:meth:`fusion.spot.SpotFrame.extremes`),
            or None.
        health: sensor -> a line for each sensor that is not ok, or None (no report).
        registration: in the ``registration`` mode, the legend of its colour map
            (:func:`fusion.registration_overlay.registration_meta`: the scale in colour
            pixels, the colour map, each eye's median and 95th percentile); else None.
    """

    stamp_ns: int
    tof_stamp_ns: int | None
    mode: str
    scale: ColourScale | None
    missing: tuple[str, ...]
    spots: Mapping[str, Any] | None = None
    health: Mapping[str, str] | None = None
    registration: Mapping[str, Any] | None = None

    def as_json(self) -> dict[str, Any]:
        """The frame's JSON for the viewer: ``stamp_ns``, ``mode``, the colour scale's keys
        (:func:`scale_meta`; null without one), ``missing``, and ``spots``, ``health`` and
        ``registration`` when there are."""
        if self.scale is None:
            scale: dict[str, Any] = {**dict.fromkeys(_SCALE_KEYS), "mark_fallback": None}
        else:
            scale = self.scale.as_json()
        meta = {
            "stamp_ns": self.stamp_ns,
            "mode": self.mode,
            **scale,
            "missing": list(self.missing),
        }
        if self.spots is not None:
            meta["spots"] = self.spots
        if self.health is not None:
            meta["health"] = dict(self.health)
        if self.registration is not None:
            meta["registration"] = dict(self.registration)
        return meta
