"""Live board detection: corners per sensor, the board's pose, steadiness, and how the watch
keeps up (the half-resolution first look, the pose published first, always the newest
frame set)."""

from __future__ import annotations

import dataclasses
import math
import threading
from types import SimpleNamespace

import numpy as np
import pytest

from tests.support import WAIT_S, FakeClock, wait_until
from trifuse.app.server.runtime import board_watch
from trifuse.app.server.runtime.board_sighting import (
    STEADY_PX,
    STILL_PX_PER_S,
    STILL_WINDOW_S,
    board_in_image,
    compare_looks,
    first_look,
    sighting,
)
from trifuse.app.server.runtime.board_watch import MAX_PAUSE_S, BoardWatch
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from trifuse.calib.detect import Detection, detect_board
from trifuse.calib.transforms import pose_error


def restamped(fs: FrameSet, stamp_ns: int) -> FrameSet:
    """The same images (the very arrays) as a new frame set with another time stamp."""
    return FrameSet(stamp_ns, dict(fs.frames))


def test_pose_steadiness_and_repeated_images(calibration_frame_sets) -> None:
    rig = default_rig()
    first, second = calibration_frame_sets[:2]
    truth = calibration_poses(12, 1, rig, CALIBRATION_BOARD)[0]
    s1 = sighting(first, rig, CALIBRATION_BOARD)
    assert s1.found == rig.names and not s1.steady  # nothing to compare with yet
    assert s1.pose_sensor == "ccd_left" and s1.complete
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
    frames["ccd_right"] = Frame("ccd_right", 0, np.zeros((960, 1280, 3), np.float64))
    s = sighting(FrameSet(0, frames), rig, CALIBRATION_BOARD)
    assert "cannot search this image" in s.detections["thermal_left"].reason
    assert "cannot search this image" in s.detections["ccd_right"].reason
    assert "ccd_left" in s.found


def test_half_resolution_first_look_finds_the_full_resolution_corners(
    calibration_frame_sets,
) -> None:
    """The colour cameras: the same corners as a search of the whole image, or the same
    verdict when the board is not (wholly) in the image."""
    rig = default_rig()
    truths = calibration_poses(12, 1, rig, CALIBRATION_BOARD)
    compared = found = outside = 0
    for fs, truth in zip(calibration_frame_sets[:6], truths, strict=False):
        for name in ("ccd_left", "ccd_right"):
            image = fs.frames[name].image
            full = detect_board(image, CALIBRATION_BOARD, "color")
            fast, coarse_only = first_look(image, CALIBRATION_BOARD, rig[name].modality)
            compared += 1
            # where the true pose puts a corner outside the image, no search finds it
            inside = board_in_image(rig, name, truth, CALIBRATION_BOARD)
            outside += not inside
            assert inside or not full.found, name
            if full.found:
                found += 1
                assert fast.found and not coarse_only, (name, fast.reason)
                assert fast.method.endswith("-crop")
                assert np.abs(fast.corners - full.corners).max() < 0.01
            else:
                assert not fast.found
    assert compared == 12 and found >= 8  # the board is mostly in view (seed 1)
    assert outside >= 1  # ... but not always
    # small images are searched as they are
    tof = calibration_frame_sets[0].frames["tof"].image
    det, coarse_only = first_look(tof, CALIBRATION_BOARD, "tof")
    assert det.found and not coarse_only and not det.method.endswith("-crop")


def test_a_board_missing_at_half_resolution_gets_a_full_search_when_allowed(
    calibration_frame_sets,
) -> None:
    """A stand-in detector that cannot find the board in half-resolution images: the full
    search runs for the cameras allowed one, and only for them."""
    rig = default_rig()
    calls: list[tuple[str, int]] = []

    def blind_when_small(image: np.ndarray, board, modality: str) -> Detection:
        calls.append((modality, image.shape[1]))
        if modality == "color" and image.shape[1] < 1280:
            return Detection(None, "not found (stand-in)", None)
        return detect_board(image, board, modality)

    fs = calibration_frame_sets[0]
    s = sighting(fs, rig, CALIBRATION_BOARD, full_search={"ccd_left"}, detect=blind_when_small)
    assert s.detections["ccd_left"].found  # the full search found it
    assert not s.detections["ccd_right"].found
    assert "(half resolution)" in s.detections["ccd_right"].reason
    assert ("color", 640) in calls and calls.count(("color", 1280)) == 1
    assert s.pose_sensor == "ccd_left"  # the complete sighting takes the better camera


def test_thermal_and_tof_orderings_follow_the_colour_cameras_pose(
    calibration_frame_sets,
) -> None:
    """A board whose polarity board.yaml leaves open: a detector that takes the wrong
    squares as black in thermal_left and the TOF (their corners come reversed) is put right
    by the colour camera's board pose through the rig, so the Feeds panel and steadiness
    see the true order; a board.yaml key is obeyed as it is."""
    rig = default_rig()
    fs = calibration_frame_sets[0]
    truth = {
        n: detect_board(fs.frames[n].image, CALIBRATION_BOARD, rig[n].modality) for n in rig.names
    }

    def wrong_polarity(image: np.ndarray, board, modality: str) -> Detection:
        det = detect_board(image, board, modality)
        if det.found and (image is fs.frames["thermal_left"].image or modality == "tof"):
            return Detection(det.corners[::-1].copy(), None, det.method)
        return det

    s = sighting(fs, rig, CALIBRATION_BOARD, detect=wrong_polarity)
    assert s.pose_sensor == "ccd_left"
    for n in rig.names:  # colour: the crop search, the same corners to 0.01 px
        assert np.abs(s.detections[n].corners - truth[n].corners).max() < 0.01, n
    assert s.detections["thermal_left"].method.endswith("-turned")
    assert s.detections["tof"].method.endswith("-turned")
    assert not s.detections["thermal_right"].method.endswith("-turned")
    again = sighting(restamped(fs, 1), rig, CALIBRATION_BOARD, previous=s, detect=wrong_polarity)
    assert again.steady  # the corners did not move: the orderings agree from pass to pass

    # With the key set, the sighting keeps what the detector gives (the key is its job).
    keyed = dataclasses.replace(CALIBRATION_BOARD, thermal_black_is_hot=True)
    s = sighting(fs, rig, keyed, detect=wrong_polarity)
    assert (
        np.abs(s.detections["thermal_left"].corners - truth["thermal_left"].corners[::-1]).max()
        < 1e-9
    )
    assert np.abs(s.detections["tof"].corners - truth["tof"].corners).max() < 1e-9


def test_the_pose_is_published_before_the_other_sensors_are_searched(
    calibration_frame_sets,
) -> None:
    """The thermal imagers' search is held back: the 3D scene's pose (``latest_pose``)
    comes from the left colour camera meanwhile; the complete sighting follows."""
    rig = default_rig()
    release = threading.Event()

    def slow_thermal(image: np.ndarray, board, modality: str) -> Detection:
        if modality == "thermal" and not release.wait(WAIT_S):
            raise RuntimeError("never released")
        return detect_board(image, board, modality)

    fs = calibration_frame_sets[0]
    seen, heard = [], []
    watch = BoardWatch(
        lambda: fs, rig, CALIBRATION_BOARD, on_sighting=seen.append, detect=slow_thermal
    )
    watch.pose_listeners.append(heard.append)
    worker = threading.Thread(target=watch.tick)
    worker.start()
    try:
        wait_until(lambda: watch.latest_pose is not None, "the early pose")
        early = watch.latest_pose
        assert early.pose_sensor == "ccd_left" and not early.complete
        assert "thermal_left" not in early.detections and watch.latest is None and not seen
        assert heard == [early]  # the 3D scene is told at once
        truth = calibration_poses(12, 1, rig, CALIBRATION_BOARD)[0]
        rot_deg, trans_m = pose_error(early.T_rig_board, truth)
        assert rot_deg < 0.2 and trans_m < 0.003, (rot_deg, trans_m)
    finally:
        release.set()
        worker.join(WAIT_S)
    assert len(seen) == 1 and seen[0].complete and seen[0].found == rig.names
    assert watch.latest is seen[0] and watch.latest_pose is seen[0] and heard[-1] is seen[0]
    (timing,) = watch.timings
    assert timing.pose_s is not None and timing.pose_s < timing.pass_s
    assert timing.pose_age_s == 0.0 and not timing.reused
    watch.stop()


def test_the_watch_searches_the_newest_frame_set_and_builds_no_backlog(
    calibration_frame_sets,
) -> None:
    """While a pass is held up, five newer frame sets arrive: the next pass searches the
    newest one; none of the four in between is ever searched."""
    rig = default_rig()
    base = calibration_frame_sets[0]
    current = {"fs": restamped(base, 1)}
    first_pass = threading.Event()
    release = threading.Event()

    def held(image: np.ndarray, board, modality: str) -> Detection:
        # the complete pass's own search ("board-detect" threads), not the pose loop's:
        # the pose loop may start first, and the complete pass would then take the newest
        # frame set at once (on a busy machine)
        if threading.current_thread().name.startswith("board-detect"):
            first_pass.set()
        if not release.wait(WAIT_S):
            raise RuntimeError("never released")
        return detect_board(image, board, modality)

    searched: list[int] = []
    watch = BoardWatch(
        lambda: current["fs"],
        rig,
        CALIBRATION_BOARD,
        rate_hz=1000.0,
        duty=1.0,
        poll_s=0.01,
        on_sighting=lambda s: searched.append(s.frames.stamp_ns),
        detect=held,
    )
    watch.start()
    try:
        assert first_pass.wait(WAIT_S), "the first pass never started"
        for stamp in range(2, 7):  # newer frame sets while the pass is held up
            current["fs"] = restamped(base, stamp)
        release.set()
        wait_until(
            lambda: len(searched) >= 2,
            lambda: f"the second pass (searched {searched}, error {watch.last_error})",
        )
        assert searched[:2] == [1, 6]
        # the newest set's images are those searched before: nothing searched again
        assert watch.timings[1].reused and watch.latest.steady
        stamps = [t.stamp_ns for t in watch.timings]
        assert not set(stamps) & {2, 3, 4, 5}, stamps
    finally:
        watch.stop()
    assert all(s in (1, 6) for s in searched)


def test_the_pose_loop_follows_a_new_picture_while_a_complete_pass_is_held_up(
    calibration_frame_sets,
) -> None:
    """The board moves (a new picture) while the complete pass over the old one waits for
    a thermal imager: the pose loop publishes the new picture's pose meanwhile."""
    rig = default_rig()
    old, new = calibration_frame_sets[0], calibration_frame_sets[1]
    current = {"fs": old}
    thermal_started = threading.Event()
    release = threading.Event()

    def slow_thermal(image: np.ndarray, board, modality: str) -> Detection:
        if modality == "thermal" and image is old.frames["thermal_left"].image:
            thermal_started.set()
            if not release.wait(WAIT_S):
                raise RuntimeError("never released")
        return detect_board(image, board, modality)

    seen = []
    watch = BoardWatch(
        lambda: current["fs"],
        rig,
        CALIBRATION_BOARD,
        on_sighting=seen.append,
        poll_s=0.01,
        detect=slow_thermal,
    )
    watch.start()
    try:
        assert thermal_started.wait(WAIT_S), "the complete pass never reached thermal"
        current["fs"] = new  # the board moved
        wait_until(
            lambda: watch.latest_pose is not None and watch.latest_pose.frames is new,
            "the pose of the new picture",
        )
        assert not seen  # the complete pass over the old picture is still held up
        pose = watch.latest_pose
        assert pose.pose_sensor == "ccd_left" and not pose.complete
        truth = calibration_poses(12, 1, rig, CALIBRATION_BOARD)[1]
        rot_deg, trans_m = pose_error(pose.T_rig_board, truth)
        assert rot_deg < 0.2 and trans_m < 0.003, (rot_deg, trans_m)
        release.set()
        wait_until(lambda: len(seen) >= 2, "the complete sightings of both pictures")
        assert seen[0].frames is old and seen[1].frames is new
        # the complete sighting of the old picture never replaced the newer pose
        assert watch.latest_pose.frames is new
        # the new picture's colour images were searched once, by the pose loop
        assert seen[1].detections["ccd_left"] is pose.detections["ccd_left"]
    finally:
        release.set()
        watch.stop()


def test_watch_calls_back_with_each_new_frame_set(calibration_frame_sets) -> None:
    rig = default_rig()
    latest = {"fs": None}
    seen = []
    watch = BoardWatch(
        lambda: latest["fs"], rig, CALIBRATION_BOARD, on_sighting=seen.append, rate_hz=1000.0
    )
    watch.duty = 1.0
    watch.tick()  # no frames yet: nothing happens
    latest["fs"] = calibration_frame_sets[0]
    watch.tick()
    watch.tick()  # the same frame set: not searched again
    assert len(seen) == 1 and watch.latest is seen[0] and seen[0].found
    latest["fs"] = calibration_frame_sets[1]
    watch.tick()
    assert len(seen) == 2 and seen[1].frames is calibration_frame_sets[1]
    watch.enabled = False
    latest["fs"] = calibration_frame_sets[2]
    watch.tick()
    assert len(seen) == 2
    watch.stop()


def test_a_pass_is_followed_by_a_pause_as_long_as_itself(
    calibration_frame_sets, monkeypatch
) -> None:
    """``duty`` 0.5: after a pass of ``t`` seconds, no pass is due for another ``t`` (at
    most MAX_PAUSE_S). The watch's clock is simulated: each search takes ``step_s`` of it."""
    clock, lock, step_s = FakeClock(1000.0), threading.Lock(), [0.01]
    monkeypatch.setattr(board_watch, "time", SimpleNamespace(monotonic=clock))

    def timed_detect(image: np.ndarray, board, modality: str) -> Detection:
        with lock:  # the sensors are searched in a pool of threads
            clock.advance(step_s[0])
        return detect_board(image, board, modality)

    rig = default_rig()
    latest = {"fs": calibration_frame_sets[0]}
    watch = BoardWatch(
        lambda: latest["fs"], rig, CALIBRATION_BOARD, rate_hz=1000.0, detect=timed_detect
    )
    assert watch.duty == 0.5
    try:
        for k, step in enumerate((0.01, 1.0)):  # a short pass, then one longer than the cap
            step_s[0] = step
            latest["fs"] = calibration_frame_sets[k]
            started = clock.now
            watch.tick()
            done = clock.now
            timing = watch.timings[-1]
            assert timing.pass_s == pytest.approx(done - started) and timing.pass_s > 0
            pause = min(MAX_PAUSE_S, timing.pass_s)
            assert pause == (MAX_PAUSE_S if step == 1.0 else timing.pass_s)
            assert not watch.due(done + 0.999 * pause)
            assert watch.due(done + pause)
            clock.now = done + pause
    finally:
        watch.stop()


def blank_frames(rig) -> FrameSet:
    """A frame set of uniform images, one per sensor of ``rig`` (no board anywhere)."""
    frames = {}
    for n, s in rig.sensors.items():
        w, h = s.image_size
        shape = (h, w, 3) if s.modality == "color" else (h, w)
        dtype = np.uint8 if s.modality == "color" else np.float32
        frames[n] = Frame(n, 0, np.full(shape, 100, dtype))
    return FrameSet(0, frames)


def test_without_a_board_the_watch_searches_less_often() -> None:
    rig = default_rig()
    latest = {"fs": blank_frames(rig)}
    seen = []
    watch = BoardWatch(
        lambda: latest["fs"],
        rig,
        CALIBRATION_BOARD,
        on_sighting=seen.append,
        idle_full_period_s=60,
        rate_hz=1000.0,
        duty=1.0,
    )
    watch.tick()
    assert len(seen) == 1 and not seen[0].found
    latest["fs"] = blank_frames(rig)  # new frames, no board lately: the idle period
    watch.tick()
    assert len(seen) == 1
    watch.idle_full_period_s = 0.0
    watch.tick()
    assert len(seen) == 2
    watch.stop()


def test_without_a_board_only_the_colour_cameras_are_glanced_at_until_it_is_back(
    calibration_frame_sets, monkeypatch
) -> None:
    """Idle (the last complete pass found no board), the watch glances at the colour
    cameras every ``idle_period_s`` and searches nothing else until the complete passes'
    idle period; a glance that finds the board starts a complete pass at once."""
    clock = FakeClock(1000.0)
    monkeypatch.setattr(board_watch, "time", SimpleNamespace(monotonic=clock))
    searched: list[str] = []
    lock = threading.Lock()

    def counted(image: np.ndarray, board, modality: str) -> Detection:
        with lock:  # the sensors are searched in a pool of threads
            searched.append(modality)
        return detect_board(image, board, modality)

    rig = default_rig()
    latest = {"fs": blank_frames(rig)}
    seen = []
    watch = BoardWatch(
        lambda: latest["fs"],
        rig,
        CALIBRATION_BOARD,
        on_sighting=seen.append,
        idle_period_s=3.0,
        idle_full_period_s=15.0,
        rate_hz=1000.0,
        duty=1.0,
        detect=counted,
    )
    try:
        watch.tick()  # a complete pass: no board anywhere
        assert len(seen) == 1 and not seen[0].found and watch.idle()
        assert {"color", "thermal", "tof"} <= set(searched)
        searched.clear()
        latest["fs"] = blank_frames(rig)
        clock.advance(1.0)
        watch.tick()  # neither a glance (3 s) nor a complete pass (15 s) is due
        assert searched == [] and len(seen) == 1
        clock.advance(2.0)
        watch.tick()  # a glance at the colour cameras, which show nothing
        assert searched and set(searched) == {"color"} and len(seen) == 1
        searched.clear()
        latest["fs"] = calibration_frame_sets[0]  # the board is back in view
        clock.advance(1.0)
        watch.tick()  # the next glance is not due yet
        assert searched == [] and len(seen) == 1
        clock.advance(2.0)
        watch.tick()  # the glance finds it: a complete pass at once, sharing its looks
        assert len(seen) == 2 and seen[1].found and seen[1].found == rig.names
        # two searches a camera (half resolution, then the crop around the board: first_look),
        # none again by the complete pass
        assert searched.count("color") == 4, searched
        assert {"thermal", "tof"} <= set(searched) and not watch.idle()
    finally:
        watch.stop()


def test_bad_settings_are_refused() -> None:
    rig = default_rig()
    with pytest.raises(ValueError, match="duty"):
        BoardWatch(lambda: None, rig, CALIBRATION_BOARD, duty=0.0)


# -- stillness in frame time ------------------------------------------------------------------


def _look(stamp_s: float, shift_px: float, image: np.ndarray | None = None):
    """One look at a 9 x 6 board in ccd_left: a frame stamped ``stamp_s`` (its own image
    unless ``image`` is given) and corners moved ``shift_px`` to the right."""
    grid = np.stack(np.meshgrid(np.arange(9.0), np.arange(6.0)), -1).reshape(-1, 2)
    corners = 100.0 + 40.0 * grid + np.array([shift_px, 0.0])
    img = np.zeros((4, 4, 3), np.uint8) if image is None else image
    fs = FrameSet(round(stamp_s * 1e9), {"ccd_left": Frame("ccd_left", round(stamp_s * 1e9), img)})
    return fs, {"ccd_left": Detection(corners, None, "stand-in")}


def test_stillness_is_judged_in_frame_time_not_per_search() -> None:
    """The same 4 px seen between two searches: a board still over 1.5 s of frame time (a
    slow machine's searches), moving over 0.3 s; a jump to another pose is never still,
    however long between the looks; looks too close in time, or no new picture, tell
    nothing, and the very same picture moved by nothing."""
    still_px = STEADY_PX + STILL_PX_PER_S * STILL_WINDOW_S

    def motion(span_s: float, moved_px: float, same: bool = False):
        a_fs, a_det = _look(10.0, 0.0)
        image = a_fs.frames["ccd_left"].image if same else None
        b_fs, b_det = _look(10.0 + span_s, moved_px, image)
        return compare_looks(a_fs, a_det, b_fs, b_det)

    slow = motion(1.5, 4.0)
    assert slow.decided and slow.still, slow.describe()  # was "moving" (4 px > 2 px)
    fast = motion(0.3, 4.0)
    assert fast.decided and not fast.still and fast.speed_px_s == pytest.approx(13.3, abs=0.1)
    assert "moving: 4.0 px in 0.30 s of frame time" in fast.describe()
    assert not motion(10.0, still_px + 1.0).still  # a pose change, ten seconds apart
    assert motion(30.0, still_px - 0.1).still
    close = motion(0.05, 0.5)
    assert not close.decided and not close.still and "waiting for frames" in close.describe()
    same = motion(0.0, 0.0, same=True)
    assert same.decided and same.still and same.same_picture
    # a sighting compared with the previous one the same way
    a_fs, a_det = _look(0.0, 0.0)
    b_fs, b_det = _look(1.5, 4.0)
    assert compare_looks(b_fs, b_det, a_fs, a_det).still  # order does not matter
    assert compare_looks(a_fs, {}, b_fs, b_det) is None  # nothing seen both times


def test_a_slow_watch_finds_a_held_board_still_by_a_second_look(calibration_frame_sets) -> None:
    """A machine whose passes take longer than the board is held: the previous sighting
    was of another pose, so this one alone cannot tell. The watch looks at the newest
    frames as well: the board held there (the very same images, as the simulated head
    delivers a held pose, or new images of the same pose, as a camera does) makes the
    sighting steady; a board that moved on leaves it moving."""
    rig = default_rig()
    pose_a, pose_b = calibration_frame_sets[0], calibration_frame_sets[1]
    latest = {"fs": restamped_frames(pose_b, 0)}
    watch, seen = busy_watch(rig, latest)
    try:
        watch.tick()  # the board at pose b
        searched = restamped_frames(pose_a, 3.0)  # 3 s later: pose a
        cases = {
            "same images 1.5 s later": (restamped_frames(pose_a, 4.5), True),
            "new images of the same pose": (restamped_frames(pose_a, 4.5, copy=True), True),
            "moved on to pose b": (restamped_frames(pose_b, 4.5), False),
        }
        for what, (newest, still) in cases.items():
            alone = sighting(searched, rig, CALIBRATION_BOARD, previous=seen[0])
            assert not alone.steady, what  # against the previous pose: it moved
            latest["fs"] = searched
            watch.latest = seen[0]
            watch._searched = None
            watch._next_start = -math.inf

            def arrive(p, newest=newest) -> None:  # frames arrive during the pass
                latest["fs"] = newest

            watch.pose_listeners[:] = [arrive]
            watch.tick()
            s = seen[-1]
            assert s.frames is searched, what
            assert s.steady == still, (what, s.motion and s.motion.describe())
            assert s.motion is not None and s.motion.decided, what
    finally:
        watch.stop()


def test_a_set_straddling_a_jump_of_the_board_is_not_still_by_its_same_images(
    calibration_frame_sets,
) -> None:
    """The simulated board jumps from pose b to pose a. The set searched holds the colour
    cameras' first frames of pose a and the thermal imagers' and TOF's last of pose b
    (slower sensors, taken just before the jump; a busy run captured such a set and its
    calibration found the sensors disagreeing). The newest frames, 50 ms later: the colour
    cameras' very same images (the held pose), the others' first of pose a, too soon to be
    looked at. The unchanged colour images alone do not make the board still."""
    rig = default_rig()
    pose_a, pose_b = calibration_frame_sets[0], calibration_frame_sets[1]
    colour = {n for n in rig.names if rig[n].modality == "color"}
    before = restamped_frames(pose_b, 2.98)
    searched = FrameSet(
        round(3e9),
        {
            n: Frame(n, round(3e9), f.image, f.distance_m) if n in colour else before.frames[n]
            for n, f in pose_a.frames.items()
        },
    )
    after = restamped_frames(pose_a, 3.05, copy=True)
    newest = FrameSet(
        after.stamp_ns,
        {
            n: Frame(n, after.stamp_ns, searched.frames[n].image, None) if n in colour else f
            for n, f in after.frames.items()
        },
    )
    latest = {"fs": restamped_frames(pose_b, 0)}
    watch, seen = busy_watch(rig, latest)
    try:
        watch.tick()  # the board held at pose b
        latest["fs"] = searched
        watch.pose_listeners[:] = [lambda _p: latest.update(fs=newest)]  # during the pass
        watch.tick()
        s = seen[-1]
        assert (
            s.frames is searched
            and newest.frames["ccd_left"].image is pose_a.frames["ccd_left"].image
        )
        assert not s.steady, s.motion and s.motion.describe()
    finally:
        watch.stop()


def busy_watch(rig, latest: dict) -> tuple[BoardWatch, list]:
    """A watch of ``latest["fs"]`` that searches on every tick (no pause between passes),
    and the list its sightings go to."""
    seen: list = []
    watch = BoardWatch(
        lambda: latest["fs"], rig, CALIBRATION_BOARD, on_sighting=seen.append, rate_hz=1000.0
    )
    watch.duty = 1.0
    return watch, seen


def restamped_frames(fs: FrameSet, stamp_s: float, copy: bool = False) -> FrameSet:
    """``fs``'s pictures as frames stamped ``stamp_s`` (their images the very arrays, or
    copies with ``copy``: another camera frame of the same scene)."""
    stamp = round(stamp_s * 1e9)
    frames = {
        n: Frame(n, stamp, f.image.copy() if copy else f.image, f.distance_m)
        for n, f in fs.frames.items()
    }
    return FrameSet(stamp, frames)
