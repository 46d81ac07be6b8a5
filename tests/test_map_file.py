"""The thermal 3D map on disk (app.storage.map_file): the PLY read back by an independent
reader (plyfile), the map file's exact round trip, and the refusal of malformed or foreign
files."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from app.storage import map_file
from app.storage.map_file import (
    MAP_FORMAT,
    NO_COLOUR,
    MapFileError,
    load_map,
    read_map_info,
    save_map,
    write_ply,
)
from calib.transforms import make_T, rotation_from_euler_deg
from fusion.voxel_map import MapSettings, VoxelMap

VOXEL = 0.05


def make_map() -> VoxelMap:
    """A map of random points (seeded) integrated three times at slightly different poses:
    most voxels occupied (hit in two frames or more), some seen once; a third of the points
    without temperature, a quarter without colour."""
    rng = np.random.default_rng(7)
    m = VoxelMap(MapSettings(voxel_m=VOXEL, free_budget=0))
    pts = rng.uniform((-2, -1, 1), (2, 1, 5), size=(3000, 3))
    for k in range(3):
        temps = rng.normal(295.0, 5.0, len(pts))
        temps[rng.random(len(pts)) < 0.33] = np.nan
        rgb = rng.uniform(0, 255, (len(pts), 3))
        rgb[rng.random(len(pts)) < 0.25] = np.nan
        T = make_T(rotation_from_euler_deg(0, 2.0 * k, 0), (0.01 * k, 0, 0))
        chosen = rng.random(len(pts)) < 0.8  # each frame sees most points
        m.integrate(T, np.where(chosen[:, None], pts, np.nan), float(k), temps, rgb)
    return m


@pytest.fixture(scope="module")
def voxel_map() -> VoxelMap:
    m = make_map()
    occupied = m.occupied()
    assert 0 < occupied.sum() < len(m)  # both kinds, so that the PLY's selection shows
    assert np.isnan(m["temp_mean"][occupied]).any() and np.isnan(m["rgb"][occupied]).any()
    return m


def test_the_ply_holds_the_occupied_voxels_as_an_independent_reader_sees_them(
    tmp_path: Path, voxel_map: VoxelMap
) -> None:
    path = write_ply(tmp_path / "map.ply", voxel_map)
    ply = PlyData.read(str(path))
    assert ply.text is False and ply.byte_order == "<"
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == [
        "x", "y", "z", "red", "green", "blue", "temperature", "temperature_max", "observations",
        "quality",
    ]  # fmt: skip
    kinds = {p.name: p.val_dtype for p in vertex.properties}
    assert kinds["x"] == "f4" and kinds["red"] == "u1" and kinds["observations"] == "u4"
    comments = " ".join(ply.comments)
    assert "trifuse" in comments and f"voxel size {VOXEL:g} m" in comments
    assert "degrees Celsius" in comments and "metres" in comments
    occ = voxel_map.occupied()
    v = vertex.data
    assert len(v) == occ.sum()
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), voxel_map["centre"][occ])
    # kelvin -> Celsius in float32: within one float32 step at 300 (3e-5)
    np.testing.assert_allclose(
        v["temperature"], voxel_map["temp_mean"][occ] - 273.15, atol=1e-4, equal_nan=True
    )
    np.testing.assert_allclose(
        v["temperature_max"], voxel_map["temp_max"][occ] - 273.15, atol=1e-4, equal_nan=True
    )
    assert np.isnan(v["temperature"]).sum() == np.isnan(voxel_map["temp_mean"][occ]).sum() > 0
    seen_t = np.isfinite(v["temperature"])  # MeshLab's scalar: no NaN, absolute zero
    np.testing.assert_array_equal(v["quality"][seen_t], v["temperature"][seen_t])
    assert (v["quality"][~seen_t] == np.float32(-273.15)).all()
    rgb = voxel_map["rgb"][occ]
    seen = np.isfinite(rgb).all(axis=1)
    got = np.stack([v["red"], v["green"], v["blue"]], 1)
    assert (got[~seen] == NO_COLOUR).all() and (~seen).any()
    assert np.abs(got[seen].astype(float) - rgb[seen]).max() <= 0.5  # rounded
    np.testing.assert_array_equal(v["observations"], voxel_map["hits"][occ])


def test_an_empty_map_is_a_ply_without_points(tmp_path: Path) -> None:
    path = write_ply(tmp_path / "empty.ply", VoxelMap(MapSettings(voxel_m=0.1)))
    assert len(PlyData.read(str(path))["vertex"].data) == 0


def test_the_map_file_round_trip_is_exact(tmp_path: Path) -> None:
    original = make_map()
    path = save_map(tmp_path / "m.map.npz", original, info={"recordings": ["a.mcap"]})
    loaded = load_map(path)
    assert loaded.settings == original.settings
    assert len(loaded) == len(original)
    a, b = original.arrays(), loaded.arrays()
    assert a.keys() == b.keys()
    for name in a:
        assert a[name].dtype == b[name].dtype, name
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)  # NaN == NaN here
    np.testing.assert_array_equal(loaded.occupied(), original.occupied())
    assert read_map_info(path) == {"recordings": ["a.mcap"]}
    # The loaded map goes on as the original does: the same frame into both (old voxels
    # and new ones) gives the same maps.
    pts = np.random.default_rng(8).uniform((-3, -1, 1), (3, 1, 6), size=(500, 3))
    for m in (original, loaded):
        m.integrate(np.eye(4), pts, 9.0, np.full(len(pts), 300.0))
    assert len(loaded) > len(b["keys"])
    for name, x in original.arrays().items():
        np.testing.assert_array_equal(x, loaded.arrays()[name], err_msg=name)


def test_nothing_is_overwritten_unless_asked_and_no_temporary_is_left(
    tmp_path: Path, voxel_map: VoxelMap
) -> None:
    ply, npz = tmp_path / "m.ply", tmp_path / "m.map.npz"
    ply.write_bytes(b"precious")
    npz.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        write_ply(ply, voxel_map)
    with pytest.raises(FileExistsError):
        save_map(npz, voxel_map)
    assert ply.read_bytes() == npz.read_bytes() == b"precious"
    write_ply(ply, voxel_map, overwrite=True)
    save_map(npz, voxel_map, overwrite=True)
    assert len(PlyData.read(str(ply))["vertex"].data) == voxel_map.occupied().sum()
    assert len(load_map(npz)) == len(voxel_map)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.map.npz", "m.ply"]


def _npz(path: Path, **arrays: np.ndarray) -> Path:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())
    return path


def _content(voxel_map: VoxelMap) -> dict[str, np.ndarray]:
    """What save_map writes, to be spoiled one way at a time."""
    arrays = voxel_map.arrays()
    out = {name: arrays[name] for name in map_file._ARRAYS}
    out["format"] = np.array(MAP_FORMAT)
    out["settings"] = np.array(json.dumps({"voxel_m": VOXEL, "free_budget": 0}))
    return out


def _spoil(content: dict[str, np.ndarray], name: str, value: np.ndarray | None):
    spoiled = dict(content)
    if value is None:
        del spoiled[name]
    else:
        spoiled[name] = value
    return spoiled


MALFORMED = [
    ("format", np.array("trifuse-map/2"), "expected 'trifuse-map/1'"),
    ("format", None, "no 'format' entry"),
    ("format", np.array(b"trifuse-map/1"), "expected 'trifuse-map/1'"),
    ("hits", None, "no hits"),
    ("settings", np.array("{not json"), "settings"),
    ("settings", np.array(json.dumps({"voxel_m": -1.0})), "voxel_m"),
    ("settings", np.array(json.dumps({"voxel": 0.05})), "unknown settings"),
    ("temp_mean", np.zeros(3, np.float32), "temp_mean has shape"),
    ("centre", np.zeros((2, 2), np.float32), "centre has shape"),
    ("rgb", np.array(["a"]), "rgb holds"),
    ("path_T_world_tof", np.zeros((1, 3, 3)), "do not match"),
    ("keys", np.zeros(0, np.int64), "has shape"),
]


@pytest.mark.parametrize(("name", "value", "message"), MALFORMED, ids=[m[2] for m in MALFORMED])
def test_a_malformed_map_file_is_refused_naming_the_file(
    tmp_path: Path, voxel_map: VoxelMap, name: str, value: np.ndarray | None, message: str
) -> None:
    path = _npz(tmp_path / "bad.map.npz", **_spoil(_content(voxel_map), name, value))
    with pytest.raises(MapFileError, match=message) as info:
        load_map(path)
    assert str(path) in str(info.value)


def test_voxel_keys_must_be_unique_and_match_their_centres(
    tmp_path: Path, voxel_map: VoxelMap
) -> None:
    content = _content(voxel_map)
    keys = content["keys"].copy()
    keys[1] = keys[0]
    with pytest.raises(MapFileError, match="repeat"):
        load_map(_npz(tmp_path / "a.npz", **_spoil(content, "keys", keys)))
    swapped = content["keys"].copy()
    swapped[[0, 1]] = swapped[[1, 0]]
    with pytest.raises(MapFileError, match="do not match the centres"):
        load_map(_npz(tmp_path / "b.npz", **_spoil(content, "keys", swapped)))


def test_foreign_files_are_refused(tmp_path: Path) -> None:
    text = tmp_path / "notes.map.npz"
    text.write_text("just text")
    npy = tmp_path / "array.npy"
    np.save(npy, np.zeros(3))
    pickled = _npz(tmp_path / "pickled.npz", format=np.array([{"a": 1}], dtype=object))
    cut = tmp_path / "cut.npz"
    good = _npz(tmp_path / "good.npz", format=np.array(MAP_FORMAT))
    cut.write_bytes(good.read_bytes()[:40])
    for path, message in [
        (tmp_path / "missing.map.npz", "no such map file"),
        (tmp_path, "a directory"),
        (text, "not a readable map file"),
        (npy, "expected a .npz archive"),
        (pickled, "not a readable map file"),
        (cut, "not a readable map file"),
    ]:
        with pytest.raises(MapFileError, match=message) as info:
            load_map(path)
        assert str(path) in str(info.value), path
    assert zipfile.is_zipfile(good)
