"""The voxel map's core (fusion.voxel_hash, fusion.voxel_map) on synthetic clouds whose
truth is known exactly: hashing, hits, temperature memory, free space, bounds, errors."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.calib.camera import Intrinsics
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.geometry import tof_rays
from trifuse.fusion.voxel_hash import VoxelHash
from trifuse.fusion.voxel_map import DepthImage, MapSettings, VoxelMap

TOF = Intrinsics(165.5, 165.8, 87.9, 71.2, (-0.12, 0.05, 0.0003, -0.0002, 0.0))
W, H = 176, 144
RAYS = tof_rays(TOF, W, H)


def wall_depth(z_wall: float, box: tuple[float, float, float, float, float] | None = None):
    """Radial distances (H, W) of a fronto-parallel wall at ``z_wall`` metres, optionally
    with a box face ``(x0, x1, y0, y1, z)`` in front of it."""
    z = np.full((H, W), z_wall)
    if box is not None:
        x0, x1, y0, y1, zb = box
        t = zb / RAYS[..., 2]
        x, y = RAYS[..., 0] * t, RAYS[..., 1] * t
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        z = np.where(inside, zb, z)
    return z / RAYS[..., 2]


def test_the_hash_finds_every_key_it_was_given_and_no_other() -> None:
    rng = np.random.default_rng(1)
    table = VoxelHash(capacity=1024)
    keys = rng.choice(1 << 40, size=50_000, replace=False).astype(np.int64)
    for part in np.array_split(keys, 7):  # grows several times on the way
        table.insert(part)
    assert table.size == len(keys) and table.capacity >= 4 * len(keys)
    np.testing.assert_array_equal(table.lookup(keys), np.arange(len(keys)))
    others = np.setdiff1d(rng.choice(1 << 40, size=5000), keys)
    assert (table.lookup(others) == -1).all()
    # keys that collide in their first slot: consecutive multiples of the table size
    crowd = VoxelHash(capacity=1024)
    same = np.arange(1, 300, dtype=np.int64) * crowd.capacity
    crowd.insert(same)
    np.testing.assert_array_equal(crowd.lookup(same), np.arange(len(same)))


def test_a_wall_lands_in_the_voxels_it_passes_through() -> None:
    m = VoxelMap(MapSettings(voxel_m=0.05))
    d = wall_depth(3.0)
    pts = RAYS * d[..., None]
    pose = make_T(rotation_from_euler_deg(0, 30, 0), (0.5, 0.0, -1.0))
    for k in range(3):
        st = m.integrate(pose, pts, float(k), np.full((H, W), 300.0), None, DepthImage(d, TOF))
    assert st.points == W * H and st.new_voxels == 0 and st.carved == 0
    assert m.occupied().all()
    # every voxel centre lies within half a voxel diagonal of the wall's plane
    centre_tof = (m["centre"] - pose[:3, 3]) @ pose[:3, :3]
    assert np.abs(centre_tof[:, 2] - 3.0).max() <= 0.05 * np.sqrt(3) / 2 + 1e-6
    assert m["hits"].sum() == 3 * W * H
    np.testing.assert_allclose(m["temp_mean"], 300.0, atol=1e-4)
    assert len(m.path) == 3 and np.allclose(m.path[-1][1], pose)


def test_temperature_averages_first_then_follows_a_change() -> None:
    s = MapSettings(voxel_m=0.1, recency=0.2)
    m = VoxelMap(s)
    pts = (RAYS * wall_depth(2.0)[..., None])[60:80, 80:100]
    rng = np.random.default_rng(3)
    readings = []
    for k in range(4):  # 1/n weights: the plain mean of the first readings
        t = 300.0 + rng.normal(0, 0.5)
        readings.append(t)
        m.integrate(np.eye(4), pts, float(k), np.full(pts.shape[:2], t))
    np.testing.assert_allclose(m["temp_mean"], np.mean(readings), atol=1e-4)
    np.testing.assert_allclose(m["temp_max"], max(readings), atol=1e-4)
    # then the surface heats by 10 K: recency 0.2 closes 1 - 0.8^k of the gap
    before = float(m["temp_mean"][0])
    for k in range(10):
        m.integrate(np.eye(4), pts, 10.0 + k, np.full(pts.shape[:2], 310.0))
    expected = 310.0 - (310.0 - before) * 0.8**10
    np.testing.assert_allclose(m["temp_mean"], expected, atol=1e-3)
    np.testing.assert_allclose(m["temp_last"], 310.0)
    np.testing.assert_allclose(m["temp_max"], 310.0)
    np.testing.assert_allclose(m["last_seen"], 19.0)
    assert (m["temp_n"] == 14).all()


def test_unseen_temperatures_and_colours_stay_unknown() -> None:
    m = VoxelMap(MapSettings(voxel_m=0.1))
    pts = (RAYS * wall_depth(2.0)[..., None]).reshape(-1, 3)
    temps = np.full(len(pts), np.nan)
    rgb = np.full((len(pts), 3), np.nan)
    left = pts[:, 0] < 0
    temps[left] = 295.0
    rgb[~left] = (10.0, 20.0, 30.0)
    m.integrate(np.eye(4), pts, 0.0, temps, rgb)
    x = m["centre"][:, 0]
    assert np.isnan(m["temp_mean"][x > 0.1]).all() and (m["temp_n"][x > 0.1] == 0).all()
    np.testing.assert_allclose(m["temp_mean"][x < -0.1], 295.0)
    np.testing.assert_allclose(m["rgb"][x > 0.1], [[10.0, 20.0, 30.0]] * int((x > 0.1).sum()))
    assert np.isnan(m["rgb"][x < -0.1]).all()


def test_free_space_carves_an_object_that_went_away() -> None:
    """A box 1 m in front of the wall, seen for 3 frames, then gone: the TOF rays now
    pass through its voxels to the wall, so they turn free; the wall stays."""
    s = MapSettings(voxel_m=0.05, free_budget=1_000_000)
    m = VoxelMap(s)
    box = (-0.3, 0.3, -0.3, 0.3, 2.0)
    with_box = wall_depth(3.0, box)
    for k in range(3):
        m.integrate(np.eye(4), RAYS * with_box[..., None], float(k), None, None,
                    DepthImage(with_box, TOF))  # fmt: skip
    on_box = np.flatnonzero(np.abs(m["centre"][:, 2] - 2.0) < 0.1)
    assert len(on_box) > 100 and m.occupied()[on_box].all()
    empty = wall_depth(3.0)
    for k in range(3, 12):
        st = m.integrate(np.eye(4), RAYS * empty[..., None], float(k), None, None,
                         DepthImage(empty, TOF))  # fmt: skip
    assert not m.occupied()[on_box].any()
    on_wall = np.abs(m["centre"][:, 2] - 3.0) < 0.1
    assert m.occupied()[on_wall].all()
    assert st.carved == len(on_box)  # the box's voxels, nothing of the wall
    expected = max(3 * s.hit_logodds + 9 * s.miss_logodds, s.min_logodds)
    np.testing.assert_allclose(m["logodds"][on_box], expected, rtol=1e-6)


def test_the_free_space_budget_bounds_the_work_and_takes_voxels_in_turn() -> None:
    m = VoxelMap(MapSettings(voxel_m=0.05, free_budget=1000))
    d = wall_depth(3.0)
    pts = RAYS * d[..., None]
    m.integrate(np.eye(4), pts, 0.0)
    n = len(m)
    checked = [m.integrate(np.eye(4), pts, 1.0 + k, depth=DepthImage(d, TOF)).free_checked
               for k in range(3)]  # fmt: skip
    assert n > 3000 and checked == [1000, 1000, 1000]


def test_the_extent_and_the_voxel_cap_bound_memory() -> None:
    m = VoxelMap(MapSettings(voxel_m=0.1, max_extent_m=2.0, max_voxels=500))
    rng = np.random.default_rng(5)
    pts = rng.uniform(-4, 4, size=(20_000, 3))
    st = m.integrate(np.eye(4), pts, 0.0)
    outside = int((np.abs(pts) > 2.0 + 0.1).any(axis=1).sum())
    assert st.outside_extent >= outside
    assert len(m) == 500 and st.dropped_full > 0
    assert st.new_voxels + st.dropped_full == len(np.unique(m.keys_of(pts)[0]))
    m.integrate(np.eye(4), pts, 1.0)
    assert len(m) == 500


def test_arrays_round_trip_and_bad_input_is_refused() -> None:
    m = VoxelMap(MapSettings(voxel_m=0.07))
    pts = RAYS * wall_depth(2.5)[..., None]
    m.integrate(make_T(np.eye(3), (0.1, 0.2, 0.3)), pts, 4.0, np.full((H, W), 301.0))
    again = VoxelMap.from_arrays(m.settings, m.arrays())
    for name, a in m.arrays().items():
        np.testing.assert_array_equal(again.arrays()[name], a)
    again.integrate(np.eye(4), pts, 5.0)  # the hash was rebuilt: known voxels found
    assert len(again) >= len(m)
    with pytest.raises(ValueError, match="T_world_tof"):
        m.integrate(np.eye(3), pts, 0.0)
    with pytest.raises(ValueError, match="temperature_k"):
        m.integrate(np.eye(4), pts, 0.0, np.zeros(3))
    with pytest.raises(ValueError, match="voxel_m"):
        MapSettings(voxel_m=0.0)
    bad = m.arrays()
    bad["keys"] = bad["keys"][:-1]
    with pytest.raises(ValueError):
        VoxelMap.from_arrays(m.settings, bad)
