"""The console's push source: a :class:`~app.sources.base.FrameSource` whose frames are
the ones drivers push (newest frame wins per sensor), with per-sensor counts of rejected
messages for the console's sensor health.

Messages are decoded by :mod:`app.sources.push.decode`; the WebSocket endpoint that feeds
the source is :mod:`app.sources.push.router`'s.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.decode import decode_message
from trifuse.app.sources.push.protocol import (
    DEFAULT_MAX_MESSAGE_BYTES,
    DEFAULT_MAX_PIXELS,
    PREFIX,
    MessageHeader,
    PushError,
    identify,
)
from trifuse.app.sources.slots import NewestFrameSlots
from trifuse.calib.rig import MODALITIES, Rig


class PushSource(FrameSource):
    """Frames pushed by on-robot drivers: one newest-frame slot per sensor.

    Args:
        rig: the rig whose sensors may be pushed (names, modalities, image sizes).
        sensors: without a rig: sensor name -> modality (``color``, ``thermal``, ``tof``);
            with a rig: a subset of its sensors to accept.
        image_sizes: without a rig: sensor -> (width, height) to enforce (optional).
        max_message_bytes: larger messages are rejected (default 16 MiB). The WebSocket
            server must let such messages through to be answered: run uvicorn with
            ``ws_max_size`` above this
            (:func:`~app.sources.push.router.uvicorn_ws_max_size`); beyond *its* limit
            the server closes the connection (code 1009).
        max_pixels: largest image (width * height) a part may declare.

    Attributes:
        sensors, rig: as for every source.
        modalities: sensor -> modality.
        image_sizes: sensor -> (width, height), where known.
    """

    source_kind = "push"

    def __init__(
        self,
        rig: Rig | None = None,
        *,
        sensors: Mapping[str, str] | Sequence[str] | None = None,
        image_sizes: Mapping[str, tuple[int, int]] | None = None,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_pixels: int = DEFAULT_MAX_PIXELS,
    ) -> None:
        if rig is not None:
            names = list(rig.names) if sensors is None else list(sensors)
            unknown = [s for s in names if s not in rig]
            if unknown:
                raise ValueError(f"sensors: {unknown} are not in the rig (sensors: {rig.names})")
            self.modalities = {s: rig[s].modality for s in names}
            self.image_sizes = {s: tuple(rig[s].image_size) for s in names}
        else:
            if not isinstance(sensors, Mapping) or not sensors:
                raise ValueError(
                    "sensors: without a rig, expected a mapping of sensor name -> modality"
                )
            bad = {s: m for s, m in sensors.items() if m not in MODALITIES}
            if bad:
                raise ValueError(
                    f"sensors: modalities must be one of {list(MODALITIES)}, got {bad}"
                )
            self.modalities = dict(sensors)
            self.image_sizes = {s: tuple(v) for s, v in (image_sizes or {}).items()}
            unknown = sorted(set(self.image_sizes) - set(self.modalities))
            if unknown:
                raise ValueError(f"image_sizes: {unknown} are not among the sensors")
        if max_message_bytes <= PREFIX.size:
            raise ValueError(
                f"max_message_bytes: expected > {PREFIX.size}, got {max_message_bytes}"
            )
        self.rig = rig
        self.sensors = list(self.modalities)
        self.max_message_bytes = int(max_message_bytes)
        self.max_pixels = int(max_pixels)
        self._slots = NewestFrameSlots(self.sensors)
        self._lock = threading.Lock()
        self._rejected = 0
        self._connections = 0
        self._last_error = ""
        # per known sensor: [rejected, since_accepted, last_error, last_rejected_s, accepted_s]
        self._by_sensor: dict[str, list[Any]] = {s: [0, 0, "", None, None] for s in self.sensors}

    # -- decoding -----------------------------------------------------------------------

    def decode(self, data: bytes | bytearray | memoryview) -> tuple[MessageHeader, Frame]:
        """Validate and decode one message into a Frame (not stored). Raises PushError."""
        return decode_message(
            data,
            self.modalities,
            self.image_sizes,
            max_message_bytes=self.max_message_bytes,
            max_pixels=self.max_pixels,
        )

    def accept(
        self, data: bytes | bytearray | memoryview, last_stamps: dict[str, int] | None = None
    ) -> tuple[MessageHeader, Frame, bool]:
        """Decode one message and store its frame as the sensor's newest.

        ``last_stamps`` (per connection: sensor -> latest accepted stamp) rejects a frame
        not newer than the previous one of its sensor on the same connection. Returns the
        header, the frame, and whether it replaced an unread frame. Raises PushError (the
        message is then counted as rejected and nothing is stored).
        """
        if self._slots.closed:
            raise PushError("the console's push source is closed")
        try:
            header, frame = self.decode(data)
            if last_stamps is not None:
                prev = last_stamps.get(frame.sensor)
                if prev is not None and frame.stamp_ns <= prev:
                    raise PushError(
                        f"sensor {frame.sensor!r}: stamp_ns {frame.stamp_ns} is not after the "
                        f"previous frame's {prev} on this connection"
                    )
                last_stamps[frame.sensor] = frame.stamp_ns
        except PushError as exc:
            sensor = identify(data).get("sensor")
            with self._lock:
                self._rejected += 1
                self._last_error = str(exc)
                entry = self._by_sensor.get(sensor) if isinstance(sensor, str) else None
                if entry is not None:  # counted per sensor only for this console's sensors
                    entry[0] += 1
                    entry[1] += 1
                    entry[2] = str(exc)
                    entry[3] = time.monotonic()
            raise
        replaced = self._slots.put(frame)
        with self._lock:
            entry = self._by_sensor[frame.sensor]
            entry[1] = 0
            entry[4] = time.monotonic()
        return header, frame, replaced

    # -- the stream ---------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        """Pushed frames as they come: each sensor's newest, oldest stamp first; a slow
        consumer skips frames (newest wins). Ends on :meth:`close`."""
        return self._slots.frames()

    def take(self, timeout_s: float | None = None) -> Frame | None:
        """One frame, or None on timeout or after :meth:`close`."""
        return self._slots.take(timeout_s)

    def peek(self, sensor: str) -> Frame | None:
        """The unread newest frame of ``sensor``, left in place (None if none)."""
        return self._slots.peek(sensor)

    def stats(self) -> dict[str, Any]:
        """``sensors`` (per sensor received/delivered/dropped/last stamp), ``rejected``
        messages, open ``connections``, the ``last_error``, and ``rejected_by_sensor``: per
        sensor of this console, messages ``rejected``, rejected ``since_accepted`` (its
        last accepted frame), its ``last_error`` and the ``time.monotonic()`` seconds of
        the ``last_rejected_s`` and ``last_accepted_s`` messages (None before any)."""
        with self._lock:
            return {
                "sensors": self._slots.stats(),
                "rejected": self._rejected,
                "connections": self._connections,
                "last_error": self._last_error,
                "rejected_by_sensor": {
                    s: {
                        "rejected": e[0],
                        "since_accepted": e[1],
                        "last_error": e[2],
                        "last_rejected_s": e[3],
                        "last_accepted_s": e[4],
                    }
                    for s, e in self._by_sensor.items()
                },
            }

    def count_connection(self, delta: int) -> None:
        """A WebSocket connection opened (+1) or closed (-1)."""
        with self._lock:
            self._connections += delta

    @property
    def closed(self) -> bool:
        return self._slots.closed

    def close(self) -> None:
        """End the stream; later messages are rejected and connections closed."""
        self._slots.close()
