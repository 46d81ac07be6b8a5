"""The rig as OpenCV ``FileStorage`` YAML files (issue 21; docs/FORMATS.md, "Rig formats").

:func:`export` writes, with ``cv2.FileStorage`` itself (in memory, nothing on disk):

* ``<sensor>.yml`` per sensor, the layout of OpenCV's own calibration sample
  (``samples/cpp/calibration.cpp``): ``image_width``, ``image_height``, ``camera_matrix``
  (3 x 3 ``!!opencv-matrix``, pixels), ``distortion_coefficients`` (1 x N in OpenCV's order
  ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``, N = 4, 5 or 8 as the rig has it), plus ``modality`` and
  the extrinsics ``R`` (3 x 3) and ``T`` (3 x 1, metres) in ``cv2.stereoCalibrate``'s
  convention with the reference sensor as the first camera: a point ``X`` in the reference
  sensor's frame is ``R @ X + T`` in this sensor's, i.e. ``[R | T]`` = ``T_sensor_reference``
  (the reference sensor's own file has R = I, T = 0). That is what ``stereoRectify``,
  ``projectPoints(X, rvec=Rodrigues(R), tvec=T, ...)`` and most OpenCV code expect;
* ``rig.yml``: ``reference``, ``sensors`` (the names in rig order, one ``<name>.yml``
  each) and ``eyes`` (a sequence of ``{name, color, thermal}``).

Frames and pixels are OpenCV's, as trifuse's (docs/CONVENTIONS.md): the numbers are
copied. FileStorage writes doubles with 17 significant digits, so they read back exactly.
A sensor may not be called ``rig`` (its file would be ``rig.yml``).

:func:`import_` reads such files back, and also plain files from OpenCV's calibration
sample (unknown keys such as ``avg_reprojection_error`` are ignored) when the options say
what they lack. Lost: radiometry, range correction and uncertainty. Text is parsed with
``cv2.FileStorage`` (YAML, XML or JSON, as OpenCV detects it) once
:mod:`calib.rig_formats.filestorage_text` has found it cannot crash it (nesting, size);
matrices are checked for their size and element type before OpenCV allocates them.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import PurePosixPath
from typing import Any

import cv2
import numpy as np

from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.rig_formats import Exported, Imported
from trifuse.calib.rig_formats.common import (
    ImportedCamera,
    assemble_rig,
    check_modalities_option,
    extras_lost,
    eyes_from_option,
    modality_for,
    sensor_name_for,
)
from trifuse.calib.rig_formats.filestorage_text import check_filestorage_text
from trifuse.calib.transforms import invert, make_T, rigidity_problem

INDEX_FILE = "rig.yml"
"""The file that lists the sensors, the reference and the eyes."""
SENSOR_SUFFIX = ".yml"
_MAX_MATRIX_SIDE = 16
"""Largest rows or cols of a matrix read (checked before OpenCV allocates it)."""
_MATRIX_TYPES = ("d", "f")
"""A matrix's element types read (``dt``): OpenCV would saturate 1333.0 to 255 as ``u``
or read one element as many with ``3d``."""
_CV_PARSE_RE = re.compile(r"\((\d+)\): (.*?)'?$")
"""OpenCV's parse errors end ``... in function '<text>(<line>): <reason>'``."""
_READ = cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY
_WRITE = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML


# -- export ---------------------------------------------------------------------------------


def _writer() -> cv2.FileStorage:
    """A FileStorage writing YAML to memory (``releaseAndGetString`` gives the text)."""
    return cv2.FileStorage("rig.yml", _WRITE)


def sensor_yaml(sensor: Sensor, T_sensor_reference: np.ndarray, reference: str) -> str:
    """One sensor's FileStorage YAML (see the module docstring).

    Args:
        sensor: the sensor.
        T_sensor_reference: (4, 4) maps points from the reference sensor's frame into
            this sensor's (metres): stereoCalibrate's ``R``, ``T``.
        reference: the reference sensor's name (for the file's comment).
    """
    i = sensor.intrinsics
    fs = _writer()
    fs.writeComment(f"trifuse rig sensor {sensor.name!r} ({sensor.modality}); OpenCV camera")
    fs.writeComment("frame (x right, y down, z forward), pixels; R, T as cv2.stereoCalibrate's")
    fs.writeComment(f"with {reference!r} as the first camera: x_this = R x_{reference} + T (m)")
    fs.write("modality", sensor.modality)
    fs.write("image_width", int(sensor.width))
    fs.write("image_height", int(sensor.height))
    fs.write("camera_matrix", i.K)
    fs.write("distortion_coefficients", np.asarray(i.distortion, dtype=np.float64).reshape(1, -1))
    fs.write("R", np.ascontiguousarray(T_sensor_reference[:3, :3]))
    fs.write("T", np.ascontiguousarray(T_sensor_reference[:3, 3:4]))
    return fs.releaseAndGetString()


def index_yaml(rig: Rig) -> str:
    """``rig.yml``: the reference, the sensors in rig order and the eyes."""
    fs = _writer()
    fs.writeComment("trifuse rig (OpenCV FileStorage): one <sensor>.yml per sensor; the rig")
    fs.writeComment("frame is the reference sensor's (R = I, T = 0 in its file)")
    fs.write("reference", rig.reference)
    fs.startWriteStruct("sensors", cv2.FILE_NODE_SEQ)
    for name in rig.sensors:
        fs.write("", name)
    fs.endWriteStruct()
    fs.startWriteStruct("eyes", cv2.FILE_NODE_SEQ)
    for eye_name, eye in rig.eyes.items():
        fs.startWriteStruct("", cv2.FILE_NODE_MAP)
        fs.write("name", eye_name)
        fs.write("color", eye.color)
        fs.write("thermal", eye.thermal)
        fs.endWriteStruct()
    fs.endWriteStruct()
    return fs.releaseAndGetString()


def export(rig: Rig) -> Exported:
    """The rig as OpenCV FileStorage files: ``rig.yml`` and ``<sensor>.yml`` per sensor.

    Returns:
        The files (relative path -> text) and what they cannot hold (radiometry, range
        correction, uncertainty where a sensor has them).

    Raises:
        RigError: a sensor named ``rig``, or a name that FileStorage would read back as
            something else (``true``, ``null``: OpenCV writes them unquoted).
    """
    if INDEX_FILE.removesuffix(SENSOR_SUFFIX) in rig.sensors:
        raise RigError(f"OpenCV export: a sensor named 'rig' would overwrite {INDEX_FILE}")
    files = {INDEX_FILE: index_yaml(rig)}
    for name, sensor in rig.sensors.items():
        T = np.eye(4) if name == rig.reference else rig.T(name, rig.reference)
        files[name + SENSOR_SUFFIX] = sensor_yaml(sensor, T, rig.reference)
    try:  # FileStorage writes "true", "null" unquoted: they read back as other values
        back = _read_index(files[INDEX_FILE], INDEX_FILE)
    except RigError:
        back = None
    want = (
        rig.reference,
        list(rig.sensors),
        {n: (e.color, e.thermal) for n, e in rig.eyes.items()},
    )
    if back != want:
        names = [*rig.sensors, *rig.eyes]
        raise RigError(
            f"OpenCV export: some of the names {names} would not read back from FileStorage "
            "(OpenCV writes true, false and null unquoted): rename them"
        )
    return Exported(files=files, lost=extras_lost(rig, "the OpenCV files have none"))


# -- import ---------------------------------------------------------------------------------


def _open(text: str, source: str) -> cv2.FileStorage:
    """``text`` as a FileStorage to read; RigError naming ``source`` for text that could
    harm OpenCV's parser (checked first, :func:`check_filestorage_text`) or that OpenCV
    refuses."""
    check_filestorage_text(text, source)
    try:
        fs = cv2.FileStorage(text, _READ)
    except (cv2.error, SystemError) as exc:  # OpenCV's parse errors surface as SystemError
        raise RigError(f"{source}: not an OpenCV FileStorage file: {_cv_message(exc)}") from None
    if not fs.isOpened() or not fs.root().isMap():
        raise RigError(f"{source}: not an OpenCV FileStorage file with a top-level mapping")
    return fs


def _cv_message(exc: BaseException) -> str:
    """The useful part of an OpenCV exception (the cause of a SystemError): ``line N:
    reason`` for a parse error, else the text after ``error:`` (without OpenCV's source
    path, and without the start of the text it quotes as a file name)."""
    cause = exc.__cause__ if exc.__cause__ is not None else exc
    text = " ".join(str(cause).split())
    parsed = _CV_PARSE_RE.search(text)
    if parsed:
        return f"line {parsed.group(1)}: {parsed.group(2)}"
    found = text.split(" error: ", 1)
    return (found[1] if len(found) == 2 else text)[:200] or type(cause).__name__


def _string(node: cv2.FileNode, source: str, key: str) -> str:
    """A string node's text, else RigError naming the file and key."""
    if not node.isString():
        raise RigError(f"{source}: {key}: expected a name, got {_describe(node)}")
    return node.string()


def _describe(node: cv2.FileNode) -> str:
    """What a node holds, for error messages."""
    if node.empty() or node.isNone():
        return "nothing"
    if node.isInt() or node.isReal():
        return f"the number {node.real()!r}"
    if node.isSeq():
        return "a sequence"
    if node.isMap():
        return "a mapping"
    return "another kind of value"


def _integer(fs: cv2.FileStorage, key: str, source: str) -> int:
    """``key`` as a positive integer, else RigError naming the file and key."""
    node = fs.getNode(key)
    if node.empty():
        raise RigError(f"{source}: {key}: missing")
    if not node.isInt() or node.real() <= 0:
        raise RigError(f"{source}: {key}: expected a positive integer, got {_describe(node)}")
    return int(node.real())


def _matrix(
    fs: cv2.FileStorage, key: str, source: str, shapes: tuple[tuple[int, int], ...] | None
) -> np.ndarray | None:
    """An ``!!opencv-matrix`` as a float64 array, None when the key is missing.

    ``shapes`` are the accepted (rows, cols); None accepts any up to the size limit.
    RigError naming the file and key for anything else."""
    node = fs.getNode(key)
    if node.empty():
        return None
    where = f"{source}: {key}"
    if not node.isMap():
        raise RigError(f"{where}: expected an !!opencv-matrix, got {_describe(node)}")
    dims = []
    for side in ("rows", "cols"):
        n = node.getNode(side)
        if not n.isInt() or not 0 < n.real() <= _MAX_MATRIX_SIDE:
            raise RigError(
                f"{where}: {side}: expected an integer from 1 to {_MAX_MATRIX_SIDE}, "
                f"got {_describe(n)}"
            )
        dims.append(int(n.real()))
    if shapes is not None and tuple(dims) not in shapes:
        wanted = " or ".join(f"{r} x {c}" for r, c in shapes)
        raise RigError(f"{where}: expected {wanted}, got {dims[0]} x {dims[1]}")
    dt = node.getNode("dt")
    if not dt.isString() or dt.string() not in _MATRIX_TYPES:
        raise RigError(
            f"{where}: dt: expected one of {list(_MATRIX_TYPES)} (doubles or floats), got "
            f"{dt.string() if dt.isString() else _describe(dt)!r}"
        )
    try:
        mat = node.mat()
    except (cv2.error, SystemError) as exc:
        raise RigError(f"{where}: not a valid matrix: {_cv_message(exc)}") from None
    if mat is None:
        raise RigError(f"{where}: not a valid matrix")
    mat = np.asarray(mat, dtype=np.float64).reshape(dims)
    if not np.all(np.isfinite(mat)):
        raise RigError(f"{where}: expected finite numbers, got {mat.tolist()}")
    return mat


def _read_sensor(
    text: str, source: str, name: str, modalities: Mapping[str, str] | None, lost: list[str]
) -> ImportedCamera:
    """One sensor's file as an :class:`ImportedCamera`, its pose in the reference's frame
    (``inv([R | T])``) or None without R and T; a modality taken from the name is noted
    in ``lost``."""
    fs = _open(text, source)
    width = _integer(fs, "image_width", source)
    height = _integer(fs, "image_height", source)
    K = _matrix(fs, "camera_matrix", source, ((3, 3),))
    if K is None:
        raise RigError(f"{source}: camera_matrix: missing")
    fixed = np.array([K[0, 1], K[1, 0], K[2, 0], K[2, 1], K[2, 2] - 1.0])
    if not np.all(np.abs(fixed) <= 1e-12):
        raise RigError(
            f"{source}: camera_matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no "
            f"skew), got {K.tolist()}"
        )
    D = _matrix(fs, "distortion_coefficients", source, None)
    if D is None:
        raise RigError(f"{source}: distortion_coefficients: missing")
    if 1 not in D.shape:
        raise RigError(f"{source}: distortion_coefficients: expected one row or one column")
    R = _matrix(fs, "R", source, ((3, 3),))
    t = _matrix(fs, "T", source, ((3, 1), (1, 3)))
    if (R is None) != (t is None):
        raise RigError(f"{source}: expected both R and T (the pose) or neither")
    pose = None
    if R is not None and t is not None:
        T_sensor_reference = make_T(R, t.reshape(3))
        problem = rigidity_problem(T_sensor_reference)
        if problem is not None:
            raise RigError(f"{source}: R: not a rotation: {problem}")
        pose = invert(T_sensor_reference)
    stated_node = fs.getNode("modality")
    stated = None if stated_node.empty() else _string(stated_node, source, "modality")
    if stated is None and (modalities is None or name not in modalities):
        lost.append(f"modality of {name}: {source} has none; taken from the name")
    return ImportedCamera(
        name=name,
        source=source,
        modality=modality_for(name, source, modalities, stated),
        image_size=(width, height),
        K=K,
        distortion=tuple(float(v) for v in D.ravel()),
        T_frame_sensor=pose,
    )


def _read_index(text: str, source: str) -> tuple[str | None, list[str], dict[str, Any]]:
    """``rig.yml``: (reference or None, sensor names, eyes as eye -> (color, thermal))."""
    fs = _open(text, source)
    ref_node = fs.getNode("reference")
    reference = None if ref_node.empty() else _string(ref_node, source, "reference")
    seq = fs.getNode("sensors")
    if seq.empty() or not seq.isSeq() or seq.size() == 0:
        raise RigError(f"{source}: sensors: expected a sequence of sensor names")
    names = [_string(seq.at(k), source, f"sensors[{k}]") for k in range(seq.size())]
    eyes: dict[str, Any] = {}
    eyes_node = fs.getNode("eyes")
    if not eyes_node.empty() and not eyes_node.isNone():
        if not eyes_node.isSeq():
            raise RigError(f"{source}: eyes: expected a sequence of {{name, color, thermal}}")
        for k in range(eyes_node.size()):
            eye = eyes_node.at(k)
            if not eye.isMap():
                raise RigError(f"{source}: eyes[{k}]: expected {{name, color, thermal}}")
            parts = [
                _string(eye.getNode(f), source, f"eyes[{k}].{f}")
                for f in ("name", "color", "thermal")
            ]
            if parts[0] in eyes:
                raise RigError(f"{source}: eyes[{k}]: eye {parts[0]!r} is listed twice")
            eyes[parts[0]] = (parts[1], parts[2])
    return reference, names, eyes


def import_(
    files: Mapping[str, str],
    *,
    eyes: Mapping[str, Any] | None = None,
    modalities: Mapping[str, str] | None = None,
    reference: str | None = None,
    allow_no_poses: bool = False,
) -> Imported:
    """A rig from OpenCV FileStorage files.

    With ``rig.yml`` (in any folder; its sensors' files are beside it) the sensors, their
    order, the reference and the eyes come from it, and every other file must be one of
    its sensors'. Without it, every file is a sensor named after the file's stem, in the
    order of ``files``.

    Args:
        files: relative path -> text.
        eyes: eye name -> (colour sensor, thermal sensor), replacing ``rig.yml``'s.
        modalities: sensor -> modality, replacing the files' (``modality``) and the
            name's prefix.
        reference: the reference sensor, replacing ``rig.yml``'s; default as
            :func:`calib.rig_formats.ros_format.assemble_rig`.
        allow_no_poses: accept files without ``R`` and ``T`` (the sensor is then put at
            the rig frame's origin, listed in ``lost``); refused by default, see
            :mod:`calib.rig_formats.ros_format`.

    Raises:
        RigError naming the file and key: text OpenCV cannot read, a missing or malformed
        key, a sensor of ``rig.yml`` without its file or a file not in ``rig.yml``, a
        missing pose without ``allow_no_poses``, bad options.
    """
    lost: list[str] = []
    eyes_source = "option eyes"
    index_paths = [p for p in files if PurePosixPath(p).name == INDEX_FILE]
    if len(index_paths) > 1:
        raise RigError(f"{index_paths[1]}: a second {INDEX_FILE} (after {index_paths[0]})")
    entries: list[tuple[str, str]] = []  # (sensor name, path)
    if index_paths:
        index_path = index_paths[0]
        listed_ref, names, listed_eyes = _read_index(files[index_path], index_path)
        folder = PurePosixPath(index_path).parent
        for name in names:
            path = str(folder / (name + SENSOR_SUFFIX))
            if path not in files:
                raise RigError(f"{index_path}: sensor {name!r}: its file {path} is missing")
            entries.append((name, path))
        extra = sorted(set(files) - {index_path} - {p for _, p in entries})
        if extra:
            raise RigError(f"{extra[0]}: not a sensor of {index_path} (sensors: {names})")
        if listed_ref is not None and listed_ref not in names:
            raise RigError(f"{index_path}: reference: {listed_ref!r} is not among its sensors")
        reference = reference if reference is not None else listed_ref
        if eyes is None:
            eyes, eyes_source = listed_eyes, f"{index_path}: eyes"
    else:
        for path in files:
            name, _ = sensor_name_for(None, path)
            entries.append((name, path))
        lost.append(f"reference, sensor order and eyes: no {INDEX_FILE} among the files")
    check_modalities_option(modalities, [n for n, _ in entries])
    eyes_from_option(eyes)  # RigError for a malformed option before reading the sensors
    cameras = [_read_sensor(files[path], path, name, modalities, lost) for name, path in entries]
    return assemble_rig(
        cameras,
        reference=reference,
        eyes=eyes,
        allow_no_poses=allow_no_poses,
        format_name="OpenCV FileStorage",
        lost=lost,
        eyes_source=eyes_source,
    )
