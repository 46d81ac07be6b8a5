"""The console's live frames in rerun (``trifuse serve --rerun [ADDRESS]``; issue 36, item 2):
the rig's cameras at their poses, each sensor's images, the TOF's points coloured by
temperature, the fused pair and, while the console builds one, the thermal map with the
head's path (:class:`app.recording.rerun_log.RerunHead`), on a rerun viewer.

The console connects to the viewer, as rerun's SDKs do (the viewer listens; by default
:data:`DEFAULT_ADDRESS`, a viewer on this machine; from another one, the viewer's address,
or ``ssh -R 9876:127.0.0.1:9876 ROBOT`` and the default): nothing more listens on the robot.

rerun's gRPC sink keeps whatever is logged while it is not connected (measured: 100 colour
images, 370 MB, with no viewer there), so the console logs only while the viewer's port
answers (a TCP probe every :data:`PROBE_S`), and connects a new sink, logging the rig
again, each time the viewer comes (back): what a viewer misses is never kept. At most
:data:`RATE_HZ` frame sets a second are logged, in a thread of its own (``rerun``, the
newest set: a slow viewer drops sets, never the fusion); while connected it keeps the
console fusing (the fused pair).
"""

from __future__ import annotations

import socket
import time
import uuid
from urllib.parse import urlsplit

from trifuse.app.errors import describe_error
from trifuse.app.latest_worker import LatestWorker
from trifuse.app.recording.rerun_log import RerunHead, require_rerun
from trifuse.app.server.runtime.map_worker import MapWorker
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import FrameSet

DEFAULT_ADDRESS = "rerun+http://127.0.0.1:9876/proxy"
"""A rerun viewer on this machine (``rerun`` listens there by default)."""
RATE_HZ = 5.0
"""Frame sets logged a second, at most."""
PROBE_S = 2.0
"""How often the viewer's port is tried, seconds."""
MAP_S = 5.0
"""How often the thermal map is logged while it grows, seconds."""
MAP_POINTS = 100_000
"""The most points of the map logged (its level of detail, as the 3D console's)."""


def viewer_endpoint(address: str) -> tuple[str, int]:
    """(host, port) of a rerun viewer's address ``rerun+http://HOST:PORT/proxy`` (or
    ``rerun+https``, ``rerun``); ValueError in one line for another."""
    parts = urlsplit(address)
    if parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname:
        raise ValueError(
            f"--rerun: expected a rerun viewer's address rerun+http://HOST:PORT/proxy, "
            f"got {address!r}"
        )
    try:
        port = parts.port or 9876
    except ValueError:
        raise ValueError(f"--rerun: the port of {address!r} is not a number") from None
    return parts.hostname, port


class RerunLive:
    """Logs the pipeline's frame sets to a rerun viewer (see the module doc).

    Args:
        pipeline: the console's pipeline (its frame sets, rig, radiometry).
        hub: its stream (the newest fused picture).
        address: the viewer's address (default :data:`DEFAULT_ADDRESS`).
        rate_hz: frame sets logged a second, at most.
        mapper: the console's thermal map (logged every :data:`MAP_S` while it grows).

    Attributes:
        connected: whether the viewer answered the last probe; ``connections``: how many
            times it came; ``logged``: frame sets logged; ``error``: the last failure,
            worded (the next set goes on).
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        hub: FrameHub,
        address: str | None = None,
        rate_hz: float = RATE_HZ,
        mapper: MapWorker | None = None,
    ) -> None:
        self.rr = require_rerun()
        self.address = address or DEFAULT_ADDRESS
        self.host, self.port = viewer_endpoint(self.address)
        self.pipeline, self.hub, self.rate_hz, self.mapper = pipeline, hub, rate_hz, mapper
        self._map_s, self._map_frames = 0.0, 0
        self.stream = self.rr.RecordingStream("trifuse", recording_id=str(uuid.uuid4()))
        self.head: RerunHead | None = None
        self.connected = False
        self.connections = self.logged = 0
        self.error: str | None = None
        self._next_s = self._probe_s = 0.0
        self._fused_seq = 0
        self._worker = LatestWorker(self._log, name="rerun", on_error=self._failed)

    def start(self) -> RerunLive:
        self.pipeline.set_listeners.append(self._on_set)
        self._worker.start()
        return self

    def stop(self) -> None:
        if self._on_set in self.pipeline.set_listeners:
            self.pipeline.set_listeners.remove(self._on_set)
        self._worker.stop()
        if self.connected:
            self.stream.flush(timeout_sec=2.0)

    def status(self) -> dict[str, object]:
        return {
            "address": self.address,
            "connected": self.connected,
            "connections": self.connections,
            "logged": self.logged,
            "error": self.error,
        }

    def _failed(self, exc: Exception) -> None:
        self.error = describe_error(exc)

    def _on_set(self, fs: FrameSet) -> None:
        """A frame set (fusion thread; never waits): handed over when one is due."""
        now = time.monotonic()
        if now >= self._next_s:
            self._next_s = now + 1.0 / self.rate_hz
            self._worker.submit(fs)

    def _reachable(self) -> bool:
        try:
            with socket.create_connection((self.host, self.port), timeout=0.5):
                return True
        except OSError:
            return False

    def _log(self, fs: FrameSet) -> None:
        """Log ``fs`` (the ``rerun`` thread) while the viewer answers."""
        now = time.monotonic()
        if now >= self._probe_s:
            self._probe_s = now + PROBE_S
            up = self._reachable()
            if up and not self.connected:  # a new sink: nothing kept from before
                self.stream.connect_grpc(self.address)
                self.head = RerunHead(
                    self.stream, self.pipeline.rig, self.pipeline.settings.palette
                )
                self.connections += 1
            self.connected = up
        if not self.connected or self.head is None:
            return
        self.pipeline.touch_demand()  # someone watches: keep fusing (the fused pair)
        rig = self.pipeline.rig
        if rig is not self.head.rig:
            self.head.set_rig(rig)
        self.head.log_frames(fs.frames, self.pipeline.radiometry)
        latest = self.hub.latest
        if latest is not None and latest.seq != self._fused_seq:
            self._fused_seq = latest.seq
            stamp = int(latest.meta.get("stamp_ns", fs.stamp_ns))
            picture = latest.jpeg if latest.jpeg is not None else latest.bgr[..., ::-1]
            self.head.log_fused(stamp, picture)
        self._log_map(fs.stamp_ns, now)
        self.logged += 1
        self.error = None

    def _log_map(self, stamp_ns: int, now: float) -> None:
        """The thermal map, the head's path and pose, when the map grew and one is due."""
        m = self.mapper
        if m is None or now < self._map_s or m.frames == self._map_frames:
            return
        self._map_s = now + MAP_S
        assert self.head is not None
        with m.lock:  # the map holds still while its points are taken
            if m.T_world_rig is None or not m.map.path:
                return
            self._map_frames = m.frames
            self.head.log_map(stamp_ns, m.map, m.T_world_rig, MAP_POINTS)
