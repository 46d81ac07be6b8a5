"""The fused stereo stream: the newest frame only, to any number of viewers.

A producer thread publishes JPEG frames into a :class:`FrameHub`; each viewer (WebSocket or
MJPEG) waits for a frame newer than the last one it sent and sends the newest there is, so
a slow viewer skips frames instead of building a queue, and never slows the others. The
routes ``/stream`` and ``/stream.mjpg`` are in :mod:`app.server.routers.stream_routes`.

The hub measures the stream (:class:`app.server.runtime.rates.StreamRates`): frames published and
new pictures per second over the last few seconds. Each frame's metadata carries these
figures (``rates``), so the viewer shows the same numbers as the Source panel and
``/api/status``, next to the rate at which it receives frames itself.

Each viewer holds the hub's :attr:`FrameHub.demand` while connected (:meth:`FrameHub.watching`):
the console fuses and encodes only while someone listens (:mod:`app.server.runtime.demand`),
and encodes JPEG only while a JPEG viewer listens or nobody takes the pictures themselves
(:attr:`FrameHub.wants_jpeg`).

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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

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


@dataclass(frozen=True)
class StreamFrame:
    """One stereo frame of the stream, as the hub published it.

    Attributes:
        seq: its number in the stream (1, 2, ...).
        jpeg: the picture as JPEG; None while no JPEG viewer listens and the picture goes
            as itself (:attr:`FrameHub.wants_jpeg`).
        meta: the picture's metadata as its producer gave it (JSON-able, never copied or
            changed: :meth:`fusion.frame_meta.FrameMeta.as_json` from the console); a
            viewer receives it in :meth:`header`.
        bgr: the fused picture itself, (H, W, 3) uint8 BGR, read-only and never written
            again (the video viewers encode it, :mod:`app.server.runtime.video_stream`);
            None when nobody takes it (:attr:`FrameHub.wants_bgr`).
        sent_ns: when it was published, wall clock (ns since the epoch).
        rates: the stream's rates then (:class:`app.server.runtime.rates.RatesSnapshot`).
    """

    seq: int
    jpeg: bytes | None
    meta: Mapping[str, Any]
    bgr: np.ndarray | None
    sent_ns: int
    rates: RatesSnapshot

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
        self.jpeg_viewers = 0
        """Viewers of ``/stream`` and ``/stream.mjpg`` (counted in :attr:`viewers` too)."""
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
        by other takers of the pictures (a recording of the fused video, fused_video_tap.py):
        while there is one, frames carry their BGR."""

    @property
    def wants_bgr(self) -> bool:
        """Whether frames should carry their BGR picture (a video viewer is connected, or
        pictures are kept for a benchmark: :attr:`kept`, or taken: :attr:`takers`)."""
        return bool(self.video_viewers) or self.kept is not None or bool(self.takers)

    @property
    def wants_jpeg(self) -> bool:
        """Whether frames should carry a JPEG: a JPEG viewer is connected, or nobody takes
        the pictures themselves (:attr:`wants_bgr`; JPEG is the stream's default). Encoding
        it for video viewers alone would cost CPU a frame for nobody."""
        return self.jpeg_viewers > 0 or not self.wants_bgr

    def publish(
        self,
        jpeg: bytes | None,
        meta: Mapping[str, Any],
        new: bool = True,
        bgr: np.ndarray | None = None,
    ) -> StreamFrame:
        """Make ``jpeg`` the newest frame (any thread). ``meta`` must be JSON-able; the
        frame keeps it as it is (the caller never changes it again).

        ``new``: the picture is new (False: the previous picture published again because
        its input did not change). ``bgr``: the picture (see :class:`StreamFrame`; the
        caller never writes to it again). The frame gets its ``seq``, ``sent_ns`` and the
        stream's ``rates`` (:class:`StreamFrame`)."""
        self.rates.tick(new)
        rates = self.rates.snapshot()
        with self._lock:
            self._seq += 1
            frame = StreamFrame(self._seq, jpeg, meta, bgr, time.time_ns(), rates)
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
        """Publish the newest frame again, as a repeat (``new`` False: the same picture,
        JPEG and metadata, a new ``seq``); None without one. For a video encoder whose new
        viewer needs a key frame while no new picture comes (a paused replay)."""
        frame = self._frame
        if frame is None:
            return None
        return self.publish(frame.jpeg, frame.meta, new=False, bgr=frame.bgr)

    def forget(self) -> None:
        """No frame until the next :meth:`publish` (the producer rests: its last frame
        would be stale for a viewer arriving later)."""
        with self._lock:
            self._frame = None

    @property
    def latest(self) -> StreamFrame | None:
        return self._frame

    @contextmanager
    def watching(self, jpeg: bool = False) -> Iterator[None]:
        """A viewer is connected for the block: counted in ``viewers`` (and with ``jpeg`` in
        ``jpeg_viewers``), holding :attr:`demand`."""
        self.viewers += 1
        self.jpeg_viewers += jpeg
        try:
            with self.demand.hold():
                yield
        finally:
            self.viewers -= 1
            self.jpeg_viewers -= jpeg

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
        """The newest frame that has a JPEG, with the JPEG, each time there is a newer one
        (skipping what was missed)."""
        event = asyncio.Event()
        last = 0
        with self.notifying(event):
            while True:
                frame = self._frame
                if frame is not None and frame.seq > last and frame.jpeg is not None:
                    last = frame.seq
                    yield frame, frame.jpeg
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
