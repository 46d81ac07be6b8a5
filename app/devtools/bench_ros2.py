"""Benchmark ``ros2``: the console on a robot's live ROS 2 topics (issue 36, item 1).

A publisher process (:mod:`app.devtools.ros2_publisher`, ``--scene``) sends the simulated
head's images of the inspection room at their real sizes and rates over DDS as ROS 2
camera drivers do (two 1280 x 960 colour cameras at 30 Hz, rgb8 and JPEG; two 382 x 288
16-bit thermal imagers at 27 Hz; a 176 x 144 TOF's distance and amplitude at 15 Hz);
``trifuse serve --ros2`` reads them, and one viewer on ``/stream`` keeps it fusing. Needs
the ``[ros2]`` extra.
"""

from __future__ import annotations

import asyncio
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from trifuse.app.devtools.benchmark import benchmark, check_repeat
from trifuse.app.devtools.console_process import ConsoleProcess, stop_process
from trifuse.app.devtools.ros2_publisher import TOPIC_MAP
from trifuse.app.devtools.stream_clients import FastViewer, cancel, wait_first_frames
from trifuse.app.procfs import tree_cpu_s

WINDOW_S = 10.0
"""One reading spans this many seconds; ``--repeat`` sets how many."""
SETTLE_S = 5.0
"""After the viewer's first frame, before the first window."""
START_TIMEOUT_S = 120.0
SENSOR_FPS = 30.0
"""The colour cameras' rate: a frame set a second each at most."""


async def _windows(console: ConsoleProcess, publisher: int, windows: int) -> dict[str, float]:
    viewer = FastViewer(console.ws_url, console.token)
    task = asyncio.create_task(viewer.run())
    try:
        await wait_first_frames([viewer], START_TIMEOUT_S)
        await asyncio.sleep(SETTLE_S)
        cores, pub_cores, fps = [], [], []
        for _ in range(windows):
            c0, p0, f0, t0 = (tree_cpu_s(console.pid), tree_cpu_s(publisher), viewer.frames,
                              time.monotonic())  # fmt: skip
            await asyncio.sleep(WINDOW_S)
            dt = time.monotonic() - t0
            cores.append((tree_cpu_s(console.pid) - c0) / dt)
            pub_cores.append((tree_cpu_s(publisher) - p0) / dt)
            fps.append((viewer.frames - f0) / dt)
        status = console.status()
    finally:
        await cancel([task])
    if viewer.error:
        raise RuntimeError(f"the viewer failed: {viewer.error}")
    rates = {f"rate_{n}_hz": float(v) for n, v in status["rates_hz"].items()}
    return {
        "fused_fps": statistics.median(fps),
        "console_cores": statistics.median(cores),
        "publisher_cores": statistics.median(pub_cores),
        **rates,
    }


@benchmark(
    "ros2",
    "the console on live ROS 2 topics over DDS (a publisher process sends the simulated "
    "head's five sensors at their real sizes and rates): frame sets fused a second against "
    f"the sensors' {SENSOR_FPS:g}, each sensor's rate received, the console's and the "
    f"publisher's cores; --repeat N: N windows of {WINDOW_S:g} s (needs the [ros2] extra)",
    baselines=(("fused_fps", "sensor_fps"),),
    default_repeat=3,
)
def ros2(repeat: int) -> dict[str, float]:
    """``trifuse serve --ros2`` (the publisher's topic map, the simulated head's rig, a DDS
    domain of its own) with one viewer on ``/stream`` (in this process, not counted): per
    window of :data:`WINDOW_S` s, the pictures the viewer got a second (``fused_fps``), the
    CPU of the console's and the publisher's process trees over wall time (cores); the
    sensors' rates the console received (``/api/status``) at the end; medians. ``load_1min``:
    the machine's load average before the first window."""
    check_repeat(repeat)
    from trifuse.app.recording.ros2_live import require_cyclonedds
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.storage.rigfile import save_rig

    require_cyclonedds()
    domain = 100 + os.getpid() % 100  # apart from other DDS traffic
    seconds = START_TIMEOUT_S + SETTLE_S + repeat * WINDOW_S + 10
    with tempfile.TemporaryDirectory(prefix="trifuse-bench-ros2-") as tmp:
        topics = Path(tmp) / "topics.yaml"
        topics.write_text(TOPIC_MAP)
        rig = save_rig(Path(tmp) / "head.yaml", default_rig())
        publisher = subprocess.Popen(
            [sys.executable, "-m", "trifuse.app.devtools.ros2_publisher", str(seconds),
             "--domain", str(domain), "--scene"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            args = ["--workdir", str(Path(tmp) / "work"), "--ros2", str(topics),
                    "--ros2-domain", str(domain), "--rig", str(rig)]  # fmt: skip
            with ConsoleProcess(
                args, log_path=Path(tmp) / "serve.log", timeout_s=START_TIMEOUT_S
            ) as console:
                load = os.getloadavg()[0]
                try:
                    figures = asyncio.run(_windows(console, publisher.pid, repeat))
                except Exception as exc:
                    log = console.output()[-2000:]
                    raise RuntimeError(f"ros2: {exc}; the console's log:\n{log}") from exc
        finally:
            stop_process(publisher)
    return {**figures, "sensor_fps": SENSOR_FPS, "load_1min": load}
