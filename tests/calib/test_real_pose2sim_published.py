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
trifuse -0.33, -0.28, -0.11, -0.01 %; OpenCV's plain pipeline (opencv_figures.measure: detectors'
own corners, 5 coefficients) +0.51, -0.24, +0.08, +1.35 %.

Four boards have corners 0.07-0.12 of a corner spacing from the image's edge; calib.detect's
border rule refused them at a quarter of a spacing and takes them at a twentieth (OpenCV keeps
them too): trifuse finds every board OpenCV finds.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from tests.pose2sim_support import BAD_CORNER_PX, CAMERAS, SET, TARGET, pose2sim_recipe
from trifuse.app.devtools.bench_real_calib import run_trifuse, trifuse_name, write_capture
from trifuse.app.devtools.opencv_figures import measure

pytestmark = pytest.mark.slow  # calibrations of Pose2Sim's real set: about 10 s


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
        recipe[camera] = pose2sim_recipe(camera)
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
