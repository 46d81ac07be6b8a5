"""The console in a real browser (Debian's chromium driven by Playwright).

Skipped, with the reason, where /usr/bin/chromium is not installed; ``.ci/run`` installs
it, so CI always runs these.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    not os.path.exists(CHROMIUM), reason=f"browser tests need Debian's chromium at {CHROMIUM}"
)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def console():
    """`trifuse serve` on the simulated head, on a free loopback port."""
    port = _free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from app.cli import main; sys.exit(main(sys.argv[1:]))",
            "serve",
            "--port",
            str(port),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        line = proc.stdout.readline()
        assert f"http://127.0.0.1:{port}/" in line, line
        for _ in range(100):
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                time.sleep(0.1)
        yield f"http://127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        yield b
        b.close()


def test_viewer_shows_moving_fused_frames(console, browser) -> None:
    page = browser.new_page(viewport={"width": 1280, "height": 540})
    page.goto(console + "/")
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
    page.goto(console + "/console/")
    page.wait_for_function(
        "() => !document.body.innerText.includes('Connecting...')", timeout=60000
    )
    page.wait_for_function("() => document.body.innerText.includes('shared points')", timeout=60000)
    text = page.evaluate("() => document.body.innerText")
    line = next(t for t in text.splitlines() if t.startswith("Left - right"))
    assert "+1.5" in line, line  # the simulated imagers are +0.75 K and -0.75 K off
    box = page.get_by_label("Offset thermal_left (K)")
    box.fill("-1.5")
    box.press("Enter")
    page.wait_for_function(
        "() => /Left - right: [+-]0\\.0\\d K/.test(document.body.innerText)", timeout=20000
    )
    page.close()
