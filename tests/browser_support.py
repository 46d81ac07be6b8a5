"""Running ``trifuse serve`` and Debian's chromium for the browser tests.

Browser tests skip, with the reason, where /usr/bin/chromium is not installed; ``.ci/run``
installs it, so CI always runs them. The fixtures ``console`` (the console on the
simulated inspection room, one per test module) and ``browser`` live in conftest.py.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from trifuse.app.devtools.browser_console import CHROMIUM, CHROMIUM_FLAGS
from trifuse.app.devtools.console_process import ConsoleProcess, stop_process

FLAGS = list(CHROMIUM_FLAGS)
WAIT_MS = 300_000
"""Bound of a browser test's wait for the console (ms): generous, because a 2-core machine
busy with other work runs the console several times slower; the awaited event ends the wait
as soon as it comes. Also every page's default timeout (conftest.py's ``browser``)."""
ROOT = Path(__file__).resolve().parents[1]

needs_chromium = pytest.mark.skipif(
    not os.path.exists(CHROMIUM), reason=f"browser tests need Debian's chromium at {CHROMIUM}"
)


# -- the simulator's disk cache, warmed once per run ----------------------------------------

TEST_BOARD_POSES = 20
"""Board poses of the calibration scenario the tests' consoles show (``--board-poses``):
half the default, so half the rendering; 16 of them give a calibration well within the
calibration issue's targets (test_browser_calibration.py)."""
WARM_SCENARIOS = {"inspection": {}, "calibration": {"board_poses": TEST_BOARD_POSES}}
_warmups: dict[str, subprocess.Popen] = {}


def start_cache_warmup() -> None:
    """Render every pose the tests' consoles show into the simulator's disk cache, one
    background process per scenario, while the first tests run (conftest.py starts them
    when the run has console tests). Consoles then load their pictures instead of rendering
    beside the tests (and beside each other)."""
    cache = os.environ.get("TRIFUSE_SIM_CACHE", "")
    if _warmups or cache.lower() in ("off", "0", "no", "false"):
        return
    for name, kwargs in WARM_SCENARIOS.items():
        code = (
            "from app.server.runtime import serve as s; "
            f"s.warm_simulator_cache({{{name!r}: {kwargs!r}}})"
        )
        _warmups[name] = subprocess.Popen(
            [sys.executable, "-c", code],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )


def wait_for_cache_warmup(scenario: str, timeout_s: float = 1200.0) -> None:
    """Block until the warm-up of ``scenario`` (if one was started) has finished; fail if
    it failed."""
    proc = _warmups.get(scenario)
    if proc is None:
        return
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the simulator's {scenario} poses were not rendered after {timeout_s} s")
    if proc.returncode != 0:
        pytest.fail(f"rendering the simulator's {scenario} poses failed: {proc.stderr.read()}")


def cache_warmups() -> list[subprocess.Popen]:
    """The warm-up processes started (tests/prerender_support.py lets them finish first)."""
    return list(_warmups.values())


def stop_cache_warmup() -> None:
    for proc in _warmups.values():
        stop_process(proc)


def scenario_of(args: Sequence[str]) -> str:
    """The simulated scenario ``trifuse serve ARGS`` shows (``inspection`` by default)."""
    args = list(args)
    return args[args.index("--scenario") + 1] if "--scenario" in args else "inspection"


def start_console(
    args: Sequence[str], port: int | None = None, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, ConsoleProcess]:
    """Start ``trifuse serve ARGS`` on a free loopback port (with its own random token
    unless ``env`` gives one; the calibration scenario once its poses are rendered);
    returns the process and the console (its URL as printed: ``https`` under TLS) once it
    answers. Its output is the text pipe ``proc.stdout``."""
    if scenario_of(args) == "calibration":  # the inspection room's live mode needs none
        wait_for_cache_warmup("calibration")
    console = ConsoleProcess(args, env=env, port=port, timeout_s=WAIT_MS / 1e3)
    return console.proc, console


@contextlib.contextmanager
def console_running(args: Sequence[str]) -> Iterator[ConsoleProcess]:
    """``trifuse serve ARGS`` for the duration of the block; yields the console."""
    _, console = start_console(args)
    with console:
        yield console


def run_calibration(page) -> str:
    """Click the Calibration panel's Run calibration, wait until it has calibrated (or
    failed), assert it did not fail; the page's text then."""
    page.get_by_role("button", name="Run calibration", exact=True).click()
    page.wait_for_function(
        "() => /Calibrated \\d+ views|Calibration failed/.test(document.body.innerText)",
        timeout=600000,
        polling=1000,
    )
    text = page.evaluate("() => document.body.innerText")
    assert "Calibration failed" not in text, text
    return text
