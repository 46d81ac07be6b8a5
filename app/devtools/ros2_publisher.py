"""A stand-in for a robot's ROS 2 camera drivers (tests and ``trifuse bench --only ros2``):
publishes a rig's synthetic images over DDS as ROS 2 nodes do (topics ``rt/...``, types
``sensor_msgs::msg::dds_::Image_`` / ``CompressedImage_``, CDR, best effort), each sensor
at its own rate (:data:`RATES_HZ`, the real head's), with header stamps. Needs the
``[ros2]`` extra.

    python -m trifuse.app.devtools.ros2_publisher SECONDS [--rig RIG.yaml] [--domain N]
                                                  [--scene] [--bad-left] [--late S:MS]
                                                  [--tf WORLD:RIG]

Topics (:data:`TOPIC_MAP`'s): colour ``/<sensor>/image_raw`` (rgb8; the right one as
``/<sensor>/image_raw/compressed``, JPEG), thermal ``/<sensor>/image_raw`` (16UC1,
centi-kelvin: 29315 = 20 C), TOF ``/tof/distance`` (16UC1 mm, 0 = none) and
``/tof/amplitude`` (mono16). Each sensor's k-th image carries its k in its first pixel
(colour: red; thermal: cK; distance: mm) so a test can tell which one it got; every 30th
left colour image (k = 29, 59, ...) has half the rig's size (a driver misconfigured: the
console must refuse it and go on).
"""

from __future__ import annotations

import argparse
import time
from types import SimpleNamespace

import cv2
import numpy as np

from trifuse.app.recording.ros2_live import datatype_of, dds_topic
from trifuse.app.recording.topicmap import topic_map_from_yaml
from trifuse.app.sources.ros2_cdr import COMPRESSED, IMAGE, TF_MESSAGE, encode
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.rigfile import load_rig
from trifuse.calib.rig import Rig

RATES_HZ = {"color": 30, "thermal": 27, "tof": 15}
"""Frame rates per modality (the real head's)."""

TOPIC_MAP = """format: trifuse-topic-map/1
sensors:
  ccd_left:
    color: /ccd_left/image_raw
  ccd_right:
    color: /ccd_right/image_raw/compressed
  thermal_left:
    thermal: {topic: /thermal_left/image_raw, scale: 0.01}
  thermal_right:
    thermal: {topic: /thermal_right/image_raw, scale: 0.01}
  tof:
    tof_distance: {topic: /tof/distance, scale: 0.001, invalid: 0}
    tof_amplitude: /tof/amplitude
"""
WRONG_SIZE_EVERY = 30


TF_HZ = 50.0
"""``--tf``: the rate of the head's pose on ``/tf``."""
BASE_T_RIG = np.array(
    [[0.0, -1.0, 0.0, 0.2], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.5], [0.0, 0.0, 0.0, 1.0]]
)
"""``--tf``: the rig's pose on the robot's base (90 degrees about z, 0.2 m ahead, 0.5 m up)."""


def _tf(edges: list[tuple[str, str, np.ndarray]], stamp_ns: int) -> bytes:
    """A TFMessage (CDR) of ``(parent, child, T_parent_child)`` edges."""
    from trifuse.calib.transforms import quaternion_from_rotation

    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    transforms = []
    for parent, child, T in edges:
        x, y, z, w = quaternion_from_rotation(T[:3, :3])
        transforms.append(SimpleNamespace(
            header=SimpleNamespace(stamp=stamp, frame_id=parent), child_frame_id=child,
            transform=SimpleNamespace(
                translation=SimpleNamespace(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=SimpleNamespace(x=x, y=y, z=z, w=w)),
        ))  # fmt: skip
    return encode(TF_MESSAGE, SimpleNamespace(transforms=transforms))


def scene_images(rig: Rig) -> dict[str, dict[str, np.ndarray]]:
    """Sensor -> the images of the simulated inspection room as ``rig`` sees it (one
    render, live quality), in the units the topics carry: ``rgb`` uint8; ``ck`` uint16
    centi-kelvin; ``mm`` uint16 millimetres (0: none) and ``amplitude`` uint16."""
    from trifuse.app.sources.sim.inspection import InspectionScenario

    fs, _ = InspectionScenario(seed=0, live=True, rig=rig).render(18.0)
    out: dict[str, dict[str, np.ndarray]] = {}
    for name, f in fs.frames.items():
        if rig[name].modality == "color":
            out[name] = {"rgb": np.ascontiguousarray(f.image)}
        elif rig[name].modality == "thermal":
            out[name] = {"ck": np.rint(np.nan_to_num(f.image, nan=0.0) * 100).astype(np.uint16)}
        else:
            d = np.nan_to_num(f.distance_m, nan=0.0)
            amplitude = np.asarray(f.image).clip(0, 65535).astype(np.uint16)
            out[name] = {"mm": np.rint(d * 1000).clip(0, 65535).astype(np.uint16),
                         "amplitude": amplitude}  # fmt: skip
    return out


def _message(sensor: str, modality: str, size: tuple[int, int], k: int, stamp_ns: int,
             topic: str, base: dict[str, np.ndarray] | None = None
             ) -> list[tuple[str, bytes]]:  # fmt: skip
    """(topic, CDR) of the ``k``-th image of ``sensor``: uniform images, or ``base``'s
    (:func:`scene_images`) when given and of ``size``."""
    w, h = size
    if base is not None and next(iter(base.values())).shape[:2] != (h, w):
        base = None
    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    header = SimpleNamespace(stamp=stamp, frame_id=sensor)

    def raw(encoding: str, plane: np.ndarray) -> bytes:
        step = plane.strides[0]
        msg = SimpleNamespace(header=header, height=h, width=w, encoding=encoding,
                              is_bigendian=0, step=step, data=plane.tobytes())  # fmt: skip
        return encode(IMAGE, msg)

    if modality == "color":
        rgb = base["rgb"].copy() if base else np.full((h, w, 3), 90, np.uint8)
        rgb[0, 0, 0] = k % 256
        if datatype_of(topic) == COMPRESSED:
            ok, jpeg = cv2.imencode(".jpg", rgb[..., ::-1])
            assert ok
            msg = SimpleNamespace(header=header, format="jpeg", data=jpeg.tobytes())
            return [(topic, encode(COMPRESSED, msg))]
        return [(topic, raw("rgb8", rgb))]
    if modality == "thermal":
        ck = base["ck"].copy() if base else np.full((h, w), 29_315, np.uint16)
        ck[0, 0] = 29_315 + k
        return [(topic, raw("16UC1", ck))]
    if base:
        mm, amplitude = base["mm"].copy(), base["amplitude"]
    else:
        mm, amplitude = np.full((h, w), 2_500, np.uint16), np.full((h, w), 1_000, np.uint16)
        mm[1, :] = 0  # no reading
    mm[0, 0] = 1_000 + k
    return [("/tof/distance", raw("16UC1", mm)), ("/tof/amplitude", raw("mono16", amplitude))]


def main(argv: list[str] | None = None) -> int:
    from cyclonedds._clayer import ddspy_write
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic

    from trifuse.app.sources.ros2_types import IDL_TYPES

    p = argparse.ArgumentParser()
    p.add_argument("seconds", type=float)
    p.add_argument("--rig", metavar="RIG.yaml", help="the rig (default: the simulated head's)")
    p.add_argument("--domain", type=int, default=0)
    p.add_argument("--bad-left", action="store_true", help="every left colour image too small")
    p.add_argument(
        "--scene",
        action="store_true",
        help="the simulated room's images (default: uniform; the simulated head's rig only)",
    )
    p.add_argument(
        "--late",
        metavar="SENSOR:MS",
        help="stamp one sensor's images this many milliseconds before they are taken (a "
        "driver stamping late)",
    )
    p.add_argument(
        "--tf",
        metavar="WORLD:RIG",
        help="also the head's pose on tf2: /tf WORLD -> base_link, moving 0.1 m/s along x "
        f"at {TF_HZ:g} Hz; /tf_static base_link -> RIG (:data:`BASE_T_RIG`)",
    )
    args = p.parse_args(argv)
    if args.scene and args.rig:  # the simulator's TOF model is made for its own head
        p.error("--scene: the simulated head's own rig only (no --rig)")
    rig = load_rig(args.rig) if args.rig else default_rig()
    bases = scene_images(rig) if args.scene else {}
    late_ns: dict[str, int] = {}
    if args.late:
        sensor, ms = args.late.split(":")
        late_ns[sensor] = round(float(ms) * 1e6)
    mapped = topic_map_from_yaml(TOPIC_MAP).topics
    topics = {s.sensor: t for t, s in mapped.items() if s.kind != "tof_amplitude"}  # paced
    dp = DomainParticipant(args.domain)
    qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1))
    writers = {}
    for topic in mapped:
        t = Topic(dp, dds_topic(topic), IDL_TYPES[datatype_of(topic)])
        writers[topic] = DataWriter(dp, t, qos=qos)
    tf_frames = args.tf.split(":") if args.tf else None
    if tf_frames:
        latched = Qos(Policy.Reliability.Reliable(1_000_000_000), Policy.History.KeepLast(1),
                      Policy.Durability.TransientLocal)  # fmt: skip
        tf_type = IDL_TYPES[TF_MESSAGE]
        tf_writer = DataWriter(dp, Topic(dp, dds_topic("/tf"), tf_type), qos=qos)
        static = DataWriter(dp, Topic(dp, dds_topic("/tf_static"), tf_type), qos=latched)
        ddspy_write(static._ref, _tf([("base_link", tf_frames[1], BASE_T_RIG)], time.time_ns()))
    time.sleep(1.0)  # discovery
    start = time.monotonic()
    t0_ns = time.time_ns()
    tf_k = 0
    due = {name: 0.0 for name in topics}
    count = dict.fromkeys(topics, 0)
    while (now := time.monotonic() - start) < args.seconds:
        while tf_frames and tf_k / TF_HZ <= now:
            T = np.eye(4)
            T[0, 3] = 0.1 * tf_k / TF_HZ
            stamp = t0_ns + round(tf_k * 1e9 / TF_HZ)
            ddspy_write(tf_writer._ref, _tf([(tf_frames[0], "base_link", T)], stamp))
            tf_k += 1
        for name, topic in topics.items():
            if now < due[name]:
                continue
            s = rig[name]
            rate = RATES_HZ[s.modality]
            k = count[name]
            stamp = t0_ns + round(k * 1e9 / rate) - late_ns.get(name, 0)
            size = s.image_size
            wrong = k % WRONG_SIZE_EVERY == WRONG_SIZE_EVERY - 1 or args.bad_left
            if name == "ccd_left" and wrong:
                size = (size[0] // 2, size[1] // 2)
            messages = _message(name, s.modality, size, k, stamp, topic, bases.get(name))
            for out_topic, data in messages:
                ddspy_write(writers[out_topic]._ref, data)
            count[name] += 1
            due[name] = (k + 1) / rate
        time.sleep(max(0.0, min(due.values()) - (time.monotonic() - start)))
    print(" ".join(f"{n}={c}" for n, c in count.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
