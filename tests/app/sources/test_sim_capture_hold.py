"""The simulated calibration board waits at a pose for a capture (CaptureHold): the scenario
time it gives the simulated head, and the head's frames with it."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from tests.support import small_rig
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.scenarios import CalibrationScenario, CaptureHold
from trifuse.app.sources.simulated import SimulatedHeadSource

S = 1_000_000_000  # ns per second


def shown(hold: CaptureHold, stamps_s: list[float], start_ns: int = 0) -> list[int]:
    """The pose shown at each stream time (seconds), asked in order."""
    return [hold.pose_at(hold.scenario_time(start_ns + round(s * S), start_ns)) for s in stamps_s]


def test_without_waiting_the_stream_time_is_the_scenario_time() -> None:
    hold = CaptureHold(hold_s=2.0, n_poses=4, max_hold_s=30.0)
    for k in range(200):
        assert hold.scenario_time(k * S // 10, 0) == pytest.approx(k / 10)
    assert hold.status() is None


def test_waiting_holds_an_uncaptured_pose_until_released_or_the_cap() -> None:
    """Each pose is held 1 s; waiting, pose 0 is held until it is released at 2.5 s, pose
    1 (never released) until it has been shown 4 s, the cap; then the poses go on."""
    hold = CaptureHold(hold_s=1.0, n_poses=5, max_hold_s=4.0)
    hold.waiting = True
    times = [k / 10 for k in range(25)]  # 0 .. 2.4 s
    assert set(shown(hold, times)) == {0}  # held: without waiting pose 1 comes at 0.5 s
    assert "waits at pose 1 of 5" in hold.status()
    # a view of pose 0 was captured (its frames' stamp): the next pose follows at once
    assert hold.release(round(2.0 * S)) == 0
    times = [k / 10 for k in range(25, 90)]  # 2.5 .. 8.9 s
    after = shown(hold, times)
    assert after[0] == 1
    # pose 1 is never released: shown for the cap (4 s from 2.5 s) and not longer
    moved_on = [t for t, p in zip(times, after, strict=True) if p != 1]
    assert moved_on[0] == pytest.approx(6.5) and after[times.index(moved_on[0])] == 2
    # stamps asked for again get what they got
    assert hold.pose_at(hold.scenario_time(round(1.2 * S), 0)) == 0
    assert hold.pose_at(hold.scenario_time(round(3.0 * S), 0)) == 1


def test_released_poses_and_no_waiting_go_at_the_normal_pace() -> None:
    hold = CaptureHold(hold_s=1.0, n_poses=3, max_hold_s=10.0)
    for s in (0.0, 1.0, 2.0):  # every pose captured in the first loop
        assert shown(hold, [s]) == [round(s)]
        assert hold.release(round(s * S)) == round(s)
    hold.waiting = True  # the second loop: nothing to wait for
    assert shown(hold, [2.6, 3.6, 4.6, 5.6]) == [0, 1, 2, 0]
    hold = CaptureHold(hold_s=1.0, n_poses=3, max_hold_s=10.0)
    hold.waiting = True
    assert shown(hold, [0.0, 0.4, 0.6]) == [0, 0, 0]  # held
    hold.waiting = False  # auto-capture off: the board goes on at once
    assert shown(hold, [0.7, 1.8]) == [1, 2]


def test_a_new_stream_starts_afresh_and_the_hold_pickles() -> None:
    hold = CaptureHold(hold_s=1.0, n_poses=3, max_hold_s=10.0)
    hold.waiting = True
    assert shown(hold, [0.0, 0.6, 3.0]) == [0, 0, 0]
    assert shown(hold, [0.0, 0.6], start_ns=100 * S) == [0, 0]  # another start: afresh
    copy = pickle.loads(pickle.dumps(hold))
    assert copy.waiting and copy.scenario_time(100 * S + S, 100 * S) == hold.scenario_time(
        100 * S + S, 100 * S
    )
    with pytest.raises(ValueError, match="max_hold_s"):
        CaptureHold(hold_s=2.0, n_poses=3, max_hold_s=1.0)


def test_the_calibration_scenario_paces_itself_with_its_hold() -> None:
    cal = CalibrationScenario(n_poses=3, hold_s=2.0, capture_wait_s=20.0)
    assert cal.capture_hold.max_hold_s == 22.0 and not cal.capture_hold.waiting
    assert cal.scenario_time(2 * S, 0) == pytest.approx(2.0)  # pose 1 of 3, 2 s each
    cal.capture_hold.waiting = True
    assert cal.capture_hold.pose_at(cal.scenario_time(4 * S, 0)) == 1  # held at pose 1


class PoseNumbers:
    """A scenario whose every image holds its pose's number (the board held at ``n``
    poses, ``hold_s`` each), paced by a :class:`CaptureHold` like the calibration one."""

    def __init__(self, n: int, hold_s: float, max_hold_s: float) -> None:
        self.rig = small_rig()
        self.capture_hold = CaptureHold(hold_s, n, max_hold_s)
        self.hold_s = hold_s

    def scene_key(self, t_s: float) -> int:
        return self.capture_hold.pose_at(t_s)

    def scenario_time(self, stamp_ns: int, start_ns: int) -> float:
        return self.capture_hold.scenario_time(stamp_ns, start_ns)

    def render(self, t_s: float, sensors: list[str] | None = None):
        pose = self.capture_hold.pose_at(t_s)
        frames, truth = {}, {}
        for name in sensors or self.rig.names:
            w, h = self.rig[name].image_size
            modality = self.rig[name].modality
            shape = (h, w, 3) if modality == "color" else (h, w)
            dtype = np.uint8 if modality == "color" else np.float32
            image = np.full(shape, pose, dtype)
            dist = np.ones((h, w), np.float32) if modality == "tof" else None
            frames[name], truth[name] = Frame(name, 0, image, dist), None
        return FrameSet(0, frames), truth


def poses_of(src: SimulatedHeadSource, until_s: float) -> list[tuple[float, int]]:
    """(stamp s, pose shown) of the left colour camera's frames up to ``until_s``."""
    out = []
    for f in src.frames():
        if f.stamp_ns >= until_s * S:
            break
        if f.sensor == "ccd_left":
            out.append((f.stamp_ns / S, int(f.image[0, 0, 0])))
    return out


def test_the_simulated_head_shows_the_held_pose_until_it_is_captured() -> None:
    """The simulated head asks the scenario which time a stamp shows: with the console's
    auto-capture on, the board stays at pose 0 past its 1 s hold until a view of it is
    captured (released), then the next pose follows; with it off, 1 s per pose."""

    def source(scenario: PoseNumbers) -> SimulatedHeadSource:
        return SimulatedHeadSource(
            scenario,
            render_hz=1.0,
            loop_s=4.0,
            start_ns=0,
            wait_for_render=True,
            cache_dir=False,
            render_process=False,
        )

    src = source(PoseNumbers(n=4, hold_s=1.0, max_hold_s=60.0))
    try:
        free = poses_of(src, 4.0)  # not waiting: the scenario's own pace
        assert [p for t, p in free if t in (0.0, 1.0, 2.0, 3.0)] == [0, 1, 2, 3]
    finally:
        src.close()
    scenario = PoseNumbers(n=4, hold_s=1.0, max_hold_s=60.0)
    scenario.capture_hold.waiting = True  # auto-capture is on
    src = source(scenario)
    try:
        held = []
        for f in src.frames():
            if f.sensor != "ccd_left":
                continue
            held.append((f.stamp_ns / S, int(f.image[0, 0, 0])))
            if f.stamp_ns == 5 * S:  # 5 s at pose 0: a view of it is captured
                assert scenario.capture_hold.release(f.stamp_ns) == 0
            if f.stamp_ns >= 7 * S:
                break
        assert {p for t, p in held if t <= 5.0} == {0}  # held 5 s, not 0.5
        assert next(p for t, p in held if t > 5.05) == 1  # then the next pose at once
        assert {p for t, p in held if 5.05 < t <= 7.0} == {1}  # held: not captured yet
    finally:
        src.close()
