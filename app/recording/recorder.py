"""The console's recorder: the frames a source delivers, and optionally the fused video,
written to new MCAP recordings (docs/FORMATS.md "Recordings") in a background thread.

:class:`Recorder` hands the frames offered to it (:meth:`Recorder.offer`, called by the
thread that reads the source) to a :class:`~trifuse.app.recording.recording.Recording` in
``<workdir>/recordings`` (its names, reservations and new files when time goes back: see
that module) in a thread of its own fed by a bounded queue. The source's reader never waits
for the disk: when the queue is full the frame is dropped and counted. Stopping writes what
is queued, finishes the file and gives it its name. With the source's head pose
(:attr:`Recorder.head_pose`) each TOF frame's pose is written beside it.

A recording may also keep the fused stereo picture as H.264 (``/fused/video``): the
:class:`VideoFeed` given to :meth:`Recorder.start` (the console's: the pictures its stream
publishes, :class:`trifuse.app.server.runtime.fused_video_tap.FusedVideoSource`) delivers
encoded access units (:class:`~trifuse.app.recording.video_track.VideoUnit`) through the
same queue; every unit it delivers reaches the writer (the P-frame chain stays whole; each
file of the recording begins with a key frame). A failure of the video is shown in the
recording state; the sensor recording goes on without video.

A recording the console was writing when it was killed is kept: when the recorder is made
again, :func:`trifuse.app.recording.recovery.recover_interrupted` names it
``<YYYYmmdd-HHMMSS>.partial.mcap`` (readable up to its last complete chunk), its stale
reservation is removed, and the recording state says so (``interrupted``, ``error``; the
Source panel shows it) until the next recording starts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from trifuse.app.errors import ControlError, describe_error
from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.recording import Recording, VideoTap
from trifuse.app.recording.recovery import recover_interrupted
from trifuse.app.recording.video_track import VideoSettings, VideoUnit, video_metadata
from trifuse.app.recording.writer import Note
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig

log = logging.getLogger(__name__)

RECORDINGS = "recordings"
"""The folder of the console's work directory that its recordings go to."""


class VideoFeed(Protocol):
    """Where a recording's fused video comes from."""

    settings: VideoSettings
    """The encoding (bitrate, key-frame interval), written in the channel's metadata."""

    def open(self, deliver: Callable[[VideoUnit], bool]) -> VideoTap:
        """Start delivering access units to ``deliver`` (in a thread of the feed's; it may
        block; False: deliver no more)."""
        ...


@dataclass
class RecordingState:
    """What the recorder is doing (sizes in bytes; ``duration_s`` is recording time in
    seconds, from the first to the last frame stamp, summed over the recording's files)."""

    available: bool
    active: bool = False
    path: str | None = None
    size_bytes: int = 0
    duration_s: float = 0.0
    frames_written: int = 0
    frames_dropped: int = 0
    frames_rejected: int = 0
    queued: int = 0
    stopping: bool = False
    files: list[str] = field(default_factory=list)
    error: str | None = None
    interrupted: list[str] = field(default_factory=list)
    """Recordings a killed console left unfinished, kept under a new name at start-up."""
    fused_video: bool = False
    """The recording keeps the fused stereo picture as H.264 (``/fused/video``)."""
    video_frames_written: int = 0
    """Pictures written to ``/fused/video`` (all files of the recording)."""
    video_frames_skipped: int = 0
    """New pictures the console published that the video did not keep: dropped while the
    encoder was behind (:attr:`VideoTap.passed_over`), or refused to keep the chain whole (a new
    file waits for a key frame)."""
    video_error: str | None = None
    """Why the fused video stopped (the sensor recording went on), or None."""


_STOP = object()


class _Session(Recording):
    """One console recording from start to stop: a :class:`Recording` written by a thread
    of its own from a bounded queue (frames offered, the video tap's access units)."""

    def __init__(
        self,
        directory: Path,
        rig: Rig,
        max_queue: int,
        writer_kw: dict,
        video: VideoFeed | None = None,
        head_pose: Callable[[int], np.ndarray | None] | None = None,
    ) -> None:
        # errors (disk, permissions) reach the caller of start()
        super().__init__(rig, directory=directory, **writer_kw)
        self.head_pose = head_pose  # the source's pose of the head, kept at each TOF frame
        self.video_source = video
        self.video_error: str | None = None  # the tap could not start
        self.queue: queue.Queue = queue.Queue(maxsize=max_queue)
        self.accepting = True
        self.dropped = 0
        self.rejected = 0
        self.error: str | None = None
        self.last_reject: str | None = None
        if video is not None:
            self.add_fused_video(video_metadata(video.settings))
        self.thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self.thread.start()
        if video is not None:
            try:
                self.tap = video.open(self._put_video)
            except Exception as exc:  # no video; the sensor recording goes on
                self.video_error = describe_error(exc)
                log.error("the recording's fused video could not start: %s", self.video_error)

    def _put_video(self, unit: VideoUnit) -> bool:
        """Queue an access unit (the tap's thread): waits for room, never drops one (the
        chain behind it would break); False once the recording stops taking them."""
        while self.accepting and self.thread.is_alive():
            try:
                self.queue.put(unit, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def stop_video(self) -> None:
        """Stop taking pictures (before the queue gets its end mark)."""
        if self.tap is not None:
            self.tap.stop()

    def _write(self, frame: Frame) -> None:
        try:
            self.write(frame)
        except RecordingError as exc:  # a frame the rig does not describe: skip it
            self.rejected += 1
            self.last_reject = str(exc)
            return
        if self.head_pose is not None and frame.distance_m is not None:  # a TOF frame
            pose = self.head_pose(frame.stamp_ns)
            if pose is not None:
                self.write_pose(frame.stamp_ns, pose)

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            if item is _STOP:
                break
            if self.error is not None:
                continue  # a failed disk: drain without writing
            try:
                if isinstance(item, VideoUnit):
                    self.write_video(item.data, item.key, item.stamp_ns)
                elif isinstance(item, Note):
                    self.write_note(item)
                else:
                    self._write(item)
            except Exception as exc:  # disk full, I/O error: keep what was written
                self.error = describe_error(exc)
                log.error("recording stopped writing: %s", self.error)
                self.accepting = False
                with contextlib.suppress(Exception):
                    self.finish()
        try:
            self.finish()
        except Exception as exc:
            self.error = self.error or describe_error(exc)
            log.error("recording could not be finished: %s", self.error)

    # -- reporting ----------------------------------------------------------------------

    def state(self) -> RecordingState:
        current = self.current
        state = RecordingState(
            True,
            True,
            None if current is None else str(current),
            self.size_bytes(),
            self.duration_s,
            files=[str(f) for f in self.files],
        )
        state.frames_written, state.frames_dropped = self.frames_written, self.dropped
        state.frames_rejected, state.queued = self.rejected, self.queue.qsize()
        state.error = self.error or self.last_reject
        if self.video_source is not None:
            tap = self.tap
            state.fused_video = True
            state.video_frames_written = self.video_frames_written
            state.video_frames_skipped = self.video_refused + (tap.passed_over if tap else 0)
            state.video_error = self.video_error or (tap.error if tap else None)
            if state.error is None and state.video_error is not None:
                state.error = (
                    f"fused video stopped (the sensors are still recorded): {state.video_error}"
                )
        return state


class Recorder:
    """Records the frames offered to it into new MCAP files in ``directory``.

    Args:
        directory: where recordings go (created when the first one starts).
        max_queue: frames waiting for the disk at most; beyond it frames are dropped and
            counted (``frames_dropped``), never waited for.
        writer_kw: options of :class:`app.recording.RecordingWriter` (``jpeg_quality`` ...).

    :meth:`offer` is called by the pipeline thread for every frame and never blocks;
    :meth:`start` and :meth:`stop` by the panel or the API.
    """

    def __init__(self, directory: Path, max_queue: int = 32, **writer_kw: object) -> None:
        if max_queue < 1:
            raise ValueError(f"max_queue: expected at least 1 frame, got {max_queue}")
        self.directory = Path(directory)
        self.max_queue = max_queue
        self.writer_kw = writer_kw
        self._lock = threading.Lock()  # guards _session and the offer/stop hand-over
        self._control = threading.Lock()  # one start/stop at a time
        self._session: _Session | None = None
        self._stopping: _Session | None = None  # finishing its file(s)
        self.last: RecordingState | None = None
        self.interrupted: list[Path] = self._recover()
        self.head_pose: Callable[[int], np.ndarray | None] | None = None
        """The source's head pose (``T_world_rig`` at a stamp, ns), written beside each TOF
        frame (``/tf`` ``world -> rig``) so that a recording maps as the live head did."""

    def _recover(self) -> list[Path]:
        """Keep what recordings interrupted by a crash wrote (see the module doc)."""
        try:
            kept = recover_interrupted(self.directory)
        except OSError as exc:
            log.error("%s: could not look for interrupted recordings: %s", self.directory, exc)
            return []
        with contextlib.suppress(OSError):
            for reservation in self.directory.glob(".*.mcap.reserved"):
                if (self.directory / reservation.name[1 : -len(".reserved")]).exists():
                    reservation.unlink(missing_ok=True)  # finished and named, then killed
        for name, path in kept:
            (self.directory / f".{name}.reserved").unlink(missing_ok=True)  # its writer died
            cut = path.name != name
            log.warning(
                "%s: the console stopped while writing this recording; kept%s",
                path,
                " (cut off: it reads up to its last complete chunk)" if cut else " (complete)",
            )
        return [path for _name, path in kept]

    @property
    def active(self) -> bool:
        return self._session is not None

    def offer(self, frame: Frame) -> None:
        """Queue a frame for the recording, if one runs; drop it if the queue is full."""
        self._put(frame)

    def note(self, note: Note) -> None:
        """Queue a measurement note for the recording, if one runs (dropped, counted, if
        the queue is full)."""
        self._put(note)

    def _put(self, item: Frame | Note) -> None:
        session = self._session
        if session is None:
            return
        with self._lock:
            if self._session is not session or not session.accepting:
                return
            try:
                session.queue.put_nowait(item)
            except queue.Full:
                session.dropped += 1

    def start(self, rig: Rig, video: VideoFeed | None = None) -> RecordingState:
        """Start a new recording of ``rig``'s sensors (ControlError if one runs); with
        ``video``, it also keeps the fused pictures as ``/fused/video``."""
        with self._control:
            if self._session is not None:
                raise ControlError(
                    f"already recording to {self._session.state().path}; stop it first"
                )
            session = _Session(
                self.directory, rig, self.max_queue, dict(self.writer_kw), video, self.head_pose
            )
            with self._lock:
                self._session = session
            return session.state()

    def stop(self, timeout_s: float = 120.0) -> RecordingState:
        """Stop: write what is queued, finish and name the file(s); returns the final state
        (``active`` False, ``files`` the recordings written). ControlError without one."""
        with self._control:
            session = self._session
            if session is None:
                raise ControlError("not recording")
            session.stop_video()  # the pictures waiting are encoded and queued
            with self._lock:
                session.accepting = False
                self._session = None
                self._stopping = session
            try:
                session.queue.put(_STOP)  # after every frame queued before (no more come)
                session.thread.join(timeout_s)
                state = session.state()
                state.active = session.thread.is_alive()
                if state.active:
                    state.error = f"still writing after {timeout_s:.0f} s"
                self.last = state
            finally:
                self._stopping = None
            return state

    def state(self) -> RecordingState:
        """The running recording's state, else the last one's (or an idle state)."""
        session = self._session
        if session is not None:
            return session.state()
        stopping = self._stopping
        if stopping is not None:
            state = stopping.state()
            state.stopping = True
            return state
        if self.last is not None:
            return dataclasses.replace(self.last, files=list(self.last.files))
        if self.interrupted:
            names = ", ".join(f"{RECORDINGS}/{p.name}" for p in self.interrupted)
            return RecordingState(
                available=True,
                interrupted=[str(p) for p in self.interrupted],
                error=f"the console stopped while recording; what was written is kept: {names}",
            )
        return RecordingState(available=True)

    def close(self) -> None:
        """Stop a running recording (the file is finished and kept)."""
        with contextlib.suppress(ControlError):
            self.stop()
