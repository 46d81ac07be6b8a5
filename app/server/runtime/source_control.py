"""What the console plays and records: the controls the Source panel and the REST API share.

:class:`SourceControl` is what the panel and the routes call: the state of the source,
each sensor's delivered rate and health (:meth:`SourceControl.sensor_health`), replay
controls (pause, resume, seek, rate) and recording start/stop. It needs the pipeline's
source wrapped in a :class:`~trifuse.app.server.runtime.source_tap.SourceTap` (rates,
health, recording); the recordings are written by a
:class:`~trifuse.app.recording.recorder.Recorder` into ``<workdir>/recordings``, with the
fused video, when asked, from the pictures the stream publishes
(:class:`~trifuse.app.server.runtime.fused_video_tap.FusedVideoSource`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import cast

from trifuse.app.errors import ControlError
from trifuse.app.recording.recorder import RECORDINGS, Recorder, RecordingState
from trifuse.app.recording.video_track import VideoSettings
from trifuse.app.server.runtime.fused_video_tap import FusedVideoSource
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.rates import RatesSnapshot
from trifuse.app.server.runtime.sensor_health import Rejections, SensorHealth, push_rejections
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.capabilities import (
    RejectionStats,
    ReplayControls,
    SourceKind,
    device_states,
    head_pose_of,
    kind_of,
    replay_controls,
)
from trifuse.calib.numbers import is_int_or_float
from trifuse.calib.rig import Rig

RATE_MIN, RATE_MAX = 0.25, 4.0
"""Replay speeds the console offers (1.0 = real time)."""
HEALTH_CACHE_S = 0.5
"""The health lines put in the stream's metadata are recomputed at most this often (s)."""


@dataclass
class SourceState:
    """The source: what it is, and for a replay where it is (seconds from its start), its
    length (seconds), whether it is paused, its speed (1.0 = real time) and the frames per
    sensor it dropped to keep real time since it was opened."""

    description: str
    kind: SourceKind
    sensors: list[str]
    position_s: float | None = None
    duration_s: float | None = None
    paused: bool | None = None
    rate: float | None = None
    dropped: dict[str, int] | None = None


def check_rate(rate: float) -> float:
    """A replay speed in [RATE_MIN, RATE_MAX] (ValueError naming what arrived otherwise)."""
    if not is_int_or_float(rate) or not math.isfinite(rate):
        raise ValueError(f"rate: expected a number {RATE_MIN}..{RATE_MAX}, got {rate!r}")
    if not RATE_MIN <= rate <= RATE_MAX:
        raise ValueError(f"rate: expected {RATE_MIN}..{RATE_MAX} (x real time), got {rate}")
    return float(rate)


class SourceControl:
    """The source's state and controls, shared by the Source panel and the REST API.

    Args:
        pipeline: the running fusion pipeline; its ``source`` should be a
            :class:`SourceTap` (per-sensor rates and recording need it).
        hub: the stream hub (number of viewers).
        description: one line saying what the source is.
        workdir: the console's work directory; recordings go to ``workdir/recordings``.
            None: recording is unavailable.
        rig: the rig recordings store (default: the pipeline's rig at each start).
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        hub: FrameHub,
        description: str = "",
        workdir: Path | None = None,
        rig: Callable[[], Rig] | None = None,
    ) -> None:
        self.pipeline, self.hub, self.description = pipeline, hub, description
        src = pipeline.source
        self.tap = src if isinstance(src, SourceTap) else None
        self.source = self.tap.inner if self.tap is not None else src
        self.kind: SourceKind = kind_of(self.source)
        self._rig = rig or (lambda: pipeline.rig)
        self.recorder: Recorder | None = None
        if workdir is not None and self.tap is not None:
            self.recorder = self.tap.recorder or Recorder(Path(workdir) / RECORDINGS)
            self.tap.recorder = self.recorder
            self.pipeline.measurements.on_note = self.recorder.note  # alarms, settings
            self.recorder.head_pose = head_pose_of(self.tap.inner)
        self.fused_video = False
        """Recordings started from now on also keep the fused video (the Source panel's
        "Record fused video"; ``POST /api/recording/start`` follows it)."""
        self.video_settings = VideoSettings()
        self._notes: tuple[float, dict[str, str]] | None = None
        if self.tap is not None:
            self.tap.health.set_rig(pipeline.rig)  # frames must fit what fusion expects
            pipeline.sensor_notes = self.health_notes

    # -- state --------------------------------------------------------------------------

    @property
    def is_replay(self) -> bool:
        return self.kind == "replay"

    def source_state(self) -> SourceState:
        st = SourceState(self.description, self.kind, list(self.source.sensors))
        src = replay_controls(self.source)
        if src is not None:
            st.position_s = max(0.0, (src.position_ns - src.start_ns) / 1e9)
            st.duration_s = float(src.duration_s)
            st.paused = bool(src.paused)
            st.rate = float(src.rate)
            st.dropped = dict(src.dropped)
        return st

    @property
    def paused(self) -> bool:
        """A replay held by :meth:`pause`."""
        src = replay_controls(self.source)
        return src is not None and bool(src.paused)

    def rates_hz(self) -> dict[str, float]:
        """Frames per second each sensor delivers to the console now (all 0 while a replay
        is paused; empty without a tap)."""
        if self.tap is None:
            return {}
        rates = self.tap.meter.rates_hz(list(self.source.sensors))
        return dict.fromkeys(rates, 0.0) if self.paused else rates

    def stream_rates(self) -> RatesSnapshot:
        """The stream's rates over the last :data:`~app.server.runtime.rates.RATE_WINDOW_S` seconds
        (taken at whole seconds: the viewer's frame metadata carries the same figures):
        frames published per second and, of these, new pictures per second. A repeated
        picture is the previous one published again because its input did not change (the
        simulated head shows each rendered pose for several frames). Zeros while a replay is
        paused; a stalled stream reads 0 once the window has passed."""
        snap = self.hub.rates.snapshot()
        if self.paused:
            return dataclasses.replace(snap, stream_fps=0.0, new_fps=0.0)
        return snap

    def sensor_health(self, now_s: float | None = None) -> dict[str, SensorHealth]:
        """Each sensor's health (:mod:`app.server.runtime.sensor_health`): the frames the tap saw,
        the push ingest's rejections, a replay's skipped messages, camera readers' states;
        empty without a tap."""
        if self.tap is None:
            return {}
        src = self.source
        rejections: dict[str, Rejections] = {}
        # a replay's skipped messages count as rejected; live ROS 2 topics' refused messages
        if self.kind in ("push", "replay") or getattr(src, "counts_rejections", False):
            rejections = push_rejections(cast(RejectionStats, src).stats())
        devices = device_states(src) if self.kind == "live" else {}
        return self.tap.health.report(
            now_s,
            rates_hz=self.rates_hz(),
            paused=self.paused,
            rejections=rejections,
            devices=devices,
        )

    def health_notes(self) -> dict[str, str]:
        """``{sensor: line}`` for the sensors that are not ok (recomputed at most every
        :data:`HEALTH_CACHE_S`; the pipeline puts it in each frame's metadata)."""
        now = time.monotonic()
        cached = self._notes
        if cached is not None and now - cached[0] < HEALTH_CACHE_S:
            return cached[1]
        notes = {s: h.line() for s, h in self.sensor_health(now).items() if not h.ok}
        self._notes = (now, notes)
        return notes

    def recording_state(self) -> RecordingState:
        if self.recorder is None:
            why = (
                "recording needs the console's work directory (trifuse serve --workdir)"
                if self.tap is not None
                else "recording needs the source wrapped in a SourceTap"
            )
            return RecordingState(available=False, error=why)
        return self.recorder.state()

    # -- replay controls ----------------------------------------------------------------

    def _replay(self, what: str) -> ReplayControls:
        src = replay_controls(self.source)
        if src is None:
            raise ControlError(
                f"{what}: the source is {self.kind} ({self.description}), not a replay; "
                "pause, resume, seek and rate apply to recordings only"
            )
        return src

    def pause(self) -> SourceState:
        self._replay("pause").pause()
        return self.source_state()

    def resume(self) -> SourceState:
        self._replay("resume").resume()
        return self.source_state()

    def seek(self, position_s: float) -> SourceState:
        """Continue from ``position_s`` seconds after the recording's start
        (ValueError outside 0..duration_s)."""
        src = self._replay("seek")
        duration = float(src.duration_s)
        if (
            not is_int_or_float(position_s)
            or not math.isfinite(position_s)
            or not 0.0 <= position_s <= duration
        ):
            raise ValueError(
                f"position_s: expected seconds 0..{duration:.3f} (the recording's length), "
                f"got {position_s!r}"
            )
        src.seek(int(src.start_ns + round(position_s * 1e9)))
        return self.source_state()

    def set_rate(self, rate: float) -> SourceState:
        """Replay speed, RATE_MIN..RATE_MAX times real time (ValueError otherwise)."""
        src = self._replay("rate")
        src.rate = check_rate(rate)
        return self.source_state()

    # -- recording ----------------------------------------------------------------------

    def start_recording(self, fused_video: bool | None = None) -> RecordingState:
        """Start recording; ``fused_video`` (default :attr:`fused_video`): also keep the
        fused pictures the console publishes as ``/fused/video``."""
        if self.recorder is None:
            raise ControlError(self.recording_state().error or "recording is unavailable")
        video = None
        if self.fused_video if fused_video is None else fused_video:
            video = FusedVideoSource(self.hub, self.pipeline.demand, self.video_settings)
        state = self.recorder.start(self._rig(), video)
        self.pipeline.measurements.note_settings()  # what the readings are corrected with
        return state

    def stop_recording(self) -> RecordingState:
        if self.recorder is None:
            raise ControlError(self.recording_state().error or "recording is unavailable")
        return self.recorder.stop()

    def stop(self) -> None:
        """Shut down: a running recording is finished and kept."""
        if self.recorder is not None:
            self.recorder.close()
