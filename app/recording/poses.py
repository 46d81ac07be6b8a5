"""The head's pose in a recording: the ``world -> rig`` transforms on ``/tf``.

Where the source knew the head's pose (the simulated head; a robot's localisation),
``trifuse record`` writes it per frame set as a ``foxglove.FrameTransform`` with parent
``world`` and child ``rig`` (:meth:`~app.recording.writer.RecordingWriter.write_pose`,
docs/FORMATS.md "The head's pose"). :func:`read_poses` reads them back; a robot's own
recording may name the frames differently, so the parents ``world``, ``map`` and ``odom``
(:data:`~app.recording.layout.POSE_PARENTS`, in that order of preference: one recording's
poses come from one parent) and the children ``rig`` or the rig's reference sensor (whose
frame is the rig frame) are all read as ``T_world_rig``. Both ``foxglove.FrameTransform``
and ``foxglove.FrameTransforms`` (a list per message) are read, on any topic.

:meth:`RecordingPoses.at` gives the pose at any stamp: the pose of that stamp, else the two
poses around it interpolated (translation linearly, rotation by slerp) when they are at
most ``max_gap_s`` apart, else the nearest pose within ``tolerance_s``, else None.

Frames: ``T_world_rig`` (4, 4) float64, the rig frame's pose in the recording's world
frame (metres); stamps in int nanoseconds (the messages' own timestamps, their log time
where a timestamp is zero).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap_protobuf.decoder import DecoderFactory

from trifuse.app.recording.layout import METADATA_NAME, POSE_PARENTS, RIG_FRAME
from trifuse.app.recording.mcapindex import McapDamage, McapIndex
from trifuse.calib.transforms import rotation_from_quaternion, slerp_rotation

TOLERANCE_S = 0.05
"""Default of :meth:`RecordingPoses.at`: a stamp outside the poses' span takes the nearest
pose at most this far away, seconds."""
MAX_GAP_S = 0.5
"""Default of :meth:`RecordingPoses.at`: two poses at most this far apart are interpolated
between, seconds."""

_TRANSFORM_SCHEMAS = ("foxglove.FrameTransform", "foxglove.FrameTransforms")


@dataclass(frozen=True, eq=False)
class RecordingPoses:
    """The head's poses in one recording.

    Attributes:
        stamps_ns: (P,) int64, strictly increasing.
        T_world_rig: (P, 4, 4) float64, the rig's pose at each stamp (metres).
        parent: the frame id the poses were read from (``world``, ``map`` or ``odom``).
        child: ``rig`` or the rig's reference sensor.
        notes: what was skipped or where reading stopped (damage, bad transforms).
    """

    stamps_ns: np.ndarray
    T_world_rig: np.ndarray
    parent: str
    child: str
    notes: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def at(
        self,
        stamp_ns: int,
        *,
        tolerance_s: float = TOLERANCE_S,
        max_gap_s: float = MAX_GAP_S,
    ) -> np.ndarray | None:
        """(4, 4) ``T_world_rig`` at ``stamp_ns``, or None.

        The pose of that very stamp if there is one; else, between two poses at most
        ``max_gap_s`` apart, their interpolation (translation linear, rotation slerp, by
        the stamp's fraction of the way); else the nearest pose if it is at most
        ``tolerance_s`` away (before the first pose, after the last, across a gap); else
        None.
        """
        stamps = self.stamps_ns
        i = int(np.searchsorted(stamps, stamp_ns))
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self.T_world_rig[i].copy()
        if 0 < i < len(stamps):
            t0, t1 = int(stamps[i - 1]), int(stamps[i])
            if (t1 - t0) <= max_gap_s * 1e9:
                return interpolate_pose(
                    self.T_world_rig[i - 1], self.T_world_rig[i], (stamp_ns - t0) / (t1 - t0)
                )
        best = None
        for j in (i - 1, i):
            if 0 <= j < len(stamps):
                gap = abs(int(stamps[j]) - int(stamp_ns))
                if gap <= tolerance_s * 1e9 and (best is None or gap < best[0]):
                    best = (gap, j)
        return None if best is None else self.T_world_rig[best[1]].copy()


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """(4, 4) the pose a fraction ``s`` (0..1) of the way from ``T0`` to ``T1``: the
    translation linearly, the rotation along the shortest arc (slerp)."""
    T = np.eye(4)
    T[:3, :3] = slerp_rotation(T0[:3, :3], T1[:3, :3], s)
    T[:3, 3] = (1.0 - s) * T0[:3, 3] + s * T1[:3, 3]
    return T


def _stamp(msg: Any, log_time: int) -> int:
    ts = msg.timestamp
    stamp = int(ts.seconds) * 1_000_000_000 + int(ts.nanos)
    return stamp if stamp > 0 else int(log_time)


def _pose_matrix(msg: Any) -> np.ndarray | None:
    """(4, 4) of a FrameTransform message; None if its quaternion is zero or not finite."""
    q = np.array([msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w], float)
    t = np.array([msg.translation.x, msg.translation.y, msg.translation.z], float)
    norm = float(np.linalg.norm(q))
    if not (np.isfinite(norm) and norm > 1e-9 and np.isfinite(t).all()):
        return None
    T = np.eye(4)
    T[:3, :3] = rotation_from_quaternion(q / norm)
    T[:3, 3] = t
    return T


def read_poses(
    path: str | Path, reference: str | None = None, log_range: tuple[int, int] | None = None
) -> RecordingPoses | None:
    """Every ``world -> rig`` pose of the recording at ``path`` (see the module
    docstring), or None if it has none.

    Args:
        path: the recording (.mcap).
        reference: the rig's reference sensor, also read as the child (default: the
            ``reference`` of the recording's ``trifuse.recording`` metadata, if any).
        log_range: ``(first, last)`` log times (ns): only the transforms logged between
            them are read (only the chunks that hold such messages); None: all.

    Returns:
        The poses sorted by stamp (of repeated stamps, the first), or None. A damaged file
        gives the poses before the damage (noted in ``notes``).

    Raises:
        RecordingError: the file does not open or is no MCAP file.
    """
    index = McapIndex.open(path)
    try:
        if reference is None:
            reference = index.metadata.get(METADATA_NAME, {}).get("reference")
        children = [RIG_FRAME] + ([reference] if reference and reference != RIG_FRAME else [])
        decoders = DecoderFactory()
        found: dict[tuple[str, str], list[tuple[int, np.ndarray]]] = {
            (p, c): [] for p in POSE_PARENTS for c in children
        }
        notes: list[str] = []
        bad = 0
        try:
            lo, hi = log_range if log_range is not None else (None, None)
            for ref in index.chunks:
                if lo is not None and (ref.end_ns < lo or ref.start_ns > hi):
                    continue
                for message in index.read_chunk(ref):
                    if lo is not None and not lo <= message.log_time <= hi:
                        continue
                    channel = index.channels[message.channel_id]
                    schema = index.schema_of(channel)
                    if schema is None or schema.name not in _TRANSFORM_SCHEMAS:
                        continue
                    decode = decoders.decoder_for(channel.message_encoding, schema)
                    if decode is None:
                        continue
                    try:
                        msg = decode(message.data)
                    except Exception:
                        bad += 1
                        continue
                    items = msg.transforms if schema.name.endswith("s") else [msg]
                    for tf in items:
                        key = (tf.parent_frame_id, tf.child_frame_id)
                        if key not in found:
                            continue
                        T = _pose_matrix(tf)
                        if T is None:
                            bad += 1
                            continue
                        found[key].append((_stamp(tf, message.log_time), T))
        except McapDamage as exc:
            notes.append(f"poses read up to the damage at byte {exc.offset}: {exc.reason}")
        if index.damage is not None and not notes:
            damage = index.damage
            notes.append(f"poses read up to the damage at byte {damage.offset}: {damage.reason}")
        if bad:
            notes.append(f"{bad} transforms skipped (undecodable, or a zero quaternion)")
    finally:
        index.close()
    used = [key for key, poses in found.items() if poses]  # in order of preference
    if not used:
        return None
    parent, child = used[0]
    poses = sorted(found[used[0]], key=lambda p: p[0])
    stamps = np.array([stamp for stamp, _ in poses], dtype=np.int64)
    keep = np.ones(len(stamps), dtype=bool)
    keep[1:] = np.diff(stamps) > 0
    T = np.stack([T for _, T in poses])[keep]
    if len(used) > 1:
        ignored = ", ".join(f"{p} -> {c}" for p, c in used[1:])
        notes.append(f"poses {parent} -> {child} used; {ignored} ignored")
    return RecordingPoses(stamps[keep], T, parent, child, tuple(notes))
