"""Recordings whose writer died: the temporary file's name and its recovery.

While a recording is written, its data is in ``.<name>.mcap.<random>.partial`` beside it
(:func:`new_partial`, made by :class:`~app.recording.writer.RecordingWriter`), locked
(``flock``) and sealed about once a second (:mod:`app.recording.sealed_file`), so a killed
program leaves a complete MCAP of all but its last second. :func:`recover_interrupted`
(called when the console's recorder is made) finds such files that no living writer holds
and keeps each under a visible name (docs/FORMATS.md, "Recordings").
"""

from __future__ import annotations

import fcntl
import os
import random
import re
import string
import time
from pathlib import Path

from trifuse.app.recording.mcapindex import McapIndex
from trifuse.app.recording.sealed_file import SealedMcapFile
from trifuse.app.storage.atomic import fsync_dir
from trifuse.app.storage.numbered import suffixed_names


def new_partial(path: Path) -> SealedMcapFile:
    """A new ``.<name>.<random>.partial`` beside ``path`` (never an existing file)."""
    for _ in range(100):
        token = "".join(random.choices(string.ascii_lowercase + string.digits + "_", k=8))
        try:
            return SealedMcapFile(path.parent / f".{path.name}.{token}.partial")
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: no free temporary name for {path.name}")


_PARTIAL_RE = re.compile(r"^\.(?P<name>.+\.mcap)\.[a-z0-9_]{8}\.partial$")
INTERRUPTED_SUFFIX = ".partial.mcap"
"""``<name>.partial.mcap``: a recording that was being written when the program died."""


def recover_interrupted(directory: str | Path) -> list[tuple[str, Path]]:
    """Give the recordings whose writer died (killed, crashed) a visible name.

    Returns (the name the recording was to have, where it is now) for each one kept.

    A temporary file ``.<name>.mcap.<random>.partial`` that no living writer holds (its lock
    is free) is what a recording had written when its program died. It is never deleted:

    * a finished file (footer and summary intact: the writer died while naming it) becomes
      ``<name>.mcap`` (or is dropped if it is ``<name>.mcap`` already, as a second link);
    * a file cut short becomes ``<name>.partial.mcap`` (``-2``, ``-3`` ... if taken); it
      reads up to its last seal (:class:`~app.recording.ReplaySource` reports the
      damage where it ends);
    * a file without frames (nothing was recorded) is removed once it is a minute old.

    Files being written (locked) are left alone. Names are never reused: each file is
    hard-linked to its new name, which fails rather than replacing a file.
    """
    directory = Path(directory)
    try:
        entries = sorted(directory.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return []
    out: list[tuple[str, Path]] = []
    for temp in entries:
        m = _PARTIAL_RE.match(temp.name)
        if m is None or not temp.is_file() or temp.is_symlink():
            continue
        try:
            fd = os.open(temp, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # a writer is alive (or the file system cannot tell: leave it)
            final = directory / m["name"]
            st = os.fstat(fd)
            if st.st_size == 0 or not _has_frames(temp):  # nothing recorded (a writer may
                if time.time() - st.st_mtime > 60:  # be starting: wait a minute)
                    temp.unlink(missing_ok=True)
                continue
            if final.exists() and os.path.samefile(final, temp):
                temp.unlink(missing_ok=True)  # finished and named; this is a second link
                continue
            candidates = [final] if _finished(temp) else []
            stem = m["name"][: -len(".mcap")]
            candidates += [
                directory / n for n in suffixed_names(stem, INTERRUPTED_SUFFIX, limit=999)
            ]
            for target in candidates:
                try:
                    os.link(temp, target)
                except FileExistsError:
                    continue
                temp.unlink()
                fsync_dir(directory)
                out.append((m["name"], target))
                break
        finally:
            os.close(fd)
    return out


def _has_frames(path: Path) -> bool:
    """Whether an MCAP file holds any chunk of messages (a sealed file that got no frame
    holds only its header, metadata and attachment)."""
    try:
        index = McapIndex.open(path)
    except Exception:
        return True  # damaged: keep it for a person to look at
    try:
        return bool(index.chunks)
    finally:
        index.close()


def _finished(path: Path) -> bool:
    """Whether an MCAP file is complete (its summary section and footer are intact)."""
    try:
        index = McapIndex.open(path)
    except Exception:
        return False
    try:
        return index.indexed_by == "summary" and index.damage is None
    finally:
        index.close()
