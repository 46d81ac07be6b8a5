"""What the console plays and records: a tap on the source, a background recorder, and the
controls the Source panel and the REST API share.

- :class:`SourceTap` wraps the opened :class:`FrameSource`: the fusion pipeline iterates it
  as it would the source. It measures each sensor's delivered frame rate, hands every
  frame to the :class:`Recorder` while one is recording, and checks each frame
  (:class:`~app.server.runtime.sensor_health.HealthMonitor`): garbage frames (wrong size, no finite
  pixel, implausible values) are withheld from fusion, which carries on without them.
- :class:`Recorder` writes those frames to a new MCAP recording (``app.recording.
  RecordingWriter``, docs/FORMATS.md "Recordings") in a background thread fed by a bounded
  queue. The pipeline never waits for the disk: when the queue is full the frame is dropped
  and counted. Stopping writes what is queued, finishes the file and gives it its name.
- :class:`FusedVideoTap` (when the recording keeps the fused video: the Source panel's
  "Record fused video", :attr:`SourceControl.fused_video`): the fused pictures the console
  publishes (``StreamFrame.bgr``, handed over by the hub as each frame is published) are
  encoded as H.264 in a worker thread (:class:`app.recording.video_track.FusedVideoEncoder`)
  and the access units go through the recorder's queue to ``/fused/video``. It holds the
  fusion's demand (the console fuses while it records) and never slows the pipeline: a
  picture waits in a short inbox, the oldest dropped and counted when the encoder falls
  behind; every picture it encodes reaches the writer (the P-frame chain stays whole; each
  file of the recording begins with a key frame). A failure of the video is logged and
  shown in the recording state; the sensor recording goes on without video.
- :class:`SourceControl` is what the panel and the routes call: the state of the source,
  each sensor's health (:meth:`SourceControl.sensor_health`), replay controls (pause,
  resume, seek, rate) and recording start/stop.

Recordings go to ``<workdir>/recordings/<YYYYmmdd-HHMMSS>.mcap`` (local time of the start;
``-2``, ``-3`` ... appended when the name is taken). Nothing is ever overwritten: a name is
reserved by an empty hidden file ``.<name>.reserved`` while it is being written, and the
writer refuses a name that exists. When the source's time goes back (a replay that loops
or is seeked backwards), the recording continues in a new file, so that each file's
frames stay in time order.

A recording the console was writing when it was killed is kept: when the console starts
again, :func:`app.recording.writer.recover_interrupted` names it
``recordings/<YYYYmmdd-HHMMSS>.partial.mcap`` (readable up to its last complete chunk), its
stale reservation is removed, and the recording state says so (``interrupted``, ``error``;
the Source panel shows it) until the next recording starts.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.video_track import (
    FusedVideoEncoder,
    VideoSettings,
    VideoUnit,
    video_metadata,
)
from trifuse.app.recording.writer import RecordingWriter, recover_interrupted
from trifuse.app.server.runtime.demand import Demand, Hold
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.rates import RATE_WINDOW_S, RatesSnapshot, window_rate
from trifuse.app.server.runtime.sensor_health import (
    HealthMonitor,
    Rejections,
    SensorHealth,
    expected_of,
    push_rejections,
)
from trifuse.app.server.runtime.stream import FrameHub, StreamFrame
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig

log = logging.getLogger(__name__)

SourceKind = Literal["simulated", "replay", "live", "push"]
RATE_MIN, RATE_MAX = 0.25, 4.0
"""Replay speeds the console offers (1.0 = real time)."""
HEALTH_CACHE_S = 0.5
"""The health lines put in the stream's metadata are recomputed at most this often (s)."""
RECORDINGS = "recordings"
"""The folder of the work directory that console recordings go to."""
VIDEO_INBOX = 3
"""Pictures waiting for the fused-video encoder at most (a burst of the pipeline's)."""
VIDEO_AHEAD_S = 0.1
"""A file's first video picture may be at most this much later than its newest sensor
frame (a later one belongs to the time before a replay went back, seconds)."""


class ControlError(RuntimeError):
    """A control that does not apply now (replay control on a live source, a second
    recording, stop without a recording); the REST API answers 409 with the message."""


# -- rates --------------------------------------------------------------------------------


class RateMeter:
    """Frames per second of each sensor over the last ``window_s`` seconds (thread-safe;
    the same window as the stream's rates, :data:`app.server.runtime.rates.RATE_WINDOW_S`)."""

    def __init__(self, window_s: float = RATE_WINDOW_S) -> None:
        self.window_s = window_s
        self._lock = threading.Lock()
        self._times: dict[str, deque[float]] = {}
        self._first: dict[str, float] = {}
        self.last_s: float | None = None  # monotonic time of the newest frame

    def tick(self, sensor: str, now_s: float | None = None) -> None:
        """Count one frame of ``sensor`` (arrival at monotonic ``now_s`` seconds)."""
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            times = self._times.get(sensor)
            if times is None:
                times = self._times[sensor] = deque()
                self._first[sensor] = now
            times.append(now)
            while times[0] < now - self.window_s:
                times.popleft()
            self.last_s = now

    def rates_hz(
        self, sensors: list[str] | None = None, now_s: float | None = None
    ) -> dict[str, float]:
        """``{sensor: Hz}``: frames in the window divided by the window (or by the time
        since the sensor's first frame, if shorter); 0.0 for a sensor without frames."""
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            names = list(sensors) if sensors is not None else []
            names += [s for s in self._times if s not in names]
            return {
                s: window_rate(self._times.get(s, deque()), self._first.get(s), now, self.window_s)
                for s in names
            }


# -- recording ----------------------------------------------------------------------------


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
    encoder was behind (:class:`FusedVideoTap`), or refused to keep the chain whole (a new
    file waits for a key frame)."""
    video_error: str | None = None
    """Why the fused video stopped (the sensor recording went on), or None."""


_STOP = object()


def _duration_s(writer: RecordingWriter) -> float:
    """Seconds between the first and the last frame stamp a writer wrote (0 if none)."""
    if writer.first_ns is None or writer.last_ns is None:
        return 0.0
    return (writer.last_ns - writer.first_ns) / 1e9


@dataclass(frozen=True)
class FusedVideoSource:
    """Where a recording's fused video comes from.

    Attributes:
        hub: the stream's frames; their ``bgr`` pictures are encoded (the tap is one of
            ``hub.takers`` while it records, so that frames carry them).
        demand: held while recording, so that the console fuses (None: it always does).
        settings: the encoding (bitrate, key-frame interval).
    """

    hub: FrameHub
    demand: Demand | None = None
    settings: VideoSettings = field(default_factory=VideoSettings)


class FusedVideoTap:
    """Encodes the pictures a :class:`FrameHub` publishes, in a thread of its own, and hands
    each access unit to ``deliver`` (see the module doc).

    The hub calls :meth:`_take` with every frame it publishes (``hub.takers``, so frames
    carry their BGR picture); a new picture waits in an inbox of :data:`VIDEO_INBOX`
    pictures (a repeat of the previous picture is not new: the video shows it on), the
    oldest dropped and counted when the encoder falls behind; the thread encodes them in
    order.

    Args:
        source: the hub, the demand to hold, the encoding.
        deliver: called with each :class:`VideoUnit` in the tap's thread; it may block;
            False: stop.

    Attributes:
        encoded: pictures encoded and delivered; ``passed_over``: new pictures dropped
            from the inbox (the encoder was behind); ``error``: why the tap stopped, or
            None.
    """

    def __init__(self, source: FusedVideoSource, deliver: Callable[[VideoUnit], bool]) -> None:
        self.source, self._deliver = source, deliver
        self.encoder = FusedVideoEncoder(source.settings)
        self.encoded = 0
        self.passed_over = 0
        self.error: str | None = None
        self._inbox: deque[tuple[np.ndarray, int]] = deque()
        self._last_bgr: np.ndarray | None = None  # the last picture taken (publishing thread)
        self._lock = threading.Lock()  # the inbox; the hub's takers and the hold, released once
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorder-video", daemon=True)
        self._hold: Hold | None = None
        self._taking = False

    def start(self) -> FusedVideoTap:
        """Take pictures from now on (frames carry them; the console fuses)."""
        with self._lock:
            if self.source.demand is not None:
                self._hold = self.source.demand.hold()
            self.source.hub.takers.append(self._take)
            self._taking = True
        self._thread.start()
        return self

    def _take(self, frame: StreamFrame) -> None:
        """A frame published (the publishing thread: quick, never blocks)."""
        bgr, stamp = frame.bgr, frame.meta.get("stamp_ns")
        if bgr is None or bgr is self._last_bgr or not isinstance(stamp, int):
            return  # no picture, or a repeat of the last one
        self._last_bgr = bgr
        with self._lock:
            if len(self._inbox) >= VIDEO_INBOX:
                self._inbox.popleft()
                self.passed_over += 1
            self._inbox.append((bgr, stamp))
            self._ready.set()

    def request_key(self) -> None:
        """Make the next picture a key frame (the recording began a new file)."""
        self.encoder.request_key()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Take no more pictures, encode and deliver those waiting, end the thread, release
        the hub and the demand. Idempotent."""
        self._release()
        with self._lock:
            self._stop.set()
            self._ready.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def _release(self) -> None:
        with self._lock:
            if self._taking:
                self._taking = False
                with contextlib.suppress(ValueError):
                    self.source.hub.takers.remove(self._take)
            hold, self._hold = self._hold, None
        if hold is not None:
            hold.release()

    def _next(self) -> tuple[np.ndarray, int] | None:
        """The oldest picture waiting (blocks); None once stopped and none is left."""
        while True:
            with self._lock:
                if self._inbox:
                    return self._inbox.popleft()
                if self._stop.is_set():
                    return None
                self._ready.clear()
            self._ready.wait(1.0)

    def _run(self) -> None:
        try:
            while (item := self._next()) is not None:
                unit = self.encoder.encode(*item)
                if not self._deliver(unit):
                    break
                self.encoded += 1
        except Exception as exc:  # the encoder, a picture: the sensor recording goes on
            self.error = describe_error(exc)
            log.error("the recording's fused video stopped: %s", self.error)
        finally:
            self._release()
            with self._lock:
                self._stop.set()
                self._inbox.clear()
            self.encoder.close()


class _Session:
    """One recording from start to stop (possibly several files, see the module doc)."""

    def __init__(
        self,
        directory: Path,
        rig: Rig,
        max_queue: int,
        writer_kw: dict,
        video: FusedVideoSource | None = None,
        head_pose: Callable[[int], np.ndarray | None] | None = None,
    ) -> None:
        self.directory, self.rig, self.writer_kw = directory, rig, writer_kw
        self.head_pose = head_pose  # the source's pose of the head, kept at each TOF frame
        self.video_source = video
        self.tap: FusedVideoTap | None = None
        self.video_written_before = 0  # pictures of the files already finished
        self.video_refused = 0  # units the files refused (to keep the chain whole)
        self.video_error: str | None = None  # the tap could not start
        self.queue: queue.Queue = queue.Queue(maxsize=max_queue)
        self.accepting = True
        self.dropped = 0
        self.rejected = 0
        self.written_before = 0  # frames of the files already finished
        self.duration_before_s = 0.0  # their recording time
        self.files: list[Path] = []
        self.error: str | None = None
        self.last_reject: str | None = None
        self._last_stamp: dict[str, int] = {}
        self.writer: RecordingWriter | None = None
        self._reservation: Path | None = None
        self._open_next()  # errors (disk, permissions) reach the caller of start()
        self.thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self.thread.start()
        if video is not None:
            try:
                self.tap = FusedVideoTap(video, self._put_video).start()
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

    # A new file: reserve a free name, then open the writer on it.
    def _open_next(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        stem = time.strftime("%Y%m%d-%H%M%S")
        for k in range(1, 10_000):
            name = f"{stem}.mcap" if k == 1 else f"{stem}-{k}.mcap"
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
                self.writer = RecordingWriter(path, self.rig, **self.writer_kw)
            except FileExistsError:
                reservation.unlink(missing_ok=True)
                continue
            except BaseException:
                reservation.unlink(missing_ok=True)
                raise
            self._reservation = reservation
            self._last_stamp.clear()
            if self.video_source is not None:
                self.writer.add_fused_video(metadata=video_metadata(self.video_source.settings))
                if self.tap is not None:
                    self.tap.request_key()  # the new file's video starts with a key frame
            return
        raise FileExistsError(f"{self.directory}: no free recording name for {stem}")

    def _finish_file(self) -> None:
        """Close the current file (summary, fsync, name) and release its reservation."""
        writer, self.writer = self.writer, None
        if writer is None:
            return
        try:
            if writer.frames_written:
                self.files.append(writer.close())
                self.written_before += writer.frames_written
                self.duration_before_s += _duration_s(writer)
                self.video_written_before += writer.video_frames_written
            else:
                writer.abort()  # nothing recorded: no empty file
        finally:
            if self._reservation is not None:
                self._reservation.unlink(missing_ok=True)
                self._reservation = None

    def _write(self, frame: Frame) -> None:
        last = self._last_stamp.get(frame.sensor)
        if last is not None and frame.stamp_ns < last and self.writer is not None:
            if self.writer.frames_written:
                self._finish_file()  # time went back: a new file keeps each in order
                self._open_next()
            else:
                self._last_stamp.clear()
        if self.writer is None:
            self._open_next()
        try:
            self.writer.write(frame)  # type: ignore[union-attr]
        except RecordingError as exc:  # a frame the rig does not describe: skip it
            self.rejected += 1
            self.last_reject = str(exc)
            return
        self._last_stamp[frame.sensor] = frame.stamp_ns
        if self.head_pose is not None and frame.distance_m is not None:  # a TOF frame
            pose = self.head_pose(frame.stamp_ns)
            if pose is not None:
                self.writer.write_pose(frame.stamp_ns, pose)  # type: ignore[union-attr]

    def _write_video(self, unit: VideoUnit) -> None:
        """Write an access unit to the current file's ``/fused/video``; a unit the file
        refuses (a delta frame before its first key frame, a stamp not after the last, a
        picture from before the replay went back) is counted, and the tap asked for a key
        frame."""
        if self.writer is None:
            self._open_next()
        writer = self.writer
        assert writer is not None
        track = writer.fused_video
        if track is None:
            return
        ahead = (
            track.awaiting_key
            and writer.last_ns is not None
            and unit.stamp_ns > writer.last_ns + VIDEO_AHEAD_S * 1e9
        )
        if not ahead and writer.write_video(unit.data, unit.key, unit.stamp_ns):
            return
        self.video_refused += 1
        if track.awaiting_key and self.tap is not None:
            self.tap.request_key()

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            if item is _STOP:
                break
            if self.error is not None:
                continue  # a failed disk: drain without writing
            try:
                if isinstance(item, VideoUnit):
                    self._write_video(item)
                else:
                    self._write(item)
            except Exception as exc:  # disk full, I/O error: keep what was written
                self.error = describe_error(exc)
                log.error("recording stopped writing: %s", self.error)
                self.accepting = False
                with contextlib.suppress(Exception):
                    self._finish_file()
        try:
            self._finish_file()
        except Exception as exc:
            self.error = self.error or describe_error(exc)
            log.error("recording could not be finished: %s", self.error)

    # -- reporting ----------------------------------------------------------------------

    def state(self) -> RecordingState:
        writer = self.writer
        size, duration, written, path = 0, self.duration_before_s, self.written_before, None
        if writer is not None:
            path = str(writer.path)
            with contextlib.suppress(OSError):
                size = writer.temp_path.stat().st_size
            written += writer.frames_written
            duration += _duration_s(writer)
        elif self.files:
            path = str(self.files[-1])
        for f in self.files:
            with contextlib.suppress(OSError):
                size += f.stat().st_size
        state = RecordingState(True, True, path, size, duration, files=[str(f) for f in self.files])
        state.frames_written, state.frames_dropped = written, self.dropped
        state.frames_rejected, state.queued = self.rejected, self.queue.qsize()
        state.error = self.error or self.last_reject
        if self.video_source is not None:
            tap = self.tap
            state.fused_video = True
            state.video_frames_written = self.video_written_before + (
                writer.video_frames_written if writer is not None else 0
            )
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
        session = self._session
        if session is None:
            return
        with self._lock:
            if self._session is not session or not session.accepting:
                return
            try:
                session.queue.put_nowait(frame)
            except queue.Full:
                session.dropped += 1

    def start(self, rig: Rig, video: FusedVideoSource | None = None) -> RecordingState:
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


# -- the tap ------------------------------------------------------------------------------


class SourceTap(FrameSource):
    """A :class:`FrameSource` that forwards another's frames, counting them per sensor and
    handing each to a :class:`Recorder` (which never blocks).

    Attributes:
        inner: the wrapped source (its ``close`` is called by this one's).
        meter: delivered frame rates per sensor (every frame, usable or not).
        recorder: the recorder frames are offered to (None: no recording); it gets every
            frame as received.
        health: checks each frame; garbage frames are not passed on (the consumer sees the
            sensor missing). Judged against the source's rig until :class:`SourceControl`
            gives it the pipeline's.
    """

    def __init__(self, inner: FrameSource, recorder: Recorder | None = None) -> None:
        self.inner = inner
        self.sensors = list(inner.sensors)
        self.rig = inner.rig
        self.meter = RateMeter()
        self.recorder = recorder
        self.health = HealthMonitor(self.sensors, expected_of(inner.rig, self.sensors))

    def frames(self) -> Iterator[Frame]:
        meter, health = self.meter, self.health
        for frame in self.inner.frames():
            now = time.monotonic()
            meter.tick(frame.sensor, now)
            recorder = self.recorder
            if recorder is not None:
                recorder.offer(frame)
            if health.observe(frame, now) is not None:
                continue  # garbage: shown in the sensor's health, not fused
            yield frame

    def close(self) -> None:
        self.inner.close()


# -- the controls -------------------------------------------------------------------------


@dataclass
class SourceState:
    """The source: what it is, and for a replay where it is (seconds from its start), its
    length (seconds), whether it is paused and its speed (1.0 = real time)."""

    description: str
    kind: SourceKind
    sensors: list[str]
    position_s: float | None = None
    duration_s: float | None = None
    paused: bool | None = None
    rate: float | None = None


def kind_of(source: FrameSource) -> SourceKind:
    """``replay`` (recordings, ROS 2 bags), ``simulated``, ``push`` or ``live``."""
    from trifuse.app.recording.player import MessageReplay
    from trifuse.app.sources.push.source import PushSource
    from trifuse.app.sources.simulated import SimulatedHeadSource

    if isinstance(source, MessageReplay):
        return "replay"
    if isinstance(source, SimulatedHeadSource):
        return "simulated"
    if isinstance(source, PushSource):
        return "push"
    return "live"


def check_rate(rate: float) -> float:
    """A replay speed in [RATE_MIN, RATE_MAX] (ValueError naming what arrived otherwise)."""
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not math.isfinite(rate):
        raise ValueError(f"rate: expected a number {RATE_MIN}..{RATE_MAX}, got {rate!r}")
    if not RATE_MIN <= rate <= RATE_MAX:
        raise ValueError(f"rate: expected {RATE_MIN}..{RATE_MAX} (x real time), got {rate}")
    return float(rate)


class SourceControl:
    """The source's state and controls, shared by the Source panel and the REST API.

    Args:
        pipeline: the running fusion pipeline; its ``source`` should be a
            :class:`SourceTap` (per-sensor rates and recording need it).
        hub: the stream hub (number of viewers).
        description: one line saying what the source is.
        workdir: the console's work directory; recordings go to ``workdir/recordings``.
            None: recording is unavailable.
        rig: the rig recordings store (default: the pipeline's rig at each start).
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        hub: FrameHub,
        description: str = "",
        workdir: Path | None = None,
        rig: Callable[[], Rig] | None = None,
    ) -> None:
        self.pipeline, self.hub, self.description = pipeline, hub, description
        src = pipeline.source
        self.tap = src if isinstance(src, SourceTap) else None
        self.source = self.tap.inner if self.tap is not None else src
        self.kind: SourceKind = kind_of(self.source)
        self._rig = rig or (lambda: pipeline.rig)
        self.recorder: Recorder | None = None
        if workdir is not None and self.tap is not None:
            self.recorder = self.tap.recorder or Recorder(Path(workdir) / RECORDINGS)
            self.tap.recorder = self.recorder
            self.recorder.head_pose = getattr(self.tap.inner, "head_pose", None)
        self.fused_video = False
        """Recordings started from now on also keep the fused video (the Source panel's
        "Record fused video"; ``POST /api/recording/start`` follows it)."""
        self.video_settings = VideoSettings()
        self._notes: tuple[float, dict[str, str]] | None = None
        if self.tap is not None:
            self.tap.health.set_rig(pipeline.rig)  # frames must fit what fusion expects
            pipeline.sensor_notes = self.health_notes

    # -- state --------------------------------------------------------------------------

    @property
    def is_replay(self) -> bool:
        return self.kind == "replay"

    def source_state(self) -> SourceState:
        st = SourceState(self.description, self.kind, list(self.source.sensors))
        if self.is_replay:
            src = self.source
            st.position_s = max(0.0, (src.position_ns - src.start_ns) / 1e9)  # type: ignore[attr-defined]
            st.duration_s = float(src.duration_s)  # type: ignore[attr-defined]
            st.paused = bool(src.paused)  # type: ignore[attr-defined]
            st.rate = float(src.rate)  # type: ignore[attr-defined]
        return st

    @property
    def paused(self) -> bool:
        """A replay held by :meth:`pause`."""
        return self.is_replay and bool(self.source.paused)  # type: ignore[attr-defined]

    def rates_hz(self) -> dict[str, float]:
        """Frames per second each sensor delivers to the console now (all 0 while a replay
        is paused; empty without a tap)."""
        if self.tap is None:
            return {}
        rates = self.tap.meter.rates_hz(list(self.source.sensors))
        return dict.fromkeys(rates, 0.0) if self.paused else rates

    def stream_rates(self) -> RatesSnapshot:
        """The stream's rates over the last :data:`~app.server.runtime.rates.RATE_WINDOW_S` seconds
        (taken at whole seconds: the viewer's frame metadata carries the same figures):
        frames published per second and, of these, new pictures per second. A repeated
        picture is the previous one published again because its input did not change (the
        simulated head shows each rendered pose for several frames). Zeros while a replay is
        paused; a stalled stream reads 0 once the window has passed."""
        snap = self.hub.rates.snapshot()
        if self.paused:
            return dataclasses.replace(snap, stream_fps=0.0, new_fps=0.0)
        return snap

    def sensor_health(self, now_s: float | None = None) -> dict[str, SensorHealth]:
        """Each sensor's health (:mod:`app.server.runtime.sensor_health`): the frames the tap saw,
        the push ingest's rejections, a replay's skipped messages, camera readers' states;
        empty without a tap."""
        if self.tap is None:
            return {}
        src = self.source
        rejections: dict[str, Rejections] = {}
        devices: dict[str, tuple[str, str]] = {}
        if self.kind in ("push", "replay"):  # a replay's skipped messages count as rejected
            rejections = push_rejections(src.stats())  # type: ignore[attr-defined]
        status = getattr(src, "status", None)
        if self.kind == "live" and callable(status):
            with contextlib.suppress(Exception):
                for name, d in status().items():
                    devices[name] = (str(getattr(d, "state", "")), str(getattr(d, "reason", "")))
        return self.tap.health.report(
            now_s,
            rates_hz=self.rates_hz(),
            paused=self.paused,
            rejections=rejections,
            devices=devices,
        )

    def health_notes(self) -> dict[str, str]:
        """``{sensor: line}`` for the sensors that are not ok (recomputed at most every
        :data:`HEALTH_CACHE_S`; the pipeline puts it in each frame's metadata)."""
        now = time.monotonic()
        cached = self._notes
        if cached is not None and now - cached[0] < HEALTH_CACHE_S:
            return cached[1]
        notes = {s: h.line() for s, h in self.sensor_health(now).items() if not h.ok}
        self._notes = (now, notes)
        return notes

    def recording_state(self) -> RecordingState:
        if self.recorder is None:
            why = (
                "recording needs the console's work directory (trifuse serve --workdir)"
                if self.tap is not None
                else "recording needs the source wrapped in a SourceTap"
            )
            return RecordingState(available=False, error=why)
        return self.recorder.state()

    # -- replay controls ----------------------------------------------------------------

    def _replay(self, what: str):
        if not self.is_replay:
            raise ControlError(
                f"{what}: the source is {self.kind} ({self.description}), not a replay; "
                "pause, resume, seek and rate apply to recordings only"
            )
        return self.source

    def pause(self) -> SourceState:
        self._replay("pause").pause()
        return self.source_state()

    def resume(self) -> SourceState:
        self._replay("resume").resume()
        return self.source_state()

    def seek(self, position_s: float) -> SourceState:
        """Continue from ``position_s`` seconds after the recording's start
        (ValueError outside 0..duration_s)."""
        src = self._replay("seek")
        duration = float(src.duration_s)
        if (
            isinstance(position_s, bool)
            or not isinstance(position_s, int | float)
            or not math.isfinite(position_s)
            or not 0.0 <= position_s <= duration
        ):
            raise ValueError(
                f"position_s: expected seconds 0..{duration:.3f} (the recording's length), "
                f"got {position_s!r}"
            )
        src.seek(int(src.start_ns + round(position_s * 1e9)))
        return self.source_state()

    def set_rate(self, rate: float) -> SourceState:
        """Replay speed, RATE_MIN..RATE_MAX times real time (ValueError otherwise)."""
        src = self._replay("rate")
        src.rate = check_rate(rate)
        return self.source_state()

    # -- recording ----------------------------------------------------------------------

    def start_recording(self, fused_video: bool | None = None) -> RecordingState:
        """Start recording; ``fused_video`` (default :attr:`fused_video`): also keep the
        fused pictures the console publishes as ``/fused/video``."""
        if self.recorder is None:
            raise ControlError(self.recording_state().error or "recording is unavailable")
        video = None
        if self.fused_video if fused_video is None else fused_video:
            demand = getattr(self.pipeline, "demand", None)
            video = FusedVideoSource(self.hub, demand, self.video_settings)
        return self.recorder.start(self._rig(), video)

    def stop_recording(self) -> RecordingState:
        if self.recorder is None:
            raise ControlError(self.recording_state().error or "recording is unavailable")
        return self.recorder.stop()

    def stop(self) -> None:
        """Shut down: a running recording is finished and kept."""
        if self.recorder is not None:
            self.recorder.close()
