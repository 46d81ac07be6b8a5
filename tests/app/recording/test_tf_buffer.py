"""The tf2 buffer (app/recording/tf_buffer.py): poses through a chain of frames either way
round, the nearest dynamic transform within the tolerance, none beyond it or between
frames the tree does not join; the topic map's ``pose`` section and its refusals."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.app.recording.errors import TopicMapError
from trifuse.app.recording.tf_buffer import TfBuffer
from trifuse.app.recording.topicmap import PoseSpec, topic_map_from_yaml
from trifuse.calib.transforms import make_T, rotation_from_euler_deg

MAP = "format: trifuse-topic-map/1\nsensors:\n  tof:\n    tof_distance: /d\n"


def test_a_chain_either_way_and_the_nearest_transform_in_time() -> None:
    tf = TfBuffer()
    base_tof = make_T(rotation_from_euler_deg(10, 20, 30), (0.2, 0.0, 0.5))
    tf.add("base", "tof", 0, base_tof, static=True)
    for k in range(10):  # odom -> base at 10 Hz, x = k / 10
        tf.add("odom", "base", k * 100_000_000, make_T(np.eye(3), (k / 10, 0, 0)), static=False)
    at = 430_000_000  # nearest: k = 4
    want = make_T(np.eye(3), (0.4, 0, 0)) @ base_tof
    np.testing.assert_allclose(tf.lookup("odom", "tof", at), want, atol=1e-12)
    np.testing.assert_allclose(tf.lookup("tof", "odom", at), np.linalg.inv(want), atol=1e-12)
    assert tf.lookup("odom", "tof", 5_000_000_000) is None  # 4.1 s after the last
    assert tf.lookup("odom", "tof", 5_000_000_000, tolerance_ns=5_000_000_000) is not None
    assert tf.lookup("odom", "camera", at) is None


def test_the_topic_maps_pose_section() -> None:
    tmap = topic_map_from_yaml(MAP + "pose: {world: odom, rig: tof_link}\n")
    assert tmap.pose == PoseSpec("odom", "tof_link", "/tf", "/tf_static")
    assert topic_map_from_yaml(MAP).pose is None
    for section, says in [
        ("pose: {world: odom}", "pose.rig: expected a tf2 frame name"),
        ("pose: {world: a, rig: a}", "world and rig are the same frame"),
        ("pose: {world: a, rig: b, parent: c}", "unknown key(s) ['parent']"),
        ("pose: odom", "expected a mapping with world and rig"),
    ]:
        with pytest.raises(TopicMapError) as e:
            topic_map_from_yaml(MAP + section + "\n")
        assert says in str(e.value), (section, str(e.value))
