"""The video stream's presets (``/stream.video``, docs/FORMATS.md): what a viewer picks
(:data:`PRESETS`), the ladder of levels the rate controller moves on (:data:`LEVELS`:
bitrate cap, picture size, frame rate), the rungs the viewers' encoders run at
(:func:`rung_for`: viewers on one rung share one encoder) and the console-wide default
preset (:class:`StreamSettings`). The encoder is :class:`app.recording.h264.VideoEncoder`.
"""

from __future__ import annotations

import math
import threading
import typing
from dataclasses import dataclass
from typing import Literal

from trifuse.app.recording.h264 import MIN_BPS, Level

VideoPreset = Literal["auto", "8", "4", "2", "1"]
"""A viewer's choice: ``auto`` (the ladder follows the link) or a level's name (Mbit/s)."""
PRESETS: tuple[str, ...] = typing.get_args(VideoPreset)
DEFAULT_PRESET: VideoPreset = "auto"

LEVELS: tuple[Level, ...] = (
    Level("8", 8_000_000, (2560, 960), 30),
    Level("4", 4_000_000, (1920, 720), 30),
    Level("2", 2_000_000, (1280, 480), 25),
    Level("1", 1_000_000, (1280, 480), 15),
)
"""Highest first. ``auto`` uses the highest level whose ``max_bps`` the bitrate target
reaches (the lowest below 1 Mbit/s); a fixed preset caps the bitrate at its level's."""
LEVEL_BY_NAME: dict[str, Level] = {lv.name: lv for lv in LEVELS}


def check_preset(preset: str) -> VideoPreset:
    """``preset`` if it is one of :data:`PRESETS` (ValueError naming them otherwise)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown video preset {preset!r}: expected one of {list(PRESETS)}")
    return typing.cast(VideoPreset, preset)


def level_for(preset: str, bitrate_bps: float) -> Level:
    """The level a viewer with ``preset`` uses at ``bitrate_bps``: a fixed preset's own;
    ``auto``: the highest level whose cap the bitrate reaches (else the lowest)."""
    if check_preset(preset) != "auto":
        return LEVEL_BY_NAME[preset]
    for lv in LEVELS:
        if bitrate_bps >= lv.max_bps:
            return lv
    return LEVELS[-1]


RUNG_STEP = 0.7
"""The bitrates an encoder runs at on a level: the level's cap times a power of this
(8, 5.6, 3.9 ... Mbit/s on level ``8``), down to :data:`app.recording.h264.MIN_BPS`. One
congestion step of the rate controller (``video_rate.DECREASE``, the same factor) moves a
viewer one rung down."""


@dataclass(frozen=True)
class Rung:
    """What one shared encoder of ``/stream.video`` makes: ``level`` (picture size, frame
    rate) at ``bitrate_bps`` (bit/s). Viewers on the same rung get the same access units."""

    level: Level
    bitrate_bps: int


def rung_for(level: Level, bitrate_bps: float) -> Rung:
    """The rung of a viewer whose rate controller aims at ``bitrate_bps`` (bit/s) on
    ``level``: the highest ``level.max_bps * RUNG_STEP**k`` (k = 0, 1, ...) not above it,
    and not below :data:`app.recording.h264.MIN_BPS`."""
    cap = level.max_bps
    if bitrate_bps >= cap:
        return Rung(level, cap)
    if bitrate_bps <= MIN_BPS:
        return Rung(level, MIN_BPS)
    k = math.ceil(math.log(bitrate_bps / cap) / math.log(RUNG_STEP) - 1e-9)
    return Rung(level, max(MIN_BPS, round(cap * RUNG_STEP**k)))


class StreamSettings:
    """The console-wide video settings (``ctx.stream_settings``; ``/api/stream/settings``,
    the GUI's dropdown). ``preset``: the preset of viewers that ask for none; setting an
    unknown one raises ValueError. Thread-safe (a plain attribute swap)."""

    def __init__(self, preset: str = DEFAULT_PRESET) -> None:
        self._lock = threading.Lock()
        self._preset: VideoPreset = check_preset(preset)

    @property
    def preset(self) -> VideoPreset:
        return self._preset

    @preset.setter
    def preset(self, value: str) -> None:
        checked = check_preset(value)
        with self._lock:
            self._preset = checked
