"""A stand-in for a robot's ROS 2 camera drivers (tests and ``trifuse bench``): publishes a
rig's synthetic images over DDS as ROS 2 nodes do (topics ``rt/...``, types
``sensor_msgs::msg::dds_::Image_`` / ``CompressedImage_``, CDR, best effort), each sensor
at its own rate, with header stamps.

    python -m tests.ros2_publisher SECONDS [--small] [--domain N]

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

from tests.support import RATES_HZ, small_rig
from trifuse.app.sources.ros2_cdr import COMPRESSED, IMAGE, encode
from trifuse.app.sources.ros2_live import datatype_of, dds_topic
from trifuse.app.sources.sim.head import default_rig

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


def _message(sensor: str, modality: str, size: tuple[int, int], k: int, stamp_ns: int,
             topic: str) -> list[tuple[str, bytes]]:  # fmt: skip
    """(topic, CDR) of the ``k``-th image of ``sensor``."""
    w, h = size
    stamp = SimpleNamespace(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    header = SimpleNamespace(stamp=stamp, frame_id=sensor)

    def raw(encoding: str, plane: np.ndarray) -> bytes:
        step = plane.strides[0]
        msg = SimpleNamespace(header=header, height=h, width=w, encoding=encoding,
                              is_bigendian=0, step=step, data=plane.tobytes())  # fmt: skip
        return encode(IMAGE, msg)

    if modality == "color":
        rgb = np.full((h, w, 3), 90, np.uint8)
        rgb[0, 0, 0] = k % 256
        if datatype_of(topic) == COMPRESSED:
            ok, jpeg = cv2.imencode(".jpg", rgb[..., ::-1])
            assert ok
            msg = SimpleNamespace(header=header, format="jpeg", data=jpeg.tobytes())
            return [(topic, encode(COMPRESSED, msg))]
        return [(topic, raw("rgb8", rgb))]
    if modality == "thermal":
        ck = np.full((h, w), 29_315, np.uint16)
        ck[0, 0] = 29_315 + k
        return [(topic, raw("16UC1", ck))]
    mm = np.full((h, w), 2_500, np.uint16)
    mm[0, 0] = 1_000 + k
    mm[1, :] = 0  # no reading
    amplitude = np.full((h, w), 1_000, np.uint16)
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
    p.add_argument("--small", action="store_true", help="the small rig (a tenth of the sizes)")
    p.add_argument("--domain", type=int, default=0)
    p.add_argument("--bad-left", action="store_true", help="every left colour image too small")
    args = p.parse_args(argv)
    rig = small_rig() if args.small else default_rig()
    topics = {
        "ccd_left": "/ccd_left/image_raw",
        "ccd_right": "/ccd_right/image_raw/compressed",
        "thermal_left": "/thermal_left/image_raw",
        "thermal_right": "/thermal_right/image_raw",
        "tof": "/tof/distance",
    }
    dp = DomainParticipant(args.domain)
    qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1))
    writers = {}
    for topic in [*topics.values(), "/tof/amplitude"]:
        t = Topic(dp, dds_topic(topic), IDL_TYPES[datatype_of(topic)])
        writers[topic] = DataWriter(dp, t, qos=qos)
    time.sleep(1.0)  # discovery
    start = time.monotonic()
    t0_ns = time.time_ns()
    due = {name: 0.0 for name in topics}
    count = dict.fromkeys(topics, 0)
    while (now := time.monotonic() - start) < args.seconds:
        for name, topic in topics.items():
            if now < due[name]:
                continue
            s = rig[name]
            rate = RATES_HZ[s.modality]
            k = count[name]
            stamp = t0_ns + round(k * 1e9 / rate)
            size = s.image_size
            wrong = k % WRONG_SIZE_EVERY == WRONG_SIZE_EVERY - 1 or args.bad_left
            if name == "ccd_left" and wrong:
                size = (size[0] // 2, size[1] // 2)
            for out_topic, data in _message(name, s.modality, size, k, stamp, topic):
                ddspy_write(writers[out_topic]._ref, data)
            count[name] += 1
            due[name] = (k + 1) / rate
        time.sleep(max(0.0, min(due.values()) - (time.monotonic() - start)))
    print(" ".join(f"{n}={c}" for n, c in count.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
