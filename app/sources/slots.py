"""Newest-frame slots: what live sources hand to a consumer that may be slower than them.

One slot per sensor holds its newest unread frame; a new frame replaces the unread one
(counted as dropped). A consumer never sees a backlog, only the newest frame of each
sensor, oldest stamp first.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Iterator
from typing import Any

from trifuse.app.sources.frames import Frame


class NewestFrameSlots:
    """One slot per sensor holding its newest unread frame (thread-safe).

    Producers :meth:`put` frames; a frame replaces the sensor's unread one (counted as
    dropped), so memory stays one frame per sensor however slow the consumer is. The
    consumer takes the oldest-stamped frame among the filled slots, so frames come out in
    time order per sensor and, across sensors, in time order up to the short race between
    two producers stamping and storing.

    Args:
        end_when_finished: the stream ends once every sensor's producer has called
            :meth:`finish` and the slots are empty (cameras); otherwise only :meth:`close`
            ends it (pushed frames: drivers come and go).
    """

    def __init__(self, sensors: Iterable[str], end_when_finished: bool = False) -> None:
        self.sensors = list(sensors)
        self._cond = threading.Condition()
        self._slots: dict[str, Frame | None] = dict.fromkeys(self.sensors)
        self._received = dict.fromkeys(self.sensors, 0)
        self._dropped = dict.fromkeys(self.sensors, 0)
        self._delivered = dict.fromkeys(self.sensors, 0)
        self._last_stamp: dict[str, int | None] = dict.fromkeys(self.sensors)
        self._finished: set[str] = set()
        self._end_when_finished = end_when_finished
        self._closed = False

    def put(self, frame: Frame) -> bool:
        """Store ``frame`` as its sensor's newest; True if it replaced an unread frame."""
        with self._cond:
            if frame.sensor not in self._slots:
                raise KeyError(f"unknown sensor {frame.sensor!r} (expected one of {self.sensors})")
            replaced = self._slots[frame.sensor] is not None
            if replaced:
                self._dropped[frame.sensor] += 1
            self._slots[frame.sensor] = frame
            self._received[frame.sensor] += 1
            self._last_stamp[frame.sensor] = frame.stamp_ns
            self._cond.notify_all()
            return replaced

    def finish(self, sensor: str) -> None:
        """The producer of ``sensor`` has stopped (its slot may still hold a frame)."""
        with self._cond:
            self._finished.add(sensor)
            self._cond.notify_all()

    def close(self) -> None:
        """End the stream now; waiting consumers return."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def _ended(self) -> bool:
        if self._closed:
            return True
        return (
            self._end_when_finished
            and self._finished >= set(self.sensors)
            and all(f is None for f in self._slots.values())
        )

    def take(self, timeout_s: float | None = None) -> Frame | None:
        """The oldest-stamped frame among the filled slots, emptying its slot.

        Blocks until a frame is there; returns None on timeout or when the stream ended
        (see :attr:`ended`).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while True:
                if self._closed:
                    return None
                filled = [f for f in self._slots.values() if f is not None]
                if filled:
                    frame = min(filled, key=lambda f: f.stamp_ns)
                    self._slots[frame.sensor] = None
                    self._delivered[frame.sensor] += 1
                    return frame
                if self._ended():
                    return None
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left)

    @property
    def ended(self) -> bool:
        """Whether :meth:`take` will never return a frame again."""
        with self._cond:
            return self._ended()

    def peek(self, sensor: str) -> Frame | None:
        """The unread frame of ``sensor`` (None if there is none), leaving it in place."""
        with self._cond:
            return self._slots[sensor]

    def frames(self) -> Iterator[Frame]:
        """Frames as they come (see :meth:`take`) until the stream ends."""
        while True:
            frame = self.take()
            if frame is None:
                return
            yield frame

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per sensor: frames ``received``, ``delivered``, ``dropped`` (replaced unread),
        the latest ``last_stamp_ns`` (None before any) and whether the producer ``finished``."""
        with self._cond:
            return {
                s: {
                    "received": self._received[s],
                    "delivered": self._delivered[s],
                    "dropped": self._dropped[s],
                    "last_stamp_ns": self._last_stamp[s],
                    "finished": s in self._finished,
                }
                for s in self.sensors
            }


# -- configuration --------------------------------------------------------------------------
