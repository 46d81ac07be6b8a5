"""A recording in rerun (``trifuse fuse --rerun OUT.rrd``; issue 36, item 2): every ``every``-th
frame set that makes a picture (the :data:`fusion.stereo_step.OFFLINE` policy, as ``trifuse
fuse``) logged with :class:`app.rerun_log.RerunHead`: its sensors' images, the TOF's cloud
coloured by temperature and the fused pair, under the rig's poses and pinholes.

The file is written beside its name (a temporary ``.NAME.XXXX.tmp`` that a crash leaves for
:func:`app.storage.atomic.remove_temporaries`) and linked to it once complete: never
overwritten, never half there.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from trifuse.app.recording.player import MessageReplay
from trifuse.app.rerun_log import RerunHead, require_rerun
from trifuse.app.sources.base import frame_sets
from trifuse.app.storage.atomic import fsync_dir, make_dirs
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.stereo_step import OFFLINE, Skip, StereoStep


def export_rerun(
    source: MessageReplay,
    rig: Rig,
    path: str | Path,
    every: int = 1,
    settings: DisplaySettings | None = None,
) -> int:
    """Log ``source``'s pictured frame sets (every ``every``-th) to the new rerun file
    ``path``; returns how many were logged. FileExistsError when ``path`` exists (before
    anything is read); nothing is left at ``path`` when no set makes a picture (ValueError)
    or on any failure."""
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: exists; refusing to overwrite it")
    rr = require_rerun()
    make_dirs(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        stream = rr.RecordingStream("trifuse", recording_id=path.stem)
        stream.save(tmp)
        head = RerunHead(stream, rig, (settings or DisplaySettings()).palette)
        step = StereoStep(rig, settings, OFFLINE)
        source.realtime = False
        source.expect(rig)
        logged = 0
        for i, fs in enumerate(frame_sets(source, step.sensors)):
            step.note(fs)
            step.update_depth()
            if i % every:
                continue
            inputs = step.inputs(fs)
            if isinstance(inputs, Skip):
                continue
            picture = step.render(inputs)
            head.log_frames(fs.frames, step.radiometry)
            head.log_fused(fs.stamp_ns, picture)
            logged += 1
        stream.flush()
        stream.disconnect()  # the file is complete once its sink is closed
        if not logged:
            raise ValueError(
                "no frame set could be fused (both eyes' colour and thermal frames after the "
                "first TOF frame)"
            )
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise FileExistsError(f"{path}: exists; refusing to overwrite it") from None
        fsync_dir(path.parent)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return logged
