"""The thermal 3D map on disk (app.storage.map_file): the PLY read back by an independent
reader (plyfile), the map file's exact round trip, and the refusal of malformed or foreign
files."""

from __future__ import annotations

import io
import json
import re
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from tests.support import ROOT, measure_in_child
from trifuse.app.storage import map_file
from trifuse.app.storage.map_file import (
    MAP_FORMAT,
    NO_COLOUR,
    MapFileError,
    load_map,
    read_map_info,
    save_map,
    write_ply,
)
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.voxel_map import MapSettings, VoxelMap

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
    # absurd settings: each refused naming the field and its bound
    *(
        ("settings", np.array(json.dumps({"voxel_m": VOXEL, **bad})), message)
        for bad, message in [
            ({"max_voxels": 10**15}, r"max_voxels: expected an integer from 1 to 50000000"),
            ({"max_voxels": 4e6}, r"max_voxels: expected an integer .* got 4000000\.0"),
            ({"voxel_m": float("nan")}, r"voxel_m: expected a positive number at most 40, got nan"),
            ({"max_extent_m": float("inf")}, r"max_extent_m: expected a positive number at most"),
            ({"min_logodds": -float("inf")}, r"min_logodds: expected a negative number at least"),
            ({"occupied_logodds": float("nan")}, r"occupied_logodds: expected a number from"),
            ({"free_margin_m": -1.0}, r"free_margin_m: expected a number from 0 to 40"),
            ({"free_budget": 10**12}, r"free_budget: expected an integer from 0 to"),
        ]
    ),
    (
        "settings",
        np.array(json.dumps({"voxel_m": VOXEL, "max_voxels": 10})),
        "more than max_voxels 10",
    ),
    ("settings", np.array(json.dumps([VOXEL])), "settings: expected a JSON object, got list"),
    ("settings", np.zeros(3), "settings is not a JSON text"),
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


def test_a_compressed_or_foreign_map_file_is_refused_before_its_arrays_are_read(
    tmp_path: Path, voxel_map: VoxelMap
) -> None:
    content = _content(voxel_map)
    compressed = tmp_path / "compressed.map.npz"
    np.savez_compressed(compressed, **content)
    with pytest.raises(MapFileError, match=r"keys\.npy is not stored uncompressed"):
        load_map(compressed)
    extra = _npz(tmp_path / "extra.map.npz", **content, notes=np.zeros(3))
    with pytest.raises(MapFileError, match=r"unknown entries \['notes.npy'\]"):
        load_map(extra)


def test_read_map_info_refuses_what_is_no_json_object(tmp_path: Path, voxel_map: VoxelMap) -> None:
    content = _content(voxel_map)
    for info, message in [
        ("[1, 2]", "info: expected a JSON object, got list"),
        ("{", "info: Expecting property name"),
        ('{"a": ' + "1" * 5000 + "}", "info: Exceeds the limit"),  # int() of 5000 digits
        ('{"a": "' + "[" * 200 + '"}', None),  # brackets in a string are no nesting
    ]:
        path = _npz(tmp_path / "m.map.npz", **content, info=np.array(info))
        if message is None:
            assert read_map_info(path) == {"a": "[" * 200}
            continue
        with pytest.raises(MapFileError, match=message) as caught:
            read_map_info(path)
        assert str(path) in str(caught.value)


# -- hostile files: refused at once, in bounded memory ------------------------------------------


def _npy_header(shape: tuple[int, ...], dtype: str) -> bytes:
    """The .npy header (version 1.0) of an array of ``shape`` and ``dtype``."""
    buf = io.BytesIO()
    descr = np.lib.format.dtype_to_descr(np.dtype(dtype))
    header = {"descr": descr, "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue()


def _zip(
    path: Path, stored: dict[str, bytes], deflated: dict[str, list[bytes]] | None = None
) -> Path:
    """A zip of the ``stored`` members (name -> bytes) and the ``deflated`` ones (name ->
    chunks written in turn; zlib level 1: a gibibyte of zeros in about a second)."""
    with zipfile.ZipFile(path, "w") as z:
        for name, data in stored.items():
            z.writestr(name, data)
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for name, chunks in (deflated or {}).items():
            with z.open(name, "w", force_zip64=True) as f:
                for chunk in chunks:
                    f.write(chunk)
    return path


def _members(voxel_map: VoxelMap, **replace: bytes) -> dict[str, bytes]:
    """The entries of a good map file (what save_map writes), some replaced."""
    buf = io.BytesIO()
    np.savez(buf, **_content(voxel_map))
    with zipfile.ZipFile(buf) as z:
        return {**{n: z.read(n) for n in z.namelist()}, **replace}


def _json_npy(text: str) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.array(text))
    return buf.getvalue()


HOSTILE = {
    # name: (entries replacing a good file's, deflated entries added, the function, refusal)
    # a known entry whose header declares 800 GB, in a 35 kB file
    "keys of 800 GB": (
        {"keys.npy": _npy_header((100_000_000_000,), "<i8") + bytes(64)},
        None,
        "load_map",
        r"keys declares \(100000000000,\) int64 \(800000000000 bytes\), but holds 64 bytes",
    ),
    # an entry no map file has: 1 GiB once loaded, 4.7 MB deflated
    "an extra 1 GiB array": (
        {},
        {"extra.npy": [_npy_header((1 << 28,), "<f4"), *[bytes(1 << 20)] * 1024]},
        "load_map",
        r"not a trifuse map file: unknown entries \['extra.npy'\]",
    ),
    "info nested 100000 deep": (
        {"info.npy": _json_npy("[" * 100_000 + "]" * 100_000)},
        None,
        "read_map_info",
        "info: nested deeper than 100 levels",
    ),
    # an unterminated string of escaped quotes: a scan for strings that retried from each
    # quote took hours
    "info of 500000 escaped quotes": (
        {"info.npy": _json_npy('{"a": "' + '\\"' * 499_990)},
        None,
        "read_map_info",
        "info: Unterminated string starting at",
    ),
    "settings nested 8000 deep": (  # within the 16384 characters of settings
        {"settings.npy": _json_npy("[" * 8000 + "]" * 8000)},
        None,
        "load_map",
        "settings: nested deeper than 100 levels",
    ),
}


@pytest.mark.parametrize("hostile", list(HOSTILE))
def test_hostile_map_files_are_refused_at_once_in_bounded_memory(
    tmp_path: Path, voxel_map: VoxelMap, hostile: str
) -> None:
    """Each file is refused with a MapFileError naming it and what is wrong, fast, and the
    process's peak memory grows by at most 20 MiB (measured: 0 to 9). Before the checks:
    the 800 GB keys raised a MemoryError, the extra array was loaded (+1026 MiB, 6.6 s),
    the deep JSON raised a RecursionError; the escaped quotes would take 1.5 hours to scan
    with the first pattern tried for JSON strings, 57 MiB with the second."""
    replace, deflated, function, refusal = HOSTILE[hostile]
    path = _zip(tmp_path / "hostile.map.npz", _members(voxel_map, **replace), deflated)
    got = measure_in_child(
        "from app.storage import map_file\nfrom app.storage.map_file import MapFileError",
        f"(map_file.{function}({str(path)!r}), 'loaded')[1]",
        "MapFileError",
    )
    assert got["outcome"].startswith(f"{path}: "), got
    assert re.search(refusal, got["outcome"]), got
    assert got["grew_mib"] < 20, got
    assert got["took_s"] < 5, got  # refused at once: reading 1 GiB took seconds


def test_the_hostile_files_are_well_formed_but_for_their_one_defect(
    tmp_path: Path, voxel_map: VoxelMap
) -> None:
    """The generators above spoil one entry of a good file each: the same file with the
    good entry loads (so the refusals come from the defects, not from the zip writing)."""
    path = _zip(tmp_path / "good.map.npz", _members(voxel_map))
    assert len(load_map(path)) == len(voxel_map)
    assert read_map_info(path) == {}


LIMITED_CHILD = """
import resource, sys
from trifuse.app.storage import map_file
with open("/proc/self/statm") as f:
    vsz = int(f.read().split()[0]) * resource.getpagesize()
resource.setrlimit(resource.RLIMIT_AS, (vsz + int(sys.argv[2]), resource.RLIM_INFINITY))
try:
    map_file.load_map(sys.argv[1])
    print("loaded")
except map_file.MapFileError as exc:
    print(exc)
"""


def test_a_map_too_large_for_the_memory_is_a_map_file_error(tmp_path: Path) -> None:
    """A well-formed map file of 3 million voxels (216 MB) loaded with 64 MiB of address
    space to spare: the MemoryError becomes a MapFileError naming the file; with room
    enough the same file loads (its zero keys then repeat: a MapFileError too, but after
    reading every array)."""
    n = 3_000_000
    arrays = VoxelMap(MapSettings(voxel_m=VOXEL)).arrays()
    content = {name: np.zeros((n, *arrays[name].shape[1:]), arrays[name].dtype) for name in arrays}
    content["path_stamp_s"], content["path_T_world_tof"] = np.zeros(0), np.zeros((0, 4, 4))
    content["format"] = np.array(MAP_FORMAT)
    content["settings"] = np.array(json.dumps({"voxel_m": VOXEL}))
    path = _npz(tmp_path / "big.map.npz", **content)
    assert path.stat().st_size > 200e6
    outcomes = {}
    for room in (64 << 20, 2 << 30):
        child = subprocess.run(
            [sys.executable, "-c", LIMITED_CHILD, str(path), str(room)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        )
        outcomes[room] = child.stdout.strip()
    assert outcomes[64 << 20] == f"{path}: too large to load in this machine's memory"
    assert outcomes[2 << 30] == f"{path}: malformed map file: map: voxel keys repeat"


def _claim(data: bytes, member: str, compress_size: int, file_size: int) -> bytes:
    """The zip ``data`` with ``member``'s sizes in the central directory (what zipfile
    reads) replaced."""
    out = bytearray(data)
    at = out.find(b"PK\x01\x02")
    while at >= 0:
        name_len = struct.unpack_from("<H", out, at + 28)[0]
        if out[at + 46 : at + 46 + name_len] == member.encode():
            struct.pack_into("<II", out, at + 20, compress_size, file_size)
            return bytes(out)
        at = out.find(b"PK\x01\x02", at + 46)
    raise AssertionError(f"no {member} in the zip")


def test_zip_entries_that_claim_more_than_the_file_holds_are_refused(
    tmp_path: Path, voxel_map: VoxelMap
) -> None:
    """keys.npy declares 1 GB in its header, and its zip entry claims 4 GB stored (the file
    has 35 kB), 4 GB unpacked from its real size, or its real size: each refused before
    anything is read."""
    big_keys = _npy_header((125_000_000,), "<i8") + bytes(64)
    data = _zip(tmp_path / "m.map.npz", _members(voxel_map, **{"keys.npy": big_keys})).read_bytes()
    for name, compress_size, file_size, message in [
        ("past-the-end", 4_000_000_000, 4_000_000_000, "the file ends inside keys"),
        ("unpacked", len(big_keys), 4_000_000_000, r"keys\.npy is not stored uncompressed"),
        ("as-is", len(big_keys), len(big_keys), r"keys declares \(125000000,\) int64"),
    ]:
        path = tmp_path / f"{name}.map.npz"
        path.write_bytes(_claim(data, "keys.npy", compress_size, file_size))
        with pytest.raises(MapFileError, match=message):
            load_map(path)
