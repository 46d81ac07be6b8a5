"""A whole calibration session driven from the browser, then a kill and a restart.

The console runs on the simulated head's calibration scenario (the heated board held at
``TEST_BOARD_POSES`` = 20 poses, 3 s each). In Chromium: Capture writes a view to disk at
once; Auto-capture until each sensor has four views; once their images are searched the
Calibration folder shows where to hold the board next (issue 30, 6) in words ("move
closer ..., turn the left edge away ..., lower-right corner of ccd_...") with the sigma it
is for, and the live image of that camera with the board's outline where it should
appear, drawn also in the Feeds image of every sensor that would see the board there (the
3D scene shows the ghost board); Auto-capture on to ``MIN_VIEWS`` views; Run calibration
shows the polarity found per sensor and the verdicts, overall and per sensor; Save rig.
The saved rig must meet the calibration issue's accuracy against the simulator's ground
truth where its verdict says good, and lie within three of its stated sigmas where the
verdict asks for more views (the views auto-capture takes depend on the machine's speed).
Then the server is killed (SIGKILL) in the middle of a second calibration and started again
on the same work directory: every captured view and the saved rig are still there, and the
console lists them. Screenshots are kept beside the test's temporary files.

One console and one page for all of it: the next-view guidance comes on the way to a
calibration, as it does for a user (it had its own console and calibration before).
"""

from __future__ import annotations

import json
import re
import signal
from pathlib import Path

import numpy as np
import pytest

from tests.browser_support import (
    TEST_BOARD_POSES,
    WAIT_MS,
    element_shot,
    needs_chromium,
    run_calibration,
    start_console,
    tick_box,
)
from tests.support import FOCAL, POSE, poll_until
from trifuse.app.devtools.console_process import ConsoleProcess
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.capture import load_capture
from trifuse.app.storage.rigfile import load_rig
from trifuse.calib.transforms import pose_error

# a console, a browser, auto-capture of the scenario's poses with a pause for the next-view
# guidance, a calibration, a kill and a restart: 75 s alone, 130-175 s beside other work
pytestmark = [needs_chromium, pytest.mark.slow]

# Of the scenario's 20 poses. 12 simulated views (seeds 1-3) already calibrate within the
# calibration issue's targets with a margin of 2.5 (worst pair 0.44 mm of 1 mm, 0.07 deg of
# 0.2 deg: `trifuse calibrate --truth`), so 16 leave room for a less varied choice.
MIN_VIEWS = 16
GUIDED_VIEWS = 4
"""Views of the board each sensor has when the next-view guidance is checked (the fewest a
sensor is calibrated from)."""
SENSORS = tuple(default_rig().names)
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


def _views_on_disk(workdir: Path) -> list[str]:
    return [v.name for v in load_capture(workdir / "captures").views]


VIEWS_LINE = r"^(\d+) views$"
"""The Calibration folder's count of captured views, a line of its own (the next-view line
also says "N views so far", and it is recomputed later)."""


def _views_shown(page) -> int:
    m = re.search(VIEWS_LINE, page.evaluate("() => document.body.innerText"), re.MULTILINE)
    return int(m.group(1)) if m else 0


def _cyan_pixels(page, name: str) -> int:
    """:data:`CYAN_PIXELS_JS` for the Feeds image of ``name``."""
    return int(page.evaluate(CYAN_PIXELS_JS, name))


def _fewest_views(console: ConsoleProcess) -> int:
    """The fewest views of the board any sensor has in the session."""
    coverage = console.get("/api/captures")["coverage"]
    return min((coverage[name]["views"] if name in coverage else 0) for name in SENSORS)


def _tof_pair_limit(report: dict, camera: str, target: tuple[float, float]) -> tuple[float, float]:
    """How far (degrees, metres) ``camera``'s pose to the TOF may be from the truth: the
    calibration issue's ``target`` when the report's verdict calls the camera good, else
    the larger of the target and three times the 1-sigma the report states for it (its
    rotation and translation to the TOF), once the verdict says which views to capture next.
    """
    verdict = report["verdict"]["sensors"][camera]
    if verdict["grade"] == "good":
        return target
    assert "capture about" in verdict["line"], verdict["line"]
    sigma = {f["what"]: f["sigma"] for f in verdict["figures"]}
    return (
        max(target[0], 3.0 * sigma["rotation to tof"]),
        max(target[1], 3.0 * sigma["translation to tof"] / 1000.0),
    )


def _check_next_view_guidance(page, tmp_path: Path) -> None:
    """Once the views are searched: the next view in words with the sigma it is for, the
    outline in the live image of the camera the words refer to and in that sensor's Feeds
    image; screenshots of the panel, the image and the ghost board in the 3D scene."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout  # the fixture has it

    try:
        page.wait_for_function(
            "() => /expected after this view|no more views needed/.test(document.body.innerText)",
            timeout=600000,
            polling=1000,
        )
    except PlaywrightTimeout:  # what the panel says instead (e.g. "no single view helps")
        said = re.search(r"Next view: .*", page.evaluate("() => document.body.innerText"))
        pytest.fail(f"no next-view suggestion in 600 s; the panel says: {said and said[0]}")
    text = page.evaluate("() => document.body.innerText")
    line = re.search(r"Next view: (.+)", text).group(1)
    assert re.search(r"(move closer|move back|this distance|at) \(?\d", line), line
    assert re.search(r"(square-on|turn the \w+ edge away)", line), line
    assert re.search(r"of (ccd_left|ccd_right|thermal_\w+|tof)", line), line
    assert re.search(r"its target now, [\d.]+× expected after this view", text), text
    page.wait_for_function("() => document.body.innerText.includes('next view: ')")
    page.wait_for_timeout(2000)
    page.screenshot(path=str(tmp_path / "next-pose-panel.png"), full_page=True)
    image = page.get_by_text(re.compile(r"^next view: ")).locator("..")
    element_shot(image, path=str(tmp_path / "next-pose-image.png"))  # the panel re-makes it
    # the same outline in the Feeds image of the sensor the caption names, read together:
    # the panel re-makes its image (the caption is briefly absent, its subject may change)
    page.wait_for_function(
        "() => { const m = /next view: (\\w+)/.exec(document.body.innerText);"
        f" return m !== null && ({CYAN_PIXELS_JS})(m[1]) > 100; }}",
        polling=500,
    )
    # the ghost board in the 3D scene, near the head: zoom in on it (for the eye only)
    page.mouse.move(250, 570)
    for _ in range(2):
        page.mouse.wheel(0, -250)
        page.wait_for_timeout(300)
    page.wait_for_timeout(3000)
    page.screenshot(path=str(tmp_path / "next-pose-scene.png"))


def test_calibration_session_from_the_browser_survives_a_kill(browser, tmp_path) -> None:
    from playwright.sync_api import TimeoutError as PlaywrightTimeout  # the fixture has it

    workdir = tmp_path / "work"
    args = ["--scenario", "calibration", "--board-poses", str(TEST_BOARD_POSES)]
    args += ["--workdir", str(workdir)]
    log = tmp_path / "console.log"  # not a pipe: the console's log lines never stall it
    proc, console = start_console(args, log_path=log)
    try:
        page = browser.new_page(viewport={"width": 900, "height": 1200})
        page_log: list[str] = []  # what the page logs, for a failure's message
        page.on("console", lambda m: page_log.append(m.text[:200]))
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
        # One click, one view on disk, before anything else happens.
        page.get_by_role("button", name="Capture", exact=True).click()
        page.wait_for_function("() => document.body.innerText.includes('Captured view 0001')")
        assert _views_on_disk(workdir) == ["0001"]

        # Auto-capture, until every sensor has GUIDED_VIEWS views of the board: while it is
        # on, the scenario's board waits at each pose until it is taken, so every view is of
        # one pose (never of a frame set that straddles a pose change) whatever the
        # machine's speed. Then, with auto-capture off, where to hold the board next.
        tick_box(page, page.get_by_label("Auto-capture"), "Auto-capture")
        assert poll_until(
            lambda: _fewest_views(console) >= GUIDED_VIEWS, WAIT_MS / 1e3, poll_s=0.5
        ), (console.get("/api/captures"), log.read_text()[-3000:])
        page.get_by_label("Auto-capture").uncheck()
        _check_next_view_guidance(page, tmp_path)

        # Auto-capture on to MIN_VIEWS views (the poses not taken yet come round again).
        tick_box(page, page.get_by_label("Auto-capture"), "Auto-capture")
        try:
            page.wait_for_function(
                f"() => {{ const m = document.body.innerText.match(/{VIEWS_LINE}/m);"
                f" return m && +m[1] >= {MIN_VIEWS}; }}",
                timeout=900000,  # on a loaded machine the board search lags behind
                polling=2000,
            )
        except PlaywrightTimeout:  # why the last pose was not taken, for the next look
            text = page.evaluate("() => document.body.innerText")
            lines = [ln for ln in text.splitlines() if re.search(r"Not taken|uto-captur", ln)]
            on_disk, shown = len(_views_on_disk(workdir)), _views_shown(page)
            page.screenshot(path=str(tmp_path / "auto-capture-timeout.png"))
            # A page that stopped following the console (busy round, session 33: 20 views on
            # disk, the page showing 15 and view 0017's message for ten minutes) against a
            # console that stopped counting: the same page loaded afresh.
            page.reload()
            page.wait_for_function(
                "() => !document.body.innerText.includes('Connecting...')", timeout=300000
            )
            poll_until(lambda: _views_shown(page) >= on_disk, 120.0, poll_s=1.0)
            pytest.fail(
                f"auto-capture: {on_disk} views on disk after 900 s, not {MIN_VIEWS} (the "
                f"panel counts {shown}, {_views_shown(page)} once reloaded); it says: {lines}; "
                f"the page's last messages: {page_log[-15:]}"
            )
        page.get_by_label("Auto-capture").uncheck()
        shown = _views_shown(page)
        assert len(_views_on_disk(workdir)) >= shown >= MIN_VIEWS

        text = run_calibration(page)
        # the polarity found per sensor: the scenario's board is heated, black squares hot
        assert "Board polarity per sensor" in text, text
        for name in ("thermal_left", "thermal_right"):
            assert re.search(rf"{name}\s+hot\s+poses\s", text), text
        assert re.search(r"tof\s+dark\s+poses\s", text), text
        # the verdicts, overall, per sensor and per eye
        assert re.search(r"Verdict: (good|usable|poor)", text), text
        for name in SENSORS:
            assert re.search(rf"{name} (good|usable|poor): σ of the", text), (name, text)
        assert re.search(r"left eye \(ccd_left – thermal_left\) (good|usable|poor)", text)
        page.get_by_role("button", name="Save rig", exact=True).click()
        page.wait_for_function("() => document.body.innerText.includes('Saved rig-0001')")
        page.screenshot(path=str(tmp_path / "calibration-panel.png"), full_page=True)
        page.close()

        saved = workdir / "rigs" / "rig-0001.yaml"
        rig, truth = load_rig(saved), default_rig()
        report = json.loads((workdir / "rigs" / "rig-0001.report.json").read_text())
        assert len(report["views"]) >= MIN_VIEWS
        # The calibration issue's accuracy, checked as its own test does: focal length per
        # modality, and every pair of sensors' relative pose (pairs with the TOF: 0.2 deg
        # and 3 mm; the others 0.1 deg and 1 mm). Which views auto-capture takes depends on
        # the machine's speed: a less varied set leaves a camera's pose to the TOF less
        # certain (busy round, session 34: sigma 0.17 deg, error 0.22 deg, verdict "usable,
        # capture about 1 more view"). A camera the calibration calls good meets the target;
        # one it does not is within three of its stated sigmas, and the verdict asks for views.
        for name in truth.names:
            focal = abs(rig[name].intrinsics.fx / truth[name].intrinsics.fx - 1)
            assert focal < FOCAL[truth[name].modality], (name, focal)
            for other in truth.names:
                if other != name:
                    rot, trans = pose_error(rig.T(other, name), truth.T(other, name))
                    limit = max(POSE[truth[name].modality], POSE[truth[other].modality])
                    if "tof" in (name, other):
                        limit = _tof_pair_limit(report, other if name == "tof" else name, limit)
                    assert rot < limit[0] and trans < limit[1], (name, other, rot, trans, limit)

        # A second calibration, killed half-way.
        views_before = _views_on_disk(workdir)
        saved_bytes = saved.read_bytes()
        assert console.post("/api/calibrate")[0] == 202
        assert console.get("/api/calibrate")["state"] == "running"
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        print(log.read_text(errors="replace")[-4000:])  # shown when the test fails

    assert _views_on_disk(workdir) == views_before
    assert saved.read_bytes() == saved_bytes
    proc, console = start_console(args)
    try:
        listing = console.get("/api/captures")
        assert [v["name"] for v in listing["views"]] == views_before
        assert [v["name"] for v in console.get("/api/rigs")] == ["rig-0001"]
        assert np.allclose(
            np.array(console.get("/api/rigs/rig-0001")["sensors"]["ccd_right"]["T_rig_sensor"]),
            rig["ccd_right"].T_rig_sensor,
        )
    finally:
        proc.terminate()
        proc.wait(10)
