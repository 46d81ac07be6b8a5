"""The Thermal panel in a real browser (Debian's chromium driven by Playwright): automatic
balancing of the two thermal imagers on the simulated inspection room, and saving the
radiometry as a rig version. Fixtures ``console`` and ``browser`` are in conftest.py."""

from __future__ import annotations

import re

import pytest
import yaml

from tests.browser_support import click_until, needs_chromium, tick_box, wait_on_page

pytestmark = [needs_chromium, pytest.mark.slow]

DIFFERENCE = re.compile(r"Left - right: \*?\*?([+-]\d+\.\d+) K over (\d+) shared points")


def _difference(page) -> float:
    text = page.evaluate("() => document.body.innerText")
    return float(DIFFERENCE.search(text).group(1))


def _shown(page) -> list[str]:
    return [ln for ln in page.inner_text("body").splitlines() if "Left - right" in ln]


def test_auto_balance_brings_the_imagers_together(console, browser) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 1200})
    page.goto(console.signin("/console/"))
    page.wait_for_function("() => document.body.innerText.includes('shared points')")
    # balanced by default: switched off and reset, the imagers' own difference shows
    assert page.get_by_label("Auto-balance").is_checked()
    click_until(
        page,
        page.get_by_role("button", name="Reset balance"),
        lambda: console.get("/api/thermal")["balance"]["auto"] is False,
        "Reset balance",
    )
    wait_on_page(
        page,
        lambda: re.search(r"Left - right: \*?\*?[+-]1\.\d\d K", page.inner_text("body")),
        lambda: f"the imagers' own difference: {_shown(page)}, {console.get('/api/thermal')}",
    )
    assert not page.get_by_label("Auto-balance").is_checked()
    assert console.get("/api/thermal")["balance"]["auto"] is False
    # the simulated imagers are +0.75 K and -0.75 K off (test_browser.py says why +-0.03)
    assert abs(_difference(page) - 1.50) <= 0.03
    tick_box(page, page.get_by_label("Auto-balance"), "Auto-balance")
    # the filter (3 s time constant, 2 estimates a second) converges within ~10 s
    page.wait_for_function(
        "() => /Left - right: \\*?\\*?[+-]0\\.[01]\\d K/.test(document.body.innerText)",
    )
    assert abs(_difference(page)) < 0.2  # the bound on the median difference
    page.wait_for_function("() => document.body.innerText.includes('(automatic)')")
    state = console.get("/api/thermal")
    assert state["balance"]["auto"] is True
    left = state["radiometry"]["thermal_left"]["balance_offset_k"]
    right = state["radiometry"]["thermal_right"]["balance_offset_k"]
    # split evenly: each imager corrected by half the 1.50 K (+-0.03 K as above)
    assert abs(left + 0.75) <= 0.03 and abs(right - 0.75) <= 0.03

    page.get_by_role("button", name="Save as rig version").click()
    page.wait_for_function("() => document.body.innerText.includes('Saved the radiometry')")
    versions = console.get("/api/rigs")
    saved = yaml.safe_load(open(versions[-1]["path"]).read())
    for name, half in (("thermal_left", -0.75), ("thermal_right", 0.75)):
        assert abs(saved["sensors"][name]["radiometry"]["balance_offset_k"] - half) <= 0.03
    page.close()
