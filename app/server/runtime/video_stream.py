"""``/stream.video``: the fused stereo stream as H.264, adapting to the viewer's link (the
route: :mod:`app.server.routers.stream_routes`).

Protocol (docs/FORMATS.md, "The video stream"): per frame a JSON text message (the
``/stream`` metadata plus ``codec``, ``key``, ``width``, ``height``, ``bitrate_bps``,
``fps_target``, ``preset``, ``level``), then one binary message, the access unit in
Annex B. The viewer answers ``{"ack": SEQ, "recv_ms": T}`` once it drew frame ``SEQ``
(``T``: when the frame arrived, milliseconds on the viewer's clock; optional),
``{"keyframe": true}`` for an IDR (it also frees the window: the frames it could not
decode will never be acknowledged), ``{"preset": "4"}`` to change its preset; anything else
is ignored. A message over :data:`app.server.runtime.stream.MAX_MESSAGE_CHARS` closes the
socket with 1009, more than :data:`app.server.runtime.stream.MAX_MESSAGES_PER_S` messages a
second with 1008, before anything parses them. ``?preset=`` unknown: the socket closes with
1008; none: the console's default
(:attr:`FrameHub.stream_settings <app.server.runtime.stream.FrameHub.stream_settings>`).

Viewers share encoders. Each viewer's :class:`app.server.runtime.video_rate.RateController`
aims at a bitrate and a level; the viewer watches the :class:`SharedEncoder` of that
target's rung (:func:`app.server.runtime.video_presets.rung_for`: the level at a bitrate
rounded down to the level's cap times a power of 0.7), one per rung in the hub
(:attr:`FrameHub.video_encoders <app.server.runtime.stream.FrameHub.video_encoders>`),
opened when its first viewer comes and closed, its memory returned, when its last one
leaves. A change of rate moves the viewer to another encoder. An encoder encodes the hub's
newest picture in a worker thread (``asyncio.to_thread``) whenever one of its viewers may
send a frame (:meth:`RateController.wait_s`: fewer than
:data:`app.server.runtime.video_rate.WINDOW` frames unacknowledged, the level's frame rate),
and hands the access unit to every viewer. A viewer starts on a key frame: joining an
encoder, or after a keyframe request, it asks the encoder for an IDR (one every
:data:`KEY_INTERVAL_S` at most, shared by all who wait) and skips what comes before it;
while no new picture comes (a paused replay), the newest is published again for it
(:meth:`FrameHub.repeat <app.server.runtime.stream.FrameHub.repeat>`). A viewer that cannot
take the units as they come keeps at most :data:`QUEUE_FRAMES` of them waiting; one more and
it drops them, waits for the next key frame and its rate steps down
(:meth:`RateController.on_dropped`), which usually moves it to an encoder of its own pace. A
viewer alone on its encoder gets exactly the old behaviour: a frame is encoded only when it
may be sent, from the newest picture.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import json
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from fastapi import WebSocket, WebSocketDisconnect

from trifuse.app.errors import describe_error
from trifuse.app.recording.h264 import EncodedFrame, VideoEncoder
from trifuse.app.server.runtime.stream import (
    FrameHub,
    StreamFrame,
    ViewerMessageRefused,
    ViewerMessages,
    close_quietly,
)
from trifuse.app.server.runtime.video_presets import PRESETS, Rung, rung_for
from trifuse.app.server.runtime.video_rate import WINDOW, RateController, Target
from trifuse.app.server.runtime.video_stats import VideoViewerStats
from trifuse.calib.numbers import is_int, is_int_or_float

log = logging.getLogger(__name__)

IDLE_WAIT_S = 0.25
"""The longest a sender or an encoder sleeps without news (a stalled link is checked)."""
KEY_INTERVAL_S = 0.5
"""An encoder makes a requested IDR at most this often: viewers joining or asking meanwhile
wait for the same one (an IDR costs every viewer of the encoder a large frame)."""
QUEUE_FRAMES = WINDOW
"""Access units that may wait for a viewer's window; one more and they are dropped."""
INTERNAL_ERROR = 1011


@dataclass(frozen=True)
class Unit:
    """One access unit of a :class:`SharedEncoder`: the hub's ``frame`` encoded as ``enc``
    at ``rung`` in ``encode_ms`` (milliseconds). The same object goes to every viewer."""

    frame: StreamFrame
    enc: EncodedFrame
    rung: Rung
    encode_ms: float
    _meta: dict[str, str] = field(default_factory=dict, compare=False, repr=False)

    @property
    def seq(self) -> int:
        return self.frame.seq

    def meta_text(self, preset: str) -> str:
        """The JSON text message that goes before the unit, for a viewer with ``preset``
        (made once per preset)."""
        text = self._meta.get(preset)
        if text is None:
            level = self.rung.level
            text = self._meta[preset] = json.dumps(
                {
                    **self.frame.header(),
                    "codec": self.enc.codec,
                    "key": self.enc.key,
                    "width": self.enc.width,
                    "height": self.enc.height,
                    "bitrate_bps": self.rung.bitrate_bps,
                    "fps_target": level.fps,
                    "preset": preset,
                    "level": level.name,
                }
            )
        return text


def _find_malloc_trim() -> Callable[[int], int] | None:
    libc = ctypes.util.find_library("c")
    return getattr(ctypes.CDLL(libc), "malloc_trim", None) if libc else None


_MALLOC_TRIM = _find_malloc_trim()


def release_memory() -> None:
    """glibc's ``malloc_trim(0)``: gives freed heap pages back to the system (an encoder
    at level 8 frees about 37 MB, which would otherwise stay in the process's arenas);
    nothing where there is no glibc."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


class SharedEncoder:
    """One H.264 encoder at one rung, fanned out to the viewers watching it (see the module
    doc). Made by :func:`watch` on the server's loop; its task ends, and the encoder is
    freed, once its last viewer has left.

    Args:
        hub: the stream's frames.
        rung: what to encode (level: size and frame rate; bitrate).
        clock: monotonic seconds.
    """

    def __init__(
        self, hub: FrameHub, rung: Rung, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.hub, self.rung, self.clock = hub, rung, clock
        self.viewers: list[VideoSession] = []
        self.wake = asyncio.Event()
        """Set when a viewer may take a frame, a key frame is wanted or a viewer leaves."""
        self.frames = 0
        self.encoder: VideoEncoder | None = None
        self._want_key = True
        self._key_t = -math.inf  # when the last IDR was made
        self._last_seq = 0
        self._encoded_t = -math.inf  # when the last frame was encoded
        self.task = asyncio.get_running_loop().create_task(self._run())

    def retune(self, rung: Rung) -> None:
        """Encode at ``rung`` from the next frame on (its viewer alone moves: the encoder
        changes its bitrate between frames, and makes an IDR only for a new level)."""
        encoders = self.hub.video_encoders
        if encoders.get(self.rung) is self:
            del encoders[self.rung]
        self.rung = rung
        encoders[rung] = self
        self.wake.set()

    def want_key(self) -> None:
        """A viewer needs an IDR (it comes within :data:`KEY_INTERVAL_S` of the last one)."""
        self._want_key = True
        self.wake.set()

    def _key_due(self, t: float) -> bool:
        return self._want_key and t - self._key_t >= KEY_INTERVAL_S

    def _stalled(self, t: float, frame: StreamFrame | None) -> bool:
        """Viewers wait for a key frame, which may be made, but no new picture came for
        :data:`KEY_INTERVAL_S` (a paused replay): the newest is to be published again."""
        return (
            frame is not None
            and frame.bgr is not None
            and frame.seq <= self._last_seq
            and self._key_due(t)
            and t - self._encoded_t >= KEY_INTERVAL_S
            and any(v.needs_key for v in self.viewers)
        )

    def _wait_s(self, t: float, frame: StreamFrame | None) -> float | None:
        """Seconds until a frame should be encoded (0: now); None: until news. Only a
        picture not encoded yet, for a viewer that may send it and would use it (a viewer
        waiting for a key frame uses only an IDR)."""
        if frame is None or frame.bgr is None or frame.seq <= self._last_seq:
            return None
        key_due = self._key_due(t)
        takers = [v for v in self.viewers if key_due or not v.needs_key]
        waits = [w for v in takers if (w := v.wait_s(t)) is not None]
        if not key_due and self._want_key:  # when the next IDR may be made
            waits.append(KEY_INTERVAL_S - (t - self._key_t))
        return min(waits, default=None)

    async def _run(self) -> None:
        try:
            with self.hub.notifying(self.wake):
                while self.viewers:
                    self.wake.clear()  # before looking: a publish from now on wakes the wait
                    now = self.clock()
                    frame = self.hub.latest
                    if self._stalled(now, frame):
                        frame = self.hub.repeat()
                    wait = self._wait_s(now, frame)
                    if wait == 0.0 and frame is not None:
                        await self._encode(frame, now)
                        continue
                    timeout = IDLE_WAIT_S if wait is None else min(wait, IDLE_WAIT_S)
                    try:
                        await asyncio.wait_for(self.wake.wait(), max(timeout, 0.001))
                    except TimeoutError:
                        pass
        except Exception as exc:  # the encoder failed: its viewers are told, the console goes on
            log.warning("video encoder stopped: %s", describe_error(exc))
            for viewer in list(self.viewers):
                viewer.encoder_failed(exc)
        finally:
            if self.hub.video_encoders.get(self.rung) is self:
                del self.hub.video_encoders[self.rung]
            if self.encoder is not None:
                self.encoder.close()
                self.encoder = None
                try:
                    asyncio.get_running_loop().run_in_executor(None, release_memory)
                except RuntimeError:  # the loop's executor is shut down: the process ends
                    pass

    async def _encode(self, frame: StreamFrame, t: float) -> None:
        force, rung = self._key_due(t), self.rung
        t0 = time.perf_counter()
        bgr = frame.bgr
        if bgr is None:
            return
        enc = await asyncio.to_thread(self._encode_in_thread, bgr, rung, force, t)
        encode_ms = (time.perf_counter() - t0) * 1000
        self._last_seq, self._encoded_t = frame.seq, t
        self.frames += 1
        if enc.key:
            self._want_key, self._key_t = False, t
        unit = Unit(frame, enc, rung, encode_ms)
        for viewer in list(self.viewers):  # those watching now
            viewer.offer(unit)

    def _encode_in_thread(self, bgr: np.ndarray, rung: Rung, force: bool, t: float) -> EncodedFrame:
        if self.encoder is None:
            self.encoder = VideoEncoder(rung.level, rung.bitrate_bps)
        elif (self.encoder.level, self.encoder.bitrate_bps) != (rung.level, rung.bitrate_bps):
            self.encoder.set_level(rung.level, rung.bitrate_bps)  # retuned
        return self.encoder.encode(bgr, force_key=force, t_s=t)


def watch(hub: FrameHub, rung: Rung, viewer: VideoSession) -> SharedEncoder:
    """The hub's encoder at ``rung`` (opened if there is none), with ``viewer`` watching it
    and an IDR asked for."""
    encoder = hub.video_encoders.get(rung)
    if encoder is None or encoder.task.done():
        encoder = hub.video_encoders[rung] = SharedEncoder(hub, rung, viewer.clock)
    encoder.viewers.append(viewer)
    encoder.want_key()
    return encoder


def unwatch(encoder: SharedEncoder, viewer: VideoSession) -> None:
    """``viewer`` leaves ``encoder``; without viewers it closes (its task ends)."""
    if viewer in encoder.viewers:
        encoder.viewers.remove(viewer)
    if not encoder.viewers:
        if encoder.hub.video_encoders.get(encoder.rung) is encoder:
            del encoder.hub.video_encoders[encoder.rung]
        encoder.wake.set()


class VideoSession:
    """One viewer of ``/stream.video`` (see the module doc).

    Args:
        hub: the stream's frames (they must carry ``bgr``: the session registers in
            ``hub.video_viewers`` so that they do).
        ws: the accepted WebSocket.
        preset: one of :data:`PRESETS` (checked by the caller).
        window: the most frames in flight.
        clock: monotonic seconds.
    """

    def __init__(
        self,
        hub: FrameHub,
        ws: WebSocket,
        preset: str,
        window: int = WINDOW,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.hub, self.ws, self.clock = hub, ws, clock
        self.ctl = RateController(preset, window)
        self.stats = VideoViewerStats(preset=preset, window=window)
        self.encoder: SharedEncoder | None = None
        self.needs_key = True
        """Units are skipped until an IDR (the decoder starts there)."""
        self._queue: deque[Unit] = deque()
        self._last_seq = 0  # the newest unit queued
        self._wake = asyncio.Event()
        self._closed = False
        self._failure: Exception | None = None
        self._messages = ViewerMessages(clock)
        self._sent_ns: dict[int, int] = {}  # seq in flight -> its publication, ns

    async def run(self) -> None:
        """Serve the viewer until it leaves."""
        self.hub.video_viewers.append(self.stats)
        reader: asyncio.Task[None] | None = None
        try:
            with self.hub.watching():
                reader = asyncio.create_task(self._read())
                await self._send_loop()
            if self._failure is not None:
                raise self._failure
        except ViewerMessageRefused as exc:
            await close_quietly(self.ws, exc.code, str(exc))
        except (WebSocketDisconnect, RuntimeError):
            pass
        except Exception as exc:  # an encoder failure: tell the viewer, keep the console
            log.warning("video viewer stopped: %s", describe_error(exc))
            await close_quietly(self.ws, INTERNAL_ERROR, describe_error(exc))
        finally:
            if reader is not None:
                reader.cancel()
            self.hub.video_viewers.remove(self.stats)
            self._closed = True
            if self.encoder is not None:
                unwatch(self.encoder, self)
                self.encoder = None

    # -- what the encoder asks --------------------------------------------------------------

    def wait_s(self, t: float) -> float | None:
        """Seconds until this viewer may take a new frame (0: now); None while units wait
        for it, its window is full or it has left."""
        if self._closed or self._queue:
            return None
        return self.ctl.wait_s(t)

    def offer(self, unit: Unit) -> None:
        """A unit of the encoder this viewer watches: queued to be sent, skipped while a key
        frame is awaited, or, with :data:`QUEUE_FRAMES` waiting already, all dropped."""
        if self._closed:
            return
        if unit.seq <= self._last_seq:  # an encoder joined late encoded a frame sent already
            if self.needs_key and self.encoder is not None:
                self.encoder.want_key()
            return
        if self.needs_key:
            if not unit.enc.key:
                return
            self.needs_key = False
        if len(self._queue) >= QUEUE_FRAMES:
            self._drop()
            return
        self._queue.append(unit)
        self._last_seq = unit.seq
        self._wake.set()

    def encoder_failed(self, exc: Exception) -> None:
        """The encoder stopped with ``exc``: the viewer is closed with the reason."""
        self._failure = exc
        self._closed = True
        self._wake.set()

    def _drop(self) -> None:
        """The viewer fell behind: drop what waits, step down, wait for a key frame."""
        self._queue.clear()
        self.needs_key = True
        now = self.clock()
        self.ctl.on_dropped(now)
        self._follow(self.ctl.target(now), ask_key=True)

    def _follow(self, target: Target, ask_key: bool = False) -> None:
        """Watch the encoder of ``target``'s rung: the same, asking it for an IDR with
        ``ask_key``; retuned, if this viewer is its only one and no other encoder is at that
        rung (no IDR unless the level changes); else another, waiting for its IDR."""
        rung = rung_for(target.level, target.bitrate_bps)
        encoder = self.encoder
        if encoder is not None:
            alone = encoder.viewers == [self]
            if encoder.rung != rung and alone and rung not in self.hub.video_encoders:
                encoder.retune(rung)
            if encoder.rung == rung:
                if ask_key:
                    encoder.want_key()
                return
            unwatch(encoder, self)
        self._queue.clear()
        self.needs_key = True
        self.encoder = watch(self.hub, rung, self)

    # -- sending ----------------------------------------------------------------------------

    async def _send_loop(self) -> None:
        while not self._closed:
            self._wake.clear()  # before looking: news from now on wakes the wait
            now = self.clock()
            target = self.ctl.target(now)  # a stalled link steps the bitrate down meanwhile
            self._follow(target)
            if self._queue and self.ctl.in_flight < self.ctl.window:
                await self._send(self._queue.popleft(), target)
                continue
            self._refresh_stats(now, target)
            try:
                await asyncio.wait_for(self._wake.wait(), IDLE_WAIT_S)
            except TimeoutError:
                pass

    async def _send(self, unit: Unit, target: Target) -> None:
        enc = unit.enc
        sent = self.clock()
        self.ctl.on_sent(unit.seq, len(enc.data), sent)  # before the ack can arrive
        self._sent_ns[unit.seq] = unit.frame.sent_ns
        s = self.stats
        s.count_sent(sent, len(enc.data), enc.key)
        s.codec, s.width, s.height, s.encode_ms = enc.codec, enc.width, enc.height, unit.encode_ms
        self._refresh_stats(sent, target)
        await self.ws.send_text(unit.meta_text(self.ctl.preset))
        await self.ws.send_bytes(enc.data)
        if not self._queue and self.encoder is not None:
            self.encoder.wake.set()  # this viewer may take the next frame

    # -- receiving --------------------------------------------------------------------------

    async def _read(self) -> None:
        try:
            while True:
                msg = await self.ws.receive()
                if msg["type"] == "websocket.disconnect":
                    return
                text = self._messages.admit(msg)
                if text is not None:
                    self._handle(text)
        except ViewerMessageRefused as exc:
            self._failure = exc
        except (WebSocketDisconnect, RuntimeError):
            return
        finally:
            self._closed = True
            self._wake.set()

    def _handle(self, text: str) -> None:
        """One message from the viewer (see the module doc); anything else is ignored."""
        try:
            data = json.loads(text)
        except (ValueError, RecursionError):  # not JSON; nested too deep
            return
        if not isinstance(data, dict):
            return
        now = self.clock()
        seq = data.get("ack")
        if is_int(seq):
            self.ctl.on_ack(seq, now, _seconds(data.get("recv_ms")))
            sent_ns = self._sent_ns.get(seq)
            if sent_ns is not None:
                self.stats.latency_ms = (time.time_ns() - sent_ns) / 1e6
            for s in [s for s in self._sent_ns if s <= seq]:
                del self._sent_ns[s]
        if data.get("keyframe") is True:
            self.ctl.reset_in_flight()
            self._sent_ns.clear()
            self._queue.clear()
            self.needs_key = True
            if self.encoder is not None:
                self.encoder.want_key()
        preset = data.get("preset")
        if isinstance(preset, str) and preset in PRESETS:
            self.ctl.set_preset(preset)
            self.stats.preset = preset
        self._refresh_stats(now)
        self._wake.set()
        if self.encoder is not None:
            self.encoder.wake.set()

    def _refresh_stats(self, t: float, target: Target | None = None) -> None:
        s, ctl = self.stats, self.ctl
        if target is not None:
            s.level, s.bitrate_bps, s.fps_target = target.level.name, target.bitrate_bps, target.fps
        s.delivered_bps = ctl.delivered_bps(t)
        s.rtt_ms = None if ctl.last_rtt_s is None else ctl.last_rtt_s * 1000
        s.min_rtt_ms = ctl.min_rtt_s * 1000 if ctl.last_rtt_s is not None else None
        s.in_flight = ctl.in_flight
        s.congestion_events = ctl.congestion_events
        s.undone_events = ctl.undone_events
        s.last_congestion = ctl.last_congestion
        q = ctl.queue_delay_s
        s.queue_ms = None if q is None else q * 1000


def _seconds(ms: object) -> float | None:
    """A finite number of milliseconds from the viewer, in seconds; None otherwise."""
    if is_int_or_float(ms) and math.isfinite(ms):
        return float(ms) / 1000
    return None
