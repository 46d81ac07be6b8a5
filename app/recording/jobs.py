"""Offline jobs over many recordings (``trifuse fuse``, ``trifuse map``), run here or on a
Ray cluster by the same code.

A job is a list of pieces (:mod:`app.recording.pieces`) and a task function that turns one
piece into an iterable of results (:func:`fuse_task`: fused pictures then the piece's end;
:func:`map_task`: the piece's map). A runner runs the tasks and hands their results back
in the order of the pieces; the job's writer (:class:`app.recording.fuse.FusedWriter`, the
map's merge) takes them in that order on this machine. So:

* :class:`LocalRunner` runs the tasks here, one after the other, lazily: the pictures are
  written as they are fused.
* :class:`RayRunner` sends them to Ray (``ray.init`` of this machine, or of a cluster's
  address): one CPU per task, at most two tasks per CPU of the cluster queued, their results
  taken in order. A task whose worker dies (a node lost, a process killed) is run again by
  Ray (:data:`MAX_RETRIES` times); only the driver writes, and each piece's results are
  taken once, so nothing is written twice. A task that raises (bad data) stops the job with
  that error: it would fail again.

Either way the output is the same bytes: the pieces are the same, each is computed from its
piece alone, and the writer numbers and joins in piece order.

Data locality: tasks open the recordings by their absolute path (:func:`app.recording.
pieces.open_task_recording`); every node must see them there (a shared file system, or an
object store mounted at that path). Object store URLs are not read directly.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
import logging
import os
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from trifuse.app.progress_actor import JobTracker
from trifuse.app.recording.fuse import (
    FusedFrame,
    FusedWriter,
    FuseResult,
    PieceEnd,
    fuse_piece,
    video_fps,
)
from trifuse.app.recording.map3d import MAX_IMAGE_AGE_S, MapRun, choose_poses, map_piece
from trifuse.app.recording.pieces import (
    FusePiece,
    MapPiece,
    open_task_recording,
    plan_fuse,
    plan_map,
    warmup_s,
)
from trifuse.app.recording.reader import ReplaySource
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.geometry import tof_sensor_name
from trifuse.fusion.stereo import EYE_ORDER
from trifuse.fusion.voxel_map import MapSettings

T = TypeVar("T")
R = TypeVar("R")

Progress = Callable[[int, int | None], None]
"""``progress(done, total or None)`` of a whole job (units: the tasks' own)."""

MAX_RETRIES = 3
"""Times Ray runs a task again after its worker died."""
REPORT_INTERVAL_S = 0.25
"""How often a Ray task reports its progress, and the driver looks, seconds."""

RAY_EXTRA = "pip install -e '.[ray]'"


class Runner(Protocol):
    """Runs a job's tasks, handing their results back in order."""

    name: str

    def run(
        self,
        fn: Callable[[T, Callable[[int], None]], Iterable[R]],
        tasks: Sequence[T],
        expected: Sequence[int | None],
        progress: Progress | None = None,
    ) -> Iterator[Iterable[R]]:
        """``fn(task, report)`` for each task, in order: ``report(done)`` says how far the
        task is (in the units of ``expected``, the task's total, None if unknown)."""
        ...


class JobProgress:
    """A whole job's progress from its tasks' reports (each task's latest count counts,
    so a task run again starts its share again instead of counting twice)."""

    def __init__(self, expected: Sequence[int | None], progress: Progress | None) -> None:
        known = [e for e in expected if e is not None]
        self.total = sum(known) if len(known) == len(expected) else None
        self.done: dict[int, int] = {}
        self.progress = progress

    def report(self, task: int, done: int) -> None:
        self.done[task] = done
        if self.progress is not None:
            self.progress(sum(self.done.values()), self.total)


class LocalRunner:
    """Runs the tasks in this process, one after the other (results are lazy iterables:
    a task runs while its results are taken)."""

    name = "local"

    def run(
        self,
        fn: Callable[[T, Callable[[int], None]], Iterable[R]],
        tasks: Sequence[T],
        expected: Sequence[int | None],
        progress: Progress | None = None,
    ) -> Iterator[Iterable[R]]:
        job = JobProgress(expected, progress)
        for i, task in enumerate(tasks):
            yield fn(task, lambda done, i=i: job.report(i, done))


def import_ray() -> Any:
    """The ``ray`` module, or ImportError saying how to install the extra."""
    try:
        import ray
    except ImportError as exc:
        raise ImportError(
            f"--ray needs Ray, an optional extra: {RAY_EXTRA} (or pip install 'ray>=2.40'); "
            f"without --ray the job runs on this machine ({exc})"
        ) from None
    return ray


def version() -> str:
    """trifuse's installed version (a cluster's nodes must run the same)."""
    return importlib.metadata.version("trifuse")


@functools.cache
def _remote(ray: Any) -> tuple[Any, Any]:
    """The Ray task and the progress actor's class, made once per process."""
    task = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)(_ray_task)
    return task, ray.remote(num_cpus=0)(JobTracker)


def _ray_task(
    fn: Callable[[Any, Callable[[int], None]], Iterable[Any]],
    task: Any,
    number: int,
    tracker: Any,
    driver_version: str,
) -> list[Any]:
    """What a Ray worker runs: ``fn(task)`` to the end, reporting its progress."""
    import socket

    import cv2
    import ray

    if version() != driver_version:
        raise RuntimeError(
            f"{socket.gethostname()} runs trifuse {version()}, the job's machine "
            f"{driver_version}: install the same version on every node"
        )
    cv2.setNumThreads(1)  # one CPU per task: OpenCV's own threads would compete
    host, pid = socket.gethostname(), os.getpid()
    last = [0.0]

    def report(done: int) -> None:
        now = time.monotonic()
        if now - last[0] >= REPORT_INTERVAL_S:
            last[0] = now
            tracker.report.remote(number, done, host, pid)

    ray.get(tracker.report.remote(number, 0, host, pid))  # known before the task can die
    return list(fn(task, report))


def _init_on_loopback(ray: Any, **options: Any) -> None:
    """``ray.init`` of a new single-node instance whose every port listens on 127.0.0.1.

    Ray's servers (GCS, raylet, agents, workers, the driver's) listen on every interface
    unless the node's address is 127.0.0.1, and ``ray.init`` replaces 127.0.0.1 with the
    machine's reachable address except in Ray's single-node mode
    (``ray._private.ray_constants.ENABLE_RAY_CLUSTER`` false, as on Windows and macOS; its
    variable ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` counts only before Ray is imported).
    The mode is on while the instance starts and put back after (a later job's driver in
    this process may have to be reachable from a cluster). Every node must then be at
    127.0.0.1, else the instance is shut down and RuntimeError raised: a Ray version that
    changed this would otherwise listen on every interface unnoticed.

    Args:
        ray: the ``ray`` module.
        options: ``ray.init``'s other arguments (``address`` is ``local``).
    """
    constants = importlib.import_module("ray._private.ray_constants")
    before = constants.ENABLE_RAY_CLUSTER
    constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(address="local", **options)
    finally:
        constants.ENABLE_RAY_CLUSTER = before
    addresses = {node["NodeManagerAddress"] for node in ray.nodes()}
    if addresses != {"127.0.0.1"}:
        ray.shutdown()
        raise RuntimeError(
            f"Ray's local instance took the address {sorted(addresses)}, not 127.0.0.1: it "
            "would listen on every interface; this Ray version needs another way to keep it "
            "on loopback"
        )


class RayRunner:
    """Runs the tasks as Ray tasks (see the module docstring).

    Args:
        address: a running cluster's address (``HOST:PORT``, ``ray://HOST:PORT`` or
            ``auto``), or None: a new Ray instance on this machine, with ``num_cpus``
            (default: all), every port of it on loopback only (:func:`_init_on_loopback`).
        num_cpus: CPUs of the local instance.
        on_worker: called with ``(task number, host, pid)`` when a task reports from a
            worker it had not reported from (its first run, or a run again after its
            worker was lost): diagnostics; the tests kill that worker.

    Raises:
        ImportError: Ray is not installed (the ``[ray]`` extra).
    """

    def __init__(
        self,
        address: str | None = None,
        num_cpus: int | None = None,
        on_worker: Callable[[int, str, int], None] | None = None,
    ) -> None:
        self.ray = ray = import_ray()
        self.name = f"Ray at {address}" if address else "Ray on this machine"
        self.on_worker = on_worker
        self._started = False
        if not ray.is_initialized():
            quiet = {"log_to_driver": False, "logging_level": logging.WARNING}
            if address:
                ray.init(address=address, **quiet)
            else:
                _init_on_loopback(ray, num_cpus=num_cpus, include_dashboard=False, **quiet)
            self._started = True
        self.cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._tracker: Any = None

    def close(self) -> None:
        """Shut down the Ray instance this runner started (a cluster it joined stays)."""
        if self._tracker is not None:
            self.ray.kill(self._tracker)
            self._tracker = None
        if self._started:
            self.ray.shutdown()
            self._started = False

    def __enter__(self) -> RayRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(
        self,
        fn: Callable[[T, Callable[[int], None]], Iterable[R]],
        tasks: Sequence[T],
        expected: Sequence[int | None],
        progress: Progress | None = None,
    ) -> Iterator[Iterable[R]]:
        ray = self.ray
        task, tracker_class = _remote(ray)
        if self._tracker is None:
            self._tracker = tracker_class.remote()
        tracker = self._tracker
        ray.get(tracker.reset.remote())
        job = JobProgress(expected, progress)
        seen: set[tuple[int, str, int]] = set()
        taken: set[int] = set()
        window = 2 * self.cpus
        queued: deque[tuple[int, Any]] = deque()
        submitted = 0
        try:
            while queued or submitted < len(tasks):
                while submitted < len(tasks) and len(queued) < window:
                    ref = task.remote(fn, tasks[submitted], submitted, tracker, version())
                    queued.append((submitted, ref))
                    submitted += 1
                number, ref = queued[0]
                ready, _ = ray.wait([ref], timeout=REPORT_INTERVAL_S)
                done, workers = ray.get(tracker.snapshot.remote())
                for k, ran in workers.items():
                    for host, pid in ran:
                        if (k, host, pid) not in seen:
                            seen.add((k, host, pid))
                            if self.on_worker is not None:
                                self.on_worker(k, host, pid)
                for k, n in done.items():
                    if k not in taken and job.done.get(k) != n:
                        job.report(k, n)
                if not ready:
                    continue
                queued.popleft()
                result = self._result(ref, number)
                taken.add(number)
                final = expected[number]
                job.report(number, final if final is not None else done.get(number, 0))
                yield result
        finally:
            for _, ref in queued:
                ray.cancel(ref, force=True)

    def _result(self, ref: Any, number: int) -> list[Any]:
        """The task's results; its own error (e.g. a recording that cannot be read) as
        raised in the task, a worker lost more often than Ray retries as RuntimeError."""
        ray = self.ray
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = exc.cause
            if isinstance(cause, ImportError):
                raise RuntimeError(
                    f"piece {number}: a node cannot import what the task needs ({cause}): "
                    f"install trifuse {version()} (and its dependencies) on every node"
                ) from None
            if isinstance(cause, Exception):
                raise cause from None
            raise
        except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as exc:
            raise RuntimeError(
                f"piece {number}: its worker was lost {MAX_RETRIES + 1} times ({exc}); "
                "nothing of it was written"
            ) from None


# -- the tasks --------------------------------------------------------------------------


@dataclass(frozen=True)
class FuseTask:
    """One piece of a fusion job and how to fuse it."""

    piece: FusePiece
    rig: Rig
    settings: DisplaySettings
    every: int


def fuse_task(task: FuseTask, report: Callable[[int], None]) -> Iterator[FusedFrame | PieceEnd]:
    """The piece's pictures then its end (:func:`app.recording.fuse.fuse_piece`)."""
    with open_task_recording(task.piece.recording) as src:
        yield from fuse_piece(src, task.rig, task.piece, task.settings, task.every, report)


@dataclass(frozen=True)
class MapTask:
    """One piece of a map job and how to build it."""

    piece: MapPiece
    rig: Rig
    settings: MapSettings
    estimate: bool


def map_task(task: MapTask, report: Callable[[int], None]) -> list[MapRun]:
    """The piece's map (:func:`app.recording.map3d.map_piece`)."""
    return [map_piece(task.piece, task.rig, task.settings, task.estimate, report)]


# -- the jobs ---------------------------------------------------------------------------


@dataclass
class FuseOutput:
    """One recording of a fusion job: where its pictures go and how it splits.

    Attributes:
        recording: the recording.
        out_dir: the directory its pictures go to (exists, empty).
        rig: the rig it is fused with.
        fps: its video's frame rate.
        pieces: its pieces, in order.
    """

    recording: Path
    out_dir: Path
    rig: Rig
    fps: float
    pieces: list[FusePiece]


def plan_fuse_job(
    jobs: Sequence[tuple[Path, Path]],
    rig: Rig | None,
    settings: DisplaySettings,
    every: int,
    chunk_s: float,
) -> list[FuseOutput]:
    """Plan the fusion of ``(recording, out_dir)`` pairs: each recording with ``rig``, or
    the rig it holds (ValueError if it holds none), split by :func:`app.recording.pieces.
    plan_fuse` (``chunk_s`` seconds per piece; 0: one piece per recording)."""
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    planned = []
    for recording, out_dir in jobs:
        with ReplaySource(recording, realtime=False) as src:
            use = rig or src.rig
            if use is None:
                raise ValueError(f"{recording}: the recording holds no rig; give one with --rig")
            reference = use.eyes[EYE_ORDER[0]].color
            warm = warmup_s(settings.span_smoothing_s)
            pieces = plan_fuse(src, reference, chunk_s, warm, every)
            planned.append(FuseOutput(recording, out_dir, use, video_fps(src, use, every), pieces))
    return planned


def run_fuse_job(
    outputs: Sequence[FuseOutput],
    settings: DisplaySettings,
    every: int,
    runner: Runner,
    progress: Progress | None = None,
) -> list[FuseResult]:
    """Fuse the planned recordings with ``runner``; write each one's pictures, frames.csv
    and video (:class:`app.recording.fuse.FusedWriter`). Returns what was written for each.
    On an error the job stops; what was written stays, the video's pieces are removed."""
    tasks = [FuseTask(p, o.rig, settings, every) for o in outputs for p in o.pieces]
    owner = [i for i, o in enumerate(outputs) for _ in o.pieces]
    last = {i: k for k, i in enumerate(owner)}
    results: list[FuseResult] = []
    writer: FusedWriter | None = None
    try:
        expected = [t.piece.expected for t in tasks]
        for k, items in enumerate(runner.run(fuse_task, tasks, expected, progress)):
            i = owner[k]
            if writer is None:
                writer = FusedWriter(outputs[i].out_dir, outputs[i].fps)
            for item in items:
                writer.add(item)
            if last[i] == k:
                results.append(writer.close())
                writer = None
    finally:
        if writer is not None:
            writer.abort()
    return results


def run_map_job(
    sources: Sequence[ReplaySource],
    rig: Rig,
    settings: MapSettings,
    pose_mode: str,
    chunk_s: float,
    runner: Runner,
    progress: Progress | None = None,
) -> MapRun:
    """The map of ``sources`` (in order) with ``runner``: the pieces' maps merged in order
    (:meth:`app.recording.map3d.MapRun.absorb`). Poses as ``pose_mode`` says
    (:func:`app.recording.map3d.choose_poses`); estimated poses make one piece of all."""
    t0 = time.perf_counter()
    estimate = all(p is None for p in choose_poses(sources, rig, pose_mode))
    pieces = plan_map(sources, tof_sensor_name(rig), chunk_s, MAX_IMAGE_AGE_S, estimate)
    tasks = [MapTask(p, rig, settings, estimate) for p in pieces]
    run: MapRun | None = None
    for items in runner.run(map_task, tasks, [p.expected for p in pieces], progress):
        for piece_run in items:
            if run is None:
                run = piece_run
            else:
                run.absorb(piece_run)
    assert run is not None  # a job has at least one piece
    run.seconds = time.perf_counter() - t0
    return run
