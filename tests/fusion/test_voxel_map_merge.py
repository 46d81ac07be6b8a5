"""VoxelMap.merge: maps of consecutive pieces of a recording merged in plan order read as
one map of all the frames (exactly where the module promises it, within float32 rounding
for the means), deterministically, within the voxel cap."""

from __future__ import annotations

from dataclasses import asdict
from itertools import pairwise

import numpy as np
import pytest

from trifuse.calib.camera import Intrinsics
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.geometry import tof_rays
from trifuse.fusion.voxel_map import DepthImage, MapSettings, VoxelMap, _prior_weight

# hits only; hit_logodds a power of two (float32 sums exact) and max_logodds out of reach
# of 6 frames: the log-odds of a merge and of a sequential build agree exactly
EXACT = MapSettings(voxel_m=0.1, recency=0.1, hit_logodds=0.5, max_logodds=50.0)
N_FRAMES = 6  # <= 1 / recency readings per voxel: the recency mean is a plain running mean

TOF = Intrinsics(165.5, 165.8, 87.9, 71.2, (-0.12, 0.05, 0.0003, -0.0002, 0.0))
W, H = 176, 144


def make_frames(seed: int, n: int, points: int = 3000) -> list[dict]:
    """``n`` frames of random points in front of a slightly moving head: the frames
    overlap in space, some points are invalid, some lack a temperature or a colour."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        p = rng.uniform((-1.0, -1.0, 1.5), (1.0, 1.0, 2.5), size=(points, 3))
        p[rng.random(points) < 0.02] = np.nan
        temps = 300.0 + rng.normal(0.0, 3.0, points)
        temps[rng.random(points) < 0.3] = np.nan
        rgb = rng.uniform(0.0, 255.0, size=(points, 3))
        rgb[rng.random(points) < 0.3] = np.nan
        R = rotation_from_euler_deg(*rng.uniform(-5.0, 5.0, 3))
        T = make_T(R, rng.uniform(-0.2, 0.2, 3))
        frames.append({"T": T, "p": p, "stamp": 10.0 + k, "temps": temps, "rgb": rgb})
    return frames


def build(settings: MapSettings, frames: list[dict]) -> VoxelMap:
    m = VoxelMap(settings)
    for f in frames:
        m.integrate(f["T"], f["p"], f["stamp"], f["temps"], f["rgb"], f.get("depth"))
    return m


def by_key(m: VoxelMap, name: str) -> dict[int, np.ndarray]:
    arrays = m.arrays()
    return dict(zip(arrays["keys"].tolist(), arrays[name], strict=True))


def assert_identical(x: VoxelMap, y: VoxelMap) -> None:
    """Every array of the two maps byte for byte (NaN bits, row order included)."""
    ax, ay = x.arrays(), y.arrays()
    assert ax.keys() == ay.keys()
    for name in ax:
        assert ax[name].dtype == ay[name].dtype and ax[name].shape == ay[name].shape, name
        assert ax[name].tobytes() == ay[name].tobytes(), name


def test_the_closed_form_prior_weight_is_the_product_of_the_blend_steps() -> None:
    n_a, n_b = np.meshgrid(np.arange(0, 40), np.arange(0, 40), indexing="ij")
    n_a, n_b = n_a.ravel(), n_b.ravel()
    for recency in (1.0, 0.5, 1 / 3, 0.3, 0.2, 0.1, 0.07, 0.05, 0.01):
        lam = _prior_weight(n_a, n_b, recency)
        brute = np.ones(len(n_a))
        for i, (na, nb) in enumerate(zip(n_a.tolist(), n_b.tolist(), strict=True)):
            for k in range(1, nb + 1):
                brute[i] *= 1.0 - max(1.0 / (na + k), recency)
        np.testing.assert_allclose(lam, brute, rtol=1e-12, atol=1e-300, err_msg=f"{recency}")
    assert _prior_weight(np.array([0]), np.array([0]), 0.1)[0] == 1.0  # nothing blended in
    assert _prior_weight(np.array([0]), np.array([3]), 0.1)[0] == 0.0  # nothing before


def test_merging_with_an_empty_map_changes_nothing_either_way() -> None:
    frames = make_frames(1, 3)
    original = build(EXACT, frames)
    m = build(EXACT, frames)
    st = m.merge(VoxelMap(EXACT))
    assert (st.voxels, st.new_voxels, st.dropped_full) == (0, 0, 0)
    assert_identical(m, original)
    assert m.revision == original.revision + 1
    assert asdict(m.stats) == asdict(original.stats)
    empty = VoxelMap(EXACT)
    st = empty.merge(original)
    assert st.voxels == st.new_voxels == len(original) and st.dropped_full == 0
    assert_identical(empty, original)
    assert asdict(empty.stats) == asdict(original.stats)
    assert empty.path[0][1] is not original.path[0][1]  # copies, not shared poses


@pytest.mark.parametrize("cuts", [(3,), (2, 4)])
def test_merged_pieces_read_as_one_sequential_build(cuts: tuple[int, ...]) -> None:
    frames = make_frames(2, N_FRAMES)
    bounds = (0, *cuts, N_FRAMES)
    pieces = [build(EXACT, frames[i:j]) for i, j in pairwise(bounds)]
    whole = build(EXACT, frames)  # depth=None: no free-space carving anywhere
    merged = build(EXACT, frames[: cuts[0]])  # = pieces[0], built afresh
    for piece in pieces[1:]:
        merged.merge(piece)

    # the voxels: the union of the pieces' (and, without carving or a cap, even the
    # sequential build's row order: first appearance, sorted within a frame)
    piece_keys = [p.arrays()["keys"] for p in pieces]
    got, want = merged.arrays(), whole.arrays()
    assert set(got["keys"].tolist()) == set().union(*(k.tolist() for k in piece_keys))
    assert set(got["keys"].tolist()) == set(want["keys"].tolist())
    np.testing.assert_array_equal(got["keys"], want["keys"])
    # hits: the pieces' sums; the path: the pieces' one after the other
    hits = {}
    for p in pieces:
        for key, h in by_key(p, "hits").items():
            hits[key] = hits.get(key, 0) + int(h)
    assert {k: int(h) for k, h in by_key(merged, "hits").items()} == hits
    np.testing.assert_array_equal(
        got["path_stamp_s"], np.concatenate([p.arrays()["path_stamp_s"] for p in pieces])
    )
    np.testing.assert_array_equal(got["path_T_world_tof"], want["path_T_world_tof"])
    # exact against the sequential build
    for name in ("centre", "hits", "logodds", "temp_n", "rgb_n", "temp_max", "temp_last"):
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    np.testing.assert_array_equal(got["last_seen"], want["last_seen"])
    assert (whole["temp_n"] <= 1 / EXACT.recency).all() and whole["temp_n"].max() > 1
    # stats: the pieces' sums, new_voxels the voxels of the merged map: the sequential's
    assert asdict(merged.stats) == asdict(whole.stats)
    assert merged.stats.new_voxels == len(merged) < sum(p.stats.new_voxels for p in pieces)

    # The means: with n <= 1 / recency readings both are running means of the same float64
    # readings. A running-mean step stores float32 (error <= half an ulp of the largest
    # value) after weighing with a float32 weight (error <= 2**-24 * the readings' spread);
    # errors of earlier steps shrink by (1 - w) <= 1. So each of the sequential mean and
    # the pieces' means is within n * e of the exact mean, e = ulp / 2 + 2**-24 * spread;
    # a merge's convex combination keeps that and rounds once more to float32 (ulp / 2).
    # Hence |merged - sequential| <= (2 * n + merges) * e.
    merges = len(pieces) - 1
    for name, lo, hi in (("temp_mean", 270.0, 330.0), ("rgb", 0.0, 255.0)):
        ok = np.isfinite(want[name])
        np.testing.assert_array_equal(np.isfinite(got[name]), ok, err_msg=name)
        assert lo <= want[name][ok].min() and want[name][ok].max() <= hi  # the bounds hold
        e = np.spacing(np.float32(hi)) / 2 + 2.0**-24 * (hi - lo)
        tol = (2 * N_FRAMES + merges) * e
        np.testing.assert_allclose(got[name][ok], want[name][ok], rtol=0, atol=tol, err_msg=name)


def test_merging_is_deterministic_and_order_matters_only_as_documented() -> None:
    rays = tof_rays(TOF, W, H)
    rng = np.random.default_rng(4)
    frames = []
    for k in range(6):  # a wall with free space in front: carving in each piece
        z = 3.0 + rng.uniform(-0.3, 0.3)
        d = np.full((H, W), z) / rays[..., 2]
        T = make_T(rotation_from_euler_deg(0.0, 3.0 * k, 0.0), (0.05 * k, 0.0, 0.0))
        frames.append({"T": T, "p": rays * d[..., None], "stamp": float(k),
                       "temps": rng.normal(300.0, 2.0, (H, W)), "rgb": None,
                       "depth": DepthImage(d, TOF)})  # fmt: skip
    s = MapSettings(voxel_m=0.1)

    def plan(order: tuple[int, ...]) -> VoxelMap:
        pieces = [build(s, frames[0:2]), build(s, frames[2:4]), build(s, frames[4:6])]
        merged = pieces[order[0]]
        for i in order[1:]:
            merged.merge(pieces[i])
        return merged

    assert plan((0, 1, 2)).stats.carved > 0
    assert_identical(plan((0, 1, 2)), plan((0, 1, 2)))
    # the other order: the same voxels with the same hits and maxima, but rows, path and
    # the latest readings in that order
    forward, backward = plan((0, 1, 2)), plan((2, 1, 0))
    assert by_key(forward, "hits").keys() == by_key(backward, "hits").keys()
    assert not np.array_equal(forward.arrays()["keys"], backward.arrays()["keys"])
    for name in ("hits", "temp_max", "temp_n"):
        f, b = by_key(forward, name), by_key(backward, name)
        assert all(np.array_equal(f[k], b[k]) for k in f), name
    np.testing.assert_array_equal(forward.arrays()["path_stamp_s"], [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(backward.arrays()["path_stamp_s"], [4, 5, 2, 3, 0, 1])
    f, b = by_key(forward, "last_seen"), by_key(backward, "last_seen")
    assert any(f[k] != b[k] for k in f)  # the last piece merged is the "latest"


def test_the_voxel_cap_holds_and_counts_what_it_drops() -> None:
    frames = make_frames(5, 4)
    big = MapSettings(voxel_m=0.1, max_voxels=1_000_000)
    a, b = build(big, frames[:2]), build(big, frames[2:])
    a_keys, b_keys = a.arrays()["keys"], b.arrays()["keys"]
    new = b_keys[~np.isin(b_keys, a_keys)]  # in b's row order
    room = 10
    assert len(new) > room
    capped = MapSettings(voxel_m=0.1, max_voxels=len(a) + room)
    m = VoxelMap.from_arrays(capped, a.arrays())
    st = m.merge(VoxelMap.from_arrays(capped, b.arrays()))
    assert len(m) == capped.max_voxels
    assert (st.voxels, st.new_voxels, st.dropped_full) == (len(b), room, len(new) - room)
    assert m.stats.dropped_full == len(new) - room
    np.testing.assert_array_equal(m.arrays()["keys"], np.concatenate([a_keys, new[:room]]))
    # full: every new voxel is dropped, the known ones still merge
    st = m.merge(VoxelMap.from_arrays(capped, b.arrays()))
    assert len(m) == capped.max_voxels and st.new_voxels == 0
    assert st.dropped_full == len(new) - room
    assert m.stats.dropped_full == 2 * (len(new) - room)
    # settings must agree; a map is not merged into itself
    with pytest.raises(ValueError, match=r"settings differ.*max_voxels"):
        a.merge(m)
    with pytest.raises(ValueError, match="itself"):
        a.merge(a)
