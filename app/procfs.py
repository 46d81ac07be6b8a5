"""What Linux's ``/proc`` says about a process: memory, threads, file descriptors, CPU time,
child processes, threads' CPU time. For the stream soak and the benchmarks, and the
console's ``GET /api/threads`` (psutil is not a dependency). Standard library only: app's
bottom layer."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path


def parse_proc_status(text: str) -> tuple[float, int]:
    """(resident memory in MB, threads) from the text of ``/proc/PID/status``."""
    rss = re.search(r"^VmRSS:\s+(\d+)\s+kB", text, re.M)
    threads = re.search(r"^Threads:\s+(\d+)", text, re.M)
    if rss is None or threads is None:
        raise ValueError("/proc status: no VmRSS or Threads line")
    return int(rss.group(1)) / 1024.0, int(threads.group(1))


def parse_proc_cpu_s(stat: str, waited_children: bool = False) -> float:
    """User + system CPU seconds from the text of ``/proc/PID/stat``: the process's own
    (``utime`` + ``stime``, fields 14 and 15), or with ``waited_children`` those of its
    ended children it has waited for (``cutime`` + ``cstime``, fields 16 and 17)."""
    fields = stat[stat.rindex(")") + 2 :].split()  # fields[0] is field 3, the state
    first = 13 if waited_children else 11
    return (int(fields[first]) + int(fields[first + 1])) / os.sysconf("SC_CLK_TCK")


def child_pids(pid: int) -> list[int]:
    """The process's live child processes (of all its threads); [] once it has ended."""
    children: list[int] = []
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return children
    for task in tasks:
        try:
            children += [int(c) for c in (task / "children").read_text().split()]
        except OSError:  # the thread ended meanwhile
            pass
    return children


def tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) used so far by the process ``pid`` and every live
    descendant, plus the ended children they have waited for. A descendant that ends
    between two readings and is waited for moves its whole time into its parent's figure:
    differences over a window count it in the window where it ended."""
    total = 0.0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            stat = Path(f"/proc/{p}/stat").read_text()
        except OSError:  # ended meanwhile
            continue
        total += parse_proc_cpu_s(stat) + parse_proc_cpu_s(stat, waited_children=True)
        todo += child_pids(p)
    return total


@dataclass(frozen=True)
class ProcSample:
    """One reading of a process: resident memory (MB), threads, open file descriptors, CPU
    seconds used so far (its own) and live child processes."""

    rss_mb: float
    threads: int
    fds: int
    cpu_s: float
    children: int = 0


def sample_process(pid: int) -> ProcSample:
    """The process's RSS, threads, open file descriptors, CPU time and child processes
    (Linux ``/proc``)."""
    rss, threads = parse_proc_status(Path(f"/proc/{pid}/status").read_text())
    fds = len(os.listdir(f"/proc/{pid}/fd"))
    cpu = parse_proc_cpu_s(Path(f"/proc/{pid}/stat").read_text())
    return ProcSample(rss, threads, fds, cpu, len(child_pids(pid)))
