"""The real captures of tests/data (app/devtools/real_sets.py) and their OpenCV reference.

Each registered set: its files and licence are there, its README carries the OpenCV
reference table, and OpenCV's plain pipeline (calib/opencv_reference.py) reproduces those
figures in this run. The tolerances allow for OpenCV builds that round differently; on one
build the figures repeat exactly.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trifuse.app.devtools.opencv_figures import measure, reference_table, top_left_first
from trifuse.app.devtools.real_sets import (
    REAL_SETS,
    Checkerboard,
    published_relative_pose,
    sensor_files,
)
from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import CalibrationError
from trifuse.calib.opencv_reference import (
    CharucoTarget,
    calibrate_camera_opencv,
    stereo_calibrate_opencv,
)
from trifuse.calib.transforms import make_T, rotation_from_euler_deg

SLOW = {"caliscope-charuco-4cam"}
"""About 20 s of ChArUco detection on 4 x 57 video frames."""


def _params(names):
    return [
        pytest.param(n, marks=pytest.mark.slow) if n in SLOW else pytest.param(n) for n in names
    ]


@pytest.mark.parametrize("name", list(REAL_SETS))
def test_set_files_and_licence_are_there(name: str) -> None:
    rs = REAL_SETS[name]
    licence = rs.path / rs.licence[1]
    assert licence.is_file() and licence.stat().st_size > 500, licence
    assert (rs.path / "README.md").is_file()
    views = {}
    for sensor in rs.sensors:
        files = sensor_files(rs, sensor)
        assert files and all(p.is_file() for p in files.values()), sensor.name
        views[sensor.name] = set(files)
        if not sensor.is_video:
            assert len(sorted(files)[:: rs.view_step]) == rs.reference[sensor.name].views
    for a, b in rs.pairs:
        assert views[a] & views[b], f"{a} and {b} share no view"


@pytest.mark.parametrize("name", list(REAL_SETS))
def test_readme_carries_the_reference_table(name: str) -> None:
    rs = REAL_SETS[name]
    readme = (rs.path / "README.md").read_text(encoding="utf-8")
    assert reference_table(rs.reference, rs.reference_pairs) in readme


@pytest.mark.parametrize("name", _params(REAL_SETS))
def test_opencv_reference_reproduces(name: str) -> None:
    rs = REAL_SETS[name]
    m = measure(rs)
    assert list(m.sensors) == list(rs.reference)
    for sensor, want in rs.reference.items():
        got = m.sensors[sensor]
        assert (got.found, got.views) == (want.found, want.views), sensor
        assert got.rms_px == pytest.approx(want.rms_px, abs=0.005), sensor
        for f in ("fx", "fy", "cx", "cy"):
            assert getattr(got, f) == pytest.approx(getattr(want, f), rel=1e-3), (sensor, f)
        assert got.dist == pytest.approx(want.dist, rel=1e-2, abs=1e-3), sensor
    assert len(m.pairs) == len(rs.reference_pairs)
    for got, want in zip(m.pairs, rs.reference_pairs, strict=True):
        assert (got.a, got.b, got.views) == (want.a, want.b, want.views)
        assert got.rms_px == pytest.approx(want.rms_px, abs=0.01)
        assert got.baseline_m == pytest.approx(want.baseline_m, rel=1e-3)
        assert got.rotation_deg == pytest.approx(want.rotation_deg, abs=0.01)


def test_bumblebee_opencv_agrees_with_the_published_calibration() -> None:
    """BoofCV's published stereo calibration and OpenCV's agree within 1 % (focal lengths,
    baseline): the registry's published figures are read the right way round."""
    rs = REAL_SETS["boofcv-bumblebee2-chess"]
    for cam in ("ccd_left", "ccd_right"):
        assert rs.reference[cam].fx == pytest.approx(rs.published[f"{cam}.fx"], rel=0.01)
    pair = rs.reference_pairs[0]
    assert pair.baseline_m == pytest.approx(rs.published["ccd_left-ccd_right.baseline_m"], rel=0.01)


def test_caliscope_published_poses_read_as_world_to_camera() -> None:
    """caliscope's relative poses, read as x_cam = R x_world + t, agree with OpenCV's stereo
    within 3 % in baseline and 1 degree (the other reading gives other figures)."""
    rs = REAL_SETS["caliscope-charuco-4cam"]
    for pair in rs.reference_pairs:
        key = f"{pair.a}-{pair.b}"
        assert pair.baseline_m == pytest.approx(rs.published[f"{key}.baseline_m"], rel=0.03)
        assert pair.rotation_deg == pytest.approx(rs.published[f"{key}.rotation_deg"], abs=1.0)


# -- calib/opencv_reference on synthetic ground truth and bad input ---------------------


def _project(K: Intrinsics, T_cam_board: np.ndarray, pts: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(T_cam_board[:3, :3])
    uv, _ = cv2.projectPoints(pts, rvec, T_cam_board[:3, 3], K.K, K.dist)
    return uv.reshape(-1, 2)


def test_stereo_calibrate_recovers_a_known_pose() -> None:
    board = Checkerboard(4, 6, 0.03)
    pts = board.points()
    K = Intrinsics(520.0, 522.0, 319.5, 239.5, (-0.3, 0.12, 0.0, 0.0, 0.0))
    T_b_a = make_T(rotation_from_euler_deg(0.5, 2.0, -0.3), [-0.12, 0.001, 0.002])
    views_a, views_b = [], []
    for k in range(6):
        R = rotation_from_euler_deg(20.0 * np.sin(k), 25.0 * np.cos(k), 5.0 * k)
        T_a_board = make_T(R, [-0.04 + 0.01 * k, -0.06, 0.5 + 0.05 * k])
        views_a.append(_project(K, T_a_board, pts))
        views_b.append(_project(K, T_b_a @ T_a_board, pts))
    st = stereo_calibrate_opencv([pts] * 6, views_a, views_b, K, K, (640, 480))
    assert st.rms_px < 1e-3
    np.testing.assert_allclose(st.T_b_a, T_b_a, atol=1e-6)
    assert st.baseline_m == pytest.approx(np.linalg.norm(T_b_a[:3, 3]), rel=1e-6)
    cam = calibrate_camera_opencv([pts] * 6, views_a, (640, 480))
    assert cam.intrinsics.fx == pytest.approx(520.0, rel=1e-4)
    assert cam.rms_px < 1e-3


def test_top_left_first_undoes_a_half_turn() -> None:
    c = Checkerboard(4, 6, 1.0).points()[:, :2] * 10 + 100
    np.testing.assert_array_equal(top_left_first(c[::-1]), c)
    np.testing.assert_array_equal(top_left_first(c), c)


def test_published_relative_pose_of_world_to_camera_poses() -> None:
    R_a, t_a = np.eye(3), np.array([0.0, 0.0, 1.0])  # camera a's centre at (0, 0, -1)
    R_b = rotation_from_euler_deg(0.0, 30.0, 0.0)
    t_b = -R_b @ np.array([0.2, 0.0, -1.0])  # camera b's centre 0.2 m to the side of a's
    base, rot = published_relative_pose(R_a, t_a, R_b, t_b)
    assert base == pytest.approx(0.2)
    assert rot == pytest.approx(30.0)


def test_bad_input_is_refused_with_a_clear_message() -> None:
    with pytest.raises(ValueError, match="DICT_4X4_1000"):
        CharucoTarget((4, 5), 0.054, 0.04, "DICT_NOPE")
    with pytest.raises(ValueError, match="marker < square"):
        CharucoTarget((4, 5), 0.054, 0.06, "DICT_4X4_1000")
    pts = Checkerboard(4, 6, 0.03).points()
    with pytest.raises(CalibrationError, match="at least 3 views"):
        calibrate_camera_opencv([pts] * 2, [pts[:, :2]] * 2, (640, 480))
    with pytest.raises(ValueError, match="as many views"):
        calibrate_camera_opencv([pts] * 3, [pts[:, :2]] * 2, (640, 480))
    with pytest.raises(ValueError, match="dist_coeffs"):
        calibrate_camera_opencv([pts] * 3, [pts[:, :2]] * 3, (640, 480), dist_coeffs=6)
