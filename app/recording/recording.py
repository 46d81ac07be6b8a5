"""One recording written from its first frame to its end: sensor frames, the head's poses
and the fused video's access units (:class:`Recording`), the path every recorder takes:
the console's :class:`~trifuse.app.recording.recorder.Recorder` (in its writing thread) and
``trifuse record`` (in its own; docs/FORMATS.md "Recordings").

A recording goes into one given file (``trifuse record --out``: exactly that file, kept
even without frames) or into a directory (the console): ``<YYYYmmdd-HHMMSS>.mcap`` (local
time of the start; ``-2``, ``-3`` ... appended when the name is taken). Nothing is ever
overwritten: a name is reserved by an empty hidden file ``.<name>.reserved`` while it is
being written, and the writer refuses a name that exists. When the source's time goes back
(a replay that loops or is seeked backwards), a directory's recording continues in a new
file, so that each file's frames stay in time order; a file without frames is removed.

The fused video's access units keep the P-frame chain whole: each file's video begins with
a key frame; a unit a file refuses is counted and the video's source asked for a key frame.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from trifuse.app.recording.video_track import FusedVideoTrack
from trifuse.app.recording.writer import FrameObserver, Note, RecordingWriter
from trifuse.app.sources.frames import Frame
from trifuse.app.storage.numbered import suffixed_names
from trifuse.calib.rig import Rig

VIDEO_AHEAD_S = 0.1
"""A file's first video picture may be at most this much later than its newest sensor
frame (a later one belongs to the time before a replay went back, seconds)."""


class VideoTap(Protocol):
    """A running fused video (what :meth:`VideoFeed.open` returns)."""

    passed_over: int
    """New pictures it did not encode (the encoder was behind)."""
    error: str | None
    """Why it stopped, or None."""

    def request_key(self) -> None:
        """Make the next picture a key frame (the recording began a new file)."""

    def stop(self) -> None:
        """Deliver what waits, then deliver no more (idempotent)."""


class Recording:
    """One recording written from its first frame to its end: sensor frames, the head's
    poses and the fused video's access units, into one file or, for the console, a series.

    The one path both recorders take: the console's
    :class:`~trifuse.app.recording.recorder.Recorder` (in its writing thread) and ``trifuse
    record`` (in its own thread, the fused video with ``--fused-video``).

    Args:
        rig: the rig stored (frames of other sensors are refused: RecordingError).
        path: exactly this file (it must not exist); the recording stays in it when a
            sensor's time goes back, and it is kept even without frames.
        directory: or a new file in this folder, named and reserved as the module doc says;
            when a sensor's time goes back the recording goes on in a new file; a file
            without frames is removed.
        writer_kw: options of :class:`~trifuse.app.recording.writer.RecordingWriter`
            (``jpeg_quality`` ...).

    The first file is opened here (errors reach the caller). A writer observer
    (:attr:`observers`, e.g. :class:`~trifuse.app.recording.video_track.FusedVideoFuser`)
    watches every file. Not thread-safe: one thread writes.

    Attributes:
        tap: asked for a key frame when a new file begins or a unit was refused (the
            console's :class:`VideoTap`); None: nobody is.
        files: the files finished so far.
        video_refused: access units the files refused (to keep the chain whole).
    """

    def __init__(
        self,
        rig: Rig,
        *,
        path: Path | None = None,
        directory: Path | None = None,
        **writer_kw: object,
    ) -> None:
        if (path is None) == (directory is None):
            raise ValueError(
                f"Recording: expected a path or a directory, got {path=}, {directory=}"
            )
        self.rig, self.writer_kw = rig, writer_kw
        self.path = None if path is None else Path(path)
        self.directory = None if directory is None else Path(directory)
        self.observers: list[FrameObserver] = []
        self.tap: VideoTap | None = None
        self.files: list[Path] = []
        self.video_refused = 0
        self._video_metadata: dict[str, str] | None = None
        self._before = _Counts()  # the files already finished
        self._last_stamp: dict[str, int] = {}
        self._reservation: Path | None = None
        self._opened = 0
        self.writer: RecordingWriter | None = None
        self._open_next()

    # -- writing --------------------------------------------------------------------------

    def add_fused_video(self, metadata: dict[str, str] | None = None) -> FusedVideoTrack:
        """Keep the fused video (``/fused/video``, with ``metadata`` about its encoding) in
        this file and every next one; returns this file's track."""
        self._video_metadata = dict(metadata or {})
        return self._writer().add_fused_video(metadata=self._video_metadata)

    def write(self, frame: Frame) -> bool:
        """Write one frame; False if it repeats the sensor's last one (skipped). RecordingError
        for a frame the rig does not describe (nothing is written then)."""
        last = self._last_stamp.get(frame.sensor)
        if (
            self.path is None
            and last is not None
            and frame.stamp_ns < last
            and self.writer is not None
        ):
            if self.writer.frames_written:
                self._finish_file()  # time went back: a new file keeps each in order
                self._open_next()
            else:
                self._last_stamp.clear()
        written = self._writer().write(frame)
        self._last_stamp[frame.sensor] = frame.stamp_ns
        return written

    def write_pose(self, stamp_ns: int, T_world_rig: np.ndarray) -> bool:
        """Write the head's pose ``T_world_rig`` (4, 4) at ``stamp_ns``
        (:meth:`~trifuse.app.recording.writer.RecordingWriter.write_pose`)."""
        return self._writer().write_pose(stamp_ns, T_world_rig)

    def write_note(self, note: Note) -> None:
        """Write a measurement note to the current file
        (:meth:`~trifuse.app.recording.writer.RecordingWriter.write_note`)."""
        self._writer().write_note(note)

    def write_video(self, data: bytes, key: bool, stamp_ns: int) -> bool:
        """Write an access unit (H.264 Annex B; ``key``: an IDR) taken at ``stamp_ns`` to the
        current file's ``/fused/video``; a unit the file refuses (a delta frame before its
        first key frame, a stamp not after the last, a picture from before the replay went
        back) is counted, and :attr:`tap` asked for a key frame. False: refused (or no
        video track)."""
        writer = self._writer()
        track = writer.fused_video
        if track is None:
            return False
        ahead = (
            track.awaiting_key
            and writer.last_ns is not None
            and stamp_ns > writer.last_ns + VIDEO_AHEAD_S * 1e9
        )
        if not ahead and writer.write_video(data, key, stamp_ns):
            return True
        self.video_refused += 1
        if track.awaiting_key and self.tap is not None:
            self.tap.request_key()
        return False

    def finish(self) -> list[Path]:
        """Finish the current file (summary, fsync, name); returns every file written.
        Idempotent."""
        self._finish_file()
        return list(self.files)

    def abort(self) -> None:
        """Stop writing and remove the current file (the finished ones stay)."""
        writer, self.writer = self.writer, None
        try:
            if writer is not None:
                writer.abort()
        finally:
            self._release()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *_exc: object) -> None:
        """Finished, also on Ctrl-C (what was recorded is kept); removed on an error."""
        if exc_type is None or issubclass(exc_type, KeyboardInterrupt):
            self.finish()
        else:
            self.abort()

    # -- what was written -----------------------------------------------------------------

    @property
    def temp_path(self) -> Path | None:
        """Where the current file is written until it is finished (None: none open)."""
        return None if self.writer is None else self.writer.temp_path

    @property
    def current(self) -> Path | None:
        """The name the current file gets, else the last file finished's, or None."""
        if self.writer is not None:
            return self.writer.path
        return self.files[-1] if self.files else None

    @property
    def frames_written(self) -> int:
        """Frames written into all the files."""
        return self._before.frames + (self.writer.frames_written if self.writer else 0)

    @property
    def video_frames_written(self) -> int:
        """Access units written to ``/fused/video`` in all the files."""
        return self._before.video + (self.writer.video_frames_written if self.writer else 0)

    @property
    def duration_s(self) -> float:
        """Recording time: from the first to the last frame stamp, summed over the files."""
        return self._before.duration_s + (_duration_s(self.writer) if self.writer else 0.0)

    def size_bytes(self) -> int:
        """Bytes on disk: the current file so far and the finished ones."""
        size = 0
        if self.writer is not None:
            with contextlib.suppress(OSError):
                size = self.writer.temp_path.stat().st_size
        for f in self.files:
            with contextlib.suppress(OSError):
                size += f.stat().st_size
        return size

    # -- the files ------------------------------------------------------------------------

    def _writer(self) -> RecordingWriter:
        if self.writer is None:
            self._open_next()
        assert self.writer is not None
        return self.writer

    def _open_next(self) -> None:
        """A new file: the path given, or a free name reserved in the directory."""
        if self.path is not None:
            if self._opened:
                raise RuntimeError(f"{self.path}: the recording is finished")
            self._open(self.path)
            return
        assert self.directory is not None
        self.directory.mkdir(parents=True, exist_ok=True)
        stem = time.strftime("%Y%m%d-%H%M%S")
        for name in suffixed_names(stem, ".mcap", 9_999):
            path = self.directory / name
            reservation = self.directory / f".{name}.reserved"
            if path.exists():
                continue
            try:
                fd = os.open(reservation, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                continue  # another recording is writing that name now
            os.close(fd)
            try:
                self._open(path)
            except FileExistsError:
                reservation.unlink(missing_ok=True)
                continue
            except BaseException:
                reservation.unlink(missing_ok=True)
                raise
            self._reservation = reservation
            return
        raise FileExistsError(f"{self.directory}: no free recording name for {stem}")

    def _open(self, path: Path) -> None:
        self.writer = RecordingWriter(path, self.rig, **self.writer_kw)  # type: ignore[arg-type]
        self.writer.observers = self.observers
        self._opened += 1
        self._last_stamp.clear()
        if self._video_metadata is not None:
            self.writer.add_fused_video(metadata=self._video_metadata)
            if self.tap is not None:
                self.tap.request_key()  # the new file's video starts with a key frame

    def _finish_file(self) -> None:
        """Close the current file (summary, fsync, name) and release its reservation; a
        file of the directory without frames is removed instead."""
        writer = self.writer
        if writer is None:
            return
        try:
            if writer.frames_written or self.path is not None:
                path = writer.close()  # its observers may still write (the video's last sets)
                self.files.append(path)
                self._before.add(writer)
            else:
                writer.abort()  # nothing recorded: no empty file
        finally:
            self.writer = None
            self._release()

    def _release(self) -> None:
        if self._reservation is not None:
            self._reservation.unlink(missing_ok=True)
            self._reservation = None


@dataclass
class _Counts:
    """What the finished files of a :class:`Recording` hold."""

    frames: int = 0
    video: int = 0
    duration_s: float = 0.0

    def add(self, writer: RecordingWriter) -> None:
        self.frames += writer.frames_written
        self.video += writer.video_frames_written
        self.duration_s += _duration_s(writer)


def _duration_s(writer: RecordingWriter) -> float:
    """Seconds between the first and the last frame stamp a writer wrote (0 if none)."""
    if writer.first_ns is None or writer.last_ns is None:
        return 0.0
    return (writer.last_ns - writer.first_ns) / 1e9
