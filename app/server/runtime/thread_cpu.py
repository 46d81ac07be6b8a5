"""The CPU time each of the console's threads has used, by the thread's Python name
(``GET /api/threads``): where a loaded console's cores go, without a profiler attached.

Linux's ``/proc/self/task/TID/stat`` for every live :func:`threading.enumerate` thread
(its ``native_id``); elsewhere, or for a thread that ended meanwhile, no figure. Threads
of C libraries (x264's, OpenCV's and OpenBLAS's pools) are not Python threads: their time
is in the process's total only.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

from trifuse.app.procfs import parse_proc_cpu_s


@dataclass(frozen=True)
class ThreadCpu:
    """One thread: its Python ``name``, ``native_id`` (the kernel's) and ``cpu_s``, user
    plus system CPU seconds since it started (None where ``/proc`` does not say)."""

    name: str
    native_id: int | None
    cpu_s: float | None


def thread_cpu() -> list[ThreadCpu]:
    """Every live Python thread of this process with its CPU time so far."""
    out = []
    for t in threading.enumerate():
        nid = t.native_id
        cpu = None
        if nid is not None:
            try:
                cpu = parse_proc_cpu_s(Path(f"/proc/self/task/{nid}/stat").read_text())
            except (OSError, ValueError):  # ended meanwhile; no /proc here
                pass
        out.append(ThreadCpu(t.name, nid, cpu))
    return out
