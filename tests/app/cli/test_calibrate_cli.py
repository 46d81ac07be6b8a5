"""``trifuse calibrate`` end to end: simulated captures against the ground truth, the real
OpenCV sample images against their reference, and malformed input."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import FOCAL, OPENCV_LEFT_9X6, POSE
from trifuse.app.cli import main
from trifuse.app.cli.calibrate import time_text
from trifuse.app.workflows.report_format import coverage_sentence
from trifuse.calib.coverage import coarse_reached
from trifuse.calib.transforms import pose_error, rvec_from_rotation

REAL = OPENCV_LEFT_9X6
BOARD_9x6 = "pattern: checkerboard\ninner_corners: [9, 6]\nsquare_size_m: 0.025\n"


def test_simulated_calibration_meets_the_accuracy_targets(simulated: dict) -> None:
    rig, truth = simulated["rig"], simulated["truth"]
    assert rig.names == truth.names and rig.reference == "tof"
    for name in truth.names:
        est, true = rig[name], truth[name]
        for f in ("fx", "fy"):
            rel = abs(getattr(est.intrinsics, f) / getattr(true.intrinsics, f) - 1)
            assert rel < FOCAL[true.modality], (name, f, rel)
        # Every pair of sensors, so the TOF's pose is checked too (relative to the others).
        for other in truth.names:
            if other == name:
                continue
            rot, trans = pose_error(rig.T(other, name), truth.T(other, name))
            worst = max(POSE[true.modality], POSE[truth[other].modality])
            assert rot < worst[0] and trans < worst[1], (name, other, rot, trans)


def test_reported_sigmas_are_consistent_with_the_errors(simulated: dict) -> None:
    rig, truth, report = simulated["rig"], simulated["truth"], simulated["report"]
    for name in truth.names:
        sigma = report["sensors"][name]["sigma"]
        est, true = rig[name], truth[name]
        for f in ("fx", "fy", "cx", "cy"):
            err = abs(getattr(est.intrinsics, f) - getattr(true.intrinsics, f))
            assert err < 3 * sigma[f], (name, f, err, sigma[f])
        d_rot = np.degrees(
            rvec_from_rotation(est.T_rig_sensor[:3, :3])
            - rvec_from_rotation(true.T_rig_sensor[:3, :3])
        )
        d_t = est.T_rig_sensor[:3, 3] - true.T_rig_sensor[:3, 3]
        if name == rig.reference:
            continue
        assert np.all(np.abs(d_rot) < 3 * np.array(sigma["rotation_deg"])), (name, d_rot)
        assert np.all(np.abs(d_t) < 3 * np.array(sigma["translation_m"])), (name, d_t)


def test_report_has_what_the_issue_lists(simulated: dict) -> None:
    report = simulated["report"]
    for name in simulated["truth"].names:
        s = report["sensors"][name]
        assert s["views_detected"] >= 20 and 0 < s["rms_px"] < 0.3
        assert set(s["intrinsics"]) == {"fx", "fy", "cx", "cy"}
        assert len(s["distortion"]) == 5
        assert np.asarray(s["T_rig_sensor"]).shape == (4, 4)
        assert {"fx", "fy", "cx", "cy", "rotation_deg", "translation_m"} <= set(s["sigma"])
        assert {"x", "y", "size", "skew", "empty_regions"} <= set(s["coverage"])
    for view, per in report["views"].items():
        for entry in per.values():
            assert isinstance(entry["outlier"], bool) and entry["rms_px"] >= 0, view
    # 30 views meet the targets (tests above); the verdicts from the sigmas agree.
    assert report["verdict"]["grade"] == "good" and report["min_views"] == 3
    assert len(report["verdict"]["pairs"]) == 3  # both eyes and the stereo pair
    # Every image has a detection entry: found, or the reason it was not used.
    assert len(report["detections"]) == 30
    for per in report["detections"].values():
        for d in per.values():
            assert d["found"] or d["reason"]


def _real_capture(root: Path) -> Path:
    cap = root / "real"
    cap.mkdir()
    (cap / "board.yaml").write_text(BOARD_9x6)
    for f in sorted(REAL.glob("left*.jpg")):
        (cap / f.stem).mkdir()
        shutil.copy(f, cap / f.stem / "ccd_left.jpg")
    return cap


def test_real_images_against_the_opencv_reference(tmp_path: Path) -> None:
    cap = _real_capture(tmp_path)
    report_path = tmp_path / "report.json"
    assert (
        main(
            [
                "calibrate",
                str(cap),
                "--out",
                str(tmp_path / "rig.yaml"),
                "--report",
                str(report_path),
            ]
        )
        == 0
    )
    report = json.loads(report_path.read_text())
    s = report["sensors"]["ccd_left"]
    assert s["views_detected"] >= 12
    assert s["rms_px"] < 0.45
    # Reference fx, fy = 536.07, 536.02 (classic detector, fixed 11x11 sub-pixel window).
    assert s["intrinsics"]["fx"] == pytest.approx(536.07, rel=0.01)
    assert s["intrinsics"]["fy"] == pytest.approx(536.02, rel=0.01)
    # The reference's "outlier view" left02 (1.2 px) comes from its fixed 11x11 sub-pixel
    # window, wider than half of left02's 21.8 px corner spacing: the window then reaches
    # the neighbouring corners. Our window follows the spacing, and left02 is an ordinary
    # view (see test_left02_outlier_is_the_fixed_window below).
    rms = {v: per["ccd_left"]["rms_px"] for v, per in report["views"].items()}
    assert rms["left02"] < 1.5 * float(np.median(list(rms.values())))


def test_left02_outlier_is_the_fixed_window() -> None:
    """Reproduce the reference: with cornerSubPix 11x11, left02 is the worst view."""
    obj = np.zeros((54, 3), np.float32)
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
    names, objs, imgs = [], [], []
    for f in sorted(REAL.glob("left*.jpg")):
        gray = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(gray, (9, 6))
        assert ok
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.001)
        c = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (11, 11), (-1, -1), crit)
        names.append(f.stem)
        objs.append(obj)
        imgs.append(c)
    rms, *_rest, per_view = cv2.calibrateCameraExtended(objs, imgs, (640, 480), None, None)
    assert rms == pytest.approx(0.409, abs=0.01)
    assert names[int(np.argmax(per_view))] == "left02" and per_view.max() > 1.0


# -- the summary: coverage in one line per sensor, rejected images by view ------------------


def test_coverage_sentence_names_the_empty_and_thin_regions() -> None:
    """6 x 8 cells: the bottom-left coarse region (rows 4-5, cols 0-2) empty, half of the top
    edge region (rows 0-1, cols 3-4) empty: 40 of 48 cells reached."""
    counts = np.ones((6, 8), np.int64)
    counts[4:, :3] = 0
    counts[0, 3:5] = 0
    fractions = coarse_reached(counts)
    assert fractions[2, 0] == 0.0 and fractions[0, 1] == 0.5 and fractions[1, 1] == 1.0
    assert coverage_sentence(counts) == (
        "corners cover 83 % of the image; none in the bottom-left corner; few in the top edge"
    )
    counts[0, 3] = 7  # three of the top edge's four cells: no longer thin
    assert coverage_sentence(counts) == (
        "corners cover 85 % of the image; none in the bottom-left corner"
    )
    assert coverage_sentence(np.ones((6, 8))) == "corners cover the whole image"
    assert coverage_sentence(np.zeros((6, 8))) == "no corner anywhere in the image"
    almost = np.ones((6, 8))
    almost[5, 7] = 0  # 47 of 48: not rounded up to 100 %
    assert coverage_sentence(almost) == "corners cover 97 % of the image"


def test_summary_gives_coverage_in_a_line_and_rejected_images_by_view(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    monkeypatch.setenv("TRIFUSE_DETECTION_CACHE", str(tmp_path / "cache"))  # searched here
    cap = _real_capture(tmp_path)
    cv2.imwrite(str(cap / "left05" / "ccd_left.jpg"), np.full((480, 640), 128, np.uint8))
    report_path = tmp_path / "report.json"
    code = main(
        ["calibrate", str(cap), "--out", str(tmp_path / "r.yaml"), "--report", str(report_path)]
    )
    out = capsys.readouterr().out
    assert code == 0
    report = json.loads(report_path.read_text())
    coverage = report["sensors"]["ccd_left"]["coverage"]
    counts = np.array(coverage["corner_counts"])
    percent = math.floor(100 * np.count_nonzero(counts) / counts.size)
    assert 0 < percent < 100 and coverage["reached"] == np.count_nonzero(counts) / counts.size
    lines = out.splitlines()
    bars = next(i for i, line in enumerate(lines) if line.startswith("ccd_left       coverage"))
    assert lines[bars + 1].strip().startswith(f"corners cover {percent} % of the image")
    assert "never saw a corner" not in out and "row 0, col" not in out
    reason = report["detections"]["left05"]["ccd_left"]["reason"]
    assert "not found" in reason
    assert f"  ccd_left, view left05: {reason}" in lines
    # the summary's time is the calibration's; the last line gives the whole time
    calibrated = re.search(r"^Calibrated 1 sensor\(s\) in ([\d.]+) s,", out, re.MULTILINE)
    took = re.fullmatch(
        r"Took ([\d.]+) s in all: starting and reading the capture ([\d.]+) s, detecting the "
        r"board ([\d.]+) s, calibrating ([\d.]+) s, the rest ([\d.]+) s",
        lines[-1],
    )
    assert calibrated is not None and took is not None, lines[-1]
    total, reading, detecting, calibrating, rest = map(float, took.groups())
    assert calibrating == float(calibrated.group(1)) and detecting > 0
    assert total == pytest.approx(reading + detecting + calibrating + rest, abs=0.25)
    # again: every image's corners from the detection cache, and the line says so
    again = ["calibrate", str(cap), "--out", str(tmp_path / "r2.yaml")]
    assert main(again) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    images = len(list(cap.glob("*/ccd_left.jpg")))  # the 13 photographs
    assert f"({images} of {images} images searched before)" in last, last


def test_time_text() -> None:
    assert time_text(14.24, 0.41, 10.6, 2.93) == (
        "Took 14.2 s in all: starting and reading the capture 0.4 s, detecting the board "
        "10.6 s, calibrating 2.9 s, the rest 0.3 s"
    )
    assert time_text(1.0, 0.5, 0.3, 0.3).endswith("the rest 0.0 s")  # rounding, never < 0
    assert "detecting the board 0.1 s (3 of 4 images searched before), calib" in time_text(
        1.0, 0.5, 0.1, 0.3, (3, 4)
    )


# -- malformed input: one clear line, exit 2, no traceback ----------------------------------


def _run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(args)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def test_missing_board_yaml(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _real_capture(tmp_path)
    (cap / "board.yaml").unlink()
    code, err = _run(["calibrate", str(cap), "--out", str(tmp_path / "r.yaml")], capsys)
    assert code == 2 and "board.yaml" in err


def test_image_of_the_wrong_size(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _real_capture(tmp_path)
    img = cv2.imread(str(cap / "left03" / "ccd_left.jpg"))
    cv2.imwrite(str(cap / "left03" / "ccd_left.jpg"), cv2.resize(img, (320, 240)))
    code, err = _run(["calibrate", str(cap), "--out", str(tmp_path / "r.yaml")], capsys)
    assert code == 2 and "left03" in err and "320x240" in err


def test_board_not_found_anywhere(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = tmp_path / "blank"
    cap.mkdir()
    (cap / "board.yaml").write_text(BOARD_9x6)
    for k in range(4):
        (cap / f"{k:04d}").mkdir()
        cv2.imwrite(str(cap / f"{k:04d}" / "ccd_left.png"), np.full((480, 640), 128, np.uint8))
    code, err = _run(["calibrate", str(cap), "--out", str(tmp_path / "r.yaml")], capsys)
    assert code == 2 and "not found in any image" in err


def test_single_view(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _real_capture(tmp_path)
    for d in sorted(cap.iterdir()):
        if d.is_dir() and d.name != "left01":
            shutil.rmtree(d)
    code, err = _run(["calibrate", str(cap), "--out", str(tmp_path / "r.yaml")], capsys)
    assert code == 2 and "1 view" in err


def test_never_overwrites(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _real_capture(tmp_path)
    out = tmp_path / "rig.yaml"
    out.write_text("precious")
    code, err = _run(["calibrate", str(cap), "--out", str(out)], capsys)
    assert code == 2 and "refusing to overwrite" in err and out.read_text() == "precious"


def test_board_polarity_keys_are_tri_state_and_round_trip() -> None:
    """Absent (None): found from the data; true/false: an override. Load -> save -> load
    gives the same board, and the default board.yaml carries no polarity key."""
    from trifuse.calib.board import Board, board_from_dict

    auto = Board(9, 6, 0.06)
    assert auto.thermal_black_is_hot is None and auto.tof_black_is_dark is None
    assert set(auto.to_dict()) == {"pattern", "inner_corners", "square_size_m"}
    assert board_from_dict(auto.to_dict()) == auto
    for hot in (True, False):
        for dark in (True, False, None):
            b = Board(9, 6, 0.06, thermal_black_is_hot=hot, tof_black_is_dark=dark)
            assert board_from_dict(b.to_dict()) == b
            assert b.to_dict()["thermal_black_is_hot"] is hot
    assert board_from_dict({**auto.to_dict(), "tof_black_is_dark": None}) == auto
    for key in ("thermal_black_is_hot", "tof_black_is_dark"):
        with pytest.raises(ValueError, match=f"{key}: expected true or false"):
            board_from_dict({**auto.to_dict(), key: "yes"})


def test_board_yaml_polarity_keys_reach_the_detector(
    tmp_path: Path, calibration_frame_sets
) -> None:
    """``trifuse calibrate``'s detection (calibration_run.detect_capture) searches with
    the keys board.yaml sets: on the simulated heated board (black hot, dark in the TOF),
    ``thermal_black_is_hot: false`` and ``tof_black_is_dark: false`` give the corner lists
    reversed, leaving the colour cameras alone."""
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
    from trifuse.app.storage.capture import load_capture
    from trifuse.app.storage.capture_writer import write_board, write_view
    from trifuse.app.workflows.calibration_run import detect_capture
    from trifuse.calib.board import Board

    rig = default_rig()
    runs = {}
    for keys in ({}, {"thermal_black_is_hot": False, "tof_black_is_dark": False}):
        cap = tmp_path / ("keyed" if keys else "auto")
        write_board(cap, Board(9, 6, CALIBRATION_BOARD.square_size_m, **keys))
        for i, fs in enumerate(calibration_frame_sets[:2]):
            write_view(cap, f"{i + 1:04d}", fs, rig)
        capture = load_capture(cap)
        assert (capture.board.thermal_black_is_hot, capture.board.tof_black_is_dark) == (
            keys.get("thermal_black_is_hot"),
            keys.get("tof_black_is_dark"),
        )
        sensors = ["ccd_left", "thermal_left", "thermal_right", "tof"]
        runs[bool(keys)] = detect_capture(capture, sensors).observations
    auto, keyed = runs[False], runs[True]
    compared = 0
    for view, per in auto.items():
        for s, corners in per.items():
            if s not in keyed[view]:
                continue
            compared += 1
            turned = rig[s].modality in ("thermal", "tof")
            same = keyed[view][s][::-1] if turned else keyed[view][s]
            assert np.abs(same - corners).max() < 0.05, (view, s)
    assert compared >= 8
