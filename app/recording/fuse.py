"""Offline fusion of recordings (``trifuse fuse``): JPEG frames and a video.

A recording is fused in pieces (:mod:`app.recording.pieces`; one piece unless it is longer
than the job's ``chunk_s``), each replayed as fast as possible and grouped into frame sets
around the left eye's colour frames (:func:`app.sources.base.frame_sets`), and each set
goes through the console's stereo-picture step (:class:`fusion.stereo_step.StereoStep`):
each new TOF frame updates both eyes' mappings (with the rig's range correction); every
``every``-th set is composed into the side-by-side picture (:func:`fuse_piece`, pure of
files: it runs where the job sends it) under the step's
:data:`~fusion.stereo_step.OFFLINE` policy: only sets with both eyes' colour and thermal
frames after the first depth make a picture (the others are counted by reason); the messages the
replay skips (undecodable, or an image of another size than the rig's:
:mod:`app.recording.player`) are counted per piece and sensor. :class:`FusedWriter` writes
the pieces' pictures in order as ``DIR/NNNNNN.jpg``, ``DIR/frames.csv`` (each picture's
time stamps) and ``DIR/fused.mp4`` (OpenCV ``mp4v`` per piece, joined).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import av
import cv2
import numpy as np

from trifuse.app.recording.errors import RecordingDamaged
from trifuse.app.recording.pieces import FusePiece
from trifuse.app.recording.player import MessageReplay, Skips, add_skips, skips_between
from trifuse.app.sources.base import frame_sets
from trifuse.app.storage.atomic import atomic_write_bytes, atomic_write_text, fsync_dir
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.frame_meta import FrameMeta
from trifuse.fusion.stereo import EYE_ORDER
from trifuse.fusion.stereo_step import OFFLINE, MissingSensors, Skip, StereoStep

VIDEO_NAME = "fused.mp4"
JPEG_QUALITY = 90


@dataclass
class FusedFrame:
    """One fused picture of a piece.

    Attributes:
        jpeg: the side-by-side picture, JPEG (quality :data:`JPEG_QUALITY`).
        meta: its metadata: the frame set's (left colour frame's) stamp, the stamp of the
            TOF frame the mapping came from, the mode and colour scale ...
    """

    jpeg: bytes
    meta: FrameMeta


@dataclass
class PieceEnd:
    """The last item of a piece (:func:`fuse_piece`): its video and its counts.

    Attributes:
        video: the piece's pictures as an mp4v video (bytes), None if there is none.
        video_problem: why there is no video.
        sets: frame sets of the piece's range seen.
        tof_updates: TOF frames used to update the mapping (warm-up included).
        skipped: reason -> count of sets chosen for composing but not composed.
        messages_skipped: sensor -> reason -> messages of the piece's range the replay
            skipped.
        damage: the recording's damage, if the replay stopped at one.
    """

    video: bytes | None = None
    video_problem: str | None = None
    sets: int = 0
    tof_updates: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    messages_skipped: Skips = field(default_factory=dict)
    damage: RecordingDamaged | None = None


@dataclass
class FuseResult:
    """What :class:`FusedWriter` wrote for one recording.

    Attributes:
        frames: pictures written (JPEGs, and video frames if ``video``).
        sets: colour reference frame sets seen.
        tof_updates: TOF frames used to update the mapping.
        skipped: reason -> count of sets chosen for composing but not composed.
        messages_skipped: sensor -> reason -> messages the replay skipped.
        video: the video's path, or None.
        video_problem: why there is no video.
        fps: the video's frame rate.
        damage: the recording's damage met by each piece that stopped at one.
    """

    frames: int = 0
    sets: int = 0
    tof_updates: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    messages_skipped: Skips = field(default_factory=dict)
    video: Path | None = None
    video_problem: str | None = None
    fps: float = 30.0
    damage: list[RecordingDamaged] = field(default_factory=list)


def video_fps(source: MessageReplay, rig: Rig, every: int) -> float:
    """The fused video's frame rate: the reference colour frames' rate (from the file's
    statistics; 30 Hz if unknown) over ``every``."""
    ref = rig.eyes[EYE_ORDER[0]].color
    count = getattr(source, "message_count", lambda *_: None)(ref, "color")
    rate = (count - 1) / source.duration_s if count and count > 1 and source.duration_s else None
    return (rate or 30.0) / every


def fuse_piece(
    source: MessageReplay,
    rig: Rig,
    piece: FusePiece,
    settings: DisplaySettings,
    every: int = 1,
    progress: Callable[[int], None] | None = None,
    policy: MissingSensors = OFFLINE,
) -> Iterator[FusedFrame | PieceEnd]:
    """Fuse one piece of ``source`` (:mod:`app.recording.pieces`): a
    :class:`FusedFrame` per picture, in order, then a :class:`PieceEnd`.

    The replay starts at ``piece.seek_ns`` and numbers the frame sets from
    ``piece.first_set``; sets before ``piece.start_set`` only update the mapping and the
    display's smoothing; every ``every``-th set (by its number in the recording) from there
    to ``piece.end_set`` is composed. ``progress(pictures considered)`` is called after
    each set considered for composing. Frames are checked against ``rig``'s sizes
    (:meth:`~app.recording.player.MessageReplay.expect`); the messages skipped from the
    piece's first set written on are counted (``PieceEnd.messages_skipped``; those of the
    warm-up belong to the piece before). Damage in the recording ends the piece where it is
    (``PieceEnd.damage``, without its traceback; nothing is raised for it). ``policy``: what
    sets missing a sensor make (:class:`~fusion.stereo_step.MissingSensors`).
    """
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    step = StereoStep(rig, settings, policy)
    eyes = step.eyes
    ref = eyes[EYE_ORDER[0]].color
    others = [s for e in eyes.values() for s in (e.color, e.thermal) if s != ref]
    sensors = [ref, *others, step.tof]
    source.realtime = False
    source.expect(rig)
    counted_from: Skips | None = {} if piece.start_set <= piece.first_set else None
    end = PieceEnd()
    w, h = step.fusion.size
    fd, video_name = tempfile.mkstemp(prefix="trifuse-piece-", suffix=".mp4")
    os.close(fd)
    video_tmp = Path(video_name)
    fps = video_fps(source, rig, every)
    video = cv2.VideoWriter(
        str(video_tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w * len(eyes), h)
    )
    if not video.isOpened():
        video = None
        end.video_problem = "OpenCV has no mp4v encoder here"
    bgr = np.empty((h, w * len(eyes), 3), np.uint8)
    considered = pictures = 0
    if piece.seek_ns is not None:
        source.seek(piece.seek_ns)
    try:
        for i, fs in enumerate(frame_sets(source, sensors, reference=ref), piece.first_set):
            if piece.end_set is not None and i >= piece.end_set:
                break
            if counted_from is None and i >= piece.start_set:
                counted_from = source.skipped
            step.note(fs)
            end.tof_updates += step.update_depth()
            warming = i < piece.start_set
            end.sets += not warming
            if i % every:
                continue
            inputs = step.inputs(fs)
            if isinstance(inputs, Skip):
                if not warming:
                    end.skipped[inputs.reason] = end.skipped.get(inputs.reason, 0) + 1
            else:
                picture = step.render(inputs)
                if warming:
                    continue
                cv2.cvtColor(picture, cv2.COLOR_RGB2BGR, dst=bgr)
                ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
                if not ok:
                    raise RuntimeError("OpenCV could not encode a fused frame as JPEG")
                if video is not None:
                    video.write(bgr)
                pictures += 1
                yield FusedFrame(jpg.tobytes(), step.meta(inputs))
            if not warming:
                considered += 1
                if progress is not None:
                    progress(considered)
    except RecordingDamaged as exc:
        end.damage = exc.with_traceback(None)  # its frames would keep the piece's buffers
    finally:
        if video is not None:
            video.release()
        try:
            if video is not None and pictures:
                end.video = video_tmp.read_bytes()
        finally:
            video_tmp.unlink(missing_ok=True)
    if video is not None and not pictures:
        end.video_problem = "no frames were fused"
    end.messages_skipped = skips_between(counted_from, source.skipped)  # not the warm-up's
    yield end


class FusedWriter:
    """Writes the pictures of one recording's pieces, given in order, into ``out_dir``
    (which must exist, empty): ``NNNNNN.jpg`` numbered across the pieces, ``frames.csv``
    and ``fused.mp4`` (the pieces' videos joined without re-encoding, by PyAV). Every file
    is written once, atomically; the video is joined and renamed into place at
    :meth:`close`.
    """

    def __init__(self, out_dir: str | Path, fps: float) -> None:
        self.out_dir = Path(out_dir)
        self.result = FuseResult(fps=fps)
        self._rows = ["index,stamp_ns,tof_stamp_ns"]
        self._segments: list[Path] = []
        self._video_problem: str | None = None  # the first piece's without a video

    def add(self, item: FusedFrame | PieceEnd) -> None:
        """Write a picture, or take a piece's end (its video waits in a hidden file)."""
        r = self.result
        if isinstance(item, FusedFrame):
            atomic_write_bytes(self.out_dir / f"{r.frames:06d}.jpg", item.jpeg, False)
            meta = item.meta
            self._rows.append(f"{r.frames},{meta.stamp_ns},{meta.tof_stamp_ns}")
            r.frames += 1
            return
        r.sets += item.sets
        r.tof_updates += item.tof_updates
        for reason, n in item.skipped.items():
            r.skipped[reason] = r.skipped.get(reason, 0) + n
        add_skips(r.messages_skipped, item.messages_skipped)
        if item.damage is not None:
            r.damage.append(item.damage)
        if item.video is not None:
            segment = self.out_dir / f".{VIDEO_NAME}.part{len(self._segments):04d}.mp4"
            atomic_write_bytes(segment, item.video, False)
            self._segments.append(segment)
        elif item.video_problem is not None:
            self._video_problem = self._video_problem or item.video_problem

    def abort(self) -> None:
        """The job stopped: remove the pieces' videos (the pictures written stay)."""
        for segment in self._segments:
            segment.unlink(missing_ok=True)

    def close(self) -> FuseResult:
        """Write ``frames.csv`` and the video; returns what was written."""
        r = self.result
        atomic_write_text(self.out_dir / "frames.csv", "\n".join(self._rows) + "\n", False)
        try:
            if self._segments:
                joined = self.out_dir / f".{VIDEO_NAME}.partial.mp4"
                join_videos(self._segments, joined)
                with joined.open("rb") as f:  # durable before it gets its name
                    os.fsync(f.fileno())
                os.replace(joined, self.out_dir / VIDEO_NAME)
                fsync_dir(self.out_dir)
                r.video = self.out_dir / VIDEO_NAME
            else:
                r.video_problem = self._video_problem or "no frames were fused"
        finally:
            self.abort()
        return r


def join_videos(segments: Sequence[Path], out: Path) -> None:
    """Join mp4 videos of one codec and size into ``out`` without re-encoding: the
    packets of each follow those of the one before, their time stamps shifted."""
    with av.open(str(out), "w", format="mp4") as joined:
        stream = None
        offset = 0
        for path in segments:
            with av.open(str(path)) as part:
                src = part.streams.video[0]
                if stream is None:
                    stream = joined.add_stream_from_template(src)
                elif src.time_base != stream.time_base:
                    raise ValueError(f"{path}: another time base than the first piece's video")
                end = offset
                for packet in part.demux(src):
                    if packet.dts is None:  # the demuxer's empty end-of-stream packet
                        continue
                    packet.pts += offset
                    packet.dts += offset
                    end = max(end, packet.pts + packet.duration)
                    packet.stream = stream
                    joined.mux(packet)
                offset = end
