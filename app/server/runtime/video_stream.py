"""``/stream.video``: the fused stereo stream as H.264, adapting to the viewer's link.

Protocol (docs/FORMATS.md, "The video stream"): per frame a JSON text message (the
``/stream`` metadata plus ``codec``, ``key``, ``width``, ``height``, ``bitrate_bps``,
``fps_target``, ``preset``, ``level``), then one binary message, the access unit in
Annex B. The viewer answers ``{"ack": SEQ, "recv_ms": T}`` once it drew frame ``SEQ``
(``T``: when the frame arrived, milliseconds on the viewer's clock; optional),
``{"keyframe": true}`` for an IDR (it also frees the window: the frames it could not
decode will never be acknowledged), ``{"preset": "4"}`` to change its preset; anything else
is ignored. ``?preset=`` unknown: the socket closes with 1008; none: the console's default
(:attr:`FrameHub.stream_settings <app.server.runtime.stream.FrameHub.stream_settings>`).

One :class:`VideoSession` per viewer: up to :data:`app.server.runtime.video_rate.WINDOW`
frames unacknowledged; a frame is encoded only when it may be sent, from the newest
picture (skipped pictures are skipped before encoding, so the P-frame chain never
breaks); encoding runs in a worker thread (``asyncio.to_thread``), one
:class:`app.recording.h264.VideoEncoder` per viewer. The first frame, and
the first after a preset, level or size change or a keyframe request, is an IDR.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from app.errors import describe_error
from app.recording.h264 import EncodedFrame, VideoEncoder
from app.server.runtime.stream import FrameHub, StreamFrame
from app.server.runtime.video_presets import PRESETS
from app.server.runtime.video_rate import WINDOW, RateController, Target
from app.server.runtime.video_stats import VideoViewerStats

log = logging.getLogger(__name__)

IDLE_WAIT_S = 0.25
"""The longest the sender sleeps without news (it then checks for a stalled link)."""
POLICY_VIOLATION = 1008
INTERNAL_ERROR = 1011


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
        self.encoder: VideoEncoder | None = None
        self._wake = asyncio.Event()
        self._want_key = True
        self._closed = False
        self._sent_ns: dict[int, int] = {}  # seq in flight -> its publication, ns

    async def run(self) -> None:
        """Serve the viewer until it leaves."""
        self.hub.video_viewers.append(self.stats)
        reader: asyncio.Task[None] | None = None
        try:
            with self.hub.watching(), self.hub.notifying(self._wake):
                reader = asyncio.create_task(self._read())
                await self._send_loop()
        except (WebSocketDisconnect, RuntimeError):
            pass
        except Exception as exc:  # an encoder failure: tell the viewer, keep the console
            log.warning("video viewer stopped: %s", describe_error(exc))
            await self._close(INTERNAL_ERROR, describe_error(exc))
        finally:
            if reader is not None:
                reader.cancel()
            self.hub.video_viewers.remove(self.stats)
            if self.encoder is not None:
                self.encoder.close()

    async def _close(self, code: int, reason: str) -> None:
        try:
            await self.ws.close(code=code, reason=reason[:120])
        except (RuntimeError, WebSocketDisconnect):
            pass

    # -- sending ----------------------------------------------------------------------------

    async def _send_loop(self) -> None:
        last_seq = 0
        while not self._closed:
            self._wake.clear()  # before looking: a publish from now on wakes the wait
            now = self.clock()
            frame = self.hub.latest
            fresh = frame is not None and frame.bgr is not None and frame.seq > last_seq
            wait = self.ctl.wait_s(now)
            if fresh and wait == 0.0 and frame is not None:
                await self._send(frame)
                last_seq = frame.seq
                continue
            self.ctl.target(now)  # a stalled link steps the bitrate down meanwhile
            self._refresh_stats(now)
            timeout = IDLE_WAIT_S if wait is None or not fresh else min(wait, IDLE_WAIT_S)
            try:
                await asyncio.wait_for(self._wake.wait(), max(timeout, 0.001))
            except TimeoutError:
                pass

    async def _send(self, frame: StreamFrame) -> None:
        now = self.clock()
        target = self.ctl.target(now)
        force, self._want_key = self._want_key, False
        t0 = time.perf_counter()
        bgr = frame.bgr
        if bgr is None:
            return
        enc = await asyncio.to_thread(self._encode, bgr, target, force, now)
        self.stats.encode_ms = (time.perf_counter() - t0) * 1000
        if self._closed:
            return
        meta: dict[str, Any] = {
            **frame.meta,
            "codec": enc.codec,
            "key": enc.key,
            "width": enc.width,
            "height": enc.height,
            "bitrate_bps": target.bitrate_bps,
            "fps_target": target.fps,
            "preset": self.ctl.preset,
            "level": target.level.name,
        }
        sent = self.clock()
        self.ctl.on_sent(frame.seq, len(enc.data), sent)  # before the ack can arrive
        self._sent_ns[frame.seq] = int(frame.meta.get("sent_ns", time.time_ns()))
        self.stats.count_sent(sent, len(enc.data), enc.key)
        self.stats.codec, self.stats.width, self.stats.height = enc.codec, enc.width, enc.height
        self._refresh_stats(sent, target)
        await self.ws.send_text(json.dumps(meta))
        await self.ws.send_bytes(enc.data)

    def _encode(self, bgr: np.ndarray, target: Target, force: bool, t: float) -> EncodedFrame:
        """In a worker thread: the encoder at the target's level and bitrate, one frame."""
        if self.encoder is None:
            self.encoder = VideoEncoder(target.level, target.bitrate_bps)
        else:
            self.encoder.set_level(target.level, target.bitrate_bps)
        return self.encoder.encode(bgr, force_key=force, t_s=t)

    # -- receiving --------------------------------------------------------------------------

    async def _read(self) -> None:
        try:
            while True:
                msg = await self.ws.receive()
                if msg["type"] == "websocket.disconnect":
                    return
                text = msg.get("text")
                if text is not None:
                    self._handle(text)
        except (WebSocketDisconnect, RuntimeError):
            return
        finally:
            self._closed = True
            self._wake.set()

    def _handle(self, text: str) -> None:
        """One message from the viewer (see the module doc); anything else is ignored."""
        try:
            data = json.loads(text)
        except ValueError:
            return
        if not isinstance(data, dict):
            return
        now = self.clock()
        seq = data.get("ack")
        if isinstance(seq, int) and not isinstance(seq, bool):
            self.ctl.on_ack(seq, now, _seconds(data.get("recv_ms")))
            sent_ns = self._sent_ns.get(seq)
            if sent_ns is not None:
                self.stats.latency_ms = (time.time_ns() - sent_ns) / 1e6
            for s in [s for s in self._sent_ns if s <= seq]:
                del self._sent_ns[s]
        if data.get("keyframe") is True:
            self._want_key = True
            self.ctl.reset_in_flight()
            self._sent_ns.clear()
        preset = data.get("preset")
        if isinstance(preset, str) and preset in PRESETS:
            self.ctl.set_preset(preset)
            self.stats.preset = preset
            self._want_key = True
        self._refresh_stats(now)
        self._wake.set()

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
    if isinstance(ms, int | float) and not isinstance(ms, bool) and math.isfinite(ms):
        return float(ms) / 1000
    return None


def make_video_router(hub: FrameHub) -> APIRouter:
    """``/stream.video`` (WebSocket; see the module doc)."""
    router = APIRouter()

    @router.websocket("/stream.video")
    async def _video(ws: WebSocket) -> None:
        await ws.accept()
        preset = ws.query_params.get("preset") or hub.stream_settings.preset
        if preset not in PRESETS:
            reason = f"unknown preset {preset[:40]!r}: expected one of {', '.join(PRESETS)}"
            await ws.close(code=POLICY_VIOLATION, reason=reason)
            return
        await VideoSession(hub, ws, preset).run()

    return router
