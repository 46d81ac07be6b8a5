"""The recording's fused video in the console: the pictures the stream publishes, encoded as
H.264 for a :class:`~trifuse.app.recording.recorder.Recorder`.

When a recording keeps the fused video (the Source panel's "Record fused video",
:attr:`trifuse.app.server.runtime.source_control.SourceControl.fused_video`), the fused
pictures the console publishes (``StreamFrame.bgr``, handed over by the hub as each frame
is published) are encoded in a worker thread
(:class:`trifuse.app.recording.video_track.FusedVideoEncoder`) and the access units go
through the recorder's queue to ``/fused/video``. The tap holds the fusion's demand (the
console fuses while it records) and never slows the pipeline: a picture waits in a short
inbox (:class:`~trifuse.app.latest_worker.LatestWorker`), the oldest dropped and counted
when the encoder falls behind; every picture it encodes reaches the writer (the P-frame
chain stays whole). A failure of the video is logged and shown in the recording state; the
sensor recording goes on without video.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.latest_worker import LatestWorker
from trifuse.app.recording.video_track import FusedVideoEncoder, VideoSettings, VideoUnit
from trifuse.app.server.runtime.demand import Demand, Hold
from trifuse.app.server.runtime.stream import FrameHub, StreamFrame

log = logging.getLogger(__name__)

VIDEO_INBOX = 3
"""Pictures waiting for the fused-video encoder at most (a burst of the pipeline's)."""


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

    def open(self, deliver: Callable[[VideoUnit], bool]) -> FusedVideoTap:
        """A running :class:`FusedVideoTap` handing its units to ``deliver`` (a
        :class:`~trifuse.app.recording.recorder.VideoFeed`)."""
        return FusedVideoTap(self, deliver).start()


class FusedVideoTap(LatestWorker[tuple[np.ndarray, int]]):
    """Encodes the pictures a :class:`FrameHub` publishes, in a thread of its own (it is a
    :class:`~trifuse.app.latest_worker.LatestWorker`), and hands each access unit to
    ``deliver`` (see the module doc).

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
        encoded: pictures encoded and delivered; ``error``: why the tap stopped, or None.
    """

    def __init__(self, source: FusedVideoSource, deliver: Callable[[VideoUnit], bool]) -> None:
        super().__init__(
            self._encode,
            name="recorder-video",
            keep=VIDEO_INBOX,
            on_error=self._fail,
            finish_on_stop=True,
        )
        self.source, self._deliver = source, deliver
        self.encoder = FusedVideoEncoder(source.settings)
        self.encoded = 0
        self.error: str | None = None
        self._last_bgr: np.ndarray | None = None  # the last picture taken (publishing thread)
        self._lock = threading.Lock()  # the hub's takers and the hold, released once
        self._hold: Hold | None = None
        self._taking = False
        self._ended = False  # delivered its last unit (a failure, or deliver said stop)

    @property
    def passed_over(self) -> int:
        """New pictures dropped from the inbox (the encoder was behind)."""
        return self.dropped

    def start(self) -> FusedVideoTap:
        """Take pictures from now on (frames carry them; the console fuses)."""
        with self._lock:
            if self.source.demand is not None:
                self._hold = self.source.demand.hold()
            self.source.hub.takers.append(self._take)
            self._taking = True
        return super().start()

    def _take(self, frame: StreamFrame) -> None:
        """A frame published (the publishing thread: quick, never blocks)."""
        bgr, stamp = frame.bgr, frame.meta.get("stamp_ns")
        if bgr is None or bgr is self._last_bgr or not isinstance(stamp, int):
            return  # no picture, or a repeat of the last one
        self._last_bgr = bgr
        self.submit((bgr, stamp))

    def request_key(self) -> None:
        """Make the next picture a key frame (the recording began a new file)."""
        self.encoder.request_key()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Take no more pictures, encode and deliver those waiting, end the thread, release
        the hub and the demand. Idempotent."""
        self._release()
        super().stop(timeout_s)
        if not self.alive:
            self.encoder.close()

    def _release(self) -> None:
        with self._lock:
            if self._taking:
                self._taking = False
                with contextlib.suppress(ValueError):
                    self.source.hub.takers.remove(self._take)
            hold, self._hold = self._hold, None
        if hold is not None:
            hold.release()

    def _encode(self, item: tuple[np.ndarray, int]) -> None:
        """Encode one picture and deliver it (the tap's thread); nothing once ended."""
        if self._ended:
            return
        unit = self.encoder.encode(*item)
        if not self._deliver(unit):
            self._end()
            return
        self.encoded += 1

    def _fail(self, exc: Exception) -> None:
        """The encoder or a picture failed: the sensor recording goes on without video."""
        self.error = describe_error(exc)
        log.error("the recording's fused video stopped: %s", self.error)
        self._end()

    def _end(self) -> None:
        """No more pictures: release the hub and the demand, and the encoder."""
        self._ended = True
        self._release()
        self.encoder.close()
