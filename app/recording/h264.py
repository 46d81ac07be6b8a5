"""H.264 encoding of the fused stereo picture (libx264 through PyAV), for the video stream
(``/stream.video``, :mod:`app.server.runtime.video_stream`) and the fused video of
recordings (:mod:`app.recording.video_track`).

A :class:`Level` says what to encode (picture size, frame rate, bitrate cap);
:class:`VideoEncoder` encodes: ultrafast / zerolatency, no B-frames, periodic intra refresh,
the bitrate held by the VBV; its output is Annex B access units (start codes, SPS/PPS
in-band before every IDR), what WebCodecs decodes when its config has no ``description``
and what Foxglove's ``foxglove.CompressedVideo`` carries.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import av
import cv2
import numpy as np


@dataclass(frozen=True)
class Level:
    """One step of the ladder.

    Attributes:
        name: the preset that names it (``"8"``: 8 Mbit/s).
        max_bps: the highest bitrate at this level, bit/s.
        size: the coded picture, (width, height) pixels.
        fps: the highest frame rate, frames/s.
    """

    name: str
    max_bps: int
    size: tuple[int, int]
    fps: int


MIN_BPS = 300_000
"""The controller's floor, bit/s (below the lowest level's cap: a congested link still
gets a picture, at the lowest level)."""


@dataclass(frozen=True)
class EncodedFrame:
    """One access unit.

    Attributes:
        data: H.264 Annex B (start codes); an IDR carries its SPS and PPS first.
        key: an IDR frame (a decoder may start here).
        width, height: the coded picture, pixels.
        codec: the WebCodecs codec string (``"avc1.PPCCLL"``: profile, constraints and
            level from the SPS).
    """

    data: bytes
    key: bool
    width: int
    height: int
    codec: str


VBV_S = 0.25
"""The VBV buffer, seconds of the bitrate: the rate holds over a quarter of a second."""
KEYINT_S = 2.0
"""Intra refresh period, seconds: a damaged picture heals within this."""
_START = b"\x00\x00\x01"


def codec_string(annexb: bytes) -> str | None:
    """``"avc1.PPCCLL"`` from the first SPS (NAL type 7) in ``annexb``; None without one."""
    i = annexb.find(_START)
    while i >= 0 and i + 6 < len(annexb):
        if annexb[i + 3] & 0x1F == 7:
            return "avc1." + annexb[i + 4 : i + 7].hex()
        i = annexb.find(_START, i + 3)
    return None


def is_idr(annexb: bytes) -> bool:
    """Whether ``annexb`` holds an IDR slice (NAL type 5)."""
    i = annexb.find(_START)
    while i >= 0 and i + 3 < len(annexb):
        if annexb[i + 3] & 0x1F == 5:
            return True
        i = annexb.find(_START, i + 3)
    return False


class VideoEncoder:
    """An H.264 encoder (libx264 through PyAV; the stream's viewers on one rung share one,
    :mod:`app.server.runtime.video_stream`): ultrafast, zerolatency, no
    B-frames, intra refresh every :data:`KEYINT_S`, ABR at ``bitrate_bps`` held by a VBV
    of :data:`VBV_S`; BT.601 limited range (tagged in the VUI).

    The picture handed to :meth:`encode` is resized (``cv2.INTER_AREA``) to the level's
    size and converted to I420 in preallocated buffers. :meth:`set_bitrate` changes the
    bitrate of the open encoder (x264 reconfigures between frames: no IDR);
    :meth:`set_level` re-opens it when the size or frame rate changes, and the next frame
    is an IDR. Not thread-safe: one thread encodes.

    Args:
        level: the ladder step (size, frame rate, bitrate cap).
        bitrate_bps: the starting bitrate, bit/s (at most the level's cap).
    """

    def __init__(self, level: Level, bitrate_bps: int | None = None) -> None:
        self.level = level
        self.bitrate_bps = min(bitrate_bps or level.max_bps, level.max_bps)
        self.codec = "avc1.42e01f"  # until the first IDR tells
        self.frames = 0
        self._open()

    def _open(self) -> None:
        w, h = self.level.size
        fps = self.level.fps
        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height = w, h
        ctx.pix_fmt = "yuv420p"
        ctx.time_base = Fraction(1, 1000)
        ctx.framerate = Fraction(fps, 1)
        ctx.bit_rate = self.bitrate_bps
        cap = self.level.max_bps
        keyint = max(1, round(KEYINT_S * fps))
        ctx.options = {
            "preset": "ultrafast",
            "tune": "zerolatency",
            "forced-idr": "1",  # a requested key frame is an IDR, not a recovery point
            "maxrate": str(cap),
            "bufsize": str(int(cap * VBV_S)),
            "x264-params": (
                f"keyint={keyint}:bframes=0:intra-refresh=1:scenecut=0"
                ":colormatrix=smpte170m:range=tv:threads=2"
            ),
        }
        ctx.open()
        self._ctx = ctx
        self._i420 = np.empty((h * 3 // 2, w), np.uint8)
        self._resized = np.empty((h, w, 3), np.uint8)
        self._pts = 0
        self._need_key = True

    def set_bitrate(self, bitrate_bps: int) -> None:
        """Aim at ``bitrate_bps`` (clipped to the level's cap) from the next frame on."""
        bps = int(min(max(bitrate_bps, MIN_BPS), self.level.max_bps))
        if bps != self.bitrate_bps:
            self.bitrate_bps = bps
            self._ctx.bit_rate = bps

    def set_level(self, level: Level, bitrate_bps: int) -> None:
        """Encode at ``level`` from the next frame on: a new size or frame rate re-opens the
        encoder (the next frame is an IDR); else only the bitrate changes."""
        if level.size != self.level.size or level.fps != self.level.fps:
            self.level = level
            self.bitrate_bps = min(bitrate_bps, level.max_bps)
            self._open()
        else:
            self.level = level
        self.set_bitrate(bitrate_bps)

    def encode(
        self, bgr: np.ndarray, force_key: bool = False, t_s: float | None = None
    ) -> EncodedFrame:
        """Encode one (H, W, 3) uint8 BGR picture; an IDR when ``force_key`` or after
        :meth:`set_level`. ``t_s``: its time (seconds, increasing) for the rate control;
        default: one frame period after the previous frame."""
        if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
            raise ValueError(
                f"expected an (H, W, 3) uint8 BGR picture, got {bgr.shape} {bgr.dtype}"
            )
        w, h = self.level.size
        src = bgr
        if bgr.shape[:2] != (h, w):
            cv2.resize(bgr, (w, h), dst=self._resized, interpolation=cv2.INTER_AREA)
            src = self._resized
        cv2.cvtColor(src, cv2.COLOR_BGR2YUV_I420, dst=self._i420)
        frame = av.VideoFrame.from_ndarray(self._i420, format="yuv420p")
        pts = self._pts + round(1000 / self.level.fps) if t_s is None else round(t_s * 1000)
        self._pts = max(pts, self._pts + 1) if self.frames else pts
        frame.pts = self._pts
        key = force_key or self._need_key
        if key:
            frame.pict_type = av.video.frame.PictureType.I
        data = b"".join(bytes(p) for p in self._ctx.encode(frame))
        self.frames += 1
        idr = is_idr(data)
        if idr:
            self._need_key = False
            self.codec = codec_string(data) or self.codec
        return EncodedFrame(data, idr, w, h, self.codec)

    def close(self) -> None:
        """Release the encoder (frames still inside it are dropped); an encode running in
        another thread finishes first (it holds the codec context until then)."""
        self._ctx = None  # type: ignore[assignment]
