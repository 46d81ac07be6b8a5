"""Running ``trifuse serve`` and Debian's chromium for the browser tests: consoles, waiting
on a page (:func:`wait_on_page`), the 3D scene's page and its screenshots
(:func:`open_scene`, :func:`shot_when`, :func:`drawn_fraction`).

Browser tests skip, with the reason, where /usr/bin/chromium is not installed; ``.ci/run``
installs it, so CI always runs them. The fixtures ``console`` (the console on the
simulated inspection room, one per test module) and ``browser`` live in conftest.py.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
import pytest

from tests.support import ROOT, WAIT_S, wait_until
from trifuse.app.devtools.browser_console import CHROMIUM, CHROMIUM_FLAGS
from trifuse.app.devtools.console_process import ConsoleProcess, stop_process
from trifuse.app.sources.sim.pose_cache import default_cache_dir

V = TypeVar("V")

FLAGS = list(CHROMIUM_FLAGS)
WAIT_MS = 300_000
"""Bound of a browser test's wait for the console (ms): generous, because a 2-core machine
busy with other work runs the console several times slower; the awaited event ends the wait
as soon as it comes. Also every page's default timeout (conftest.py's ``browser``)."""

FRAME_INTERVAL_MS = 250
"""The test browser's pages draw at most every this many ms (:data:`FEWER_FRAMES_JS`)."""
FEWER_FRAMES_JS = """(() => {
  const intervalMs = INTERVAL_MS;
  const native = window.requestAnimationFrame.bind(window);
  let queue = new Map(), seq = 0, scheduled = false, last = -Infinity;
  const flush = (ts) => {
    scheduled = false;
    last = ts;
    const due = queue;
    queue = new Map();
    for (const cb of due.values()) {
      try { cb(ts); } catch (e) { setTimeout(() => { throw e; }); }
    }
  };
  window.requestAnimationFrame = (cb) => {
    const id = ++seq;
    queue.set(id, cb);
    if (!scheduled) {
      scheduled = true;
      const wait = last + intervalMs - performance.now();
      if (wait <= 0) native(flush); else setTimeout(() => native(flush), wait);
    }
    return id;
  };
  window.cancelAnimationFrame = (id) => { queue.delete(id); };
})();""".replace("INTERVAL_MS", str(FRAME_INTERVAL_MS))
"""Run in every page of the test browser before its own scripts: ``requestAnimationFrame``
callbacks come together at most every :data:`FRAME_INTERVAL_MS`. Viser's 3D scene draws
continuously for 250 ms after each scene update, and the console updates it several times
a second, so in software WebGL (``--disable-gpu``) a page took a whole core drawing 12
frames a second (50 at most), beside the tests' consoles and workers (BENCHMARKS.md, "The
test suite's time"). At 4 frames a second it takes 0.58 of a core; a test waiting on a
picture waits a frame longer at most. (2 frames a second took 0.39 of a core, but not less of
the whole suite's CPU: not kept.) The viewer (``/``) draws each picture as it arrives, not in
these callbacks. Benchmarks (``trifuse bench``) do not use it."""

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
    if _warmups or default_cache_dir() is None:  # TRIFUSE_SIM_CACHE=off: no disk cache
        return
    for name, kwargs in WARM_SCENARIOS.items():
        code = (
            "from trifuse.app.server.runtime import serve as s; "
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
    args: Sequence[str],
    port: int | None = None,
    env: dict[str, str] | None = None,
    log_path: Path | None = None,
) -> tuple[subprocess.Popen, ConsoleProcess]:
    """Start ``trifuse serve ARGS`` on a free loopback port (with its own random token
    unless ``env`` gives one; the calibration scenario once its poses are rendered);
    returns the process and the console (its URL as printed: ``https`` under TLS) once it
    answers. Its output goes to ``log_path`` (appended; a file never stalls it) or else to
    the text pipe ``proc.stdout``."""
    if scenario_of(args) == "calibration":  # the inspection room's live mode needs none
        wait_for_cache_warmup("calibration")
    console = ConsoleProcess(args, env=env, port=port, log_path=log_path, timeout_s=WAIT_MS / 1e3)
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


# -- waiting on a page ----------------------------------------------------------------------


def wait_on_page(
    page,
    condition: Callable[[], V],
    what: str | Callable[[], object] = "the condition",
    timeout_s: float = WAIT_S,
    poll_s: float = 0.5,
) -> V:
    """:func:`tests.support.wait_until` with the Playwright ``page``'s own wait between
    polls, so that the page runs meanwhile (its WebSocket's messages are handed over)."""
    return wait_until(
        condition, what, timeout_s, poll_s=poll_s, pause=lambda s: page.wait_for_timeout(s * 1e3)
    )


def choose(page, label: str, option: str, timeout_s: float = WAIT_S) -> None:
    """Pick ``option`` in the Viser dropdown labelled ``label`` (a Mantine Select). On a
    loaded machine the click that opens its list can come to nothing (a busy run waited
    300 s for an option that never showed): the label is clicked again until the option
    shows, within ``timeout_s``."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    item = page.get_by_role("option", name=option, exact=True)

    def listed() -> bool:
        if item.is_visible():
            return True
        page.get_by_label(label).click()
        try:
            item.wait_for(state="visible", timeout=5000)
        except PlaywrightTimeout:
            return False
        return True

    wait_on_page(page, listed, f"the option {option!r} in {label!r}", timeout_s, poll_s=0.1)
    item.click()


def tick_box(page, box, what: str) -> None:
    """Tick the Viser checkbox locator ``box`` and wait until it shows ticked
    (:func:`click_until`). Playwright's ``check()`` wants the box ticked right after its
    click: in busy run 26 (BENCHMARKS.md, session 25) the click on "Build map", just after
    its folder opened (the folder's panel intercepting the first tries), did not change
    the box's state at once and ``check()`` failed."""
    if not box.is_checked():
        click_until(page, box, box.is_checked, what)


def click_until(
    page,
    target,
    done: Callable[[], bool],
    what: str,
    retry_s: float = 30.0,
    timeout_s: float = WAIT_S,
) -> None:
    """Click the Playwright locator ``target`` (a Viser button) and wait until ``done()``
    (the console's side of the click, read from its API) holds, within ``timeout_s``. A
    click with no effect after ``retry_s`` is repeated, with a warning in the run's
    summary: in busy run 12 (BENCHMARKS.md, session 22) two buttons' actions had not
    started after 5 and 10 minutes (lost clicks or stalled consoles, not known). Only for
    actions that may be repeated."""
    target.click()
    clicks = 1

    def effect() -> bool:
        nonlocal clicks
        if done():
            return True
        if clicks * retry_s <= time.monotonic() - start:
            said = f"{what}: no effect {retry_s:g} s after click {clicks}; clicking again"
            warnings.warn(said, stacklevel=1)
            target.click()
            clicks += 1
        return False

    start = time.monotonic()
    wait_on_page(page, effect, lambda: f"{what} ({clicks} clicks)", timeout_s, poll_s=0.2)


# -- the 3D scene's page --------------------------------------------------------------------

VIEWPORT = {"width": 800, "height": 600}
"""The size of a 3D scene's page (px): :func:`scene_pixels` cuts the view out of it."""
CONNECTED = "() => !document.body.innerText.includes('Connecting...')"
"""A page condition: Viser's client has connected."""


def open_scene(browser, url: str):
    """A page at ``url`` (800 x 600), connected, with Viser's software-WebGL notice closed
    (it would cover the top left of every screenshot)."""
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(url)
    page.wait_for_function(CONNECTED)
    notice = page.locator(".mantine-Notification-root", has_text="Software WebGL")
    with contextlib.suppress(Exception):  # only under software WebGL
        notice.locator("button").first.click()
    return page


def scene_pixels(png: bytes) -> np.ndarray:
    """The 3D view left of Viser's control panel, (H, W, 3) BGR, from a screenshot."""
    shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return shot[20:580, 10:450]


def drawn_fraction(view: np.ndarray) -> float:
    """Fraction of pixels that differ clearly from the white background."""
    return float((np.abs(view.astype(int) - 255).sum(axis=2) > 60).mean())


def element_shot(locator, attempts: int = 5, **kwargs) -> bytes:
    """``locator.screenshot(**kwargs)``, taken again (the locator found anew) when the
    element was replaced while Playwright waited for it to be stable: a Viser panel re-made
    its component (a chart sent again), and the old element left the DOM."""
    from playwright.sync_api import Error as PlaywrightError

    for k in range(attempts):
        try:
            return locator.screenshot(**kwargs)
        except PlaywrightError as exc:
            if "not attached to the DOM" not in str(exc) or k == attempts - 1:
                raise
    raise AssertionError("unreachable")


def shot_when(
    page, path: Path, ok: Callable[[np.ndarray], bool], what: str, timeout_s: float = 180.0
) -> np.ndarray:
    """Screenshots of ``page`` until the scene's pixels satisfy ``ok`` (software WebGL on
    a busy machine may take seconds to draw a new view); the last one is kept at ``path``
    and its scene pixels returned."""
    shots: list[np.ndarray] = []

    def drawn() -> bool:
        shots.append(scene_pixels(page.screenshot(path=str(path))))
        return ok(shots[-1])

    wait_on_page(page, drawn, what, timeout_s)
    return shots[-1]
