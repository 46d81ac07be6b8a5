"""The registration sigma in a real console on the simulated inspection room: /api/status
reports each eye's figures (a plain HTTP test, sharing this module's console), and the
viewer (Debian's chromium driven by Playwright) switches to the ``registration`` mode with
its Mode select and draws the colour map's scale, 0 … 2 colour pixels, under each eye with
its median and 95th percentile. The screenshot goes to /tmp/shots/viewer-registration.png
(docs/screenshots/registration.png is a copy a person looked at). Fixtures ``console`` and
``browser`` are in conftest.py."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.browser_support import needs_chromium, wait_on_page
from tests.support import wait_until
from trifuse.app.server.runtime.registration_watch import NO_COVARIANCE
from trifuse.fusion.registration_overlay import sigma_lut

pytestmark = pytest.mark.slow

SHOT = Path("/tmp/shots/viewer-registration.png")


def test_status_reports_each_eyes_registration_sigma(console) -> None:
    """Asking for the status makes the console fuse; within a few of its 2 s periods each
    eye has an estimate: finite median and 95th percentile (colour pixels) over the cells
    with depth, the range error's source, no calibration share (the simulated head's rig
    carries no covariance) and its age."""
    last: dict = {}

    def estimated() -> bool:
        last.update(console.status())
        block = last.get("registration") or {}
        return block.get("left") is not None and block.get("right") is not None

    wait_until(estimated, lambda: f"both eyes' registration sigma (status: {last})", poll_s=0.5)
    block = last["registration"]
    assert block["error"] is None
    for eye in ("left", "right"):
        e = block[eye]
        assert math.isfinite(e["median_px"]) and math.isfinite(e["p95_px"]), e
        assert 0.0 < e["median_px"] <= e["p95_px"] < 50.0, e
        assert 500 < e["cells"] <= 3000, e  # a stride keeps it under 3000
        assert e["range_source"] == "no range correction: 41 mm", e
        assert e["calibration_covariance"] is False and e["age_s"] >= 0.0, e


@needs_chromium
def test_viewer_switches_to_the_registration_mode_and_draws_its_scale(console, browser) -> None:
    fusion = console.get("/api/fusion")
    page = browser.new_page(viewport={"width": 1280, "height": 720})
    try:
        page.goto(console.signin("/"))
        page.wait_for_function("() => window.trifuseStats && window.trifuseStats.meta")
        page.wait_for_function(
            "() => !document.getElementById('mode').disabled"
            " && [...document.getElementById('mode').options].some(o => o.value === 'registration')"
        )
        page.select_option("#mode", "registration")
        wait_on_page(
            page, lambda: console.get("/api/fusion")["mode"] == "registration", "the mode set"
        )
        assert {k: v for k, v in console.get("/api/fusion").items() if k != "mode"} == {
            k: v for k, v in fusion.items() if k != "mode"
        }  # the select changed the mode only
        # the scale, once both eyes have an estimate: the colour map, 0 … 2 px, the figures
        page.wait_for_function(
            "() => { const s = window.trifuseStats.scale; return s"
            " && s.kind === 'registration' && s.sides.every(t => t.startsWith('median')); }"
        )
        scales = page.evaluate(
            """() => [...document.querySelectorAll('.scale')].map((el) => {
              const ramp = el.querySelector('canvas.ramp');
              const g = ramp.getContext('2d');
              const px = (x) => [...g.getImageData(x, 0, 1, 1).data.slice(0, 3)];
              const r = ramp.getBoundingClientRect();
              return {hidden: el.hidden, kind: el.dataset.kind,
                      label: el.getAttribute('aria-label'),
                      unit: el.querySelector('.caption.unit').textContent,
                      side: el.querySelector('.caption.mode').textContent,
                      ticks: [...el.querySelectorAll('.tick')].map((t) => t.textContent),
                      low: px(0), high: px(255), w: r.width, h: r.height};
            })"""
        )
        lut = sigma_lut()
        for sc in scales:
            assert not sc["hidden"] and sc["kind"] == "registration", sc
            assert sc["label"].startswith("registration σ, colour pixels 0 … 2; median "), sc
            assert sc["unit"] == "registration σ" and sc["side"].startswith("median "), sc
            assert sc["ticks"] == ["2 px", "0", "0.5", "1", "1.5"], sc
            assert sc["low"] == lut[0].tolist() and sc["high"] == lut[255].tolist(), sc
            assert sc["w"] > 200 and sc["h"] > 5, sc
        overlay = page.evaluate("() => document.getElementById('overlay').textContent")
        assert "registration σ, colour pixels 0 … 2" in overlay and NO_COVARIANCE in overlay
        assert "registration σ: left median " in overlay, overlay
        meta = page.evaluate("() => window.trifuseStats.meta")
        assert meta["mode"] == "registration" and meta["span_k"] is None
        # the picture: the colour map over the colour image, its darkest entries (near 0 px)
        # blended in on much of the room; a dark violet cast the plain room does not have.
        # The simulated head pans: a cell whose depth moved by more than 5 % since its
        # estimate is left out until the next one (every 2-11 s), so the cover shrinks
        # between estimates; the largest cover over a few estimates is checked.
        SHOT.parent.mkdir(exist_ok=True)
        covers: list[float] = []

        def violet_cover() -> bool:
            png = page.locator("#view").screenshot()
            shot = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            violet = (shot[..., 2].astype(int) - shot[..., 1] > 25) & (shot[..., 0] > shot[..., 1])
            covers.append(float(violet.mean()))
            if covers[-1] >= max(covers):
                page.screenshot(path=str(SHOT))
            return covers[-1] > 0.3

        wait_until(
            violet_cover, lambda: f"a violet cover over 30 % (covers: {covers})", 60.0, poll_s=0.5
        )
        # the select follows a change made elsewhere
        status, _ = console.request("/api/fusion", "PUT", fusion)
        assert status == 200
        wait_on_page(
            page,
            lambda: page.evaluate("() => document.getElementById('mode').value") == fusion["mode"],
            "the select back at the console's mode",
        )
        page.wait_for_function("() => window.trifuseStats.scale?.kind === 'temperature'")
    finally:
        console.request("/api/fusion", "PUT", fusion)
        page.close()
