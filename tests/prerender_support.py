"""Simulated captures and views rendered once a run, ahead, in a background process, while
other tests run.

Several slow tests start from what the simulator renders: a capture of ``trifuse simulate
calibration`` (and often its ``trifuse calibrate``), or test_thermal_conditions.py's
thermal views; 10-60 s each. Each is a job, run once a run into a folder every process of
the run sees (:class:`_Store`: pytest-xdist's workers share it), by the very commands the
tests ran themselves: the process that claims a job first runs it (an exclusive create of
``KEY.claim``, holding the pid that runs it), and it ends with ``KEY.done``, or
``KEY.failed`` holding the error. When a run collects such tests, conftest.py calls
:func:`start` (in the first worker, or the only process): a background thread claims and
runs their jobs one after the other, in the order the tests will ask for them, after the
simulator cache's warm-up, each in a subprocess at a lower priority (``nice``), so that
they take what the tests leave of the CPU. A test's fixture takes the result with
:func:`prerendered`: it waits for a job claimed elsewhere (giving it the test's priority),
and runs one nobody has claimed in its own process. Nothing a test checks changes: the
same commands with the same seeds write the same files (compared byte for byte: the
simulated capture's first 10 views against test_crash_safety.py's former rendering, the
thermal views of a condition against rendering them in the test).

Add a job: a function ``f(out: Path) -> None`` writing into ``out`` in :data:`JOBS`, its
prerequisites in :data:`NEEDS`, and the tests that want it in :func:`jobs_of`.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path

import pytest

from tests.support import ROOT, wait_until

NICE = 10
"""The background's niceness: it takes what the tests (and their consoles and browsers)
leave of the CPU. On a machine busy with other work it then gets little until a test
waits for it; 0 would make it take its share there too."""
TIMEOUT_S = 1800.0
"""Bound of a test's wait for its capture (a job runs 10-60 s on an idle core)."""


def _cli(*argv: str) -> None:
    from trifuse.app.cli import main

    assert main(list(argv)) == 0, argv


def _simulate(out: Path, *options: str, keep_rig: bool = True) -> None:
    """``trifuse simulate calibration --out OUT OPTIONS`` (then, unless ``keep_rig``, the
    capture's rig.yaml removed: a capture without one)."""
    _cli("simulate", "calibration", "--out", str(out), *options)
    if not keep_rig:
        (out / "rig.yaml").unlink()


def _calibrate(capture: Path, out: Path) -> None:
    """``trifuse calibrate CAPTURE --out OUT/rig.yaml --report OUT/report.json``."""
    out.mkdir(parents=True, exist_ok=True)
    _cli(
        "calibrate",
        str(capture),
        "--out",
        str(out / "rig.yaml"),
        "--report",
        str(out / "report.json"),
    )


def _simulated(out: Path) -> None:
    """conftest.py's ``simulated``: the 30 views of seed 1 (job ``simulated-capture``),
    calibrated."""
    _calibrate(out.parent / "simulated-capture" / "captures", out)


def _matrix_cooled(out: Path) -> None:
    """test_calibration_matrix.py's cooled 8x5 board seen by a head with ccd_right and
    thermal_left upside down (the rig file beside the capture)."""
    from tests.support import upside_down
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.storage.rigfile import save_rig

    out.mkdir()
    rig = out / "upside-down.yaml"
    save_rig(rig, upside_down(default_rig(), ("ccd_right", "thermal_left")))
    _simulate(
        out / "cooled",
        *("--views", "20", "--seed", "4", "--thermal-board", "cooled"),
        *("--board", "8x5", "--square-size", "0.05", "--rig", str(rig)),
    )


TARGET_VIEWS = {"charuco": 12, "asymmetric_circles": 15}
"""test_sim_targets.py's views per pattern (its ``VIEWS``, where the margins are given)."""


def _sim_targets(pattern: str) -> Callable[[Path], None]:
    def job(out: Path) -> None:
        """test_sim_targets.py's run of ``pattern``: its views of seed 3, calibrated."""
        views = str(TARGET_VIEWS[pattern])
        argv = ("--views", views, "--seed", "3", "--pattern", pattern)
        _simulate(out / "captures", *argv)
        _calibrate(out / "captures", out)

    return job


THERMAL_MORE_SEEDS = (8, (12,))
"""test_thermal_conditions.py's ``more_seeds`` views: poses per seed, seeds. One seed of 8
poses, 16 images a condition: a cut or faint image costs our detector 1-4 s of failed
searches, and with a second seed the four slowest conditions took 200 s of the suite's
CPU. Eight poses keep the cooling session's late, faint views."""
THERMAL = ("thermal_left", "thermal_right")


def _thermal_views(name: str) -> Callable[[Path], None]:
    def job(out: Path) -> None:
        """The thermal views under BENCH_CONDITIONS[name] of :data:`THERMAL_MORE_SEEDS`,
        both imagers, each seed's as a pickled tuple of ThermalView (``seed-N.pkl``)."""
        from trifuse.app.sources.sim.condition_views import thermal_condition_views
        from trifuse.app.sources.sim.head import default_rig
        from trifuse.app.sources.sim.thermal_conditions import BENCH_CONDITIONS

        out.mkdir()
        poses, seeds = THERMAL_MORE_SEEDS
        for seed in seeds:
            views = thermal_condition_views(
                BENCH_CONDITIONS[name], poses, (seed,), default_rig(), THERMAL
            )
            (out / f"seed-{seed}.pkl").write_bytes(pickle.dumps(tuple(views)))

    return job


def _calibration_frame_sets(out: Path) -> None:
    """conftest.py's ``calibration_frame_sets``: twelve views of the calibration scenario
    (seed 1), every sensor's frames, pickled (``frames.pkl``)."""
    from trifuse.app.sources.sim.scenarios import calibration_views

    out.mkdir()
    frames = [v.frames for v in calibration_views(12, seed=1)]
    (out / "frames.pkl").write_bytes(pickle.dumps(frames))


JOBS: dict[str, Callable[[Path], None]] = {
    "calibration-frame-sets": _calibration_frame_sets,
    "simulated-capture": lambda out: _simulate(out / "captures", "--views", "30", "--seed", "1"),
    "simulated": _simulated,
    # test_calibration_matrix.py's captures (its docstring says what each varies)
    "matrix-white-hot": lambda out: _simulate(
        out / "white-hot",
        *("--views", "14", "--seed", "3", "--thermal-board", "white-hot", "--tof-board", "bright"),
        keep_rig=False,
    ),
    "matrix-cooled": _matrix_cooled,
    "matrix-few-views": lambda out: _simulate(
        out / "few-views",
        *("--views", "16", "--seed", "5", "--board", "7x10", "--square-size", "0.06"),
        *("--sensor-views", "thermal_right=3"),
        keep_rig=False,
    ),
    "targets-charuco": _sim_targets("charuco"),
    "targets-asymmetric_circles": _sim_targets("asymmetric_circles"),
    # test_symmetric_board.py's 4 x 6 board end to end
    "board-4x6": lambda out: _simulate(
        out, *("--views", "16", "--seed", "3", "--board", "4x6", "--square-size", "0.08")
    ),
}
THERMAL_JOB = "thermal-"
"""Prefix of test_thermal_conditions.py's more_seeds jobs, one per condition: thermal-NAME."""


def job(key: str) -> Callable[[Path], None]:
    """The job called ``key``."""
    if key.startswith(THERMAL_JOB):
        return _thermal_views(key.removeprefix(THERMAL_JOB))
    return JOBS[key]


NEEDS = {"simulated": ("simulated-capture",)}
"""A job's prerequisites (queued before it; it reads their folders)."""


def jobs_of(item: pytest.Item) -> list[str]:
    """The jobs the collected test ``item`` will ask for (by its module and fixtures)."""
    fixtures = set(getattr(item, "fixturenames", ()))
    module = item.path.name
    jobs = []
    if "simulated_capture" in fixtures:
        jobs.append("simulated-capture")
    if "simulated" in fixtures:
        jobs.append("simulated")
    if "calibration_frame_sets" in fixtures:
        jobs.append("calibration-frame-sets")
    if module == "test_calibration_matrix.py" and "captures" in fixtures:
        jobs += ["matrix-white-hot", "matrix-cooled", "matrix-few-views"]
    params = getattr(getattr(item, "callspec", None), "params", {})
    if module == "test_sim_targets.py" and "run" in fixtures and "run" in params:
        jobs.append(f"targets-{params['run']}")
    if item.name == "test_a_simulated_capture_of_a_4x6_board_end_to_end":
        jobs.append("board-4x6")
    if getattr(item, "originalname", "") == "test_detection_under_condition_more_seeds":
        jobs.append(THERMAL_JOB + params["name"])
    return jobs


def xdist_worker() -> str | None:
    """This process's pytest-xdist worker (``gw0``, ``gw1``, ...), None outside xdist."""
    return os.environ.get("PYTEST_XDIST_WORKER")


# -- the background run ----------------------------------------------------------------------


class _Store:
    """The jobs' folders under ``base``, each job run once by the process that claims it
    (see the module doc)."""

    def __init__(self, base: Path) -> None:
        self.base = base
        base.mkdir(parents=True, exist_ok=True)

    def out(self, key: str) -> Path:
        return self.base / key

    def _mark(self, key: str, kind: str) -> Path:
        return self.base / f"{key}.{kind}"

    def claim(self, key: str) -> bool:
        """Whether this process got ``key`` to run (no other process had claimed it)."""
        try:
            os.close(os.open(self._mark(key, "claim"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        except FileExistsError:
            return False
        return True

    def running(self, key: str, pid: int) -> None:
        """Say which process runs the claimed ``key`` (a waiter gives it its priority)."""
        self._mark(key, "claim").write_text(str(pid))

    def finish(self, key: str, error: str | None = None) -> None:
        if error is None:
            self._mark(key, "done").touch()
        else:
            self._mark(key, "failed").write_text(error)

    def ended(self, key: str) -> bool:
        return self._mark(key, "done").exists() or self._mark(key, "failed").exists()

    def wait(self, key: str) -> Path:
        """The folder of ``key``, claimed by some process, once it has ended (its runner
        hurried meanwhile: it may name itself after the claim)."""
        wait_until(
            lambda: self.ended(key) or self._hurry(key),
            f"the render of {key}",
            TIMEOUT_S,
            poll_s=0.2,
        )
        failed = self._mark(key, "failed")
        if failed.exists():
            pytest.fail(f"the render of {key} failed:\n{failed.read_text()}")
        return self.out(key)

    def _hurry(self, key: str) -> bool:
        """Give the process running ``key`` this one's priority, where the system lets a
        process lower a niceness (root; else it stays ``nice``). False: a wait's poll."""
        with contextlib.suppress(OSError, ValueError):
            pid = int(self._mark(key, "claim").read_text())
            os.setpriority(os.PRIO_PROCESS, pid, os.getpriority(os.PRIO_PROCESS, 0))
        return False

    def run_here(self, key: str) -> Path:
        """The folder of ``key`` (after its prerequisites): run in this process if nobody
        has claimed it, else waited for."""
        for dep in NEEDS.get(key, ()):
            self.run_here(dep)
        if not self.claim(key):
            return self.wait(key)
        self.running(key, os.getpid())
        try:
            job(key)(self.out(key))
        except BaseException:
            self.finish(key, traceback.format_exc()[-4000:])
            raise
        self.finish(key)
        return self.out(key)


class _Background:
    """Claims and runs the queued jobs one after the other, each in a ``nice`` subprocess;
    a job another process has claimed is left to it."""

    def __init__(self, store: _Store, queue: list[str], after: list[subprocess.Popen]) -> None:
        self.store, self.queue, self.after = store, queue, after
        self.proc: subprocess.Popen | None = None
        self.key = ""
        self.stopping = False
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._run, name="prerender", daemon=True)
        self.thread.start()

    def _idle_until(self, ready: Callable[[], bool]) -> bool:
        """Wait until ``ready()`` or :meth:`stop`; whether it is ready."""
        while not self.stopping:
            if ready():
                return True
            time.sleep(0.5)
        return False

    def _run(self) -> None:
        # the simulator cache's warm-up first (the consoles wait for it)
        if not self._idle_until(lambda: all(p.poll() is not None for p in self.after)):
            return
        for key in self.queue:
            deps = NEEDS.get(key, ())  # queued before it, perhaps claimed elsewhere
            if not self._idle_until(lambda deps=deps: all(map(self.store.ended, deps))):
                return
            code = (
                f"import os, sys; os.nice({NICE}); sys.path.insert(0, {str(ROOT)!r}); "
                "from pathlib import Path; from tests.prerender_support import job; "
                f"job({key!r})(Path({str(self.store.out(key))!r}))"
            )
            with self.lock:  # no job starts once stop() has begun
                if self.stopping:
                    return
                if not self.store.claim(key):
                    continue
                self.key = key
                self.proc = subprocess.Popen(
                    [sys.executable, "-c", code],
                    cwd=ROOT,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    text=True,
                )
                self.store.running(key, self.proc.pid)
            _, err = self.proc.communicate()
            status = self.proc.returncode
            self.store.finish(key, None if status == 0 else err[-4000:] or f"exit status {status}")

    def stop(self, kill: bool) -> None:
        """No more jobs; the one under way killed (``kill``) or let finish (other workers
        may wait for it)."""
        with self.lock:
            self.stopping = True
            proc = self.proc
        if kill and proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        self.thread.join(60 if kill else TIMEOUT_S)
        if proc is not None and not self.store.ended(self.key):
            self.store.finish(self.key, "the run ended before the background render did")


_store: _Store | None = None
_background: _Background | None = None


def _run_store(tmp_path_factory: pytest.TempPathFactory) -> _Store:
    """The run's store: in its temporary folder (under xdist, beside the workers' own)."""
    global _store
    if _store is None:
        base = tmp_path_factory.getbasetemp()
        _store = _Store((base if xdist_worker() is None else base.parent) / "prerender")
    return _store


def start(session: pytest.Session, after: Iterable[subprocess.Popen] = ()) -> None:
    """Start making the jobs the session's tests will ask for, in their order, once the
    processes ``after`` have ended (in the only process of the run, or its first worker)."""
    global _background
    if session.config.option.collectonly or xdist_worker() not in (None, "gw0"):
        return
    queue: list[str] = []
    for item in session.items:
        for key in jobs_of(item):
            queue += [k for k in (*NEEDS.get(key, ()), key) if k not in queue]
    if queue and _background is None:
        store = _run_store(session.config._tmp_path_factory)  # tmp_path_factory's
        _background = _Background(store, queue, list(after))


def stop() -> None:
    """End the background run: the job under way killed, or under xdist let finish (a
    worker still running may wait for it)."""
    global _background
    if _background is not None:
        _background.stop(kill=xdist_worker() is None)
        _background = None


def prerendered(key: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder job ``key`` wrote, run here if no process of the run has claimed it,
    else waited for."""
    return _run_store(tmp_path_factory).run_here(key)
