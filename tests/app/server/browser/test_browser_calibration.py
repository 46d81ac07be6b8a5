"""A whole calibration session driven from the browser, then a kill and a restart.

The console runs on the simulated head's calibration scenario (the heated board held at
``TEST_BOARD_POSES`` = 20 poses, 3 s each). In Chromium: Capture writes a view to disk at
once; Auto-capture takes the steady, novel poses; Run calibration; Save rig. The saved
rig must meet the calibration issue's accuracy against the simulator's ground truth. Then
the server is killed (SIGKILL) in the middle of a second calibration and started again on
the same work directory: every captured view and the saved rig are still there, and the
console lists them.
"""

from __future__ import annotations

import json
import re
import signal
from pathlib import Path

import numpy as np
import pytest

from tests.browser_support import TEST_BOARD_POSES, needs_chromium, run_calibration, start_console
from tests.support import FOCAL, POSE
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.capture import load_capture
from trifuse.app.storage.rigfile import load_rig
from trifuse.calib.transforms import pose_error

# a console, a browser, auto-capture of the scenario's poses, a kill and a calibration:
# 90-140 s
pytestmark = [needs_chromium, pytest.mark.slow]

# Of the scenario's 20 poses. 12 simulated views (seeds 1-3) already calibrate within the
# calibration issue's targets with a margin of 2.5 (worst pair 0.44 mm of 1 mm, 0.07 deg of
# 0.2 deg: `trifuse calibrate --truth`), so 16 leave room for a less varied choice.
MIN_VIEWS = 16


def _views_on_disk(workdir: Path) -> list[str]:
    return [v.name for v in load_capture(workdir / "captures").views]


def _views_shown(page) -> int:
    m = re.search(r"(\d+) views", page.evaluate("() => document.body.innerText"))
    return int(m.group(1)) if m else 0


def test_calibration_session_from_the_browser_survives_a_kill(browser, tmp_path) -> None:
    from playwright.sync_api import TimeoutError as PlaywrightTimeout  # the fixture has it

    workdir = tmp_path / "work"
    args = ["--scenario", "calibration", "--board-poses", str(TEST_BOARD_POSES)]
    args += ["--workdir", str(workdir)]
    proc, console = start_console(args)
    try:
        page = browser.new_page(viewport={"width": 900, "height": 1200})
        page.goto(console.signin("/console/"))
        page.wait_for_function("() => !document.body.innerText.includes('Connecting...')")
        page.wait_for_function("() => document.body.innerText.includes('Board (')")
        # One click, one view on disk, before anything else happens.
        page.get_by_role("button", name="Capture", exact=True).click()
        page.wait_for_function("() => document.body.innerText.includes('Captured view 0001')")
        assert _views_on_disk(workdir) == ["0001"]

        page.get_by_label("Auto-capture").check()
        try:
            page.wait_for_function(
                f"() => {{ const m = document.body.innerText.match(/(\\d+) views/);"
                f" return m && +m[1] >= {MIN_VIEWS}; }}",
                timeout=900000,  # on a loaded machine the board search lags behind
                polling=2000,
            )
        except PlaywrightTimeout:  # why the last pose was not taken, for the next look
            text = page.evaluate("() => document.body.innerText")
            lines = [ln for ln in text.splitlines() if re.search(r"Not taken|uto-captur", ln)]
            pytest.fail(
                f"auto-capture: {len(_views_on_disk(workdir))} views on disk after 900 s, "
                f"not {MIN_VIEWS} (the panel counts {_views_shown(page)}); it says: {lines}"
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
        # and 3 mm; the others 0.1 deg and 1 mm).
        for name in truth.names:
            focal = abs(rig[name].intrinsics.fx / truth[name].intrinsics.fx - 1)
            assert focal < FOCAL[truth[name].modality], (name, focal)
            for other in truth.names:
                if other != name:
                    rot, trans = pose_error(rig.T(other, name), truth.T(other, name))
                    limit = max(POSE[truth[name].modality], POSE[truth[other].modality])
                    assert rot < limit[0] and trans < limit[1], (name, other, rot, trans)

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
