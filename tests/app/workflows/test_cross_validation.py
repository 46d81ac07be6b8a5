"""Cross-validation of a rig calibration (app.workflows.cross_validation): two halves of the
views calibrated alone, and how far apart their fusions put a thermal value, per eye, in
colour pixels over 0.5-10 m, against what the halves' covariances predict. On the
prerendered ``trifuse calibrate`` of the 30 simulated views (its report.json), on corners
projected from the simulated head (a thermal imager turned in half the views), on a few
views of the simulated capture through the CLI (``--no-cross-validation``), and on a real
colour + LWIR pair (no TOF: skipped with the reason)."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.support import DATA_DIR, copy_first_views, run_cli
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.app.workflows.cross_validation import (
    CONSISTENT_FACTOR,
    DISTANCES_M,
    cross_validate,
    cross_validation_lines,
    split_views,
)
from trifuse.app.workflows.report_html import render_report_html
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Eye, Rig, Sensor
from trifuse.calib.rig_calibration import CalibrationOptions, SensorSpec, calibrate_rig
from trifuse.calib.transforms import rotation_from_rvec, transform_points

RIG = default_rig()
CZHA626 = DATA_DIR / "czha626-thermal-visible"
NOISE_PX = {"color": 0.08, "thermal": 0.06, "tof": 0.05}
SPECS = {n: SensorSpec(n, RIG[n].modality, RIG[n].image_size) for n in RIG.names}
LINE = re.compile(
    r"cross-validation \(2 halves of (\d+) views\): (\w+) eye worst ([\d.]+) px at ([\d.]+) m, "
    r"predicted ([\d.]+) px: (.*)"
)


def observe(n_views: int, seed: int, rig_of_odd_views: Rig = RIG) -> dict:
    """Corners of the simulated head's board poses projected with ``RIG`` plus noise (seeded),
    the 2nd, 4th, ... views (half B) with ``rig_of_odd_views``: view -> sensor -> (54, 2)."""
    rng = np.random.default_rng(seed)
    obs: dict[str, dict[str, np.ndarray]] = {}
    for i, T_rig_board in enumerate(calibration_poses(n_views, seed=1, rig=RIG)):
        rig = rig_of_odd_views if i % 2 else RIG
        for s in RIG.names:
            pts = transform_points(rig.T(s, "tof") @ T_rig_board, CALIBRATION_BOARD.object_points())
            uv = RIG[s].intrinsics.project(pts)
            w, h = RIG[s].image_size
            if np.isfinite(uv).all() and (uv > 3).all() and (uv < (w - 4, h - 4)).all():
                noise = rng.normal(0, NOISE_PX[RIG[s].modality], uv.shape)
                obs.setdefault(f"{i + 1:04d}", {})[s] = uv + noise
    return obs


def cross_validated(obs: dict) -> dict:
    result = calibrate_rig(obs, CALIBRATION_BOARD, SPECS, CalibrationOptions(), eyes=RIG.eyes)
    return cross_validate(result, obs, CALIBRATION_BOARD, SPECS)


def test_halves_are_alternate_views_in_capture_order() -> None:
    a, b = split_views(["0003", "0001", "0002", "0005", "0004"])
    assert (a, b) == (["0001", "0003", "0005"], ["0002", "0004"])


@pytest.mark.slow  # the 30-view simulated calibration (prerendered)
def test_the_simulated_calibration_is_cross_validated(simulated: dict) -> None:
    """The halves of the 30 simulated views (15 + 15, alternate) fuse within a pixel of
    one another at every distance (median 0.04-0.12 px from 1 m on), and by about what
    their own covariances predict: consistent. Each half is less certain than the whole.
    Measured: worst 0.35 and 0.43 px at 0.5 m against 0.25 and 0.26 predicted, 0.55-1.7
    times the prediction."""
    cv = simulated["report"]["cross_validation"]
    assert cv["skipped"] is None and cv["tof"] == "tof" and cv["factor"] == CONSISTENT_FACTOR
    views = sorted(simulated["report"]["views"])
    assert (cv["views"]["A"], cv["views"]["B"]) == (views[0::2], views[1::2])
    assert len(views) == 30 and 0 < cv["seconds"] < 120
    lines = cross_validation_lines(cv)
    assert len(lines) == 2
    for line, (name, e) in zip(lines, cv["eyes"].items(), strict=True):
        assert e["skipped"] is None and e["distance_m"] == pytest.approx(DISTANCES_M)
        median, p95, top = (np.array(e[k], dtype=float) for k in ("median_px", "p95_px", "max_px"))
        assert np.isfinite(median).all() and np.isfinite(top).all()
        assert np.all(median <= p95) and np.all(p95 <= top)
        assert top.max() < 1.0  # sub-pixel everywhere, at every distance
        assert median[DISTANCES_M >= 1.0].max() < 0.15
        assert e["worst_median_px"] == median.max() and e["at_m"] == 0.5
        full = np.array(e["predicted_sigma_px"], dtype=float)
        a, b = (np.array(e["half_sigma_px"][h], dtype=float) for h in ("A", "B"))
        predicted = np.array(e["predicted_difference_px"], dtype=float)
        assert predicted == pytest.approx(np.hypot(a, b))
        assert np.all(a > full) and np.all(b > full)  # half the views: less certain
        # of the order the covariance predicts, from below or above
        ratio = median / predicted
        assert e["ratio"] == pytest.approx(ratio.max()) and 1 / 3 < ratio.min()
        assert e["ratio"] <= CONSISTENT_FACTOR and e["consistent"] is True
        assert e["verdict"] == "consistent"
        m = LINE.fullmatch(line)
        assert m is not None, line
        assert m.groups() == ("30", name, f"{median.max():.2f}", "0.5", m[5], "consistent")
        assert float(m[5]) == pytest.approx(predicted[0], abs=0.005)


def test_the_report_page_shows_the_cross_validation(simulated: dict) -> None:
    """The HTML report's section: each eye's line, a plot against distance and a table."""
    page = render_report_html(simulated["report"])
    section = page[page.index("<section id='cross-validation'>") :]
    section = section[: section.index("</section>")]
    for line in cross_validation_lines(simulated["report"]["cross_validation"]):
        assert line.split("views): ")[1] in section
    assert section.count("<svg") == 2 and section.count("<table") == 2
    assert "predicted difference" in section and "href='#cross-validation'" in page


def test_a_thermal_imager_turned_in_half_the_views_makes_the_halves_disagree() -> None:
    """thermal_left turned 0.3° about its vertical axis in every second view (as if its
    mount slipped back and forth): the left eye's halves fuse about 7 colour px apart
    (1330 px x 0.3°), tens of times what their sigmas predict; the right eye is
    unaffected. Measured: 72x at 1.5 m; the right eye 0.86x."""
    T = RIG["thermal_left"].T_rig_sensor.copy()
    T[:3, :3] = T[:3, :3] @ rotation_from_rvec(np.radians([0.0, 0.3, 0.0]))
    turned = RIG.with_sensor(replace(RIG["thermal_left"], T_rig_sensor=T))
    cv = cross_validated(observe(16, 7, turned))
    left, right = cv["eyes"]["left"], cv["eyes"]["right"]
    assert cv["skipped"] is None and left["skipped"] is None and right["skipped"] is None
    assert 5.0 < np.median(left["median_px"]) < 9.0
    assert left["consistent"] is False and left["ratio"] > 10 * CONSISTENT_FACTOR
    assert left["verdict"].startswith(
        f"halves disagree: {left['ratio']:.1f}x the difference their sigmas predict at "
        f"{left['ratio_at_m']:g} m"
    )
    assert right["consistent"] is True and right["verdict"] == "consistent"
    assert right["worst_median_px"] < 0.5


def test_too_few_views_to_halve_is_a_reason_not_an_error() -> None:
    """Five views cannot make two halves of three: skipped, with the reason, before any
    half is calibrated. An eye whose thermal imager has too few views in a half is skipped
    alone, naming the sensor and the half; the other eye is compared."""
    cv = cross_validated(observe(5, 3))
    assert cv["skipped"] == "5 views: two halves need at least 3 views each (6 in all)"
    assert cv["eyes"] == {} and cross_validation_lines(cv) == [
        "cross-validation skipped: 5 views: two halves need at least 3 views each (6 in all)"
    ]
    obs = observe(10, 3)
    for v in sorted(obs)[4:]:  # thermal_right in views 0001-0004 only: 2 in each half
        del obs[v]["thermal_right"]
    cv = cross_validated(obs)
    assert cv["skipped"] is None
    assert cv["eyes"]["right"]["skipped"] == (
        "thermal_right sees the board in 2 of half A's 5 views; a half needs 3"
    )
    assert cv["eyes"]["left"]["skipped"] is None and cv["eyes"]["left"]["consistent"] is not None
    assert "right eye skipped: thermal_right sees the board" in cross_validation_lines(cv)[1]


@pytest.mark.slow  # two calibrations of eight simulated views through the CLI
def test_the_cli_cross_validates_a_few_views_unless_told_not_to(
    simulated_capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Eight views of the simulated capture: ``trifuse calibrate`` cross-validates their
    halves of four by default (the summary's line per eye, the report's key, its time in
    the timing line); ``--no-cross-validation`` skips it and says so. The rig is the same."""
    cap = tmp_path / "eight"
    copy_first_views(simulated_capture, cap, 8, ("board.yaml", "rig.yaml"))
    runs = {}
    for flag in ((), ("--no-cross-validation",)):
        out_dir = tmp_path / ("without" if flag else "with")
        out_dir.mkdir()
        argv = ["calibrate", str(cap), "--out", str(out_dir / "rig.yaml")]
        code, out, err = run_cli([*argv, "--report", str(out_dir / "r.json"), *flag], capsys)
        assert code == 0, err
        report = json.loads((out_dir / "r.json").read_text())
        runs[bool(flag)] = out, report, load_rig(out_dir / "rig.yaml")
    out, report, rig = runs[False]
    cv = report["cross_validation"]
    assert cv["skipped"] is None and [len(cv["views"][h]) for h in ("A", "B")] == [4, 4]
    lines = [line for line in out.splitlines() if line.startswith("cross-validation")]
    assert lines == cross_validation_lines(cv) and len(lines) == 2
    for line, e in zip(lines, cv["eyes"].values(), strict=True):
        assert LINE.fullmatch(line) and e["verdict"] == "consistent"
        assert np.isfinite(np.array(e["median_px"], dtype=float)).all()
    timing = out.strip().splitlines()[-1]
    assert re.search(r"calibrating [\d.]+ s, cross-validation [\d.]+ s, the rest", timing)

    out, report, rig_without = runs[True]
    assert report["cross_validation"]["skipped"] == "not run (--no-cross-validation)"
    assert "cross-validation skipped: not run (--no-cross-validation)" in out.splitlines()
    assert "cross-validation" not in out.strip().splitlines()[-1]
    for name in rig.names:  # the same calibration (two runs differ in the 13th digit)
        a, b = rig[name], rig_without[name]
        assert np.allclose(a.T_rig_sensor, b.T_rig_sensor, rtol=0, atol=1e-12), name
        assert np.allclose(a.intrinsics.K, b.intrinsics.K, rtol=1e-12, atol=0), name


@pytest.mark.skipif(not CZHA626.is_dir(), reason="tests/data/czha626-thermal-visible absent")
def test_a_real_colour_and_lwir_pair_without_a_tof_is_calibrated_and_skipped_with_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """czha626's real colour + LWIR pair (12 MP visible, 640 x 480 LWIR), eight views with
    a rig.yaml naming them an eye: enough for two halves, but no TOF to fuse through (no
    real set here has one). The calibration is written; the cross-validation says why it
    was not run."""
    cap = tmp_path / "czha626"
    cap.mkdir()
    (cap / "board.yaml").write_text(
        "pattern: checkerboard\ninner_corners: [6, 5]\nsquare_size_m: 0.1\n"
    )
    color = Intrinsics(3000, 3000, 2027.5, 1519.5)
    thermal = Intrinsics(700, 700, 319.5, 239.5)
    pair = {  # the starting rig: names, sizes and the eye (no TOF)
        "ccd_left": Sensor("ccd_left", "color", (4056, 3040), color, np.eye(4)),
        "thermal_left": Sensor("thermal_left", "thermal", (640, 480), thermal, np.eye(4)),
    }
    save_rig(cap / "rig.yaml", Rig(pair, "ccd_left", {"left": Eye("ccd_left", "thermal_left")}))
    for f in sorted((CZHA626 / "thermal").glob("*.jpg"))[:8]:  # test_few_views.py's eight
        (cap / f.stem).mkdir()
        (cap / f.stem / "ccd_left.jpg").symlink_to(CZHA626 / "visible" / f.name)
        (cap / f.stem / "thermal_left.jpg").symlink_to(f)
    out_rig, report_path = tmp_path / "rig.yaml", tmp_path / "report.json"
    argv = ["calibrate", str(cap), "--out", str(out_rig), "--report", str(report_path)]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert out_rig.is_file()
    report = json.loads(report_path.read_text())
    assert set(report["sensors"]) == {"ccd_left", "thermal_left"}
    why = report["cross_validation"]["skipped"]
    assert why == "no TOF calibrated: the fusion takes its depth from the TOF"
    assert f"cross-validation skipped: {why}" in out.splitlines()
