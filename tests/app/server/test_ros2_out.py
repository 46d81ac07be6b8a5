"""The console's messages back to ROS 2 (app/server/runtime/ros2_out.py), read by a DDS
reader as a ROS 2 node would (topics ``rt/...``, ROS 2's type names) and decoded by
mcap-ros2-support's decoder: ``/tf_static`` holds every sensor's pose in the rig (a reader
that joins later still gets it: transient local), each ``/trifuse/<sensor>/camera_info``
its intrinsics and distortion, ``/trifuse/fused/compressed`` the fused pair as JPEG."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from tests.app.sources.test_ros2_cdr import TF_MSGDEF
from tests.support import LOOPBACK_DDS, ListSource, small_rig, synth_frames, wait_until
from trifuse.app.recording.ros2 import MSGDEFS
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.ros2_cdr import CAMERA_INFO, COMPRESSED, TF_MESSAGE
from trifuse.calib.transforms import rotation_from_quaternion

pytest.importorskip("cyclonedds", reason="the [ros2] extra (in the test extra)")
from trifuse.app.server.runtime.ros2_out import (
    FUSED_TOPIC,
    TF_STATIC_TOPIC,
    Ros2Out,
    camera_info_topic,
)

DOMAIN = 43


@pytest.fixture(autouse=True)
def loopback_dds(monkeypatch: pytest.MonkeyPatch) -> None:
    """DDS on loopback with unicast discovery (the publisher process inherits it)."""
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK_DDS)


def _reader(participant, topic: str, datatype: str, latched: bool):
    from cyclonedds.core import Policy, Qos
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from trifuse.app.recording.ros2_live import dds_topic
    from trifuse.app.sources.ros2_types import IDL_TYPES

    qos = (Qos(Policy.Reliability.Reliable(1_000_000_000), Policy.History.KeepLast(1),
               Policy.Durability.TransientLocal) if latched
           else Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1)))  # fmt: skip
    return DataReader(participant, Topic(participant, dds_topic(topic), IDL_TYPES[datatype]),
                      qos=qos)  # fmt: skip


def _take(reader, datatype: str, msgdef: str):
    """The newest sample ``reader`` holds, decoded by mcap-ros2-support (None: none yet)."""
    from cyclonedds._clayer import ddspy_take
    from cyclonedds.core import InstanceState, SampleState, ViewState

    taken = ddspy_take(reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, 8)
    samples = [data for data, info in taken if info.valid_data]
    if not samples:
        return None
    schema = Schema(id=1, name=datatype, encoding="ros2msg", data=msgdef.encode())
    return DecoderFactory().decoder_for("cdr", schema)(samples[-1])


def test_the_calibration_and_the_fused_pair_reach_a_ros2_node() -> None:
    from cyclonedds.domain import DomainParticipant

    rig = small_rig()
    hub = FrameHub()
    pipeline = FusionPipeline(ListSource(synth_frames(rig, 1.0, seed=2)), rig, hub)
    out = Ros2Out(pipeline, hub, DOMAIN)
    node = DomainParticipant(DOMAIN)
    fused = _reader(node, FUSED_TOPIC, COMPRESSED, latched=False)
    try:
        with hub.watching():
            out.start()
            pipeline.start()
            got = {"fused": wait_until(lambda: _take(fused, COMPRESSED, MSGDEFS[COMPRESSED]),
                                       "a fused picture on ROS 2")}  # fmt: skip
            time.sleep(0.5)  # a node joining later: the latched topics still reach it
            tf = _reader(node, TF_STATIC_TOPIC, TF_MESSAGE, latched=True)
            info = _reader(node, camera_info_topic("thermal_right"), CAMERA_INFO, latched=True)
            got["tf"] = wait_until(lambda: _take(tf, TF_MESSAGE, TF_MSGDEF), "/tf_static")
            got["info"] = wait_until(lambda: _take(info, CAMERA_INFO, MSGDEFS[CAMERA_INFO]),
                                     "thermal_right's camera_info")  # fmt: skip
    finally:
        out.stop()
        pipeline.stop()
    assert out.error is None
    picture = cv2.imdecode(np.frombuffer(bytes(got["fused"].data), np.uint8), cv2.IMREAD_COLOR)
    assert picture.shape == (96, 256, 3) and got["fused"].format == "jpeg"
    transforms = {t.child_frame_id: t for t in got["tf"].transforms}
    assert set(transforms) == set(rig.names)
    for name, t in transforms.items():
        assert t.header.frame_id == "rig"
        T = rig[name].T_rig_sensor
        tr, q = t.transform.translation, t.transform.rotation
        np.testing.assert_allclose([tr.x, tr.y, tr.z], T[:3, 3], atol=1e-12)
        R = rotation_from_quaternion([q.x, q.y, q.z, q.w])
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-9)
    ci, s = got["info"], rig["thermal_right"]
    assert (ci.width, ci.height, ci.header.frame_id) == (*s.image_size, "thermal_right")
    np.testing.assert_allclose(np.reshape(ci.k, (3, 3)), s.intrinsics.K)
    assert ci.distortion_model == "rational_polynomial"  # 8 coefficients
    np.testing.assert_allclose(ci.d, s.intrinsics.distortion)
