"""The head's pose in recordings (issue 20): ``world -> rig`` on ``/tf`` written per frame
set (RecordingWriter.write_pose, the simulated survey), read back (app.recording.poses,
ReplaySource.head_pose), the pose between poses, other robots' frame names, damage."""

from __future__ import annotations

from pathlib import Path

import foxglove
import numpy as np
import pytest
from foxglove.channels import FrameTransformChannel, FrameTransformsChannel
from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3
from scipy.spatial.transform import Rotation

from tests.support import poll_until, small_rig, synth_frames, write_recording
from trifuse.app.cli import main
from trifuse.app.recording import RecordingError, RecordingWriter, ReplaySource
from trifuse.app.recording.poses import interpolate_pose, read_poses
from trifuse.app.recording.simrecord import (
    POSE_HZ,
    pose_index,
    shown_pose,
    sim_scenario,
    sim_schedule,
)
from trifuse.app.sources.sim.survey import SurveyScenario
from trifuse.app.storage.rigfile import save_rig
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_angle_deg, rotation_from_euler_deg

WIRE_ATOL = 1e-12
"""The wire format keeps float64 (translation, quaternion): a pose comes back to rounding
(quaternion <-> matrix, about 1e-15)."""


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


def random_poses(n: int, seed: int) -> np.ndarray:
    """(n, 4, 4) seeded rigid poses: any rotation, translations within 5 m."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=rng).as_matrix()
    t = rng.uniform(-5, 5, (n, 3))
    return np.stack([make_T(R[i], t[i]) for i in range(n)])


def test_poses_written_with_the_frames_come_back_exactly(tmp_path: Path, rig: Rig) -> None:
    frames = synth_frames(rig, 0.3, seed=2)
    stamps = sorted({f.stamp_ns for f in frames})
    poses = random_poses(len(stamps), seed=3)
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, rig) as w:
        by_stamp = dict(zip(stamps, poses, strict=True))
        for f in sorted(frames, key=lambda f: f.stamp_ns):
            w.write_pose(f.stamp_ns, by_stamp[f.stamp_ns])  # once per stamp: repeats skipped
            w.write(f)
    assert w.poses_written == len(stamps)
    got = read_poses(path)
    assert got is not None and (got.parent, got.child) == ("world", "rig") and not got.notes
    np.testing.assert_array_equal(got.stamps_ns, stamps)
    np.testing.assert_allclose(got.T_world_rig, poses, atol=WIRE_ATOL)
    # the rig is still read from the file (the poses are not mistaken for its transforms)
    with ReplaySource(path, realtime=False) as src:
        assert src.rig == rig
        np.testing.assert_allclose(src.head_pose(stamps[3]), poses[3], atol=WIRE_ATOL)


def test_a_recording_without_poses_has_none(tmp_path: Path, rig: Rig) -> None:
    path = write_recording(tmp_path / "r.mcap", rig, synth_frames(rig, 0.1, seed=1))
    assert read_poses(path) is None
    with ReplaySource(path, realtime=False) as src:
        assert src.head_pose(0) is None
    (tmp_path / "text.mcap").write_text("not a recording")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_poses(tmp_path / "text.mcap")


def test_the_writer_refuses_a_pose_that_is_not_rigid(tmp_path: Path, rig: Rig) -> None:
    with RecordingWriter(tmp_path / "r.mcap", rig) as w:
        for bad, why in [
            (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
            (np.full((4, 4), np.nan), "NaN"),
            (np.eye(3), "shape"),
        ]:
            with pytest.raises(RecordingError, match=why):
                w.write_pose(0, bad)
        with pytest.raises(RecordingError, match="stamp_ns"):
            w.write_pose(-1, np.eye(4))
        assert w.poses_written == 0


def test_the_pose_between_poses() -> None:
    """Slerp and linear translation between poses at most max_gap_s apart; the nearest
    pose within tolerance_s outside them; None further away."""
    T0 = make_T(rotation_from_euler_deg(0, 10, 0), (0.0, 0.0, 1.0))
    T1 = make_T(rotation_from_euler_deg(0, 50, 0), (1.0, 0.0, 3.0))
    T2 = make_T(rotation_from_euler_deg(20, 50, 0), (1.0, 0.0, 3.0))
    from trifuse.app.recording.poses import RecordingPoses

    poses = RecordingPoses(
        np.array([0, 100_000_000, 2_000_000_000]), np.stack([T0, T1, T2]), "world", "rig"
    )
    np.testing.assert_array_equal(poses.at(100_000_000), T1)
    quarter = poses.at(25_000_000)
    assert quarter is not None
    expected = make_T(rotation_from_euler_deg(0, 20, 0), (0.25, 0.0, 1.5))
    np.testing.assert_allclose(quarter, expected, atol=1e-12)
    # before the first pose, after the last: the nearest within 50 ms
    np.testing.assert_array_equal(poses.at(-40_000_000), T0)
    assert poses.at(-60_000_000) is None
    np.testing.assert_array_equal(poses.at(2_030_000_000), T2)
    assert poses.at(2_100_000_000) is None
    # a gap of 1.9 s is not bridged: only the nearest pose within tolerance
    np.testing.assert_array_equal(poses.at(140_000_000), T1)
    assert poses.at(1_000_000_000) is None
    assert poses.at(1_000_000_000, max_gap_s=2.0) is not None
    # slerp takes the short way round (a half turn less a degree, then on)
    A = np.eye(4)
    B = make_T(rotation_from_euler_deg(0, 179, 0), (0, 0, 0))
    mid = interpolate_pose(A, B, 0.5)
    assert rotation_angle_deg(mid[:3, :3]) == pytest.approx(89.5, abs=1e-9)


def _tf(parent: str, child: str, stamp_ns: int, T: np.ndarray) -> FrameTransform:
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    return FrameTransform(
        timestamp=Timestamp(stamp_ns // 10**9, stamp_ns % 10**9),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        rotation=Quaternion(x=x, y=y, z=z, w=w),
    )


def test_a_robots_frame_names_are_read(tmp_path: Path) -> None:
    """A robot's own recording: ``odom -> tof`` (the reference sensor) as FrameTransforms
    lists, ``map -> rig`` singly on another topic (preferred: map before odom), and
    transforms of other frames that are no head pose."""
    poses = random_poses(6, seed=5)
    path = tmp_path / "robot.mcap"
    ctx = foxglove.Context()
    with foxglove.open_mcap(str(path), context=ctx):
        many = FrameTransformsChannel("/tf", context=ctx)
        one = FrameTransformChannel("/localisation", context=ctx)
        for k in range(6):
            stamp = 1_000_000_000 + k * 50_000_000
            other = _tf("base_link", "tof", stamp, np.eye(4))
            many.log(FrameTransforms(transforms=[other, _tf("odom", "tof", stamp, poses[k])]))
    assert read_poses(path) is None  # the child 'tof' is the rig only when it is the reference
    got = read_poses(path, reference="tof")
    assert got is not None and (got.parent, got.child) == ("odom", "tof")
    np.testing.assert_allclose(got.T_world_rig, poses, atol=WIRE_ATOL)

    path2 = tmp_path / "robot2.mcap"
    ctx = foxglove.Context()
    with foxglove.open_mcap(str(path2), context=ctx):
        many = FrameTransformsChannel("/tf", context=ctx)
        one = FrameTransformChannel("/localisation", context=ctx)
        for k in range(6):
            stamp = 1_000_000_000 + k * 50_000_000
            many.log(FrameTransforms(transforms=[_tf("odom", "rig", stamp, np.eye(4))]))
            one.log(_tf("map", "rig", stamp, poses[k]))
    got = read_poses(path2)
    assert got is not None and (got.parent, got.child) == ("map", "rig")
    np.testing.assert_allclose(got.T_world_rig, poses, atol=WIRE_ATOL)
    assert any("odom -> rig ignored" in n for n in got.notes)


def test_a_damaged_recording_gives_its_poses_before_the_damage(tmp_path: Path, rig: Rig) -> None:
    frames = synth_frames(rig, 1.0, seed=4)
    stamps = sorted({f.stamp_ns for f in frames})
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, rig, chunk_size=32 * 1024) as w:
        for f in sorted(frames, key=lambda f: f.stamp_ns):
            w.write_pose(f.stamp_ns, make_T(np.eye(3), (f.stamp_ns / 1e9, 0, 0)))
            w.write(f)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    got = read_poses(cut)
    assert got is not None and 0 < len(got) < len(stamps)
    assert got.notes and "damage" in got.notes[0]
    np.testing.assert_array_equal(got.stamps_ns, stamps[: len(got)])
    np.testing.assert_allclose(got.T_world_rig[:, 0, 3], got.stamps_ns / 1e9, atol=1e-12)


def test_the_pose_the_frames_of_the_survey_show() -> None:
    """Exact mode: the survey's pose at the instant; live mode: its orientation at the
    instant, its position at the rendered pose (a picture is turned, not moved) - while the
    robot drives they differ by the distance it drives in up to 0.1 s."""
    sc = sim_scenario("survey", small_rig(), live=False)
    assert isinstance(sc, SurveyScenario)
    for t_s in (1.03, 24.05, 31.07):
        stamp = round(t_s * 1e9)
        true = sc.T_world_rig(t_s)
        np.testing.assert_array_equal(shown_pose(sc, stamp, None), true)
        live = shown_pose(sc, stamp, POSE_HZ)
        np.testing.assert_array_equal(live[:3, :3], true[:3, :3])
        rendered = sc.T_world_rig(pose_index(stamp, POSE_HZ) / POSE_HZ)
        np.testing.assert_array_equal(live[:3, 3], rendered[:3, 3])
        assert np.linalg.norm(live[:3, 3] - true[:3, 3]) < 0.375 * 0.1 + 1e-9  # top speed
    with pytest.raises(ValueError, match="scenario"):
        sim_scenario("garden", small_rig())


def test_a_simulated_survey_recording_carries_the_heads_pose(
    tmp_path: Path, rig: Rig, capsys: pytest.CaptureFixture[str]
) -> None:
    """``trifuse record --source sim --scenario survey``: one pose per instant (frame set),
    at the instant's stamp; in its first seconds the head only turns, so the pose the
    frames show is the survey's own (``SurveyScenario.T_world_rig``) to the wire's
    precision. Re-recording the recording keeps the poses."""
    rig_path = save_rig(tmp_path / "rig.yaml", rig)
    out = tmp_path / "survey.mcap"
    argv = ["record", "--source", "sim", "--scenario", "survey", "--duration", "1"]
    assert main([*argv, "--rig", str(rig_path), "--out", str(out)]) == 0
    assert "survey scenario" in capsys.readouterr().out
    got = read_poses(out)
    assert got is not None and (got.parent, got.child) == ("world", "rig")
    schedule = sim_schedule(rig, 1.0)
    np.testing.assert_array_equal(got.stamps_ns, [stamp for stamp, _ in schedule])
    survey = SurveyScenario(rig=rig)
    truth = np.stack([survey.T_world_rig(s / 1e9) for s in got.stamps_ns])
    np.testing.assert_allclose(got.T_world_rig, truth, atol=WIRE_ATOL)
    assert rotation_angle_deg(truth[-1][:3, :3]) > 1.0  # the head has turned meanwhile

    again = tmp_path / "again.mcap"
    assert main(["record", "--source", f"replay:{out}", "--out", str(again)]) == 0
    kept = read_poses(again)
    assert kept is not None
    np.testing.assert_array_equal(kept.stamps_ns, got.stamps_ns)
    np.testing.assert_allclose(kept.T_world_rig, got.T_world_rig, atol=WIRE_ATOL)
    with ReplaySource(again, realtime=False) as src:
        assert src.rig == rig
    # --scenario is for the simulated head only
    refused = ["record", "--source", f"replay:{out}", "--scenario", "survey"]
    assert main([*refused, "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--scenario goes with --source sim" in capsys.readouterr().err


def test_the_simulated_heads_survey_shows_the_pose_it_reports(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``open_source(scenario="survey")`` (``trifuse serve --scenario survey``): the head
    moves, so frames show their sample's pose as rendered (no turning), and ``truth_at``
    gives that pose: the survey's at the sample's time."""
    from trifuse.app.recording.open_source import SCENARIOS, open_source
    from trifuse.app.sources.sim.survey import survey_pose

    monkeypatch.setenv("TRIFUSE_SIM_CACHE", "off")  # keep the shared disk cache as it is
    assert "survey" in SCENARIOS
    opened = open_source(scenario="survey")
    src = opened.source
    try:
        assert "survey" in opened.description and src.live is False
        assert isinstance(src.scenario, SurveyScenario)  # type: ignore[attr-defined]
        seen = 0
        for frame in src.frames():
            truth = src.truth_at(frame.stamp_ns, sensors=[])  # type: ignore[attr-defined]
            assert truth.T_world_rig is not None
            np.testing.assert_array_equal(truth.T_world_rig, survey_pose(truth.pose_t_s))
            seen += 1
            if seen == 10:
                break
        # once later poses are rendered, a frame 1.5 s on shows the one nearest its time
        # (1.5 s, or a neighbour on a slow machine): the head has turned, and truth_at says
        # so
        poll_until(lambda: src.rendered_count >= 4, 60, poll_s=0.05)  # type: ignore[attr-defined]
        later = src.truth_at(src.start_ns + 1_500_000_000, sensors=[])  # type: ignore[attr-defined]
    finally:
        src.close()
    assert seen == 10 and later.pose_t_s > 0
    np.testing.assert_array_equal(later.T_world_rig, survey_pose(later.pose_t_s))
    assert rotation_angle_deg(later.T_world_rig[:3, :3]) > 10.0
