"""Foxglove live (issue 21): ``trifuse serve --foxglove-port N`` publishes what the console
receives on foxglove-sdk's WebSocket server (subprotocol ``foxglove.sdk.v1``), with the
topics and schemas of a recording, so that one Foxglove layout shows a recording and the
live head (docs/FORMATS.md, "Foxglove live").

What goes out (the recording's message builders, :mod:`app.recording.messages`):

- each sensor's frames as a recording has them (:mod:`app.recording.layout`):
  ``/<sensor>/image`` (``foxglove.CompressedImage`` JPEG), ``/<sensor>/temperature``
  (``foxglove.RawImage`` 16UC1 centi-kelvin), ``/<tof>/distance`` and ``/<tof>/amplitude``
  (RawImage 16UC1), each frame once (a frame set repeats the slower sensors' frames);
- ``/<sensor>/calibration`` (``foxglove.CameraCalibration``) and ``/tf``
  (``foxglove.FrameTransform``): the rig's transforms (parent ``rig``) once a second and at
  once for a new subscriber, from the rig in use (a new calibration shows at once); the
  head's pose ``world -> rig`` with each TOF frame when the source knows it
  (``source.head_pose(stamp_ns)``: the simulated head, a recording with poses);
- ``/fused/video``: the console's fused stereo picture as a recording keeps it
  (``foxglove.CompressedVideo`` H.264, :class:`~app.recording.video_track.FusedVideoTrack`),
  encoded by the recording's :class:`~app.server.runtime.fused_video_tap.FusedVideoTap` at
  :data:`LIVE_VIDEO` (4 Mbit/s, a key frame every second and for each new subscriber);
  while it is subscribed the tap holds the console's fusion demand (the console fuses);
- live only (no recording has them): ``/<tof>/points`` (:data:`POINTS_STREAM`;
  ``foxglove.PointCloud`` in the TOF's frame, frame id the TOF's name: the TOF frame's
  valid points through the rig's range correction, flying pixels left out as the fusion
  does, every :data:`POINTS_STRIDE`-th pixel of every :data:`POINTS_STRIDE`-th row, at most
  :data:`POINTS_HZ` a second; fields ``x y z`` metres and ``amplitude``, float32) and
  ``/trifuse/health`` (:data:`HEALTH_TOPIC`, JSON, schema :data:`HEALTH_SCHEMA`: each
  sensor's health and rate as ``/api/status`` reports them, the stream's rates, the
  missing sensors, what this publisher dropped; once a second).

Message log times are the source's stamps (a frame's ``stamp_ns``; the newest frame set's
for the calibration, the transforms and the health), so every topic shares the source's
clock.

It works only for a subscriber. The pipeline's frame-set listener
(:attr:`~app.server.runtime.pipeline.FusionPipeline.set_listeners`) returns at once while
no Foxglove client subscribes to anything; otherwise it hands the frame set to this
publisher's thread through an inbox of :data:`INBOX_SETS` sets (a full inbox drops its
oldest set, counted in :attr:`FoxgloveLive.dropped`): the fusion thread never waits. The
thread encodes only the messages of channels that have a subscriber
(``channel.has_sinks()``; :attr:`FoxgloveLive.encoded` counts them). Without a client it
wakes once a second and does nothing else.

The port binds 127.0.0.1 only: it has no authentication (the console's token does not
guard it; docs/SECURITY.md). Reach it from elsewhere through an SSH tunnel.

Limits (issue 29): the SDK's server listens on a random address of 127.0.0.0/8 with a queue
of :data:`MESSAGE_BACKLOG` messages a client, behind the console's port, a relay that caps
clients and their messages (:mod:`app.server.runtime.foxglove_gate`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import secrets
import socket
import threading
import time
from typing import Any

import foxglove
import numpy as np
from foxglove.channels import FrameTransformChannel, PointCloudChannel
from foxglove.messages import (
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    Pose,
    Quaternion,
    Timestamp,
    Vector3,
)

from trifuse.app.errors import describe_error
from trifuse.app.latest_worker import LatestWorker
from trifuse.app.recording.layout import RIG_FRAME, TF_TOPIC, WORLD_FRAME
from trifuse.app.recording.messages import (
    calibration_message,
    frame_messages,
    sensor_channels,
    transform_message,
)
from trifuse.app.recording.video_track import (
    FusedVideoTrack,
    VideoSettings,
    VideoUnit,
    video_frame_id,
    video_metadata,
)
from trifuse.app.server.runtime.foxglove_gate import (
    LOOPBACK,
    MAX_CLIENTS,
    FoxgloveGate,
    in_use_message,
)
from trifuse.app.server.runtime.fused_video_tap import FusedVideoSource, FusedVideoTap
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.sources.capabilities import HeadPose, head_pose_of
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import rigidity_problem
from trifuse.fusion.mapping import MappingOptions, TofGrid, mixed_pixels

log = logging.getLogger(__name__)

"""The only address the Foxglove server binds (it has no authentication)."""
SUBPROTOCOL = "foxglove.sdk.v1"
"""The WebSocket subprotocol foxglove-sdk 0.30's server speaks (it refuses the older
``foxglove.websocket.v1``)."""
HEALTH_TOPIC = "/trifuse/health"
HEALTH_SCHEMA_NAME = "trifuse.Health"
POINTS_STREAM = "points"
"""``/<tof>/points``: the TOF point cloud (live only)."""
POINTS_HZ = 5.0
"""Point clouds a second at most."""
POINTS_STRIDE = 2
"""Every POINTS_STRIDE-th pixel of every POINTS_STRIDE-th row of the TOF goes in the cloud."""
INBOX_SETS = 2
"""Frame sets waiting for the publisher's thread at most (the oldest is dropped)."""
STATIC_PERIOD_S = 1.0
"""The calibration and the rig's transforms go out this often (and for a new subscriber)."""
HEALTH_PERIOD_S = 1.0
IDLE_WAKE_S = 1.0
"""Without a subscriber the thread wakes this often (to notice nothing)."""
BUSY_WAKE_S = 0.2
LIVE_VIDEO = VideoSettings(bitrate_bps=4_000_000, keyint_s=1.0)
"""The fused video's encoding on the live server (a recording's is 10 Mbit/s)."""
MESSAGE_BACKLOG = 32
"""Messages queued for a client at most (the SDK's ``message_backlog_size``, its default
1024); when full the oldest message data is dropped."""
HEALTH_SCHEMA: dict[str, Any] = {
    "title": HEALTH_SCHEMA_NAME,
    "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer", "description": "the newest frame set's stamp"},
        "sensors": {
            "type": "object",
            "description": "sensor -> its health (as /api/status reports it)",
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "state": {"type": "string", "enum": ["ok", "silent", "never", "failing"]},
                    "reason": {"type": "string"},
                    "line": {"type": "string"},
                    "last_frame_age_s": {"type": ["number", "null"]},
                    "rate_hz": {"type": "number"},
                },
            },
        },
        "missing": {"type": "array", "items": {"type": "string"}},
        "stream": {
            "type": "object",
            "properties": {"fps": {"type": "number"}, "new_fps": {"type": "number"}},
        },
        "publisher": {
            "type": "object",
            "description": "this Foxglove publisher's counters",
            "properties": {
                "encoded": {"type": "integer"},
                "dropped": {"type": "integer"},
                "failed": {"type": "integer"},
                "video_pictures": {"type": "integer"},
                "video_skipped": {"type": "integer"},
            },
        },
    },
}


def points_topic(tof: str) -> str:
    """``/<tof>/points``."""
    return f"/{tof}/{POINTS_STREAM}"


def _timestamp(stamp_ns: int) -> Timestamp:
    return Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)


def start_foxglove_server(
    port: int,
    context: foxglove.Context,
    listener: object | None = None,
    host: str = LOOPBACK,
    message_backlog: int = MESSAGE_BACKLOG,
) -> foxglove.WebSocketServer:
    """foxglove-sdk's WebSocket server on ``host``:``port`` (0: any free port) for
    ``context``'s channels, queueing at most ``message_backlog`` messages a client. OSError
    in one line when the port is taken or not allowed."""
    try:
        return foxglove.start_server(
            name="trifuse",
            host=host,
            port=port,
            context=context,
            server_listener=listener,
            message_backlog_size=message_backlog,
        )
    except RuntimeError as e:
        if "in use" in str(e):
            raise OSError(in_use_message(port)) from None
        raise OSError(f"cannot serve Foxglove on {host}:{port}: {e}") from None


def _hidden_loopback() -> str:
    """A random address of 127.0.0.0/8 for the SDK's server (only the relay connects to it;
    a web page cannot guess it to go round the relay's limits)."""
    return "127." + ".".join(str(1 + secrets.randbelow(254)) for _ in range(3))


class _Listener:
    """foxglove-sdk's server listener: who subscribes to what (called in its threads)."""

    def __init__(self, live: FoxgloveLive) -> None:
        self.live = live

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.live._subscribed(client.id, channel.id, True)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self.live._subscribed(client.id, channel.id, False)


class FoxgloveLive:
    """The console's live Foxglove server (see the module doc).

    Args:
        control: the console's source control: its pipeline (frame sets, rig), stream hub
            and the fusion's demand (the fused video), sensor health and rates.
        port: the port on 127.0.0.1 (0: any free one; :attr:`port` tells).
        head_pose: stamp (ns) -> ``T_world_rig`` (4, 4) or None; default the source's
            ``head_pose`` if it has one.
        jpeg_quality: of the colour images (a recording's default).
        video: the fused video's encoding.
        max_clients: Foxglove clients at once; ``message_backlog``: messages queued for a
            client at most (see the module doc, "Limits").

    Attributes:
        encoded: messages encoded and published (frames, calibrations, transforms, clouds,
            health; not the video's pictures).
        taken: frame sets handed to the thread; ``dropped``: of these, dropped unread (the
            thread was busy); ``failed``: frames or messages that failed (``last_error``).
        video_pictures: access units published on ``/fused/video``; ``video_skipped``: units
            the track refused (it waits for a key frame after a gap).
    """

    def __init__(
        self,
        control: SourceControl,
        port: int,
        head_pose: HeadPose | None = None,
        jpeg_quality: int = 90,
        video: VideoSettings = LIVE_VIDEO,
        max_clients: int = MAX_CLIENTS,
        message_backlog: int = MESSAGE_BACKLOG,
    ) -> None:
        self.control = control
        self.pipeline = control.pipeline
        self.head_pose = head_pose or head_pose_of(control.source)
        self.jpeg_quality = jpeg_quality
        self.video_settings = video
        self.encoded = self.taken = self.dropped = self.failed = 0
        self.video_pictures = self.video_skipped = 0
        self.last_error: str | None = None
        rig: Rig = self.pipeline.rig
        self.tof = self.pipeline.tof
        self._ctx = foxglove.Context()
        self._channels: dict[tuple[str, str], Any] = {}
        for s in rig.sensors.values():
            self._channels.update(sensor_channels(self._ctx, s))
        self._tf = FrameTransformChannel(TF_TOPIC, context=self._ctx)
        self._video = FusedVideoTrack(self._ctx, video_frame_id(rig), video_metadata(video))
        self._points = PointCloudChannel(
            points_topic(self.tof),
            context=self._ctx,
            metadata={"trifuse.sensor": self.tof, "trifuse.kind": "tof_points"},
        )
        self._health = foxglove.Channel(HEALTH_TOPIC, schema=HEALTH_SCHEMA, context=self._ctx)
        self._static_ids = {self._tf.id()} | {
            ch.id() for (_, kind), ch in self._channels.items() if kind == "calibration"
        }
        self._subs: set[tuple[int, int]] = set()  # (client id, channel id)
        self._lock = threading.Lock()  # _subs, the due flags
        self._static_due = False
        self._key_due = False
        self._sent: dict[str, int] = {}  # sensor -> stamp of its last frame published
        self._next_static = self._next_health = 0.0
        self._next_points = 0.0
        self._grid: TofGrid | None = None
        self._tap: FusedVideoTap | None = None
        self._video_failed = False  # the tap stopped with an error while subscribed
        self._worker: LatestWorker[FrameSet] = LatestWorker(
            self._publish_set,
            name="foxglove-live",
            keep=INBOX_SETS,
            on_error=self._failed,
            housekeeping=self._housekeeping,
            period_s=lambda: BUSY_WAKE_S if self._subs else IDLE_WAKE_S,
        )
        try:
            self.server = self._start_server(message_backlog)
        except BaseException:
            self._close_channels()
            raise
        try:
            self.gate = FoxgloveGate(port, (self._server_host, self.server.port), max_clients)
        except BaseException:
            self.server.stop()
            self._close_channels()
            raise
        self.port: int = self.gate.port

    def _start_server(self, message_backlog: int) -> foxglove.WebSocketServer:
        """The SDK's server on a hidden loopback address (127.0.0.1 where that fails)."""
        self._server_host = _hidden_loopback()
        try:
            return start_foxglove_server(
                0, self._ctx, _Listener(self), self._server_host, message_backlog
            )
        except OSError:
            self._server_host = LOOPBACK
            return start_foxglove_server(0, self._ctx, _Listener(self), LOOPBACK, message_backlog)

    # -- life -----------------------------------------------------------------------------

    def start(self) -> FoxgloveLive:
        self.pipeline.set_listeners.append(self._on_set)
        self._worker.start()
        self.gate.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop publishing, end the fused video, close the server. Idempotent."""
        with contextlib.suppress(ValueError):
            self.pipeline.set_listeners.remove(self._on_set)
        self._worker.stop(timeout_s)
        self.gate.stop()
        self._stop_video()
        self.server.stop()
        self._close_channels()

    def _close_channels(self) -> None:
        for ch in [*self._channels.values(), self._tf, self._video, self._points, self._health]:
            with contextlib.suppress(Exception):
                ch.close()

    @property
    def url(self) -> str:
        """What to open in Foxglove (Open connection, Foxglove WebSocket)."""
        return f"ws://{LOOPBACK}:{self.port}"

    @property
    def subscribed(self) -> bool:
        """Whether any client subscribes to any channel."""
        return bool(self._subs)

    @property
    def busy(self) -> bool:
        """Whether the publisher's thread has a frame set waiting or in hand."""
        return self._worker.busy

    def status(self) -> dict[str, int | str | None]:
        return {
            "port": self.port,
            "clients": self.gate.clients,
            "refused": self.gate.refused,
            "subscriptions": len(self._subs),
            "encoded": self.encoded,
            "taken": self.taken,
            "dropped": self.dropped,
            "failed": self.failed,
            "video_pictures": self.video_pictures,
            "video_skipped": self.video_skipped,
            "last_error": self.last_error,
        }

    # -- the server's and the pipeline's threads ----------------------------------------

    def _subscribed(self, client: int, channel: int, on: bool) -> None:
        with self._lock:
            if on:
                self._subs.add((client, channel))
                if channel in self._static_ids:
                    self._static_due = True
                if channel == self._video.channel.id():
                    self._key_due = True  # a new viewer decodes from the next key frame
            else:
                self._subs.discard((client, channel))
        self._worker.wake()

    def _on_set(self, fs: FrameSet) -> None:
        """The pipeline's listener (fusion thread): nothing without a subscriber; else the
        set goes to the inbox (never waits)."""
        if not self._subs:
            return
        if self._worker.submit(fs):
            self.dropped += 1
        self.taken += 1

    # -- the publisher's thread (:attr:`_worker`: each set, then the housekeeping) --------

    def _failed(self, exc: BaseException) -> None:
        """A frame or message that failed: logged (once per new error) and counted; the
        console goes on."""
        self.failed += 1
        error = describe_error(exc)
        if error != self.last_error:
            log.warning("Foxglove live: %s", error)
        self.last_error = error

    def _housekeeping(self) -> None:
        self._video_wanted(self._video.channel.has_sinks())
        if not self._subs:
            return
        now = time.monotonic()
        with self._lock:
            static = self._static_due or now >= self._next_static
            self._static_due = False
        if static:
            self._next_static = now + STATIC_PERIOD_S
            self._publish_static()
        if now >= self._next_health and self._health.has_sinks():
            self._next_health = now + HEALTH_PERIOD_S
            self._publish_health()

    def _stamp(self) -> int:
        """The newest frame set's stamp (the source's clock), else the host's clock."""
        stamp = self.pipeline.status.last_stamp_ns
        return int(stamp) if stamp else time.time_ns()

    def _publish_set(self, fs: FrameSet) -> None:
        rig = self.pipeline.rig
        for name, frame in fs.frames.items():
            if name not in rig.sensors or self._sent.get(name) == frame.stamp_ns:
                continue
            self._sent[name] = frame.stamp_ns
            try:
                self._publish_frame(rig, frame)
            except Exception as exc:
                self._failed(exc)

    def _publish_frame(self, rig: Rig, frame: Frame) -> None:
        name, stamp = frame.sensor, int(frame.stamp_ns)
        s = rig[name]
        channels = self._channels

        def wanted(kind: str) -> bool:
            return channels[(name, kind)].has_sinks()

        for kind, msg in frame_messages(frame, s, stamp, self.jpeg_quality, "16UC1", wanted):
            channels[(name, kind)].log(msg, log_time=stamp)
            self.encoded += 1
        if name != self.tof or frame.distance_m is None:
            return
        if self.head_pose is not None and self._tf.has_sinks():
            T = self.head_pose(stamp)
            if T is not None and rigidity_problem(T) is None:
                T = np.asarray(T, dtype=np.float64)
                self._tf.log(transform_message(T, WORLD_FRAME, RIG_FRAME, stamp), log_time=stamp)
                self.encoded += 1
        now = time.monotonic()
        if now >= self._next_points and self._points.has_sinks():
            self._next_points = now + 1.0 / POINTS_HZ
            self._points.log(self._cloud(rig, frame, stamp), log_time=stamp)
            self.encoded += 1

    def _cloud(self, rig: Rig, frame: Frame, stamp: int) -> PointCloud:
        """The TOF frame's valid points (decimated), TOF frame, metres, with amplitude."""
        s = rig[self.tof]
        if self._grid is None or self._grid.rig is not rig:
            self._grid = _Grid(rig, self.tof)
        d = np.asarray(frame.distance_m, dtype=np.float32)
        amplitude = np.asarray(frame.image, dtype=np.float32)
        if s.range_correction is not None:
            d = s.range_correction.apply(d, amplitude)
        ok = np.isfinite(d) & (d > 0.1) & (d <= 10.0)
        ok &= ~mixed_pixels(d, MappingOptions().edge_rel)
        keep = np.zeros_like(ok)
        keep[::POINTS_STRIDE, ::POINTS_STRIDE] = True
        ok &= keep
        data = np.empty((int(ok.sum()), 4), np.float32)
        data[:, :3] = self._grid.rays[ok] * d[ok, None]
        data[:, 3] = amplitude[ok]
        f32 = PackedElementFieldNumericType.Float32
        return PointCloud(
            timestamp=_timestamp(stamp),
            frame_id=self.tof,
            pose=Pose(position=Vector3(x=0, y=0, z=0), orientation=Quaternion(x=0, y=0, z=0, w=1)),
            point_stride=16,
            fields=[
                PackedElementField(name=n, offset=4 * k, type=f32)
                for k, n in enumerate(("x", "y", "z", "amplitude"))
            ],
            data=data.astype("<f4", copy=False).tobytes(),
        )

    def _publish_static(self) -> None:
        """The calibrations and the rig's transforms (to the channels subscribed)."""
        rig, stamp = self.pipeline.rig, self._stamp()
        tf = self._tf.has_sinks()
        for name, s in rig.sensors.items():
            cal = self._channels[(name, "calibration")]
            if cal.has_sinks():
                cal.log(calibration_message(s, stamp), log_time=stamp)
                self.encoded += 1
            if tf:
                self._tf.log(
                    transform_message(s.T_rig_sensor, RIG_FRAME, name, stamp), log_time=stamp
                )
                self.encoded += 1

    def _publish_health(self) -> None:
        control = self.control
        health = control.sensor_health()
        rates = control.stream_rates()
        msg = {
            "stamp_ns": self._stamp(),
            "sensors": {n: {**h.as_dict(), "line": h.line()} for n, h in health.items()},
            "missing": sorted(self.pipeline.status.missing),
            "stream": {"fps": rates.stream_fps, "new_fps": rates.new_fps},
            "publisher": {
                "encoded": self.encoded,
                "dropped": self.dropped,
                "failed": self.failed,
                "video_pictures": self.video_pictures,
                "video_skipped": self.video_skipped,
            },
        }
        self._health.log(msg, log_time=msg["stamp_ns"])
        self.encoded += 1

    # -- the fused video ------------------------------------------------------------------

    def _video_wanted(self, wanted: bool) -> None:
        """Start the fused video's tap for the first subscriber, stop it after the last.
        A tap that failed (the encoder) is not started again until its subscribers left."""
        tap = self._tap
        if tap is not None and tap.error is not None and not self._video_failed:
            self._video_failed = True
            self._failed(RuntimeError(f"the fused video stopped: {tap.error}"))
        if not wanted:
            self._video_failed = False
            if tap is not None:
                self._stop_video()
        elif tap is None:
            source = FusedVideoSource(self.control.hub, self.pipeline.demand, self.video_settings)
            self._key_due = False
            self._tap = FusedVideoTap(source, self._deliver_video).start()
        elif self._key_due:
            self._key_due = False
            tap.request_key()

    def _stop_video(self) -> None:
        tap, self._tap = self._tap, None
        if tap is not None:
            tap.stop()

    def _deliver_video(self, unit: VideoUnit) -> bool:
        """An access unit from the tap (its thread) onto ``/fused/video``."""
        if self._video.write(unit.data, unit.key, unit.stamp_ns):
            self.video_pictures += 1
        else:
            self.video_skipped += 1
            tap = self._tap
            if self._video.awaiting_key and tap is not None:
                tap.request_key()
        return not self._worker.stopping


class _Grid(TofGrid):
    """A :class:`TofGrid` that remembers the rig it was made for."""

    def __init__(self, rig: Rig, tof: str) -> None:
        super().__init__(rig, tof)
        self.rig = rig


def check_foxglove_port(port: int) -> None:
    """OSError in one line unless 127.0.0.1:``port`` is free now (``trifuse serve`` asks
    before anything starts; :func:`start_foxglove_server` says it again if the port was
    taken meanwhile)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((LOOPBACK, port))
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise OSError(in_use_message(port)) from None
            raise OSError(f"cannot serve Foxglove on {LOOPBACK}:{port}: {e.strerror}") from None
