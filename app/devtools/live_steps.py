"""The steps a fused frame set needs, each measured alone (benchmark ``live``, issue 32): what
the console's cost per frame set is compared with.

Measured in the benchmark's own process on the recording it replays, in CPU time
(``time.process_time``) on one OpenCV thread (the work itself: what OpenCV's thread pool
adds, the console counts as its own), medians:

- ``read_<sensor>_ms``: reading one frame of the sensor from the recording and decoding it
  (a colour JPEG, a thermal or TOF plane), as the replay does;
- ``map_ms``: both eyes' mappings from one TOF frame (one after the other);
- ``compose_ms``: one picture from a frame set whose depth is mapped (radiometry, warp, AGC,
  composition: :meth:`fusion.stereo_step.StereoStep.render`);
- ``h264_ms``: encoding one picture for an H.264 viewer (the top level of the ladder).

:func:`necessary_ms` weighs them by what a frame set needs at the rates the console ran at.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

import cv2

T = TypeVar("T")

SAMPLES = 20
"""Pictures composed and encoded, TOF frames mapped (medians)."""


def _cpu_ms(fn: Callable[[], object]) -> float:
    return _timed(fn)[1]


def _timed(fn: Callable[[], T]) -> tuple[T, float]:
    """``fn()`` and the CPU time it took, ms."""
    t0 = time.process_time()
    value = fn()
    return value, (time.process_time() - t0) * 1e3


def step_costs(recording: Path) -> dict[str, float]:
    """The steps' CPU times (ms, see the module doc) on ``recording``'s frames."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _costs(recording)
    finally:
        cv2.setNumThreads(threads)


def _costs(recording: Path) -> dict[str, float]:
    from trifuse.app.recording.h264 import VideoEncoder
    from trifuse.app.recording.reader import ReplaySource
    from trifuse.app.server.runtime.video_presets import LEVELS
    from trifuse.app.sources.base import FrameSetAssembler
    from trifuse.fusion.compose import DisplaySettings
    from trifuse.fusion.stereo_step import CONSOLE, Skip, StereoStep

    reads: dict[str, list[float]] = {}
    frames = []
    with ReplaySource(recording, realtime=False) as src:
        rig = src.rig
        it = src.frames()
        while True:
            t0 = time.process_time()
            frame = next(it, None)
            if frame is None:
                break
            reads.setdefault(frame.sensor, []).append((time.process_time() - t0) * 1e3)
            frames.append(frame)
    if rig is None:
        raise RuntimeError(f"{recording}: no rig")
    out = {f"read_{s}_ms": statistics.median(v) for s, v in reads.items()}

    step = StereoStep(rig, DisplaySettings(), CONSOLE)
    asm = FrameSetAssembler.stereo(step.sensors)
    sets = [fs for f in frames for fs in asm.push(f)]
    tofs = [f for f in frames if f.sensor == step.tof][:SAMPLES]
    fusion = step.fusion
    out["map_ms"] = statistics.median(
        _cpu_ms(lambda f=f: fusion.update_depth(f.distance_m, f.image)) for f in tofs
    )
    pictures, compose = [], []
    for fs in sets[: SAMPLES + 1]:
        step.note(fs)
        step.update_depth(fs.stamp_ns)
        inputs = step.inputs(fs)
        if isinstance(inputs, Skip):
            continue
        rgb, ms = _timed(lambda inputs=inputs: step.render(inputs))
        compose.append(ms)
        pictures.append(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if len(compose) < 2:
        raise RuntimeError(f"{recording}: fewer than 2 pictures to measure")
    out["compose_ms"] = statistics.median(compose[1:])  # the first fills the buffers
    encoder = VideoEncoder(LEVELS[0])
    out["h264_ms"] = statistics.median(_cpu_ms(lambda p=p: encoder.encode(p)) for p in pictures)
    return out


def necessary_ms(
    costs: Mapping[str, float],
    rates_hz: Mapping[str, float],
    fps: float,
    mapped_hz: float,
    h264: bool,
) -> float:
    """The CPU a frame set needs (ms) at the console's rates: each sensor's frames read and
    decoded at the rate the console took them, the TOF frames it mapped, the picture
    composed and (``h264``: a video viewer) encoded. ``rates_hz``: sensor -> frames a
    second the console took; ``fps``: frame sets a second it fused; ``mapped_hz``: TOF
    frames a second it mapped (``depth_updates``)."""
    if fps <= 0:
        return float("nan")
    need = costs["compose_ms"] + (costs["h264_ms"] if h264 else 0.0)
    for sensor, hz in rates_hz.items():
        need += costs.get(f"read_{sensor}_ms", 0.0) * hz / fps
    return need + costs["map_ms"] * mapped_hz / fps
