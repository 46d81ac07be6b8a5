"""A robot's live ROS 2 image topics as a frame source, without a ROS installation (issue 36,
item 1): ``trifuse serve --ros2 TOPICS.yaml``.

The topics of a topic map (:mod:`app.recording.topicmap`, the one a bag replay uses) are
read over DDS with Eclipse Cyclone DDS's Python binding (the ``[ros2]`` extra), on the RTPS
wire every ROS 2 middleware on DDS interoperates on: ROS 2 topic ``/a/b`` is DDS topic
``rt/a/b``, of type ``sensor_msgs::msg::dds_::Image_`` (or ``CompressedImage_`` for a topic
whose name ends in ``/compressed`` or ``/compressedDepth``, image_transport's names). The
samples are taken as serialised bytes from the binding's C layer and decoded by
:mod:`app.sources.ros2_cdr` (the binding's own decoder takes 107 ms a colour frame:
docs/FINDINGS.md), then converted as a bag's (:func:`app.recording.ros2.convert_image`:
the same encodings, scales and invalid values). Frames carry the messages' header stamps;
a TOF's distance and amplitude pair by stamp; a sensor whose stamps run behind the others'
by more than a frame is worded in :attr:`Ros2LiveSource.notes` (the Source panel). With a
``pose`` section the map names the tf2 frames of the world and the rig: ``/tf`` and
``/tf_static`` give the head's pose (:meth:`Ros2LiveSource.head_pose`), which the console's
thermal map uses rather than estimating it.

One newest-frame slot per sensor (:class:`app.sources.slots.NewestFrameSlots`): a slow
console gets the newest frames, never a backlog. A message that cannot be used (an
unsupported encoding, another size than the rig's, larger than ``max_message_bytes``) is
counted and worded per topic in :attr:`Ros2LiveSource.problems` and, per sensor, in the
console's sensor health (:meth:`Ros2LiveSource.stats`); the other topics go on.

Large samples need large socket buffers (a 1280 x 960 colour frame is ~2,600 UDP
fragments): unless ``CYCLONEDDS_URI`` is set, the participant asks for
:data:`SOCKET_BUFFER` (the kernel's ``net.core.rmem_max`` may cap it).
"""

from __future__ import annotations

import os
import statistics
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, ClassVar

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.recording.ros2 import convert_image
from trifuse.app.recording.tf_buffer import TfBuffer
from trifuse.app.recording.topicmap import TopicMap, TopicSpec
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.ros2_cdr import COMPRESSED, IMAGE, TF_MESSAGE, decode
from trifuse.app.sources.slots import NewestFrameSlots
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_quaternion

SOCKET_BUFFER = "64MB"
"""The socket receive buffer the participant asks for (unless ``CYCLONEDDS_URI`` is set)."""
DEFAULT_MAX_MESSAGE_BYTES = 64 << 20
"""Larger messages are refused (counted per topic)."""
LAG_KEEP = 30
"""Messages per sensor whose delays (arrival - header stamp) judge whether it runs behind."""
PAIR_KEEP = 8
"""TOF halves (distance or amplitude) kept waiting for their other half, per sensor."""
IMAGE_KINDS = ("color", "thermal", "tof_distance", "tof_amplitude")


def require_cyclonedds() -> ModuleType:
    """The ``cyclonedds`` module; RuntimeError in one line naming the extra when missing."""
    try:
        import cyclonedds
        import cyclonedds.domain
    except ImportError:
        raise RuntimeError(
            "--ros2: Cyclone DDS is not installed; install the extra: pip install -e '.[ros2]'"
        ) from None
    return cyclonedds


def dds_topic(topic: str) -> str:
    """ROS 2 topic ``/a/b`` -> DDS topic ``rt/a/b``."""
    return "rt/" + topic.lstrip("/")


def datatype_of(topic: str) -> str:
    """The message type a topic carries, by image_transport's names."""
    tail = topic.rstrip("/").rsplit("/", 1)[-1]
    return COMPRESSED if tail in ("compressed", "compressedDepth") else IMAGE


@dataclass
class TopicStats:
    """What one topic delivered: messages used, refused (in all and since the last one
    used), the last refusal worded and when (``time.monotonic``)."""

    received: int = 0
    refused: int = 0
    refused_since_used: int = 0
    problem: str | None = None
    refused_s: float | None = field(default=None, repr=False)


class Ros2LiveSource(FrameSource):
    """Frames from live ROS 2 image topics (see the module doc).

    Args:
        topic_map: which topics are which sensor's images.
        rig: the rig (image sizes are checked against it), or None.
        domain_id: the DDS domain (ROS_DOMAIN_ID).
        reliable: QoS reliable (default best effort, what camera drivers publish with;
            a best-effort reader also matches reliable writers).
        max_message_bytes: larger messages are refused.
    """

    source_kind = "live"
    counts_rejections: ClassVar[bool] = True
    """Its :meth:`stats` has ``rejected_by_sensor`` (:class:`app.sources.capabilities.
    RejectionStats`): the console's sensor health shows the refusals."""

    def __init__(
        self,
        topic_map: TopicMap,
        rig: Rig | None = None,
        *,
        domain_id: int = 0,
        reliable: bool = False,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
    ) -> None:
        require_cyclonedds()
        from cyclonedds.core import (
            InstanceState,
            Policy,
            Qos,
            ReadCondition,
            SampleState,
            ViewState,
            WaitSet,
        )
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        from trifuse.app.sources.ros2_types import IDL_TYPES

        self._not_read: list[str] = []  # topics of sensors the rig lacks, worded
        usable = dict(topic_map.modalities)
        if rig is not None:
            for sensor, modality in topic_map.modalities.items():
                if sensor not in rig.sensors or rig[sensor].modality != modality:
                    del usable[sensor]
                    for topic in topic_map.for_sensor(sensor).values():
                        self._not_read.append(
                            f"topic {topic.topic}: sensor {sensor!r} is not a {modality} sensor "
                            f"of the rig (sensors: {', '.join(rig.names)}); not read"
                        )
        if not usable:
            raise ValueError(f"topic map: no sensor of the rig in it ({'; '.join(self._not_read)})")
        topic_map = TopicMap(
            {t: s for t, s in topic_map.topics.items() if s.sensor in usable},
            usable,
            topic_map.stamp,
            topic_map.pose,
        )
        self.topic_map, self.rig, self.domain_id = topic_map, rig, domain_id
        self.sensors = topic_map.sensors
        self.max_message_bytes = max_message_bytes
        self.topic_stats = {
            t: TopicStats() for t, s in topic_map.topics.items() if s.kind in IMAGE_KINDS
        }
        self.slots = NewestFrameSlots(self.sensors)
        self._tof_parts = {
            s: {k for k in topic_map.for_sensor(s) if k.startswith("tof_")} for s in self.sensors
        }
        self._halves: dict[str, dict[int, dict[str, np.ndarray]]] = {}
        self.tf_refused, self.tf_problem = 0, None
        self._lags: dict[str, deque[float]] = {}
        self._last_stamp: dict[str, int] = {}
        self._period_s: dict[str, float] = {}
        if "CYCLONEDDS_URI" not in os.environ:
            os.environ["CYCLONEDDS_URI"] = (
                "<CycloneDDS><Domain><Internal>"
                f'<SocketReceiveBufferSize min="default" max="{SOCKET_BUFFER}"/>'
                "</Internal></Domain></CycloneDDS>"
            )
        self._dp = DomainParticipant(domain_id)
        reliability = Policy.Reliability.Reliable(1_000_000_000) if reliable else (
            Policy.Reliability.BestEffort)  # fmt: skip
        qos = Qos(reliability, Policy.History.KeepLast(1))
        self._waitset = WaitSet(self._dp)
        self._readers: list[tuple[Any, TopicSpec, str]] = []
        for topic, spec in topic_map.topics.items():
            if spec.kind not in IMAGE_KINDS:
                continue  # camera_info: the rig holds the calibration
            datatype = datatype_of(topic)
            t = Topic(self._dp, dds_topic(topic), IDL_TYPES[datatype])
            reader = DataReader(self._dp, t, qos=qos)
            unread = SampleState.NotRead | ViewState.Any | InstanceState.Any
            self._waitset.attach(ReadCondition(reader, unread))
            self._readers.append((reader, spec, datatype))
        self.tf = TfBuffer()
        self._tf_readers: list[tuple[Any, bool]] = []
        pose = topic_map.pose
        if pose is not None:  # the head's pose from tf2: the thermal map uses it
            keep = Policy.History.KeepLast(100)
            latched = Qos(Policy.Reliability.Reliable(1_000_000_000), keep,
                          Policy.Durability.TransientLocal)  # fmt: skip
            streams = ((pose.topic, False, Qos(Policy.Reliability.BestEffort, keep)),
                       (pose.static_topic, True, latched))  # fmt: skip
            for topic, static, q in streams:
                t = Topic(self._dp, dds_topic(topic), IDL_TYPES[TF_MESSAGE])
                reader = DataReader(self._dp, t, qos=q)
                self._waitset.attach(ReadCondition(reader, SampleState.NotRead | ViewState.Any
                                                   | InstanceState.Any))  # fmt: skip
                self._tf_readers.append((reader, static))
            self.head_pose = self._head_pose  # a PosedSource now (app.sources.capabilities)
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ros2-live", daemon=True)
        self._thread.start()

    # -- the reading thread ---------------------------------------------------------------

    def _run(self) -> None:
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import InstanceState, SampleState, ViewState

        every = SampleState.Any | ViewState.Any | InstanceState.Any
        while not self._closed.is_set():
            self._waitset.wait(200_000_000)  # ns: a close is noticed within 0.2 s
            for reader, spec, datatype in self._readers:
                taken = ddspy_take(reader._ref, every, 4)
                if isinstance(taken, int):
                    continue  # an error code: the next wake tries again
                for data, info in taken:
                    if info.valid_data:
                        self._handle(spec, datatype, data)
            for reader, static in self._tf_readers:
                taken = ddspy_take(reader._ref, every, 100)
                for data, info in [] if isinstance(taken, int) else taken:
                    if info.valid_data:
                        self._transforms(data, static)

    def _transforms(self, data: bytes, static: bool) -> None:
        """A TFMessage into :attr:`tf` (a malformed one counted in ``tf_refused``)."""
        try:
            msg = decode(TF_MESSAGE, data)
        except ValueError as exc:
            self.tf_refused += 1
            self.tf_problem = describe_error(exc)
            return
        for t in msg.transforms:
            st = t.header.stamp
            tr, q = t.transform.translation, t.transform.rotation
            T = make_T(rotation_from_quaternion([q.x, q.y, q.z, q.w]), (tr.x, tr.y, tr.z))
            stamp = int(st.sec) * 1_000_000_000 + int(st.nanosec)
            self.tf.add(t.header.frame_id, t.child_frame_id, stamp, T, static)

    def _head_pose(self, stamp_ns: int) -> np.ndarray | None:
        """(4, 4) ``T_world_rig`` at ``stamp_ns`` from tf2 (None: not known then)."""
        pose = self.topic_map.pose
        assert pose is not None
        return self.tf.lookup(pose.world, pose.rig, stamp_ns)

    def _handle(self, spec: TopicSpec, datatype: str, data: bytes) -> None:
        stats = self.topic_stats[spec.topic]
        try:
            if len(data) > self.max_message_bytes:
                raise ValueError(
                    f"a message of {len(data)} bytes, more than the limit {self.max_message_bytes}"
                )
            msg = decode(datatype, data)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            size = self.rig[spec.sensor].image_size if self.rig is not None else None
            image = convert_image(msg, datatype, spec, size)
        except Exception as exc:  # one topic's bad message: counted, worded; the rest go on
            stats.refused += 1
            stats.refused_since_used += 1
            stats.problem = f"{spec.topic}: {describe_error(exc)}"
            stats.refused_s = time.monotonic()
            return
        stats.received += 1
        self._lag(spec.sensor, stamp)
        stats.refused_since_used = 0
        if spec.kind in ("color", "thermal"):
            self.slots.put(Frame(spec.sensor, stamp, image))
            return
        self._pair(spec, stamp, image)

    def _pair(self, spec: TopicSpec, stamp: int, image: np.ndarray) -> None:
        """A TOF half: a frame once the sensor's other half of the same stamp is there (a
        map without amplitude: ones)."""
        parts = self._tof_parts[spec.sensor]
        waiting = self._halves.setdefault(spec.sensor, {})
        halves = waiting.setdefault(stamp, {})
        halves[spec.kind] = image
        if set(halves) >= parts:
            del waiting[stamp]
            distance = halves.get("tof_distance")
            amplitude = halves.get("tof_amplitude")
            if amplitude is None:
                amplitude = np.ones_like(distance)
            self.slots.put(Frame(spec.sensor, stamp, amplitude, distance))
        while len(waiting) > PAIR_KEEP:
            del waiting[min(waiting)]

    # -- the consumer ---------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        yield from self.slots.frames()

    def stats(self) -> dict[str, Any]:
        """``rejected_by_sensor``: sensor -> its topics' refusals, ``since_accepted``,
        ``last_rejected_s`` (``time.monotonic``), ``last_error`` (the newest refusal's topic
        and reason)."""
        out: dict[str, dict[str, Any]] = {}
        for topic, st in self.topic_stats.items():
            if st.refused_s is None:
                continue
            sensor = self.topic_map.topics[topic].sensor
            r = out.setdefault(sensor, {"since_accepted": 0, "last_rejected_s": None,
                                        "last_error": ""})  # fmt: skip
            r["since_accepted"] += st.refused_since_used
            if r["last_rejected_s"] is None or st.refused_s > r["last_rejected_s"]:
                r["last_rejected_s"], r["last_error"] = st.refused_s, st.problem or ""
        return {"rejected_by_sensor": out}

    def _lag(self, sensor: str, stamp_ns: int) -> None:
        """Note how far ``sensor``'s header stamps lie behind the time they arrive (its
        last :data:`LAG_KEEP` messages), and the period between its stamps."""
        lags = self._lags.setdefault(sensor, deque(maxlen=LAG_KEEP))
        lags.append((time.time_ns() - stamp_ns) * 1e-9)
        last = self._last_stamp.get(sensor)
        if last is not None and stamp_ns > last:
            self._period_s[sensor] = (stamp_ns - last) * 1e-9
        self._last_stamp[sensor] = stamp_ns

    def stamp_warnings(self) -> dict[str, str]:
        """Sensor -> a line when its stamps run behind the other sensors' by more than one
        of its frames (the median of its last messages' delays against the median of the
        others'): a driver stamping late, or a clock of its own."""
        delays = {s: statistics.median(d) for s, d in list(self._lags.items()) if len(d) > 2}
        out = {}
        for sensor, delay in delays.items():
            others = [d for s, d in delays.items() if s != sensor]
            period = self._period_s.get(sensor)
            if not others or period is None:
                continue
            behind = delay - statistics.median(others)
            if behind > period:
                out[sensor] = (
                    f"{sensor}: its header stamps run {behind * 1e3:.0f} ms behind the other "
                    f"sensors' (more than a frame, {period * 1e3:.0f} ms): frame sets pair "
                    "images of different instants"
                )
        return out

    @property
    def notes(self) -> list[str]:
        """The Source panel's lines: topics not read (a sensor the rig lacks), sensors whose
        stamps run behind the others'."""
        return [*self._not_read, *self.stamp_warnings().values()]

    @property
    def problems(self) -> dict[str, str]:
        """Topic -> the last refusal of one of its messages, worded (topics with none left
        out)."""
        return {t: s.problem for t, s in self.topic_stats.items() if s.problem}

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self.slots.close()
        self._thread.join(timeout=2.0)
        self._dp = None  # the participant and its readers go with their last reference
