"""Simulated captures and views rendered ahead, in a background process, while other tests
run.

Several slow tests start from what the simulator renders: a capture of ``trifuse simulate
calibration`` (and often its ``trifuse calibrate``), or test_thermal_conditions.py's
thermal views; 10-60 s each, on the test's own core while the machine's second core is
mostly idle. When a run collects such tests, conftest.py calls :func:`start`: a background
thread runs their jobs one after the other (in the order the tests will ask for them,
after the simulator cache's warm-up, each in a subprocess at a lower priority, ``nice``)
into a folder of the session's temporary ones, by the very commands the tests ran
themselves. The test's fixture takes the result with :func:`prerendered`, waiting for it
if need be (the job then runs at a normal priority). Nothing a test checks changes: the
same commands with the same seeds write the same files (compared byte for byte: the
simulated capture's first 10 views against test_crash_safety.py's former rendering, the
thermal views of a condition against rendering them in the test). A job the background
was not given (a test the collection hook did not see) runs in the test's own process.

With pytest-xdist's workers (the README's test command) both cores already run tests: there
is no background, and the workers of one run share each job (:class:`_Shared`): the first
worker whose test asks for it runs it, in its own process, while another that asks waits for
it to finish.

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


THERMAL_MORE_SEEDS = (8, (12, 13))
"""test_thermal_conditions.py's ``more_seeds`` views: poses per seed, seeds."""
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


class _Jobs:
    """Jobs run into folders under ``base``, each once."""

    def __init__(self, base: Path) -> None:
        self.base = base
        self.finished: set[str] = set()

    def out(self, key: str) -> Path:
        return self.base / key

    def run_here(self, key: str) -> Path:
        """Run ``key`` (after its prerequisites) in this process, unless done already."""
        if key not in self.finished:
            for dep in NEEDS.get(key, ()):
                self.run_here(dep)
            job(key)(self.out(key))
            self.finished.add(key)
        return self.out(key)


class _Shared(_Jobs):
    """Jobs run into folders under ``base``, a folder every xdist worker of the run sees:
    each job once in the run, by the worker that claims it first (an exclusive create of
    ``KEY.claim``); it leaves ``KEY.done``, or ``KEY.failed`` with the error, and the other
    workers wait for one of them."""

    def run_here(self, key: str) -> Path:
        if key in self.finished:
            return self.out(key)
        for dep in NEEDS.get(key, ()):
            self.run_here(dep)
        done, failed = self.base / f"{key}.done", self.base / f"{key}.failed"
        try:
            os.close(os.open(self.base / f"{key}.claim", os.O_CREAT | os.O_EXCL))
        except FileExistsError:  # another worker runs it
            wait_until(
                lambda: done.exists() or failed.exists(),
                f"another worker's render of {key}",
                TIMEOUT_S,
                poll_s=0.5,
            )
            if failed.exists():
                pytest.fail(f"another worker's render of {key} failed:\n{failed.read_text()}")
        else:
            try:
                job(key)(self.out(key))
            except BaseException:
                failed.write_text(traceback.format_exc()[-4000:])
                raise
            done.touch()
        self.finished.add(key)
        return self.out(key)


class _Background(_Jobs):
    """Runs the queued jobs one after the other, each in a ``nice`` subprocess."""

    def __init__(self, base: Path, queue: list[str], after: list[subprocess.Popen]) -> None:
        super().__init__(base)
        self.queue, self.after = queue, after
        self.done = {k: threading.Event() for k in queue}
        self.failed: dict[str, str] = {}
        self.proc: subprocess.Popen | None = None
        self.stopping = False
        self.lock = threading.Lock()
        self.wanted = threading.Event()  # a test waits: no more waiting, normal priority
        self.thread = threading.Thread(target=self._run, name="prerender", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        # the simulator cache's warm-up first (the consoles wait for it), unless a test
        # waits for a job already
        while any(p.poll() is None for p in self.after) and not self.stopping:
            if self.wanted.wait(0.5):
                break
        for key in self.queue:
            code = (
                f"import os, sys; os.nice({0 if self.wanted.is_set() else NICE}); "
                f"sys.path.insert(0, {str(ROOT)!r}); "
                "from pathlib import Path; from tests.prerender_support import job; "
                f"job({key!r})(Path({str(self.out(key))!r}))"
            )
            with self.lock:  # no job starts once stop() has begun
                if self.stopping:
                    break
                self.proc = subprocess.Popen(
                    [sys.executable, "-c", code],
                    cwd=ROOT,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.PIPE,
                    text=True,
                )
            _, err = self.proc.communicate()
            if self.proc.returncode == 0:
                self.finished.add(key)
            else:
                self.failed[key] = err[-4000:] or f"exit status {self.proc.returncode}"
            self.done[key].set()
        for event in self.done.values():  # stopped: nothing more will come
            event.set()

    def wait(self, key: str) -> Path | None:
        """The folder of ``key`` once the background has made it; None if it is not
        queued or the run was stopped before it."""
        if key not in self.done:
            return None
        if not self.done[key].is_set():  # a test waits for it: a normal priority meanwhile
            self.wanted.set()
            self._renice()
        finished = self.done[key].wait(TIMEOUT_S)
        self.wanted.clear()
        if not finished:
            pytest.fail(f"the background render of {key} did not finish in {TIMEOUT_S:.0f} s")
        if key in self.failed:
            pytest.fail(f"the background render of {key} failed:\n{self.failed[key]}")
        return self.out(key) if key in self.finished else None

    def _renice(self) -> None:
        """Give the job under way this process's priority, where the system lets a process
        lower a niceness (root; else it stays ``nice``)."""
        proc = self.proc
        if proc is not None and proc.poll() is None:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, proc.pid, os.getpriority(os.PRIO_PROCESS, 0))

    def stop(self) -> None:
        with self.lock:
            self.stopping = True
            if self.proc is not None and self.proc.poll() is None:
                self.proc.kill()
        self.thread.join(60)


_background: _Background | None = None
_here: _Jobs | None = None  # jobs this process ran itself


def start(session: pytest.Session, after: Iterable[subprocess.Popen] = ()) -> None:
    """Start making the captures the session's tests will ask for, in their order, once
    the processes ``after`` have ended, in a folder of the session's temporary ones."""
    global _background
    if session.config.option.collectonly or xdist_worker() is not None:
        return
    queue: list[str] = []
    for item in session.items:
        for key in jobs_of(item):
            queue += [k for k in (*NEEDS.get(key, ()), key) if k not in queue]
    if queue and _background is None:
        base = session.config._tmp_path_factory.mktemp("prerender")  # tmp_path_factory's
        _background = _Background(base, queue, list(after))


def stop() -> None:
    """End the background run (killing the job under way)."""
    global _background
    if _background is not None:
        _background.stop()
        _background = None


def prerendered(key: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder job ``key`` wrote: the background's, waiting for it if need be, or
    (not queued there) one of ``tmp_path_factory``'s, where this process runs it now (under
    xdist, the run's folder shared by the workers: :class:`_Shared`)."""
    global _here
    if _background is not None and (out := _background.wait(key)) is not None:
        return out
    if _here is None:
        if xdist_worker() is None:
            _here = _Jobs(tmp_path_factory.mktemp("prerender"))
        else:  # the workers' temporary folders are beside each other
            shared = tmp_path_factory.getbasetemp().parent / "prerender"
            shared.mkdir(exist_ok=True)
            _here = _Shared(shared)
    return _here.run_here(key)
