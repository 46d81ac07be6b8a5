"""The console's tap on its source: what the fusion pipeline iterates instead of the source.

:class:`SourceTap` wraps the opened :class:`~trifuse.app.sources.base.FrameSource`: it
measures each sensor's delivered frame rate (:class:`~trifuse.app.server.runtime.rates.
RateWindow`), hands every frame to the :class:`~trifuse.app.recording.recorder.Recorder`
while one is recording, and checks each frame
(:class:`~trifuse.app.server.runtime.sensor_health.HealthMonitor`): garbage frames (wrong
size, no finite pixel, implausible values) are withheld from fusion, which carries on
without them.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

from trifuse.app.recording.recorder import Recorder
from trifuse.app.server.runtime.rates import RateWindow
from trifuse.app.server.runtime.sensor_health import HealthMonitor, expected_of
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame


class SourceTap(FrameSource):
    """A :class:`FrameSource` that forwards another's frames, counting them per sensor and
    handing each to a :class:`~trifuse.app.recording.recorder.Recorder` (which never blocks).

    Attributes:
        inner: the wrapped source (its ``close`` is called by this one's).
        meter: delivered frame rates per sensor (every frame, usable or not).
        recorder: the recorder frames are offered to (None: no recording); it gets every
            frame as received.
        health: checks each frame; garbage frames are not passed on (the consumer sees the
            sensor missing). Judged against the source's rig until
            :class:`~trifuse.app.server.runtime.source_control.SourceControl` gives it the
            pipeline's.
    """

    def __init__(self, inner: FrameSource, recorder: Recorder | None = None) -> None:
        self.inner = inner
        self.sensors = list(inner.sensors)
        self.rig = inner.rig
        self.realtime = inner.realtime
        self.meter = RateWindow()
        self.recorder = recorder
        self.health = HealthMonitor(self.sensors, expected_of(inner.rig, self.sensors))

    def frames(self) -> Iterator[Frame]:
        meter, health = self.meter, self.health
        for frame in self.inner.frames():
            now = time.monotonic()
            meter.tick(frame.sensor, now)
            recorder = self.recorder
            if recorder is not None:
                recorder.offer(frame)
            if health.observe(frame, now) is not None:
                continue  # garbage: shown in the sensor's health, not fused
            yield frame

    def close(self) -> None:
        self.inner.close()
