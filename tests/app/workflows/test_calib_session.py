"""The calibration session on disk: take, search, delete, novelty, calibrate, save, reopen."""

from __future__ import annotations

import json
import re
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from tests.support import WAIT_S, poll_until, wait_searched
from trifuse.app.sources.frames import FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from trifuse.app.storage.capture import load_capture
from trifuse.app.storage.rigfile import load_rig
from trifuse.app.workflows.calib_session import CalibrationSession, SessionError
from trifuse.calib.board import Board
from trifuse.calib.detect import Detection
from trifuse.calib.transforms import pose_error, rotation_from_euler_deg

N_VIEWS = 12


@pytest.fixture
def views(calibration_frame_sets) -> list[FrameSet]:
    """Twelve simulated views of the board (seed 1, conftest.py), every sensor's frames."""
    return calibration_frame_sets


def test_take_writes_each_view_at_once_and_finds_the_board(tmp_path, views) -> None:
    rig = default_rig()
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    info = session.take(views[0])
    # On disk before the search ends: a complete view of the capture directory.
    capture = load_capture(tmp_path / "captures")
    assert [v.name for v in capture.views] == ["0001"] == [info.name]
    assert capture.views[0].sensors == rig.names
    assert capture.board == CALIBRATION_BOARD
    wait_searched(session)
    found = {s: session.view("0001").found(s) for s in rig.names}
    assert all(found.values()), found
    session.close()


def test_novelty_decides_auto_capture(tmp_path, views) -> None:
    rig = default_rig()
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    session.take(views[0])
    wait_searched(session)
    same = session.view("0001").detections
    assert session.worth_taking(same, steady=True) is None  # the same pose again
    assert session.worth_taking(same, steady=False) is None
    # A board at another place of the image is new for that sensor.
    moved = {s: Detection(d.corners * 0.5, None, d.method) for s, d in same.items()}
    why = session.worth_taking(moved, steady=True)
    assert why is not None and "ccd_left" in why
    assert session.worth_taking(moved, steady=False) is None
    session.close()


def test_auto_capture_says_why_a_sighting_is_not_taken(tmp_path, views) -> None:
    """The reasons an operator reads under Auto-capture: not seen, moving (in the board
    watch's words), the views' searches still running, captured already (the nearest
    view and how far its board pose is); a new pose is taken."""
    rig = default_rig()
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    session.take(views[0])
    pending = session.assess({}, steady=True)
    assert not pending.take and pending.kind == "not seen", pending
    wait_searched(session)
    view = session.view("0001")
    assert view.T_rig_board is not None  # its board pose, from the finest sensor
    truth = calibration_poses(N_VIEWS, 1, rig, CALIBRATION_BOARD)[0]
    rot_deg, trans_m = pose_error(view.T_rig_board, truth)
    assert rot_deg < 0.2 and trans_m < 0.003, (rot_deg, trans_m)
    same = view.detections
    moved = {s: Detection(d.corners * 0.5, None, d.method) for s, d in same.items()}
    words = "moving: 7.3 px in 0.50 s"
    moving = session.assess(moved, steady=False, motion=words)  # a new pose, not still
    assert (moving.take, moving.kind, moving.reason) == (False, "moving", words)
    # captured already says more than moving: holding still there would not help
    assert session.assess(same, steady=False, motion=words).kind == "captured"
    # the same pose, 3 cm and 2 degrees away by the sighting's board pose
    near = truth.copy()
    near[:3, :3] = rotation_from_euler_deg(2.0, 0.0, 0.0) @ near[:3, :3]
    near[:3, 3] += (0.03, 0.0, 0.0)
    captured = session.assess(same, steady=True, T_rig_board=near)
    assert not captured.take and captured.kind == "captured" and captured.nearest == "0001"
    assert re.search(r"already captured: view 0001 is 3\.\d cm / 2\.\d° away", captured.reason)
    assert "a new one needs > 0.2" in captured.reason
    session.take(views[1])  # its search runs: novelty waits for it
    searching = session.assess(same, steady=True)
    if searching.kind == "searching":  # (unless the search was quicker than this line)
        assert searching.reason == "waiting for the board search of view 0002"
    wait_searched(session)
    again = session.assess(session.view("0002").detections, steady=True)
    assert not again.take and again.nearest == "0002"  # view 0002 itself is captured now
    taken = session.assess(moved, steady=True)
    assert taken.take and taken.kind == "new pose" and taken.reason.startswith("new pose for")
    session.close()


def test_delete_moves_the_view_aside_and_numbers_go_on(tmp_path, views) -> None:
    session = CalibrationSession(tmp_path, default_rig(), CALIBRATION_BOARD)
    for fs in views[:3]:
        session.take(fs)
    kept = session.delete("0002")
    assert kept.parent == tmp_path / "deleted" and (kept / "ccd_left.png").is_file()
    assert [v.name for v in session.views()] == ["0001", "0003"]
    assert session.take(views[3]).name == "0004"  # never reuses a deleted view's name
    with pytest.raises(KeyError, match="no view '0002'"):
        session.delete("0002")
    session.close()


def test_refuses_what_cannot_be_done(tmp_path, views) -> None:
    rig = default_rig()
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    with pytest.raises(SessionError, match="at least 3 to start"):
        session.start_calibration()
    with pytest.raises(SessionError, match="run a calibration first"):
        session.save()
    with pytest.raises(SessionError, match="nothing to capture"):
        session.take(FrameSet(0, {}))
    session.close()
    with pytest.raises(SessionError, match="another --workdir"):
        CalibrationSession(tmp_path, rig, Board(cols=7, rows=5, square_size_m=0.03))


@pytest.mark.slow  # a calibration of twelve simulated views: about 12 s
def test_calibrate_save_and_reopen(tmp_path, views) -> None:
    """A session calibrates its views, saves numbered rig versions, and a new session on
    the same directory (a restarted console) finds every view and version."""
    truth = default_rig()
    session = CalibrationSession(tmp_path, truth, CALIBRATION_BOARD)
    for fs in views:
        session.take(fs)
    job = session.start_calibration()
    with pytest.raises(SessionError, match="running already"):
        session.start_calibration()
    job = session.wait(300)
    assert job.state == "done", job.error
    assert job.progress == 1.0 and job.views == [f"{i:04d}" for i in range(1, N_VIEWS + 1)]
    first = session.save()
    assert first.name == "rig-0001" and first.path.is_file()
    with pytest.raises(SessionError, match="saved already"):
        session.save()
    report = json.loads((tmp_path / "rigs" / "rig-0001.report.json").read_text())
    assert report["rms_px"] == pytest.approx(first.rms_px) and report["rms_px"] < 0.3
    # The polarity, found from the data (the simulated board: black hot and dark).
    for name, words in (("thermal_left", "hot"), ("thermal_right", "hot"), ("tof", "dark")):
        p = report["polarity"][name]
        assert p["polarity"] == f"black squares {words}" and p["decided_by"] == "data"
        assert not p["turned"] and p["problem"] is None
    rig = load_rig(first.path)
    for name in truth.names:  # 12 views: a rough but sound calibration
        rot_deg, trans_m = pose_error(rig[name].T_rig_sensor, truth[name].T_rig_sensor)
        assert rot_deg < 0.3 and trans_m < 0.005, (name, rot_deg, trans_m)

    session.delete("0005")  # drop a view, calibrate again: a second version
    assert session.start_calibration() is not None
    assert session.wait(300).state == "done"
    assert "0005" not in session.job.views
    second = session.save()
    assert second.name == "rig-0002"
    assert load_rig(first.path)[truth.names[0]] == rig[truth.names[0]]  # first one kept
    session.close()

    reopened = CalibrationSession(tmp_path, truth, CALIBRATION_BOARD)
    assert [v.name for v in reopened.views()] == [
        f"{i:04d}" for i in range(1, N_VIEWS + 1) if i != 5
    ]
    assert [v.name for v in reopened.versions()] == ["rig-0001", "rig-0002"]
    wait_searched(reopened)
    assert all(reopened.view("0001").found(s) for s in truth.names)
    assert np.allclose(
        reopened.load_version("rig-0002")["ccd_left"].T_rig_sensor,
        load_rig(second.path)["ccd_left"].T_rig_sensor,
    )
    reopened.close()


def test_the_board_yaml_keys_reach_the_sessions_search(tmp_path, views) -> None:
    """A session whose board says the black squares are cold in thermal and bright in the
    TOF searches its views that way: on the simulated board (black hot and dark) the thermal
    and TOF corner lists come out reversed, the colour ones as without the keys."""
    rig = default_rig()
    keyed_board = Board(
        9,
        6,
        CALIBRATION_BOARD.square_size_m,
        thermal_black_is_hot=False,
        tof_black_is_dark=False,
    )
    found = {}
    for name, board in (("auto", CALIBRATION_BOARD), ("keyed", keyed_board)):
        session = CalibrationSession(tmp_path / name, rig, board)
        session.take(views[0])
        wait_searched(session)
        found[name] = session.view("0001").detections
        session.close()
    for s in rig.names:
        auto, keyed = found["auto"][s], found["keyed"][s]
        assert auto.found and keyed.found, s
        turned = rig[s].modality in ("thermal", "tof")
        expected = auto.corners[::-1] if turned else auto.corners
        assert np.abs(keyed.corners - expected).max() < 0.05, s
    # A session's board is its own: reopening with other keys is refused, saying so.
    with pytest.raises(SessionError, match="thermal_black_is_hot: false"):
        CalibrationSession(tmp_path / "keyed", rig, CALIBRATION_BOARD)


def test_a_calibration_seen_running_can_be_waited_for_at_once(tmp_path, views, monkeypatch) -> None:
    """Another thread that sees the job running may wait for it at once: the job shows as
    running only once its thread has started (the start is slowed down here; before, the
    wait failed with "cannot join thread before it is started")."""
    from trifuse.app.workflows import calib_session

    class SlowStart(threading.Thread):
        def start(self) -> None:
            time.sleep(0.3)
            super().start()

    slow = SimpleNamespace(**{k: getattr(threading, k) for k in dir(threading) if k[0] != "_"})
    slow.Thread = SlowStart
    monkeypatch.setattr(calib_session, "threading", slow)
    monkeypatch.setattr(
        CalibrationSession, "_calibrate", lambda self, job, options: setattr(job, "state", "done")
    )
    session = CalibrationSession(tmp_path, default_rig(), CALIBRATION_BOARD)
    for fs in views[:3]:
        session.take(fs)
    seen: dict[str, object] = {}

    def waiter() -> None:
        poll_until(lambda: session.job.state != "idle", WAIT_S, poll_s=0.001)
        try:
            seen["job"] = session.wait(WAIT_S)
        except RuntimeError as exc:
            seen["error"] = exc

    other = threading.Thread(target=waiter)
    other.start()
    session.start_calibration()
    other.join(WAIT_S)
    session.close()
    assert "error" not in seen, seen["error"]
    assert seen["job"].state == "done"


def test_a_restarted_session_and_a_calibration_do_not_search_again(
    tmp_path, views, monkeypatch
) -> None:
    """The session's searches are kept by image content (app.storage.detection_cache): a
    console restarted on the session, and ``trifuse calibrate`` on its capture, take the
    corners found before, the same to the bit, without searching an image again."""
    from trifuse.app.storage import detection_cache
    from trifuse.app.workflows.calibration_run import detect_capture

    monkeypatch.setenv(detection_cache.CACHE_ENV, str(tmp_path / "cache"))
    searched: list[str] = []
    real = detection_cache.detect_board_configured

    def counted(image, board, modality):
        searched.append(modality)
        return real(image, board, modality)

    monkeypatch.setattr(detection_cache, "detect_board_configured", counted)
    rig = default_rig()
    session = CalibrationSession(tmp_path / "work", rig, CALIBRATION_BOARD)
    for fs in views[:2]:
        session.take(fs)
    wait_searched(session)
    before = {v.name: v.detections for v in session.views()}
    session.close()
    assert len(searched) == 2 * len(rig.names)
    detection_cache._caches.clear()  # a new process: nothing in memory

    reopened = CalibrationSession(tmp_path / "work", rig, CALIBRATION_BOARD)
    wait_searched(reopened)
    run = detect_capture(load_capture(tmp_path / "work" / "captures"))
    assert len(searched) == 2 * len(rig.names)
    for view in reopened.views():
        for sensor, det in view.detections.items():
            old = before[view.name][sensor]
            assert (det.reason, det.method) == (old.reason, old.method)
            assert det.corners is None or np.array_equal(det.corners, old.corners)
            if det.found:
                assert np.array_equal(run.observations[view.name][sensor], det.corners)
    reopened.close()
