"""ChArUco boards (issue 30, point 5): board.yaml, detection with partial views, the
calibration core on NaN rows, the CLI's refusals; and a real four-camera recording with a
published calibration (caliscope, tests/data/caliscope-charuco-4cam) against OpenCV's
plain pipeline on the same frames and against the published result."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tests.target_render import look_at_pose, render, to_u8, truth_points
from trifuse.app.cli import main
from trifuse.app.devtools.real_sets import REAL_SETS, load_views
from trifuse.calib.board import Board, board_from_dict
from trifuse.calib.detect import detect_board
from trifuse.calib.opencv_reference import (
    calibrate_camera_opencv,
    find_charuco_opencv,
    stereo_calibrate_opencv,
)
from trifuse.calib.rig_calibration import CalibrationOptions, SensorSpec, calibrate_rig
from trifuse.calib.rig_result import CalibrationResult
from trifuse.calib.transforms import invert, make_T, pose_error

BOARD = Board(6, 4, 0.04, pattern="charuco", marker_size_m=0.03, dictionary="DICT_4X4_50")
INVERTED = Board(
    6, 4, 0.04, pattern="charuco", marker_size_m=0.03, dictionary="DICT_4X4_50", inverted=True
)
SIZE = (640, 480)
K = np.array([[600.0, 0.0, 319.5], [0.0, 605.0, 239.5], [0.0, 0.0, 1.0]])
T_LEFT_RIGHT = make_T(cv2.Rodrigues(np.array([0.0, 0.05, 0.01]))[0], np.array([-0.12, 0.0, 0.0]))
"""Right camera's pose: points in the left frame -> right frame (x_r = T x_l)."""


def _poses() -> list[np.ndarray]:
    """Board poses in the left camera's frame: tilted both ways, some leaving the image."""
    out = []
    for k, (tilt, shift) in enumerate(
        [
            ((25, 0), (0.0, 0.0)),
            ((-25, 10), (0.05, 0.03)),
            ((0, 30), (-0.05, 0.0)),
            ((10, -30), (0.0, -0.04)),
            ((-15, -20), (0.3, 0.0)),  # leaves the image on the right
            ((15, 20), (-0.32, 0.05)),  # on the left
            ((20, 15), (0.0, 0.25)),  # at the bottom
            ((-20, -15), (0.03, -0.26)),  # at the top
            ((30, 5), (0.1, 0.1)),
            ((-5, -35), (-0.1, -0.08)),
        ]
    ):
        out.append(look_at_pose(BOARD, 0.55 + 0.03 * k, tilt, shift, roll_deg=8.0 * (k % 3 - 1)))
    return out


@pytest.fixture(scope="module")
def synthetic() -> dict:
    """Two colour cameras, ten views of an inverted ChArUco board, rendered exactly."""
    rng = np.random.default_rng(30)
    images: dict[str, dict[str, np.ndarray]] = {}
    truth: dict[str, dict[str, np.ndarray]] = {}
    for k, T in enumerate(_poses()):
        view = f"{k:04d}"
        for name, T_cam in (("ccd_left", T), ("ccd_right", T_LEFT_RIGHT @ T)):
            images.setdefault(view, {})[name] = to_u8(render(INVERTED, K, T_cam, SIZE, rng=rng))
            truth.setdefault(view, {})[name] = truth_points(INVERTED, K, T_cam)
    return {"images": images, "truth": truth}


# -- board.yaml ------------------------------------------------------------------------------


def test_board_yaml_round_trip_and_geometry() -> None:
    data = {
        "pattern": "charuco",
        "squares": [7, 5],
        "square_size_m": 0.04,
        "marker_size_m": 0.03,
        "dictionary": "DICT_4X4_50",
        "inverted": True,
    }
    b = board_from_dict(data)
    assert b == INVERTED and b.to_dict() == data
    assert (b.cols, b.rows, b.squares, b.n_corners) == (6, 4, (7, 5), 24)
    assert b.orderings == 1 and b.partial_views
    assert not Board(9, 6, 0.025).partial_views
    # Corner ids as OpenCV numbers them, in the checkerboard's frame (first inner corner).
    ocv = np.asarray(b.opencv_charuco().getChessboardCorners(), np.float64)
    np.testing.assert_allclose(b.object_points(), ocv - [0.04, 0.04, 0.0], atol=1e-8)  # float32
    assert b.extent_m() == pytest.approx((-0.04, -0.04, 0.24, 0.16))


@pytest.mark.parametrize("board", [BOARD, INVERTED], ids=["normal", "inverted"])
def test_is_black_is_opencvs_board_image(board: Board) -> None:
    w, h = 700, 500  # 100 px a square
    img = board.opencv_charuco().generateImage((w, h), marginSize=0, borderBits=1)
    v, u = np.mgrid[0:h, 0:w]
    mine = board.is_black((u + 0.5) / 2500.0 - 0.04, (v + 0.5) / 2500.0 - 0.04)
    opencv_black = (img < 128) ^ board.inverted
    # Equal but along edges, where OpenCV's drawing rounds to whole pixels.
    assert np.mean(mine == opencv_black) > 0.985


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"dictionary": "DICT_9X9_50"}, "expected an OpenCV predefined ArUco dictionary"),
        ({"marker_size_m": 0.04}, "markers must fit the squares"),
        ({"marker_size_m": -0.01}, "markers must fit the squares"),
        ({"squares": [20, 20]}, "DICT_4X4_50 has 50 markers, a 20x20-square"),
        ({"squares": [2, 5]}, "expected two integers >= 3"),
        ({"inner_corners": [6, 4]}, r"unknown key\(s\) \['inner_corners'\]"),
    ],
)
def test_board_yaml_errors_name_the_problem(change: dict, match: str) -> None:
    data = {**INVERTED.to_dict(), **change}
    with pytest.raises(ValueError, match=match) as exc:
        board_from_dict(data)
    assert "\n" not in str(exc.value)


# -- detection -------------------------------------------------------------------------------


def test_partial_views_have_nan_rows_and_accurate_corners(synthetic: dict) -> None:
    partial = 0
    errors = []
    for view, per in synthetic["images"].items():
        for name, img in per.items():
            det = detect_board(img, INVERTED, "color")
            truth = synthetic["truth"][view][name]
            inside = np.all((truth > 1) & (truth < np.array(SIZE) - 2), axis=1)
            if not det.found:  # only a view that shows too little of the board
                assert inside.sum() < 12 and "at least 6" in det.reason, (view, name)
                continue
            assert det.corners.shape == (INVERTED.n_corners, 2)
            seen = np.isfinite(det.corners[:, 0])
            assert not np.any(seen & ~inside), (view, name)  # nothing seen off the image
            partial += not seen.all()
            errors.append(np.linalg.norm(det.corners[seen] - truth[seen], axis=1))
    e = np.concatenate(errors)
    assert partial >= 6  # the views that leave the image
    assert np.median(e) < 0.12 and e.max() < 0.5, (np.median(e), e.max())


def test_thermal_heated_or_cooled_and_unresolvable_tof() -> None:
    rng = np.random.default_rng(5)
    T = look_at_pose(BOARD, 0.6, (15, -10))
    hot = render(BOARD, K, T, SIZE, rng=rng, black=310.0, white=300.0, background=296.0, noise=0.05)
    truth = truth_points(BOARD, K, T)
    for name, img in (("heated", hot), ("cooled", 600.0 - hot)):
        det = detect_board(img.astype(np.float32), BOARD, "thermal")
        assert det.found, (name, det.reason)
        assert np.nanmax(np.linalg.norm(det.corners - truth, axis=1)) < 0.5, name
    # A 176 x 144 TOF camera 1.2 m away: 30 mm markers of about 4 px, cells of < 1 px.
    Kt = np.array([[150.0, 0.0, 87.5], [0.0, 150.0, 71.5], [0.0, 0.0, 1.0]])
    amp = render(BOARD, Kt, look_at_pose(BOARD, 1.2, (10, 10)), (176, 144), rng=rng,
                 black=200.0, white=1000.0, background=500.0, noise=5.0)  # fmt: skip
    det = detect_board(amp.astype(np.float32), BOARD, "tof")
    assert not det.found and "not resolvable" in det.reason, det.reason


def test_too_few_corners_is_a_reason_not_a_silent_miss() -> None:
    rng = np.random.default_rng(6)
    # Only the left column of squares in the image: 3 or fewer corners.
    T = look_at_pose(BOARD, 0.5, (0, 0), shift_m=(0.34, 0.0))
    det = detect_board(to_u8(render(BOARD, K, T, SIZE, rng=rng)), BOARD, "color")
    assert not det.found
    assert "ChArUco" in det.reason and ("at least 6" in det.reason or "not found" in det.reason)


# -- calibration core on partial views -------------------------------------------------------


def test_rig_calibration_on_partial_views_meets_the_truth(synthetic: dict) -> None:
    obs: dict[str, dict[str, np.ndarray]] = {}
    for view, per in synthetic["images"].items():
        for name, img in per.items():
            det = detect_board(img, INVERTED, "color")
            if det.found:
                obs.setdefault(view, {})[name] = det.corners
    assert any(not np.isfinite(c).all() for per in obs.values() for c in per.values())
    specs = {n: SensorSpec(n, "color", SIZE) for n in ("ccd_left", "ccd_right")}
    res = calibrate_rig(obs, INVERTED, specs, CalibrationOptions(reference="ccd_left"))
    assert res.ordering is None and res.polarity == {} and not res.excluded_sensors
    for s in res.sensors.values():
        assert s.intrinsics.fx == pytest.approx(K[0, 0], rel=0.005)
        assert s.intrinsics.fy == pytest.approx(K[1, 1], rel=0.005)
        assert s.rms_px < 0.2
    T_right_left = invert(res.sensors["ccd_right"].T_rig_sensor)
    rot_deg, trans_m = pose_error(T_right_left, T_LEFT_RIGHT)
    assert rot_deg < 0.1 and trans_m < 0.001, (rot_deg, trans_m)
    # Every corner in the problem was seen: the report's corners have no NaN.
    assert np.all(np.isfinite(res.corners.uv_px))
    seen = sum(int(np.isfinite(c[:, 0]).sum()) for per in obs.values() for c in per.values())
    assert len(res.corners.uv_px) == seen


# -- the CLI: a capture end to end, and bad input --------------------------------------------


def _write_capture(root: Path, synthetic: dict, board: dict, views: int = 10) -> Path:
    root.mkdir()
    (root / "board.yaml").write_text(yaml.safe_dump(board, sort_keys=False))
    for view in sorted(synthetic["images"])[:views]:
        (root / view).mkdir()
        for name, img in synthetic["images"][view].items():
            cv2.imwrite(str(root / view / f"{name}.png"), img)
    return root


def test_cli_calibrates_a_charuco_capture(tmp_path: Path, synthetic: dict) -> None:
    cap = _write_capture(tmp_path / "cap", synthetic, INVERTED.to_dict())
    report = tmp_path / "report.json"
    args = ["calibrate", str(cap), "--out", str(tmp_path / "rig.yaml"), "--report", str(report)]
    assert main(args) == 0
    rep = json.loads(report.read_text())
    assert rep["board"]["pattern"] == "charuco"
    for name in ("ccd_left", "ccd_right"):
        s = rep["sensors"][name]
        assert s["views_detected"] >= 9
        assert s["intrinsics"]["fx"] == pytest.approx(600.0, rel=0.005)


def _refused(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.strip().count("\n") == 0, err
    return err


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"dictionary": "DICT_4X4_5000"}, "DICT_4X4_5000"),
        ({"marker_size_m": 0.05}, "markers must fit the squares"),
    ],
)
def test_cli_refuses_a_bad_board_yaml(
    tmp_path: Path, synthetic: dict, capsys: pytest.CaptureFixture[str], change: dict, match: str
) -> None:
    cap = _write_capture(tmp_path / "cap", synthetic, {**INVERTED.to_dict(), **change}, views=3)
    err = _refused(["calibrate", str(cap), "--out", str(tmp_path / "rig.yaml")], capsys)
    assert match in err and "board.yaml" in err


def test_cli_refuses_views_of_mixed_sizes(
    tmp_path: Path, synthetic: dict, capsys: pytest.CaptureFixture[str]
) -> None:
    cap = _write_capture(tmp_path / "cap", synthetic, INVERTED.to_dict(), views=4)
    img = cv2.imread(str(cap / "0002" / "ccd_left.png"))
    cv2.imwrite(str(cap / "0002" / "ccd_left.png"), cv2.resize(img, (320, 240)))
    err = _refused(["calibrate", str(cap), "--out", str(tmp_path / "rig.yaml")], capsys)
    assert "320x240" in err and "ccd_left" in err


# -- real data: caliscope's four webcams -------------------------------------------------------

CALISCOPE = REAL_SETS["caliscope-charuco-4cam"]
CALISCOPE_BOARD = Board(
    3, 4, 0.054, pattern="charuco", marker_size_m=0.75 * 0.054, dictionary="DICT_4X4_1000",
    inverted=True,
)  # fmt: skip
SLOW_WHY = (
    "ChArUco detection on all 228 frames twice (trifuse's and OpenCV's): 12 s. Every frame is "
    "needed: on every second frame OpenCV's own cam_0 -> cam_3 pose is 16 % and 9 deg off"
)


@pytest.fixture(scope="module")
def caliscope() -> dict:  # slow: see SLOW_WHY
    """Both detectors on the same frames, then OpenCV's plain pipeline (calibrateCamera per
    camera, stereoCalibrate with the intrinsics fixed per pair) and trifuse's rig
    calibration with the intrinsics fixed (the same split as OpenCV's and caliscope's)
    and refined."""
    target = CALISCOPE.board
    ours: dict[str, dict[str, np.ndarray]] = {}
    theirs: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}

    def both(image: np.ndarray) -> tuple:
        return find_charuco_opencv(image, target), detect_board(image, CALISCOPE_BOARD, "color")

    # Each frame is decoded once and searched by both detectors; two frames at a time
    # (OpenCV releases the GIL; each detector alone keeps one core busy).
    with ThreadPoolExecutor(max_workers=2) as pool:
        for s in CALISCOPE.sensors:
            views = load_views(CALISCOPE, s)
            theirs[s.name] = {}
            names = sorted(views)
            found = pool.map(both, [views[v] for v in names])
            for view, (hit, det) in zip(names, found, strict=True):
                if hit is not None:
                    theirs[s.name][view] = hit
                if det.found:
                    ours.setdefault(view, {})[s.name] = det.corners
    obj = CALISCOPE_BOARD.object_points()
    cams = {}
    for s in CALISCOPE.sensors:
        hits = theirs[s.name].values()
        cams[s.name] = calibrate_camera_opencv(
            [obj[i] for i, _ in hits], [uv for _, uv in hits], s.image_size
        )
    pairs = {}
    for a, b in CALISCOPE.pairs:
        objs, pa, pb = [], [], []
        for view in sorted(set(theirs[a]) & set(theirs[b])):
            common, ia, ib = np.intersect1d(theirs[a][view][0], theirs[b][view][0],
                                            return_indices=True)  # fmt: skip
            if len(common) >= 6:
                objs.append(obj[common])
                pa.append(theirs[a][view][1][ia])
                pb.append(theirs[b][view][1][ib])
        pairs[b] = stereo_calibrate_opencv(
            objs, pa, pb, cams[a].intrinsics, cams[b].intrinsics, (1280, 720)
        )
    specs = {s.name: SensorSpec(s.name, "color", s.image_size) for s in CALISCOPE.sensors}
    results = {
        refine: calibrate_rig(
            ours,
            CALISCOPE_BOARD,
            specs,
            CalibrationOptions(reference="cam_0", refine_intrinsics=refine),
        )
        for refine in (False, True)
    }
    return {"ours": ours, "theirs": theirs, "cams": cams, "pairs": pairs, "results": results}


def _relative(result: CalibrationResult, b: str) -> tuple[float, float]:
    """Baseline (m) and rotation (deg) of cam_0 -> b in a calibration result."""
    T = invert(result.sensors[b].T_rig_sensor) @ result.sensors["cam_0"].T_rig_sensor
    c = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(T[:3, 3])), float(np.degrees(np.arccos(c)))


@pytest.mark.slow  # SLOW_WHY
def test_caliscope_boards_found_at_least_as_often_as_opencv(caliscope: dict) -> None:
    for s in CALISCOPE.sensors:
        mine = {v for v, per in caliscope["ours"].items() if s.name in per}
        assert len(mine) >= len(caliscope["theirs"][s.name]), s.name
        for view in caliscope["theirs"][s.name]:  # the same corners where both found it
            ids, uv = caliscope["theirs"][s.name][view]
            if view in mine:
                np.testing.assert_allclose(caliscope["ours"][view][s.name][ids], uv, atol=1e-3)


@pytest.mark.slow  # SLOW_WHY
def test_caliscope_focal_lengths_against_opencv_and_published(caliscope: dict) -> None:
    """Intrinsics fixed (OpenCV's and caliscope's split): each camera's focal length is
    OpenCV's calibrateCamera's on the same detections, but cam_3's (edge-on views; Zhang's
    fit of its 40 partial views has a sigma of 5 % and stops 1.6 % away with OpenCV's
    default stopping rule). Against the published focal lengths (caliscope's, from another
    recording of the same webcams): within 1 % for cam_3 only, 1.2-1.6 % for cam_0 and
    cam_1, +4.9 % for cam_2, as OpenCV's; each within 3 sigma of the sigma it reports.
    Intrinsics refined jointly: cam_0 and cam_3 within 0.5 % of the published, cam_2 1.9 %;
    cam_1 is pulled 22 % away by its frames being out of step (next test)."""
    fixed, joint = caliscope["results"][False], caliscope["results"][True]
    pub = CALISCOPE.published
    for name, s in fixed.sensors.items():
        fx, sigma = s.intrinsics.fx, s.sigma["fx"]
        ref = caliscope["cams"][name].intrinsics.fx
        assert abs(fx / ref - 1) < (1e-4 if name != "cam_3" else 0.025), (name, fx, ref)
        assert abs(fx / pub[f"{name}.fx"] - 1) < (0.02 if name != "cam_2" else 0.055), (name, fx)
        assert abs(fx - pub[f"{name}.fx"]) < 3 * sigma, (name, fx, sigma)
    for name, tol in (("cam_0", 0.01), ("cam_2", 0.025), ("cam_3", 0.01)):
        fx = joint.sensors[name].intrinsics.fx
        assert abs(fx / pub[f"{name}.fx"] - 1) < tol, (name, fx)


@pytest.mark.slow  # SLOW_WHY
def test_caliscope_cam_1_is_out_of_step(caliscope: dict) -> None:
    """cam_1's frames lag: paired with cam_0's previous frame, the two fit better (RMS 0.54
    against 0.83 px, intrinsics fixed). Why its joint fit is 1-5 px per view where every
    camera alone fits 0.2 px, and why refining the intrinsics with the poses moves its fx."""
    obs = caliscope["ours"]
    specs = {n: SensorSpec(n, "color", (1280, 720)) for n in ("cam_0", "cam_1")}
    opts = CalibrationOptions(reference="cam_0", refine_intrinsics=False)
    rms = {}
    for shift in (0, -1):
        paired: dict[str, dict[str, np.ndarray]] = {}
        for view, per in obs.items():
            if "cam_0" in per:
                paired.setdefault(view, {})["cam_0"] = per["cam_0"]
            if "cam_1" in per:
                paired.setdefault(f"{int(view) + shift:04d}", {})["cam_1"] = per["cam_1"]
        rms[shift] = calibrate_rig(paired, CALISCOPE_BOARD, specs, opts).rms_px
    assert rms[-1] < 0.75 * rms[0], rms


@pytest.mark.slow  # SLOW_WHY
def test_caliscope_relative_poses_against_opencv_and_published(caliscope: dict) -> None:
    """cam_0 -> cam_1 / cam_2 / cam_3, intrinsics fixed. The issue's target (0.5 deg and 1 %
    of the baseline of the published result) is met by cam_1 (-0.5 %, +0.05 deg) and in
    rotation by cam_2 (+2.5 %, +0.49 deg); not by cam_3 (+4.8 %, +2.9 deg), whose intrinsics
    are uncertain at 5 % (above) and whose rotation follows them (OpenCV's pairwise
    stereoCalibrate with its own cam_3 intrinsics: +2.8 %, -0.7 deg). The bounds are the
    measured differences plus a margin, so that a regression shows."""
    fixed = caliscope["results"][False]
    pub = CALISCOPE.published
    bounds = {  # (published: rel. baseline, deg), (OpenCV's pairwise: rel. baseline, deg)
        "cam_1": ((0.01, 0.5), (0.01, 0.5)),
        "cam_2": ((0.035, 0.6), (0.04, 1.0)),
        "cam_3": ((0.06, 3.5), (0.03, 4.0)),
    }
    for b, ((pub_base, pub_deg), (cv_base, cv_deg)) in bounds.items():
        base, rot = _relative(fixed, b)
        ref = caliscope["pairs"][b]
        assert abs(base / pub[f"cam_0-{b}.baseline_m"] - 1) < pub_base, (b, base)
        assert abs(rot - pub[f"cam_0-{b}.rotation_deg"]) < pub_deg, (b, rot)
        assert abs(base / ref.baseline_m - 1) < cv_base, (b, base, ref.baseline_m)
        assert abs(rot - ref.rotation_deg) < cv_deg, (b, rot, ref.rotation_deg)
