"""One ``/stream.video`` viewer's figures, as ``/api/status`` reports them (``stream.video``).

The viewer's session (:mod:`app.server.runtime.video_stream`) updates them; the hub lists
them while the viewer is connected (:attr:`app.server.runtime.stream.FrameHub.video_viewers`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from trifuse.app.server.runtime.rates import RateWindow

FPS_WINDOW_S = 2.0
"""The frame rate is counted over this many seconds."""


@dataclass
class VideoViewerStats:
    """Figures of one video viewer (times in seconds on the session's monotonic clock).

    Attributes:
        preset: the preset asked for (``auto``, ``8`` ...).
        level: the ladder step in use (``"8"`` ...).
        codec: the WebCodecs codec string of the stream (``"avc1.42c032"``).
        width, height: the coded picture, pixels.
        bitrate_bps: the controller's target, bit/s.
        fps_target: the level's frame rate.
        delivered_bps: bits acknowledged over the last second, per second.
        rtt_ms: the last frame's round trip (sent -> acknowledged), ms.
        min_rtt_ms: the least round trip of the last 10 s, ms.
        latency_ms: the last acknowledged frame's age: from its publication (the fused
            picture ready) to its acknowledgement (decoded and drawn), ms.
        encode_ms: the last frame's encoding time, ms.
        in_flight: frames sent and not acknowledged; ``window``: the most allowed.
        frames_sent, keyframes, bytes_sent: since the viewer connected.
        congestion_events: the controller's steps down.
        undone_events: steps down undone (the acknowledgements were late, not the frames).
        last_congestion: why the last step down was taken (``queue``, ``stall``, ``short``,
            ``late``: behind its shared encoder).
        queue_ms: the last frame's delay above the least of the last 10 s, ms (one-way when
            the viewer says when frames arrive, else the round trip).
    """

    preset: str
    level: str = ""
    codec: str = ""
    width: int = 0
    height: int = 0
    bitrate_bps: int = 0
    fps_target: int = 0
    delivered_bps: float = 0.0
    rtt_ms: float | None = None
    min_rtt_ms: float | None = None
    latency_ms: float | None = None
    encode_ms: float | None = None
    in_flight: int = 0
    window: int = 0
    frames_sent: int = 0
    keyframes: int = 0
    bytes_sent: int = 0
    congestion_events: int = 0
    undone_events: int = 0
    queue_ms: float | None = None
    last_congestion: str | None = None
    _sent: RateWindow = field(
        default_factory=lambda: RateWindow(FPS_WINDOW_S, from_first=False), repr=False
    )

    def count_sent(self, t: float, nbytes: int, key: bool) -> None:
        """A frame of ``nbytes`` went out at ``t``."""
        self.frames_sent += 1
        self.keyframes += key
        self.bytes_sent += nbytes
        self._sent.tick("sent", t)

    def fps(self, t: float) -> float:
        """Frames sent per second over the last :data:`FPS_WINDOW_S` before ``t``
        (divided by the whole window from the first frame on)."""
        return self._sent.rate("sent", t)

    def as_dict(self, t: float) -> dict[str, Any]:
        """The figures (JSON-able), with ``fps`` at ``t``."""
        out = {k: v for k, v in vars(self).items() if not k.startswith("_")}
        out["fps"] = self.fps(t)
        return out
