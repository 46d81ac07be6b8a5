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
