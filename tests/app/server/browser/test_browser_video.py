"""The viewer's video stream in a real browser (Debian's chromium driven by Playwright, against
a real console): H.264 from ``/stream.video`` decoded with WebCodecs and drawn, the overlay's
figures, the Stream select (video presets, JPEG, the console's default, the URL's
``?stream=``), the bitrate falling on a throttled link, and the JPEG fallback where the
browser cannot decode the video. Fixtures ``console`` and ``browser`` are in conftest.py."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from tests.browser_support import needs_chromium

pytestmark = [needs_chromium, pytest.mark.slow]

SHOT = Path("/tmp/shots/viewer-video.png")

_STATS = """() => {
  const s = window.trifuseStats, c = document.getElementById('view');
  return {codec: s.codec, frames: s.frames, fps: s.fps, mbps: s.mbps, bitrateBps: s.bitrateBps,
          level: s.level, coded: s.coded, choice: s.choice, note: s.note, mode: s.mode,
          seq: s.meta ? s.meta.seq : null, w: c.width, h: c.height,
          select: document.getElementById('stream').value,
          overlay: document.getElementById('overlay').textContent};
}"""

# A fingerprint of the picture on the canvas: its mean grey level in 48 x 18 cells.
_FINGERPRINT = """() => {
  const small = document.createElement('canvas');
  small.width = 48; small.height = 18;
  const g = small.getContext('2d');
  g.drawImage(document.getElementById('view'), 0, 0, 48, 18);
  const d = g.getImageData(0, 0, 48, 18).data, out = [];
  for (let i = 0; i < d.length; i += 4) out.push((d[i] + d[i + 1] + d[i + 2]) / 3);
  return out;
}"""

_CHANGED = (
    "(first) => { const now = (" + _FINGERPRINT + ")();"
    " let diff = 0; for (let i = 0; i < now.length; i += 1) diff += Math.abs(now[i] - first[i]);"
    " return diff / now.length > 2; }"
)

_VIDEO_LINE = re.compile(
    r"video: target (\d+\.\d\d) Mbit/s, level ([8421]) \((\d+)x(\d+), up to (\d+) fps\), "
    r"stream (auto|8|4|2|1)"
)
LEVEL_SIZES = {"8": "2560x960", "4": "1920x720", "2": "1280x480", "1": "1280x480"}


def _stats(page: Any) -> dict[str, Any]:
    return page.evaluate(_STATS)


def _shown(page: Any) -> tuple[int, int]:
    """The size the picture's canvas is shown at, device pixels."""
    return tuple(
        page.evaluate(
            "() => { const c = document.getElementById('view'), r = devicePixelRatio;"
            " return [Math.round(c.clientWidth * r), Math.round(c.clientHeight * r)]; }"
        )
    )


def _open(console: Any, browser: Any, query: str = "", init_script: str | None = None) -> Any:
    """A signed-in viewer page at ``/`` + ``query`` (its console errors in ``page.errors``)."""
    page = browser.new_page(viewport={"width": 1280, "height": 540})
    page.errors = []
    page.on("console", lambda m: page.errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: page.errors.append(str(e)))
    if init_script:
        page.add_init_script(init_script)
    page.goto(console.signin("/"))
    if query:
        page.goto(console.url + "/" + query)
    return page


def _wait_codec(page: Any, codec: str, more_frames: int = 3) -> dict[str, Any]:
    """Until ``more_frames`` frames of ``codec`` are drawn from now and the overlay names
    it; the stats then."""
    page.wait_for_function(
        f"() => window.trifuseStats.codec === '{codec}'"
        f" && document.getElementById('overlay').textContent.startsWith('{codec} ')"
    )
    n = page.evaluate("() => window.trifuseStats.frames")
    page.wait_for_function(
        f"() => window.trifuseStats.codec === '{codec}'"
        f" && window.trifuseStats.frames >= {n + more_frames}"
    )
    return _stats(page)


def test_video_stream_draws_moving_frames_with_its_figures(console, browser) -> None:
    """With WebCodecs the viewer takes the video stream (the console's default preset, auto):
    decoded frames are drawn into the canvas at the size it is shown at (its backing store
    follows the window; ``?canvas=full``: 2560 x 960) and the picture moves; the overlay
    names H.264, the received Mbit/s and the console's bitrate target and level, which
    ``trifuseStats`` carries too. A screenshot goes to /tmp/shots/viewer-video.png."""
    page = _open(console, browser)
    s = _wait_codec(page, "H.264")
    assert s["choice"] == "auto" and s["select"] == "auto" and s["mode"] == "websocket"
    first = page.evaluate(_FINGERPRINT)
    page.wait_for_function(_CHANGED, arg=first)  # the head pans: the picture moves
    s = _wait_codec(page, "H.264", more_frames=30)
    assert (s["w"], s["h"]) == _shown(page) and s["w"] < 2560, s  # every level, as shown
    assert s["level"] in LEVEL_SIZES and s["coded"] == LEVEL_SIZES[s["level"]], s
    assert 300_000 <= s["bitrateBps"] <= 8_000_000 and s["mbps"] > 0 and s["fps"] > 0, s
    page.wait_for_function(  # the overlay's next refresh shows the frames counted above
        "() => /Mbit\\/s, latency/.test(document.getElementById('overlay').textContent)"
    )
    text = _stats(page)["overlay"]
    head = re.match(
        r"H\.264 \(websocket\): received (\d+\.\d) fps, (\d+\.\d\d) Mbit/s, latency -?\d+ ms", text
    )
    assert head is not None and float(head[2]) > 0, text
    m = _VIDEO_LINE.search(text)
    assert m is not None, text
    assert m[2] in LEVEL_SIZES and f"{m[3]}x{m[4]}" == LEVEL_SIZES[m[2]] and m[6] == "auto", text
    assert 0.3 <= float(m[1]) <= 8.0, text
    status = console.get("/api/status")["stream"]["video"]
    assert [v["preset"] for v in status] == ["auto"] and status[0]["frames_sent"] > 0, status
    SHOT.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOT))
    page.set_viewport_size({"width": 1800, "height": 760})  # the backing store follows
    page.wait_for_function(
        "([w, h]) => { const c = document.getElementById('view'); return c.width > w"
        " && c.width === Math.round(c.clientWidth * devicePixelRatio); }",
        arg=[s["w"], s["h"]],
    )
    s = _wait_codec(page, "H.264", more_frames=5)
    assert (s["w"], s["h"]) == _shown(page) and page.evaluate(_FINGERPRINT) != [0.0] * 864
    assert page.errors == []
    page.close()
    page = _open(console, browser, "?canvas=full")
    s = _wait_codec(page, "H.264")
    assert (s["w"], s["h"]) == (2560, 960) and page.errors == []
    page.close()


def test_stream_select_switches_presets_and_to_jpeg(console, browser) -> None:
    """The select's first value is the console's default preset (``/api/stream/settings``);
    JPEG switches to ``/stream`` (and is remembered over a reload); a preset brings the
    video back at that level; another preset is a message on the open socket (no new
    socket), the picture then coded smaller and drawn at the same size; ``?stream=``
    overrides what was remembered."""
    status, _ = console.request("/api/stream/settings", "PUT", {"preset": "2"})
    assert status == 200
    try:
        page = _open(console, browser)
        sockets: list[str] = []
        page.on("websocket", lambda ws: sockets.append(ws.url))
        s = _wait_codec(page, "H.264")
        assert (s["choice"], s["select"], s["level"], s["coded"]) == ("2", "2", "2", "1280x480")

        page.select_option("#stream", "jpeg")
        s = _wait_codec(page, "JPEG")
        assert s["bitrateBps"] is None and s["level"] is None and s["choice"] == "jpeg"
        assert s["overlay"].startswith("JPEG (websocket): received"), s["overlay"]
        assert "video: target" not in s["overlay"]
        assert sockets[-1].endswith("/stream")
        assert page.evaluate("() => localStorage.getItem('trifuse.viewer.stream')") == "jpeg"

        page.reload()
        s = _wait_codec(page, "JPEG")
        assert (s["choice"], s["select"]) == ("jpeg", "jpeg")

        page.select_option("#stream", "4")
        page.wait_for_function("() => window.trifuseStats.level === '4'")
        s = _wait_codec(page, "H.264")
        assert (s["level"], s["coded"]) == ("4", "1920x720") and sockets[-1].endswith("?preset=4")
        opened = len(sockets)
        page.select_option("#stream", "1")
        page.wait_for_function("() => window.trifuseStats.level === '1'")
        s = _wait_codec(page, "H.264")
        assert (s["level"], s["coded"]) == ("1", "1280x480")
        assert (s["w"], s["h"]) == _shown(page)  # drawn at the size shown, as every level
        assert len(sockets) == opened  # the preset changed on the open socket
        # the overlay is redrawn twice a second: wait for the redraw after the change
        page.wait_for_function(
            "() => / level 1 \\(.*stream 1/.test(document.getElementById('overlay').textContent)"
        )
        assert _VIDEO_LINE.search(_stats(page)["overlay"])[6] == "1"

        page.goto(console.url + "/?stream=8")  # the URL wins over the stored "1"
        s = _wait_codec(page, "H.264")
        assert (s["choice"], s["select"], s["level"]) == ("8", "8", "8")
        assert page.errors == []
        page.close()
    finally:
        console.request("/api/stream/settings", "PUT", {"preset": "auto"})


def test_a_throttled_link_lowers_the_bitrate(console, browser) -> None:
    """Chromium's network emulation (DevTools protocol; it throttles WebSockets too) at
    1.5 Mbit/s: the console's bitrate target for the viewer falls below the link's rate and
    the ladder steps down, the overlay and ``/api/status`` say so; with the link clear again
    the target climbs back."""
    page = _open(console, browser, "?stream=auto")
    _wait_codec(page, "H.264", more_frames=10)
    # a loaded machine may slow the acks like a congested link: start from a clear one
    page.wait_for_function("() => window.trifuseStats.bitrateBps >= 2e6")
    before = _stats(page)["bitrateBps"]
    cdp = page.context.new_cdp_session(page)
    cdp.send("Network.enable")
    link = {"offline": False, "latency": 0}
    cdp.send(
        "Network.emulateNetworkConditions",
        {**link, "downloadThroughput": 1.5e6 / 8, "uploadThroughput": 1.5e6 / 8},
    )
    page.wait_for_function(f"() => window.trifuseStats.bitrateBps < {min(before, 1.5e6)}")
    page.wait_for_function("() => ['2', '1'].includes(window.trifuseStats.level)")
    s = _wait_codec(page, "H.264")
    low = s["bitrateBps"]
    assert low < before and s["coded"] == "1280x480", (before, s)
    page.wait_for_function(
        "() => /level [21] \\(1280x480/.test(document.getElementById('overlay').textContent)"
    )
    viewers = console.get("/api/status")["stream"]["video"]
    viewer = next(v for v in viewers if v["preset"] == "auto")
    assert viewer["congestion_events"] >= 1 and viewer["bitrate_bps"] < before, viewer
    cdp.send(
        "Network.emulateNetworkConditions",
        {**link, "downloadThroughput": -1, "uploadThroughput": -1},
    )
    page.wait_for_function(f"() => window.trifuseStats.bitrateBps > {low}")
    assert page.errors == []
    page.close()


def test_viewer_uses_jpeg_where_the_browser_cannot_decode_the_video(console, browser) -> None:
    """Without WebCodecs (an insecure context, an old browser) the viewer takes the JPEG
    stream, only JPEG selectable, and says why; a browser whose decoder refuses the
    stream's codec falls back to JPEG too."""
    no_webcodecs = "delete window.VideoDecoder; delete window.EncodedVideoChunk;"
    page = _open(console, browser, init_script=no_webcodecs)
    s = _wait_codec(page, "JPEG")
    assert s["choice"] == "auto" and "no WebCodecs" in s["note"], s
    page.wait_for_function(
        "() => document.getElementById('overlay').textContent.includes('JPEG: no WebCodecs')"
    )
    disabled = page.evaluate(
        "() => [...document.querySelectorAll('#stream option')].filter((o) => o.disabled)"
        ".map((o) => o.value)"
    )
    assert disabled == ["auto", "8", "4", "2", "1"]
    page.close()

    refuses = "VideoDecoder.isConfigSupported = async (c) => ({supported: false, config: c});"
    page = _open(console, browser, init_script=refuses)
    s = _wait_codec(page, "JPEG")
    assert re.search(r"cannot decode avc1\.[0-9a-f]{6}", s["note"]), s
    assert page.errors == []
    page.close()


_DAMAGED_FRAME = """
(() => {
  const decode = VideoDecoder.prototype.decode;
  let n = 0;
  VideoDecoder.prototype.decode = function (chunk) {
    n += 1;
    if (n === 20) throw new DOMException("a damaged frame (test)", "EncodingError");
    return decode.call(this, chunk);
  };
})();
"""


def test_viewer_recovers_from_a_decoder_error_with_a_keyframe(console, browser) -> None:
    """A decoder error (the 20th frame's decode throws): the viewer starts a new decoder,
    asks for a key frame, the console sends one within the frames already in flight, and
    the video goes on (no fallback to JPEG)."""
    events: list[tuple[str, Any]] = []  # the video socket's messages, in order

    def on_socket(ws: Any) -> None:
        if "/stream.video" not in ws.url:
            return
        ws.on("framesent", lambda data: events.append(("sent", data)))
        ws.on(
            "framereceived",
            lambda data: (
                events.append(("key", json.loads(data).get("key")))
                if isinstance(data, str)
                else None
            ),
        )

    page = browser.new_page(viewport={"width": 1280, "height": 540})
    page.on("websocket", on_socket)
    page.add_init_script(_DAMAGED_FRAME)
    page.goto(console.signin("/"))
    page.goto(console.url + "/?stream=4")
    page.wait_for_function("() => window.trifuseStats.decodeErrors === 1")
    s = _wait_codec(page, "H.264", more_frames=10)
    assert s["note"] is None and s["level"] == "4" and s["frames"] >= 19 + 10, s
    assert page.evaluate("() => window.trifuseStats.decodeErrors") == 1
    asked = events.index(("sent", json.dumps({"keyframe": True}, separators=(",", ":"))))
    keys = [key for kind, key in events[asked:] if kind == "key"]
    # the frames sent before the request arrived (at most the window and one being
    # encoded), then the key frame
    assert True in keys[:8], keys[:8]
    page.close()
