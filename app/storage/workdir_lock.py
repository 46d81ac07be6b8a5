"""One console per work directory: an advisory lock (``flock``) on ``.trifuse.lock``.

Two consoles on one work directory would number captures and rig versions over each other,
and the second one's start-up clean-up would delete the first one's unfinished temporary
files. :func:`lock_workdir` takes the lock for as long as the process lives (the kernel
releases it when the process ends, however it ends) and names the holder's process id when
it is taken.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import IO

LOCK_NAME = ".trifuse.lock"


class WorkdirInUse(Exception):
    """Another process holds the work directory's lock."""


def lock_workdir(workdir: Path) -> IO[str]:
    """Create ``workdir`` if needed and lock it; returns the open lock file (keep it open:
    closing it releases the lock).

    Raises:
        WorkdirInUse: another console holds it (the message names its process id).
        OSError: the directory or the lock file cannot be made.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    f = open(workdir / LOCK_NAME, "a+")  # held open (locked) for the process's life
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        holder = f.read().strip() or "unknown"
        f.close()
        raise WorkdirInUse(
            f"{workdir} is in use by another console (process {holder}); stop it, or give "
            "this one another --workdir"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f
