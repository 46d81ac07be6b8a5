"""The console's thermal 3D map (issue 20): built from the live frame sets in a thread of
its own while an operator has it on.

The pipeline's frame-set listener (:attr:`FusionPipeline.set_listeners`) keeps the newest
image of every sensor (thermal images in kelvin through the pipeline's radiometry, as the
fused picture shows them) and, on each new TOF frame, leaves one job for the worker (a job
not taken yet is replaced by the newer one and counted as skipped: a busy machine maps
fewer frames, never late ones). The head's pose comes from the source when it knows it
(``source.head_pose(stamp_ns)``: the simulated head's truth, a recording's ``world ->
rig``), else from the TOF clouds (:class:`fusion.odometry.TofOdometry`).

Saved maps go to ``<workdir>/maps/`` as a map file (``.map.npz``, loadable again) and a PLY
beside it; nothing is overwritten (a name taken gets a suffix).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.latest_worker import LatestWorker
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.sources.capabilities import HeadPose
from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.map_file import MAP_SUFFIX, load_map, save_map, write_ply
from trifuse.app.storage.numbered import first_free, suffixed_names
from trifuse.fusion.map_builder import MapBuilder
from trifuse.fusion.voxel_map import MapSettings, VoxelMap


@dataclass(frozen=True)
class _Job:
    stamp_ns: int
    distance_m: np.ndarray
    amplitude: np.ndarray | None
    images: dict[str, np.ndarray]


class MapWorker:
    """Builds :attr:`builder`'s map from ``pipeline``'s frame sets (module docstring).

    Args:
        pipeline: the console's fusion pipeline (its rig, radiometry and frame sets).
        head_pose: stamp (ns) -> ``T_world_rig`` (4, 4) or None (unknown: estimated).
        maps_dir: where maps are saved and listed.
        settings: the map's settings.
        enabled: build from the start (else :meth:`set_enabled`).

    Attributes:
        lock: held while the map changes; readers (the 3D scene) hold it while copying.
        frames, skipped, failed: TOF frames mapped, dropped for a busier one, failed.
        last_ms: the last frame's cost, milliseconds (median of the last 30 in
            :meth:`status`).
        last_error: the newest failure (None: none).
        T_world_rig: the newest pose mapped (None before the first).
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        head_pose: HeadPose | None,
        maps_dir: Path,
        settings: MapSettings | None = None,
        enabled: bool = False,
    ) -> None:
        self.pipeline = pipeline
        self.head_pose = head_pose
        self.maps_dir = Path(maps_dir)
        self.lock = threading.RLock()
        self.builder = MapBuilder(pipeline.rig, settings)
        self.enabled = enabled
        self.frames = self.skipped = self.failed = 0
        self.costs_ms: list[float] = []
        self.last_error: str | None = None
        self.T_world_rig: np.ndarray | None = None
        self._images: dict[str, np.ndarray] = {}
        self._last_tof_ns: int | None = None
        self._worker = LatestWorker(self._map, name="thermal-map", on_error=self._failed)

    @property
    def map(self) -> VoxelMap:
        return self.builder.map

    def start(self) -> MapWorker:
        self.pipeline.set_listeners.append(self._on_set)
        self._worker.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        if self._on_set in self.pipeline.set_listeners:
            self.pipeline.set_listeners.remove(self._on_set)
        self._worker.stop(timeout_s)

    # -- operator actions ---------------------------------------------------------------

    def set_enabled(self, on: bool) -> None:
        """Start or stop building (the map stays)."""
        self.enabled = bool(on)

    def set_paused(self, paused: bool) -> None:
        """Pause: frames are not added (the map stays shown); resume adds them again."""
        with self.lock:
            self.builder.paused = bool(paused)

    def reset(self) -> None:
        """An empty map (the pose estimate starts again)."""
        with self.lock:
            self.builder.reset()
            self.frames = self.skipped = self.failed = 0
            self.costs_ms.clear()
            self.T_world_rig = None

    def save(self, name: str | None = None) -> tuple[Path, Path]:
        """Save the map as ``<maps_dir>/<name>.map.npz`` and a PLY beside it; a name in
        use gets a numbered suffix. Returns the paths of the map file and the PLY."""
        stem = name or datetime.now(UTC).strftime("map-%Y%m%d-%H%M%S")
        if not stem or "/" in stem or stem.startswith("."):
            raise ValueError(f"name: expected a plain file name, got {name!r}")
        self.maps_dir.mkdir(parents=True, exist_ok=True)

        def taken(s: str) -> bool:
            return (self.maps_dir / f"{s}{MAP_SUFFIX}").exists() or (
                self.maps_dir / f"{s}.ply"
            ).exists()

        stem = first_free(suffixed_names(stem), taken)
        path, ply = self.maps_dir / f"{stem}{MAP_SUFFIX}", self.maps_dir / f"{stem}.ply"
        with self.lock:
            save_map(path, self.map)
            write_ply(ply, self.map)
        return path, ply

    def saved(self) -> list[str]:
        """Names of the saved maps (newest first)."""
        if not self.maps_dir.is_dir():
            return []
        files = sorted(
            self.maps_dir.glob(f"*{MAP_SUFFIX}"), key=lambda p: p.stat().st_mtime, reverse=True
        )
        return [p.name[: -len(MAP_SUFFIX)] for p in files]

    def load(self, name: str) -> None:
        """Show the saved map ``name`` (building pauses, so that it is not mixed with
        where the head is now; Resume adds to it)."""
        if name not in self.saved():
            raise FileNotFoundError(f"no saved map named {name!r} in {self.maps_dir}")
        loaded = load_map(self.maps_dir / f"{name}{MAP_SUFFIX}")
        with self.lock:
            self.builder.reset()
            self.builder.map = loaded
            self.builder.paused = True
            self.T_world_rig = None

    def status(self) -> dict:
        """The map's figures (for ``/api/map`` and the panel)."""
        with self.lock:
            m = self.map
            occupied = int(m.occupied().sum())
            cost = float(np.median(self.costs_ms)) if self.costs_ms else None
            return {
                "enabled": self.enabled,
                "paused": self.builder.paused,
                "frames": self.frames,
                "skipped": self.skipped,
                "failed": self.failed,
                "voxels": len(m),
                "occupied": occupied,
                "voxel_m": m.settings.voxel_m,
                "memory_mb": round(m.nbytes / 1e6, 1),
                "ms_per_frame": None if cost is None else round(cost, 2),
                "pose_source": self.builder.pose_source,
                "path_points": len(m.path),
                "last_error": self.last_error,
            }

    # -- the work -----------------------------------------------------------------------

    def _on_set(self, fs: FrameSet) -> None:
        """The pipeline's listener: keep the newest images; a new TOF frame is a job."""
        if not self.enabled or self.builder.paused:
            return
        rig = self.pipeline.rig
        tof = self.builder.tof
        for name, frame in fs.frames.items():
            if name == tof or name not in rig.sensors:
                continue
            image = frame.image
            if rig[name].modality == "thermal":
                r = self.pipeline.radiometry.get(name)
                image = np.asarray(image, np.float32) if r is None else r.apply(image)
            self._images[name] = image
        frame = fs.frames.get(tof)
        if frame is None or frame.distance_m is None or frame.stamp_ns == self._last_tof_ns:
            return
        self._last_tof_ns = frame.stamp_ns
        job = _Job(frame.stamp_ns, frame.distance_m, frame.image, dict(self._images))
        if self._worker.submit(job):  # the job not taken yet is replaced
            self.skipped += 1

    def _map(self, job: _Job) -> None:
        """Add one TOF frame to the map (the worker thread)."""
        pose = self.head_pose(job.stamp_ns) if self.head_pose is not None else None
        t0 = time.perf_counter()
        with self.lock:
            if self.builder.rig is not self.pipeline.rig:  # the rig in use changed
                kept = self.builder.map
                self.builder = MapBuilder(self.pipeline.rig, kept.settings)
                self.builder.map = kept
            added = self.builder.add(
                job.stamp_ns * 1e-9, job.distance_m, job.images, pose, job.amplitude
            )
            if added is not None:
                self.frames += 1
                self.T_world_rig = (
                    pose
                    if pose is not None
                    else self.map.path[-1][1] @ np.linalg.inv(self.builder.T_rig_tof)
                )
        self.costs_ms = [*self.costs_ms[-29:], (time.perf_counter() - t0) * 1e3]

    def _failed(self, exc: Exception) -> None:
        """A frame that could not be mapped: shown in the panel; the console goes on."""
        self.failed += 1
        self.last_error = describe_error(exc)
