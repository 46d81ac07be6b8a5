"""Benchmark ``link``: the fused stream over an emulated radio link (issue 18), JPEG
(``/stream``) against video (``/stream.video``) on the same link in the same run, and what
the 3D console (``/console/``) receives per second.

The console (``trifuse serve --host``, the simulated inspection room, its pose cache filled
first) listens on the host's end of an emulated link (:mod:`app.devtools.netem`); Debian's
Chromium runs inside the link's namespace (Playwright, through
:meth:`app.devtools.netem.EmulatedLink.wrapper`) and opens the viewer page there, so every
byte of the stream crosses the link. Links: :data:`LINKS`; the console page on
:data:`CONSOLE_LINK`.
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import os
import statistics
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np

from trifuse.app.devtools.benchmark import benchmark, check_repeat
from trifuse.app.devtools.browser_console import (
    CHROMIUM,
    CHROMIUM_FLAGS,
    require_chromium,
    websocket_tap,
)
from trifuse.app.devtools.console_bandwidth import (
    ConsolePage,
    get_console_bandwidth,
    measure_console,
    set_console_bandwidth,
)
from trifuse.app.devtools.console_process import ConsoleProcess, prewarm_pose_cache
from trifuse.app.devtools.netem import EmulatedLink, LinkShape, emulated_link

LINKS = (LinkShape(10, 30, 1), LinkShape(3, 60, 2))
"""The issue's links: 10 Mbit/s, 30 ms, 1 % loss; 3 Mbit/s, 60 ms, 2 % (each direction)."""
CONSOLE_LINK = LinkShape(100, 0, 0)
STREAMS = {"jpeg": "jpeg", "video": "auto"}
"""Stream name in the figures -> the viewer page's ``?stream=`` value."""
WINDOW_S = 20.0
"""Measured seconds per link and stream (after :data:`SETTLE_S`)."""
SETTLE_S = 3.0
"""From the viewer's first frame to the window: the adaptive bitrate finds its level."""
CONSOLE_SETTLE_S = 5.0
CONSOLE_WINDOW_S = 15.0
"""``/console/``'s measurement: seconds per bandwidth mode, after as many settling."""
STALL_MS = 200.0
"""A gap between drawn frames longer than this counts as stall time."""
KEEP_FRAMES = 100
"""Pictures the console keeps for the quality comparison (``TRIFUSE_BENCH_KEEP_FRAMES``)."""
SAMPLES = 10
"""Canvas samples per window, :data:`SAMPLE_EVERY_S` apart, compared with the server's."""
SAMPLE_EVERY_S = 2.0
TARGETS = {"fps": 25.0, "latency_ms": 150.0, "stall_ms": 1000.0, "ssim": 0.95}
"""The issue's targets for the video on the 10 Mbit/s link."""

PROBE = websocket_tap(
    "__linkBench",
    "{ draws: [], samples: [], lastMeta: null, sampling: false, maxSamples: 0,"
    " sampleEveryMs: 0, lastSampleAt: -1e12 }",
    """
        if (typeof ev.data !== "string") return;
        try { const m = JSON.parse(ev.data); if (m && m.seq !== undefined) rec.lastMeta = m; }
        catch (e) {}
    """,
    """
  const draw = CanvasRenderingContext2D.prototype.drawImage;
  CanvasRenderingContext2D.prototype.drawImage = function (...args) {
    const out = draw.apply(this, args);
    if (!this.canvas || this.canvas.id !== "view") return out;
    const now = Date.now(), t = performance.now(), canvas = this.canvas;
    queueMicrotask(() => {  // after the page's own bookkeeping of this frame
      const s = window.trifuseStats && window.trifuseStats.meta;
      const m = s && s.seq !== undefined ? s : rec.lastMeta;
      if (!m) return;
      rec.draws.push([t, now - m.stamp_ns / 1e6, now - m.sent_ns / 1e6, m.seq]);
      if (rec.sampling && rec.samples.length < rec.maxSamples &&
          t - rec.lastSampleAt >= rec.sampleEveryMs) {
        rec.lastSampleAt = t;
        const entry = { seq: m.seq, bitmap: null };
        rec.samples.push(entry);
        createImageBitmap(canvas).then((b) => { entry.bitmap = b; });
      }
    });
    return out;
  };
    """,
)
"""Injected into the viewer page: per frame drawn on the picture's canvas (``#view``), the
time (``performance.now()``), the latency from capture (``stamp_ns``: the simulated head
stamps its frames with the host's wall clock, the browser runs on the same clock) and from
the server's send (``sent_ns``) to the draw, and its ``seq`` (``window.trifuseStats.meta``
of the frame, else the last metadata received); while ``sampling``, a snapshot of the
canvas every ``sampleEveryMs`` (an ImageBitmap, read out after the window)."""

SAMPLE_PNG = """async (i) => {
  const b = window.__linkBench.samples[i].bitmap;
  if (!b) return null;
  const c = document.createElement("canvas");
  c.width = b.width; c.height = b.height;
  c.getContext("2d").drawImage(b, 0, 0);
  return c.toDataURL("image/png");
}"""

_DIRECT = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def _server_picture(console: ConsoleProcess, seq: int) -> np.ndarray | None:
    """The console's fused picture of frame ``seq`` ((H, W, 3) uint8 BGR), None if gone."""
    import cv2

    req = urllib.request.Request(f"{console.url}/api/stream/frame/{seq}.png")
    req.add_header("Authorization", f"token {console.token}")
    try:
        with _DIRECT.open(req, timeout=10) as r:
            data = r.read()
    except urllib.error.HTTPError as exc:
        if exc.code == 404:
            return None
        raise
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def _decode_data_url(url: str) -> np.ndarray:
    import cv2

    data = base64.b64decode(url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def draw_figures(draws: list[list[float]], t0_ms: float, t1_ms: float) -> dict[str, float]:
    """Figures of the frames drawn between ``t0_ms`` and ``t1_ms`` (``performance.now()``).

    ``draws``: per frame [draw time ms, latency from capture ms, latency from send ms, seq].
    Returns ``fps`` (median of the frames drawn in each whole second of the window),
    ``latency_ms`` and ``latency_p95_ms`` (from capture), ``send_latency_ms``,
    ``longest_stall_ms`` (the longest time without a new frame, the window's ends
    included) and ``stall_ms`` (the time in gaps over :data:`STALL_MS`)."""
    times = [d[0] for d in draws if t0_ms <= d[0] < t1_ms]
    lat = sorted(d[1] for d in draws if t0_ms <= d[0] < t1_ms)
    send = [d[2] for d in draws if t0_ms <= d[0] < t1_ms]
    seconds = int((t1_ms - t0_ms) // 1000)
    per_s = [0] * max(seconds, 1)
    for t in times:
        k = int((t - t0_ms) // 1000)
        if k < len(per_s):
            per_s[k] += 1
    edges = [t0_ms, *times, t1_ms]
    gaps = [b - a for a, b in itertools.pairwise(edges)]
    nan = float("nan")
    return {
        "fps": float(statistics.median(per_s)),
        "latency_ms": statistics.median(lat) if lat else nan,
        "latency_p95_ms": lat[min(len(lat) - 1, int(0.95 * len(lat)))] if lat else nan,
        "send_latency_ms": statistics.median(send) if send else nan,
        "longest_stall_ms": max(gaps),
        "stall_ms": sum(g for g in gaps if g > STALL_MS),
    }


def _quality(page: Any, pictures: dict[int, np.ndarray | None]) -> dict[str, float]:
    """Mean SSIM and PSNR of the page's canvas samples against the server's pictures of the
    same ``seq``, at the size the page shows them (its canvas's: the server's picture scaled
    down to it with ``INTER_AREA``; a larger sample is scaled to the server's size);
    ``quality_samples``: how many were compared."""
    import cv2

    from trifuse.app.devtools.image_quality import psnr, ssim

    seqs = page.evaluate("() => window.__linkBench.samples.map((s) => s.seq)")
    ssims, psnrs = [], []
    for i, seq in enumerate(seqs):
        reference = pictures.get(seq)
        url = page.evaluate(SAMPLE_PNG, i)
        if reference is None or not url:
            continue
        shown = _decode_data_url(url)
        (h, w), (rh, rw) = shown.shape[:2], reference.shape[:2]
        if w < rw and h < rh:
            reference = cv2.resize(reference, (w, h), interpolation=cv2.INTER_AREA)
        elif (h, w) != (rh, rw):
            shown = cv2.resize(shown, (rw, rh), interpolation=cv2.INTER_LINEAR)
        ssims.append(ssim(reference, shown))
        psnrs.append(min(psnr(reference, shown), 99.0))
    nan = float("nan")
    return {
        "ssim": statistics.mean(ssims) if ssims else nan,
        "min_ssim": min(ssims) if ssims else nan,
        "psnr_db": statistics.mean(psnrs) if psnrs else nan,
        "quality_samples": float(len(ssims)),
    }


def watch_stream(
    browser: Any, console: ConsoleProcess, link: EmulatedLink, stream: str, window_s: float
) -> dict[str, float]:
    """One viewer page (``?stream=stream``) in the link's namespace for ``window_s``
    seconds after :data:`SETTLE_S`: :func:`draw_figures`, ``mbit_s`` received over the
    link (its counter: headers and retransmissions included), the quality
    (:func:`_quality`), and for video ``video_decoded`` (1: the page showed H.264, 0: it
    fell back to JPEG), the page's ``level`` and ``bitrate_mbps`` at the end."""
    page = browser.new_page()
    try:
        page.add_init_script(PROBE)
        page.goto(f"{console.url}/?stream={stream}&token={console.token}")
        page.wait_for_function("() => window.__linkBench.draws.length > 0", timeout=120_000)
        page.wait_for_timeout(SETTLE_S * 1e3)
        page.evaluate(
            f"() => Object.assign(window.__linkBench, {{ sampling: true, maxSamples: {SAMPLES},"
            f" sampleEveryMs: {SAMPLE_EVERY_S * 1e3} }})"
        )
        t0 = page.evaluate("() => performance.now()")
        bytes0, start = link.received_bytes(), time.monotonic()
        pictures: dict[int, np.ndarray | None] = {}
        while time.monotonic() - start < window_s:
            page.wait_for_timeout(500)
            for seq in page.evaluate("() => window.__linkBench.samples.map((s) => s.seq)"):
                if seq not in pictures:  # at once: the console keeps only the last ones
                    pictures[seq] = _server_picture(console, seq)
        t1 = page.evaluate("() => performance.now()")
        mbit_s = (link.received_bytes() - bytes0) * 8 / (time.monotonic() - start) / 1e6
        page.evaluate("() => { window.__linkBench.sampling = false; }")
        draws = page.evaluate("() => window.__linkBench.draws")
        stats = page.evaluate(
            "() => { const s = window.trifuseStats || {};"
            " return [s.codec || null, s.level ?? null, s.bitrateBps ?? null]; }"
        )
        figures = {**draw_figures(draws, t0, t1), "mbit_s": mbit_s, **_quality(page, pictures)}
        if stream != "jpeg":
            codec, level, bitrate = stats
            figures["video_decoded"] = 1.0 if codec not in (None, "JPEG") else 0.0
            with contextlib.suppress(TypeError, ValueError):
                figures["level"] = float(level)  # the ladder step, Mbit/s
            if isinstance(bitrate, int | float):
                figures["bitrate_mbps"] = bitrate / 1e6
        return figures
    finally:
        page.close()


def watch_together(
    browser: Any, console: ConsoleProcess, link: EmulatedLink, window_s: float
) -> dict[str, float]:
    """The issue's "viewer plus console": ``/console/`` in its ``low`` bandwidth mode open
    in the link's namespace while a video viewer (``?stream=auto``) is watched as by
    :func:`watch_stream`, whose ``mbit_s`` then counts both pages (everything the link
    carried); ``console_mbit_s``: the console page's WebSocket payload over the same time.
    The console's mode is restored at the end."""
    was = get_console_bandwidth(console.url, console.token)
    set_console_bandwidth(console.url, console.token, "low")
    page = ConsolePage(browser, console.url, console.token)
    try:
        page.page.wait_for_timeout(CONSOLE_SETTLE_S * 1e3)
        start, t0 = len(page.tally.messages), time.monotonic()
        figures = watch_stream(browser, console, link, STREAMS["video"], window_s)
        stop, dt = len(page.tally.messages), time.monotonic() - t0
        console_figures = page.tally.figures(start, stop, dt)
        figures["console_mbit_s"] = console_figures["total_mbit_s"]
        return figures
    finally:
        page.close()
        set_console_bandwidth(console.url, console.token, was)


def video_route_answers(console: ConsoleProcess) -> bool:
    """Whether the console accepts a WebSocket on ``/stream.video`` (the issue's video
    stream); the connection is closed at once."""
    from websockets.sync.client import connect

    url = console.url.replace("http", "ws", 1) + "/stream.video"
    try:
        with connect(
            url,
            additional_headers={"Authorization": f"token {console.token}"},
            open_timeout=10,
            proxy=None,
        ):
            return True
    except Exception:  # refused, 403/404 at the handshake: no video stream here
        return False


def secure_origin_flags(url: str) -> list[str]:
    """Chromium's flags that make ``url``'s origin a secure context: WebCodecs (the video
    viewer) exists only there, and a plain-http console on the link's address is not one
    (an operator's browser has HTTPS, ``--certfile``, or loopback)."""
    return [f"--unsafely-treat-insecure-origin-as-secure={url}"]


def _link_key(shape: LinkShape) -> str:
    return f"l{shape.rate_mbit:g}"


@benchmark(
    "link",
    "the fused stream over an emulated radio link (10 Mbit/s 30 ms 1 %, 3 Mbit/s 60 ms 2 %), "
    "video against JPEG in headless Chromium inside a network namespace: fps, latency "
    "capture to canvas, stalls, Mbit/s, SSIM/PSNR; video with /console/ (low bandwidth) "
    "on the same link; /console/'s Mbit/s by kind in each bandwidth mode (needs root; "
    "--repeat N: N windows of 20 s per link and stream)",
    default_repeat=1,
)
def link(repeat: int) -> dict[str, float]:
    """Per link in :data:`LINKS` (``l10_*``, ``l3_*``) and stream (``jpeg``: ``/stream``,
    ``video``: ``/stream.video`` where the console has it), ``repeat`` windows of
    :data:`WINDOW_S` seconds, each with a fresh viewer page (medians over the windows):
    :func:`watch_stream`'s figures, e.g. ``l10_video_fps``, ``l10_jpeg_latency_ms``.
    ``l10_together_*``: :func:`watch_together` on the first link (the video viewer with
    the console open in its low bandwidth mode). ``console_*``:
    :func:`app.devtools.console_bandwidth.measure_console` on :data:`CONSOLE_LINK` (each
    mode's Mbit/s by kind). ``load_1min``: the machine's load average before the first
    window."""
    check_repeat(repeat)
    require_chromium("link")
    from playwright.sync_api import sync_playwright

    prewarm_pose_cache()
    env = {**os.environ, "TRIFUSE_BENCH_KEEP_FRAMES": str(KEEP_FRAMES)}
    with (
        tempfile.TemporaryDirectory(prefix="trifuse-bench-link-") as tmp,
        emulated_link(CONSOLE_LINK.rate_mbit, 0, 0, name="bench") as net,
        sync_playwright() as p,
    ):
        console = ConsoleProcess(
            ["--workdir", str(Path(tmp) / "work")],
            env=env,
            log_path=Path(tmp) / "serve.log",
            host=net.host_ip,
            timeout_s=300.0,
        )
        with console:
            streams = dict(STREAMS) if video_route_answers(console) else {"jpeg": "jpeg"}
            figures: dict[str, float] = {"video_route": float("video" in streams)}
            browser = p.chromium.launch(
                executable_path=net.wrapper(CHROMIUM),
                args=[*CHROMIUM_FLAGS, *secure_origin_flags(console.url)],
            )
            try:
                figures["load_1min"] = os.getloadavg()[0]
                for shape in LINKS:
                    net.shape(shape)
                    for name, mode in streams.items():
                        runs = [
                            watch_stream(browser, console, net, mode, WINDOW_S)
                            for _ in range(repeat)
                        ]
                        for key in runs[0]:
                            values = [r[key] for r in runs if key in r]
                            figures[f"{_link_key(shape)}_{name}_{key}"] = statistics.median(values)
                net.shape(LINKS[0])
                runs = [watch_together(browser, console, net, WINDOW_S) for _ in range(repeat)]
                for key in runs[0]:
                    values = [r[key] for r in runs if key in r]
                    figures[f"{_link_key(LINKS[0])}_together_{key}"] = statistics.median(values)
                net.shape(CONSOLE_LINK)
                console_figures = measure_console(
                    browser, console.url, console.token, CONSOLE_WINDOW_S, settle_s=CONSOLE_SETTLE_S
                )
                figures.update({f"console_{k}": v for k, v in console_figures.items()})
            except Exception as exc:
                log = console.output()[-2000:]
                raise RuntimeError(f"link: {exc}; the console's log:\n{log}") from exc
            finally:
                browser.close()
    return figures
