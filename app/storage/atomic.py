"""Crash-safe file writing: nothing the user captured or calibrated is half-written.

Every write goes to a temporary file in the target directory, is fsynced, then renamed
(or hard-linked, when an existing file must not be replaced) into place; the directory is
fsynced after. A crash leaves the old file or the new one, never a mixture.

What a write interrupted by a crash (a kill, a power cut) leaves behind is at most a hidden
temporary file ``.<name>.<random>.tmp`` beside the target; :func:`remove_temporaries`
clears those when the program starts again: the write they belonged to either completed
under the target's name (the temporary file is a second link to it) or never returned, so
no one was told that it had.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

_TEMPORARY_RE = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")
"""The name of a temporary file of :func:`atomic_write_bytes` (``tempfile.mkstemp``)."""


def umask() -> int:
    """The process's umask (read without changing it where /proc allows)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (new, renamed files) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_dirs(path: str | Path) -> Path:
    """``mkdir -p path``, each folder it creates made durable in its parent (fsync)."""
    path = Path(path)
    missing = []
    p = path
    while not p.is_dir():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    path.mkdir(parents=True, exist_ok=True)
    for p in reversed(missing):
        try:
            fsync_dir(p.parent)
        except PermissionError:  # a parent we may write but not read: best effort
            pass
    return path


def remove_temporaries(directory: str | Path) -> list[Path]:
    """Remove the temporary files that writes interrupted by a crash left in ``directory``
    (not its subfolders); returns them. Only names of :func:`atomic_write_bytes`'
    temporaries are touched; a missing directory has none."""
    removed = []
    try:
        entries = list(Path(directory).iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for p in entries:
        if _TEMPORARY_RE.match(p.name) and p.is_file() and not p.is_symlink():
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def atomic_write_bytes(path: str | Path, data: bytes, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically, with a plain file's permissions.

    With ``overwrite=False`` an existing ``path`` raises FileExistsError, and the final
    step is a hard link, so no file created meanwhile by someone else is replaced.
    """
    path = Path(path)
    make_dirs(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        if overwrite:
            os.replace(tmp, path)
            fsync_dir(path.parent)
        else:
            link_new(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path


def link_new(tmp: str | Path, path: Path) -> None:
    """Give the complete file ``tmp`` (synced) the new name ``path`` in its directory, a hard
    link, so no file created meanwhile by someone else is replaced: FileExistsError when
    ``path`` exists. ``tmp`` stays (the caller removes it)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(f"{path}: exists; refusing to overwrite it") from None
    fsync_dir(path.parent)


def atomic_write_text(path: str | Path, text: str, overwrite: bool = True) -> Path:
    """:func:`atomic_write_bytes` of UTF-8 text."""
    return atomic_write_bytes(path, text.encode("utf-8"), overwrite)
