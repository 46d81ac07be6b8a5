"""The stream soak's settings, samples, figures and verdict (``trifuse bench --soak``; the
run itself and what the criteria mean: app/devtools/bench_soak.py). Pure: no I/O."""

from __future__ import annotations

import itertools
import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

MIN_FPS_RATIO = 0.9
"""Median fast-viewer fps over the soak / the 1-viewer baseline, at least."""
MIN_VIEWER_RATIO = 0.8
"""The slowest fast viewer's mean fps over the soak / the baseline, at least."""
MAX_RSS_SLOPE_MB_PER_MIN = 1.0
"""Server RSS growth after the warm-up, MB per minute, at most (why: app/devtools/bench_soak.py)."""
MIN_FIT_S = 120.0
"""The RSS slope is judged only when fitted over this many seconds at least."""
MAX_THREAD_GROWTH = 4
MAX_FD_GROWTH = 8

CRITERIA = (
    f"fast fps >= {MIN_FPS_RATIO} x baseline (median), slowest viewer >= "
    f"{MIN_VIEWER_RATIO} x; RSS slope <= {MAX_RSS_SLOPE_MB_PER_MIN} MB/min (judged from "
    f"{MIN_FIT_S:g} s of samples); threads +{MAX_THREAD_GROWTH}, fds +{MAX_FD_GROWTH} at "
    "most; no pose rendering; everyone connected and served"
)

SLOW_KINDS = ("ws", "mjpeg")


@dataclass(frozen=True)
class SoakConfig:
    """What ``trifuse bench --soak`` runs (defaults: the issue's ten-minute run); see the
    module docstring of app/devtools/bench_soak.py for the phases and the slow readers."""

    soak_s: float = 600.0
    """Length of the soak phase, seconds."""
    viewers: int = 10
    """Fast viewers during the soak (one during the baseline)."""
    baseline_s: float = 20.0
    """Length of the 1-viewer baseline phase, seconds."""
    window_s: float = 5.0
    """One row of the table: the viewers' and the server's figures over this many seconds."""
    warmup_s: float | None = None
    """Soak seconds before the RSS figures start; None: 10 % of the soak, 2-12 windows."""
    # -- the start
    prewarm: bool = True
    """Fill the disk cache of rendered poses before the console starts."""
    settle_s: float = 5.0
    """After the first frame, before the baseline: the console loads its poses."""
    start_timeout_s: float = 120.0
    """The console must answer within this many seconds of its start."""
    # -- the slow readers
    slow: tuple[str, ...] = SLOW_KINDS
    """The slow readers that join the soak (:data:`SLOW_KINDS`)."""
    rcvbuf: int = 4096
    """The slow readers' socket receive buffer, bytes."""
    ack_delay_s: float = 1.0
    """The slow WebSocket viewer acks a frame this long after it arrived, ..."""
    read_s: float = 20.0
    """... reads this long between stalls ..."""
    stall_s: float = 15.0
    """... and stops reading for this long (below the server's ping timeout of 20 s)."""
    mjpeg_bytes_per_s: int = 4096
    """The slow MJPEG reader's pace."""

    def warmup(self) -> float:
        """Soak seconds before the RSS figures start (``warmup_s`` or its default)."""
        if self.warmup_s is not None:
            return self.warmup_s
        return min(max(0.1 * self.soak_s, 2 * self.window_s), 12 * self.window_s, 60.0)

    def describe(self) -> str:
        """The run in a line, for the top of the output."""
        slow = []
        if "ws" in self.slow:
            slow.append(
                f"ws (ack after {self.ack_delay_s:g} s, stops reading for {self.stall_s:g} s "
                f"every {self.read_s + self.stall_s:g} s)"
            )
        if "mjpeg" in self.slow:
            slow.append(f"mjpeg ({self.mjpeg_bytes_per_s / 1e3:g} kB/s)")
        return (
            f"{self.viewers} fast viewers + slow: {', '.join(slow) or 'none'}; receive buffer "
            f"of the slow {self.rcvbuf} B; soak {self.soak_s:g} s after a 1-viewer baseline "
            f"of {self.baseline_s:g} s; windows of {self.window_s:g} s"
        )


# -- samples ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Window:
    """One sample: the window ending ``t_s`` seconds into its phase."""

    t_s: float
    fast_fps: tuple[float, ...]
    latency_ms: float
    rss_mb: float
    threads: int
    fds: int
    server_cpu_pct: float
    server_fps: float
    server_viewers: int
    slow_frames: dict[str, int] = field(default_factory=dict)
    slow_bytes: dict[str, int] = field(default_factory=dict)
    children: int = 0
    """The server's child processes: the simulated head's render process runs only while
    poses are missing from the disk cache."""

    @property
    def median_fps(self) -> float:
        return statistics.median(self.fast_fps) if self.fast_fps else math.nan

    @property
    def min_fps(self) -> float:
        return min(self.fast_fps) if self.fast_fps else math.nan

    @property
    def share(self) -> float:
        """The median fast viewer's frames / the frames the server published."""
        return self.median_fps / self.server_fps if self.server_fps > 0 else math.nan


@dataclass
class Phase:
    """The samples of one phase: its windows and the server's RSS every ``bench_soak.RSS_EVERY_S``
    (``rss``: pairs of seconds into the phase and MB)."""

    windows: list[Window] = field(default_factory=list)
    rss: list[tuple[float, float]] = field(default_factory=list)


# -- figures and criteria --------------------------------------------------------------


def slope_per_minute(t_s: Sequence[float], values: Sequence[float]) -> float:
    """Least-squares slope of ``values`` over ``t_s`` (seconds), per minute; NaN with
    fewer than two distinct times."""
    if len(t_s) != len(values):
        raise ValueError(f"slope: {len(t_s)} times but {len(values)} values")
    n = len(t_s)
    if n < 2:
        return math.nan
    mt = sum(t_s) / n
    mv = sum(values) / n
    sxx = sum((t - mt) ** 2 for t in t_s)
    if sxx == 0:
        return math.nan
    sxy = sum((t - mt) * (v - mv) for t, v in zip(t_s, values, strict=True))
    return 60.0 * sxy / sxx


@dataclass(frozen=True)
class Criterion:
    """One pass/fail condition. ``judged`` False: the run was too short to tell (the RSS
    slope of a run of seconds is the allocator's noise); it neither passes nor fails."""

    name: str
    value: float
    limit: str
    ok: bool
    judged: bool = True

    @property
    def failed(self) -> bool:
        return self.judged and not self.ok


@dataclass
class SoakReport:
    """What a soak measured: both phases, figures, the viewers' end state, criteria."""

    config: SoakConfig
    baseline: Phase
    soak: Phase
    figures: dict[str, float]
    viewers: list[dict[str, Any]]
    criteria: list[Criterion]

    @property
    def ok(self) -> bool:
        return not any(c.failed for c in self.criteria)

    def format(self) -> str:
        """The soak's table, then the summary and the criteria."""
        rows = [format_row(w, self.figures["baseline_fps"]) for w in self.soak.windows]
        return "\n".join([TABLE_HEAD, *rows, "", format_summary(self)])


TABLE_HEAD = (
    f"{'t_s':>6} {'fast_med':>8} {'fast_min':>8} {'ratio':>5} {'lat_ms':>6} {'srv_fps':>7} "
    f"{'srv_cpu%':>8} {'rss_mb':>7} {'thr':>4} {'fds':>4} {'viewers':>7}  slow: frames/kB"
)


def format_row(w: Window, baseline_fps: float) -> str:
    """One line of the table: the window ``w``; ``ratio`` is its median fast fps over
    ``baseline_fps``."""
    ratio = w.median_fps / baseline_fps if baseline_fps else math.nan
    slow = " ".join(f"{k} {w.slow_frames[k]}/{w.slow_bytes[k] / 1e3:.0f}" for k in w.slow_frames)
    return (
        f"{w.t_s:6.1f} {w.median_fps:8.1f} {w.min_fps:8.1f} {ratio:5.2f} {w.latency_ms:6.0f} "
        f"{w.server_fps:7.1f} {w.server_cpu_pct:8.0f} {w.rss_mb:7.1f} {w.threads:4d} "
        f"{w.fds:4d} {w.server_viewers:7d}  {slow}"
    ).rstrip()


def format_summary(report: SoakReport) -> str:
    """The figures in a few lines, the slow readers, errors, the criteria, PASS/FAIL."""
    f = report.figures
    lines = [
        f"baseline (1 viewer): {f['baseline_fps']:.1f} fps "
        f"(server published {f['baseline_server_fps']:.1f} fps; the viewer got "
        f"{100 * f['baseline_share']:.0f} % of them)",
        f"fast viewers ({f['viewers']:.0f}): median {f['fast_fps_median']:.1f} fps = "
        f"{f['fast_fps_ratio']:.2f} x baseline (server published {f['server_fps_median']:.1f}, "
        f"median viewer got {100 * f['fast_share']:.0f} % of them); "
        f"slowest viewer {f['fast_viewer_min_fps']:.1f} fps mean, worst window "
        f"{f['fast_window_min_fps']:.1f}; latency median {f['latency_ms_median']:.0f} ms",
        f"server RSS: {f['rss_start_mb']:.1f} MB after a {f['warmup_s']:.0f} s warm-up, end "
        f"{f['rss_end_mb']:.1f}, max {f['rss_max_mb']:.1f}, slope "
        f"{f['rss_slope_mb_per_min']:+.2f} MB/min ({f['rss_samples']:.0f} samples)",
        f"server threads {f['threads_start']:.0f} -> {f['threads_end']:.0f}, fds "
        f"{f['fds_start']:.0f} -> {f['fds_end']:.0f}, CPU {f['server_cpu_pct']:.0f} % "
        f"(this process {f['client_cpu_pct']:.0f} %)",
    ]
    for v in report.viewers:
        if v["kind"] != "fast":
            stalls = f"{v['stalls']} stalls, " if v["kind"] == "ws" else ""
            lines.append(
                f"slow {v['kind']}: {v['frames']} frames, {v['bytes'] / 1e3:.0f} kB, {stalls}"
                + (f"ERROR {v['error']}" if v["error"] else "connected to the end")
            )
    for v in report.viewers:
        if v["kind"] == "fast" and v["error"]:
            lines.append(f"fast viewer {v['index']}: ERROR {v['error']}")
    lines.append("criteria:")
    for c in report.criteria:
        mark = "FAIL" if c.failed else "ok  " if c.judged else "n/a "
        lines.append(f"  {mark} {c.name} = {c.value:.3g} ({c.limit})")
    unjudged = [c.name for c in report.criteria if not c.judged]
    verdict = "PASS" if report.ok else "FAIL"
    if unjudged:
        verdict += f" (not judged, the run is too short: {', '.join(unjudged)})"
    lines.append(verdict)
    return "\n".join(lines)


def median_of(values: Sequence[float]) -> float:
    """The median of the values that are not NaN (NaN: nothing measured); NaN if none."""
    values = [v for v in values if v == v]  # NaN: nothing measured
    return statistics.median(values) if values else math.nan


def summarize(
    cfg: SoakConfig,
    baseline: Phase,
    soak: Phase,
    viewers: Sequence[dict[str, Any]],
    client_cpu_pct: float = math.nan,
) -> tuple[dict[str, float], list[Criterion]]:
    """Figures and criteria from both phases and the viewers' end state (dicts with
    ``kind``, ``frames``, ``bytes``, ``error``; ``kind`` ``fast`` or a slow kind)."""
    windows = soak.windows
    base_fps = median_of([w.median_fps for w in baseline.windows])
    warmup = cfg.warmup()
    rss = [(t, mb) for t, mb in soak.rss if t >= warmup - 1e-6]
    late = [w for w in windows if w.t_s >= warmup - 1e-6] or windows[-1:]
    n_fast = len(windows[0].fast_fps) if windows else 0
    durations = [b - a for a, b in itertools.pairwise([0.0, *(w.t_s for w in windows)])]
    soak_s = windows[-1].t_s if windows else math.nan
    per_viewer = [
        sum(w.fast_fps[i] * dt for w, dt in zip(windows, durations, strict=True)) / soak_s
        for i in range(n_fast)
    ]
    nan = math.nan
    fig: dict[str, float] = {
        "viewers": float(n_fast),
        "baseline_fps": base_fps,
        "baseline_server_fps": median_of([w.server_fps for w in baseline.windows]),
        "baseline_share": median_of([w.share for w in baseline.windows]),
        "fast_fps_median": median_of([w.median_fps for w in windows]),
        "fast_viewer_min_fps": min(per_viewer, default=nan),
        "fast_window_min_fps": min((w.min_fps for w in windows), default=nan),
        "latency_ms_median": median_of([w.latency_ms for w in windows]),
        "server_fps_median": median_of([w.server_fps for w in windows]),
        "fast_share": median_of([w.share for w in windows]),
        "server_cpu_pct": median_of([w.server_cpu_pct for w in windows]),
        "client_cpu_pct": client_cpu_pct,
        "warmup_s": warmup,
        "rss_start_mb": rss[0][1] if rss else nan,
        "rss_end_mb": rss[-1][1] if rss else nan,
        "rss_max_mb": max((mb for _, mb in rss), default=nan),
        "rss_slope_mb_per_min": slope_per_minute([t for t, _ in rss], [mb for _, mb in rss]),
        "rss_samples": float(len(rss)),
        "threads_start": float(late[0].threads) if late else nan,
        "threads_end": float(windows[-1].threads) if windows else nan,
        "fds_start": float(late[0].fds) if late else nan,
        "fds_end": float(windows[-1].fds) if windows else nan,
        "render_processes": float(max((w.children for w in late), default=0)),
    }
    fig["fast_fps_ratio"] = fig["fast_fps_median"] / base_fps if base_fps else nan
    fig["fast_viewer_min_ratio"] = fig["fast_viewer_min_fps"] / base_fps if base_fps else nan
    for v in viewers:
        if v["kind"] != "fast":
            fig[f"slow_{v['kind']}_frames"] = float(v["frames"])
            fig[f"slow_{v['kind']}_kb"] = v["bytes"] / 1e3

    slope = fig["rss_slope_mb_per_min"]
    fit_s = (rss[-1][0] - rss[0][0]) if rss else 0.0
    threads = fig["threads_end"] - fig["threads_start"]
    fds = fig["fds_end"] - fig["fds_start"]
    connected = sum(1 for v in viewers if not v["error"])
    progress = all(v["bytes"] > 0 for v in viewers if v["kind"] != "fast")
    ratio, min_ratio = fig["fast_fps_ratio"], fig["fast_viewer_min_ratio"]
    worst = fig["fast_window_min_fps"]
    renders = fig["render_processes"]
    criteria = [  # comparisons with NaN are False: nothing measured fails
        Criterion("fast_fps_ratio", ratio, f">= {MIN_FPS_RATIO}", ratio >= MIN_FPS_RATIO),
        Criterion(
            "fast_viewer_min_ratio",
            min_ratio,
            f">= {MIN_VIEWER_RATIO}",
            min_ratio >= MIN_VIEWER_RATIO,
        ),
        Criterion(
            "rss_slope_mb_per_min",
            slope,
            f"<= {MAX_RSS_SLOPE_MB_PER_MIN}, fitted over {fit_s:.0f} s after the warm-up",
            slope <= MAX_RSS_SLOPE_MB_PER_MIN,
            judged=fit_s >= MIN_FIT_S,
        ),
        Criterion(
            "thread_growth", threads, f"<= {MAX_THREAD_GROWTH}", threads <= MAX_THREAD_GROWTH
        ),
        Criterion("fd_growth", fds, f"<= {MAX_FD_GROWTH}", fds <= MAX_FD_GROWTH),
        Criterion(
            "fast_window_min_fps", worst, "> 0: every fast viewer served in every window", worst > 0
        ),
        Criterion(
            "render_processes",
            renders,
            "== 0 after the warm-up: the console renders no poses (its RSS would grow by "
            "8.4 MB a pose: the disk cache was not full)",
            renders == 0,
        ),
        Criterion(
            "viewers_connected",
            float(connected),
            f"== {len(viewers)} to the end; each slow reader got data",
            connected == len(viewers) and progress,
        ),
    ]
    return fig, criteria


# -- the video stream's viewers (``trifuse bench --soak --video``) --------------------------


@dataclass(frozen=True)
class VideoLoadConfig:
    """What ``trifuse bench --soak --video`` runs: for each count of :attr:`counts`, that
    many viewers of ``/stream.video`` at once (each acknowledges every frame as it arrives),
    measured for :attr:`step_s`; ``runs`` times, a fresh console each time."""

    counts: tuple[int, ...] = (1, 10, 50)
    """Viewers at once, one step each, in this order."""
    step_s: float = 30.0
    """Each step's measuring time, seconds."""
    runs: int = 1
    """Repeats of the whole run (the summary gives the median of each figure)."""
    preset: str = "auto"
    """The viewers' preset (``?preset=``)."""
    settle_s: float = 5.0
    """After every viewer got its first frame, before measuring."""
    after_s: float = 15.0
    """After the viewers left, before the console's memory is read again."""
    status_every_s: float = 1.0
    """``/api/status`` is asked this often while measuring (its answer time is a figure)."""
    prewarm: bool = True
    """Fill the disk cache of rendered poses before the console starts."""
    start_timeout_s: float = 180.0
    """The console must answer, and every viewer have a frame, within this many seconds."""

    def describe(self) -> str:
        return (
            f"/stream.video viewers {', '.join(map(str, self.counts))} (preset {self.preset}),"
            f" {self.step_s:g} s each after {self.settle_s:g} s to settle; memory again "
            f"{self.after_s:g} s after they left; {self.runs} run(s)"
        )


@dataclass(frozen=True)
class VideoStep:
    """One step: ``viewers`` at once. Frame rates are over the measuring time.

    Attributes:
        viewer_fps: each viewer's frames per second.
        console_fps: frames the console published per second (its own rate).
        status_ms: each ``/api/status`` answer time, ms (NaN: no answer).
        latency_ms: median from publication (``sent_ns``) to a viewer having the frame, ms.
        server_cpu_pct: the console's CPU, % of one core.
        rss_before_mb, rss_after_mb: the console's RSS before the viewers came and
            ``after_s`` after they left, MB.
        rss_during_mb: its RSS samples while they watched, MB.
        rungs: distinct (level, bitrate) of the viewers' last frames: the encoders in use
            when viewers share them (one per viewer before they did).
        levels: viewers per level of their last frame.
        errors: viewers that ended with an error.
    """

    viewers: int
    viewer_fps: tuple[float, ...]
    console_fps: float
    status_ms: tuple[float, ...]
    latency_ms: float
    server_cpu_pct: float
    rss_before_mb: float
    rss_during_mb: tuple[float, ...]
    rss_after_mb: float
    rungs: int
    levels: dict[str, int]
    errors: int = 0

    def figures(self) -> dict[str, float]:
        """The step in numbers (the medians of runs are taken over these)."""
        status = [s for s in self.status_ms if s == s]
        return {
            "fps_median": median_of(list(self.viewer_fps)),
            "fps_min": min(self.viewer_fps, default=math.nan),
            "console_fps": self.console_fps,
            "status_ms_median": median_of(status),
            "status_ms_max": max(status, default=math.nan),
            "latency_ms": self.latency_ms,
            "server_cpu_pct": self.server_cpu_pct,
            "rss_before_mb": self.rss_before_mb,
            "rss_during_max_mb": max(self.rss_during_mb, default=math.nan),
            "rss_after_mb": self.rss_after_mb,
            "rungs": float(self.rungs),
            "errors": float(self.errors),
        }


VIDEO_HEAD = (
    f"{'viewers':>7} {'fps_med':>7} {'fps_min':>7} {'console':>7} {'status_ms':>11} "
    f"{'lat_ms':>6} {'cpu%':>5} {'rss_before':>10} {'rss_max':>7} {'rss_after':>9} "
    f"{'rungs':>5}  levels"
)


def format_video_row(viewers: int, f: dict[str, float], levels: str = "") -> str:
    """One line of the video table: a step's :meth:`VideoStep.figures` (or their medians)."""
    status = f"{f['status_ms_median']:.0f}/{f['status_ms_max']:.0f}"
    errors = f"  ERRORS {f['errors']:.0f}" if f["errors"] else ""
    return (
        f"{viewers:7d} {f['fps_median']:7.2f} {f['fps_min']:7.2f} {f['console_fps']:7.2f} "
        f"{status:>11} {f['latency_ms']:6.0f} {f['server_cpu_pct']:5.0f} "
        f"{f['rss_before_mb']:10.0f} {f['rss_during_max_mb']:7.0f} {f['rss_after_mb']:9.0f} "
        f"{f['rungs']:5.0f}  {levels}{errors}"
    ).rstrip()


def video_medians(runs: Sequence[Sequence[VideoStep]]) -> list[tuple[int, dict[str, float]]]:
    """For each viewer count, the median over ``runs`` of each figure (a run: its steps in
    the order of the counts)."""
    if not runs:
        return []
    out = []
    for i, step in enumerate(runs[0]):
        per_run = [run[i].figures() for run in runs if len(run) > i]
        out.append((step.viewers, {k: median_of([f[k] for f in per_run]) for k in per_run[0]}))
    return out
