"""What ``trifuse record`` says about the file it writes: where it is while being written,
and what it holds (and which commands use it) when finished."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.cli.args import PROG
from trifuse.app.cli.output import out

if TYPE_CHECKING:
    from trifuse.app.recording.recording import Recording


def say_where(writer: Recording) -> None:
    """Where the recording is written until it is finished."""
    out(
        f"Writing into {writer.temp_path}; it becomes {writer.path} when the recording is "
        "finished (Ctrl-C or SIGTERM finish it too). If this program is killed, that file is "
        "a complete MCAP of everything but about the last second."
    )


def record_summary(path: Path, writer: Recording) -> None:
    """What the finished recording holds, and the commands that use it."""
    from trifuse.app.recording import ReplaySource

    with ReplaySource(path, realtime=False) as rec:
        size_mb = path.stat().st_size / 1e6
        out(
            f"Wrote {writer.frames_written} frames ({rec.duration_s:.3f} s, "
            f"{size_mb:.1f} MB) to {path}:"
        )
        for ch in sorted(rec.index.channels.values(), key=lambda c: c.topic):
            schema = rec.index.schema_of(ch)
            n = (rec.index.message_counts or {}).get(ch.id, 0)
            out(f"  {ch.topic:<28} {schema.name if schema else '-':<28} {n} messages")
    out("Open it in Foxglove as it is, or watch it in the console and fuse it offline:")
    out(f"  {PROG} serve --replay {shlex.quote(str(path))}")
    out(f"  {PROG} fuse {shlex.quote(str(path))} --out DIR")
    out("Format: docs/FORMATS.md (Recordings).")
