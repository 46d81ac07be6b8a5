"""The thermal 3D map of recordings (``trifuse map``): every TOF frame into a
:class:`~fusion.map_builder.MapBuilder`.

A map job (:func:`app.recording.jobs.run_map_job`) splits the recordings into pieces
(:mod:`app.recording.pieces`); :func:`map_piece` replays a piece's spans as fast as they
are read, each piece into a map of its own, and the job merges the pieces' maps in order
(:meth:`MapRun.absorb`). Each TOF frame with distances is added with:

* the images of the rig's thermal imagers (through each imager's radiometry, as
  ``trifuse fuse`` does: kelvin) and colour cameras nearest to it in time, at most
  ``max_image_age_s`` away (a sensor without such a frame is left out of that frame: its
  points take no value from it);
* the head's pose: ``recording`` takes the recording's ``world -> rig`` transforms
  (:mod:`app.recording.poses`: the pose of the TOF frame's stamp, or interpolated between
  the poses around it; a frame without one is skipped and counted), ``estimate`` the pose
  from the TOF clouds (KISS-ICP, :class:`~fusion.odometry.TofOdometry`; the world is the
  rig frame at the first frame, and the recordings are taken as one continuous run in the
  order given), ``auto`` the recording's poses when every recording has them, the estimate
  when none has (a mix is refused: their world frames would not agree).

The recordings are read as ``trifuse fuse`` reads them (:class:`~app.recording.reader.
ReplaySource`): a recording cut short or left by a killed ``record`` (no summary section)
gives the frames before its damage, which the run names (``damage``); messages the replay
skips (undecodable, or an image of another size than the rig's) are counted per sensor.
"""

from __future__ import annotations

import re
import time
import typing
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from trifuse.app.recording.errors import RecordingDamaged
from trifuse.app.recording.pieces import MapPiece, MapSpan, open_task_recording
from trifuse.app.recording.player import Skips, add_skips, skips_between
from trifuse.app.recording.poses import TOLERANCE_S, RecordingPoses, read_poses
from trifuse.app.recording.reader import ReplaySource
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig, rig_to_yaml
from trifuse.fusion.geometry import tof_sensor_name
from trifuse.fusion.map_builder import MapBuilder
from trifuse.fusion.stereo_step import ThermalKelvin
from trifuse.fusion.voxel_map import MapSettings, VoxelMap

PoseMode = Literal["auto", "recording", "estimate"]
POSE_MODES: tuple[str, ...] = typing.get_args(PoseMode)
POSE_PROBE_S = 10.0
"""How far into a recording :func:`choose_poses` looks for the head's poses first, seconds."""
MAX_IMAGE_AGE_S = 0.1
"""Default: a thermal or colour frame further than this from a TOF frame is not used for
it, seconds."""


@dataclass
class MapRun:
    """What a map job (or one of its pieces: :func:`map_piece`) did.

    Attributes:
        map: the map.
        pose_source: ``recording`` (the recordings' poses) or ``estimate`` (from the
            TOF clouds).
        pose_frames: the frame names the recordings' poses came from (``world -> rig``),
            None when estimated.
        tof_frames: TOF frames with distances read.
        integrated: TOF frames added to the map.
        skipped: reason -> TOF frames not added.
        images_missing: sensor -> TOF frames that had no image of it within the age limit.
        messages_skipped: sensor -> reason -> messages the replays skipped.
        damage: per damaged recording, the damage the replay stopped at.
        notes: per recording, what reading its poses noted.
        seconds: wall time (of a piece: its own; of a job: the whole job's).
    """

    map: VoxelMap
    pose_source: str
    pose_frames: str | None = None
    tof_frames: int = 0
    integrated: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    images_missing: dict[str, int] = field(default_factory=dict)
    messages_skipped: Skips = field(default_factory=dict)
    damage: list[RecordingDamaged] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1

    def absorb(self, later: MapRun) -> None:
        """Add the next piece's map (:meth:`fusion.voxel_map.VoxelMap.merge`) and counts."""
        self.map.merge(later.map)
        self.tof_frames += later.tof_frames
        self.integrated += later.integrated
        counts = ((self.skipped, later.skipped), (self.images_missing, later.images_missing))
        for mine, theirs in counts:
            for key, n in theirs.items():
                mine[key] = mine.get(key, 0) + n
        add_skips(self.messages_skipped, later.messages_skipped)
        self.damage += later.damage
        self.notes += [n for n in later.notes if n not in self.notes]
        frames = {f for f in (self.pose_frames, later.pose_frames) if f}
        self.pose_frames = ", ".join(sorted(frames)) or None


def open_recordings(paths: Sequence[Path], rig: Rig | None) -> tuple[list[ReplaySource], Rig]:
    """Open every recording (as fast as it is read), with the rig to build with:
    ``rig`` if given, else the recordings' (they must agree); checks that none has, by its
    statistics, no TOF distances (a recording without statistics, cut short or left by a
    killed ``record``, is read to find out, as ``trifuse fuse`` reads it). Returns
    (sources, rig); closes what it opened when it raises.

    Raises:
        RecordingError: a file is no recording; ValueError: no rig, rigs that differ, no
            TOF in the rig or no TOF distances in a recording.
    """
    sources: list[ReplaySource] = []
    try:
        for path in paths:
            sources.append(ReplaySource(path, realtime=False))
        if rig is None:
            rigs: list[tuple[Path, Rig]] = []
            for src in sources:
                if src.rig is None:
                    raise ValueError(f"{src.path}: the recording holds no rig; give one with --rig")
                rigs.append((src.path, src.rig))
            first = rig_to_yaml(rigs[0][1])
            for path, other in rigs[1:]:
                if rig_to_yaml(other) != first:
                    raise ValueError(
                        f"{path}: its rig differs from that of {rigs[0][0]}; give the rig to "
                        "build with (--rig)"
                    )
            rig = rigs[0][1]
        tof = tof_sensor_name(rig)
        for src in sources:
            if src.message_count(tof, "tof_distance") == 0:
                raise ValueError(
                    f"{src.path}: no TOF distances of {tof!r} in the recording: nothing to map"
                )
        return sources, rig
    except BaseException:
        for src in sources:
            src.close()
        raise


def _poses_at_start(src: ReplaySource, reference: str) -> RecordingPoses | None:
    """The recording's poses of its first :data:`POSE_PROBE_S` seconds, else of the whole
    file (read only when the start has none)."""
    start = src.start_ns
    probe = read_poses(src.path, reference, (start, start + round(POSE_PROBE_S * 1e9)))
    return probe if probe is not None else read_poses(src.path, reference)


def choose_poses(
    sources: Sequence[ReplaySource], rig: Rig, mode: str
) -> list[RecordingPoses | None]:
    """Whether each recording has poses, as the ``mode`` uses them: a recording's poses of
    its first seconds (:func:`_poses_at_start`), None for each when estimating.

    Raises:
        ValueError: an unknown mode; ``recording`` with a recording that has no poses;
            ``auto`` with recordings of which some have poses and some not.
    """
    if mode not in POSE_MODES:
        raise ValueError(f"pose: expected one of {', '.join(POSE_MODES)}, got {mode!r}")
    if mode == "estimate":
        return [None] * len(sources)
    poses = [_poses_at_start(src, rig.reference) for src in sources]
    without = [str(src.path) for src, p in zip(sources, poses, strict=True) if p is None]
    if mode == "recording" and without:
        raise ValueError(
            f"{without[0]}: no head poses in the recording (world -> rig on /tf); "
            "estimate them from the TOF (--pose estimate)"
        )
    if without and len(without) < len(sources):
        raise ValueError(
            f"{without[0]}: no head poses in the recording (world -> rig on /tf), while "
            "other recordings have them: their world frames would not agree; map them "
            "apart, or estimate every pose (--pose estimate)"
        )
    return [None] * len(sources) if without else poses


def map_piece(
    piece: MapPiece,
    rig: Rig,
    settings: MapSettings,
    estimate: bool,
    progress: Callable[[int], None] | None = None,
    max_image_age_s: float = MAX_IMAGE_AGE_S,
) -> MapRun:
    """Build the map of one piece of a map job (:mod:`app.recording.pieces`; see the
    module docstring).

    Args:
        piece: the spans of recordings to add, in order.
        rig: the rig (intrinsics, poses, range correction, radiometry).
        settings: the map's settings.
        estimate: estimate the head's pose from the TOF clouds (else the recordings').
        progress: called with the TOF frames of the piece done after each.
        max_image_age_s: see :data:`MAX_IMAGE_AGE_S`.

    Frames are checked against ``rig``'s sizes (:meth:`~app.recording.player.
    MessageReplay.expect`); the messages skipped in a span's range (from its first TOF frame
    added to the one after its last) are counted. Damage in a recording ends its span where
    it is (``damage`` says so).
    """
    t0 = time.perf_counter()
    builder = MapBuilder(rig, settings, estimate_pose=estimate)
    run = MapRun(builder.map, "estimate" if estimate else "recording")
    images = [n for n in rig.names if rig[n].modality in ("thermal", "color")]
    kelvin = ThermalKelvin(rig, [n for n in images if rig[n].modality == "thermal"])
    age_ns = round(max_image_age_s * 1e9)

    def add(tof: Frame, history: dict[str, deque[Frame]], rec_poses: RecordingPoses | None) -> None:
        run.tof_frames += 1
        integrate(tof, history, rec_poses)
        if progress is not None:
            progress(run.tof_frames)

    def integrate(
        tof: Frame, history: dict[str, deque[Frame]], rec_poses: RecordingPoses | None
    ) -> None:
        chosen: dict[str, np.ndarray] = {}
        for name in images:
            best = min(history[name], key=lambda f: abs(f.stamp_ns - tof.stamp_ns), default=None)
            if best is None or abs(best.stamp_ns - tof.stamp_ns) > age_ns:
                run.images_missing[name] = run.images_missing.get(name, 0) + 1
                continue
            if name in kelvin.radiometry:
                chosen[name] = kelvin(name, best.image)
            else:
                chosen[name] = best.image
        T = None
        if not estimate:
            T = rec_poses.at(tof.stamp_ns) if rec_poses is not None else None
            if T is None:
                run.skip(f"no head pose within {TOLERANCE_S * 1e3:g} ms in the recording")
                return
        try:
            stats = builder.add(tof.stamp_ns / 1e9, tof.distance_m, chosen, T, tof.image)
        except ValueError as exc:
            if not estimate:
                raise
            # one reason per kind of failure, not per count ("odometry: N valid points...")
            run.skip(f"the pose could not be estimated ({re.sub(r'[0-9]+', 'N', str(exc))})")
            return
        if stats is None:
            run.skip("no pose")
        else:
            run.integrated += 1

    frames_of_poses: set[str] = set()
    for span in piece.spans:
        with open_task_recording(span.recording) as src:
            src.expect(rig)
            rec_poses = None
            if not estimate:
                rec_poses = read_poses(src.path, rig.reference, _log_range(src, span))
                if rec_poses is not None:
                    frames_of_poses.add(f"{rec_poses.parent} -> {rec_poses.child}")
                    run.notes += [f"{src.path}: {note}" for note in rec_poses.notes]
            history: dict[str, deque[Frame]] = {n: deque() for n in images}
            pending: deque[Frame] = deque()
            seen = 0  # TOF distance frames read in this span
            last = None if span.add_tof is None else span.skip_tof + span.add_tof
            counted_from: Skips | None = {} if span.seek_ns is None else None
            counted_to: Skips | None = None
            if span.seek_ns is not None:
                src.seek(span.seek_ns)
            try:
                for frame in src.frames():
                    if frame.sensor == builder.tof and frame.distance_m is not None:
                        seen += 1
                        if counted_from is None and seen > span.skip_tof:
                            counted_from = src.skipped
                        if counted_to is None and last is not None and seen > last:
                            counted_to = src.skipped
                        if span.skip_tof < seen and (last is None or seen <= last):
                            pending.append(frame)
                    elif frame.sensor in history:
                        history[frame.sensor].append(frame)
                    # A TOF frame is added once nothing nearer in time can come.
                    while pending and frame.stamp_ns > pending[0].stamp_ns + age_ns:
                        add(pending.popleft(), history, rec_poses)
                    if last is not None and seen > last and not pending:
                        break
                    oldest = pending[0].stamp_ns if pending else frame.stamp_ns
                    for h in history.values():
                        while h and h[0].stamp_ns < oldest - age_ns:
                            h.popleft()
            except RecordingDamaged as exc:
                run.damage.append(exc.with_traceback(None))  # its frames hold the span's
            while pending:
                add(pending.popleft(), history, rec_poses)
            counted_to = src.skipped if counted_to is None else counted_to
            add_skips(run.messages_skipped, skips_between(counted_from, counted_to))
    run.pose_frames = ", ".join(sorted(frames_of_poses)) or None
    run.seconds = time.perf_counter() - t0
    return run


def _log_range(src: ReplaySource, span: MapSpan) -> tuple[int, int] | None:
    """The log times whose poses a span needs, a second's margin each side (None: all)."""
    if span.seek_ns is None and span.end_ns is None:
        return None
    margin = 1_000_000_000
    lo = src.start_ns if span.seek_ns is None else span.seek_ns
    hi = src.end_ns if span.end_ns is None else span.end_ns
    return lo - margin, hi + margin
