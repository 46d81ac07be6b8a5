"""What the commands print: results and progress lines on stdout, warnings on stderr."""

from __future__ import annotations

import sys
from collections.abc import Callable


def out(msg: str) -> None:
    """One line (or several) of a command's output on stdout, flushed."""
    print(msg, flush=True)


def err(msg: str) -> None:
    """A warning or progress line on stderr, flushed."""
    print(msg, file=sys.stderr, flush=True)


def stage_progress() -> Callable[[str, float], None]:
    """A progress callback ``(stage, fraction 0..1)`` that prints ``[ 40%] stage`` each time
    the percentage enters a new tenth."""
    last = [-1]

    def progress(stage: str, fraction: float) -> None:
        percent = int(100 * fraction)
        if percent // 10 != last[0] // 10:
            last[0] = percent
            out(f"[{percent:3d}%] {stage}")

    return progress


def progress_bar(done: int, total: int | None, width: int = 30) -> str:
    """``[#####.....] done/total frames``, or ``[????] done frames`` with no total."""
    if not total:
        return f"[{'?' * width}] {done} frames"
    filled = min(width, round(width * done / total))
    return f"[{'#' * filled}{'.' * (width - filled)}] {done}/{total} frames"


def frame_progress() -> Callable[[int, int | None], None]:
    """A progress callback ``(frames done, total or None)``: a bar redrawn in place on a
    terminal, else a line each time it enters a new tenth (every 100 frames without a
    total), on stderr."""
    tty = sys.stderr.isatty()
    shown = [-1]

    def progress(done: int, total: int | None) -> None:
        tenth = (10 * done // total) if total else done // 100
        if tty:
            print(f"\r{progress_bar(done, total)}", end="", file=sys.stderr, flush=True)
        elif tenth != shown[0]:
            shown[0] = tenth
            err(progress_bar(done, total))

    return progress
