"""Test set-up: the checkout on ``sys.path`` (``tests.*`` support modules; trifuse itself is
imported as installed, ``pip install -e '.[test]'``) and shared fixtures. The real test
images kept in ``tests/data`` (with their licences) are ``support.DATA_DIR``.

Plain helpers shared by test modules live in support modules, never in a test module that
another imports (nor this file: it holds fixtures and hooks only): ``support.py`` (the
checkout's paths ``ROOT``/``DATA_DIR``, waiting, a simulated clock, small rigs, synthetic frames
and recordings, capture directories, the CLI, a web app on a port), ``board_support.py``
(simulated board detections), ``palette_support.py`` (vendor-style thermal images),
``pose2sim_support.py`` (Pose2Sim's real set and recipe), ``scene_support.py`` (the 3D scene's
fake pipeline), ``ros2_support.py`` (ROS 2 bags), ``fuzz_support.py`` (the loaders' fuzzing:
strategies, mutators, case counts) and ``browser_support.py`` (consoles, the browser, the 3D
scene's page). Paths come from ``support.ROOT``/``DATA_DIR``, never from a test file's own
place, so test modules may live in any folder under tests/.
Tests check behaviour, not speed: code paced by the wall clock takes a simulated one
(``support.FakeClock``), waits are for a condition with a generous time-out
(``support.wait_until``), and timings are measured by ``trifuse bench``."""

import contextlib
import io
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


LONGEST_FILES = (
    "app/server/browser/test_browser_calibration.py",
    "app/sources/test_thermal_conditions.py",
    "app/sources/test_sim_targets.py",
    "app/server/browser/test_browser_map.py",
    "calib/test_calibration_matrix.py",
    "app/storage/test_crash_safety.py",
)
"""The test files that take longest under pytest-xdist, longest first (paths under tests/):
about 280, 280, 110, 95, 90 and 85 s in the run of 2026-11-29 19:10 (BENCHMARKS.md, "The
test suite's time"). Given out first, each to the next free worker, so that none of them
starts late and ends the run alone. Only the order depends on it."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests that need the 30-view simulated capture (fixtures ``simulated`` and
    ``simulated_capture``, about 40 s once per run) are slow ones too. Under pytest-xdist
    the :data:`LONGEST_FILES` run first, then the other test files with slow tests (in
    their order), then the rest: the workers take a file at a time, and the short ones then
    fill the end of the run instead of one worker finishing a browser session alone.
    (Alone, a run keeps the files' order: the quick tests run while the background renders
    what the slow ones need.)"""
    from tests.prerender_support import xdist_worker

    for item in items:
        if {"simulated", "simulated_capture"} & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
    if xdist_worker() is None:
        return
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    rank = {ROOT / "tests" / f: k for k, f in enumerate(LONGEST_FILES)}

    def order(item: pytest.Item) -> tuple[int, bool]:
        return rank.get(item.path, len(rank)), item.path not in slow_files

    items.sort(key=order)  # stable: the order is kept within a file


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject.toml's options): one worker a core, at most 4 (a worker of
    the slow tests runs a console and a browser beside it)."""
    return max(1, min(os.cpu_count() or 1, 4))


def pytest_sessionstart(session: pytest.Session) -> None:
    """Under pytest-xdist, OpenCV runs each call on one thread: the workers keep the cores
    busy already, and OpenCV's own threads only add their overhead (the thermal detections
    of test_thermal_conditions.py: 20.0 s of CPU on two threads, 16.8 s on one). Tests that
    compare OpenCV's thread counts set their own."""
    from tests.prerender_support import xdist_worker

    if xdist_worker() is not None:
        import cv2

        cv2.setNumThreads(1)


def pytest_collection_finish(session: pytest.Session) -> None:
    """A run with slow tests (the consoles and browser sessions) warms the simulator's disk
    cache in the background from the start (tests/browser_support.py); then a background
    process renders the simulated captures and views the run's tests will ask for
    (tests/prerender_support.py). Under xdist, the first worker does both, for all."""
    from tests import prerender_support
    from tests.browser_support import cache_warmups, start_cache_warmup

    slow = any(item.get_closest_marker("slow") for item in session.items)
    if slow and prerender_support.xdist_worker() in (None, "gw0"):
        start_cache_warmup()
    prerender_support.start(session, after=cache_warmups())


def pytest_sessionfinish(session: pytest.Session) -> None:
    from tests import prerender_support
    from tests.browser_support import stop_cache_warmup

    stop_cache_warmup()
    prerender_support.stop()


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory):
    """`trifuse serve` on the simulated inspection room, on a free loopback port, with a
    fresh work directory; one per test module, so that no idle console shares the CPU
    with another module's own (the calibration session test starts its own)."""
    from tests.browser_support import console_running

    workdir = tmp_path_factory.mktemp("console-work")
    with console_running(["--workdir", str(workdir)]) as url:
        yield url


@pytest.fixture(scope="module")
def browser():
    """Debian's chromium, headless, driven by Playwright; one per module, because the
    Playwright sync API keeps an event loop running in the main thread while it lives
    (``asyncio.run`` in later tests would fail). Its pages draw at most 4 frames a second
    (tests/browser_support.py's ``FEWER_FRAMES_JS``)."""
    from tests.browser_support import CHROMIUM, FEWER_FRAMES_JS, FLAGS, WAIT_MS

    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        new_page, new_context = b.new_page, b.new_context

        # waits without a timeout of their own take WAIT_MS (Playwright's 30 s is short for
        # a console beside another worker's); pages draw fewer frames (FEWER_FRAMES_JS)
        def patient_page(**kwargs):
            page = new_page(**kwargs)
            page.set_default_timeout(WAIT_MS)
            page.add_init_script(FEWER_FRAMES_JS)
            return page

        def patient_context(**kwargs):
            context = new_context(**kwargs)
            context.set_default_timeout(WAIT_MS)
            context.add_init_script(FEWER_FRAMES_JS)
            return context

        b.new_page, b.new_context = patient_page, patient_context
        yield b
        b.close()


@pytest.fixture(scope="session")
def calibration_frame_sets(tmp_path_factory: pytest.TempPathFactory):
    """Twelve simulated views of the calibration board (seed 1), all five sensors (rendered
    once a run: tests/prerender_support.py)."""
    import pickle

    from tests.prerender_support import prerendered

    out = prerendered("calibration-frame-sets", tmp_path_factory)
    return pickle.loads((out / "frames.pkl").read_bytes())


@pytest.fixture(scope="session")
def simulated_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The capture directory of ``trifuse simulate calibration --views 30 --seed 1``
    (rendered ahead: tests/prerender_support.py). Read it; copy it to change it."""
    from tests.prerender_support import prerendered

    return prerendered("simulated-capture", tmp_path_factory) / "captures"


@pytest.fixture(scope="session")
def simulated(simulated_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """``simulated_capture`` and its ``trifuse calibrate`` (rendered and run ahead:
    tests/prerender_support.py): the capture directory, the calibrated rig (and its path),
    the ground-truth rig and the report. Shared by the calibration and range calibration
    tests."""
    import json

    from tests.prerender_support import prerendered
    from trifuse.app.storage.rigfile import load_rig

    out = prerendered("simulated", tmp_path_factory)
    rig_path, report_path = out / "rig.yaml", out / "report.json"
    return {
        "capture": simulated_capture,
        "rig": load_rig(rig_path),
        "rig_path": rig_path,
        "truth": load_rig(simulated_capture / "ground_truth_rig.yaml"),
        "report": json.loads(report_path.read_text()),
    }


@pytest.fixture
def server():
    """A Viser server on a free loopback port, quiet, stopped after the test (the panels'
    tests build their GUI on it)."""
    import viser

    with contextlib.redirect_stdout(io.StringIO()):
        srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    srv.stop()
