"""The console's 3D scene in a real browser (Debian's chromium driven by Playwright): the
"3D scene" folder, switching the cloud colouring and the rig shown, and a screenshot of the
scene (saved to /tmp/shots/scene3d.png). Fixtures ``console`` and ``browser`` are in
conftest.py."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.browser_support import needs_chromium

pytestmark = needs_chromium

SHOTS = Path("/tmp/shots")


def choose(page, label: str, option: str) -> None:
    """Pick ``option`` in the Viser dropdown labelled ``label`` (a Mantine Select)."""
    page.get_by_label(label).click()
    page.get_by_role("option", name=option, exact=True).click()


def test_scene_folder_switches_colouring_and_rig(console, browser) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 600})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(console.signin("/console/"))
    page.wait_for_function(
        "() => !document.body.innerText.includes('Connecting...')", timeout=60000
    )
    page.wait_for_function(
        "() => /Cloud: [\\d,]+ points, color/.test(document.body.innerText)", timeout=120000
    )
    text = page.evaluate("() => document.body.innerText")
    assert "3D scene" in text and "Rig shown" in text and "Cloud colour" in text
    assert page.get_by_label("Rig shown").input_value() == "in use"

    # the scene, with the cloud coloured by the colour camera and textured frustums
    page.wait_for_timeout(4000)  # a texture update (2 Hz) and the renderer catching up
    SHOTS.mkdir(parents=True, exist_ok=True)
    png = page.screenshot(path=str(SHOTS / "scene3d.png"))
    shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    view = shot[150:560, 120:460]  # the 3D view left of the panel, below the notice
    drawn = (np.abs(view.astype(int) - 255).sum(axis=2) > 60).mean()
    assert drawn > 0.2, f"only {drawn:.0%} of the view differs from the background"

    # bigger frustums show their live images from the starting viewpoint (typed into the
    # slider's number box: arrow keys would also move the 3D camera)
    uuid = page.locator("label", has_text="Frustum size (m)").get_attribute("for")
    box = page.locator(f"[id='{uuid}']").locator("xpath=..").locator("input:not([type=hidden])")
    box.fill("0.3")
    box.blur()
    page.wait_for_timeout(3000)
    page.screenshot(path=str(SHOTS / "scene3d_frustums.png"))

    for mode, pattern in (
        ("temperature", r"Cloud: [\d,]+ points, temperature: from thermal_left, [-\d.]+ to"),
        ("depth", r"Cloud: [\d,]+ points, depth: radial distance [\d.]+ to [\d.]+ m"),
        ("color", r"Cloud: [\d,]+ points, color: from ccd_left"),
    ):
        choose(page, "Cloud colour", mode)
        page.wait_for_function(
            "p => new RegExp(p).test(document.body.innerText)", arg=pattern, timeout=30000
        )

    # the simulated head offers its ground truth: same poses as the rig in use here
    choose(page, "Rig shown", "ground truth")
    page.wait_for_function(
        "() => document.body.innerText.includes('ground truth vs in use')", timeout=30000
    )
    text = page.evaluate("() => document.body.innerText")
    assert "ccd_left\t0.000\t0.0\t+0.0" in text, text
    choose(page, "Rig shown", "in use")
    page.wait_for_function(
        "() => document.body.innerText.includes('Showing the rig in use.')", timeout=30000
    )
    assert not errors, errors
    page.close()
