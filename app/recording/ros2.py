"""Replaying ROS 2 bags stored as MCAP (no ROS installation needed).

``sensor_msgs/msg/Image`` (``mono8``, ``mono16``, ``16UC1``, ``16SC1``, ``32FC1``,
``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``), ``sensor_msgs/msg/CompressedImage`` (JPEG, PNG,
16-bit PNG, ``compressedDepth``) and ``sensor_msgs/msg/CameraInfo`` are decoded with
mcap-ros2-support and mapped onto sensors by a topic map (:mod:`app.recording.topicmap`).
:class:`Ros2BagSource` shares the replay machinery of
:class:`~app.recording.reader.ReplaySource` (rate, pause, seek, loop, damage, TOF pairing).

:data:`MSGDEFS` holds the ROS 2 message definitions as text (with their dependencies, in
the concatenated form rosbag2 stores), for writing such bags without ROS (tests, tools).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Message
from mcap_ros2.decoder import DecoderFactory

from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.images import (
    plane_from_compressed,
    raw_plane,
    rgb_from_compressed,
    rgb_from_raw,
    values,
)
from trifuse.app.recording.mcapindex import McapDamage
from trifuse.app.recording.player import MessageReplay, Route
from trifuse.app.recording.topicmap import TopicMap, TopicSpec, load_topic_map
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig

_SEP = "=" * 80
_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_DEPS = f"{_SEP}\nMSG: std_msgs/Header\n{_HEADER}{_SEP}\nMSG: builtin_interfaces/Time\n{_TIME}"
MSGDEFS: dict[str, str] = {
    "sensor_msgs/msg/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n" + _DEPS
    ),
    "sensor_msgs/msg/CompressedImage": (
        "std_msgs/Header header\nstring format\nuint8[] data\n" + _DEPS
    ),
    "sensor_msgs/msg/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
        "uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n"
        + _DEPS
        + f"{_SEP}\nMSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\n"
        "uint32 height\nuint32 width\nbool do_rectify\n"
    ),
}
"""ROS 2 message definitions, ``datatype -> text``, for ``Writer.register_msgdef`` of
mcap-ros2-support."""

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
_TYPES_OF_KIND = {
    "color": (IMAGE, COMPRESSED),
    "thermal": (IMAGE, COMPRESSED),
    "tof_distance": (IMAGE, COMPRESSED),
    "tof_amplitude": (IMAGE, COMPRESSED),
    "camera_info": (CAMERA_INFO,),
}
CAMERA_INFO_PROBE_S = 2.0
"""At opening, camera info is looked for in this much of the start of the bag."""


def _datatype(name: str) -> str:
    """``sensor_msgs/Image`` and ``sensor_msgs/msg/Image`` -> ``sensor_msgs/msg/Image``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name


def _header_stamp(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def convert_image(
    msg: Any, datatype: str, spec: TopicSpec, size: tuple[int, int] | None = None
) -> np.ndarray:
    """A decoded Image / CompressedImage -> the program's array for ``spec.kind``; the
    image's size (its header) is checked against ``size`` (the rig's, or None: at most the
    largest a rig describes) before it is decoded."""
    if datatype == COMPRESSED:
        if spec.kind == "color":
            return rgb_from_compressed(bytes(msg.data), size)
        plane = plane_from_compressed(bytes(msg.data), msg.format, size)
    else:
        be = bool(msg.is_bigendian)
        plane = raw_plane(bytes(msg.data), msg.width, msg.height, msg.step, msg.encoding, be, size)
        if spec.kind == "color":
            return rgb_from_raw(plane, msg.encoding)
        if plane.ndim != 2:
            raise ValueError(f"{spec.kind}: expected a single-channel image, got {msg.encoding!r}")
    out = values(plane, spec.scale, spec.offset, spec.invalid)
    if spec.kind == "tof_distance":
        out[~(out > 0)] = np.nan  # a radial distance is positive
    return out


def intrinsics_from_camera_info(msg: Any) -> tuple[Intrinsics, tuple[int, int]]:
    """(Intrinsics, (width, height)) of a decoded CameraInfo (``plumb_bob`` /
    ``rational_polynomial``: OpenCV's coefficient order)."""
    k = list(msg.k)
    d = tuple(float(v) for v in msg.d) or (0.0,) * 5
    if len(d) not in (4, 5, 8):
        d = (tuple(d) + (0.0,) * 8)[:8] if len(d) < 8 else tuple(d[:8])
    return Intrinsics(k[0], k[4], k[2], k[5], d), (int(msg.width), int(msg.height))


class Ros2BagSource(MessageReplay):
    """Replays the images of a ROS 2 bag (MCAP) as trifuse frames, through a topic map.

    Args:
        path: the bag's ``.mcap`` file.
        topic_map: a :class:`~app.recording.topicmap.TopicMap` or the path of one.
        rate, loop, realtime, on_damage, pair_tolerance_s: see
            :class:`~app.recording.player.MessageReplay`.
        rig: the rig of the head (a Rig or a rig file path), if known; a bag carries none.

    Attributes:
        sensors: the topic map's sensors (also those the bag has no messages of).
        camera_info: sensor -> (Intrinsics, (width, height)) from the ``camera_info``
            topics (the first one found near the start; updated while playing).
        notes: mapped topics the bag does not have, and other non-fatal findings.

    A mapped topic of the wrong message type raises RecordingError (at opening when the
    bag has its summary, else when the replay meets it).
    """

    def __init__(
        self,
        path: str | Path,
        topic_map: TopicMap | str | Path,
        rate: float = 1.0,
        loop: bool = False,
        realtime: bool = True,
        *,
        rig: Rig | str | Path | None = None,
        on_damage: str = "raise",
        pair_tolerance_s: float = 0.001,
    ) -> None:
        tmap = topic_map if isinstance(topic_map, TopicMap) else load_topic_map(topic_map)
        if rig is not None and not isinstance(rig, Rig):
            from trifuse.app.storage.rigfile import load_rig

            rig = load_rig(rig)
        super().__init__(
            path,
            rate=rate,
            loop=loop,
            realtime=realtime,
            on_damage=on_damage,
            pair_tolerance_s=pair_tolerance_s,
        )
        try:
            self.topic_map = tmap
            self.sensors = tmap.sensors
            self.rig = rig
            if rig is not None:
                self._check_rig(rig)
            self.expect(rig)
            self._decoders = DecoderFactory()
            self.camera_info: dict[str, tuple[Intrinsics, tuple[int, int]]] = {}
            for sensor in self.sensors:
                parts = {k for k in tmap.for_sensor(sensor) if k.startswith("tof_")}
                if parts:
                    self._tof_parts[sensor] = parts
            present = {ch.topic for ch in self.index.channels.values()}
            for cid, ch in self.index.channels.items():
                if ch.topic in tmap.topics:
                    self._route_of(cid)  # checks the message type now
            if self.index.indexed_by == "summary":
                for topic, spec in tmap.topics.items():
                    if topic not in present:
                        self.notes.append(
                            f"topic {topic} ({spec.sensor} {spec.kind}) is not in the bag"
                        )
            self._probe_camera_info()
        except BaseException:
            self.index.close()
            raise

    def _check_rig(self, rig: Rig) -> None:
        for sensor, modality in self.topic_map.modalities.items():
            if sensor not in rig:
                raise RecordingError(
                    f"topic map: sensor {sensor!r} is not in the rig (sensors: {rig.names})"
                )
            if rig[sensor].modality != modality:
                raise RecordingError(
                    f"topic map: sensor {sensor!r} is {modality} by its topics, but "
                    f"{rig[sensor].modality} in the rig"
                )

    def _route(self, channel: Channel) -> Route | None:
        spec = self.topic_map.topics.get(channel.topic)
        if spec is None:
            return None
        schema = self.index.schema_of(channel)
        datatype = _datatype(schema.name) if schema is not None else "?"
        if datatype not in _TYPES_OF_KIND[spec.kind]:
            raise RecordingError(
                f"{self.path}: topic {channel.topic} ({spec.sensor} {spec.kind}): expected "
                f"{' or '.join(_TYPES_OF_KIND[spec.kind])} messages, the bag has {datatype}"
            )
        cdr = self._decoders.decoder_for(channel.message_encoding, schema)
        if cdr is None:
            raise RecordingError(
                f"{self.path}: topic {channel.topic}: cannot decode {channel.message_encoding!r} "
                f"messages (expected cdr with a ros2msg schema)"
            )
        use_header = self.topic_map.stamp == "header"

        def decode(message: Message, size: tuple[int, int] | None = None) -> tuple[int, Any]:
            msg = cdr(message.data)
            stamp = _header_stamp(msg) if use_header else 0
            if stamp <= 0:
                stamp = message.log_time
            if spec.kind == "camera_info":
                return stamp, msg
            return stamp, convert_image(msg, datatype, spec, size)

        return Route(spec.sensor, spec.kind, decode)

    def _side_message(self, route: Route, message: Message) -> None:
        if route.kind == "camera_info":
            _stamp, msg = route.decode(message)
            self.camera_info[route.sensor] = intrinsics_from_camera_info(msg)

    def _probe_camera_info(self) -> None:
        wanted = {t.sensor for t in self.topic_map.topics.values() if t.kind == "camera_info"}
        if not wanted:
            return
        limit = self.start_ns + round(CAMERA_INFO_PROBE_S * 1e9)
        try:
            for message in self.index.messages(self.start_ns):
                if message.log_time > limit or wanted <= self.camera_info.keys():
                    break
                ch = self.index.channels[message.channel_id]
                spec = self.topic_map.topics.get(ch.topic)
                if spec is None or spec.kind != "camera_info" or spec.sensor in self.camera_info:
                    continue
                route = self._route_of(message.channel_id)
                if route is not None:
                    try:
                        self._side_message(route, message)
                    except Exception as exc:
                        self.notes.append(f"camera info on {ch.topic} is malformed: {exc}")
        except McapDamage:
            pass
