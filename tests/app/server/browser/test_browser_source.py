"""The Source panel in a real browser (Debian's chromium driven by Playwright): it tops the
console's GUI, and Record then Stop recording leaves a recording in the work directory's
``recordings/``. Fixtures ``console`` and ``browser`` are in conftest.py.

A screenshot of the panel goes to /tmp/shots/source.png (for a person to look at)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.browser_support import needs_chromium
from tests.support import wait_until
from trifuse.app.recording import ReplaySource

pytestmark = [needs_chromium, pytest.mark.slow]

SHOT = Path("/tmp/shots/source.png")

# The Source folder's box: the ancestor of its title that holds the Record button's text.
_FOLDER_BOX = """() => {
  const walk = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  let e = null;
  while (walk.nextNode()) {
    const t = walk.currentNode;
    if (t.nodeValue.trim() === 'Source') { e = t.parentElement; break; }
  }
  while (e && !(e.innerText || '').includes('Fused:')) e = e.parentElement;
  const r = e.getBoundingClientRect();
  return {x: r.x, y: r.y - 12, width: r.width, height: r.height + 16};
}"""


def test_record_and_stop_from_the_source_panel(console, browser) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 900})
    try:
        page.goto(console.signin("/console/"))
        page.wait_for_function("() => !document.body.innerText.includes('Connecting...')")
        page.wait_for_function("() => document.body.innerText.includes('Fused:')")
        text = page.evaluate("() => document.body.innerText")
        assert "simulated: the simulated head" in text
        # the stream's rates say what they count (the viewer shows the same: test_browser.py)
        assert re.search(
            r"Fused: \d+\.\d fps new pictures, stream \d+\.\d fps \(last 3 s; \d+ new of \d+ "
            r"frames\)",
            text,
        ), text
        # the first folder of the GUI
        folders = [t for t in ("Source", "Fusion", "Thermal") if t in text.splitlines()]
        assert folders[0] == "Source", text[:400]
        assert page.get_by_role("button", name="Pause", exact=True).count() == 0  # not a replay

        page.get_by_role("button", name="Record", exact=True).click()
        stop = page.get_by_role("button", name="Stop recording", exact=True)
        stop.wait_for()
        wait_until(
            lambda: console.get("/api/status")["recording"]["frames_written"] >= 5,
            lambda: console.get("/api/status")["recording"],
            60,
            poll_s=0.2,
        )
        page.wait_for_function(
            "() => document.body.innerText.includes('Recording') "
            "&& /\\d+ frames/.test(document.body.innerText)",
        )
        SHOT.parent.mkdir(parents=True, exist_ok=True)
        page.wait_for_timeout(600)  # the panel's next refresh (size, duration)
        page.screenshot(path=str(SHOT), clip=page.evaluate(_FOLDER_BOX))

        stop.click()
        page.get_by_role("button", name="Record", exact=True).wait_for()
        page.wait_for_function("() => /Saved recordings\\//.test(document.body.innerText)")
        rec = console.get("/api/status")["recording"]
        assert not rec["active"] and rec["error"] is None, rec
        files = [Path(f) for f in rec["files"]]
        assert files and all(f.parent.name == "recordings" and f.exists() for f in files), rec
        assert Path(files[0]).name in page.evaluate("() => document.body.innerText")
        with ReplaySource(files[0], realtime=False) as src:
            frames = list(src.frames())
        assert len(frames) >= 5 and {f.sensor for f in frames} <= set(src.sensors)
    finally:
        page.close()
