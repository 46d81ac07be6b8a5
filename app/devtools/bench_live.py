"""Benchmark ``live`` (issue 32): how many frame sets a second the console fuses, against the
rate the sensors give, in the same run.

Two sources: a replay of a recording of the simulated head at its full rate (made first,
``trifuse record --source sim --duration 2``; the sensors' rate is the recording's colour
rate, from its statistics) and the simulated head itself (pose cache filled first, not
timed). For each, two phases of ``repeat`` windows of :data:`WINDOW_S` seconds:

- nobody watching the stream; a REST client asks ``/api/status`` once a second, which keeps
  the console fusing (its demand), as an operator's status page does;
- one local headless Chromium viewer of the H.264 stream (``/?stream=auto``), which decodes
  and draws it on the same machine.

Per window, from ``/api/status``: the fused frame sets a second (``fps``, the stream's own
rate), the left colour camera's delivered rate (``color_hz``, ``rates_hz``) and the frames of
it a replay dropped to keep real time (``dropped_hz``, the source's ``dropped``); their sum
(``speed_hz``) against the recording's rate is the replay's speed (a replay that slowed its
clock would deliver fewer and drop none), and the console's cores
(user + system CPU of its process tree over the window); with the viewer, the frames it
drew a second (``trifuseStats.fps``); and the cores each of the console's Python threads
used (``GET /api/threads``, ``thread_<name>_cores``: the fusion thread, its eye, depth and
replay-decode workers, the video encoder's ``asyncio`` workers, the server's ``MainThread``,
the background checks ``drift-check``, ``registration-sigma``, ``thermal-balance``; workers
of one pool summed; what C libraries' own threads use is in ``cores`` only). Medians over
the windows.

The replay's cost per frame set (the console's CPU over the frame sets it fused,
``replay_set_ms``) is compared with what a set needs, its steps measured alone on the same
recording in the same run (:mod:`app.devtools.live_steps`, ``step_*``), weighed by the rates
the console ran at (``replay_necessary_ms``): ``replay_cost_ratio`` (issue 32: at most 1.5).
"""

from __future__ import annotations

import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from trifuse.app.devtools.benchmark import benchmark, check_repeat
from trifuse.app.devtools.browser_console import headless_chromium, require_chromium
from trifuse.app.devtools.console_process import ConsoleProcess, prewarm_pose_cache
from trifuse.app.devtools.live_steps import necessary_ms, step_costs
from trifuse.app.procfs import tree_cpu_s

WINDOW_S = 10.0
"""One reading spans this many seconds; ``--repeat`` sets how many windows a phase has."""
SETTLE_S = 5.0
"""Before a phase's first window: the demand turns wanted, the rates' 3 s window fills."""
RECORD_S = 2.0
"""The recording replayed: this many seconds of the simulated head (it loops)."""
START_TIMEOUT_S = 180.0
COLOR = "ccd_left"


def _record(out: Path) -> float:
    """Record :data:`RECORD_S` s of the simulated head into ``out``; its colour rate (Hz)."""
    from trifuse.app.recording import ReplaySource

    command = [sys.executable, "-m", "trifuse.app.cli", "record", "--source", "sim"]
    command += ["--out", str(out), "--duration", f"{RECORD_S:g}"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"live: trifuse record failed: {done.stderr.strip()[-500:]}")
    with ReplaySource(out, realtime=False) as rec:
        count = rec.message_count(COLOR, "color")
        if not count or count < 2 or not rec.duration_s:
            raise RuntimeError(f"live: {out} has no {COLOR} rate in its statistics")
        return (count - 1) / rec.duration_s


def _dropped(status: dict[str, Any]) -> int:
    """The colour frames a replay dropped to keep real time so far (0 for other sources)."""
    return int(((status.get("source") or {}).get("dropped") or {}).get(COLOR, 0))


def _thread_cpu_s(console: ConsoleProcess) -> dict[str, float]:
    """CPU seconds so far per thread name (``GET /api/threads``), a pool's workers summed
    (``fusion-eye_0`` -> ``fusion_eye``)."""
    out: dict[str, float] = {}
    for t in console.get("/api/threads"):
        if t["cpu_s"] is not None:
            name = re.sub(r"[^a-z0-9]+", "_", re.sub(r"_\d+$", "", t["name"]).lower()).strip("_")
            out[name] = out.get(name, 0.0) + float(t["cpu_s"])
    return out


def _window(console: ConsoleProcess, page: Any | None) -> dict[str, float]:
    """One window of :data:`WINDOW_S` s, asking the status once a second."""
    fps: list[float] = []
    rates: dict[str, list[float]] = {}
    threads0 = _thread_cpu_s(console)
    cpu0, t0 = tree_cpu_s(console.pid), time.monotonic()
    first = console.status()
    dropped0, mapped0 = _dropped(first), int(first.get("depth_updates", 0))
    while time.monotonic() - t0 < WINDOW_S:
        status = console.status()
        fps.append(float(status["fps"]))
        for sensor, hz in status["rates_hz"].items():
            rates.setdefault(sensor, []).append(float(hz))
        time.sleep(1.0)
    elapsed = time.monotonic() - t0
    threads = _thread_cpu_s(console)
    last = console.status()
    dropped_hz = (_dropped(last) - dropped0) / elapsed
    color_hz = statistics.median(rates.get(COLOR, [0.0]))
    out = {
        "fps": statistics.median(fps),
        "color_hz": color_hz,
        "dropped_hz": dropped_hz,
        "speed_hz": color_hz + dropped_hz,
        "cores": (tree_cpu_s(console.pid) - cpu0) / elapsed,
        "mapped_hz": (int(last.get("depth_updates", 0)) - mapped0) / elapsed,
        **{f"rate_{s}_hz": statistics.median(v) for s, v in rates.items()},
        **{f"thread_{n}_cores": (v - threads0.get(n, 0.0)) / elapsed for n, v in threads.items()},
    }
    if page is not None:
        out["drawn_fps"] = float(page.evaluate("() => window.trifuseStats.fps"))
    return out


def _phase(console: ConsoleProcess, windows: int, page: Any | None) -> dict[str, float]:
    console.status()  # the demand turns wanted
    time.sleep(SETTLE_S)
    seen = [_window(console, page) for _ in range(windows)]
    keys = dict.fromkeys(k for w in seen for k in w)  # a thread may start in a later window
    return {k: statistics.median(w.get(k, 0.0) for w in seen) for k in keys}


def _source(
    console: ConsoleProcess,
    browser: Any,
    windows: int,
    name: str,
    costs: dict[str, float] | None,
) -> dict[str, float]:
    """Both phases on one console; figures named ``{name}_...`` and ``{name}_viewer_...``;
    with the steps' ``costs`` (:func:`~app.devtools.live_steps.step_costs`), the console's
    CPU per frame set (``set_ms``), what the set needs (``necessary_ms``) and their ratio."""
    alone = _phase(console, windows, None)
    page = browser.new_page(viewport={"width": 1400, "height": 700})
    try:
        url = console.signin("/")
        page.goto(url + ("&" if "?" in url else "?") + "stream=auto")
        page.wait_for_function(
            "() => window.trifuseStats && window.trifuseStats.frames > 10",
            timeout=START_TIMEOUT_S * 1000,
        )
        watched = _phase(console, windows, page)
    finally:
        page.close()
    figures = {}
    for prefix, phase, h264 in ((name, alone, False), (f"{name}_viewer", watched, True)):
        rates = {k[5:-3]: v for k, v in phase.items() if k.startswith("rate_")}
        figures.update({f"{prefix}_{k}": v for k, v in phase.items()})
        if costs is not None:  # the replay: its frames are those the steps were measured on
            need = necessary_ms(costs, rates, phase["fps"], phase["mapped_hz"], h264)
            cost = 1e3 * phase["cores"] / phase["fps"] if phase["fps"] > 0 else float("nan")
            figures.update({f"{prefix}_set_ms": cost, f"{prefix}_necessary_ms": need})
            figures[f"{prefix}_cost_ratio"] = cost / need
    return figures


@benchmark(
    "live",
    "the console's fused frame sets a second against the sensors' rate (same run): a replay "
    "of a full-rate recording and the simulated head, each with nobody watching and with one "
    "local Chromium viewer of the H.264 stream; cores; --repeat N: N windows of "
    f"{WINDOW_S:g} s per phase",
    baselines=(
        ("replay_fps", "sensor_fps"),
        ("replay_speed_hz", "sensor_fps"),
        ("replay_viewer_fps", "sensor_fps"),
        ("replay_viewer_speed_hz", "sensor_fps"),
        ("sim_fps", "sensor_fps"),
        ("sim_viewer_fps", "sensor_fps"),
    ),
    default_repeat=2,
)
def live(repeat: int) -> dict[str, float]:
    """See the module doc. ``sensor_fps``: the recording's colour rate (the simulated head
    gives the same 30 Hz); ``replay_speed_hz / sensor_fps`` is the replay's speed against
    real time."""
    check_repeat(repeat)
    require_chromium("live")
    prewarm_pose_cache()
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="trifuse-bench-live-") as tmp, headless_chromium() as b:
        recording = Path(tmp) / "sim.mcap"
        figures["sensor_fps"] = _record(recording)
        costs = step_costs(recording)
        figures.update({f"step_{k}": v for k, v in costs.items()})
        runs = (("replay", ["--replay", str(recording)], costs), ("sim", [], None))
        for name, args, source_costs in runs:
            log = Path(tmp) / f"{name}.log"
            args = [*args, "--workdir", str(Path(tmp) / f"work-{name}")]
            with ConsoleProcess(args, log_path=log, timeout_s=START_TIMEOUT_S) as console:
                try:
                    figures.update(_source(console, b, repeat, name, source_costs))
                except Exception as exc:
                    tail = console.output()[-2000:]
                    raise RuntimeError(f"live ({name}): {exc}; the console's log:\n{tail}") from exc
    return figures
