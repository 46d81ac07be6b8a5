"""What a :class:`~app.sources.base.FrameSource` can do beyond yielding frames, declared as
small protocols, and the one-line questions the console asks of a source.

A source satisfies a protocol by having its members (no registration): a recording being
replayed has :class:`ReplayControls` and :class:`NotedSource`, the simulated head and a
recording with ``world -> rig`` transforms are :class:`PosedSource`, cameras are
:class:`DeviceStatusSource`. What a source *is* (:data:`SourceKind`) it declares in its class
attribute ``source_kind``. The console never probes a source with ``getattr``: it asks the
functions at the end of this module.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

SourceKind = Literal["simulated", "replay", "live", "push"]
"""What a source is: a simulated head, a recording (or ROS 2 bag) replayed, live devices, or
frames pushed to ``/ingest``."""

HeadPose = Callable[[int], np.ndarray | None]
"""stamp (ns) -> ``T_world_rig`` (4, 4) float64 of the head at that stamp, or None (unknown)."""


class KindedSource(Protocol):
    """Every :class:`~app.sources.base.FrameSource`: its class declares ``source_kind``
    (``live`` unless it says otherwise)."""

    @property
    def source_kind(self) -> SourceKind:
        """What the source is."""


@runtime_checkable
class PosedSource(Protocol):
    """A source that knows where the head was: the simulated head (its ground truth), a
    recording with ``world -> rig`` transforms."""

    def head_pose(self, stamp_ns: int) -> np.ndarray | None:
        """(4, 4) ``T_world_rig`` at ``stamp_ns`` (ns), or None if unknown there."""


@runtime_checkable
class ReplayControls(Protocol):
    """A recording being replayed (:class:`~app.recording.player.MessageReplay`): its time
    line in log-time nanoseconds, pause, seek and speed."""

    @property
    def start_ns(self) -> int:
        """Log time of the first message (ns)."""

    @property
    def duration_s(self) -> float:
        """Seconds from the first to the last message."""

    @property
    def position_ns(self) -> int:
        """Log time of the last frame delivered, or where a seek will continue (ns)."""

    @property
    def paused(self) -> bool:
        """Held by :meth:`pause`."""

    rate: float
    """Playback speed (1.0 = real time); settable."""

    def pause(self) -> None:
        """Hold the stream before its next frame."""

    def resume(self) -> None:
        """Continue after :meth:`pause`."""

    def seek(self, position: float) -> int:
        """Continue from ``position`` (int: log time in ns; float: fraction of the
        duration); returns the target log time (ns)."""

    @property
    def dropped(self) -> dict[str, int]:
        """Sensor -> frames dropped to keep real time (a consumer too slow for them)."""

    def stats(self) -> dict[str, Any]:
        """Skipped messages in the shape of :class:`RejectionStats`."""


class RejectionStats(Protocol):
    """A source that counts the messages it rejected, per sensor (the push ingest; a replay's
    skipped messages): ``stats()["rejected_by_sensor"]`` is ``{sensor: {"since_accepted",
    "last_rejected_s", "last_error", ...}}``. Not runtime-checkable: cameras and the
    simulated head have a ``stats()`` of another shape; the console selects by
    :data:`SourceKind` (``push``, ``replay``)."""

    def stats(self) -> dict[str, Any]:
        """Counters; ``rejected_by_sensor`` as above."""


class DeviceState(Protocol):
    """One device's state (:class:`~app.sources.camera.DeviceStatus`)."""

    state: str
    reason: str


@runtime_checkable
class DeviceStatusSource(Protocol):
    """A source reading devices, each of which may fail or stop (cameras)."""

    def status(self) -> Mapping[str, DeviceState]:
        """Per sensor, its device's state."""


@runtime_checkable
class NotedSource(Protocol):
    """A source with non-fatal findings from opening it (a damaged summary, missing
    topics)."""

    notes: list[str]


# -- the questions the console asks -------------------------------------------------------


def kind_of(source: KindedSource) -> SourceKind:
    """The kind ``source`` declares (:attr:`~app.sources.base.FrameSource.source_kind`)."""
    return source.source_kind


def head_pose_of(source: object) -> HeadPose | None:
    """``source.head_pose`` if it has one (:class:`PosedSource`), else None."""
    return source.head_pose if isinstance(source, PosedSource) else None


def replay_controls(source: KindedSource) -> ReplayControls | None:
    """``source`` if it is a replay (its kind is ``replay``), else None."""
    return source if kind_of(source) == "replay" else None  # type: ignore[return-value]


def device_states(source: object) -> dict[str, tuple[str, str]]:
    """``{sensor: (state, reason)}`` of a :class:`DeviceStatusSource`; ``{}`` for any other
    source or if asking fails (a device thread in the middle of failing)."""
    devices: dict[str, tuple[str, str]] = {}
    if isinstance(source, DeviceStatusSource):
        with contextlib.suppress(Exception):
            for name, d in source.status().items():
                devices[name] = (str(d.state), str(d.reason))
    return devices


def notes_of(source: object) -> list[str]:
    """The findings of a :class:`NotedSource` (``[]`` for any other source)."""
    return list(source.notes or []) if isinstance(source, NotedSource) else []
