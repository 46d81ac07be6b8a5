"""Where to hold the board next, in the browser (issue 30, 6).

The console runs on the simulated head's calibration scenario (the heated board moving
through ``TEST_BOARD_POSES`` poses). In Chromium: Auto-capture until each sensor has four
views; once their images are searched the Calibration folder shows the next view in words ("move
closer ..., turn the left edge away ..., lower-right corner of ccd_...") with the sigma it
is for, and the live image of that camera with the board's outline where it should
appear, drawn also in the Feeds image of every sensor that would see the board there (the
3D scene shows the ghost board); Run calibration then shows the verdicts,
overall and per sensor. Screenshots are kept beside the test's temporary files.
"""

from __future__ import annotations

import re

import pytest

from tests.browser_support import (
    TEST_BOARD_POSES,
    WAIT_MS,
    needs_chromium,
    run_calibration,
    wait_for_cache_warmup,
)
from tests.support import poll_until
from trifuse.app.devtools.console_process import ConsoleProcess

pytestmark = [needs_chromium, pytest.mark.slow]

VIEWS = 4
"""Views of the board each sensor gets before the run (the fewest a sensor is calibrated
from)."""
SENSORS = ("ccd_left", "ccd_right", "thermal_left", "thermal_right", "tof")
CYAN_PIXELS_JS = r"""(name) => {
    const label = (i) => {  // the nearest ancestor's text: the image's label
        for (let p = i.parentElement; p; p = p.parentElement)
            if (p.innerText.trim()) return p.innerText.trim();
        return '';
    };
    const im = [...document.querySelectorAll('img')].find(
        (i) => label(i).split(/\s/)[0] === name);
    if (!im || !im.complete || im.naturalWidth === 0) return -1;
    const c = document.createElement('canvas');
    c.width = im.naturalWidth;
    c.height = im.naturalHeight;
    const g = c.getContext('2d');
    g.drawImage(im, 0, 0);
    const d = g.getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let k = 0; k < d.length; k += 4)
        if (d[k] < 60 && d[k + 1] > 180 && d[k + 2] > 215) n++;
    return n;
}"""
"""Pixels of the next view's cyan (``NEXT_RGB``, within JPEG's error) in the Feeds image of
the sensor ``name`` (the first image whose label starts with the name); -1 while it has not
loaded."""


def test_the_next_view_is_shown_after_a_few_captures_and_the_verdicts_after_a_run(
    browser, tmp_path
) -> None:
    workdir = tmp_path / "work"
    args = ["--scenario", "calibration", "--board-poses", str(TEST_BOARD_POSES)]
    args += ["--workdir", str(workdir)]
    wait_for_cache_warmup("calibration")
    log = tmp_path / "console.log"  # not a pipe: the console's log lines never stall it
    console = ConsoleProcess(args, log_path=log, timeout_s=WAIT_MS / 1e3)
    proc = console.proc
    try:
        page = browser.new_page(viewport={"width": 900, "height": 1200})
        page.goto(console.signin("/console/"))
        page.wait_for_function("() => !document.body.innerText.includes('Connecting...')")
        page.wait_for_function("() => document.body.innerText.includes('Next view:')")
        text = page.evaluate("() => document.body.innerText")
        assert "capture 3 more view(s)" in text, text
        page.wait_for_function("() => document.body.innerText.includes('Board (')")
        page.wait_for_function(
            f"(names) => names.every((n) => ({CYAN_PIXELS_JS})(n) >= 0)", arg=list(SENSORS)
        )
        before = {name: _cyan_pixels(page, name) for name in SENSORS}
        assert max(before.values()) < 20, before  # the simulated room has no cyan
        # Auto-capture, until every sensor has VIEWS views of the board: while it is on, the
        # scenario's board waits at each pose until it is taken, so every view is of one
        # pose (never of a frame set that straddles a pose change) whatever the machine's
        # speed, and every sensor gets the views a calibration needs
        page.get_by_label("Auto-capture").check()
        assert poll_until(lambda: _fewest_views(console) >= VIEWS, WAIT_MS / 1e3, poll_s=0.5), (
            console.get("/api/captures"),
            log.read_text()[-3000:],
        )
        page.get_by_label("Auto-capture").uncheck()
        page.wait_for_function(
            "() => /expected after this view|no more views needed/.test(document.body.innerText)",
            timeout=600000,
            polling=1000,
        )
        text = page.evaluate("() => document.body.innerText")
        line = re.search(r"Next view: (.+)", text).group(1)
        assert re.search(r"(move closer|move back|this distance|at) \(?\d", line), line
        assert re.search(r"(square-on|turn the \w+ edge away)", line), line
        assert re.search(r"of (ccd_left|ccd_right|thermal_\w+|tof)", line), line
        assert re.search(r"its target now, [\d.]+× expected after this view", text), text
        # the live image of the camera the words refer to, with the outline drawn
        page.wait_for_function("() => document.body.innerText.includes('next view: ')")
        page.wait_for_timeout(2000)
        page.screenshot(path=str(tmp_path / "next-pose-panel.png"), full_page=True)
        image = page.get_by_text(re.compile(r"^next view: ")).locator("..")
        image.screenshot(path=str(tmp_path / "next-pose-image.png"))
        subject = re.search(r"next view: (\w+)", page.evaluate("() => document.body.innerText"))
        page.wait_for_function(  # the same outline in the subject's Feeds image
            f"(name) => ({CYAN_PIXELS_JS})(name) > 100", arg=subject.group(1), polling=500
        )
        # the ghost board in the 3D scene, near the head: zoom in on it (for the eye only)
        page.mouse.move(250, 570)
        for _ in range(2):
            page.mouse.wheel(0, -250)
            page.wait_for_timeout(300)
        page.wait_for_timeout(3000)
        page.screenshot(path=str(tmp_path / "next-pose-scene.png"))

        text = run_calibration(page)
        assert re.search(r"Verdict: (good|usable|poor)", text), text
        for name in SENSORS:
            assert re.search(rf"{name} (good|usable|poor): σ of the", text), (name, text)
        assert re.search(r"left eye \(ccd_left – thermal_left\) (good|usable|poor)", text)
        page.screenshot(path=str(tmp_path / "next-pose-verdicts.png"), full_page=True)
        page.close()
    finally:
        proc.terminate()
        proc.wait(10)
        print(log.read_text(errors="replace")[-4000:])  # shown when the test fails


def _cyan_pixels(page, name: str) -> int:
    """:data:`CYAN_PIXELS_JS` for the Feeds image of ``name``."""
    return int(page.evaluate(CYAN_PIXELS_JS, name))


def _fewest_views(console: ConsoleProcess) -> int:
    """The fewest views of the board any sensor has in the session."""
    coverage = console.get("/api/captures")["coverage"]
    return min((coverage[name]["views"] if name in coverage else 0) for name in SENSORS)
