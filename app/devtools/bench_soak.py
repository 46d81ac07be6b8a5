"""``trifuse bench --soak``: the console's stream under load for minutes (issue 8, "Load").

Ten viewers on the stream plus slow readers; the fast viewers must keep the frame rate and
the server's memory must stay flat. Not a registered benchmark (``app.devtools.bench.REGISTRY``): it
runs for minutes, has its own options and passes or fails (exit code 1).

What runs:

- ``trifuse serve`` on the simulated inspection room, a subprocess with a temporary work
  directory and its own random token (``TRIFUSE_TOKEN``), its output into a log file (a
  pipe nobody reads would stall it once full). The disk cache of rendered head poses is
  filled first (not timed; seconds when it is already full), so that the console loads
  every pose at start instead of rendering them during the soak (its memory would grow
  by 8.4 MB a pose: not a leak, but it would hide one).
- Baseline phase: one viewer (``/stream``, websockets client, ``ack`` at once) for
  ``baseline_s``; its frames per second, median over windows, is the baseline.
- Soak phase, ``soak_s``: ``viewers`` such fast viewers, plus the slow readers:

  - ``ws``: a WebSocket viewer on a raw socket with a small receive buffer
    (``SO_RCVBUF`` ``rcvbuf`` bytes, set before connecting) that acks each frame only
    ``ack_delay_s`` after it arrived, and every ``read_s`` seconds stops reading its
    socket altogether for ``stall_s`` (right after an ack, so a frame is in flight);
    pings are answered only when it reads, so ``stall_s`` stays below the server's
    ping timeout (20 s);
  - ``mjpeg``: an MJPEG reader (``/stream.mjpg``, the fallback of a plain ``<img>``) on a
    socket with the same small receive buffer that reads ``mjpeg_bytes_per_s`` (default
    4 kB/s: one frame of 0.15-0.2 MB in 40-50 s). The harshest case: the server has no ack to
    wait for, only TCP backpressure; it must not buffer the frames it cannot send.

  Every ``window_s`` seconds: each fast viewer's frames per second over the window, the
  median latency from the server publishing a frame (``sent_ns``) to a fast viewer having
  it, the slow readers' progress, of the server process (``/proc/PID``) threads, open file
  descriptors, CPU and child processes, and from ``/api/status`` the frames published
  and the viewers counted. The server's resident memory (``VmRSS``) every second: the
  console's RSS swings by tens of MB from one second to the next (695-728 MB over two
  minutes with two viewers and nothing else), so the slope is fitted over many samples.

Criteria (:data:`CRITERIA`; exit 1 if one fails):

- the median over windows of the fast viewers' median fps is at least 0.9 x the
  baseline, and the slowest fast viewer (its mean over the soak) at least 0.8 x;
- the server's RSS grows by at most 1 MB a minute: least-squares slope over the samples
  after the warm-up (the first ``warmup_s``, default 10 % of the soak, at least two
  windows, at most 60 s: connections, buffers and allocator arenas settle). Why 1 MB/min:
  a leak of one JPEG (0.15-0.2 MB) per frame the slow WebSocket viewer takes shows as
  about 10 MB/min, a leak of 100 bytes per frame sent to 11 viewers at 15 fps as 1
  MB/min; over the 540 samples of a ten-minute run the slope's standard error is about
  0.3 MB/min (RSS noise of about 20 MB), so 1 MB/min is about three of them; 10 MB over
  10 minutes is under 2 % of the console's RSS (about 650 MB, most of it the 31 cached
  poses). Judged only when fitted over at least 2 minutes (:data:`MIN_FIT_S`): the slope
  of a run of seconds is noise; shorter runs report it as "n/a";
- threads and file descriptors: at most 4 and 8 more at the end than after the warm-up
  (the connections do not change during the soak);
- no render process after the warm-up: the console renders poses only while its disk
  cache misses some (another version of the simulator's code), and its RSS then grows by
  8.4 MB a pose: the run says nothing about leaks;
- every viewer stays connected, every fast viewer receives frames in every window and
  each slow reader gets data.

``trifuse bench --soak --video`` (:func:`run_video_load`) measures the video stream
instead (issue 29, "Load"): a console as above, warmed up by one viewer; then for each
count N of :attr:`VideoLoadConfig.counts` (default 1, 10, 50), N viewers of
``/stream.video`` at once (:class:`app.devtools.stream_clients.VideoViewer`: acks each
frame as it arrives, does not decode), for ``step_s`` after they all have a frame and
``settle_s`` more: each viewer's frames per second, the console's own rate (frames
published), the answer time of ``/api/status`` asked every second, the latency, the
console's CPU, its RSS before the viewers came, while they watched and ``after_s`` after
they left, and the (level, bitrate) rungs the viewers were on. No criteria: the figures
are for BENCHMARKS.md; exit 1 only if a viewer failed.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from trifuse.app.devtools.console_process import ConsoleProcess, prewarm_pose_cache
from trifuse.app.devtools.soak_report import (
    CRITERIA,
    SLOW_KINDS,
    TABLE_HEAD,
    VIDEO_HEAD,
    Phase,
    SoakConfig,
    SoakReport,
    VideoLoadConfig,
    VideoStep,
    Window,
    format_row,
    format_summary,
    format_video_row,
    median_of,
    summarize,
    video_medians,
)
from trifuse.app.devtools.stream_clients import (
    FastViewer,
    SlowMjpegReader,
    SlowWsViewer,
    StreamClient,
    VideoViewer,
    cancel,
    wait_first_frames,
)
from trifuse.app.procfs import sample_process

# -- sampling -----------------------------------------------------------------------------


async def _frames_out(console: ConsoleProcess) -> tuple[float, int]:
    """(frames the console has published, viewers it counts) from ``/api/status``; NaN
    and -1 if it does not answer."""
    try:
        status = await asyncio.to_thread(console.status)
        return float(status["frames_out"]), int(status["viewers"])
    except (OSError, ValueError, KeyError):
        return math.nan, -1


RSS_EVERY_S = 1.0
"""The server's RSS is read this often (more samples: a slope less swayed by the
allocator's ups and downs, which reach tens of MB between seconds)."""


async def sample_phase(
    console: ConsoleProcess,
    fast: Sequence[FastViewer],
    slow: Sequence[SlowWsViewer | SlowMjpegReader],
    duration_s: float,
    window_s: float,
    on_window: Callable[[Window], None] | None = None,
) -> Phase:
    """For ``duration_s``: every ``window_s`` the viewers' progress and the server's
    process and status, every :data:`RSS_EVERY_S` the server's RSS."""
    t0 = time.monotonic()
    t_prev = t0
    frames_prev = [v.frames for v in fast]
    cpu_prev = sample_process(console.pid).cpu_s
    published_prev = await _frames_out(console)
    phase = Phase()
    per_window = math.ceil(window_s / RSS_EVERY_S)
    tick = window_s / per_window  # windows end on ticks
    k = 0
    while True:
        k += 1
        await asyncio.sleep(max(0.0, t0 + min(k * tick, duration_s) - time.monotonic()))
        now = time.monotonic()
        proc = sample_process(console.pid)
        phase.rss.append((now - t0, proc.rss_mb))
        last = now - t0 >= duration_s - 1e-3
        if k % per_window and not last:
            continue
        dt = now - t_prev
        frames = [v.frames for v in fast]
        fps = tuple((f - p) / dt for f, p in zip(frames, frames_prev, strict=True))
        latencies = [x for v in fast for x in v.latencies_ms]
        for v in fast:
            v.latencies_ms.clear()
        published = await _frames_out(console)
        w = Window(
            t_s=now - t0,
            fast_fps=fps,
            latency_ms=statistics.median(latencies) if latencies else math.nan,
            rss_mb=proc.rss_mb,
            threads=proc.threads,
            fds=proc.fds,
            server_cpu_pct=100.0 * (proc.cpu_s - cpu_prev) / dt,
            server_fps=(published[0] - published_prev[0]) / dt,
            server_viewers=published[1],
            slow_frames={v.kind: v.frames for v in slow},
            slow_bytes={v.kind: v.bytes for v in slow},
            children=proc.children,
        )
        phase.windows.append(w)
        if on_window is not None:
            on_window(w)
        t_prev, frames_prev, cpu_prev, published_prev = now, frames, proc.cpu_s, published
        if last:
            return phase


# -- the run ------------------------------------------------------------------------------


def _viewer_state(i: int, v: StreamClient) -> dict[str, Any]:
    """What the report keeps of a client at the end."""
    return {
        "index": i,
        "kind": v.kind,
        "frames": v.frames,
        "bytes": v.bytes,
        "stalls": v.stalls,
        "error": v.error,
    }


async def soak(
    console: ConsoleProcess, cfg: SoakConfig, out: Callable[[str], None] = print
) -> SoakReport:
    """Both phases against a running console; prints a row per window to ``out``."""
    base_fps = math.nan

    def show(w: Window) -> None:
        out(format_row(w, base_fps))

    first = FastViewer(console.ws_url, console.token)
    task = asyncio.create_task(first.run())
    try:
        await wait_first_frames([first], cfg.start_timeout_s)
        await asyncio.sleep(cfg.settle_s)
        out(f"baseline: 1 viewer for {cfg.baseline_s:g} s")
        out(TABLE_HEAD)
        baseline = await sample_phase(console, [first], [], cfg.baseline_s, cfg.window_s, show)
    finally:
        await cancel([task])
    if first.error:
        raise RuntimeError(f"the baseline viewer failed: {first.error}")
    base_fps = median_of([w.median_fps for w in baseline.windows])
    out(f"baseline: {base_fps:.1f} fps")

    fast = [FastViewer(console.ws_url, console.token) for _ in range(cfg.viewers)]
    where = (console.host, console.port, console.token)
    slow: list[SlowWsViewer | SlowMjpegReader] = []
    if "ws" in cfg.slow:
        pace = {"ack_delay_s": cfg.ack_delay_s, "read_s": cfg.read_s, "stall_s": cfg.stall_s}
        slow.append(SlowWsViewer(*where, rcvbuf=cfg.rcvbuf, **pace))
    if "mjpeg" in cfg.slow:
        slow.append(SlowMjpegReader(*where, rcvbuf=cfg.rcvbuf, bytes_per_s=cfg.mjpeg_bytes_per_s))
    tasks = [asyncio.create_task(v.run()) for v in [*fast, *slow]]
    try:
        await wait_first_frames(fast, cfg.start_timeout_s)
        out(f"soak: {cfg.viewers} fast viewers + slow {', '.join(cfg.slow) or 'none'}")
        out(TABLE_HEAD)
        cpu0, t0 = time.process_time(), time.monotonic()
        phase = await sample_phase(console, fast, slow, cfg.soak_s, cfg.window_s, show)
        client_cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - t0)
    finally:
        await cancel(tasks)
    viewers = [_viewer_state(i, v) for i, v in enumerate([*fast, *slow])]
    figures, criteria = summarize(cfg, baseline, phase, viewers, client_cpu)
    return SoakReport(cfg, baseline, phase, figures, viewers, criteria)


@contextlib.contextmanager
def _inspection_console(
    start_timeout_s: float, out: Callable[[str], None]
) -> Iterator[ConsoleProcess]:
    """``trifuse serve`` on the simulated inspection room in a temporary work directory,
    stopped at the end; its log's tail is said if the block fails."""
    with tempfile.TemporaryDirectory(prefix="trifuse-soak-") as tmp:
        console = ConsoleProcess(
            ["--scenario", "inspection", "--workdir", str(Path(tmp) / "work")],
            log_path=Path(tmp) / "serve.log",
            timeout_s=start_timeout_s,
        )
        with console:
            try:
                yield console
            except BaseException:
                out(f"console log:\n{console.output()[-2000:]}")
                raise


def run_soak(cfg: SoakConfig, out: Callable[[str], None] = print) -> SoakReport:
    """Start a console, run :func:`soak` against it, stop it."""
    if cfg.viewers < 1 or cfg.soak_s <= 0 or cfg.baseline_s <= 0 or cfg.window_s <= 0:
        raise ValueError("soak: viewers, soak_s, baseline_s and window_s must be positive")
    unknown = set(cfg.slow) - set(SLOW_KINDS)
    if unknown:
        raise ValueError(f"soak: unknown slow readers {sorted(unknown)} (known: {SLOW_KINDS})")
    if cfg.prewarm:
        t = time.monotonic()
        poses = prewarm_pose_cache()
        out(f"pose cache: {poses} poses on disk ({time.monotonic() - t:.1f} s)")
    with _inspection_console(cfg.start_timeout_s, out) as console:
        out(f"console: pid {console.pid}, port {console.port}")
        return asyncio.run(soak(console, cfg, out))


def run_soak_cli(cfg: SoakConfig) -> int:
    """``trifuse bench --soak``: rows as they come, then the table and the verdict; 0 if
    every criterion holds, else 1."""

    def out(line: str) -> None:
        print(line, flush=True)

    out(f"stream soak: {cfg.describe()}")
    out(f"criteria: {CRITERIA}")
    report = run_soak(cfg, out)
    out("")
    out(format_summary(report))
    return 0 if report.ok else 1


# -- the video stream's viewers -----------------------------------------------------------


async def _status_ms(console: ConsoleProcess) -> float:
    """How long ``GET /api/status`` takes to answer, ms (NaN: no answer within 30 s)."""
    t0 = time.perf_counter()
    try:
        await asyncio.to_thread(console.request, "/api/status", "GET", None, 30.0)
    except (OSError, ValueError):
        return math.nan
    return (time.perf_counter() - t0) * 1000


def _video_url(console: ConsoleProcess, preset: str) -> str:
    return f"{console.url.replace('http', 'ws', 1)}/stream.video?preset={preset}"


async def video_step(console: ConsoleProcess, cfg: VideoLoadConfig, n: int) -> VideoStep:
    """``n`` video viewers at once (see the module doc); the step's figures."""
    rss_before = sample_process(console.pid).rss_mb
    viewers = [VideoViewer(_video_url(console, cfg.preset), console.token) for _ in range(n)]
    tasks = [asyncio.create_task(v.run()) for v in viewers]
    try:
        await wait_first_frames(viewers, cfg.start_timeout_s)
        await asyncio.sleep(cfg.settle_s)
        frames0 = [v.frames for v in viewers]
        for v in viewers:
            v.latencies_ms.clear()
        published0 = (await _frames_out(console))[0]
        cpu0, t0 = sample_process(console.pid).cpu_s, time.monotonic()
        status: list[float] = []
        rss: list[float] = []
        k = 0
        while time.monotonic() - t0 < cfg.step_s:
            status.append(await _status_ms(console))
            rss.append(sample_process(console.pid).rss_mb)
            k += 1
            await asyncio.sleep(max(0.0, t0 + k * cfg.status_every_s - time.monotonic()))
        dt = time.monotonic() - t0
        fps = tuple((v.frames - f0) / dt for v, f0 in zip(viewers, frames0, strict=True))
        published = (await _frames_out(console))[0]
        cpu = sample_process(console.pid).cpu_s
        latencies = [x for v in viewers for x in v.latencies_ms]
        levels: dict[str, int] = {}
        for v in viewers:
            levels[v.level] = levels.get(v.level, 0) + 1
        rungs = len({(v.level, v.bitrate_bps) for v in viewers})
    finally:
        await cancel(tasks)
    await asyncio.sleep(cfg.after_s)
    return VideoStep(
        viewers=n,
        viewer_fps=fps,
        console_fps=(published - published0) / dt,
        status_ms=tuple(status),
        latency_ms=statistics.median(latencies) if latencies else math.nan,
        server_cpu_pct=100.0 * (cpu - cpu0) / dt,
        rss_before_mb=rss_before,
        rss_during_mb=tuple(rss),
        rss_after_mb=sample_process(console.pid).rss_mb,
        rungs=rungs,
        levels=dict(sorted(levels.items())),
        errors=sum(1 for v in viewers if v.error),
    )


def _levels(levels: dict[str, int]) -> str:
    return " ".join(f"{n}x{name}" for name, n in levels.items())


async def video_load(
    console: ConsoleProcess, cfg: VideoLoadConfig, out: Callable[[str], None] = print
) -> list[VideoStep]:
    """One run against a running console: a warm-up viewer, then each step; a row each."""
    warm = VideoViewer(_video_url(console, cfg.preset), console.token)
    task = asyncio.create_task(warm.run())
    try:
        await wait_first_frames([warm], cfg.start_timeout_s)
        await asyncio.sleep(2 * cfg.settle_s)  # the console loads its poses meanwhile
    finally:
        await cancel([task])
    await asyncio.sleep(cfg.after_s)
    out(VIDEO_HEAD)
    steps = []
    for n in cfg.counts:
        step = await video_step(console, cfg, n)
        out(format_video_row(n, step.figures(), _levels(step.levels)))
        steps.append(step)
    return steps


def run_video_load(
    cfg: VideoLoadConfig, out: Callable[[str], None] = print
) -> list[list[VideoStep]]:
    """``cfg.runs`` runs, each on a console of its own (started and stopped here)."""
    if not cfg.counts or min(cfg.counts) < 1 or cfg.step_s <= 0 or cfg.runs < 1:
        raise ValueError("video load: counts, step_s and runs must be positive")
    if cfg.prewarm:
        t = time.monotonic()
        poses = prewarm_pose_cache()
        out(f"pose cache: {poses} poses on disk ({time.monotonic() - t:.1f} s)")
    runs = []
    for r in range(cfg.runs):
        with _inspection_console(cfg.start_timeout_s, out) as console:
            out(f"run {r + 1}/{cfg.runs}: console pid {console.pid}, port {console.port}")
            runs.append(asyncio.run(video_load(console, cfg, out)))
    return runs


def run_video_load_cli(cfg: VideoLoadConfig) -> int:
    """``trifuse bench --soak --video``: rows as they come, then the medians over the runs;
    0, or 1 if a viewer failed."""

    def out(line: str) -> None:
        print(line, flush=True)

    out(f"video load: {cfg.describe()}")
    runs = run_video_load(cfg, out)
    out("")
    out(f"median of {len(runs)} run(s):")
    out(VIDEO_HEAD)
    for n, figures in video_medians(runs):
        out(format_video_row(n, figures))
    return 1 if any(step.errors for run in runs for step in run) else 0
