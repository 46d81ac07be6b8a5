"""The files a command reads and writes: rig files named on the command line, and outputs
that are never overwritten (except a rig file rewritten in place, whose previous content is
kept as a numbered backup)."""

from __future__ import annotations

import argparse
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn
from urllib.parse import unquote, urlsplit

from trifuse.app.cli.args import UsageError
from trifuse.app.cli.output import out
from trifuse.app.storage.numbered import backup_names, first_free

if TYPE_CHECKING:
    from trifuse.calib.rig import Rig


def refuse_existing(flag: str, path: Path) -> NoReturn:
    """The one refusal of every command whose output file or directory exists already."""
    raise UsageError(f"{flag} {path}: exists; refusing to overwrite it (choose a new name)")


def check_output_dir(out_dir: Path) -> None:
    """``--out DIR`` must be a new or empty directory."""
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(
            f"--out {out_dir}: exists and is not a directory; refusing to overwrite it "
            "(choose a new directory)"
        )
    if out_dir.is_dir() and any(out_dir.iterdir()):
        raise UsageError(
            f"--out {out_dir}: directory exists and is not empty; refusing to write into it so "
            "that nothing captured there is overwritten (choose a new directory)"
        )


def add_out_dir_argument(parser: argparse.ArgumentParser) -> None:
    """``--out DIR`` of a command that writes a new directory (see :func:`check_output_dir`)."""
    parser.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output directory; must not exist or be empty (nothing is ever overwritten)",
    )


def load_rig_arg(path: str, flag: str = "") -> Rig:
    """A rig file given on the command line; its errors on one line (a YAML error's
    message spans several), naming the option."""
    from trifuse.app.storage.rigfile import load_rig

    try:
        return load_rig(path)
    except ValueError as exc:  # RigError
        lines = (line.strip() for line in str(exc).splitlines())
        text = " ".join(line for line in lines if line.strip("^"))
        raise ValueError(f"{flag} {text}" if flag else text) from None


def add_rig_out_argument(parser: argparse.ArgumentParser) -> None:
    """``--out RIG.yaml`` of a command that updates the ``--rig`` file."""
    parser.add_argument(
        "--out",
        required=True,
        metavar="RIG.yaml",
        help="rig file to write: a new file, or the --rig file itself (its previous "
        "content is then kept as RIG.yaml.~N~)",
    )


def _same_file(a: Path, b: Path | None) -> bool:
    return b is not None and a.exists() and b.exists() and a.resolve() == b.resolve()


def check_rig_out(rig_out: Path, rig_path: Path | None, **others: str | None) -> None:
    """``--out`` may be the ``--rig`` file itself (kept as a numbered backup); any other
    existing output (``others``: option name without dashes -> path) is refused."""
    outputs = [] if _same_file(rig_out, rig_path) else [("--out", rig_out)]
    outputs += [(f"--{flag}", Path(p)) for flag, p in others.items() if p]
    for flag, path in outputs:
        if path.exists():
            refuse_existing(flag, path)


def write_rig_out(rig_out: Path, rig_path: Path | None, rig: Rig, what: str) -> None:
    """Write the updated rig; when it replaces ``rig_path``, the old file stays as
    ``RIG.yaml.~N~`` first."""
    from trifuse.app.storage.rigfile import save_rig

    same = _same_file(rig_out, rig_path)
    if same:
        backup = first_free(backup_names(rig_out), Path.exists)
        os.link(rig_out, backup)  # the rig as it was stays, under a new name
        out(f"previous rig kept as {backup}")
    save_rig(rig_out, rig, overwrite=same)
    out(f"rig with {what} written to {rig_out}")


def recording_paths(arguments: list[str]) -> list[Path]:
    """The recordings named: files as given (``file://`` URLs as their path), directories
    as every ``*.mcap`` in them (sorted by name). UsageError for a path that does not
    exist, a directory without recordings, or another URL scheme (an object store is read
    where it is mounted)."""
    paths: list[Path] = []
    for text in arguments:
        scheme = re.match(r"^([a-zA-Z][a-zA-Z0-9+.-]*)://", text)
        if scheme and scheme.group(1).lower() == "file":
            text = unquote(urlsplit(text).path)
        elif scheme:
            raise UsageError(
                f"{text}: {scheme.group(1)}:// URLs are not read directly; mount the store "
                "(e.g. s3fs, mountpoint-s3, gcsfuse) at the same path on every machine and "
                "give that path"
            )
        p = Path(text)
        if p.is_dir():
            found = sorted(q for q in p.glob("*.mcap") if q.is_file())
            if not found:
                raise UsageError(f"{p}: a directory without recordings (*.mcap)")
            paths += found
        elif p.exists():
            paths.append(p)
        else:
            raise UsageError(f"{p}: no such recording")
    return paths
