"""Reading and writing rig files on disk (the pure parsing lives in ``calib.rig``)."""

from __future__ import annotations

from pathlib import Path

from trifuse.app.storage.atomic import atomic_write_text
from trifuse.app.storage.text import read_text
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig, rig_from_yaml, rig_to_yaml


def load_rig(path: str | Path) -> Rig:
    """Load and validate a rig file; RigError messages start with the file's path."""
    path = Path(path)
    text = read_text(path, "rig file", RigError)
    try:
        return rig_from_yaml(text)
    except RigError as exc:
        raise RigError(f"{path}: {exc}") from None


def save_rig(path: str | Path, rig: Rig, overwrite: bool = False) -> Path:
    """Write ``rig`` to ``path`` atomically. An existing file is kept unless ``overwrite``."""
    path = Path(path)
    atomic_write_text(path, rig_to_yaml(rig), overwrite=overwrite)
    return path
