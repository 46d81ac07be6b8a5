"""The fused stereo picture kept in a recording as H.264 video (``/fused/video``).

Foxglove plays ``foxglove.CompressedVideo`` in its Image and 3D panels when ``format`` is
``h264`` and each message is exactly one access unit in Annex B (start codes), the stream
has no B-frames, and every key frame (IDR) carries its SPS and PPS. This module makes and
writes such a track (docs/FORMATS.md, "Recordings"):

- :class:`FusedVideoEncoder`: the pictures, (H, W, 3) uint8 BGR, into access units through
  the console's :class:`~app.recording.h264.VideoEncoder` (libx264 ultrafast /
  zerolatency, no B-frames, SPS/PPS in-band before each IDR) at a recording's setting
  (:class:`VideoSettings`: full size, 10 Mbit/s) with an IDR every ``keyint_s`` seconds of
  picture time, so that a player can seek.
- :class:`FusedVideoTrack`: the channel of one recording file. It keeps the P-frame chain
  valid whatever it is handed: the first message of the file is a key frame, stamps
  increase, and after an access unit it could not write it waits for the next key frame.
- :class:`FusedVideoFuser`: ``trifuse record --fused-video``. It watches the frames a
  :class:`~app.recording.writer.RecordingWriter` writes, groups them as the console does
  (:meth:`FrameSetAssembler.stereo <app.sources.base.FrameSetAssembler.stereo>`), makes
  the console's picture (its stereo-picture step, :class:`~fusion.stereo_step.StereoStep`,
  under its :data:`~fusion.stereo_step.CONSOLE` rules for missing sensors) and adds it to
  the video through the two above.

A failure of the video (the encoder, a picture) never costs the sensor recording: the
fuser logs it, keeps it in ``error`` and carries on without video.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np
from foxglove.channels import CompressedVideoChannel
from foxglove.messages import CompressedVideo, Timestamp

from trifuse.app.errors import describe_error
from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.h264 import Level, VideoEncoder
from trifuse.app.recording.layout import (
    FUSED_VIDEO_FORMAT,
    FUSED_VIDEO_KIND,
    FUSED_VIDEO_TOPIC,
    RIG_FRAME,
)
from trifuse.app.sources.base import FrameSetAssembler
from trifuse.calib.numbers import is_integral, is_real
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.stereo import EYE_ORDER
from trifuse.fusion.stereo_step import CONSOLE, Skip, StereoStep

if TYPE_CHECKING:
    from trifuse.app.sources.frames import Frame, FrameSet

log = logging.getLogger(__name__)

RECORD_BITRATE_BPS = 10_000_000
"""Default bitrate of the recorded video, bit/s (the radio stream's top level is 8)."""
RECORD_KEYINT_S = 1.0
"""Default interval between key frames (IDR, with SPS and PPS), seconds of picture time."""
_MAX_STEP_S = 1.0
"""The rate control's clock follows the pictures' stamps, but advances at most this much per
picture, seconds (after a gap or a jump in the source's time it has no backlog of bits to
spend)."""


@dataclass(frozen=True)
class VideoSettings:
    """How the fused video is encoded; validated on construction (ValueError).

    Attributes:
        bitrate_bps: the average bitrate, bit/s (100 kbit/s .. 100 Mbit/s). 10 Mbit/s keeps
            the 2560 x 960 picture at about 41 dB PSNR (ultrafast preset; 8: 40.5 dB, 12:
            41.8 dB on the simulated inspection scene).
        keyint_s: seconds of picture time between key frames (0.1 .. 10); a player seeks
            to the key frame before the position and decodes from there.
        fps: the nominal frame rate, frames/s, for the rate control (the stamps give the
            real spacing).
    """

    bitrate_bps: int = RECORD_BITRATE_BPS
    keyint_s: float = RECORD_KEYINT_S
    fps: int = 30

    def __post_init__(self) -> None:
        bps = self.bitrate_bps
        if not is_integral(bps):
            raise ValueError(f"bitrate_bps: expected an integer bit/s, got {bps!r}")
        if not 100_000 <= bps <= 100_000_000:
            raise ValueError(f"bitrate_bps: expected 100 kbit/s .. 100 Mbit/s, got {bps} bit/s")
        k = self.keyint_s
        if not is_real(k) or not 0.1 <= k <= 10:
            raise ValueError(f"keyint_s: expected 0.1 .. 10 seconds, got {k!r}")
        fps = self.fps
        if not is_integral(fps) or not 1 <= fps <= 120:
            raise ValueError(f"fps: expected an integer 1 .. 120 frames/s, got {fps!r}")


@dataclass(frozen=True)
class VideoUnit:
    """One encoded picture on its way to a recording.

    Attributes:
        stamp_ns: the picture's time (its frame set's stamp), nanoseconds.
        data: one H.264 access unit, Annex B.
        key: an IDR (with SPS and PPS before it).
    """

    stamp_ns: int
    data: bytes
    key: bool


def nal_types(annexb: bytes) -> list[int]:
    """The NAL unit types in an Annex B buffer, in order (7 SPS, 8 PPS, 5 IDR slice, 1
    non-IDR slice, 6 SEI ...)."""
    out = []
    i = annexb.find(b"\x00\x00\x01")
    while i >= 0 and i + 3 < len(annexb):
        out.append(annexb[i + 3] & 0x1F)
        i = annexb.find(b"\x00\x00\x01", i + 3)
    return out


class FusedVideoEncoder:
    """The fused pictures of one recording into H.264 access units (see the module doc).

    Opens a :class:`VideoEncoder` at the first picture's size (rounded down to even
    pixels; later pictures of another size are scaled to it), at ``settings.bitrate_bps``.
    A picture is a key frame when it is the first, when :meth:`request_key` was called,
    when ``keyint_s`` of picture time passed since the last key frame, or when its stamp
    is not after the previous one's (the source's time went back: a new stretch starts).
    Every picture handed to :meth:`encode` becomes one access unit, so the chain of the
    units returned is whole. One thread encodes; :meth:`request_key` may come from any.
    """

    def __init__(self, settings: VideoSettings | None = None) -> None:
        self.settings = settings or VideoSettings()
        self._keyint_ns = round(self.settings.keyint_s * 1e9)
        self._encoder: VideoEncoder | None = None
        self._want_key = True
        self._last_key_ns: int | None = None
        self._last_ns: int | None = None
        self._t_s = 0.0
        self.frames = 0
        self.keyframes = 0
        self.bytes = 0

    @property
    def size(self) -> tuple[int, int] | None:
        """The coded picture (width, height), pixels; None before the first picture."""
        return None if self._encoder is None else self._encoder.level.size

    def request_key(self) -> None:
        """Make the next picture a key frame (a recording starts a new file)."""
        self._want_key = True

    def encode(self, bgr: np.ndarray, stamp_ns: int) -> VideoUnit:
        """One (H, W, 3) uint8 BGR picture taken at ``stamp_ns`` -> one access unit.

        Raises ValueError for a picture that is not (H, W, 3) uint8 of at least 16 x 16
        pixels, and whatever the encoder raises (the caller stops the video then).
        """
        if not isinstance(bgr, np.ndarray) or bgr.ndim != 3 or bgr.shape[2] != 3:
            got = bgr.shape if isinstance(bgr, np.ndarray) else type(bgr).__name__
            raise ValueError(f"fused picture: expected an (H, W, 3) uint8 BGR array, got {got}")
        if bgr.dtype != np.uint8 or bgr.shape[0] < 16 or bgr.shape[1] < 16:
            raise ValueError(
                f"fused picture: expected uint8, at least 16 x 16 pixels, got {bgr.dtype} "
                f"{bgr.shape[1]} x {bgr.shape[0]}"
            )
        stamp = int(stamp_ns)
        if self._encoder is None:
            h, w = bgr.shape[:2]
            s = self.settings
            level = Level("record", s.bitrate_bps, (w - w % 2, h - h % 2), s.fps)
            self._encoder = VideoEncoder(level)
        last = self._last_ns
        if last is None:
            step = 0.0
        elif stamp > last:
            step = min((stamp - last) / 1e9, _MAX_STEP_S)
        else:
            step = 1.0 / self.settings.fps
        self._t_s += step
        key = (
            self._want_key
            or self._last_key_ns is None
            or last is None
            or stamp <= last
            or stamp - self._last_key_ns >= self._keyint_ns
        )
        self._want_key = False
        encoded = self._encoder.encode(bgr, force_key=key, t_s=self._t_s)
        if not encoded.data:
            raise RuntimeError("the H.264 encoder returned no access unit for a picture")
        self._last_ns = stamp
        if encoded.key:
            self._last_key_ns = stamp
            self.keyframes += 1
        self.frames += 1
        self.bytes += len(encoded.data)
        return VideoUnit(stamp, encoded.data, encoded.key)

    def close(self) -> None:
        """Release the encoder."""
        if self._encoder is not None:
            self._encoder.close()
            self._encoder = None


class FusedVideoTrack:
    """The ``/fused/video`` channel of one recording file (made by
    :meth:`RecordingWriter.add_fused_video <app.recording.writer.RecordingWriter.add_fused_video>`).

    Args:
        context: the writer's ``foxglove.Context``.
        frame_id: the messages' frame id.
        metadata: more channel metadata (the encoder's settings).

    Attributes:
        written: access units written.
        skipped: access units refused (see :meth:`write`).
        awaiting_key: the next unit written must be a key frame (at the start, and after a
            unit was refused: the chain behind it would be broken).
        last_ns: the stamp of the last unit written.
    """

    def __init__(self, context: Any, frame_id: str, metadata: dict[str, str] | None = None) -> None:
        self.frame_id = frame_id
        meta = {"trifuse.kind": FUSED_VIDEO_KIND, "trifuse.frame": frame_id}
        meta.update(metadata or {})
        self.channel = CompressedVideoChannel(FUSED_VIDEO_TOPIC, context=context, metadata=meta)
        self.written = 0
        self.skipped = 0
        self.awaiting_key = True
        self.last_ns: int | None = None

    def write(self, data: bytes, key: bool, stamp_ns: int) -> bool:
        """Write one access unit (Annex B) taken at ``stamp_ns``; False if it is refused:
        a delta frame while :attr:`awaiting_key`, or a stamp not after the last one written
        (then the track awaits a key frame). RecordingError for data that is not Annex B.
        """
        if not isinstance(data, bytes | bytearray | memoryview) or len(data) < 4:
            raise RecordingError(
                f"{FUSED_VIDEO_TOPIC}: expected an H.264 access unit (bytes), got "
                f"{type(data).__name__} of {len(data) if hasattr(data, '__len__') else '?'} bytes"
            )
        data = bytes(data)
        if not (data.startswith(b"\x00\x00\x01") or data.startswith(b"\x00\x00\x00\x01")):
            raise RecordingError(
                f"{FUSED_VIDEO_TOPIC}: expected Annex B (a start code first), got {data[:4].hex()}"
            )
        if self.last_ns is not None and stamp_ns <= self.last_ns:
            self.skipped += 1
            self.awaiting_key = True
            return False
        if self.awaiting_key and not key:
            self.skipped += 1
            return False
        ts = Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
        msg = CompressedVideo(
            timestamp=ts, frame_id=self.frame_id, data=data, format=FUSED_VIDEO_FORMAT
        )
        self.channel.log(msg, log_time=stamp_ns)
        self.awaiting_key = False
        self.last_ns = stamp_ns
        self.written += 1
        return True

    def close(self) -> None:
        self.channel.close()


def video_frame_id(rig: Rig) -> str:
    """The frame id of the fused picture: the left eye's colour camera (the left half is
    drawn in its image; the right half in the right eye's), else the rig frame."""
    eye = rig.eyes.get(EYE_ORDER[0])
    return eye.color if eye is not None else RIG_FRAME


# -- fusing frame sets (trifuse record --fused-video) -------------------------------------


class VideoWriter(Protocol):
    """What :class:`FusedVideoFuser` needs of a recording writer
    (:class:`app.recording.writer.RecordingWriter`)."""

    rig: Rig

    def add_fused_video(self, metadata: dict[str, str] | None = None) -> FusedVideoTrack: ...

    def write_video(self, data: bytes, key: bool, stamp_ns: int) -> bool: ...


class FusedVideoFuser:
    """Adds the fused video to a recording as its frames are written (``trifuse record
    --fused-video``): an observer of a :class:`~app.recording.writer.RecordingWriter`
    (append it to ``writer.observers``). Frames -> sets (the console's grouping) ->
    pictures (:class:`~fusion.stereo_step.StereoStep`, the console's policy) -> access
    units (:class:`FusedVideoEncoder`) -> ``/fused/video`` (:class:`FusedVideoTrack`), all
    in the writer's thread.

    Never raises from the writer's calls: a failure is logged, kept in :attr:`error`, and
    the recording goes on without video.

    Args:
        writer: the recording; its rig makes the pictures, its track gets them.
        settings: the encoding.
        display: the display mode, palette ... (default: the console's).

    Attributes:
        pictures: pictures encoded and written; ``sets``: frame sets seen; ``skipped``:
            sets without a picture (a colour image missing:
            :class:`~fusion.stereo_step.Skip`);
            ``error``: why the video stopped, or None.
    """

    def __init__(
        self,
        writer: VideoWriter,
        settings: VideoSettings | None = None,
        display: DisplaySettings | None = None,
    ) -> None:
        self.writer = writer
        self.settings = settings or VideoSettings()
        self.pictures = self.sets = self.skipped = 0
        self.error: str | None = None
        self._encoder: FusedVideoEncoder | None = None
        self._bgr: np.ndarray | None = None
        try:
            self._step = StereoStep(writer.rig, display, CONSOLE)
            self._assembler = FrameSetAssembler.stereo(self._step.sensors)
            self._track = writer.add_fused_video(metadata=video_metadata(self.settings))
            self._encoder = FusedVideoEncoder(self.settings)
        except Exception as exc:
            self._fail(exc)

    @property
    def keyframes(self) -> int:
        """Key frames encoded."""
        return 0 if self._encoder is None else self._encoder.keyframes

    def _fail(self, exc: BaseException) -> None:
        self.error = describe_error(exc)
        log.error("fused video stopped (the sensor recording goes on): %s", self.error)
        if self._encoder is not None:
            self._encoder.close()

    def frame_written(self, frame: Frame) -> None:
        """The writer wrote ``frame``: fuse and write the sets it completes."""
        if self.error is not None:
            return
        try:
            for fs in self._assembler.push(frame):
                self._add(fs)
        except Exception as exc:
            self._fail(exc)

    def closing(self) -> None:
        """The writer is about to finish the file: the sets still open, then the encoder
        is released."""
        if self.error is not None:
            return
        try:
            for fs in self._assembler.flush():
                self._add(fs)
        except Exception as exc:
            self._fail(exc)
        if self._encoder is not None:
            self._encoder.close()

    def _add(self, fs: FrameSet) -> None:
        encoder = self._encoder
        if encoder is None:
            return
        self.sets += 1
        rgb = self._step.picture(fs)
        if isinstance(rgb, Skip):
            self.skipped += 1
            return
        if self._bgr is None or self._bgr.shape != rgb.shape:
            self._bgr = np.empty(rgb.shape, np.uint8)
        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR, dst=self._bgr)
        unit = encoder.encode(self._bgr, fs.stamp_ns)
        if self.writer.write_video(unit.data, unit.key, unit.stamp_ns):
            self.pictures += 1
        elif self._track.awaiting_key:
            encoder.request_key()


def video_metadata(settings: VideoSettings) -> dict[str, str]:
    """The fused-video channel's metadata about its encoding."""
    return {
        "trifuse.encoder": "libx264 ultrafast zerolatency, no B-frames",
        "trifuse.bitrate_bps": str(settings.bitrate_bps),
        "trifuse.keyint_s": f"{settings.keyint_s:g}",
    }
