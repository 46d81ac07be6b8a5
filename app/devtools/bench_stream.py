"""Benchmark ``stream``: the console's fused stream end to end, as a viewer page in headless
Chromium receives and draws it."""

from __future__ import annotations

import time
from pathlib import Path

from trifuse.app.devtools.benchmark import benchmark, median_ms
from trifuse.app.devtools.browser_console import (
    BrowserConsole,
    headless_chromium,
    inspection_pose_count,
    rendered_poses,
    require_chromium,
)


def _phase(windows: list[dict[str, float]], prefix: str) -> dict[str, float]:
    """Medians over the ``windows`` of :meth:`BrowserConsole.window` as ``<prefix>_<figure>``,
    and the worst window's fps as ``<prefix>_min_fps``."""
    import statistics

    out = {}
    for key in ("fps", "viewer_fps", "latency_ms", "send_latency_ms", "mb_per_s"):
        values = [w[key] for w in windows if w[key] == w[key]]  # NaN: no frame
        out[f"{prefix}_{key}"] = statistics.median(values) if values else float("nan")
    out[f"{prefix}_min_fps"] = min((w["fps"] for w in windows), default=float("nan"))
    return out


@benchmark(
    "stream",
    "the console's fused stream on the simulated head, end to end in headless Chromium: "
    "frames/s at the viewer, latency, bandwidth; while the pose cache fills, once it is "
    "full, and after a restart (minutes)",
    baselines=(("warm_frame_interval_ms", "compose_encode_ms"),),
    default_repeat=10,
)
def stream(repeat: int) -> dict[str, float]:
    """``trifuse serve`` (default: the inspection room, with everything the console runs:
    3D scene, panels, live board detection) and its viewer page in headless Chromium
    (``/usr/bin/chromium``, Playwright), all on this machine.

    Three phases, each reported as medians over windows of ``WINDOW_S`` seconds:

    - ``fill_*``: a fresh disk cache (a temporary ``XDG_CACHE_HOME``), from the viewer's
      first frame until every head pose is rendered (``fill_poses_rendered`` of ``poses``;
      at most 300 s, ``fill_s``);
    - ``warm_*``: then ``repeat`` windows on the same console;
    - ``restart_*``: a second console on the now full disk cache, ``repeat`` windows from
      its first frame; ``restart_first_frame_s``: start to first frame drawn (the first
      console's: ``fill_first_frame_s``).

    Per window: ``fps`` frames drawn by the viewer per second (``min_fps``: the worst
    window), ``viewer_fps`` what the viewer's own overlay (``window.trifuseStats``)
    showed, ``latency_ms`` from the frame leaving the source (its time stamp; the
    simulated head's clock is the host's) to the viewer drawing it, ``send_latency_ms``
    from the server publishing it, ``mb_per_s`` megabytes received per second.

    Baseline, same run, before the consoles: ``compose_encode_ms``, the pipeline's own
    work per frame when every frame is new (blend of both eyes, RGB to BGR, JPEG q80 of
    the 2560 x 960 pair), and ``warm_frame_interval_ms`` (1000 / ``warm_fps``) against it.
    """
    import tempfile

    import cv2
    import numpy as np

    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.fusion.compose import DisplaySettings
    from trifuse.fusion.stereo import StereoFusion

    require_chromium("stream")

    window_s = 3.0
    figures: dict[str, float] = {}
    fill_max_s = 300.0

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    colors = {e: frames[rig.eyes[e].color].image for e in ("left", "right")}
    thermals = {e: frames[rig.eyes[e].thermal].image for e in ("left", "right")}
    fusion = StereoFusion(rig)
    fusion.update_depth(frames["tof"].distance_m)
    blend = DisplaySettings(mode="blend")
    bgr = np.empty((*fusion.frame.shape[:2], 3), np.uint8)

    def compose_encode(_i: int) -> None:
        rgb = fusion.compose(colors, thermals, blend)
        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR, dst=bgr)
        cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 80])

    figures["compose_encode_ms"] = median_ms(compose_encode, max(repeat, 20))
    poses = inspection_pose_count()

    with (
        tempfile.TemporaryDirectory(prefix="trifuse-bench-stream-") as tmp,
        headless_chromium() as b,
    ):
        cache = Path(tmp) / "cache"
        with BrowserConsole(b, cache, Path(tmp) / "work1") as console:
            figures["fill_first_frame_s"] = console.first_frame_s()
            t_fill = time.monotonic()
            fill = []
            while rendered_poses(cache) < poses and time.monotonic() - t_fill < fill_max_s:
                fill.append(console.window(window_s))
            figures["fill_s"] = time.monotonic() - t_fill
            figures["fill_poses_rendered"] = rendered_poses(cache)
            figures["poses"] = poses
            figures.update(_phase(fill, "fill"))
            warm = [console.window(window_s) for _ in range(repeat)]
            figures.update(_phase(warm, "warm"))
        with BrowserConsole(b, cache, Path(tmp) / "work2") as console:
            figures["restart_first_frame_s"] = console.first_frame_s()
            restart = [console.window(window_s) for _ in range(repeat)]
            figures.update(_phase(restart, "restart"))
    figures["warm_frame_interval_ms"] = 1e3 / figures["warm_fps"] if figures["warm_fps"] else 0
    return figures
