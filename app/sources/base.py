"""The source interface every producer of sensor frames implements, and the grouping of
frames that arrive at different rates into frame sets.

A :class:`FrameSource` yields single :class:`Frame` objects in time order (a simulated
head, a recording being replayed, cameras, frames pushed by an on-robot driver). A
:class:`FrameSetAssembler` groups them: each frame of the *reference* sensor (by default
the fastest, a colour camera at 30 Hz) opens a frame set, which takes for every other
sensor its frame nearest in time within ``tolerance_s``. A sensor without such a frame is
reported in ``FrameSet.missing`` with the reason (never seen, or how old its latest frame
is) and never blocks the others. When the reference sensor itself stops, a *fallback*
sensor (the other colour camera) opens the sets until it comes back. When time goes back by
more than :data:`TIME_BACK_S` (a replay that loops or is sought back), the sets still
waiting are emitted and the frames kept so far are forgotten: the new time line's sets wait
for its own frames.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from typing import ClassVar

from trifuse.app.sources.capabilities import SourceKind
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.calib.rig import Rig


class FrameSource(ABC):
    """A time-ordered stream of single sensor frames.

    Attributes:
        sensors: names of the sensors this source can deliver.
        rig: the rig the frames belong to, when the source knows it (a recording carries
            its calibration; a simulated head its ground truth), else None.
        source_kind: what the source is (:data:`~app.sources.capabilities.SourceKind`);
            what else it can do it declares through the protocols of
            :mod:`app.sources.capabilities`.
        realtime: frames come at the sensors' own pace (devices, pushed frames, a
            simulated head or a replay in real time): a late consumer gets newer frames,
            so what it makes depends on its timing anyway. False: every frame, as fast as
            it is taken (a replay read as fast as possible): the console then makes exactly
            the pictures ``trifuse fuse`` makes (it maps every TOF frame before the next
            picture instead of aside, :attr:`fusion.stereo_step.DepthFeed.submit`).
    """

    sensors: list[str]
    rig: Rig | None = None
    realtime: bool = True
    source_kind: ClassVar[SourceKind] = "live"

    @abstractmethod
    def frames(self) -> Iterator[Frame]:
        """Frames in time order. Live sources block until the next frame arrives and drop
        frames the consumer was too slow for; the iterator ends when the stream does."""

    def close(self) -> None:
        """Release devices, files and threads (idempotent); nothing to release here."""
        return None

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


TIME_BACK_S = 1.0
"""A frame this much older than the newest seen starts a new time line (no device's frames
arrive a second late; a replay's loop or a seek back does that)."""


class FrameSetAssembler:
    """Groups frames of several sensors, arriving at their own rates, into frame sets.

    Args:
        sensors: the sensors expected in every frame set.
        reference: the sensor whose frames open a frame set (default: the first).
        tolerance_s: the largest time difference between the reference frame and another
            sensor's frame in the same set.
        history: frames kept per sensor to search for the nearest one.
        fallback: the sensor whose frames open the sets while the reference is silent: its
            frames do once more than ``fallback_after_s`` (in frame time) and more than
            :attr:`FALLBACK_FRAMES` of its frames have passed since the reference's latest
            frame (or since the first frame of any sensor, if the reference never came).
            None: without the reference no set is made.
        fallback_after_s: see ``fallback``.
    """

    FALLBACK_FRAMES = 3
    """Fallback frames since the reference's last one before the fallback opens sets (a
    seek or a late reference frame does not switch)."""

    def __init__(
        self,
        sensors: Iterable[str],
        reference: str | None = None,
        tolerance_s: float = 0.05,
        history: int = 8,
        fallback: str | None = None,
        fallback_after_s: float = 0.5,
    ) -> None:
        self.sensors = list(sensors)
        if not self.sensors:
            raise ValueError("sensors: expected at least one sensor name")
        self.reference = reference or self.sensors[0]
        if self.reference not in self.sensors:
            raise ValueError(f"reference: {self.reference!r} is not one of {self.sensors}")
        if tolerance_s <= 0:
            raise ValueError(f"tolerance_s: expected a positive number, got {tolerance_s}")
        if fallback is not None and (fallback not in self.sensors or fallback == self.reference):
            raise ValueError(
                f"fallback: {fallback!r} is not one of {self.sensors} other than the reference"
            )
        self.tolerance_ns = int(tolerance_s * 1e9)
        self.fallback = fallback
        self.fallback_after_ns = int(fallback_after_s * 1e9)
        self._recent: dict[str, deque[Frame]] = {s: deque(maxlen=history) for s in self.sensors}
        self._pending: deque[Frame] = deque()
        self._last_ref_ns: int | None = None  # the reference's latest stamp (or the first frame's)
        self._since_ref = 0  # fallback frames since then
        self._newest_ns: int | None = None  # the newest stamp of any sensor

    @classmethod
    def stereo(cls, sensors: Sequence[str], tolerance_s: float = 0.05) -> FrameSetAssembler:
        """The console's grouping for the stereo picture: ``sensors`` in the order of
        :attr:`fusion.stereo_step.StereoStep.sensors` (left colour camera, right colour
        camera, ...); the left colour camera opens the sets, the right one while the left
        is silent."""
        return cls(sensors, reference=sensors[0], tolerance_s=tolerance_s, fallback=sensors[1])

    def push(self, frame: Frame) -> list[FrameSet]:
        """Add one frame; returns the frame sets that are complete now (possibly none).

        A reference frame's set is emitted once every other sensor has a frame at or after
        its time, or once the reference's *next* frame arrives (late sensors are then
        reported missing): sets are never held back by a dead sensor. While the reference
        is silent, the ``fallback`` sensor's frames open the sets instead.
        """
        if frame.sensor not in self._recent:
            return []  # a sensor this consumer does not use
        out = []
        newest = self._newest_ns
        if newest is not None and newest - frame.stamp_ns > TIME_BACK_S * 1e9:
            out = self.flush()  # the old time line's waiting sets, then a new one
            for recent in self._recent.values():
                recent.clear()
            self._last_ref_ns, self._since_ref, newest = None, 0, None
        self._newest_ns = frame.stamp_ns if newest is None else max(newest, frame.stamp_ns)
        self._recent[frame.sensor].append(frame)
        if self._last_ref_ns is None:
            self._last_ref_ns = frame.stamp_ns
        if frame.sensor == self.reference:
            self._last_ref_ns, self._since_ref = frame.stamp_ns, 0
            self._pending.append(frame)
        elif frame.sensor == self.fallback:
            self._since_ref += 1
            if (
                self._since_ref > self.FALLBACK_FRAMES
                and frame.stamp_ns - self._last_ref_ns > self.fallback_after_ns
            ):
                self._pending.append(frame)
        while self._pending:
            ref = self._pending[0]
            newer_ref = len(self._pending) > 1
            if not newer_ref and not self._all_caught_up(ref.stamp_ns):
                break
            self._pending.popleft()
            out.append(self._assemble(ref))
        return out

    def flush(self) -> list[FrameSet]:
        """Emit the sets still waiting (end of stream)."""
        out = [self._assemble(ref) for ref in self._pending]
        self._pending.clear()
        return out

    def _all_caught_up(self, stamp_ns: int) -> bool:
        return all(
            self._recent[s] and self._recent[s][-1].stamp_ns >= stamp_ns
            for s in self.sensors
            if s != self.reference
        )

    def _assemble(self, ref: Frame) -> FrameSet:
        fs = FrameSet(ref.stamp_ns, {ref.sensor: ref})
        for s in self.sensors:
            if s == ref.sensor:
                continue
            recent = self._recent[s]
            if not recent:
                fs.missing[s] = "no frame received yet"
                continue
            best = min(recent, key=lambda f: abs(f.stamp_ns - ref.stamp_ns))
            dt = best.stamp_ns - ref.stamp_ns
            if abs(dt) <= self.tolerance_ns:
                fs.frames[s] = best
            else:
                latest = recent[-1]
                age = (ref.stamp_ns - latest.stamp_ns) / 1e9
                fs.missing[s] = (
                    f"no frame within {self.tolerance_ns / 1e6:.0f} ms "
                    f"(nearest {dt / 1e6:+.0f} ms, latest {age:.2f} s old)"
                )
        return fs


def frame_sets(
    source: FrameSource,
    sensors: Iterable[str] | None = None,
    reference: str | None = None,
    tolerance_s: float = 0.05,
) -> Iterator[FrameSet]:
    """The frame sets of a source (see :class:`FrameSetAssembler`)."""
    assembler = FrameSetAssembler(sensors or source.sensors, reference, tolerance_s)
    for frame in source.frames():
        yield from assembler.push(frame)
    yield from assembler.flush()
