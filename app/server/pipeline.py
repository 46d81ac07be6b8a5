"""The live fusion loop: frames from a source, grouped, fused, encoded, published.

Runs in one background thread: a :class:`FrameSource` -> :class:`FrameSetAssembler`
(the left colour camera opens each set) -> :class:`StereoFusion` (depth mapping updated
on each new TOF frame) -> JPEG -> :class:`FrameHub`. A frame set that misses a sensor
still produces a picture from what it has (colour only while the thermal imagers are
missing; the last depth while the TOF is).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from app.server.stream import FrameHub
from app.sources.base import FrameSetAssembler, FrameSource
from app.sources.frames import FrameSet
from calib.rig import Rig
from fusion.compose import DisplaySettings
from fusion.stereo import StereoFusion


@dataclass
class PipelineStatus:
    """What the status route and the viewer's overlay report."""

    frames_out: int = 0
    fps: float = 0.0
    last_stamp_ns: int = 0
    missing: dict[str, str] = field(default_factory=dict)
    error: str | None = None


class FusionPipeline:
    """Fuses a source's frames into the stereo stream, in a background thread."""

    def __init__(
        self,
        source: FrameSource,
        rig: Rig,
        hub: FrameHub,
        settings: DisplaySettings | None = None,
        jpeg_quality: int = 80,
        tolerance_s: float = 0.05,
    ) -> None:
        self.source, self.rig, self.hub = source, rig, hub
        self.settings = settings or DisplaySettings()
        self.jpeg_quality = jpeg_quality
        self.fusion = StereoFusion(rig)
        left, right = rig.eyes["left"], rig.eyes["right"]
        self.tof = self.fusion.fusion["left"].forward.tof
        sensors = [left.color, right.color, left.thermal, right.thermal, self.tof]
        self.assembler = FrameSetAssembler(sensors, reference=left.color, tolerance_s=tolerance_s)
        self.status = PipelineStatus()
        # Manual balance of the thermal imagers: kelvin added to each imager's readings.
        self.thermal_offset_k: dict[str, float] = {left.thermal: 0.0, right.thermal: 0.0}
        self._offset_buf = {
            s: np.empty(rig[s].image_size[::-1], np.float32) for s in self.thermal_offset_k
        }
        self.latest_set: FrameSet | None = None
        self._last_tof_ns: int | None = None
        self._bgr: np.ndarray | None = None  # the encoder's input, reused every frame
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fusion", daemon=True)

    def start(self) -> FusionPipeline:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self.source.close()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        t_rate, n_rate = time.perf_counter(), 0
        try:
            for frame in self.source.frames():
                if self._stop.is_set():
                    return
                for fs in self.assembler.push(frame):
                    if self._publish(fs):
                        n_rate += 1
                now = time.perf_counter()
                if now - t_rate >= 1.0:
                    self.status.fps = n_rate / (now - t_rate)
                    t_rate, n_rate = now, 0
        except Exception as exc:  # shown in the status, the server keeps running
            self.status.error = f"{type(exc).__name__}: {exc}"

    def _publish(self, fs: FrameSet) -> bool:
        self.latest_set = fs
        self.status.missing = dict(fs.missing)
        self.status.last_stamp_ns = fs.stamp_ns
        tof = fs.frames.get(self.tof)
        if tof is not None and tof.stamp_ns != self._last_tof_ns and tof.distance_m is not None:
            self.fusion.update_depth(tof.distance_m)
            self._last_tof_ns = tof.stamp_ns
        eyes = self.rig.eyes
        colors = {
            e: fs.frames[eyes[e].color].image
            for e in ("left", "right")
            if eyes[e].color in fs.frames
        }
        if len(colors) < 2:
            return False
        thermals = {
            e: fs.frames[eyes[e].thermal].image
            for e in ("left", "right")
            if eyes[e].thermal in fs.frames
        }
        settings = self.settings
        if len(thermals) < 2 or not self.fusion.ready:
            settings = DisplaySettings(mode="color")
            thermals = {
                e: np.full(self.rig[eyes[e].thermal].image_size[::-1], np.nan, np.float32)
                for e in ("left", "right")
            }
            if not self.fusion.ready:
                return self._encode(np.hstack([colors["left"], colors["right"]]), fs, "color")
        frame = self.fusion.compose(colors, thermals, settings)
        return self._encode(frame, fs, settings.mode)

    def _balanced(self, sensor: str, image: np.ndarray) -> np.ndarray:
        """The imager's temperatures plus its manual offset (into a preallocated buffer)."""
        offset = self.thermal_offset_k.get(sensor, 0.0)
        if offset == 0.0:
            return image
        return np.add(image, np.float32(offset), out=self._offset_buf[sensor])

    def _encode(self, rgb: np.ndarray, fs: FrameSet, mode: str) -> bool:
        if self._bgr is None or self._bgr.shape != rgb.shape:
            self._bgr = np.empty_like(rgb)
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR, dst=self._bgr)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            return False
        span = self.fusion.span_k
        self.hub.publish(
            buf.tobytes(),
            {
                "stamp_ns": fs.stamp_ns,
                "mode": mode,
                "span_k": list(span) if span else None,
                "missing": sorted(fs.missing),
            },
        )
        self.status.frames_out += 1
        return True
