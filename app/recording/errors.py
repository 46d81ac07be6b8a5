"""Errors of recordings, ROS 2 bags and topic maps (all ``ValueError``: bad input)."""

from __future__ import annotations

import functools
from pathlib import Path


class RecordingError(ValueError):
    """A recording, ROS 2 bag or topic map that cannot be read or written as asked.

    The message names the file and says what was expected and what was found.
    """


class RecordingDamaged(RecordingError):
    """A recording is truncated or corrupted; everything before the damage was delivered.

    Raised by a replay source's ``frames()`` at the point of damage (after the last good
    frame), or logged there with ``on_damage="stop"``.

    Attributes:
        path: the file.
        reason: what is wrong (e.g. "chunk CRC mismatch", "the file ends in the middle of a
            chunk record: truncated").
        offset: byte offset of the damaged record, if known.
        stamp_ns: log time up to which the recording was replayed completely (None: before
            the first message).
        frames_delivered: frames delivered by the iteration that met the damage.
    """

    def __init__(
        self,
        path: str | Path,
        reason: str,
        *,
        offset: int | None = None,
        stamp_ns: int | None = None,
        start_ns: int | None = None,
        frames_delivered: int = 0,
    ) -> None:
        self.path = Path(path)
        self.reason = reason
        self.offset = offset
        self.stamp_ns = stamp_ns
        self.start_ns = start_ns
        self.frames_delivered = frames_delivered
        where = f" at byte {offset}" if offset is not None else ""
        if stamp_ns is not None and start_ns is not None:
            when = f"after {(stamp_ns - start_ns) / 1e9:.3f} s of recording, "
        else:
            when = ""
        super().__init__(
            f"{self.path}: recording damaged{where} ({when}{frames_delivered} frames "
            f"replayed before it): {reason}"
        )

    def __reduce__(self) -> tuple[object, ...]:
        """Pickled with its keyword arguments (a piece's damage comes back from a Ray task)."""
        kwargs = {
            "offset": self.offset,
            "stamp_ns": self.stamp_ns,
            "start_ns": self.start_ns,
            "frames_delivered": self.frames_delivered,
        }
        return (functools.partial(type(self), **kwargs), (self.path, self.reason))


class ImageSizeError(RecordingError):
    """An image in a recording whose header gives another size than the rig's for its
    sensor (or, without a rig, more pixels than any rig describes): refused before it is
    decoded. The message says what the image claims and what was expected."""


class TopicMapError(RecordingError):
    """A topic map (YAML) with a defect; the message names the file and the field."""
