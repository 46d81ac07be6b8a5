"""Image coverage: ROS-style X / Y / size / skew bars, the region map and its names."""

from __future__ import annotations

import math

import numpy as np
import pytest

from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.board import Board
from trifuse.calib.coverage import (
    COARSE_NAMES,
    NOVELTY_THRESHOLD,
    WHOLE_IMAGE,
    coverage,
    name_empty_regions,
    pose_novelty,
    view_params,
)
from trifuse.calib.transforms import make_T, rotation_from_rvec, transform_points

BOARD = Board(9, 6, 0.03)  # 0.24 m x 0.15 m of corners: about 320 x 200 px at 1 m
CAMERA = default_rig()["ccd_left"]
SIZE = CAMERA.image_size
W, H = SIZE
CORNER_NAMES = ["top-left corner", "top-right corner", "bottom-left corner", "bottom-right corner"]


def board_view(
    at: tuple[float, float],
    distance_m: float,
    tilt_deg: float = 0.0,
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0),
) -> np.ndarray:
    """Corners (N, 2) of the board centred on image fraction ``at`` = (u, v) in [0, 1].

    The board is square-on to the camera's z axis, then tilted by ``tilt_deg`` about
    ``axis`` (board frame) through its centre; ``distance_m`` is the centre's depth.
    """
    K = CAMERA.intrinsics
    ray = K.unproject(np.array([at[0] * (W - 1), at[1] * (H - 1)]))
    obj = BOARD.object_points()
    centre = obj.mean(axis=0)
    a = np.asarray(axis, dtype=np.float64)
    R = rotation_from_rvec(a / np.linalg.norm(a) * np.radians(tilt_deg))
    t = ray / ray[2] * distance_m - R @ centre
    uv = K.project(transform_points(make_T(R, t), obj))
    assert np.all((uv >= 0) & (uv <= (W - 1, H - 1))), "test view leaves the image"
    return uv


# -- one view ---------------------------------------------------------------------------------


def test_single_centred_view() -> None:
    cov = coverage([board_view((0.5, 0.5), 1.0)], BOARD, SIZE)
    x, y, size, skew = view_params(board_view((0.5, 0.5), 1.0), BOARD, SIZE)
    assert x == pytest.approx(0.5, abs=0.01) and y == pytest.approx(0.5, abs=0.01)
    assert cov.x == 0.0 and cov.y == 0.0  # no spread at all
    assert cov.x_range == (x, x) and cov.size_range == (size, size)
    assert cov.skew_range == (skew, skew)
    assert cov.size == pytest.approx(size / 0.4)
    assert cov.skew < 0.01
    assert not cov.good_enough
    assert cov.n_views == 1
    assert cov.grid_shape == (6, 8) and cov.corner_counts.shape == (6, 8)
    assert cov.corner_counts.sum() == BOARD.n_corners
    for name in CORNER_NAMES:
        assert name in cov.empty_regions
    assert "centre" not in cov.empty_regions
    assert "top edge" in cov.empty_regions and "bottom edge" in cov.empty_regions


def test_skew_fronto_parallel_and_tilted() -> None:
    flat = view_params(board_view((0.5, 0.5), 1.0), BOARD, SIZE)[3]
    assert flat == pytest.approx(0.0, abs=0.005)
    # Tilted 45 degrees about the board's vertical axis: only perspective makes the
    # quadrilateral non-rectangular, a clear but moderate skew.
    about_vertical = view_params(board_view((0.5, 0.5), 1.0, 45.0), BOARD, SIZE)[3]
    assert about_vertical > 0.05
    # About a diagonal, foreshortening shears the image: the top-right angle is ~70 deg.
    about_diagonal = view_params(board_view((0.5, 0.5), 1.0, 45.0, (1.0, -1.0, 0.0)), BOARD, SIZE)
    assert about_diagonal[3] > 0.5


def test_view_params_known_quadrilateral() -> None:
    # A synthetic axis-aligned detection: a 2x2 board whose corners span 100 x 50 px.
    board = Board(2, 2, 0.1)
    corners = np.array([[100.0, 200.0], [200.0, 200.0], [100.0, 250.0], [200.0, 250.0]])
    x, y, size, skew = view_params(corners, board, (1000, 500))
    border = math.sqrt(100 * 50)
    assert x == pytest.approx((150 - border / 2) / (1000 - border))
    assert y == pytest.approx((225 - border / 2) / (500 - border))
    assert size == pytest.approx(math.sqrt(5000 / 500_000))
    assert skew == 0.0


def test_view_params_rejects_bad_input() -> None:
    good = board_view((0.5, 0.5), 1.0)
    with pytest.raises(ValueError, match=r"expected shape \(54, 2\)"):
        view_params(good[:-1], BOARD, SIZE)
    bad = good.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        view_params(bad, BOARD, SIZE)
    with pytest.raises(ValueError, match="image_size"):
        view_params(good, BOARD, (1280,))
    with pytest.raises(ValueError, match="grid_shape"):
        coverage([good], BOARD, SIZE, grid_shape=(0, 8))
    with pytest.raises(ValueError, match=r"corner_sets\[1\]"):
        coverage([good, good[:10]], BOARD, SIZE)


# -- a set of views ----------------------------------------------------------------------------


def test_spread_and_tilted_views_fill_the_bars() -> None:
    views = []
    for i, u in enumerate((0.14, 0.5, 0.86)):
        for j, v in enumerate((0.14, 0.5, 0.86)):
            tilt = 35.0 if (i + j) % 2 else 0.0
            views.append(board_view((u, v), 1.0, tilt, (1.0, -1.0, 0.0)))
    views.append(board_view((0.5, 0.5), 0.4))  # a close-up for the size bar
    cov = coverage(views, BOARD, SIZE)
    assert (cov.x, cov.y, cov.size, cov.skew) == (1.0, 1.0, 1.0, 1.0)
    assert cov.progress == (1.0, 1.0, 1.0, 1.0)
    assert cov.good_enough
    assert cov.x_range[0] < 0.1 and cov.x_range[1] > 0.9
    assert cov.y_range[0] < 0.1 and cov.y_range[1] > 0.9
    assert cov.empty_regions == []
    assert cov.corner_counts.min() > 0
    assert cov.corner_counts.sum() == len(views) * BOARD.n_corners
    # Without the close-up and the tilted views two bars stay short.
    flat_small = [v for k, v in enumerate(views[:-1]) if (k // 3 + k % 3) % 2 == 0]
    partial = coverage(flat_small, BOARD, SIZE)
    assert partial.x == 1.0 and partial.y == 1.0
    # Square-on views off the axis still show a little perspective skew, far from full.
    assert partial.size < 1.0 and partial.skew < 0.5
    assert not partial.good_enough
    # Corners and centre only: the middle of every edge was never reached.
    assert partial.empty_regions == ["top edge", "left edge", "right edge", "bottom edge"]


def test_no_views() -> None:
    cov = coverage([], BOARD, SIZE)
    assert (cov.x, cov.y, cov.size, cov.skew) == (0.0, 0.0, 0.0, 0.0)
    assert all(math.isnan(v) for v in cov.x_range)
    assert cov.empty_regions == [WHOLE_IMAGE]
    assert cov.corner_counts.sum() == 0
    assert not cov.good_enough and cov.n_views == 0


def test_corner_counts_use_pixel_edges() -> None:
    # 2 x 2 grid over a 100 x 50 image: cell edges at u = 49.5 and v = 24.5.
    board = Board(2, 2, 0.1)
    corners = np.array([[-0.5, -0.5], [49.4, 24.4], [49.5, 24.5], [99.6, 49.6]])
    cov = coverage([corners], board, (100, 50), grid_shape=(2, 2))
    np.testing.assert_array_equal(cov.corner_counts, [[2, 0], [0, 1]])  # last one is outside
    assert cov.empty_regions == ["top-right corner", "bottom-left corner"]


# -- region names -----------------------------------------------------------------------------


def test_name_empty_regions_coarse_and_cells() -> None:
    counts = np.ones((6, 8), dtype=int)
    counts[0:2, 0:3] = 0  # the whole top-left coarse region
    counts[5, 4] = 0  # one cell of the bottom edge
    assert name_empty_regions(counts) == ["top-left corner", "row 5, col 4 (bottom edge)"]
    assert name_empty_regions(np.ones((6, 8))) == []
    assert name_empty_regions(np.zeros((6, 8))) == [WHOLE_IMAGE]
    # Every coarse name is reachable, in reading order.
    only_centre_seen = np.zeros((3, 3), dtype=int)
    only_centre_seen[1, 1] = 5
    expected = [n for row in COARSE_NAMES for n in row if n != "centre"]
    assert name_empty_regions(only_centre_seen) == expected


# -- novelty ----------------------------------------------------------------------------------


def test_pose_novelty() -> None:
    p = view_params(board_view((0.5, 0.5), 1.0), BOARD, SIZE)
    assert pose_novelty(p, [p]) == 0.0
    assert pose_novelty(p, []) == math.inf
    q = view_params(board_view((0.12, 0.5), 1.0), BOARD, SIZE)
    assert pose_novelty(q, [p]) == pytest.approx(sum(abs(a - b) for a, b in zip(p, q, strict=True)))
    assert pose_novelty(q, [p]) > NOVELTY_THRESHOLD
    assert pose_novelty(q, [p, q]) == 0.0
    with pytest.raises(ValueError, match="previous_params"):
        pose_novelty(p, [(0.1, 0.2)])
