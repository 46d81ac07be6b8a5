"""Reading and writing rig files on disk (the pure parsing lives in ``calib.rig``)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from calib.errors import RigError
from calib.rig import Rig, rig_from_yaml, rig_to_yaml


def atomic_write_text(path: Path, text: str, overwrite: bool = True) -> None:
    """Write ``text`` to ``path`` atomically: temporary file, fsync, rename.

    With ``overwrite=False`` the final step is a hard link, which fails if ``path`` exists
    by then (no window in which another writer's file could be replaced).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise FileExistsError(f"{path}: exists; refusing to overwrite it") from None
            os.unlink(tmp)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    finally:
        Path(tmp).unlink(missing_ok=True)


def load_rig(path: str | Path) -> Rig:
    """Load and validate a rig file; RigError messages start with the file's path."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise RigError(f"{path}: cannot read rig file: {exc.strerror}") from None
    try:
        return rig_from_yaml(text)
    except RigError as exc:
        raise RigError(f"{path}: {exc}") from None


def save_rig(path: str | Path, rig: Rig, overwrite: bool = False) -> Path:
    """Write ``rig`` to ``path`` atomically. An existing file is kept unless ``overwrite``."""
    path = Path(path)
    atomic_write_text(path, rig_to_yaml(rig), overwrite=overwrite)
    return path
