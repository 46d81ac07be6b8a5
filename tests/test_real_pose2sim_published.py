"""trifuse's focal lengths against a calibration published from the same real images: Pose2Sim's
four cameras (tests/data/pose2sim-4cam-checker, 1088 x 1920, 4 x 7 inner corners, 6-7 views
each), with OpenCV's pipelines run here on the same images.

Issue 30's target: focal lengths within 1 % of the published calibration. The published one
(``Calib_scene.toml``) is Pose2Sim's recipe on these very images: OpenCV's classic detector,
``cornerSubPix`` (11 x 11), ``calibrateCamera`` with k3 fixed. Run here, that recipe gives the
published fx to 0.00 % on all four cameras, so the target compares like with like.

On cam04 the recipe's corner 3 of view cam04_07 (18 px from the image's left edge) stays where
the classic detector put it, about 14 px from the corner in the image (its reprojection error
9.9 px; the fit's RMS is 0.92 px with that view, 0.22 px without): the published fx of cam04
is pulled 1.1 % up by that one corner. Without that view the same recipe gives 1671.6 px;
that is cam04's reference here, and the test checks that the published value misses it for
this reason.

Measured (fx against published; cam04 against the recipe without the bad view):
trifuse -0.33, -0.28, -0.11, -0.01 %; OpenCV's plain pipeline (real_sets.measure: detectors'
own corners, 5 coefficients) +0.51, -0.24, +0.08, +1.35 %.

Four boards have corners 0.07-0.12 of a corner spacing from the image's edge; calib.detect's
border rule refused them at a quarter of a spacing and takes them at a twentieth (OpenCV keeps
them too): trifuse finds every board OpenCV finds.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from trifuse.app.devtools.bench_real_calib import run_trifuse, trifuse_name, write_capture
from trifuse.app.devtools.real_sets import REAL_SETS, load_views, measure

SET = REAL_SETS["pose2sim-4cam-checker"]
CAMERAS = [s.name for s in SET.sensors]
TARGET = 0.01
"""Issue 30: focal lengths within 1 % of the published calibration."""
BAD_CORNER_PX = 5.0
"""A view whose worst corner is further than this from the recipe's fit is a detection error
(measured: 9.9 px on cam04_07; every other corner of the set within 1.3 px)."""


@dataclasses.dataclass
class Recipe:
    """Pose2Sim's calibration recipe on one camera's views."""

    fx: float
    fy: float
    worst_px: dict[str, float]
    """View id -> its worst corner's reprojection error, px."""
    fx_clean: float
    """fx again without the views whose worst corner is beyond BAD_CORNER_PX."""


def _recipe_fit(
    corners: dict[str, np.ndarray], size: tuple[int, int]
) -> tuple[np.ndarray, dict[str, float]]:
    """``calibrateCamera`` as Pose2Sim calls it (k3 fixed): K (3, 3), and per view id its
    worst corner's reprojection error (px). ``corners``: view id -> (N, 1, 2) pixels."""
    obj = np.zeros((SET.board.cols * SET.board.rows, 3), np.float32)
    obj[:, :2] = np.mgrid[0 : SET.board.cols, 0 : SET.board.rows].T.reshape(-1, 2)
    obj *= SET.board.square_m
    flags = cv2.CALIB_FIX_K3 + cv2.CALIB_USE_LU
    _rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj] * len(corners), list(corners.values()), size, None, None, flags=flags
    )
    worst = {}
    for view, uv, r, t in zip(corners, corners.values(), rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj, r, t, K, dist)
        worst[view] = float(np.linalg.norm(proj.reshape(-1, 2) - uv.reshape(-1, 2), axis=1).max())
    return K, worst


def _recipe(camera: str) -> Recipe:
    """Pose2Sim's recipe on one camera: classic detector, cornerSubPix 11 x 11, k3 fixed."""
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    sensor = SET.sensor(camera)
    corners = {}
    for view, image in load_views(SET, sensor).items():
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        found, c = cv2.findChessboardCorners(grey, (SET.board.cols, SET.board.rows), None)
        if found:
            corners[view] = cv2.cornerSubPix(grey, c, (11, 11), (-1, -1), criteria)
    K, worst = _recipe_fit(corners, sensor.image_size)
    clean = {v: c for v, c in corners.items() if worst[v] <= BAD_CORNER_PX}
    K_clean, _ = _recipe_fit(clean, sensor.image_size) if len(clean) < len(corners) else (K, {})
    return Recipe(float(K[0, 0]), float(K[1, 1]), worst, float(K_clean[0, 0]))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Per camera: trifuse calibrate's pipeline on a capture of that camera alone (the cameras
    share no view), Pose2Sim's recipe, and OpenCV's plain pipeline on the whole set."""
    trifuse, recipe = {}, {}
    for camera in CAMERAS:
        one = dataclasses.replace(SET, sensors=(SET.sensor(camera),))
        capture = tmp_path_factory.mktemp(camera)
        write_capture(one, None, capture)
        name = trifuse_name(SET.sensor(camera))
        trifuse[camera] = (name, run_trifuse(capture, [name]))
        recipe[camera] = _recipe(camera)
    return trifuse, recipe, measure(SET)


def test_the_published_calibration_is_pose2sims_recipe_on_these_images(runs) -> None:
    _trifuse, recipe, _opencv = runs
    for camera in CAMERAS:
        r = recipe[camera]
        assert r.fx == pytest.approx(SET.published[f"{camera}.fx"], rel=1e-4), camera
        assert r.fy == pytest.approx(SET.published[f"{camera}.fy"], rel=1e-4), camera
    bad = {c: [v for v, px in recipe[c].worst_px.items() if px > BAD_CORNER_PX] for c in CAMERAS}
    assert bad == {"cam01": [], "cam02": [], "cam03": [], "cam04": ["cam04_07"]}
    # That one corner pulls the published fx of cam04 more than 1 % from the fit without it.
    assert recipe["cam04"].fx / recipe["cam04"].fx_clean - 1 > TARGET


def test_trifuse_focal_lengths_are_within_1_percent_of_the_published(runs) -> None:
    trifuse, recipe, opencv = runs
    lines = []
    for camera in CAMERAS:
        name, run = trifuse[camera]
        assert run.failure == "", (camera, run.failure)
        fx = run.result.sensors[name].intrinsics.fx
        sigma = run.result.sensors[name].sigma["fx"]
        ref = recipe[camera].fx_clean  # = the published fx where no corner was mislocated
        lines.append(
            f"{camera}: trifuse {fx:.1f} +- {sigma:.1f} ({fx / ref - 1:+.2%}), OpenCV plain "
            f"{opencv.sensors[camera].fx:.1f} ({opencv.sensors[camera].fx / ref - 1:+.2%}), "
            f"reference {ref:.1f}, published {SET.published[f'{camera}.fx']:.1f}"
        )
        assert math.isfinite(sigma) and sigma > 0, camera
        assert abs(fx / ref - 1) < TARGET, "\n".join(lines)


def test_trifuse_finds_every_board_opencv_finds(runs) -> None:
    trifuse, _recipe, opencv = runs
    for camera in CAMERAS:
        name, run = trifuse[camera]
        assert len(run.found[name]) >= opencv.sensors[camera].found, camera
