"""REST routes of the source: status, replay controls, recording (OpenAPI at /docs).

``GET /api/status`` reports the source, per-sensor rates, the fused stream, the recording,
each eye's registration sigma and the calibration's health (the drift check);
``/api/source/*`` pause, resume, seek and set the speed of a replay (409 on another kind of
source); ``/api/recording/*`` start and stop recording what the console receives
(docs/FORMATS.md, "Console REST API"). Bad values get a 422 naming the field.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.errors import ControlError
from trifuse.app.recording.recorder import RecordingState
from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.registration_watch import RegistrationWatch
from trifuse.app.server.runtime.source_control import SourceControl, SourceState
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.settings_spec import REPLAY_RATE, SEEK_POSITION_S


class SourceInfo(BaseModel):
    """What the console plays. The replay fields are null for other sources."""

    description: str = Field(description="one line saying what the source is")
    kind: Literal["simulated", "replay", "live", "push"]
    sensors: list[str] = Field(description="the sensors the source can deliver")
    position_s: float | None = Field(
        None, description="replay: seconds from the recording's start to the last frame"
    )
    duration_s: float | None = Field(None, description="replay: the recording's length, s")
    paused: bool | None = Field(None, description="replay: held by pause")
    rate: float | None = Field(None, description="replay: speed, 1.0 = real time")
    dropped: dict[str, int] | None = Field(
        None,
        description="replay: sensor -> frames dropped to keep real time (the console had no "
        "time for them) since the replay was opened",
    )


class RecordingInfo(BaseModel):
    """The recording in progress, or the last one (``active`` false)."""

    available: bool = Field(description="false without a work directory")
    active: bool = Field(description="recording now")
    path: str | None = Field(None, description="the file being written, or the last one")
    size_bytes: int = Field(0, description="bytes written so far (all files of the recording)")
    duration_s: float = Field(0.0, description="recording time (first to last stamp), s")
    frames_written: int = 0
    frames_dropped: int = Field(0, description="frames dropped because the disk was slow")
    frames_rejected: int = Field(0, description="frames the rig does not describe, skipped")
    queued: int = Field(0, description="frames waiting to be written")
    stopping: bool = Field(False, description="stopped; writing what was queued, finishing")
    files: list[str] = Field(
        default_factory=list, description="finished files (a new one when replay time goes back)"
    )
    interrupted: list[str] = Field(
        default_factory=list,
        description="recordings a crash interrupted, kept as *.partial.mcap (readable up to "
        "their last complete chunk)",
    )
    error: str | None = None
    fused_video: bool = Field(
        False, description="the recording keeps the fused stereo picture as H.264 (/fused/video)"
    )
    video_frames_written: int = Field(0, description="pictures written to /fused/video")
    video_frames_skipped: int = Field(
        0, description="new pictures the video did not keep (the encoder was behind)"
    )
    video_error: str | None = Field(
        None, description="why the fused video stopped (the sensors were still recorded)"
    )


class SensorInfo(BaseModel):
    """One sensor's health (app/server/runtime/sensor_health.py)."""

    state: Literal["ok", "silent", "never", "failing"] = Field(
        description="ok; silent: no frame for max(1 s, 5 frame periods); never: no frame yet; "
        "failing: frames arrive but are rejected or garbage"
    )
    reason: str = Field("", description="why, for a person")
    last_frame_age_s: float | None = Field(
        None, description="seconds since its last good frame (null: none yet)"
    )
    rate_hz: float = Field(0.0, description="frames per second it delivers (usable or not)")


class VideoViewerInfo(BaseModel):
    """One ``/stream.video`` viewer (app/server/runtime/video_stats.py)."""

    preset: str = Field(description="the preset it asked for: auto, 8, 4, 2, 1")
    level: str = Field(description="the ladder step in use (8, 4, 2, 1: its Mbit/s cap)")
    codec: str = Field(description="WebCodecs codec string, e.g. avc1.42c032")
    width: int = Field(description="coded picture width, px")
    height: int = Field(description="coded picture height, px")
    bitrate_bps: int = Field(description="the rate controller's target, bit/s")
    fps_target: int = Field(description="the level's frame rate")
    fps: float = Field(description="frames sent per second over the last 2 s")
    delivered_bps: float = Field(description="bits acknowledged over the last second, per s")
    rtt_ms: float | None = Field(description="the last frame's round trip, sent -> ack, ms")
    min_rtt_ms: float | None = Field(description="the least round trip of the last 10 s, ms")
    latency_ms: float | None = Field(
        description="the last acknowledged frame's age at its ack, from its publication, ms"
    )
    encode_ms: float | None = Field(description="the last frame's encoding time, ms")
    in_flight: int = Field(description="frames sent, not acknowledged")
    window: int = Field(description="the most frames in flight")
    frames_sent: int
    keyframes: int
    bytes_sent: int
    congestion_events: int = Field(description="the controller's steps down")
    undone_events: int = Field(
        0, description="steps down undone: the acknowledgements were late, not the frames"
    )
    last_congestion: str | None = Field(
        None, description="why the last step down was taken: queue, stall, short or late"
    )
    queue_ms: float | None = Field(
        None,
        description="the last frame's delay above the least of the last 10 s (one-way when "
        "the viewer says when frames arrive, else the round trip), ms",
    )


class StreamInfo(BaseModel):
    """The stream's settings and its video viewers."""

    default_preset: str = Field(description="the video preset of viewers that ask for none")
    video: list[VideoViewerInfo] = Field(
        default_factory=list, description="each /stream.video viewer's figures"
    )
    video_encoders: int = Field(
        0, description="H.264 encoders running: one per level and bitrate that viewers watch"
    )


def _stream(hub: FrameHub) -> StreamInfo:
    now = time.monotonic()
    return StreamInfo(
        default_preset=hub.stream_settings.preset,
        video=[VideoViewerInfo(**v.as_dict(now)) for v in list(hub.video_viewers)],
        video_encoders=len(hub.video_encoders),
    )


class RegistrationEye(BaseModel):
    """One eye's registration sigma: how far (1-sigma, semi-major axis) a thermal value
    may land from the colour pixel that sees its point, over the fusion's coarse cells with
    depth (app/server/runtime/registration_watch.py)."""

    median_px: float | None = Field(description="median over the cells, colour pixels")
    p95_px: float | None = Field(description="95th percentile over the cells, colour pixels")
    cells: int = Field(description="coarse cells with an estimate")
    range_source: str = Field(description="where the TOF range error came from")
    calibration_covariance: bool = Field(
        description="the calibration's share is in (the rig carries the covariance); false: "
        "only the range and footprint shares"
    )
    age_s: float = Field(description="seconds since the estimate was made")


class RegistrationInfo(BaseModel):
    """The registration sigma of each eye, estimated in the background at most every 2 s
    while the fusion is wanted (null: not estimated yet for the rig in use)."""

    left: RegistrationEye | None = None
    right: RegistrationEye | None = None
    error: str | None = Field(None, description="why the newest estimate failed, or null")


class DriftSensor(BaseModel):
    """One sensor's drift verdict over the last 60 s (fusion/drift.py): its rotation against
    the rig, about its own axes, degrees (the correction a refine applies)."""

    verdict: Literal["ok", "drifted", "undecided"] = Field(
        description="ok: turned less than 0.15°, known to 0.05°; drifted: more than 0.15° by "
        "4 σ; undecided: not known well enough yet, with the reason"
    )
    rotation_deg: list[float] | None = Field(
        None, description="[x, y, z] rotation vector about the sensor's own axes, degrees"
    )
    sigma_deg: list[float] | None = Field(None, description="its 1-sigma per axis, degrees")
    angle_deg: float | None = Field(None, description="the rotation's angle, degrees")
    sigma_max_deg: float | None = Field(None, description="the largest of sigma_deg, degrees")
    reason: str = Field(description="why, in a sentence")
    pairs: list[str] = Field(
        default_factory=list, description="the sensors it was compared with in the window"
    )


class DriftRefine(BaseModel):
    """The newest refine (POST /api/drift/refine or the Calibration panel's Refine rig)."""

    saved_as: str = Field(description="the rig version it saved and put in use")
    sensors: dict[str, float] = Field(description="sensor -> the angle corrected, degrees")
    age_s: float = Field(description="seconds since the refine")


class DriftInfo(BaseModel):
    """The calibration's health: whether each camera still sits where the rig in use says,
    checked on the live frame sets without a board, at most every 2 s and within 10 % of a
    core while the fusion is wanted (app/server/runtime/drift_watch.py)."""

    sensors: dict[str, DriftSensor] = Field(
        default_factory=dict,
        description="each sensor's verdict (empty before the first measure of the rig in use)",
    )
    instants: int = Field(0, description="frame sets measured in the window (60 s)")
    age_s: float | None = Field(None, description="seconds since the newest measure")
    drifted: list[str] = Field(default_factory=list, description="the sensors drifted")
    summary: str = Field(
        "", description="the health line, e.g. 'thermal_left DRIFTED 0.31° (σ 0.01°); others ok'"
    )
    alerts: list[str] = Field(
        default_factory=list,
        description="one line per drifted camera, e.g. '⚠ thermal_left has turned 0.31° "
        "against the rig: refine or recalibrate'",
    )
    error: str | None = Field(None, description="why the newest measure failed, or null")
    waiting: str | None = Field(
        None, description="why the last frame set looked at was not measured, or null"
    )
    problems: list[str] = Field(
        default_factory=list, description="the check's newest problems (no depth, no structure)"
    )
    measures: int = Field(0, description="measures made since the start")
    cpu_share: float | None = Field(
        None,
        description="the share of one core the measures took over the last minute (null "
        "before two measures)",
    )
    last_refine: DriftRefine | None = None


class AlarmEventInfo(BaseModel):
    seq: int = Field(description="the event's number (GET /api/alarms?after=N: the newer)")
    time_s: float = Field(description="frame time of the picture it was read on, seconds")
    region: str
    kind: str = Field(description="above, below or rise")
    threshold: float
    state: str = Field(description="raised or cleared")
    value: float = Field(description="the value that raised or cleared it (kelvin, K/s)")


class MeasurementsInfo(BaseModel):
    regions: int = Field(description="measurement regions")
    active_alarms: list[str] = Field(description="the alarms raised and not cleared")
    events: list[AlarmEventInfo] = Field(description="the newest alarm events, oldest first")
    readings_stamp_ns: int | None = Field(description="stamp of the picture last read")


class Status(BaseModel):
    """The console at a glance. ``viewers``, ``frames_out``, ``fps``, ``missing`` and
    ``error`` are the keys the first status route had."""

    viewers: int = Field(description="stereo stream viewers connected")
    frames_out: int = Field(description="frames published to the stream since the start")
    fps: float = Field(
        description="frames published to the stream per second over the last 3 s, new "
        "pictures and repeats (0 while nothing arrives)"
    )
    new_fps: float = Field(
        0.0, description="of these, new pictures per second (the rest repeat an unchanged one)"
    )
    depth_updates: int = Field(
        0, description="TOF frames mapped (depth put in use for the pictures) since the start"
    )
    missing: dict[str, str] = Field(description="sensors missing from the last frame set: why")
    error: str | None = Field(description="the pipeline's error, if it stopped")
    source: SourceInfo | None = None
    rates_hz: dict[str, float] = Field(
        default_factory=dict, description="frames per second each sensor delivers"
    )
    recording: RecordingInfo | None = None
    sensors: dict[str, SensorInfo] = Field(
        default_factory=dict, description="each sensor's health: state, reason, age, rate"
    )
    stream: StreamInfo | None = Field(
        None, description="the stream's default video preset and its video viewers"
    )
    registration: RegistrationInfo | None = Field(
        None,
        description="each eye's registration sigma (median, 95th percentile, colour pixels); "
        "null without the background estimate",
    )
    drift: DriftInfo | None = Field(
        None,
        description="the calibration's health: each camera's drift verdict against the rig "
        "in use; null without the background check",
    )
    measurements: MeasurementsInfo | None = Field(
        None, description="measurement regions and alarms (/api/regions, /api/alarms)"
    )


class SeekRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    position_s: float = SEEK_POSITION_S.field(allow_inf_nan=False)


class RateRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    rate: float = REPLAY_RATE.field(allow_inf_nan=False)


def _source(state: SourceState) -> SourceInfo:
    return SourceInfo(**dataclasses.asdict(state))


def _recording(state: RecordingState) -> RecordingInfo:
    return RecordingInfo(**dataclasses.asdict(state))


def make_source_router(
    hub: FrameHub,
    pipeline: FusionPipeline | None = None,
    control: SourceControl | None = None,
    registration: RegistrationWatch | None = None,
    drift: DriftWatch | None = None,
) -> APIRouter:
    """The routes; without ``control`` (and a pipeline) the status reports zeros and the
    controls answer 409; without ``registration`` (``drift``) its ``registration``
    (``drift``) is null."""
    if control is None and pipeline is not None:
        control = SourceControl(pipeline, hub)
    router = APIRouter(prefix="/api", tags=["source"])

    def need() -> SourceControl:
        if control is None:
            raise HTTPException(409, "the console has no source")
        return control

    def call(fn, *args):
        try:
            return fn(*args)
        except ControlError as exc:
            raise HTTPException(409, str(exc)) from None
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None

    @router.get("/status")
    def status() -> Status:
        """The source, per-sensor rates, the fused stream, viewers and the recording. A
        client asking for it is listening: the console fuses for the next few seconds."""
        if control is None:
            return Status(
                viewers=hub.viewers,
                frames_out=0,
                fps=0.0,
                missing={},
                error=None,
                stream=_stream(hub),
            )
        control.pipeline.touch_demand()
        s = control.pipeline.status
        rates = control.stream_rates()
        return Status(
            viewers=hub.viewers,
            frames_out=s.frames_out,
            fps=rates.stream_fps,
            new_fps=rates.new_fps,
            depth_updates=s.depth_updates,
            missing=dict(s.missing),
            error=s.error,
            source=_source(control.source_state()),
            rates_hz=control.rates_hz(),
            recording=_recording(control.recording_state()),
            sensors={n: SensorInfo(**h.as_dict()) for n, h in control.sensor_health().items()},
            stream=_stream(hub),
            registration=None
            if registration is None
            else RegistrationInfo(**registration.status()),
            drift=None if drift is None else DriftInfo(**drift.status()),
            measurements=MeasurementsInfo(**control.pipeline.measurements.status()),
        )

    @router.post("/source/pause")
    def pause() -> SourceInfo:
        """Hold the replay (409 for a source that is not a recording)."""
        return _source(call(need().pause))

    @router.post("/source/resume")
    def resume() -> SourceInfo:
        """Continue a paused replay from where it stopped."""
        return _source(call(need().resume))

    @router.post("/source/seek", dependencies=[Depends(require_json)])
    def seek(body: SeekRequest) -> SourceInfo:
        """Continue the replay from ``position_s`` (422 outside 0..duration_s)."""
        return _source(call(need().seek, body.position_s))

    @router.put("/source/rate", dependencies=[Depends(require_json)])
    def rate(body: RateRequest) -> SourceInfo:
        """Replay speed, 0.25..4 times real time."""
        return _source(call(need().set_rate, body.rate))

    @router.get("/recording")
    def recording() -> RecordingInfo:
        """The recording in progress, or the last one."""
        return _recording(need().recording_state())

    @router.post("/recording/start")
    def start_recording() -> RecordingInfo:
        """Record the frames the console receives to ``<workdir>/recordings/<time>.mcap``
        (409 while recording)."""
        return _recording(call(need().start_recording))

    @router.post("/recording/stop")
    def stop_recording() -> RecordingInfo:
        """Finish the recording: queued frames are written, the file is closed and named."""
        return _recording(call(need().stop_recording))

    return router
