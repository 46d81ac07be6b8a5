"""What the console shows of a map (fusion.map_view): the level of detail keeps a hot spot
and the surface, colours follow the mode, a threshold highlights, the path is thinned."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.calib.transforms import make_T
from trifuse.fusion.map_view import UNKNOWN_RGB, map_cloud, merged, path_segments
from trifuse.fusion.voxel_map import MapSettings, VoxelMap


def plane_map(n_side: int = 200, voxel: float = 0.01) -> VoxelMap:
    """A 2 x 2 m wall at z = 3 m of 20 C with a 5 x 5 cm hot spot of 80 C at its centre,
    left half coloured red, every voxel hit twice (occupied)."""
    m = VoxelMap(MapSettings(voxel_m=voxel))
    u = (np.arange(n_side) + 0.5) * voxel - n_side * voxel / 2
    x, y = np.meshgrid(u, u)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 3.0)], axis=1)
    temps = np.full(len(pts), 293.15)
    temps[(np.abs(pts[:, 0]) < 0.025) & (np.abs(pts[:, 1]) < 0.025)] = 353.15
    rgb = np.full((len(pts), 3), np.nan)
    rgb[pts[:, 0] < 0] = (200.0, 10.0, 10.0)
    for k in range(2):
        pose = make_T(np.eye(3), (0.0, 0.0, 0.1 * k))
        m.integrate(pose, pts - (0.0, 0.0, 0.1 * k), k, temps, rgb)
    return m


def test_every_voxel_is_shown_while_few_enough() -> None:
    m = plane_map()
    cloud = map_cloud(m, "temperature", max_points=len(m))
    assert cloud.level == 0 and len(cloud.points) == len(m) == 40_000
    assert cloud.cell_m == pytest.approx(0.01)
    assert cloud.span_k is not None and cloud.span_k[0] == pytest.approx(293.15, abs=1e-3)


def test_a_large_map_is_merged_until_it_fits_and_keeps_its_hot_spot() -> None:
    m = plane_map()
    cloud = map_cloud(m, "temperature", max_points=3000)
    assert 0 < len(cloud.points) <= 3000 and cloud.level == 2  # 4 x 4 voxel cells
    assert cloud.cell_m == pytest.approx(0.04)
    # still on the wall: the voxel centre of z = 3 m is 3.005 m (half a voxel)
    np.testing.assert_allclose(cloud.points[:, 2], 3.005, atol=1e-5)
    assert np.nanmax(cloud.temp_max) == pytest.approx(353.15, abs=1e-3)
    cells, level, occupied = merged(m, 3000)
    assert occupied == 40_000 and level == 2
    # a cell's mean temperature is its voxels' mean: weighted by the voxels per cell,
    # the cells' mean is the wall's
    cell_of = np.floor(m["centre"] / 0.04).astype(np.int64)
    per_cell = np.unique(cell_of, axis=0, return_counts=True)[1]
    assert np.average(cells["temp_mean"], weights=per_cell) == pytest.approx(
        float(np.mean(m["temp_mean"])), abs=1e-3
    )


def test_colour_mode_shows_the_cameras_colour_and_grey_where_none_saw() -> None:
    cloud = map_cloud(plane_map(), "color", max_points=100_000)
    left = cloud.points[:, 0] < 0
    np.testing.assert_array_equal(cloud.colors[left], [[200, 10, 10]] * int(left.sum()))
    np.testing.assert_array_equal(cloud.colors[~left], [UNKNOWN_RGB] * int((~left).sum()))
    assert cloud.span_k is None


def test_the_threshold_keeps_the_hot_spot_and_dims_the_rest() -> None:
    m = plane_map()
    plain = map_cloud(m, "temperature", 100_000, span_k=(280.0, 360.0))
    hot = map_cloud(m, "temperature", 100_000, span_k=(280.0, 360.0), threshold_k=323.15)
    is_hot = plain.temp_max >= 323.15
    assert hot.above == int(is_hot.sum()) == 25
    np.testing.assert_array_equal(hot.colors[is_hot], plain.colors[is_hot])
    dim, bright = hot.colors[~is_hot].astype(int), plain.colors[~is_hot].astype(int)
    assert (dim.sum(axis=1) <= bright.sum(axis=1)).all()
    assert (np.ptp(hot.colors[~is_hot].astype(int), axis=1) == 0).all()  # grey


def test_the_path_is_thinned_to_the_most_segments_asked() -> None:
    m = VoxelMap(MapSettings(voxel_m=0.1))
    pts = np.array([[0.0, 0.0, 2.0]])
    for k in range(101):
        m.integrate(make_T(np.eye(3), (0.01 * k, 0.0, 0.0)), pts, float(k))
    seg = path_segments(m, max_segments=10)
    assert len(seg) <= 11
    np.testing.assert_allclose(seg[0, 0], (0.0, 0.0, 0.0))
    np.testing.assert_allclose(seg[-1, 1], (1.0, 0.0, 0.0), atol=1e-6)
    np.testing.assert_allclose(seg[1:, 0], seg[:-1, 1])  # joined
    assert path_segments(VoxelMap(), 10).shape == (0, 2, 3)
    with pytest.raises(ValueError, match="by"):
        map_cloud(m, "depth")  # type: ignore[arg-type]


def test_equalization_gives_the_wall_colours_a_hot_spot_would_take() -> None:
    """A wall warming from 17 to 23 C with an 80 C spot: over the same span a linear
    palette paints the wall in a few entries; plateau equalization spreads it."""
    m = VoxelMap(MapSettings(voxel_m=0.01))
    x = np.linspace(-1.0, 1.0, 200)
    xx, yy = np.meshgrid(x, x)
    pts = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, 3.0)], axis=1)
    temps = 293.15 + 3.0 * pts[:, 0]
    temps[(np.abs(pts[:, 0]) < 0.03) & (np.abs(pts[:, 1]) < 0.03)] = 353.15
    for k in range(2):
        m.integrate(np.eye(4), pts, k, temps)
    span = (float(temps.min()), float(temps.max()))
    linear = map_cloud(m, "temperature", 100_000, span_k=span, agc="linear")
    plateau = map_cloud(m, "temperature", 100_000, span_k=span, agc="plateau")
    wall = linear.temp_max < 300.0

    def entries(c):
        return len(np.unique(c.colors[wall], axis=0))

    assert entries(linear) < 30 < 60 < entries(plateau)
    hottest = np.argmax(plateau.temp_max)
    assert tuple(plateau.colors[hottest]) == tuple(linear.colors[hottest])  # the top entry
