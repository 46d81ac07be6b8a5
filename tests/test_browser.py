"""The console in a real browser (Debian's chromium driven by Playwright): the viewer and
the Thermal panel. Fixtures ``console`` and ``browser`` are in conftest.py."""

from __future__ import annotations

import re

from tests.browser_support import needs_chromium

pytestmark = needs_chromium


def test_viewer_shows_moving_fused_frames(console, browser) -> None:
    page = browser.new_page(viewport={"width": 1280, "height": 540})
    page.goto(console.signin("/"))
    page.wait_for_function("() => window.trifuseStats && window.trifuseStats.meta", timeout=60000)
    first = page.evaluate("() => window.trifuseStats.meta.seq")
    page.wait_for_timeout(3000)
    stats = page.evaluate(
        "() => ({seq: window.trifuseStats.meta.seq,"
        " lat: window.trifuseStats.latencyMs, mode: window.trifuseStats.mode,"
        " w: document.getElementById('view').width})"
    )
    assert stats["mode"] == "websocket" and stats["w"] == 2560  # both eyes side by side
    assert stats["seq"] > first  # frames keep arriving
    lat = sorted(stats["lat"])
    assert lat[len(lat) // 2] < 200  # median capture-to-canvas latency on loopback, ms
    page.close()


def test_console_balances_the_thermal_imagers(console, browser) -> None:
    """The 3D console loads through /console/; the Thermal panel shows the imagers' 1.5 K
    disagreement over shared points, and a manual offset removes it."""
    page = browser.new_page(viewport={"width": 800, "height": 900})
    page.goto(console.signin("/console/"))
    page.wait_for_function(
        "() => !document.body.innerText.includes('Connecting...')", timeout=60000
    )
    page.wait_for_function("() => document.body.innerText.includes('shared points')", timeout=60000)
    text = page.evaluate("() => document.body.innerText")
    line = next(t for t in text.splitlines() if t.startswith("Left - right"))
    # The simulated imagers are +0.75 K and -0.75 K off. The median over shared points
    # reads 1.49-1.51 K depending on the head pose shown (points sample blurred edges
    # differently); the NETD noise of the median itself is about 0.001 K.
    d = float(re.search(r"Left - right: \*?\*?([+-]\d+\.\d+) K", line).group(1))
    assert abs(d - 1.50) <= 0.03, line
    box = page.get_by_label("Offset thermal_left (K)")
    box.fill("-1.5")
    box.press("Enter")
    page.wait_for_function(
        "() => /Left - right: [+-]0\\.0\\d K/.test(document.body.innerText)", timeout=20000
    )
    page.close()


def test_sign_in_form_and_token_url(console, browser) -> None:
    """Without a session every page is the sign-in form; a wrong token is refused, the right
    one signs in (a real browser's form post: its Origin header must pass the check); the
    printed URL signs in and drops the token from the address bar."""
    context = browser.new_context(viewport={"width": 800, "height": 500})
    page = context.new_page()
    assert page.goto(console.url + "/console/").status == 401
    page.fill("input[name=token]", "wrong-token-0123456789")
    page.click("button")
    assert "Wrong token" in page.content() and not context.cookies()
    page.fill("input[name=token]", console.token)
    page.click("button")
    page.wait_for_url(console.url + "/console/")
    page.wait_for_function("() => !document.body.innerText.includes('Connecting...')")
    assert [c["httpOnly"] for c in context.cookies()] == [True]
    context.close()
    context = browser.new_context(viewport={"width": 800, "height": 500})
    page = context.new_page()
    page.goto(console.signin("/"))
    assert page.url == console.url + "/"  # the token left the address bar
    page.wait_for_function("() => window.trifuseStats && window.trifuseStats.meta", timeout=60000)
    context.close()
