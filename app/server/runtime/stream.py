"""The fused stereo stream: the newest frame only, to any number of viewers.

A producer thread (the console's fusion thread) publishes pictures into a :class:`FrameHub`
and goes on with the next; each viewer (WebSocket or MJPEG) waits for a frame newer than
the last one it sent and sends the newest there is, so a slow viewer skips frames instead
of building a queue, and never slows the others or the producer. The routes ``/stream``
and ``/stream.mjpg`` are in :mod:`app.server.routers.stream_routes`; ``/stream.video`` in
:mod:`app.server.runtime.video_stream`.

A picture is encoded for JPEG viewers when the first of them takes it
(:meth:`FrameHub.jpeg_of`, in a worker thread: OpenCV releases the GIL, so the fusion of
the next frame set goes on meanwhile), once for all of them, and never for a picture no
JPEG viewer takes (one watching H.264 only, a recording, nobody).

The hub measures the stream (:class:`app.server.runtime.rates.StreamRates`): frames published and
new pictures per second over the last few seconds. Each frame's metadata carries these
figures (``rates``), so the viewer shows the same numbers as the Source panel and
``/api/status``, next to the rate at which it receives frames itself.

Each viewer holds the hub's :attr:`FrameHub.demand` while connected (:meth:`FrameHub.watching`):
the console fuses only while someone listens (:mod:`app.server.runtime.demand`).

What a viewer sends back is small and rare (an ack a frame): :class:`ViewerMessages` refuses
a message over :data:`MAX_MESSAGE_CHARS` (close 1009) and a viewer sending more than
:data:`MAX_MESSAGES_PER_S` (close 1008) before anything parses it, so that one viewer
cannot hold the server's loop (docs/SECURITY.md).
"""

from __future__ import annotations

import asyncio
import functools
import json
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from fastapi import WebSocket, WebSocketDisconnect

from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.kept_frames import KeptFrames
from trifuse.app.server.runtime.rates import RatesSnapshot, StreamRates
from trifuse.app.server.runtime.video_presets import StreamSettings
from trifuse.app.server.runtime.video_stats import VideoViewerStats

if TYPE_CHECKING:
    from trifuse.app.server.runtime.video_presets import Rung

MAX_MESSAGE_CHARS = 1024
"""The longest message a stream viewer may send, characters (text) or bytes: an ack is
about 40, ``{"preset": "auto"}`` 18."""
MAX_MESSAGES_PER_S = 200.0
"""Messages a viewer may send per second, over a burst of as many (a viewer acks at most
once per frame: 30 a second)."""
MESSAGE_TOO_BIG = 1009
POLICY_VIOLATION = 1008


class ViewerMessageRefused(ValueError):
    """A viewer's message over the limits; ``code``: the WebSocket close code to send."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code


class ViewerMessages:
    """The limits on what one stream viewer sends: at most :data:`MAX_MESSAGE_CHARS` a
    message, at most :data:`MAX_MESSAGES_PER_S` messages a second (a token bucket of as
    many). Checked before anything parses the message.

    Args:
        clock: monotonic seconds.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._tokens = MAX_MESSAGES_PER_S
        self._t = clock()

    def admit(self, message: dict[str, Any]) -> str | None:
        """The text of an ASGI ``websocket.receive`` message (None for a binary one) if it
        is within the limits; :class:`ViewerMessageRefused` otherwise."""
        text, data = message.get("text"), message.get("bytes")
        size = len(text) if text is not None else len(data) if data is not None else 0
        if size > MAX_MESSAGE_CHARS:
            unit = "characters" if text is not None else "bytes"
            raise ViewerMessageRefused(
                MESSAGE_TOO_BIG, f"message of {size} {unit}: at most {MAX_MESSAGE_CHARS} (an ack)"
            )
        now = self.clock()
        self._tokens = min(MAX_MESSAGES_PER_S, self._tokens + (now - self._t) * MAX_MESSAGES_PER_S)
        self._t = now
        if self._tokens < 1.0:
            raise ViewerMessageRefused(
                POLICY_VIOLATION, f"too many messages: at most {MAX_MESSAGES_PER_S:g} a second"
            )
        self._tokens -= 1.0
        return text


def encode_jpeg(bgr: np.ndarray, quality: int) -> bytes:
    """``bgr`` ((H, W, 3) uint8) as JPEG of ``quality`` (RuntimeError if OpenCV fails)."""
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("OpenCV could not encode the fused picture as JPEG")
    return buf.tobytes()


@dataclass(frozen=True)
class StreamFrame:
    """One stereo frame of the stream, as the hub published it.

    Attributes:
        seq: its number in the stream (1, 2, ...).
        jpeg: the picture as JPEG if its producer gave one; None: the hub encodes
            :attr:`bgr` when a JPEG viewer first asks (:meth:`FrameHub.jpeg_of`).
        meta: the picture's metadata as its producer gave it (JSON-able, never copied or
            changed: :meth:`fusion.frame_meta.FrameMeta.as_json` from the console); a
            viewer receives it in :meth:`header`.
        bgr: the fused picture itself, (H, W, 3) uint8 BGR, read-only and never written
            again (JPEG viewers and the video viewers encode it, a recording takes it); None
            when the producer gave only a JPEG.
        sent_ns: when it was published, wall clock (ns since the epoch).
        rates: the stream's rates then (:class:`app.server.runtime.rates.RatesSnapshot`).
    """

    seq: int
    jpeg: bytes | None
    meta: Mapping[str, Any]
    bgr: np.ndarray | None
    sent_ns: int
    rates: RatesSnapshot
    made_jpeg: list[asyncio.Future[bytes] | None] = field(
        default_factory=lambda: [None], compare=False
    )
    """The encoding of :attr:`bgr` for the JPEG viewers, started by the first of them
    (:meth:`FrameHub.jpeg_of`; one cell shared by the frames that publish the same picture
    again)."""

    def header(self) -> dict[str, Any]:
        """What a viewer overlays with the frame (JSON-able): :attr:`meta` with ``seq``,
        ``sent_ns`` and ``rates`` (:meth:`~app.server.runtime.rates.RatesSnapshot.as_dict`)."""
        return {
            **self.meta,
            "seq": self.seq,
            "sent_ns": self.sent_ns,
            "rates": self.rates.as_dict(),
        }

    @functools.cached_property
    def header_text(self) -> str:
        """:meth:`header` as JSON text, made once for all the frame's JPEG viewers."""
        return json.dumps(self.header())


class FrameHub:
    """The newest frame, published from any thread, awaited from the server's loop.

    Args:
        demand: what each viewer holds while connected (default: one of its own).
    """

    def __init__(self, demand: Demand | None = None) -> None:
        self.demand = demand if demand is not None else Demand("stream")
        self._lock = threading.Lock()
        self._frame: StreamFrame | None = None
        self._seq = 0
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Event]] = set()
        self.viewers = 0
        self.jpeg_quality = 80
        """The quality of the JPEG made of a picture for JPEG viewers (set by the pipeline)."""
        self.rates = StreamRates()
        """Frames published and new pictures per second (read by the panel and routes)."""
        self.stream_settings = StreamSettings()
        """The default video preset of new ``/stream.video`` viewers (``ctx.stream_settings``)."""
        self.video_viewers: list[VideoViewerStats] = []
        """The ``/stream.video`` viewers' figures (``/api/status``), one per connection."""
        self.video_encoders: dict[Rung, Any] = {}
        """The ``/stream.video`` encoders open now (``video_stream.SharedEncoder``: that
        module imports this one), one per rung that viewers watch
        (:mod:`app.server.runtime.video_stream` opens and closes them on the server's loop)."""
        self.kept = KeptFrames.from_env()
        """The last pictures by seq, for benchmarks (None: off; kept_frames.py)."""
        self.takers: list[Callable[[StreamFrame], None]] = []
        """Called with every frame published, in the publishing thread (they must be quick),
        by other takers of the pictures (a recording of the fused video, fused_video_tap.py)."""

    def publish(
        self,
        jpeg: bytes | None,
        meta: Mapping[str, Any],
        new: bool = True,
        bgr: np.ndarray | None = None,
    ) -> StreamFrame:
        """Make a picture the newest frame (any thread): its ``jpeg``, or its ``bgr`` (see
        :class:`StreamFrame`; the caller never writes to it again), or both. ``meta`` must be
        JSON-able; the frame keeps it as it is (the caller never changes it again).

        ``new``: the picture is new (False: the previous picture published again because
        its input did not change: :meth:`publish_again`). The frame gets its ``seq``,
        ``sent_ns`` and the stream's ``rates`` (:class:`StreamFrame`)."""
        if jpeg is None and bgr is None:
            raise ValueError("publish: expected a JPEG or a BGR picture, got neither")
        return self._publish(jpeg, meta, new, bgr, [None])

    def publish_again(self, meta: Mapping[str, Any]) -> StreamFrame | None:
        """Publish the newest frame's picture again (``new`` False: the same JPEG and BGR,
        the JPEG made of it shared) with ``meta``; None without a frame."""
        frame = self._frame
        if frame is None:
            return None
        return self._publish(frame.jpeg, meta, False, frame.bgr, frame.made_jpeg)

    def _publish(
        self,
        jpeg: bytes | None,
        meta: Mapping[str, Any],
        new: bool,
        bgr: np.ndarray | None,
        made_jpeg: list[asyncio.Future[bytes] | None],
    ) -> StreamFrame:
        self.rates.tick(new)
        rates = self.rates.snapshot()
        with self._lock:
            self._seq += 1
            frame = StreamFrame(self._seq, jpeg, meta, bgr, time.time_ns(), rates, made_jpeg)
            self._frame = frame
            waiters = list(self._waiters)
        if self.kept is not None:
            self.kept.add(frame.seq, frame.bgr)
        for loop, event in waiters:
            loop.call_soon_threadsafe(event.set)
        for take in list(self.takers):
            take(frame)
        return frame

    def repeat(self) -> StreamFrame | None:
        """Publish the newest frame again, as a repeat (:meth:`publish_again` with its own
        metadata); None without one. For a video encoder whose new viewer needs a key frame
        while no new picture comes (a paused replay)."""
        frame = self._frame
        return None if frame is None else self.publish_again(frame.meta)

    async def jpeg_of(self, frame: StreamFrame) -> bytes:
        """``frame``'s picture as JPEG, on the server's loop: the producer's, else its BGR
        encoded at :attr:`jpeg_quality` in a worker thread (OpenCV releases the GIL), once
        for every viewer awaiting it and every frame that publishes the same picture again.
        RuntimeError if OpenCV cannot encode it."""
        if frame.jpeg is not None:
            return frame.jpeg
        if frame.bgr is None:
            raise ValueError(f"frame {frame.seq} has no picture")
        made = frame.made_jpeg[0]
        if made is None or made.get_loop() is not asyncio.get_running_loop():
            made = frame.made_jpeg[0] = asyncio.ensure_future(
                asyncio.to_thread(encode_jpeg, frame.bgr, self.jpeg_quality)
            )
        return await asyncio.shield(made)  # a viewer leaving does not stop it for the others

    def forget(self) -> None:
        """No frame until the next :meth:`publish` (the producer rests: its last frame
        would be stale for a viewer arriving later)."""
        with self._lock:
            self._frame = None

    @property
    def latest(self) -> StreamFrame | None:
        return self._frame

    @contextmanager
    def watching(self) -> Iterator[None]:
        """A viewer is connected for the block: counted in ``viewers``, holding
        :attr:`demand`."""
        self.viewers += 1
        try:
            with self.demand.hold():
                yield
        finally:
            self.viewers -= 1

    @contextmanager
    def notifying(self, event: asyncio.Event) -> Iterator[None]:
        """Set ``event`` (in the running loop) at each :meth:`publish` during the block."""
        key = (asyncio.get_running_loop(), event)
        with self._lock:
            self._waiters.add(key)
        try:
            yield
        finally:
            with self._lock:
                self._waiters.discard(key)

    async def jpeg_frames(self, poll_s: float = 1.0) -> AsyncIterator[tuple[StreamFrame, bytes]]:
        """The newest frame with its JPEG (:meth:`jpeg_of`, made in a worker thread), each
        time there is a newer one (skipping what was missed)."""
        event = asyncio.Event()
        last = 0
        with self.notifying(event):
            while True:
                frame = self._frame
                if frame is not None and frame.seq > last:
                    last = frame.seq
                    yield frame, await self.jpeg_of(frame)
                    continue
                event.clear()
                if self._frame is frame:  # nothing newer since: wait for the next publish
                    try:
                        await asyncio.wait_for(event.wait(), poll_s)
                    except TimeoutError:
                        pass


async def close_quietly(ws: WebSocket, code: int, reason: str) -> None:
    """Close ``ws`` with ``code`` and ``reason`` (cut to 120 characters: a close frame holds
    123 bytes), unless it is closed already."""
    try:
        await ws.close(code=code, reason=reason[:120])
    except (RuntimeError, WebSocketDisconnect):
        pass
