"""Replaying trifuse recordings (MCAP with Foxglove's schemas, docs/FORMATS.md).

:class:`ReplaySource` is a :class:`~app.sources.base.FrameSource`: frames in time order,
in real time or as fast as possible, with rate, pause, seek and loop (the machinery is
:class:`~app.recording.player.MessageReplay`). The rig comes from the recording's
``rig.yaml`` attachment, or, without one, is rebuilt from the ``foxglove.CameraCalibration``
and ``foxglove.FrameTransform`` messages.

Decoding: colour JPEG -> (H, W, 3) uint8 RGB; thermal ``16UC1`` centi-kelvin -> float32
kelvin, NaN where 0 (``32FC1`` as it is); TOF distance ``16UC1`` millimetres -> float32
metres, NaN where 0 (``32FC1`` metres, NaN where not positive); TOF amplitude -> float32.
The distance and amplitude messages of one instant become one ``Frame(sensor, stamp,
image=amplitude, distance_m=distance)``.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from mcap.records import Channel, Message
from mcap_protobuf.decoder import DecoderFactory

from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.images import raw_plane, rgb_from_compressed, rgb_from_raw, values
from trifuse.app.recording.layout import (
    METADATA_NAME,
    MODALITY_OF_KIND,
    POSE_PARENTS,
    RIG_ATTACHMENT,
    RIG_FRAME,
    TF_TOPIC,
    parse_topic,
)
from trifuse.app.recording.mcapindex import McapDamage
from trifuse.app.recording.player import MessageReplay, Route
from trifuse.app.recording.poses import RecordingPoses, read_poses
from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Eye, Rig, Sensor, check_physical, rig_from_yaml
from trifuse.calib.transforms import invert, make_T, rotation_from_quaternion
from trifuse.calib.units import kelvin_from_counts, metres_from_counts

RIG_PROBE_S = 2.0
"""Without a rig attachment, calibration and transforms are looked for in this much of the
start of the recording (the writer puts them at the first frame's time)."""


def _stamp(msg: Any, message: Message) -> int:
    """The message's own timestamp in ns, or its log time if it has none."""
    ts = msg.timestamp
    stamp = int(ts.seconds) * 1_000_000_000 + int(ts.nanos)
    return stamp if stamp > 0 else message.log_time


Size = tuple[int, int] | None
"""The (width, height) an image must have (the rig's), None: any up to the rig limit."""


def decode_raw(msg: Any, size: Size = None) -> np.ndarray:
    """The pixels of a foxglove.RawImage in their stored dtype; its width and height are
    checked against ``size`` first (:func:`app.recording.images.check_size`)."""
    return raw_plane(msg.data, msg.width, msg.height, msg.step, msg.encoding, size=size)


def thermal_kelvin(msg: Any, size: Size = None) -> np.ndarray:
    """foxglove.RawImage thermal -> (H, W) float32 kelvin, NaN = no reading."""
    plane = decode_raw(msg, size)
    if msg.encoding in ("16UC1", "mono16"):
        return kelvin_from_counts(plane)
    if msg.encoding == "32FC1":
        return values(plane)
    raise ValueError(f"thermal image: expected encoding 16UC1 or 32FC1, got {msg.encoding!r}")


def distance_metres(msg: Any, size: Size = None) -> np.ndarray:
    """foxglove.RawImage TOF distance -> (H, W) float32 metres, NaN = invalid."""
    plane = decode_raw(msg, size)
    if msg.encoding in ("16UC1", "mono16"):
        return metres_from_counts(plane)
    if msg.encoding == "32FC1":
        out = values(plane)
        out[~(out > 0)] = np.nan
        return out
    raise ValueError(f"TOF distance: expected encoding 16UC1 or 32FC1, got {msg.encoding!r}")


def amplitude(msg: Any, size: Size = None) -> np.ndarray:
    """foxglove.RawImage TOF amplitude -> (H, W) float32."""
    plane = decode_raw(msg, size)
    if plane.ndim != 2:
        raise ValueError(f"TOF amplitude: expected a single-channel image, got {msg.encoding!r}")
    return plane.astype(np.float32)


def color_rgb(msg: Any, size: Size = None) -> np.ndarray:
    """foxglove.CompressedImage (JPEG/PNG) or RawImage (rgb8, bgr8, mono8) -> RGB uint8."""
    if hasattr(msg, "format"):
        return rgb_from_compressed(msg.data, size)
    return rgb_from_raw(decode_raw(msg, size), msg.encoding)


_DECODERS = {
    "color": color_rgb,
    "thermal": thermal_kelvin,
    "tof_distance": distance_metres,
    "tof_amplitude": amplitude,
}
_SCHEMAS = {
    "color": ("foxglove.CompressedImage", "foxglove.RawImage"),
    "thermal": ("foxglove.RawImage",),
    "tof_distance": ("foxglove.RawImage",),
    "tof_amplitude": ("foxglove.RawImage",),
    "calibration": ("foxglove.CameraCalibration",),
}


class ReplaySource(MessageReplay):
    """Replays a trifuse recording (see the module docstring and
    :class:`~app.recording.player.MessageReplay` for rate, pause, seek, loop, damage).

    Args:
        path: the ``.mcap`` recording.
        rate, loop, realtime, on_damage, pair_tolerance_s, clock, sleep: keyword
            arguments, see :class:`~app.recording.player.MessageReplay`.

    Attributes:
        rig: from the ``rig.yaml`` attachment, else rebuilt from the calibration and
            transform messages (None if the recording has neither).
        rig_source: ``"attachment"``, ``"messages"`` or None.
        sensors: the rig's sensors in rig order (also those without frames in the file),
            then any other sensor with frames.
        metadata: the ``trifuse.recording`` metadata (format, writer options).

    :meth:`head_pose` gives the head's pose where the recording has it (``world -> rig``
    on ``/tf``).

    Raises RecordingError if the file is not an MCAP recording (damage later in the file is
    reported when the replay reaches it).
    """

    def _opened(self) -> None:
        """Reads the rig and the sensors (see the class docstring)."""
        self._decoders = DecoderFactory()
        self.metadata = dict(self.index.metadata.get(METADATA_NAME, {}))
        self._calibrations: dict[str, Any] = {}
        self._transforms: dict[str, tuple[str, np.ndarray]] = {}
        self.rig_source: str | None = None
        self.rig = self._rig_from_attachment()
        if self.rig is None:
            self.rig = self._rig_from_messages()
        self.expect(self.rig)
        recorded = self.recorded_sensors
        names = list(self.rig.names) if self.rig is not None else []
        self.sensors = names + [s for s in recorded if s not in names]
        for sensor in self.sensors:
            parts = {
                kind
                for s, kind in self._frame_channels().values()
                if s == sensor and kind.startswith("tof_")
            }
            if parts:
                self._tof_parts[sensor] = parts
        missing = [s for s in names if s not in recorded]
        if missing and self.index.indexed_by == "summary":
            self.notes.append(f"no frames of {missing} in the recording")
        self._poses: RecordingPoses | None = None
        self._poses_read = False
        self._poses_lock = threading.Lock()

    # -- the head's pose ------------------------------------------------------------------

    def head_pose(self, stamp_ns: int) -> np.ndarray | None:
        """(4, 4) ``T_world_rig`` at ``stamp_ns`` from the recording's ``world -> rig``
        transforms (:meth:`app.recording.poses.RecordingPoses.at`: that stamp's pose, or
        interpolated between the poses around it), or None if the recording has none
        there. The poses are read at the first call (the whole file once)."""
        with self._poses_lock:
            if not self._poses_read:
                try:
                    self._poses = read_poses(self.path, self.rig.reference if self.rig else None)
                except RecordingError:
                    self._poses = None
                self._poses_read = True
        return None if self._poses is None else self._poses.at(int(stamp_ns))

    # -- channels -------------------------------------------------------------------------

    def _kind_of(self, channel: Channel) -> tuple[str, str] | None:
        meta = channel.metadata or {}
        if "trifuse.sensor" in meta and "trifuse.kind" in meta:
            return meta["trifuse.sensor"], meta["trifuse.kind"]
        return parse_topic(channel.topic)

    def _frame_channels(self) -> dict[int, tuple[str, str]]:
        """channel id -> (sensor, kind) of the frame channels known (with messages)."""
        out = {}
        counts = self.index.message_counts
        for cid, ch in self.index.channels.items():
            sk = self._kind_of(ch)
            if sk is None or sk[1] not in _DECODERS:
                continue
            if counts is not None and counts.get(cid, 0) == 0:
                continue
            out[cid] = sk
        return out

    @property
    def recorded_sensors(self) -> list[str]:
        """Sensors with frames in the file (of the channels known: all of them unless the
        file had to be scanned, then those met so far)."""
        seen: list[str] = []
        for sensor, _kind in self._frame_channels().values():
            if sensor not in seen:
                seen.append(sensor)
        return seen

    def message_count(self, sensor: str, kind: str) -> int | None:
        """Messages of one sensor's stream (from the file's statistics; None if unknown)."""
        counts = self.index.message_counts
        if counts is None:
            return None
        return sum(
            counts.get(cid, 0)
            for cid, ch in self.index.channels.items()
            if self._kind_of(ch) == (sensor, kind)
        )

    def log_times(self, sensor: str, kind: str) -> np.ndarray | None:
        """(N,) int64 sorted log times (ns) of one sensor's stream, from the file's message
        indexes (:meth:`~app.recording.mcapindex.McapIndex.log_times`); None if the file
        has none."""
        ids = [
            cid for cid, ch in self.index.channels.items() if self._kind_of(ch) == (sensor, kind)
        ]
        return self.index.log_times(ids) if ids else None

    def _decoder(self, channel: Channel) -> Any:
        schema = self.index.schema_of(channel)
        dec = self._decoders.decoder_for(channel.message_encoding, schema)
        if dec is None:
            raise RecordingError(
                f"{self.path}: channel {channel.topic}: cannot decode {channel.message_encoding!r} "
                f"messages of schema {schema.name if schema else None!r}"
            )
        return dec

    def _route(self, channel: Channel) -> Route | None:
        sk = self._kind_of(channel)
        if sk is None:
            return None
        sensor, kind = sk
        schema = self.index.schema_of(channel)
        if kind not in _DECODERS or schema is None or schema.name not in _SCHEMAS[kind]:
            return None
        proto = self._decoder(channel)
        convert = _DECODERS[kind]

        def decode(message: Message, size: Size = None) -> tuple[int, np.ndarray]:
            msg = proto(message.data)
            return _stamp(msg, message), convert(msg, size)

        return Route(sensor, kind, decode)

    # -- the rig --------------------------------------------------------------------------

    def _rig_from_attachment(self) -> Rig | None:
        try:
            data = self.index.attachment(RIG_ATTACHMENT)
        except McapDamage as exc:
            self.notes.append(f"the {RIG_ATTACHMENT} attachment is damaged ({exc.reason})")
            return None
        if data is None:
            return None
        try:
            rig = rig_from_yaml(data.decode("utf-8"))
        except (RigError, UnicodeDecodeError) as exc:
            self.notes.append(f"the {RIG_ATTACHMENT} attachment is not a valid rig file: {exc}")
            return None
        self.rig_source = "attachment"
        return rig

    def _rig_from_messages(self) -> Rig | None:
        """Read the calibration and transform messages near the start; build a rig."""
        limit = self.start_ns + round(RIG_PROBE_S * 1e9)
        wanted = {
            cid
            for cid, ch in self.index.channels.items()
            if ch.topic == TF_TOPIC or (self._kind_of(ch) or ("", ""))[1] == "calibration"
        }
        try:
            for message in self.index.messages(self.start_ns):
                if message.log_time > limit:
                    break
                ch = self.index.channels[message.channel_id]
                if message.channel_id not in wanted:
                    # channels met while scanning a file without its summary
                    if ch.topic != TF_TOPIC and (self._kind_of(ch) or ("", ""))[1] != "calibration":
                        continue
                    wanted.add(message.channel_id)
                schema = self.index.schema_of(ch)
                try:
                    msg = self._decoder(ch)(message.data)
                except Exception:
                    continue
                if schema is not None and schema.name == "foxglove.FrameTransform":
                    if msg.parent_frame_id in POSE_PARENTS:
                        continue  # the head's pose, not the rig's
                    t, q = msg.translation, msg.rotation
                    T = make_T(rotation_from_quaternion([q.x, q.y, q.z, q.w]), (t.x, t.y, t.z))
                    self._transforms.setdefault(msg.child_frame_id, (msg.parent_frame_id, T))
                elif schema is not None and schema.name == "foxglove.CameraCalibration":
                    self._calibrations.setdefault(msg.frame_id, msg)
        except McapDamage:
            pass
        modalities = {s: MODALITY_OF_KIND[k] for s, k in self._frame_channels().values()}
        try:
            rig = rig_from_calibrations(self._calibrations, self._transforms, modalities)
        except (ValueError, KeyError) as exc:
            self.notes.append(f"the calibration messages do not make a rig: {exc}")
            return None
        if rig is not None:
            self.rig_source = "messages"
        return rig


_SIDE_RE = re.compile(r"^(?P<base>.*?)[_-]?(?P<side>left|right|[lr])$", re.IGNORECASE)


def _eyes(modalities: Mapping[str, str]) -> dict[str, Eye]:
    """Pair colour and thermal sensors whose names end in the same side (left/right)."""
    by_side: dict[str, dict[str, list[str]]] = {}
    for name, modality in modalities.items():
        m = _SIDE_RE.match(name)
        if m is None or modality not in ("color", "thermal"):
            continue
        side = {"l": "left", "r": "right"}.get(m["side"].lower(), m["side"].lower())
        by_side.setdefault(side, {}).setdefault(modality, []).append(name)
    return {
        side: Eye(d["color"][0], d["thermal"][0])
        for side, d in by_side.items()
        if len(d.get("color", [])) == 1 and len(d.get("thermal", [])) == 1
    }


def rig_from_calibrations(
    calibrations: Mapping[str, Any],
    transforms: Mapping[str, tuple[str, np.ndarray]],
    modalities: Mapping[str, str],
    sensors: Iterable[str] | None = None,
) -> Rig | None:
    """A rig from CameraCalibration messages (K, D, size per sensor) and FrameTransforms
    (child -> (parent, T_parent_child)); None without calibrations.

    The reference is the parent when it is a sensor, else (parent ``rig``) the TOF sensor
    (or the first) and every pose is re-expressed relative to it; a sensor without a
    transform gets the identity (noted in the error only if that breaks the rig). Eyes pair
    colour and thermal sensors whose names end in the same side (``_left``/``_right``).
    """
    names = [s for s in (sensors or calibrations) if s in calibrations and s in modalities]
    if not names:
        return None
    poses: dict[str, np.ndarray] = {}
    for name in names:
        parent, T = transforms.get(name, (RIG_FRAME, np.eye(4)))
        if parent in calibrations and parent != name:
            T = transforms.get(parent, (RIG_FRAME, np.eye(4)))[1] @ T
        poses[name] = T
    tofs = [n for n in names if modalities[n] == "tof"]
    parents = {transforms[n][0] for n in names if n in transforms}
    sensor_parents = [p for p in parents if p in names]
    reference = sensor_parents[0] if sensor_parents else (tofs[0] if tofs else names[0])
    T_ref = invert(poses[reference])
    built = {}
    for name in names:
        msg = calibrations[name]
        K = list(msg.K)
        if len(K) != 9:
            raise ValueError(f"calibration of {name!r}: expected 9 K values, got {len(K)}")
        intr = Intrinsics(K[0], K[4], K[2], K[5], tuple(msg.D) or (0.0,) * 5)
        T = np.eye(4) if name == reference else T_ref @ poses[name]
        built[name] = Sensor(
            name,
            modalities[name],
            (int(msg.width), int(msg.height)),
            intr,
            T,  # type: ignore[arg-type]
        )
        check_physical(built[name])  # a recording's calibration is input, as a rig file is
    return Rig(sensors=built, reference=reference, eyes=_eyes({n: modalities[n] for n in names}))
