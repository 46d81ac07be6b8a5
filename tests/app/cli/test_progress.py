"""Progress of a long command (app.cli.progress) and of ``trifuse record --source sim``
(app.cli.record_sim): the time left from the rate measured as the work goes, one redrawn
line on a terminal, few plain lines in a pipe. Time is a fake clock, never measured."""

from __future__ import annotations

import functools
import io
import itertools
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from tests.support import FakeClock, run_cli
from trifuse.app.cli import record_sim
from trifuse.app.cli.progress import (
    LINE_GAP_S,
    QUIET_S,
    RATE_WINDOW_S,
    ProgressLine,
    RateMeter,
    span,
)

# The case: `record --scenario survey --duration 36`, planned 133 s (2.2 min) in
# 1944 instants, took 13.1 min on a busy machine.
STEPS, PLANNED_S, TOOK_S = 1944, 133.2, 13.1 * 60


def test_the_time_left_follows_the_recent_rate_not_the_plan() -> None:
    meter = RateMeter(100.0, start_s=0.0)
    assert meter.rate() is None and meter.remaining_s() is None
    for t in range(1, 51):  # 1 unit per second for 50 s
        meter.add(float(t), float(t))
    assert meter.remaining_s() == pytest.approx(50.0)
    for k in range(1, 121):  # then the machine gets busy: 0.1 unit per second
        meter.add(50.0 + k, 50.0 + 0.1 * k)
    # over the window (the last 60 s) the rate is 0.1/s: 38 units take 380 s (the average
    # since the start, 62 units in 170 s, would say 104 s)
    assert meter.remaining_s() == pytest.approx(38.0 / 0.1)
    assert len(meter._samples) <= RATE_WINDOW_S + 2  # the samples before the window are let go
    meter.add(200.0, 100.0)
    assert meter.remaining_s() == 0.0


def _run_steps(line: ProgressLine, clock: FakeClock, seconds_per_step: float) -> None:
    for i in range(1, STEPS + 1):
        clock.advance(seconds_per_step)
        line.update(PLANNED_S * i / STEPS, f"[{i}/{STEPS}]")


def test_in_a_pipe_a_few_lines_with_the_measured_time_left() -> None:
    clock, stream = FakeClock(), io.StringIO()
    line = ProgressLine(PLANNED_S, stream, clock)
    assert line.tty is False  # StringIO is not a terminal
    _run_steps(line, clock, TOOK_S / STEPS)
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    # a line after 10 s, then one per tenth of the work, not one per instant
    assert len(lines) == line.lines == 11, lines
    assert lines[0].startswith("[25/1944], elapsed 10 s, ETA 12.9 min")
    assert lines[-1] == f"[{STEPS}/{STEPS}], elapsed 13.1 min, ETA 0 s"
    # the time left is the measured one (13.1 min in all), not the plan's 2.2 min
    for text in lines[:-1]:
        done = int(re.match(r"\[(\d+)/", text).group(1))
        eta = re.search(r"ETA ([\d.]+) (s|min)$", text)
        assert eta is not None, text
        told = float(eta.group(1)) * (60 if eta.group(2) == "min" else 1)
        assert told == pytest.approx(TOOK_S * (1 - done / STEPS), rel=0.05, abs=1), text


@pytest.mark.parametrize(
    ("took_s", "fewest", "most"),
    [
        (4.0, 1, 1),  # its tenths come faster than LINE_GAP_S: the last line only
        (60.0, 7, 11),  # a tenth every 6 s: a line each but within LINE_GAP_S of another
        (3 * 3600.0, 3 * 3600 / QUIET_S, 3 * 3600 / QUIET_S + 11),  # quiet tenths of 18 min
    ],
)
def test_in_a_pipe_lines_are_spaced(took_s: float, fewest: float, most: float) -> None:
    clock, stream = FakeClock(), io.StringIO()
    line = ProgressLine(PLANNED_S, stream, clock)
    times = []
    for i in range(1, STEPS + 1):
        clock.advance(took_s / STEPS)
        before = line.lines
        line.update(PLANNED_S * i / STEPS, f"[{i}/{STEPS}]")
        if line.lines > before:
            times.append(clock.now)
    lines = stream.getvalue().splitlines()
    assert fewest <= len(lines) <= most and lines[-1].startswith(f"[{STEPS}/{STEPS}]")
    gaps = [b - a for a, b in itertools.pairwise(times[:-1])]  # not to the last
    assert all(LINE_GAP_S <= g <= QUIET_S + took_s / STEPS for g in gaps), gaps


def test_on_a_terminal_one_line_redrawn_in_place() -> None:
    clock, stream = FakeClock(), io.StringIO()
    line = ProgressLine(PLANNED_S, stream, clock, tty=True)
    _run_steps(line, clock, 0.01)  # 19.4 s: redrawn 4 times a second, and the last
    text = stream.getvalue()
    assert "\n" not in text and text.startswith("\r")
    draws = text.split("\r")[1:]
    assert len(draws) == line.lines and 70 <= len(draws) <= 80
    assert draws[-1].startswith(f"[{STEPS}/{STEPS}], elapsed 19 s, ETA 0 s")
    # a shorter line blanks what the longer one before it left
    assert all(len(b) >= len(a.rstrip()) for a, b in itertools.pairwise(draws))
    line.close()
    assert stream.getvalue().endswith("\n") and stream.getvalue().count("\n") == 1
    line.close()  # once only
    assert stream.getvalue().count("\n") == 1


def test_span() -> None:
    assert [span(s) for s in (42, 89.6, 210, 7560)] == ["42 s", "90 s", "3.5 min", "2.1 h"]


def test_busy_note() -> None:
    assert record_sim.busy_note(cores=2, load=1.5) == ""
    assert record_sim.busy_note(cores=2, load=9.64) == (
        "; this machine is busy (load 9.6 on 2 cores): expect longer"
    )


@pytest.fixture
def fake_recording(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    """``record --source sim`` with the rendering replaced: every instant reported done,
    each taking 13.1 min / 1944 of a fake clock (the issue's busy machine)."""
    from trifuse.app.recording import simrecord

    clock = FakeClock()

    def record_simulation(*_args: Any, progress: Any, plan: Any, **_kw: Any) -> Any:
        for i, (stamp, sensors) in enumerate(plan.schedule, start=1):
            clock.advance(TOOK_S / STEPS)
            progress(simrecord.SimProgress(i, len(plan.schedule), stamp, sensors, 0, 0, 0))
        return SimpleNamespace(frames_written=plan.frames)

    monkeypatch.setattr(simrecord, "record_simulation", record_simulation)
    monkeypatch.setattr(record_sim, "ProgressLine", functools.partial(ProgressLine, clock=clock))
    monkeypatch.setattr(record_sim, "record_summary", lambda path, writer: None)
    return clock


def test_record_sim_says_the_time_left_in_a_few_lines(
    fake_recording: FakeClock, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["record", "--source", "sim", "--scenario", "survey", "--duration", "36"]
    code, out, err = run_cli([*argv, "--out", str(tmp_path / "s.mcap")], capsys)
    assert code == 0, err
    first = out.splitlines()[0]
    assert "Recording 36 s" in first and "about 2.2 min" in first and "lasts" not in first
    progress = [line for line in out.splitlines() if line.startswith("[")]
    assert 10 <= len(progress) <= 12, progress  # not 1944
    assert progress[-1] == "[1944/1944] t = 35.97 of 36 s, elapsed 13.1 min, ETA 0 s"
    assert re.fullmatch(r"\[\d+/1944\] t = [\d.]+ of 36 s, elapsed .+, ETA [\d.]+ min", progress[4])


def test_the_survey_records_about_a_minute_by_default(
    fake_recording: FakeClock, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from trifuse.app.sources.sim.survey import SURVEY_S

    argv = ["record", "--source", "sim", "--scenario", "survey"]
    code, out, err = run_cli([*argv, "--out", str(tmp_path / "s.mcap")], capsys)
    assert code == 0, err
    first = out.splitlines()[0]
    default = record_sim.DEFAULT_DURATION_S["survey"]
    assert default < SURVEY_S and first.startswith(f"Recording {default:g} s")
    assert f"the survey lasts {SURVEY_S:g} s, --duration {SURVEY_S:g} records all of it" in first
    estimate = re.search(r"Estimated time: about (\d+) s", first)
    assert estimate is not None and 40 <= int(estimate.group(1)) <= 60, first
    assert record_sim.DEFAULT_DURATION_S["inspection"] == 2.0
