"""Rendering the simulated head's poses: in threads of this process
(:func:`render_frames`), or in a separate render process (:class:`RenderProcess`).

Render process: for the default scenario (or with ``render_process=True``) the
:class:`~app.sources.simulated.SimulatedHeadSource` renders its poses in a separate process
(``multiprocessing``, ``spawn``), not in a thread of its own: rendering is numpy work that
holds the GIL much of the time, and a render thread delayed every other thread of a
console (a 2 ms sleep overshot by 2 ms median, 6 ms p90) and took a core from it while the
cache filled. The process renders at lower priority (:data:`RENDER_NICE`), so the stream
and the viewer come first and rendering takes what CPU is left. It writes each pose into
the disk cache (:mod:`app.sources.sim.pose_cache`) when there is one, else sends the
images back through its pipe. Like any ``spawn`` child it imports the parent's
``__main__``: a script that makes a source must guard its top level with
``if __name__ == "__main__":``.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from trifuse.app.errors import describe_error
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.pose_cache import load_pose, save_pose
from trifuse.app.sources.sim.render import SensorTruth
from trifuse.calib.rig import Rig

if TYPE_CHECKING:
    from trifuse.app.sources.sim.drift import SensorDrift

RENDER_NICE = 10
"""Niceness the render process takes once the stream is running (the first pose is
rendered at normal priority: nothing can be shown before it)."""

_RENDER_COST = {"color": 1.0, "thermal": 0.2, "tof": 0.03}  # relative, to split the work


def render_frames(
    scenario: Any,
    rig: Rig,
    sensors: Sequence[str],
    t_s: float,
    workers: int,
    stop: threading.Event | None = None,
    drifted: bool | None = None,
) -> dict[str, tuple[Frame, SensorTruth]]:
    """Every sensor's frame and truth at scenario time ``t_s``, in ``workers`` threads
    (the sensors split by cost); fewer entries if ``stop`` was set meanwhile. ``drifted``:
    with a scenario that has a sensor drift, render with it (True) or without (False)
    whatever ``t_s`` (``scenario.render(..., drifted=)``); None: as the scenario renders
    ``t_s``."""
    extra = {} if drifted is None else {"drifted": drifted}
    groups: list[list[str]] = [[] for _ in range(max(1, min(workers, len(sensors))))]
    load = [0.0] * len(groups)
    for s in sorted(sensors, key=lambda s: -_RENDER_COST[rig[s].modality]):
        g = load.index(min(load))
        groups[g].append(s)
        load[g] += _RENDER_COST[rig[s].modality]
    out: dict[str, tuple[Frame, SensorTruth]] = {}

    def render(names: list[str]) -> None:
        for name in names:
            if stop is not None and stop.is_set():
                return
            frames, truth = scenario.render(t_s, [name], **extra)
            out[name] = (frames[name], truth[name])

    if len(groups) == 1:
        render(groups[0])
        return out
    errors: list[BaseException] = []

    def work(names: list[str]) -> None:
        try:
            render(names)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(g,), daemon=True) for g in groups]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    if errors:
        raise errors[0]
    return out


def _lower_priority() -> None:
    """Take the render process's niceness (:data:`RENDER_NICE`); best effort."""
    try:
        os.nice(RENDER_NICE)
    except OSError:
        pass


def _render_worker(
    conn: Any,
    scenario: Any,
    seed: int,
    live: bool,
    sensors: list[str],
    warm_up: bool,
    drift: SensorDrift | None = None,
) -> None:
    """The render process: renders the poses asked for, until the pipe closes.

    A request is ``(pose, t_s, workers, path, low_priority, drifted)`` (``drifted``: as
    :func:`render_frames`). The pose is written to
    ``path`` (answer ``("saved", pose)``) or, without a path or if writing fails, sent
    back (``("frames", pose, {sensor: (image, distance)})``); an error is answered
    ``("error", pose, message)``. With ``warm_up`` the process lowers its priority at once
    and builds the renderer's ray grids before the first request.
    """
    if scenario is None:
        from trifuse.app.sources.sim.inspection import InspectionScenario

        scenario = InspectionScenario(seed=seed, live=live, drift=drift)
    rig = scenario.rig
    niced = False
    if warm_up:
        niced = True
        _lower_priority()
        prepare = getattr(getattr(scenario, "renderer", None), "prepare", None)
        if prepare is not None:
            prepare(sensors)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        pose, t_s, workers, path, low_priority, drifted = request
        if low_priority and not niced:
            niced = True
            _lower_priority()
        try:
            out = render_frames(scenario, rig, sensors, t_s, workers, drifted=drifted)
            frames = {name: f for name, (f, _) in out.items()}
            if path is not None:
                try:
                    save_pose(Path(path), frames)
                    conn.send(("saved", pose))
                    continue
                except OSError:
                    pass
            conn.send(("frames", pose, {n: (f.image, f.distance_m) for n, f in frames.items()}))
        except (EOFError, OSError, BrokenPipeError):
            return
        except Exception as exc:
            try:
                conn.send(("error", pose, describe_error(exc)))
            except OSError:
                return


class RenderProcess:
    """A render process (``spawn``: a clean interpreter, no forked threads) and its pipe.

    Args:
        scenario: the scenario to render (pickled to the process), or None for the
            default ``InspectionScenario(seed=seed, live=live, drift=drift)`` (made in the
            process).
        seed, live, drift: the default scenario's.
        sensors: the sensors to render, in order.
        warm_up: lower the priority at once and build the renderer's ray grids before
            the first request (else the priority drops with the first ``low_priority``
            request).
    """

    def __init__(
        self,
        scenario: Any,
        seed: int,
        live: bool,
        sensors: list[str],
        warm_up: bool = False,
        drift: SensorDrift | None = None,
    ) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_render_worker,
            args=(child, scenario, seed, live, sensors, warm_up, drift),
            name="trifuse-sim-render",
            daemon=True,
        )
        self._proc.start()
        child.close()
        self._sensors = sensors

    def render(
        self,
        pose: int,
        t_s: float,
        workers: int,
        path: Path | None,
        low_priority: bool,
        stop: threading.Event,
        rig: Rig,
        drifted: bool | None = None,
    ) -> dict[str, Frame] | None:
        """The frames (stamp 0) of the pose at scenario time ``t_s`` (seconds), rendered in
        ``workers`` threads of the process and written to ``path`` of the disk cache if
        given; None once ``stop`` is set. ``rig``: the scenario's, to check the file read
        back; ``drifted``: as :func:`render_frames`. Raises RuntimeError if rendering failed
        or the process ended."""
        where = None if path is None else str(path)
        self._conn.send((pose, t_s, workers, where, low_priority, drifted))
        while not stop.is_set():
            if self._conn.poll(0.1):
                return self._frames(self._conn.recv(), path, rig)
            if not self._proc.is_alive():
                raise RuntimeError(f"render process ended (exit code {self._proc.exitcode})")
        return None

    def _frames(self, reply: tuple, path: Path | None, rig: Rig) -> dict[str, Frame]:
        """The frames of a reply of :func:`_render_worker`."""
        if reply[0] == "error":
            raise RuntimeError(f"render process: {reply[2]}")
        if reply[0] == "saved":
            assert path is not None
            frames = load_pose(path, rig, self._sensors)
            if frames is None:
                raise RuntimeError(f"render process: {path} is unreadable right after writing")
            return frames
        return {n: Frame(n, 0, image, dist) for n, (image, dist) in reply[2].items()}

    def close(self) -> None:
        try:
            self._conn.send(None)
        except OSError:
            pass
        self._conn.close()
        self._proc.join(1.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(5.0)
