"""The console's viewer page in headless Chromium, for the benchmarks that watch the stream
as an operator sees it (``stream``, ``sim-first-minute``) and for the browser tests."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from trifuse.app.devtools.console_process import ConsoleProcess

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)


def websocket_tap(name: str, record: str, on_message: str, more: str = "") -> str:
    """JavaScript to inject into a page before its own scripts: ``window[name]`` is the
    object ``record`` (a JS expression; ``rec`` in the statements), every WebSocket the page
    opens runs ``on_message`` (JS statements; ``ev`` the MessageEvent) on each message, and
    ``more`` (JS statements) runs once."""
    return f"""
(() => {{
  const rec = {record};
  window.{name} = rec;
  const Native = window.WebSocket;
  window.WebSocket = class extends Native {{
    constructor(...args) {{
      super(...args);
      this.addEventListener("message", (ev) => {{ {on_message} }});
    }}
  }};
  {more}
}})();
"""


VIEWER_PROBE = websocket_tap(
    "__trifuseBench",
    "{ frames: [], bytes: 0, meta: null }",
    """
        if (typeof ev.data !== "string") { rec.bytes += ev.data.size; return; }
        rec.meta = JSON.parse(ev.data);
        rec.bytes += ev.data.length;
    """,
    """
  const draw = CanvasRenderingContext2D.prototype.drawImage;
  CanvasRenderingContext2D.prototype.drawImage = function (...args) {
    const out = draw.apply(this, args);
    const m = rec.meta, now = Date.now();
    if (m) rec.frames.push([performance.now(), now - m.stamp_ns / 1e6, now - m.sent_ns / 1e6]);
    return out;
  };
    """,
)
"""Injected into the viewer page: per drawn frame, the time it was drawn, the latency from
the frame's source time stamp (``stamp_ns``: when the simulated head released its left
colour image) and from the server's send time (``sent_ns``, what the viewer's overlay
shows), and the bytes received over the stream's WebSocket (``window.__trifuseBench``)."""


def inspection_pose_count(render_hz: float = 2.0) -> int:
    """Distinct head poses the console's simulated head renders (its cache, as
    ``SimulatedHeadSource`` counts them: one pan period sampled at ``render_hz``)."""
    import numpy as np

    from trifuse.app.sources.sim.inspection import InspectionScenario

    scenario = InspectionScenario(seed=0)
    k = max(1, round(scenario.pan_period_s * render_hz))
    poses = {tuple(np.round(scenario.T_world_rig(i / render_hz), 9).ravel()) for i in range(k)}
    return len(poses)


class BrowserConsole:
    """``trifuse serve`` on the simulated inspection room (:class:`ConsoleProcess`, its output
    in ``workdir.parent / (workdir.name + ".log")``), with its own work directory and
    ``XDG_CACHE_HOME`` (so the disk cache of rendered poses is ``cache_home/trifuse/sim``),
    and one viewer page in headless Chromium (``browser``, Playwright) with
    :data:`VIEWER_PROBE`."""

    def __init__(self, browser: Any, cache_home: Path, workdir: Path) -> None:
        env = {**os.environ, "XDG_CACHE_HOME": str(cache_home)}
        env.pop("TRIFUSE_SIM_CACHE", None)
        self.console = ConsoleProcess(
            ["--workdir", str(workdir)],
            env=env,
            log_path=workdir.with_name(workdir.name + ".log"),
            timeout_s=300.0,
        )
        self.t_start = self.console.t_start
        try:
            self.page = browser.new_page()
            self.page.add_init_script(VIEWER_PROBE)
            self.page.goto(self.console.signin())
        except BaseException:
            self.close()
            raise

    def first_frame_s(self, timeout_s: float = 300.0) -> float:
        """Seconds from starting the server to the viewer's first drawn frame."""
        self.page.wait_for_function(
            "() => window.__trifuseBench && window.__trifuseBench.frames.length > 0",
            timeout=timeout_s * 1e3,
        )
        return time.monotonic() - self.t_start

    def window(self, seconds: float) -> dict[str, float]:
        """The viewer over the next ``seconds``: frames drawn per second, median latencies
        (ms), megabytes per second received, and the viewer's own fps figure."""
        import statistics

        js = "() => [window.__trifuseBench.frames.length, window.__trifuseBench.bytes]"
        n0, b0 = self.page.evaluate(js)
        t0 = time.monotonic()
        viewer_fps = []
        while time.monotonic() - t0 < seconds:
            self.page.wait_for_timeout(1000)
            viewer_fps.append(self.page.evaluate("() => window.trifuseStats.fps"))
        dt = time.monotonic() - t0
        n1, b1 = self.page.evaluate(js)
        frames = self.page.evaluate(f"() => window.__trifuseBench.frames.slice({n0}, {n1})")
        return {
            "fps": (n1 - n0) / dt,
            "viewer_fps": statistics.median(viewer_fps) if viewer_fps else 0.0,
            "latency_ms": statistics.median(f[1] for f in frames) if frames else float("nan"),
            "send_latency_ms": statistics.median(f[2] for f in frames) if frames else float("nan"),
            "mb_per_s": (b1 - b0) / dt / 1e6,
        }

    def close(self) -> None:
        """Close the page, stop the console."""
        page = getattr(self, "page", None)
        if page is not None:
            page.close()
            self.page = None
        self.console.close()

    def __enter__(self) -> BrowserConsole:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def rendered_poses(cache_home: Path) -> int:
    """Poses in the simulator's disk cache under ``cache_home`` (an ``XDG_CACHE_HOME``)."""
    return len(list(cache_home.glob("trifuse/sim/*/pose-*.npz")))


def require_chromium(needed_by: str) -> None:
    """RuntimeError, naming the benchmark ``needed_by``, where Debian's chromium is missing."""
    if not os.path.exists(CHROMIUM):
        raise RuntimeError(f"the {needed_by} benchmark needs Debian's chromium at {CHROMIUM}")


@contextlib.contextmanager
def headless_chromium() -> Iterator[Any]:
    """Debian's chromium (:data:`CHROMIUM`), headless, driven by Playwright's sync API, for
    the duration of the block; yields the browser."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_FLAGS))
        try:
            yield browser
        finally:
            browser.close()
