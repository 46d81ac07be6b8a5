"""Subprocesses of trifuse's own tools (benchmarks, the soak, the tests): how they end."""

from __future__ import annotations

import subprocess
from typing import Any


def stop_process(proc: Any) -> None:
    """End a console subprocess: SIGTERM (it finishes recordings and closes cleanly), then
    SIGKILL if it has not ended within 15 s."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
