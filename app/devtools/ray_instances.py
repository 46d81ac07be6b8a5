"""Local Ray instances for the ``ray`` benchmark (:mod:`app.devtools.bench_ray`): started
with their workers (:func:`start_ray`), each step watched (:func:`ray_step`: a step that
fails or gives no answer in :data:`RAY_STEP_TIMEOUT_S` raises :class:`RayStepFailed` naming
it), and what a task costs besides its work (:func:`task_overheads`).
"""

from __future__ import annotations

import _thread
import contextlib
import dataclasses
import os
import threading
import time
from collections.abc import Iterator
from typing import Any

EMPTY_TASKS = 50
"""Empty Ray tasks timed one after the other per Ray instance."""
WORKER_HOLD_S = 0.3
"""How long each warm-up task holds its worker (not counted in the workers' start)."""
RAY_STEP_TIMEOUT_S = 180.0
"""A Ray step (a start, the workers' start, a job) taking longer stops the benchmark."""


class RayStepFailed(RuntimeError):
    """A Ray step failed or did not finish in time (the message says which)."""


@contextlib.contextmanager
def ray_step(
    what: str, logs: str | None = None, timeout_s: float = RAY_STEP_TIMEOUT_S
) -> Iterator[None]:
    """Run a Ray step: RayStepFailed naming it if it raises, or if it gives no answer in
    ``timeout_s`` (then the main thread is interrupted, as by Ctrl-C); ``logs``: the Ray
    instance's log directory, for the message."""
    where = f"; Ray's logs: {logs}" if logs else ""
    fired = threading.Event()

    def fire() -> None:
        fired.set()
        _thread.interrupt_main()

    timer = threading.Timer(timeout_s, fire)
    timer.daemon = True
    if threading.current_thread() is threading.main_thread():  # else no watchdog
        timer.start()
    try:
        yield
    except KeyboardInterrupt:
        if not fired.is_set():
            raise
        raise RayStepFailed(
            f"Ray: {what}: no answer in {timeout_s:g} s, stopped (did Ray's processes "
            f"start?{where})"
        ) from None
    except RayStepFailed:
        raise
    except Exception as exc:
        hint = ""
        if type(exc).__module__.startswith("ray."):  # Ray's own, not the task's error
            hint = " (a Ray instance also dies when something on this machine runs 'ray stop' "
            hint += f"or kills its raylet{where})"
        raise RayStepFailed(f"Ray: {what} failed: {type(exc).__name__}: {exc}{hint}") from exc
    finally:
        timer.cancel()


# -- what Ray workers run -------------------------------------------------------------------


def _warm_worker(hold_s: float) -> int:
    """Import what a job's task imports, hold the worker a moment (so that the tasks of a
    warm-up land on different workers); the worker's pid."""
    import trifuse.app.recording.jobs  # noqa: F401

    time.sleep(hold_s)
    return os.getpid()


def _empty() -> None:
    return None


@dataclasses.dataclass
class RayInstance:
    """A local Ray instance started for one configuration, and what starting it took."""

    runner: Any
    init_s: float
    workers_s: float
    workers: int
    logs: str | None


def start_ray(cpus: int) -> RayInstance:
    """A new local Ray instance of ``cpus`` CPUs with its ``cpus`` workers started."""
    from trifuse.app.recording.jobs import RayRunner

    with ray_step(f"starting a local instance of {cpus} CPU(s) (ray.init)"):
        t0 = time.perf_counter()
        runner = RayRunner(num_cpus=cpus)
        init_s = time.perf_counter() - t0
    try:
        node = getattr(runner.ray._private.worker, "_global_node", None)
        logs = node.get_logs_dir_path() if node is not None else None
    except Exception:
        logs = None
    try:
        with ray_step(f"starting {cpus} worker(s)", logs):
            ray = runner.ray
            warm = ray.remote(num_cpus=1)(_warm_worker)
            t0 = time.perf_counter()
            refs = [warm.remote(WORKER_HOLD_S) for _ in range(cpus)]
            pids = ray.get(refs, timeout=RAY_STEP_TIMEOUT_S)
            workers_s = time.perf_counter() - t0 - WORKER_HOLD_S
    except BaseException:
        runner.close()
        raise
    return RayInstance(runner, init_s, workers_s, len(set(pids)), logs)


def task_overheads(ray: Any) -> tuple[list[float], float]:
    """Round trips of :data:`EMPTY_TASKS` empty tasks (ms each, after one untimed), and the
    start of the progress actor (ms: created and first answered, as a
    :class:`~app.recording.jobs.RayRunner` does once)."""
    from trifuse.app.progress_actor import JobTracker

    empty = ray.remote(num_cpus=1)(_empty)
    ray.get(empty.remote(), timeout=RAY_STEP_TIMEOUT_S)
    trips = []
    for _ in range(EMPTY_TASKS):
        t0 = time.perf_counter()
        ray.get(empty.remote(), timeout=RAY_STEP_TIMEOUT_S)
        trips.append((time.perf_counter() - t0) * 1e3)
    t0 = time.perf_counter()
    tracker = ray.remote(num_cpus=0)(JobTracker).remote()
    ray.get(tracker.snapshot.remote(), timeout=RAY_STEP_TIMEOUT_S)
    actor_ms = (time.perf_counter() - t0) * 1e3
    ray.kill(tracker)
    return trips, actor_ms
