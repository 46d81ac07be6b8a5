"""Recordings and maps in rerun files (issue 36, item 2).

``trifuse fuse --rerun OUT.rrd``: every ``every``-th frame set that makes a picture (the
:data:`fusion.stereo_step.OFFLINE` policy, as ``trifuse fuse``) logged with
:class:`app.recording.rerun_log.RerunHead`: its sensors' images, the TOF's cloud coloured by
temperature and the fused pair, under the rig's poses and pinholes, and at the end the
thermal map of those sets' TOF frames (at the recording's head poses, else estimated from
the TOF clouds) with the head's path. ``trifuse map --rerun OUT.rrd``: the thermal map of
every TOF frame, the head's path and the rig at its last pose.

The file is written beside its name (a temporary ``.NAME.XXXX.tmp`` that a crash leaves for
:func:`app.storage.atomic.remove_temporaries`) and linked to it once complete: never
overwritten, never half there.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from trifuse.app.recording.offline_sets import pictured_sets
from trifuse.app.recording.player import MessageReplay
from trifuse.app.recording.rerun_log import RerunHead, require_rerun
from trifuse.app.sources.capabilities import head_pose_of
from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.atomic import link_new, make_dirs
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.geometry import tof_sensor_name
from trifuse.fusion.map_builder import MapBuilder
from trifuse.fusion.stereo_step import OFFLINE, StereoStep
from trifuse.fusion.voxel_map import VoxelMap

MAP_POINTS = 1_000_000
"""The most points of a map logged (its level of detail, as the 3D console's)."""


@contextlib.contextmanager
def new_rerun_file(path: str | Path) -> Iterator[Any]:
    """A rerun recording stream saving to the new file ``path``: written aside (a
    ``.NAME.XXXX.tmp``) and linked to ``path`` when the block ends without an error;
    FileExistsError when ``path`` exists (before and after), nothing left on a failure."""
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
        yield stream
        stream.flush()
        stream.disconnect()  # the file is complete once its sink is closed
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        link_new(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


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
    with new_rerun_file(path) as stream:
        head = RerunHead(stream, rig, (settings or DisplaySettings()).palette)
        step = StereoStep(rig, settings, OFFLINE)
        builder = MapBuilder(rig)  # the thermal map, at the recording's poses or estimated
        pose = head_pose_of(source)
        logged, tof_ns, last_ns = 0, None, 0
        for fs, picture in pictured_sets(source, step, every):
            head.log_frames(fs.frames, step.radiometry)
            head.log_fused(fs.stamp_ns, picture)
            tof = fs.frames.get(builder.tof)
            if tof is not None and tof.distance_m is not None and tof.stamp_ns != tof_ns:
                tof_ns = tof.stamp_ns
                builder.add(tof.stamp_ns * 1e-9, tof.distance_m, _map_images(fs, step),
                            pose(tof.stamp_ns) if pose else None, tof.image)  # fmt: skip
            logged, last_ns = logged + 1, fs.stamp_ns
        if not logged:
            raise ValueError(
                "no frame set could be fused (both eyes' colour and thermal frames after the "
                "first TOF frame)"
            )
        if builder.map.path and builder.map.occupied().any():
            _log_map_at_last_pose(head, builder.map, builder.T_rig_tof, last_ns)
    return logged


def _log_map_at_last_pose(
    head: RerunHead, voxel_map: VoxelMap, T_rig_tof: np.ndarray, stamp_ns: int
) -> int:
    """``voxel_map`` with the rig at the head's last pose in it (its path's last
    ``T_world_tof``); the points logged."""
    T_world_rig = voxel_map.path[-1][1] @ np.linalg.inv(T_rig_tof)
    return head.log_map(stamp_ns, voxel_map, T_world_rig, MAP_POINTS)


def _map_images(fs: FrameSet, step: StereoStep) -> dict[str, np.ndarray]:
    """A set's images as the map takes them: thermal in kelvin, colour RGB."""
    out = {}
    for name, f in fs.frames.items():
        modality = step.rig[name].modality
        if modality == "thermal":
            out[name] = step.radiometry[name].apply(f.image)
        elif modality == "color":
            out[name] = f.image
    return out


def export_map_rerun(rig: Rig, voxel_map: VoxelMap, path: str | Path) -> int:
    """The thermal map (``trifuse map --rerun``) in the new rerun file ``path``: the rig's
    cameras placed at the head's last pose, the map's points (at most :data:`MAP_POINTS`,
    coloured by temperature as the console shows them) and the head's path, at the last
    frame's time; returns the points logged."""
    if not voxel_map.path:
        raise ValueError("the map holds no frame")
    stamp_ns = round(voxel_map.path[-1][0] * 1e9)
    T_rig_tof = rig[tof_sensor_name(rig)].T_rig_sensor
    with new_rerun_file(path) as stream:
        return _log_map_at_last_pose(RerunHead(stream, rig), voxel_map, T_rig_tof, stamp_ns)
