"""``trifuse bench --soak`` (app/devtools/bench_soak.py, with soak_report.py, app/procfs.py
and stream_clients.py): its pure helpers, the command line, and a short run of the whole
machinery against a real console (no performance assertions: the figures are for
BENCHMARKS.md, measured on an idle machine)."""

from __future__ import annotations

import math
import os
import random

import pytest

from trifuse.app.cli import main
from trifuse.app.devtools import bench_soak, soak_report
from trifuse.app.devtools.soak_report import (
    Phase,
    SoakConfig,
    VideoLoadConfig,
    VideoStep,
    Window,
    slope_per_minute,
    summarize,
)
from trifuse.app.devtools.stream_clients import MjpegParts
from trifuse.app.procfs import parse_proc_cpu_s, parse_proc_status, sample_process

# -- the slope fit --------------------------------------------------------------------------


def test_slope_of_a_line_is_exact():
    t = [0.0, 10.0, 20.0, 30.0, 60.0]
    assert slope_per_minute(t, [100 + 0.5 * x / 60 for x in t]) == pytest.approx(0.5)
    assert slope_per_minute(t, [7.0] * len(t)) == pytest.approx(0.0)
    assert slope_per_minute([0.0, 60.0], [10.0, 4.0]) == pytest.approx(-6.0)


def test_slope_is_least_squares():
    # symmetric noise around a line leaves its slope; an outlier in the middle too
    t = [0.0, 30.0, 60.0, 90.0, 120.0]
    values = [10.0, 11.0 + 3.0, 12.0 - 6.0, 13.0 + 3.0, 14.0]
    assert slope_per_minute(t, values) == pytest.approx(2.0)
    rng = random.Random(1)
    t = [float(i) for i in range(600)]
    noisy = [500 + 0.2 * x / 60 + rng.gauss(0, 10) for x in t]
    assert slope_per_minute(t, noisy) == pytest.approx(0.2, abs=0.3)


def test_slope_needs_two_times():
    assert math.isnan(slope_per_minute([], []))
    assert math.isnan(slope_per_minute([5.0], [1.0]))
    assert math.isnan(slope_per_minute([5.0, 5.0], [1.0, 2.0]))
    with pytest.raises(ValueError, match="2 times but 1 values"):
        slope_per_minute([0.0, 1.0], [1.0])


# -- /proc ----------------------------------------------------------------------------------


def test_parse_proc_status_and_stat():
    status = "Name:\tpython\nVmPeak:\t  900000 kB\nVmRSS:\t  524288 kB\nThreads:\t17\n"
    assert parse_proc_status(status) == (512.0, 17)
    with pytest.raises(ValueError, match="VmRSS"):
        parse_proc_status("Name:\tzombie\nThreads:\t1\n")
    tick = os.sysconf("SC_CLK_TCK")
    # a command name with spaces and parentheses; utime and stime are fields 14 and 15
    fields = ["S", "1", "2", "3", "4", "5", "6", "7", "8", "9", "10", str(3 * tick), str(tick)]
    stat = "4242 (python (soak) x) " + " ".join([*fields, "20", "0", "1"])
    assert parse_proc_cpu_s(stat) == pytest.approx(4.0)


def test_sample_process_of_this_process():
    s = sample_process(os.getpid())
    assert s.rss_mb > 1 and s.threads >= 1 and s.fds >= 3 and s.cpu_s > 0


# -- MJPEG parts ----------------------------------------------------------------------------


def _part(jpeg: bytes) -> bytes:
    # as app/server/runtime/stream.py writes them
    return (
        b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
        + str(len(jpeg)).encode()
        + b"\r\n\r\n"
        + jpeg
        + b"\r\n"
    )


def test_mjpeg_parts_counts_complete_parts_in_any_chunking():
    # bodies that contain CRLFs, blank lines and the boundary text itself
    bodies = [b"\xff\xd8" + bytes(range(256)) * 40, b"\r\n\r\n--frame\r\n" * 50, b"x"]
    stream = b"".join(_part(b) for b in bodies)
    for size in (1, 7, 1000, len(stream)):
        parts = MjpegParts()
        for i in range(0, len(stream), size):
            parts.feed(stream[i : i + size])
        assert parts.parts == 3, size
    parts = MjpegParts()
    parts.feed(stream[:-1])  # the last part's closing CRLF is missing
    assert parts.parts == 2
    parts.feed(stream[-1:])
    assert parts.parts == 3


def test_mjpeg_parts_refuses_what_is_not_the_stream():
    with pytest.raises(ValueError, match="part headers"):
        MjpegParts().feed(b"--frame\r\nContent-Type: image/jpeg\r\n\r\nabc")
    with pytest.raises(ValueError, match="no end of part headers"):
        MjpegParts().feed(b"x" * (MjpegParts.MAX_HEADER + 10))


# -- figures and criteria -------------------------------------------------------------------


def _window(t: float, fps: tuple[float, ...], rss: float = 500.0, **kw) -> Window:
    args = {
        "latency_ms": 5.0,
        "threads": 20,
        "fds": 30,
        "server_cpu_pct": 50.0,
        "server_fps": 20.0,
        "server_viewers": len(fps),
    }
    args.update(kw)
    return Window(t, fps, rss_mb=rss, **args)


def _phases(fast_fps: float, slope_mb_per_min: float, soak_s: float = 300.0):
    baseline = Phase([_window(5.0 * (i + 1), (20.0,)) for i in range(4)])
    n = int(soak_s / 5)
    windows = [_window(5.0 * (i + 1), (fast_fps, fast_fps + 1, fast_fps - 1)) for i in range(n)]
    rss = [(float(t), 500.0 + slope_mb_per_min * t / 60 + (-1) ** t) for t in range(1, n * 5 + 1)]
    return baseline, Phase(windows, rss)


def _viewers(error: str | None = None, slow_bytes: int = 1000) -> list[dict]:
    fast = [
        {"index": i, "kind": "fast", "frames": 100, "bytes": 10**6, "stalls": 0, "error": None}
        for i in range(3)
    ]
    fast[1]["error"] = error
    slow = [
        {"index": 3, "kind": "ws", "frames": 5, "bytes": slow_bytes, "stalls": 1, "error": None},
        {"index": 4, "kind": "mjpeg", "frames": 0, "bytes": slow_bytes, "stalls": 0, "error": None},
    ]
    return fast + slow


def _failed(criteria) -> set[str]:
    return {c.name for c in criteria if c.failed}


def test_summarize_figures():
    cfg = SoakConfig(soak_s=300, window_s=5)
    baseline, soak = _phases(19.0, 0.0)
    fig, criteria = summarize(cfg, baseline, soak, _viewers(), client_cpu_pct=12.0)
    assert fig["baseline_fps"] == 20.0
    assert fig["fast_fps_median"] == 19.0
    assert fig["fast_fps_ratio"] == pytest.approx(0.95)
    assert fig["fast_viewer_min_fps"] == pytest.approx(18.0)
    assert fig["fast_window_min_fps"] == 18.0
    assert fig["fast_share"] == pytest.approx(0.95)
    assert cfg.warmup() == 30.0
    assert fig["rss_samples"] == 271  # seconds 30 to 300
    assert abs(fig["rss_slope_mb_per_min"]) < 0.2
    assert fig["rss_max_mb"] == 501.0
    assert fig["slow_ws_frames"] == 5 and fig["slow_mjpeg_kb"] == 1.0
    assert fig["client_cpu_pct"] == 12.0
    assert [c.name for c in criteria] == [
        "fast_fps_ratio",
        "fast_viewer_min_ratio",
        "rss_slope_mb_per_min",
        "thread_growth",
        "fd_growth",
        "fast_window_min_fps",
        "render_processes",
        "viewers_connected",
    ]
    assert _failed(criteria) == set()


def test_summarize_criteria_fail():
    cfg = SoakConfig(soak_s=300, window_s=5)
    baseline, soak = _phases(15.0, 0.0)
    assert _failed(summarize(cfg, baseline, soak, _viewers())[1]) == {
        "fast_fps_ratio",
        "fast_viewer_min_ratio",
    }
    baseline, soak = _phases(19.0, 3.0)
    fig, criteria = summarize(cfg, baseline, soak, _viewers())
    assert fig["rss_slope_mb_per_min"] == pytest.approx(3.0, abs=0.2)
    assert _failed(criteria) == {"rss_slope_mb_per_min"}
    baseline, soak = _phases(19.0, 0.0)
    assert _failed(summarize(cfg, baseline, soak, _viewers(error="closed"))[1]) == {
        "viewers_connected"
    }
    assert _failed(summarize(cfg, baseline, soak, _viewers(slow_bytes=0))[1]) == {
        "viewers_connected"
    }
    soak.windows[-1] = _window(300.0, (19.0, 0.0, 19.0), threads=30, fds=50)
    assert _failed(summarize(cfg, baseline, soak, _viewers())[1]) == {
        "thread_growth",
        "fd_growth",
        "fast_window_min_fps",
    }
    # the console was still rendering poses (its disk cache was not full): not comparable
    soak.windows[-1] = _window(300.0, (19.0, 20.0, 18.0), children=1)
    assert _failed(summarize(cfg, baseline, soak, _viewers())[1]) == {"render_processes"}


def test_rss_slope_of_a_short_run_is_not_judged():
    # 50 s of samples after the warm-up: the allocator's noise, not a trend; neither
    # passes nor fails (the report says so)
    cfg = SoakConfig(soak_s=60, window_s=5)
    baseline, soak = _phases(19.0, 30.0, soak_s=60)
    fig, criteria = summarize(cfg, baseline, soak, _viewers())
    (rss,) = [c for c in criteria if c.name == "rss_slope_mb_per_min"]
    assert fig["rss_slope_mb_per_min"] == pytest.approx(30.0, abs=1)
    assert not rss.judged and not rss.failed and not rss.ok
    assert _failed(criteria) == set()
    report = soak_report.SoakReport(cfg, baseline, soak, fig, _viewers(), criteria)
    assert report.ok
    text = report.format()
    assert "n/a  rss_slope_mb_per_min" in text
    assert text.endswith("PASS (not judged, the run is too short: rss_slope_mb_per_min)")
    # nothing after the warm-up at all
    short = Phase(soak.windows[:1], [(5.0, 500.0)])
    fig, criteria = summarize(cfg, baseline, short, _viewers())
    assert math.isnan(fig["rss_slope_mb_per_min"]) and _failed(criteria) == set()


def test_warmup_defaults():
    assert SoakConfig(soak_s=600).warmup() == 60.0
    assert SoakConfig(soak_s=30, window_s=5).warmup() == 10.0
    assert SoakConfig(soak_s=200, window_s=5).warmup() == 20.0
    assert SoakConfig(soak_s=600, warmup_s=5).warmup() == 5.0


# -- the command line -----------------------------------------------------------------------


def test_cli_runs_the_soak(monkeypatch: pytest.MonkeyPatch):
    seen = []
    monkeypatch.setattr(bench_soak, "run_soak_cli", lambda cfg: seen.append(cfg) or 1)
    assert main(["bench", "--soak", "--soak-seconds", "30", "--viewers", "3"]) == 1
    assert seen == [SoakConfig(soak_s=30, viewers=3)]
    assert main(["bench", "--soak"]) == 1
    assert seen[-1] == SoakConfig(soak_s=600, viewers=10)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "--soak-seconds", "30"], "go with --soak"),
        (["bench", "--viewers", "2"], "go with --soak"),
        (["bench", "--soak", "--only", "render"], "--soak runs alone"),
        (["bench", "--soak", "--viewers", "0"], "expected a positive integer"),
    ],
)
def test_cli_refuses(argv, message, capsys: pytest.CaptureFixture[str]):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_cli_help_names_the_soak(capsys: pytest.CaptureFixture[str]):
    assert main(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--soak" in out and "--soak-seconds" in out and "--viewers" in out


# -- the video stream's viewers (--soak --video) ----------------------------------------------


def _video_step(viewers: int, fps: float, rss_after: float = 600.0, **kw) -> VideoStep:
    args = {
        "viewer_fps": (fps,) * viewers,
        "console_fps": fps,
        "status_ms": (5.0, 9.0, math.nan),
        "latency_ms": 20.0,
        "server_cpu_pct": 100.0,
        "rss_before_mb": 580.0,
        "rss_during_mb": (640.0, 690.0),
        "rss_after_mb": rss_after,
        "rungs": 1,
        "levels": {"8": viewers},
    }
    args.update(kw)
    return VideoStep(viewers, **args)


def test_video_step_figures_and_medians_of_runs():
    step = _video_step(3, 20.0, viewer_fps=(20.0, 15.0, 18.0))
    f = step.figures()
    assert (f["fps_median"], f["fps_min"], f["console_fps"]) == (18.0, 15.0, 20.0)
    assert (f["status_ms_median"], f["status_ms_max"]) == (7.0, 9.0)  # NaN: no answer
    assert (f["rss_before_mb"], f["rss_during_max_mb"], f["rss_after_mb"]) == (580, 690, 600)
    runs = [
        [_video_step(1, 24.0), _video_step(10, 20.0, rss_after=610.0)],
        [_video_step(1, 22.0), _video_step(10, 16.0, rss_after=650.0)],
        [_video_step(1, 23.0), _video_step(10, 18.0, rss_after=630.0)],
    ]
    medians = soak_report.video_medians(runs)
    assert [n for n, _ in medians] == [1, 10]
    assert medians[0][1]["fps_median"] == 23.0
    assert medians[1][1]["fps_median"] == 18.0 and medians[1][1]["rss_after_mb"] == 630.0
    row = soak_report.format_video_row(10, medians[1][1], "10x8")
    assert row.split()[:4] == ["10", "18.00", "18.00", "18.00"] and row.endswith("10x8")
    assert len(row.split()) == len(soak_report.VIDEO_HEAD.split())
    failed = soak_report.format_video_row(1, _video_step(1, 0.0, errors=1).figures())
    assert failed.endswith("ERRORS 1")


def test_cli_runs_the_video_load(monkeypatch: pytest.MonkeyPatch):
    seen = []
    monkeypatch.setattr(bench_soak, "run_video_load_cli", lambda cfg: seen.append(cfg) or 0)
    assert main(["bench", "--soak", "--video"]) == 0
    assert seen[-1] == VideoLoadConfig(counts=(1, 10, 50), step_s=30.0, runs=1)
    argv = ["bench", "--soak", "--video", "2,5", "--soak-seconds", "12", "--repeat", "3"]
    assert main(argv) == 0
    assert seen[-1] == VideoLoadConfig(counts=(2, 5), step_s=12.0, runs=3)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["bench", "--video"], "--video goes with --soak"),
        (["bench", "--soak", "--video", "--viewers", "3"], "--video goes with --soak"),
        (["bench", "--soak", "--video", "1,0"], "expected positive integers"),
        (["bench", "--soak", "--video", "ten"], "expected positive integers"),
    ],
)
def test_cli_refuses_video_load(argv, message, capsys: pytest.CaptureFixture[str]):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


# -- the machinery, end to end ----------------------------------------------------------------


@pytest.mark.slow
def test_short_soak_against_a_console():
    """Seconds, two fast viewers and both slow readers (the MJPEG one fast enough to
    complete frames): the report's structure, and every viewer got frames."""
    cfg = SoakConfig(
        soak_s=6,
        viewers=2,
        baseline_s=3,
        window_s=1.5,
        settle_s=0,
        ack_delay_s=0.2,
        read_s=1.0,
        stall_s=1.0,
        mjpeg_bytes_per_s=2_000_000,
        prewarm=False,
    )
    lines: list[str] = []
    report = bench_soak.run_soak(cfg, lines.append)
    # windows every 1.5 s, RSS every 0.75 s (fewer if the machine is so loaded that a
    # sample comes late: the phase still ends on time)
    assert 1 <= len(report.baseline.windows) <= 2 and 2 <= len(report.soak.windows) <= 4
    ends = [w.t_s for w in report.soak.windows]
    assert ends == sorted(ends) and ends[-1] >= 6.0 - 1e-3
    assert len(report.soak.windows) <= len(report.soak.rss) <= 8
    for w in report.soak.windows:
        assert len(w.fast_fps) == 2
        assert w.rss_mb > 0 and w.threads > 0 and w.fds > 0
        assert set(w.slow_frames) == {"ws", "mjpeg"}
    fast = [v for v in report.viewers if v["kind"] == "fast"]
    slow = {v["kind"]: v for v in report.viewers if v["kind"] != "fast"}
    assert len(fast) == 2 and set(slow) == {"ws", "mjpeg"}
    for v in report.viewers:
        assert v["error"] is None, v
        assert v["frames"] > 0 and v["bytes"] > 0, v
    assert slow["ws"]["stalls"] >= 1
    assert report.figures["viewers"] == 2
    for key in (
        "baseline_fps",
        "fast_fps_median",
        "fast_fps_ratio",
        "fast_viewer_min_fps",
        "rss_start_mb",
        "rss_end_mb",
        "rss_max_mb",
        "rss_slope_mb_per_min",
        "slow_ws_frames",
        "slow_mjpeg_frames",
    ):
        assert key in report.figures, key
    assert report.figures["baseline_fps"] > 0 and report.figures["rss_max_mb"] > 0
    assert {c.name for c in report.criteria} >= {"fast_fps_ratio", "rss_slope_mb_per_min"}
    text = report.format()
    assert text.splitlines()[0] == soak_report.TABLE_HEAD
    assert "criteria:" in text and text.splitlines()[-1].startswith(("PASS", "FAIL"))
    assert any(line.startswith("baseline: ") for line in lines)


@pytest.mark.slow
def test_short_video_load_against_a_console():
    """Seconds: one viewer, then two, of /stream.video on a real console; every figure is
    there and every viewer got frames (no performance assertions)."""
    cfg = VideoLoadConfig(counts=(1, 2), step_s=2.0, settle_s=0.5, after_s=1.0, prewarm=False)
    lines: list[str] = []
    (steps,) = bench_soak.run_video_load(cfg, lines.append)
    assert [s.viewers for s in steps] == [1, 2]
    for step in steps:
        assert step.errors == 0 and len(step.viewer_fps) == step.viewers
        assert min(step.viewer_fps) > 0 and step.console_fps > 0
        assert step.rss_before_mb > 0 and step.rss_after_mb > 0 and step.rss_during_mb
        assert step.status_ms and all(ms > 0 for ms in step.status_ms)
        assert sum(step.levels.values()) == step.viewers and step.rungs >= 1
    assert soak_report.VIDEO_HEAD in lines
