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
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from app.storage.atomic import atomic_write_bytes
from fusion.voxel_map import MapSettings, VoxelMap

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


def _open(path: Path) -> dict[str, np.ndarray]:
    """Every array of the .npz at ``path``, checked to be a trifuse map file."""
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise MapFileError(f"{path}: not a trifuse map file (expected a .npz archive)")
        with z:
            if "format" not in z.files:
                raise MapFileError(
                    f"{path}: not a trifuse map file (no 'format' entry; expected {MAP_FORMAT!r})"
                )
            fmt = z["format"]
            if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) != MAP_FORMAT:
                raise MapFileError(f"{path}: format {fmt!s:.40}, expected {MAP_FORMAT!r}")
            missing = [n for n in (*_ARRAYS, "settings") if n not in z.files]
            if missing:
                raise MapFileError(f"{path}: malformed map file: no {', '.join(missing)}")
            return {name: z[name] for name in z.files}
    except MapFileError:
        raise
    except FileNotFoundError:
        raise MapFileError(f"{path}: no such map file") from None
    except IsADirectoryError:
        raise MapFileError(f"{path}: a directory, not a map file") from None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise MapFileError(f"{path}: not a readable map file ({exc})") from None


def _settings(path: Path, text: np.ndarray) -> MapSettings:
    if text.shape != () or text.dtype.kind != "U":
        raise MapFileError(f"{path}: malformed map file: settings is not a JSON text")
    try:
        values = json.loads(str(text))
        if not isinstance(values, dict):
            raise TypeError(f"expected an object, got {type(values).__name__}")
        known = {f.name for f in dataclasses.fields(MapSettings)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise TypeError(f"unknown settings {unknown}")
        return MapSettings(**values)
    except (json.JSONDecodeError, TypeError, ValueError) as exc:
        raise MapFileError(f"{path}: malformed map file: settings: {exc}") from None


def load_map(path: str | Path) -> VoxelMap:
    """The map saved by :func:`save_map`.

    Raises:
        MapFileError: a missing file, not a .npz, another format, missing arrays, arrays
            of the wrong shape or type, settings that do not make a :class:`MapSettings`,
            voxel keys that repeat or do not match the voxel centres.
    """
    path = Path(path)
    content = _open(path)
    settings = _settings(path, content["settings"])
    arrays = {name: content[name] for name in _ARRAYS}
    for name, a in arrays.items():
        if a.dtype.kind not in "fiu":
            raise MapFileError(f"{path}: malformed map file: {name} holds {a.dtype}, not numbers")
    keys = arrays["keys"]
    if keys.ndim != 1 or keys.dtype.kind not in "iu":
        raise MapFileError(f"{path}: malformed map file: keys must be (N,) integers")
    stamps, poses = arrays["path_stamp_s"], arrays["path_T_world_tof"]
    if stamps.ndim != 1 or poses.shape != (len(stamps), 4, 4):
        raise MapFileError(
            f"{path}: malformed map file: path_stamp_s {stamps.shape} and path_T_world_tof "
            f"{poses.shape} do not match (expected (P,) and (P, 4, 4))"
        )
    try:
        voxel_map = VoxelMap.from_arrays(settings, arrays)
    except ValueError as exc:
        raise MapFileError(f"{path}: malformed map file: {exc}") from None
    centre = voxel_map["centre"].astype(np.float64)
    if len(centre) and not np.array_equal(voxel_map.keys_of(centre)[0], keys.astype(np.int64)):
        raise MapFileError(f"{path}: malformed map file: the voxel keys do not match the centres")
    return voxel_map


def read_map_info(path: str | Path) -> dict[str, object]:
    """What made the map (the ``info`` given to :func:`save_map`; {} if none)."""
    path = Path(path)
    content = _open(path)
    text = content.get("info")
    if text is None:
        return {}
    try:
        info = json.loads(str(text))
    except json.JSONDecodeError as exc:
        raise MapFileError(f"{path}: malformed map file: info: {exc}") from None
    if not isinstance(info, dict):
        raise MapFileError(f"{path}: malformed map file: info is not a JSON object")
    return info
