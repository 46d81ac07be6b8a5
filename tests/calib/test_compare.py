"""A calibrated rig against the truth: ``calib.rig_compare`` with known perturbations of the
simulated head's rig, and ``trifuse compare`` / ``trifuse calibrate --truth`` as a user runs
them (a real calibration from the ``simulated`` fixture, malformed input)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from tests.support import run_cli
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.rig_compare import FOCAL_TARGET, POSE_TARGET, compare_rigs
from trifuse.calib.transforms import invert, make_T, pose_error, rotation_from_rvec

TRUTH = default_rig()
NAMES = TRUTH.names  # tof, ccd_left, ccd_right, thermal_left, thermal_right
PAIRS = [(a, b) for i, a in enumerate(NAMES) for b in NAMES[i + 1 :]]


def reframed(rig: Rig, reference: str) -> Rig:
    """The same rig with ``reference``'s frame as the rig frame (every pose re-expressed)."""
    T_new_rig = invert(rig[reference].T_rig_sensor)
    sensors = {
        n: dataclasses.replace(s, T_rig_sensor=T_new_rig @ s.T_rig_sensor)
        for n, s in rig.sensors.items()
    }
    return Rig(sensors, reference, dict(rig.eyes))


def changed(rig: Rig, name: str, **fields: object) -> Rig:
    """``rig`` with one sensor's fields replaced."""
    sensors = dict(rig.sensors)
    sensors[name] = dataclasses.replace(sensors[name], **fields)
    return Rig(sensors, rig.reference, dict(rig.eyes))


def scaled_focal(i: Intrinsics, fx: float = 1.0, fy: float = 1.0) -> Intrinsics:
    return dataclasses.replace(i, fx=i.fx * fx, fy=i.fy * fy)


# -- calib.rig_compare --------------------------------------------------------------------


def test_a_rig_against_itself_in_another_rig_frame_is_exact() -> None:
    """Pairwise relative poses do not depend on the rig frame: the truth re-expressed in
    ccd_right's frame compares as equal (to rounding), and every figure passes."""
    cmp = compare_rigs(reframed(TRUTH, "ccd_right"), TRUTH)
    assert (cmp.estimate_reference, cmp.truth_reference) == ("ccd_right", "tof")
    assert list(cmp.intrinsics) == NAMES and [(p.a, p.b) for p in cmp.pairs] == PAIRS
    for p in cmp.pairs:
        assert p.rotation_deg < 1e-6 and p.translation_m < 1e-12, p
    for e in cmp.intrinsics.values():
        assert (e.fx_px, e.fy_px, e.cx_px, e.cy_px) == (0, 0, 0, 0)
        assert e.distortion == (0.0,) * 5 and e.distortion_px < 1e-9  # undistort: Newton
    assert cmp.passed and cmp.failures == [] and cmp.n_figures == 2 * 5 + 2 * 10


def test_known_perturbations_are_measured_and_judged() -> None:
    """ccd_left turned by 0.15 deg and moved by 0.5 mm in its own frame, its fx 0.2 % long;
    the TOF's fx 0.5 % long; thermal_left's fy 0.4 % short; in another rig frame."""
    rvec = np.radians(0.15) * np.array([2.0, -1.0, 2.0]) / 3.0  # unit axis
    t_D = np.array([0.0003, -0.0004, 0.0])  # 0.5 mm
    D = make_T(rotation_from_rvec(rvec), t_D)
    est = changed(
        TRUTH,
        "ccd_left",
        T_rig_sensor=TRUTH["ccd_left"].T_rig_sensor @ D,
        intrinsics=scaled_focal(TRUTH["ccd_left"].intrinsics, fx=1.002),
    )
    est = changed(est, "tof", intrinsics=scaled_focal(TRUTH["tof"].intrinsics, fx=1.005))
    est = changed(
        est, "thermal_left", intrinsics=scaled_focal(TRUTH["thermal_left"].intrinsics, fy=0.996)
    )
    cmp = compare_rigs(reframed(est, "thermal_right"), TRUTH)

    left = cmp.intrinsics["ccd_left"]
    assert left.fx_rel == pytest.approx(0.002, abs=1e-12) and left.fy_rel == 0.0
    assert left.fx_px == pytest.approx(0.002 * TRUTH["ccd_left"].intrinsics.fx, abs=1e-9)
    assert cmp.intrinsics["tof"].fx_rel == pytest.approx(0.005, abs=1e-12)
    assert cmp.intrinsics["thermal_left"].fy_rel == pytest.approx(-0.004, abs=1e-12)
    assert cmp.intrinsics["ccd_left"].focal_target_rel == FOCAL_TARGET["color"] == 0.003
    assert cmp.intrinsics["tof"].focal_target_rel == FOCAL_TARGET["tof"] == 0.01

    for p in cmp.pairs:
        if not p.involves("ccd_left"):
            assert p.rotation_deg < 1e-6 and p.translation_m < 1e-12, p
            continue
        other = p.b if p.a == "ccd_left" else p.a
        # T_other_left gains D on the right: its translation moves by R t_D (0.5 mm); the
        # inverse pose's translation moves by the rotation times the baseline as well.
        T_ol = TRUTH.T(other, "ccd_left")
        t_lo = TRUTH.T("ccd_left", other)[:3, 3]
        moved_back = np.linalg.norm(D[:3, :3].T @ (t_lo - t_D) - t_lo)
        assert p.rotation_deg == pytest.approx(0.15, abs=1e-9)
        assert p.translation_m == pytest.approx(
            max(np.linalg.norm(T_ol[:3, :3] @ t_D), moved_back), abs=1e-12
        )
        assert p.translation_m < 0.001  # every pair's translation stays within its target
        limit = POSE_TARGET["tof" if other == "tof" else "color"]
        assert (p.target_deg, p.target_m) == limit
    # 0.15 deg: too much between colour and thermal imagers (0.1), enough with the TOF (0.2).
    assert sorted(cmp.failures) == [
        "ccd_left-ccd_right rotation",
        "ccd_left-thermal_left rotation",
        "ccd_left-thermal_right rotation",
        "thermal_left fy",
    ]
    assert not cmp.passed
    assert cmp.pair("ccd_left", "tof").ok and not cmp.pair("ccd_right", "ccd_left").ok


def test_distortion_difference_is_the_displacement_at_the_image_corners() -> None:
    """A pinhole truth against an estimate with k1 = 0.01: the largest displacement is at
    the image's outer corners, fx * x * k1 * r^2 (and likewise in y)."""
    s = TRUTH["thermal_left"]
    pinhole = dataclasses.replace(s.intrinsics, distortion=(0.0,) * 5)
    truth = changed(TRUTH, "thermal_left", intrinsics=pinhole)
    k1 = 0.01
    est = changed(
        truth, "thermal_left", intrinsics=dataclasses.replace(pinhole, distortion=(k1, 0, 0, 0, 0))
    )
    e = compare_rigs(est, truth).intrinsics["thermal_left"]
    w, h = s.image_size
    i = pinhole
    expected = 0.0
    for u in (-0.5, w - 0.5):
        for v in (-0.5, h - 0.5):
            x, y = (u - i.cx) / i.fx, (v - i.cy) / i.fy
            r2 = x * x + y * y
            expected = max(expected, math.hypot(i.fx * x * k1 * r2, i.fy * y * k1 * r2))
    assert e.distortion_px == pytest.approx(expected, rel=1e-9)
    assert e.distortion == (k1, 0.0, 0.0, 0.0, 0.0)
    assert e.ok  # distortion has no target


def test_sensors_in_one_rig_only_are_listed_not_compared() -> None:
    extra = Sensor("ccd_extra", "color", (640, 480), Intrinsics(600, 600, 319.5, 239.5), np.eye(4))
    est = Rig({**{n: TRUTH[n] for n in NAMES if n != "thermal_right"}, "ccd_extra": extra}, "tof")
    cmp = compare_rigs(est, TRUTH)
    assert cmp.only_in_estimate == ["ccd_extra"] and cmp.only_in_truth == ["thermal_right"]
    assert list(cmp.intrinsics) == NAMES[:4] and len(cmp.pairs) == 6 and cmp.passed


def test_incomparable_rigs_are_refused() -> None:
    other = Sensor("cam", "color", (640, 480), Intrinsics(600, 600, 319.5, 239.5), np.eye(4))
    with pytest.raises(ValueError, match="no sensor in common"):
        compare_rigs(Rig({"cam": other}, "cam"), TRUTH)
    small = changed(TRUTH, "ccd_left", image_size=(640, 480))
    with pytest.raises(ValueError, match="640x480 images in the estimate but 1280x960"):
        compare_rigs(small, TRUTH)
    sensors = dict(TRUTH.sensors)
    sensors["ccd_left"] = dataclasses.replace(sensors["ccd_left"], modality="thermal")
    with pytest.raises(ValueError, match="thermal sensor in the estimate but color"):
        compare_rigs(Rig(sensors, "tof"), TRUTH)


# -- trifuse compare ----------------------------------------------------------------------


def test_compare_a_real_calibration(simulated: dict, capsys: pytest.CaptureFixture[str]) -> None:
    """The README's calibration against its ground truth: the verdict agrees with the
    calibration issue's check (focal lengths, every ordered pair's relative pose) and every
    printed pair error with ``pose_error`` of the relative poses."""
    rig, truth = simulated["rig"], simulated["truth"]
    truth_path = simulated["capture"] / "ground_truth_rig.yaml"
    code, out, err = run_cli(["compare", str(simulated["rig_path"]), str(truth_path)], capsys)
    assert code == 0, err

    meets = all(
        abs(getattr(rig[n].intrinsics, f) / getattr(truth[n].intrinsics, f) - 1)
        <= FOCAL_TARGET[truth[n].modality]
        for n in NAMES
        for f in ("fx", "fy")
    )
    for a in NAMES:
        for b in NAMES:
            if a != b:
                rot, trans = pose_error(rig.T(a, b), truth.T(a, b))
                limit = max(POSE_TARGET[truth[a].modality], POSE_TARGET[truth[b].modality])
                meets &= rot <= limit[0] and trans <= limit[1]
    verdict = out.strip().splitlines()[-1]
    assert verdict.startswith("Verdict: PASS" if meets else "Verdict: FAIL"), out

    rows = {}
    for line in out.splitlines():
        m = re.match(r"(\w+) – (\w+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+(\S+)", line)
        if m:
            rows[(m[1], m[2])] = m
    assert sorted(rows) == sorted(PAIRS)
    for (a, b), m in rows.items():
        rot, t_ab = pose_error(rig.T(a, b), truth.T(a, b))
        t_ba = pose_error(rig.T(b, a), truth.T(b, a))[1]
        assert float(m[3]) == pytest.approx(rot, abs=0.0005)
        assert float(m[5]) == pytest.approx(1000 * max(t_ab, t_ba), abs=0.005)
        assert m[7] == ("pass" if rot <= float(m[4]) and float(m[5]) <= float(m[6]) else "FAIL")
    fx_row = next(line for line in out.splitlines() if line.startswith("ccd_left "))
    fx_percent = 100 * (rig["ccd_left"].intrinsics.fx / truth["ccd_left"].intrinsics.fx - 1)
    assert float(fx_row.split()[3]) == pytest.approx(fx_percent, abs=0.0005)

    code, out, err = run_cli(
        ["compare", str(simulated["rig_path"]), str(truth_path), "--json"], capsys
    )
    assert code == 0, err
    data = json.loads(out)
    assert data["passed"] is meets and len(data["pairs"]) == 10
    assert data["sensors"]["tof"]["focal_target_percent"] == 1.0


def test_compare_marks_failures_and_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A rig whose ccd_right is turned by 0.3 deg: the pairs with it fail (also the TOF's,
    0.2 deg), the verdict names them, the exit status is 1; rigs that differ only in their
    reference compare as equal."""
    truth_path = save_rig(tmp_path / "truth.yaml", TRUTH)
    turn = make_T(rotation_from_rvec([0.0, np.radians(0.3), 0.0]), [0, 0, 0])
    bad = changed(TRUTH, "ccd_right", T_rig_sensor=TRUTH["ccd_right"].T_rig_sensor @ turn)
    bad_path = save_rig(tmp_path / "bad.yaml", reframed(bad, "ccd_left"))
    code, out, err = run_cli(["compare", str(bad_path), str(truth_path)], capsys)
    assert code == 1 and err == ""
    failing = [line for line in out.splitlines() if "FAIL (rot)" in line]
    assert len(failing) == 4 and all("ccd_right" in line for line in failing)
    verdict = out.strip().splitlines()[-1]
    assert verdict.startswith("Verdict: FAIL, 4 of 30 judged figures miss their target")
    assert "tof-ccd_right rotation" in verdict

    same_path = save_rig(tmp_path / "same.yaml", reframed(TRUTH, "thermal_left"))
    code, out, _ = run_cli(["compare", str(same_path), str(truth_path)], capsys)
    assert code == 0 and "FAIL" not in out and out.strip().endswith("pairs' poses).")


def test_compare_lists_sensors_in_one_rig_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth_path = save_rig(tmp_path / "truth.yaml", TRUTH)
    one_eye = Rig({n: TRUTH[n] for n in ("tof", "ccd_left", "thermal_left")}, "tof")
    code, out, err = run_cli(
        ["compare", str(save_rig(tmp_path / "e.yaml", one_eye)), str(truth_path)], capsys
    )
    assert code == 0, err
    assert "only in the truth, not compared: ccd_right, thermal_right" in out
    assert "3 sensors in common" in out and "Verdict: PASS" in out


def test_compare_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth_path = save_rig(tmp_path / "truth.yaml", TRUTH)
    malformed = tmp_path / "bad.yaml"
    malformed.write_text("format: trifuse-rig/1\nsensors: [1, 2\n")
    cam = Sensor("cam", "color", (640, 480), Intrinsics(600, 600, 319.5, 239.5), np.eye(4))
    stranger = save_rig(tmp_path / "stranger.yaml", Rig({"cam": cam}, "cam"))
    cases = [
        ([str(tmp_path / "missing.yaml"), str(truth_path)], "missing.yaml: cannot read"),
        ([str(truth_path), str(tmp_path / "missing.yaml")], "missing.yaml: cannot read"),
        ([str(malformed), str(truth_path)], "YAML"),
        ([str(stranger), str(truth_path)], "no sensor in common"),
        ([str(truth_path)], "required: TRUTH.yaml"),
    ]
    for argv, match in cases:
        code, out, err = run_cli(["compare", *argv], capsys)
        assert code == 2, argv
        assert match in err and out == "", (argv, err)
        assert len(err.strip().splitlines()) == 1


# -- trifuse calibrate --truth ------------------------------------------------------------


def test_calibrate_with_truth_prints_and_reports_the_comparison(
    simulated: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The thermal pair alone (rig frame: thermal_left's; the truth's is the TOF's)."""
    truth_path = simulated["capture"] / "ground_truth_rig.yaml"
    out_rig, report = tmp_path / "rig.yaml", tmp_path / "report.json"
    argv = ["calibrate", str(simulated["capture"]), "--out", str(out_rig), "--report", str(report)]
    argv += ["--sensors", "thermal_left,thermal_right", "--truth", str(truth_path)]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    rig, truth = load_rig(out_rig), simulated["truth"]
    assert rig.reference == "thermal_left"
    summary_end = out.index("Comparing the calibration (reference thermal_left) with")
    assert out.index("Calibrated 2 sensor(s)") < summary_end < out.index("rig written to")
    assert "only in the truth, not compared: tof, ccd_left, ccd_right" in out

    comparison = json.loads(report.read_text())["comparison"]
    assert comparison["truth"] == str(truth_path)
    assert comparison["only_in_truth"] == ["tof", "ccd_left", "ccd_right"]
    (pair,) = comparison["pairs"]
    rot, t_ab = pose_error(
        rig.T("thermal_left", "thermal_right"), truth.T("thermal_left", "thermal_right")
    )
    t_ba = pose_error(
        rig.T("thermal_right", "thermal_left"), truth.T("thermal_right", "thermal_left")
    )[1]
    assert (pair["a"], pair["b"]) == ("thermal_left", "thermal_right")
    assert pair["rotation_deg"] == pytest.approx(rot, abs=1e-12)
    assert pair["translation_mm"] == pytest.approx(1000 * max(t_ab, t_ba), abs=1e-9)
    fx = comparison["sensors"]["thermal_right"]["fx_percent"]
    assert fx == pytest.approx(
        100 * (rig["thermal_right"].intrinsics.fx / truth["thermal_right"].intrinsics.fx - 1)
    )
    assert comparison["passed"] is (comparison["failures"] == [])
    verdict = "Verdict: PASS" if comparison["passed"] else "Verdict: FAIL"
    assert verdict in out


def test_calibrate_refuses_a_truth_without_a_common_sensor_before_calibrating(
    simulated: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cam = Sensor("cam", "color", (640, 480), Intrinsics(600, 600, 319.5, 239.5), np.eye(4))
    stranger = save_rig(tmp_path / "stranger.yaml", Rig({"cam": cam}, "cam"))
    out_rig = tmp_path / "rig.yaml"
    argv = ["calibrate", str(simulated["capture"]), "--out", str(out_rig), "--truth", str(stranger)]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == "" and not out_rig.exists()
    assert err.startswith("trifuse: error: --truth") and "no sensor in common" in err
    assert len(err.strip().splitlines()) == 1
