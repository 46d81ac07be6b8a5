"""The thermal 3D map on disk: a PLY point cloud for other programs, and the map file
trifuse loads again (docs/FORMATS.md, "Thermal 3D map").

* :func:`write_ply`: the occupied voxels of a :class:`~fusion.voxel_map.VoxelMap` as a
  binary little-endian PLY 1.0 point cloud, one vertex per voxel centre: ``float x, y, z``
  (world frame, metres), ``uchar red, green, blue`` (the mean colour; grey 128 where no
  colour camera saw the voxel), ``float temperature`` and ``float temperature_max`` (the
  recency-weighted mean and the maximum, degrees Celsius, NaN where no thermal imager saw
  the voxel) and ``uint observations`` (TOF points that fell in the voxel), with
  ``comment`` lines naming trifuse, the voxel size and the units, and ``float quality``
  again the mean temperature, the one per-vertex scalar MeshLab reads (pymeshlab 2025.7
  drops other properties), -273.15 instead of NaN (MeshLab's Colorize by vertex quality
  aborts on a NaN). CloudCompare, MeshLab and Open3D read it (in CloudCompare a NaN
  scalar is "no value").
* :func:`save_map` / :func:`load_map`: every voxel (occupied or not) with all it knows,
  the head's path and the map's settings, as a NumPy ``.npz`` (no pickles) tagged
  ``format = trifuse-map/1``; :func:`load_map` checks it and raises :class:`MapFileError`
  for a malformed or foreign file.

Both are written atomically (:mod:`app.storage.atomic`) and never replace a file unless
asked to (``overwrite=True``).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import re
import zipfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from trifuse.app.storage.atomic import atomic_write_bytes
from trifuse.fusion.voxel_map import MapSettings, VoxelMap

MAP_FORMAT = "trifuse-map/1"
"""The format tag of a map file (its ``format`` entry)."""
MAP_SUFFIX = ".map.npz"
"""The map file's default suffix (``trifuse map``: the PLY path with this suffix)."""
KELVIN_AT_0_C = 273.15

PLY_VERTEX = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("temperature", "<f4"),
        ("temperature_max", "<f4"),
        ("observations", "<u4"),
        ("quality", "<f4"),
    ]
)
"""One PLY vertex as written (packed, little-endian): 31 bytes."""
_PLY_TYPES = {"<f4": "float", "u1": "uchar", "<u4": "uint"}
NO_QUALITY = np.float32(-KELVIN_AT_0_C)
"""``quality`` of a voxel no thermal imager saw: -273.15 (a NaN crashes MeshLab)."""
NO_COLOUR = 128
"""The grey (each channel) of a voxel no colour camera saw."""

_ARRAYS = (
    "keys",
    "centre",
    "hits",
    "logodds",
    "temp_mean",
    "temp_max",
    "temp_last",
    "temp_n",
    "last_seen",
    "rgb",
    "rgb_n",
    "path_stamp_s",
    "path_T_world_tof",
)
"""The arrays of a map file (:meth:`fusion.voxel_map.VoxelMap.arrays`)."""
_ENTRIES = ("format", "settings", "info", *_ARRAYS)
"""Every entry a map file may hold (``info`` may be absent)."""
_TEXT_CHARS = {"settings": 16_384, "info": 1_000_000}
"""The most characters of each text entry."""
MAX_JSON_DEPTH = 100
"""The deepest nesting of JSON arrays and objects in ``settings`` and ``info``."""
_NPY_HEADERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}
_JSON_STRING = re.compile(r'"(?:[^"\\]++|\\.)*+"?', re.DOTALL)
"""A JSON string, or an unterminated one up to the end of the text (JSON's parser stops
there). Every match starts at a quote and succeeds, and possessive quantifiers keep no
backtracking state, so the scan is linear in time and needs no memory per escape (a
pattern that needs the closing quote retries from every escaped quote of an unterminated
string: a million characters of ``\\"`` take 1.5 hours; one that backtracks, 57 MiB)."""


class MapFileError(ValueError):
    """A map file that cannot be loaded: not a map file, another format, or malformed.
    The message names the file and what was wrong."""


def ply_vertices(voxel_map: VoxelMap) -> np.ndarray:
    """(M,) :data:`PLY_VERTEX` records of the occupied voxels, in the map's order."""
    occ = voxel_map.occupied()
    out = np.zeros(int(occ.sum()), dtype=PLY_VERTEX)
    centre = voxel_map["centre"][occ]
    out["x"], out["y"], out["z"] = centre[:, 0], centre[:, 1], centre[:, 2]
    rgb = voxel_map["rgb"][occ]
    seen = np.isfinite(rgb).all(axis=1)
    colour = np.full(rgb.shape, NO_COLOUR, dtype=np.uint8)
    colour[seen] = np.clip(np.rint(rgb[seen]), 0, 255).astype(np.uint8)
    out["red"], out["green"], out["blue"] = colour[:, 0], colour[:, 1], colour[:, 2]
    out["temperature"] = voxel_map["temp_mean"][occ] - np.float32(KELVIN_AT_0_C)
    out["temperature_max"] = voxel_map["temp_max"][occ] - np.float32(KELVIN_AT_0_C)
    out["observations"] = voxel_map["hits"][occ]
    # MeshLab reads only this name as a scalar, and its Colorize by vertex quality aborts
    # on NaN (pymeshlab 2025.7): absolute zero stands for "no reading" there
    out["quality"] = np.where(np.isfinite(out["temperature"]), out["temperature"], NO_QUALITY)
    return out


def ply_bytes(voxel_map: VoxelMap, comments: tuple[str, ...] = ()) -> bytes:
    """The PLY file of :func:`write_ply` as bytes (``comments``: more comment lines, one
    line each)."""
    vertices = ply_vertices(voxel_map)
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment trifuse thermal 3D map: one vertex per occupied voxel (its centre)",
        f"comment voxel size {voxel_map.settings.voxel_m:g} m",
        "comment x y z: world frame, metres",
        "comment red green blue: mean colour, 0-255 (128 grey: no colour camera saw it)",
        "comment temperature temperature_max: mean and maximum, degrees Celsius "
        "(NaN: no thermal imager saw it)",
        "comment observations: TOF points that fell in the voxel",
    ]
    for c in comments:
        if "\n" in c or "\r" in c:
            raise ValueError(f"PLY comment: expected one line, got {c!r}")
        lines.append(f"comment {c}")
    lines.append(f"element vertex {len(vertices)}")
    for name in PLY_VERTEX.names:
        lines.append(f"property {_PLY_TYPES[PLY_VERTEX[name].str.lstrip('|')]} {name}")
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")
    return header + vertices.tobytes()


def write_ply(
    path: str | Path,
    voxel_map: VoxelMap,
    *,
    overwrite: bool = False,
    comments: tuple[str, ...] = (),
) -> Path:
    """Write the occupied voxels of ``voxel_map`` as a PLY point cloud (see the module
    docstring) atomically; FileExistsError if ``path`` exists and not ``overwrite``."""
    return atomic_write_bytes(path, ply_bytes(voxel_map, comments), overwrite)


def save_map(
    path: str | Path,
    voxel_map: VoxelMap,
    *,
    overwrite: bool = False,
    info: Mapping[str, object] | None = None,
) -> Path:
    """Write the whole map (every voxel, the path, the settings) as a map file
    (``trifuse-map/1``, see the module docstring) atomically.

    Args:
        path: the file (by convention ending in :data:`MAP_SUFFIX`).
        voxel_map: the map.
        overwrite: replace an existing file (else FileExistsError).
        info: what made the map (JSON-serialisable: recordings, pose source ...), kept
            as ``info`` (:func:`read_map_info`).
    """
    arrays = voxel_map.arrays()
    content: dict[str, np.ndarray] = {name: arrays[name] for name in _ARRAYS}
    content["format"] = np.array(MAP_FORMAT)
    content["settings"] = np.array(json.dumps(dataclasses.asdict(voxel_map.settings)))
    content["info"] = np.array(json.dumps(dict(info or {})))
    buf = io.BytesIO()
    np.savez(buf, **content)
    return atomic_write_bytes(path, buf.getvalue(), overwrite)


class _Archive:
    """A map file's zip archive whose entries are checked from their ``.npy`` headers
    before any is read: only the known entries, stored uncompressed (as :func:`save_map`
    writes them), each holding the bytes its header declares. Every array read is thus no
    larger than its share of the file."""

    def __init__(self, path: Path, zf: zipfile.ZipFile) -> None:
        self.path = path
        self.zf = zf
        size = path.stat().st_size
        self.entries: dict[str, zipfile.ZipInfo] = {}
        infos = zf.infolist()
        unknown = [i.filename for i in infos if i.filename.removesuffix(".npy") not in _ENTRIES]
        if unknown:
            raise MapFileError(
                f"{path}: not a trifuse map file: unknown entries {unknown[:5]} (a "
                f"{MAP_FORMAT} file holds {', '.join(_ENTRIES)}, as .npy)"
            )
        for info in infos:
            name = info.filename.removesuffix(".npy")
            if name in self.entries:
                raise MapFileError(f"{path}: malformed map file: {info.filename} appears twice")
            if info.compress_type != zipfile.ZIP_STORED or info.file_size != info.compress_size:
                raise MapFileError(
                    f"{path}: malformed map file: {info.filename} is not stored uncompressed "
                    "(as save_map writes it)"
                )
            if info.header_offset + info.compress_size > size:
                raise MapFileError(f"{path}: malformed map file: the file ends inside {name}")
            self.entries[name] = info
        if "format" not in self.entries:
            raise MapFileError(
                f"{path}: not a trifuse map file (no 'format' entry; expected {MAP_FORMAT!r})"
            )
        shape, dtype = self.header("format")
        short_text = shape == () and dtype.kind == "U" and dtype.itemsize <= 4 * len(MAP_FORMAT)
        fmt = str(self.read("format")) if short_text else f"{dtype} {shape}"
        if fmt != MAP_FORMAT:
            raise MapFileError(f"{path}: format {fmt:.40}, expected {MAP_FORMAT!r}")
        missing = [n for n in (*_ARRAYS, "settings") if n not in self.entries]
        if missing:
            raise MapFileError(f"{path}: malformed map file: no {', '.join(missing)}")

    def header(self, name: str) -> tuple[tuple[int, ...], np.dtype]:
        """The shape and dtype that entry ``name`` declares (its ``.npy`` header);
        MapFileError for Python objects (pickles), a header of another version, or an
        entry that holds fewer bytes than the array it declares."""
        info = self.entries[name]
        with self.zf.open(info) as f:
            version = np.lib.format.read_magic(f)
            if version not in _NPY_HEADERS:
                raise MapFileError(
                    f"{self.path}: malformed map file: {name} is a .npy of version {version}"
                )
            shape, _fortran, dtype = _NPY_HEADERS[version](f)
            start = f.tell()
        if dtype.hasobject:
            raise MapFileError(
                f"{self.path}: not a readable map file ({name} holds Python objects: pickles "
                "are never loaded)"
            )
        nbytes = math.prod(shape) * dtype.itemsize
        if start + nbytes > info.file_size:
            raise MapFileError(
                f"{self.path}: malformed map file: {name} declares {shape} {dtype} "
                f"({nbytes} bytes), but holds {info.file_size - start} bytes"
            )
        return shape, dtype

    def read(self, name: str) -> np.ndarray:
        """The array of entry ``name`` (after :meth:`header` checked it)."""
        with self.zf.open(self.entries[name]) as f:
            return np.lib.format.read_array(f, allow_pickle=False)

    def text(self, name: str) -> str:
        """The text entry ``name`` (``settings``, ``info``): a () str array of at most
        :data:`_TEXT_CHARS` characters."""
        shape, dtype = self.header(name)
        if shape != () or dtype.kind != "U":
            raise MapFileError(f"{self.path}: malformed map file: {name} is not a JSON text")
        if dtype.itemsize // 4 > _TEXT_CHARS[name]:
            raise MapFileError(
                f"{self.path}: malformed map file: {name} holds {dtype.itemsize // 4} "
                f"characters, more than {_TEXT_CHARS[name]}"
            )
        return str(self.read(name))

    def json_object(self, name: str) -> dict[str, object]:
        """The JSON object of the text entry ``name``, nested at most
        :data:`MAX_JSON_DEPTH` levels."""
        text = self.text(name)
        where = f"{self.path}: malformed map file: {name}"
        if _json_depth(text) > MAX_JSON_DEPTH:
            raise MapFileError(f"{where}: nested deeper than {MAX_JSON_DEPTH} levels")
        try:
            value = json.loads(text)
        except ValueError as exc:  # JSONDecodeError, an integer of too many digits
            raise MapFileError(f"{where}: {exc}") from None
        if not isinstance(value, dict):
            raise MapFileError(f"{where}: expected a JSON object, got {type(value).__name__}")
        return value


def _json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in JSON ``text`` (brackets in strings
    do not count), without parsing it (Python's parser recurses)."""
    codes = np.frombuffer(_JSON_STRING.sub("", text).encode("utf-8"), dtype=np.uint8)
    steps = np.isin(codes, (ord("["), ord("{"))).astype(np.int64)
    steps -= np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(steps).max(initial=0))


@contextmanager
def _archive(path: Path) -> Iterator[_Archive]:
    """The map file at ``path`` (:class:`_Archive`); every failure inside, a MemoryError
    included, becomes a MapFileError naming the file."""
    try:
        with zipfile.ZipFile(path) as zf:
            yield _Archive(path, zf)
    except MapFileError:
        raise
    except FileNotFoundError:
        raise MapFileError(f"{path}: no such map file") from None
    except IsADirectoryError:
        raise MapFileError(f"{path}: a directory, not a map file") from None
    except zipfile.BadZipFile as exc:
        raise MapFileError(
            f"{path}: not a readable map file (expected a .npz archive: {exc})"
        ) from None
    except MemoryError:
        raise MapFileError(f"{path}: too large to load in this machine's memory") from None
    except (ValueError, OSError, EOFError, KeyError, RecursionError) as exc:
        raise MapFileError(f"{path}: not a readable map file ({exc})") from None


def _settings(archive: _Archive) -> MapSettings:
    values = archive.json_object("settings")
    try:
        known = {f.name for f in dataclasses.fields(MapSettings)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise TypeError(f"unknown settings {unknown}")
        return MapSettings(**values)
    except (TypeError, ValueError) as exc:
        raise MapFileError(f"{archive.path}: malformed map file: settings: {exc}") from None


def _check_arrays(archive: _Archive, settings: MapSettings) -> None:
    """Check every array's declared shape and dtype (before any is read): numbers, N
    voxels (at most ``settings.max_voxels``) in every per-voxel array, P poses."""
    where = f"{archive.path}: malformed map file"
    headers = {name: archive.header(name) for name in _ARRAYS}
    for name, (_shape, dtype) in headers.items():
        if dtype.kind not in "fiu" or dtype.itemsize > 8:
            raise MapFileError(f"{where}: {name} holds {dtype}, not numbers")
    keys = headers["keys"][0]
    if len(keys) != 1 or headers["keys"][1].kind not in "iu":
        raise MapFileError(f"{where}: keys must be (N,) integers, got {keys}")
    n = keys[0]
    if n > settings.max_voxels:
        raise MapFileError(f"{where}: {n} voxels, more than max_voxels {settings.max_voxels}")
    for name, (shape, _dtype) in headers.items():
        if not name.startswith("path_") and shape not in ((n,), (n, 3)):
            raise MapFileError(f"{where}: {name} has shape {shape}, expected ({n},) or ({n}, 3)")
    stamps, poses = headers["path_stamp_s"][0], headers["path_T_world_tof"][0]
    if len(stamps) != 1 or poses != (stamps[0], 4, 4):
        raise MapFileError(
            f"{where}: path_stamp_s {stamps} and path_T_world_tof {poses} do not match "
            "(expected (P,) and (P, 4, 4))"
        )


def load_map(path: str | Path) -> VoxelMap:
    """The map saved by :func:`save_map`.

    Every entry's shape and type are checked from its header before any array is read
    (:class:`_Archive`), so a file never makes this allocate more than it holds.

    Raises:
        MapFileError: a missing file, not a .npz, another format, unknown, compressed or
            missing entries, arrays of the wrong shape or type, settings that do not make a
            :class:`MapSettings` (each within its bounds) or nest too deep, more voxels
            than ``max_voxels``, voxel keys that repeat or do not match the voxel centres,
            a file too large for the memory.
    """
    path = Path(path)
    with _archive(path) as archive:
        settings = _settings(archive)
        _check_arrays(archive, settings)
        arrays = {name: archive.read(name) for name in _ARRAYS}
        try:
            voxel_map = VoxelMap.from_arrays(settings, arrays)
        except ValueError as exc:
            raise MapFileError(f"{path}: malformed map file: {exc}") from None
        centre = voxel_map["centre"].astype(np.float64)
        keys = arrays["keys"].astype(np.int64)
        if len(centre) and not np.array_equal(voxel_map.keys_of(centre)[0], keys):
            raise MapFileError(
                f"{path}: malformed map file: the voxel keys do not match the centres"
            )
        return voxel_map


def read_map_info(path: str | Path) -> dict[str, object]:
    """What made the map (the ``info`` given to :func:`save_map`; {} if none). Reads only
    the ``format`` and ``info`` entries."""
    with _archive(Path(path)) as archive:
        return archive.json_object("info") if "info" in archive.entries else {}
