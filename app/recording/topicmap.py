"""Topic maps: which ROS 2 topics of a bag are which sensor's images, and their units.

A topic map is a small YAML file (format ``trifuse-topic-map/1``, docs/FORMATS.md)::

    format: trifuse-topic-map/1
    stamp: header                 # optional: header (default) or log_time
    sensors:
      ccd_left:
        color: /left/image_raw/compressed          # a topic alone ...
        camera_info: /left/camera_info
      thermal_left:
        thermal: {topic: /lwir_left/image_raw, scale: 0.01, invalid: 0}   # ... or with units
      tof:
        tof_distance: {topic: /tof/distance, scale: 0.001, invalid: 0}
        tof_amplitude: /tof/amplitude
    pose: {world: odom, rig: tof_link}   # optional, live topics: the head's pose from tf2

Raw values become kelvin (thermal) or metres (TOF distance) as ``value * scale + offset``;
a stored value equal to ``invalid`` (one number or a list) becomes NaN. A sensor's kinds
give its modality: ``color`` -> color, ``thermal`` -> thermal, ``tof_distance`` /
``tof_amplitude`` -> tof; ``camera_info`` may be added to any.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from trifuse.app.recording.errors import TopicMapError
from trifuse.app.storage.text import read_text
from trifuse.calib.numbers import check_finite
from trifuse.calib.yaml_text import YamlError, parse_yaml

TOPIC_MAP_FORMAT = "trifuse-topic-map/1"
KINDS = ("color", "thermal", "tof_distance", "tof_amplitude", "camera_info")
MODALITY_OF_KIND = {
    "color": "color",
    "thermal": "thermal",
    "tof_distance": "tof",
    "tof_amplitude": "tof",
}
_VALUE_KINDS = ("thermal", "tof_distance", "tof_amplitude")
_STAMPS = ("header", "log_time")


@dataclass(frozen=True)
class TopicSpec:
    """One mapped topic.

    Attributes:
        topic: the ROS 2 topic name.
        sensor: the sensor id it belongs to.
        kind: one of :data:`KINDS`.
        scale, offset: raw value -> SI (kelvin, metres): ``value * scale + offset``.
        invalid: stored values meaning "no reading" (-> NaN).
    """

    topic: str
    sensor: str
    kind: str
    scale: float = 1.0
    offset: float = 0.0
    invalid: tuple[float, ...] = ()


@dataclass(frozen=True)
class PoseSpec:
    """Where the head's pose comes from (live ROS 2 topics): the ``tf2`` frames of the
    world and of the rig (the TOF's frame), and the transform topics."""

    world: str
    rig: str
    topic: str = "/tf"
    static_topic: str = "/tf_static"


@dataclass(frozen=True)
class TopicMap:
    """A parsed topic map.

    Attributes:
        topics: topic name -> its spec.
        modalities: sensor id -> modality, in file order.
        stamp: ``"header"`` (frames carry the header stamp; log time if it is zero) or
            ``"log_time"``.
    """

    topics: dict[str, TopicSpec]
    modalities: dict[str, str]
    stamp: str = "header"
    pose: PoseSpec | None = None
    """The head's pose from tf2 (live topics only; a bag's replay ignores it)."""

    @property
    def sensors(self) -> list[str]:
        return list(self.modalities)

    def for_sensor(self, sensor: str) -> dict[str, TopicSpec]:
        """kind -> spec of one sensor."""
        return {t.kind: t for t in self.topics.values() if t.sensor == sensor}


def _number(value: Any, where: str) -> float:
    return check_finite(value, where, TopicMapError)


def topic_map_from_dict(data: Any, where: str = "topic map") -> TopicMap:
    """Build a TopicMap from parsed YAML; TopicMapError names the field."""
    if not isinstance(data, Mapping):
        raise TopicMapError(f"{where}: expected a mapping, got {type(data).__name__}")
    unknown = sorted(set(data) - {"format", "stamp", "sensors", "pose"}, key=str)
    if unknown:
        raise TopicMapError(
            f"{where}: unknown key(s) {unknown} (allowed: format, stamp, sensors, pose)"
        )
    if data.get("format") != TOPIC_MAP_FORMAT:
        raise TopicMapError(
            f"{where}: field 'format': expected {TOPIC_MAP_FORMAT!r}, got {data.get('format')!r}"
        )
    stamp = data.get("stamp", "header")
    if stamp not in _STAMPS:
        raise TopicMapError(f"{where}: field 'stamp': expected one of {_STAMPS}, got {stamp!r}")
    sensors = data.get("sensors")
    if not isinstance(sensors, Mapping) or not sensors:
        raise TopicMapError(f"{where}: field 'sensors': expected a mapping of sensor -> topics")
    topics: dict[str, TopicSpec] = {}
    modalities: dict[str, str] = {}
    for sensor, kinds in sensors.items():
        sensor = str(sensor)
        w = f"{where}: sensors.{sensor}"
        if not isinstance(kinds, Mapping) or not kinds:
            raise TopicMapError(f"{w}: expected a mapping of kind -> topic, got {kinds!r}")
        bad = sorted(set(map(str, kinds)) - set(KINDS))
        if bad:
            raise TopicMapError(f"{w}: unknown kind(s) {bad} (known: {', '.join(KINDS)})")
        mods = {MODALITY_OF_KIND[k] for k in kinds if k in MODALITY_OF_KIND}
        if len(mods) != 1:
            raise TopicMapError(
                f"{w}: expected the kinds of one modality (color; thermal; tof_distance and/or "
                f"tof_amplitude), optionally with camera_info; got {sorted(kinds)}"
            )
        modalities[sensor] = mods.pop()
        for kind, entry in kinds.items():
            wk = f"{w}.{kind}"
            if isinstance(entry, str):
                entry = {"topic": entry}
            if not isinstance(entry, Mapping):
                raise TopicMapError(f"{wk}: expected a topic name or a mapping, got {entry!r}")
            allowed = {"topic"} | (
                {"scale", "offset", "invalid"} if kind in _VALUE_KINDS else set()
            )
            extra = sorted(set(map(str, entry)) - allowed)
            if extra:
                raise TopicMapError(f"{wk}: unknown key(s) {extra} (allowed: {sorted(allowed)})")
            topic = entry.get("topic")
            if not isinstance(topic, str) or not topic.startswith("/"):
                raise TopicMapError(f"{wk}.topic: expected a topic name like '/x/y', got {topic!r}")
            if topic in topics:
                raise TopicMapError(f"{wk}.topic: {topic} is mapped twice")
            scale = _number(entry.get("scale", 1.0), f"{wk}.scale")
            if scale == 0:
                raise TopicMapError(f"{wk}.scale: expected a non-zero number, got 0")
            offset = _number(entry.get("offset", 0.0), f"{wk}.offset")
            inv = entry.get("invalid", [])
            inv_list = inv if isinstance(inv, list) else [inv]
            invalid = tuple(_number(v, f"{wk}.invalid") for v in inv_list)
            topics[topic] = TopicSpec(topic, sensor, str(kind), scale, offset, invalid)
    return TopicMap(topics, modalities, stamp, _pose(data.get("pose"), f"{where}: pose"))


def _pose(entry: Any, where: str) -> PoseSpec | None:
    """The ``pose`` section: ``world`` and ``rig`` frames, optional ``topic`` and
    ``static_topic``."""
    if entry is None:
        return None
    if not isinstance(entry, Mapping):
        raise TopicMapError(f"{where}: expected a mapping with world and rig, got {entry!r}")
    extra = sorted(set(map(str, entry)) - {"world", "rig", "topic", "static_topic"})
    if extra:
        raise TopicMapError(f"{where}: unknown key(s) {extra} (allowed: world, rig, topic, "
                            "static_topic)")  # fmt: skip
    values = {}
    for key in ("world", "rig", "topic", "static_topic"):
        value = entry.get(key)
        if value is None and key in ("world", "rig"):
            raise TopicMapError(f"{where}.{key}: expected a tf2 frame name, got nothing")
        if value is not None:
            if not isinstance(value, str) or not value:
                raise TopicMapError(f"{where}.{key}: expected a name, got {value!r}")
            values[key] = value
    if values["world"] == values["rig"]:
        raise TopicMapError(f"{where}: world and rig are the same frame {values['rig']!r}")
    return PoseSpec(**values)


def topic_map_from_yaml(text: str, where: str = "topic map") -> TopicMap:
    try:
        data = parse_yaml(text)
    except YamlError as exc:
        raise TopicMapError(f"{where}: not valid YAML: {exc}") from None
    return topic_map_from_dict(data, where)


def load_topic_map(path: str | Path) -> TopicMap:
    """Read a topic-map file; TopicMapError names the file and the field."""
    path = Path(path)
    return topic_map_from_yaml(read_text(path, "topic map", TopicMapError), str(path))
