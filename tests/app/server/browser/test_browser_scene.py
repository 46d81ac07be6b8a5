"""The console's 3D scene in a real browser (Debian's chromium driven by Playwright): the view
buttons move the browser's own camera (read back from what the browser reports), the
"3D scene" folder switches the cloud colouring and the rig shown, the board found by the
live detection is drawn in the calibration scenario, and screenshots of first sight, each
view and the board go to /tmp/shots (scene3d.png, scene3d-head.png, scene3d-above.png,
scene3d-side.png, board-in-scene.png; docs/screenshots/ holds copies a person looked at).

The tests that start their own server come first: the module's ``console`` (conftest.py,
the simulated inspection room) starts with the first test that asks for it, so no idle
console shares the CPU with them."""

from __future__ import annotations

import re
import threading
from pathlib import Path

import numpy as np
import pytest

from tests.browser_support import (
    choose,
    console_running,
    drawn_fraction,
    needs_chromium,
    open_scene,
    shot_when,
)
from tests.support import wait_until

pytestmark = [needs_chromium, pytest.mark.slow]

SHOTS = Path("/tmp/shots")
CLOUD_SHOWN = "() => /Cloud: [\\d,]+ points, color/.test(document.body.innerText)"
VIEW_BUTTONS = {
    "View from head": "head",
    "View from above": "above",
    "View from side": "side",
    "Overview": "overview",
}


# -- the view buttons move this browser's camera (an in-process scene, no simulator) -----


@pytest.fixture
def small_scene():
    """Viser with the console's 3D scene on the synthetic frame set of test_scene3d (a
    ramp of TOF distances 1.5-3.5 m, uniform colour and thermal images)."""
    from tests.scene_support import pipeline_for, scene_context
    from trifuse.app.server.panels.scene3d import Scene3D

    ctx = scene_context(pipeline_for())
    server = ctx.server
    scene = Scene3D(ctx).start()
    try:
        yield scene, f"http://127.0.0.1:{server.get_port()}/"
    finally:
        scene.stop()
        server.stop()


def test_view_buttons_move_the_browsers_own_camera(small_scene, browser) -> None:
    """Each button moves the camera of the browser that pressed it to the view's pose:
    what the browser itself reports back (Viser's camera messages) is checked."""
    scene, url = small_scene
    page = open_scene(browser, url)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.wait_for_function(CLOUD_SHOWN)
    (client,) = scene.server.get_clients().values()
    reports: list[tuple[np.ndarray, np.ndarray]] = []
    lock = threading.Lock()

    def reported(camera) -> None:  # called for the browser's own camera messages only
        with lock:
            reports.append((np.array(camera.position), np.array(camera.look_at)))

    client.camera.on_update(reported)
    viewport = scene.canvas_of(client)  # the canvas, whatever drawing size Viser picks
    assert viewport == (800, 600)
    positions = {}
    for label, view in VIEW_BUTTONS.items():
        want = scene.view_pose(view, viewport)
        with lock:
            reports.clear()
        page.get_by_role("button", name=label).click()

        def arrived(want=want) -> bool:
            with lock:
                return any(
                    np.allclose(p, want.position, atol=1e-3)
                    and np.allclose(a, want.look_at, atol=1e-3)
                    for p, a in reports
                )

        wait_until(arrived, f"the browser's camera at the {view} pose")
        positions[view] = np.array(want.position)
        assert client.camera.fov == pytest.approx(want.fov_rad, abs=1e-6)
    assert np.allclose(positions["head"], 0.0)  # at the rig origin
    assert positions["above"][1] < -1.0  # above the scene (-y is up)
    assert positions["side"][0] > 1.0  # on the right
    assert not errors, errors
    page.close()


# -- the board in the calibration scenario ------------------------------------------------


def test_the_board_is_drawn_where_the_detection_puts_it(browser, tmp_path) -> None:
    """The simulated calibration session (the heated board held at 40 poses): the 3D scene
    draws the board and says from which sensor its pose comes."""
    with console_running(["--scenario", "calibration", "--workdir", str(tmp_path)]) as console:
        page = open_scene(browser, console.signin("/console/"))
        page.wait_for_function(CLOUD_SHOWN, timeout=180000)
        page.wait_for_function(
            "() => /Board: [\\d.]+ m away, pose from ccd_/.test(document.body.innerText)",
            timeout=180000,
        )
        text = page.evaluate("() => document.body.innerText")
        m = re.search(r"Board: ([\d.]+) m away", text)
        assert m is not None and 0.5 < float(m.group(1)) < 4.5  # the poses: 0.6-4 m
        # as the sensors see it, with the board's line of the "3D scene" folder in view
        page.get_by_role("button", name="View from head").click()
        page.get_by_text(re.compile(r"m away, pose from")).scroll_into_view_if_needed()
        page.mouse.move(5, 300)  # no button under the pointer (it would be highlighted)
        SHOTS.mkdir(parents=True, exist_ok=True)
        shot_when(  # the camera moved: the cloud fills the view
            page,
            SHOTS / "board-in-scene.png",
            lambda px: drawn_fraction(px) > 0.3,
            "the view from the head",
        )
        page.close()


# -- the inspection room (the module's console) -------------------------------------------


def test_first_sight_and_the_view_buttons(console, browser) -> None:
    """First sight: the frustum size taken from the scene, the five names and live images
    below the head; then each view button changes what the browser shows. Screenshots of
    each go to /tmp/shots."""
    page = open_scene(browser, console.signin("/console/"))
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.wait_for_function(CLOUD_SHOWN)
    uuid = page.locator("label", has_text="Frustum size (m)").get_attribute("for")
    box = page.locator(f"[id='{uuid}']").locator("xpath=..").locator("input:not([type=hidden])")
    depth = float(box.input_value())
    assert 0.3 <= depth <= 1.5, depth  # from the room (a quarter of its median distance)
    SHOTS.mkdir(parents=True, exist_ok=True)
    first = shot_when(page, SHOTS / "scene3d.png", lambda px: drawn_fraction(px) > 0.1, "a scene")
    shots = {"overview": first}

    def differs(a: np.ndarray, b: np.ndarray) -> bool:
        return (np.abs(a.astype(int) - b.astype(int)).sum(axis=2) > 60).mean() > 0.05

    for label, view in VIEW_BUTTONS.items():
        if view == "overview":
            continue
        page.get_by_role("button", name=label).click()
        shots[view] = shot_when(  # every view shows something, and something else
            page,
            SHOTS / f"scene3d-{view}.png",
            lambda px: drawn_fraction(px) > 0.05 and all(differs(px, o) for o in shots.values()),
            f"the view of {label!r}",
        )
    assert not errors, errors
    page.close()


def test_scene_folder_switches_colouring_and_rig(console, browser) -> None:
    page = open_scene(browser, console.signin("/console/"))
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.wait_for_function(CLOUD_SHOWN, timeout=180000)
    text = page.evaluate("() => document.body.innerText")
    assert "3D scene" in text and "Rig shown" in text and "Cloud colour" in text
    assert page.get_by_label("Rig shown").input_value() == "in use"

    # the operator's frustum size is kept (typed into the slider's number box: arrow keys
    # would also move the 3D camera)
    uuid = page.locator("label", has_text="Frustum size (m)").get_attribute("for")
    box = page.locator(f"[id='{uuid}']").locator("xpath=..").locator("input:not([type=hidden])")
    box.fill("0.3")
    box.blur()
    page.wait_for_timeout(3000)
    assert box.input_value() == "0.3"
    page.screenshot(path=str(SHOTS / "scene3d_frustums.png"))

    for mode, pattern in (
        ("temperature", r"Cloud: [\d,]+ points, temperature: from thermal_left, [-\d.]+ to"),
        ("depth", r"Cloud: [\d,]+ points, depth: radial distance [\d.]+ to [\d.]+ m"),
        ("color", r"Cloud: [\d,]+ points, color: from ccd_left"),
    ):
        choose(page, "Cloud colour", mode)
        page.wait_for_function("p => new RegExp(p).test(document.body.innerText)", arg=pattern)

    # the simulated head offers its ground truth: same poses as the rig in use here
    choose(page, "Rig shown", "ground truth")
    page.wait_for_function("() => document.body.innerText.includes('ground truth vs in use')")
    text = page.evaluate("() => document.body.innerText")
    assert "ccd_left\t0.000\t0.0\t+0.0" in text, text
    choose(page, "Rig shown", "in use")
    page.wait_for_function("() => document.body.innerText.includes('Showing the rig in use.')")
    assert not errors, errors
    page.close()
