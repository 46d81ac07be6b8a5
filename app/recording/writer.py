"""Writing recordings: frames of a sensor head into an MCAP file that Foxglove opens as is.

The layout (topics, schemas, encodings) is in :mod:`app.recording.layout` and
docs/FORMATS.md ("Recordings"); the messages are built by :mod:`app.recording.messages`
(shared with the console's live Foxglove server: live and recorded, the same bytes).
Writing goes through foxglove-sdk (one private ``foxglove.Context`` per writer, so writers
never share channels) into a temporary file in the target's directory;
:meth:`RecordingWriter.close` finishes the MCAP (summary, indexes), fsyncs it and links it
to its name, refusing to replace a file that exists by then.

While it is written, the temporary file ``.<name>.<random>.partial``
(:func:`~app.recording.recovery.new_partial`) is locked (``flock``) and is a complete MCAP
at every moment (:mod:`app.recording.sealed_file`): about once a second (``seal_period_s``)
the chunk in progress is finished and put on disk with an ending (``DataEnd``, a footer
without summary), so a killed program leaves a file that every MCAP reader (the ``mcap``
package, Foxglove) opens, with only complete records, holding all but the last second.
:func:`~app.recording.recovery.recover_interrupted` (called when the console starts) finds
such a file and keeps it under a visible name.

A recording may also keep the fused stereo picture as H.264 (``/fused/video``,
:meth:`RecordingWriter.add_fused_video`, :meth:`RecordingWriter.write_video`;
:mod:`app.recording.video_track` makes it). Observers (:attr:`RecordingWriter.observers`)
see every frame written and the file's end: ``trifuse record --fused-video`` fuses there.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Protocol

import foxglove
import numpy as np
from foxglove.channels import FrameTransformChannel, LogChannel
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import Log, LogLevel, Timestamp

from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.layout import (
    MEASUREMENTS_TOPIC,
    METADATA_NAME,
    RECORDING_FORMAT,
    RIG_ATTACHMENT,
    RIG_FRAME,
    TF_TOPIC,
    WORLD_FRAME,
)
from trifuse.app.recording.mcapindex import MAX_CHUNK_BYTES
from trifuse.app.recording.messages import (
    THERMAL_ENCODINGS,
    calibration_message,
    frame_messages,
    largest_message_bytes,
    sensor_channels,
    transform_message,
)
from trifuse.app.recording.recovery import new_partial
from trifuse.app.recording.video_track import FusedVideoTrack, video_frame_id
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.storage.atomic import fsync_dir, make_dirs, umask
from trifuse.calib.numbers import is_int, is_integral
from trifuse.calib.rig import Rig, Sensor, rig_to_yaml
from trifuse.calib.transforms import rigidity_problem


@dataclass(frozen=True)
class Note:
    """A measurement note for a recording: ``name`` (``trifuse.alarm``,
    ``trifuse.measurement_settings``), ``level`` (``info``, ``warning``), ``body`` (JSON-able)
    at ``stamp_ns`` (the picture's frame time)."""

    stamp_ns: int
    name: str
    level: str
    body: dict


COMPRESSIONS = {"zstd": MCAPCompression.Zstd, "lz4": MCAPCompression.Lz4, "none": None}
MAX_CHUNK_SIZE = 16 * 2**20
"""The largest ``chunk_size`` a writer takes, bytes."""
MAX_MESSAGE_BYTES = MAX_CHUNK_BYTES - MAX_CHUNK_SIZE - 2**20
"""The largest frame message a writer may have to write (a raw frame's pixels, or a colour
frame's uncompressed size, which bounds its JPEG): a chunk (at most ``chunk_size`` plus one
message) then stays within what a reader takes (:data:`app.recording.mcapindex.
MAX_CHUNK_BYTES`). A rig whose sensors' frames are larger is refused."""


_MAX_STAMP_NS = 2**63 - 1
log = logging.getLogger(__name__)

_DEFERRED = {signal.SIGINT, signal.SIGTERM}


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM's Python handlers back while the MCAP writer runs: a signal
    that comes meanwhile is raised again when the block ends. The handlers raise
    KeyboardInterrupt at the main thread's next instruction, which may be in the file's
    ``write`` that the writer (Rust) calls: the writer then fails for good ("attempted
    another write after a write method failed") and the recording could not be finished
    (a SIGTERM during a chunk's write in a test of ``trifuse record``). Blocking the
    signals on the main thread is not enough: the kernel gives them to another thread,
    whose C handler still has the main thread run the Python one. Signals left to the
    system (``SIG_DFL``, ``SIG_IGN``) are not touched."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers are set, and run, on the main thread only
        return
    held: list[int] = []

    def hold(signum: int, _frame: object) -> None:
        held.append(signum)

    previous = {s: h for s in _DEFERRED if callable(h := signal.getsignal(s))}
    for s in previous:
        signal.signal(s, hold)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(held):
            signal.raise_signal(s)


class FrameObserver(Protocol):
    """Something that watches a recording being written (``RecordingWriter.observers``):
    ``frame_written(frame)`` after each frame written (not the skipped repeats),
    ``closing()`` when the file is about to be finished (not when it is aborted). It may
    write to the recording (e.g. :meth:`RecordingWriter.write_video`); it should not
    raise: if it does, the error is logged and the observer is dropped, the recording goes
    on."""

    def frame_written(self, frame: Frame) -> None: ...

    def closing(self) -> None: ...


def _stamp(value: object, sensor: str) -> int:
    if not is_integral(value):
        raise RecordingError(
            f"frame of {sensor!r}: stamp_ns: expected an integer number of nanoseconds, "
            f"got {value!r}"
        )
    stamp = int(value)
    if not 0 <= stamp <= _MAX_STAMP_NS:
        raise RecordingError(
            f"frame of {sensor!r}: stamp_ns: expected 0 <= stamp_ns < 2**63, got {stamp}"
        )
    return stamp


class RecordingWriter:
    """Writes frames of a rig's sensors into a new MCAP recording at ``path``.

    Args:
        path: the recording to create; it must not exist (FileExistsError), now or when
            the writer closes.
        rig: the rig the frames belong to; stored in the file (attachment ``rig.yaml``,
            and as ``foxglove.CameraCalibration`` per sensor and ``foxglove.FrameTransform``
            per sensor on ``/tf``).
        jpeg_quality: JPEG quality of the colour images, 1..100.
        thermal_encoding: ``"16UC1"`` (centi-kelvin, 0.01 K steps, 0 = no reading) or
            ``"32FC1"`` (float kelvin, NaN = no reading).
        compression: MCAP chunk compression, ``"zstd"``, ``"lz4"`` or ``"none"``.
        calibration_period_s: the calibration and transforms are written at the first
            frame's time and again at least this often (recording time), so that a player
            that seeks finds them.
        chunk_size: target uncompressed size of an MCAP chunk in bytes (the unit of
            compression and indexing).
        seal_period_s: at most this many seconds (wall clock) of frames are only in memory:
            then the chunk in progress is finished and the file sealed (see above).
        fused_video: open the ``/fused/video`` track at once (:meth:`add_fused_video`).
        metadata: more metadata records, name -> key/value strings, written after
            ``trifuse.recording`` (e.g. a simulated recording's ``trifuse.simulation``).

    Frames are checked against the rig (sensor known, image size, dtype); a frame whose
    sensor and ``stamp_ns`` equal the last one written for that sensor is skipped (a frame
    set repeats the slower sensors' frames). Where the source knows the head's pose,
    :meth:`write_pose` adds it per frame set (``T_world_rig`` on ``/tf``). Use as a
    context manager: leaving the block normally or by KeyboardInterrupt closes the
    recording (what was written is kept); any other exception aborts it (no file appears).
    """

    def __init__(
        self,
        path: str | Path,
        rig: Rig,
        *,
        jpeg_quality: int = 90,
        thermal_encoding: str = "16UC1",
        compression: str = "zstd",
        calibration_period_s: float = 1.0,
        chunk_size: int = 1 << 20,
        seal_period_s: float = 1.0,
        fused_video: bool = False,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
    ) -> None:
        self.path = Path(path)
        if not isinstance(rig, Rig):
            raise RecordingError(f"rig: expected a calib.rig.Rig, got {type(rig).__name__}")
        if not is_integral(jpeg_quality) or not 1 <= jpeg_quality <= 100:
            raise RecordingError(f"jpeg_quality: expected an integer 1..100, got {jpeg_quality!r}")
        if thermal_encoding not in THERMAL_ENCODINGS:
            raise RecordingError(
                f"thermal_encoding: expected one of {THERMAL_ENCODINGS}, got {thermal_encoding!r}"
            )
        if compression not in COMPRESSIONS:
            raise RecordingError(
                f"compression: expected one of {sorted(COMPRESSIONS)}, got {compression!r}"
            )
        if not np.isfinite(calibration_period_s) or calibration_period_s <= 0:
            raise RecordingError(
                f"calibration_period_s: expected a positive number, got {calibration_period_s!r}"
            )
        if not is_int(chunk_size) or not 1024 <= chunk_size <= MAX_CHUNK_SIZE:
            raise RecordingError(
                f"chunk_size: expected an integer 1024..{MAX_CHUNK_SIZE}, got {chunk_size!r}"
            )
        for s in rig.sensors.values():
            if largest_message_bytes(s, thermal_encoding) > MAX_MESSAGE_BYTES:
                raise RecordingError(
                    f"sensor {s.name!r}: its {s.image_size[0]}x{s.image_size[1]} {s.modality} "
                    f"frames take up to {largest_message_bytes(s, thermal_encoding)} bytes, "
                    f"more than a recording's message may ({MAX_MESSAGE_BYTES})"
                )
        if not (np.isfinite(seal_period_s) and seal_period_s > 0):
            raise RecordingError(
                f"seal_period_s: expected a positive number, got {seal_period_s!r}"
            )
        for name, record in (metadata or {}).items():
            plain = all(isinstance(x, str) for kv in record.items() for x in kv)
            if name == METADATA_NAME or not isinstance(name, str) or not plain:
                raise RecordingError(
                    f"metadata: expected records other than {METADATA_NAME!r} of string keys "
                    f"and values, got {name!r}: {record!r}"
                )
        if self.path.exists():
            raise FileExistsError(
                f"{self.path}: exists; refusing to overwrite a recording (choose a new name)"
            )
        self.rig = rig
        self.jpeg_quality = int(jpeg_quality)
        self.thermal_encoding = thermal_encoding
        self.calibration_period_ns = round(calibration_period_s * 1e9)
        self.frames_written = 0
        self.poses_written = 0
        self._last_pose_ns: int | None = None
        self.duplicates_skipped = 0
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self._last_stamp: dict[str, int] = {}
        self._next_calibration_ns: int | None = None
        self._closed = False
        self.fused_video: FusedVideoTrack | None = None
        """The ``/fused/video`` track, once :meth:`add_fused_video` opened it."""
        self.observers: list[FrameObserver] = []
        self.seal_period_s = float(seal_period_s)
        self._next_seal = time.monotonic() + self.seal_period_s

        parent = self.path.parent
        make_dirs(parent)
        self._file = new_partial(self.path)
        self.temp_path = self._file.path
        self._lock_fd: int | None = self._file.fd  # locked while the file is written
        try:
            with contextlib.suppress(OSError):  # a file system without locks: unlocked
                fcntl.flock(self._file.fd, fcntl.LOCK_EX)
            os.fchmod(self._file.fd, 0o666 & ~umask())
            self._ctx = foxglove.Context()
            options = MCAPWriteOptions(compression=COMPRESSIONS[compression], chunk_size=chunk_size)
            self._mcap = foxglove.open_mcap(self._file, context=self._ctx, writer_options=options)
            now = time.time_ns()
            self._mcap.attach(
                log_time=now,
                create_time=now,
                name=RIG_ATTACHMENT,
                media_type="application/yaml",
                data=rig_to_yaml(rig).encode("utf-8"),
            )
            self._mcap.write_metadata(
                METADATA_NAME,
                {
                    "format": RECORDING_FORMAT,
                    "rig": RIG_ATTACHMENT,
                    "reference": rig.reference,
                    "sensors": ",".join(rig.names),
                    "jpeg_quality": str(self.jpeg_quality),
                    "thermal_encoding": thermal_encoding,
                },
            )
            for name, record in (metadata or {}).items():
                self._mcap.write_metadata(name, dict(record))
            self._channels: dict[tuple[str, str], object] = {}
            for name, s in rig.sensors.items():
                self._make_channels(name, s)
            self._tf = FrameTransformChannel(TF_TOPIC, context=self._ctx)
            self._notes: LogChannel | None = None  # made with the first note
            self.notes_written = 0
            if fused_video:
                self.add_fused_video()
            self.seal()  # from the start the file on disk is an (empty) recording
        except BaseException:
            self._closed = True
            self.temp_path.unlink(missing_ok=True)
            self._unlock()
            raise

    def _unlock(self) -> None:
        self._lock_fd = None
        self._file.close()  # closing the descriptor releases the lock

    def _make_channels(self, name: str, s: Sensor) -> None:
        self._channels.update(sensor_channels(self._ctx, s, self.thermal_encoding))

    # -- writing --------------------------------------------------------------------------

    def write_set(self, frame_set: FrameSet) -> int:
        """Write the frames of a set (in time order); returns how many were new."""
        frames = sorted(frame_set.frames.values(), key=lambda f: f.stamp_ns)
        return sum(self.write(f) for f in frames)

    def write(self, frame: Frame) -> bool:
        """Write one frame; False if it repeats the sensor's last frame (skipped).

        Raises RecordingError for a frame the rig does not describe (unknown sensor, wrong
        size or type) and RuntimeError after :meth:`close`.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the recording is closed")
        if not isinstance(frame, Frame):
            raise RecordingError(f"expected a Frame, got {type(frame).__name__}")
        sensor = frame.sensor
        if sensor not in self.rig:
            raise RecordingError(
                f"frame of {sensor!r}: the sensor is not in the recording's rig "
                f"(sensors: {self.rig.names})"
            )
        stamp = _stamp(frame.stamp_ns, sensor)
        if self._last_stamp.get(sensor) == stamp:
            self.duplicates_skipped += 1
            return False
        s = self.rig[sensor]
        messages = [  # checks everything before writing anything
            (self._channels[(sensor, kind)], msg)
            for kind, msg in frame_messages(
                frame, s, stamp, self.jpeg_quality, self.thermal_encoding
            )
        ]
        with signals_deferred():
            if self._next_calibration_ns is None or stamp >= self._next_calibration_ns:
                self._write_calibration(stamp)
            for channel, msg in messages:
                channel.log(msg, log_time=stamp)  # type: ignore[attr-defined]
            self._last_stamp[sensor] = stamp
            if time.monotonic() >= self._next_seal:
                self.seal()
        self.frames_written += 1
        self.first_ns = stamp if self.first_ns is None else min(self.first_ns, stamp)
        self.last_ns = stamp if self.last_ns is None else max(self.last_ns, stamp)
        self._notify("frame_written", frame)
        return True

    def write_pose(self, stamp_ns: int, T_world_rig: np.ndarray) -> bool:
        """Write the head's pose at a frame set's time: ``foxglove.FrameTransform`` on
        ``/tf`` with parent ``world``, child ``rig``, timestamp and log time ``stamp_ns``
        (docs/FORMATS.md, "The head's pose").

        Args:
            stamp_ns: the frame set's stamp (int nanoseconds).
            T_world_rig: (4, 4) the rig frame's pose in the world frame (metres); checked
                to be rigid.

        Returns:
            False if it repeats the last pose's stamp (skipped), else True.

        Raises RecordingError for a bad stamp or a transform that is not rigid, and
        RuntimeError after :meth:`close`.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the recording is closed")
        stamp = _stamp(stamp_ns, "the head's pose")
        problem = rigidity_problem(T_world_rig)
        if problem is not None:
            raise RecordingError(f"pose at {stamp} ns: T_world_rig: {problem}")
        T = np.asarray(T_world_rig, dtype=np.float64)
        if stamp == self._last_pose_ns:
            return False
        with signals_deferred():
            self._tf.log(transform_message(T, WORLD_FRAME, RIG_FRAME, stamp), log_time=stamp)
            self._last_pose_ns = stamp
            self.poses_written += 1
            if time.monotonic() >= self._next_seal:
                self.seal()
        return True

    def write_note(self, note: Note) -> None:
        """Write a measurement note (an alarm event, the measurement settings) on
        :data:`~app.recording.layout.MEASUREMENTS_TOPIC` at its stamp (docs/FORMATS.md
        "Measurement notes"). RuntimeError after :meth:`close`."""
        if self._closed:
            raise RuntimeError(f"{self.path}: the recording is closed")
        stamp = _stamp(note.stamp_ns, "a measurement note")
        if self._notes is None:
            self._notes = LogChannel(MEASUREMENTS_TOPIC, context=self._ctx)
        sec, nsec = divmod(stamp, 1_000_000_000)
        level = LogLevel.Warning if note.level == "warning" else LogLevel.Info
        msg = Log(
            timestamp=Timestamp(sec=sec, nsec=nsec),
            level=level,
            message=json.dumps(note.body, sort_keys=True),
            name=note.name,
            file="",
            line=0,
        )
        with signals_deferred():
            self._notes.log(msg, log_time=stamp)
            self.notes_written += 1
            if time.monotonic() >= self._next_seal:
                self.seal()

    def _notify(self, what: str, *args: object) -> None:
        """Call ``what`` of every observer; one that raises is logged and dropped."""
        for observer in list(self.observers):
            try:
                getattr(observer, what)(*args)
            except Exception:
                log.exception("%s: an observer of the recording failed; dropped", self.path)
                with contextlib.suppress(ValueError):
                    self.observers.remove(observer)

    # -- the fused video ------------------------------------------------------------------

    def add_fused_video(
        self, frame_id: str | None = None, metadata: dict[str, str] | None = None
    ) -> FusedVideoTrack:
        """Open the ``/fused/video`` track (``foxglove.CompressedVideo``, h264; once: a
        second call returns the same track).

        Args:
            frame_id: the messages' frame id (default: the left eye's colour camera,
                :func:`~app.recording.video_track.video_frame_id`).
            metadata: more channel metadata (e.g. the encoder's settings).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the recording is closed")
        if self.fused_video is None:
            self.fused_video = FusedVideoTrack(
                self._ctx, frame_id or video_frame_id(self.rig), metadata
            )
        return self.fused_video

    def write_video(self, data: bytes, key: bool, stamp_ns: int) -> bool:
        """Write one access unit of the fused video (H.264 Annex B; ``key``: an IDR with
        its SPS and PPS) taken at ``stamp_ns``; False if the track refuses it (a delta
        frame before the first key frame or after a refused unit, or a stamp not after the
        last: :meth:`FusedVideoTrack.write <app.recording.video_track.FusedVideoTrack.write>`).

        Raises RuntimeError without :meth:`add_fused_video` or after :meth:`close`,
        RecordingError for a bad stamp or data that is not Annex B.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the recording is closed")
        if self.fused_video is None:
            raise RuntimeError(f"{self.path}: no fused-video track (call add_fused_video)")
        stamp = _stamp(stamp_ns, "fused video")
        with signals_deferred():
            written = self.fused_video.write(data, bool(key), stamp)
            if written and time.monotonic() >= self._next_seal:
                self.seal()
        return written

    @property
    def video_frames_written(self) -> int:
        """Access units written to ``/fused/video`` (0 without the track)."""
        return 0 if self.fused_video is None else self.fused_video.written

    def _write_calibration(self, stamp: int) -> None:
        for name, s in self.rig.sensors.items():
            cal = calibration_message(s, stamp)
            self._channels[(name, "calibration")].log(cal, log_time=stamp)  # type: ignore[attr-defined]
            tf = transform_message(s.T_rig_sensor, RIG_FRAME, name, stamp)
            self._tf.log(tf, log_time=stamp)
        self._next_calibration_ns = stamp + self.calibration_period_ns

    def seal(self) -> None:
        """Finish the chunk in progress and put everything written so far on disk as a
        complete MCAP (done about every ``seal_period_s`` by :meth:`write`)."""
        self._mcap.flush()  # the writer flushes the file too: SealedMcapFile seals it
        self._next_seal = time.monotonic() + self.seal_period_s

    # -- finishing ------------------------------------------------------------------------

    def close(self) -> Path:
        """Finish the file and give it its name; returns the path. Idempotent.

        FileExistsError if a file of that name appeared meanwhile (the temporary file is
        removed; nothing is overwritten).
        """
        if self._closed:
            return self.path
        self._notify("closing")  # may still write (the fused video's last pictures)
        self._closed = True
        try:
            with signals_deferred():
                self._mcap.close()
                self._close_channels()
                self._file.finish()  # summary and footer over the seal, fsynced
            try:
                os.link(self.temp_path, self.path)
            except FileExistsError:
                raise FileExistsError(
                    f"{self.path}: appeared while recording; refusing to overwrite it "
                    "(the recording was discarded)"
                ) from None
            fsync_dir(self.path.parent)
        finally:
            self.temp_path.unlink(missing_ok=True)
            self._unlock()
        return self.path

    def abort(self) -> None:
        """Stop writing and remove the temporary file (no recording appears)."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self._mcap.close()
        self._close_channels()
        self.temp_path.unlink(missing_ok=True)
        self._unlock()

    def _close_channels(self) -> None:
        video = [self.fused_video.channel] if self.fused_video is not None else []
        for channel in [*self._channels.values(), self._tf, *video]:
            with contextlib.suppress(Exception):
                channel.close()  # type: ignore[attr-defined]

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None or issubclass(exc_type, KeyboardInterrupt):
            self.close()
        else:
            self.abort()

    def __del__(self) -> None:
        # An unclosed writer leaves no half-written temporary file behind.
        if not getattr(self, "_closed", True):
            with contextlib.suppress(Exception):
                self.abort()
