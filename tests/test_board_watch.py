"""Live board detection: corners per sensor, the board's pose, steadiness."""

from __future__ import annotations

import numpy as np

from app.server.board_watch import BoardWatch, sighting
from app.sources.frames import Frame, FrameSet
from app.sources.sim.head import default_rig
from app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from calib.transforms import pose_error


def test_pose_steadiness_and_repeated_images(calibration_frame_sets) -> None:
    rig = default_rig()
    first, second = calibration_frame_sets[:2]
    truth = calibration_poses(12, 1, rig, CALIBRATION_BOARD)[0]
    s1 = sighting(first, rig, CALIBRATION_BOARD)
    assert s1.found == rig.names and not s1.steady  # nothing to compare with yet
    assert s1.pose_sensor == "ccd_left"
    rot_deg, trans_m = pose_error(s1.T_rig_board, truth)
    assert rot_deg < 0.2 and trans_m < 0.003, (rot_deg, trans_m)

    s2 = sighting(first, rig, CALIBRATION_BOARD, previous=s1)
    assert s2.steady
    assert all(s2.detections[n] is s1.detections[n] for n in rig.names)  # not searched again

    s3 = sighting(second, rig, CALIBRATION_BOARD, previous=s2)
    assert s3.found and not s3.steady  # the board moved


def test_a_bad_frame_is_reported_not_raised(calibration_frame_sets) -> None:
    rig = default_rig()
    frames = dict(calibration_frame_sets[0].frames)
    frames["thermal_left"] = Frame("thermal_left", 0, np.zeros((5, 5, 7), np.float32))
    s = sighting(FrameSet(0, frames), rig, CALIBRATION_BOARD)
    assert "cannot search this image" in s.detections["thermal_left"].reason
    assert "ccd_left" in s.found


def test_watch_calls_back_with_each_new_frame_set(calibration_frame_sets) -> None:
    rig = default_rig()
    latest = {"fs": None}
    seen = []
    watch = BoardWatch(lambda: latest["fs"], rig, CALIBRATION_BOARD, on_sighting=seen.append)
    watch.tick()  # no frames yet: nothing happens
    latest["fs"] = calibration_frame_sets[0]
    watch.tick()
    watch.tick()  # the same frame set: not searched again
    assert len(seen) == 1 and watch.latest is seen[0] and seen[0].found
    watch.enabled = False
    latest["fs"] = calibration_frame_sets[1]
    watch.tick()
    assert len(seen) == 1
    watch.stop()


def test_without_a_board_the_watch_searches_less_often() -> None:
    rig = default_rig()

    def blank() -> FrameSet:
        frames = {}
        for n, s in rig.sensors.items():
            w, h = s.image_size
            shape = (h, w, 3) if s.modality == "color" else (h, w)
            dtype = np.uint8 if s.modality == "color" else np.float32
            frames[n] = Frame(n, 0, np.full(shape, 100, dtype))
        return FrameSet(0, frames)

    latest = {"fs": blank()}
    seen = []
    watch = BoardWatch(
        lambda: latest["fs"], rig, CALIBRATION_BOARD, on_sighting=seen.append, idle_period_s=60
    )
    watch.tick()
    assert len(seen) == 1 and not seen[0].found
    latest["fs"] = blank()  # new frames, but no board lately: wait for the idle period
    watch.tick()
    assert len(seen) == 1
    watch.idle_period_s = 0.0
    watch.tick()
    assert len(seen) == 2
