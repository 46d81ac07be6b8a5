"""The rig as ROS ``camera_info`` files and a URDF (issue 21; docs/FORMATS.md, "Rig formats").

:func:`export` writes

* ``<sensor>.yaml`` per sensor: the calibration file of ROS's ``camera_calibration_parsers``
  (what ``camera_info_manager`` loads from a ``camera_info_url`` and what
  ``camera_calibration``'s ``cameracalibrator`` saves), with the keys in the order that
  package writes them: ``image_width``, ``image_height``, ``camera_name`` (the sensor's
  name), ``camera_matrix`` (3 x 3 ``K``), ``distortion_model``, ``distortion_coefficients``
  (1 x N), ``rectification_matrix`` (3 x 3) and ``projection_matrix`` (3 x 4), each matrix as
  ``{rows, cols, data}`` with ``data`` in row-major order;
* ``<robot_name>.urdf``, the poses (camera_info has none), from
  :mod:`calib.rig_formats.urdf_format`: the root link ``rig`` is the rig frame and sensor
  ``s`` is link ``s_optical_frame`` (set the driver's ``frame_id`` to it).

Conventions: ROS's camera frames are optical frames (x right, y down, z forward) and its
pixel centres are at integer coordinates, both as trifuse's (docs/CONVENTIONS.md): the
numbers are copied, never shifted. ``distortion_model`` is ``plumb_bob`` with OpenCV's five
coefficients ``k1 k2 p1 p2 k3`` (a sensor with four gets ``k3 = 0``), or
``rational_polynomial`` with eight ``k1 k2 p1 p2 k3 k4 k5 k6`` when k4-k6 are not all zero.
A single camera's ``rectification_matrix`` is the identity and its ``projection_matrix`` is
``[K | 0]``, as the ``sensor_msgs/CameraInfo`` documentation says a monocular camera
normally has (``image_proc`` then undistorts into an image with the same ``K``); floats are
written with ``repr``, so they read back exactly.

:func:`import_` reads such files, including those ROS tools wrote (the rectification and
projection of a stereo calibration are reported in ``lost`` and ignored: trifuse keeps the
raw camera, ``camera_matrix`` and ``distortion_coefficients``). It refuses files without
poses unless ``allow_no_poses=True``: a rig whose sensors all sit at one point looks valid
and fuses every pair with no parallax correction, a wrong overlay nothing would flag.

Lost in a round trip: radiometry, range correction, uncertainty and the eyes (give
``eyes=`` to the import); the modality comes back from the sensor's name
(``calib.rig.modality_of_name``) or the ``modalities`` option.

The helpers :func:`eyes_from_option`, :func:`modality_for` and :func:`assemble_rig` are
shared with :mod:`calib.rig_formats.opencv_format`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any

import numpy as np
import yaml

from trifuse.calib.errors import RigError
from trifuse.calib.numbers import is_int, is_int_or_float
from trifuse.calib.rig import Rig, Sensor, modality_of_name
from trifuse.calib.rig_formats import Exported, Imported, urdf_format
from trifuse.calib.rig_formats.common import (
    ImportedCamera,
    assemble_rig,
    check_modalities_option,
    extras_lost,
    modality_for,
    sensor_name_for,
)
from trifuse.calib.yaml_text import YamlError, parse_yaml

CAMERA_INFO_KEYS = (
    "image_width",
    "image_height",
    "camera_name",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
    "rectification_matrix",
    "projection_matrix",
)
"""The keys of a camera_info YAML file, in the order ``camera_calibration_parsers`` writes
them (``camera_name`` and ``distortion_model`` may be missing when reading)."""
PLUMB_BOB = "plumb_bob"
RATIONAL_POLYNOMIAL = "rational_polynomial"
_MODEL_LENGTHS = {PLUMB_BOB: (0, 4, 5), RATIONAL_POLYNOMIAL: (8,)}
"""Distortion coefficients accepted per model (0: no distortion)."""
"""A valid sensor name (as ``calib.rig``: sensor names are file names too)."""
_IDENTITY_TOL = 1e-9
"""How close R must be to the identity and P to [K | 0] to count as a single camera's."""
_SKEW_TOL = 1e-9
"""Largest skew ``K[0][1]`` accepted, relative to fx (trifuse's cameras have none)."""


def _yaml_float(x: float) -> str:
    """``repr`` of a float as YAML 1.1 (PyYAML) and 1.2 (yaml-cpp) both read it back:
    ``1e-05`` would be a string to PyYAML, so it is written ``1.0e-05``."""
    text = repr(float(x) + 0.0)  # + 0.0: no "-0.0"
    if "e" in text and "." not in text:
        text = text.replace("e", ".0e")
    return text


def _yaml_string(text: str) -> str:
    """A plain scalar where YAML reads it back as the same string, else a quoted one."""
    try:
        plain_ok = yaml.safe_load(text) == text
    except yaml.YAMLError:
        plain_ok = False
    return text if plain_ok else json.dumps(text)


def _matrix(key: str, rows: int, cols: int, data: Sequence[float]) -> list[str]:
    """The YAML lines of a ``{rows, cols, data}`` block, ``data`` row-major."""
    return [
        f"{key}:",
        f"  rows: {rows}",
        f"  cols: {cols}",
        "  data: [" + ", ".join(_yaml_float(v) for v in data) + "]",
    ]


def ros_distortion(distortion: Sequence[float]) -> tuple[str, list[float]]:
    """(distortion_model, coefficients) for trifuse's OpenCV-order coefficients:
    ``rational_polynomial`` with 8 when k4-k6 are not all zero, else ``plumb_bob`` with 5
    (``k3 = 0`` added to four)."""
    coeffs = [float(c) for c in distortion]
    if len(coeffs) == 8 and any(coeffs[5:]):
        return RATIONAL_POLYNOMIAL, coeffs
    return PLUMB_BOB, (coeffs + [0.0] * 5)[:5]


def camera_info_yaml(sensor: Sensor) -> str:
    """``sensor``'s camera_info YAML (see the module docstring), ``camera_name`` = its name."""
    i = sensor.intrinsics
    model, coeffs = ros_distortion(i.distortion)
    K = i.K
    P = np.hstack([K, np.zeros((3, 1))])
    lines = [
        f"image_width: {int(sensor.width)}",
        f"image_height: {int(sensor.height)}",
        f"camera_name: {_yaml_string(sensor.name)}",
        *_matrix("camera_matrix", 3, 3, K.ravel()),
        f"distortion_model: {model}",
        *_matrix("distortion_coefficients", 1, len(coeffs), coeffs),
        *_matrix("rectification_matrix", 3, 3, np.eye(3).ravel()),
        *_matrix("projection_matrix", 3, 4, P.ravel()),
    ]
    return "\n".join(lines) + "\n"


def export(
    rig: Rig,
    *,
    robot_name: str = "trifuse_head",
    base_link: str | None = None,
    prefix: str = "",
    link_suffix: str = urdf_format.OPTICAL_SUFFIX,
) -> Exported:
    """The rig as ROS files: ``<sensor>.yaml`` per sensor and ``<robot_name>.urdf``.

    Args:
        rig: the rig.
        robot_name, base_link, prefix, link_suffix: the URDF's options
            (:func:`calib.rig_formats.urdf_format.export`).

    Returns:
        The files (relative path -> text) and what ROS's files cannot hold: radiometry,
        range correction and uncertainty where a sensor has them, the eyes, and the
        modality (kept only by the sensor's name).

    Raises:
        RigError: as the URDF export (names that are not link names).
    """
    files = {f"{name}.yaml": camera_info_yaml(s) for name, s in rig.sensors.items()}
    urdf = urdf_format.export(
        rig, robot_name=robot_name, base_link=base_link, prefix=prefix, link_suffix=link_suffix
    )
    files.update(urdf.files)
    lost = extras_lost(rig, "ROS camera_info has none")
    if rig.eyes:
        pairs = ", ".join(f"{n}=({e.color}, {e.thermal})" for n, e in rig.eyes.items())
        lost.append(f"eyes ({pairs}): ROS has no eye pairs; pass eyes= to the import")
    by_name = [n for n, s in rig.sensors.items() if modality_of_name(n) == s.modality]
    others = {n: s.modality for n, s in rig.sensors.items() if n not in by_name}
    note = "modality: camera_info has none"
    if by_name:
        note += f"; the import infers it from the name's prefix for {', '.join(by_name)}"
    if others:
        note += f"; pass modalities={others!r} to the import"
    lost.append(note)
    return Exported(files=files, lost=lost)


# -- import ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraInfo:
    """The contents of one camera_info YAML file.

    Attributes:
        camera_name: as written (a number as its text), or None when the file has none.
        width, height: image size in pixels.
        distortion_model: as written (``plumb_bob`` when the file has none).
        model_stated: whether the file has a ``distortion_model``.
        K: (3, 3) camera matrix; R: (3, 3) rectification; P: (3, 4) projection (pixels).
        D: the distortion coefficients.
    """

    camera_name: str | None
    width: int
    height: int
    distortion_model: str
    model_stated: bool
    K: np.ndarray
    D: tuple[float, ...]
    R: np.ndarray
    P: np.ndarray


def _number(value: Any, where: str) -> float:
    """``value`` as a finite float (bools refused), else RigError naming ``where``."""
    if not is_int_or_float(value):
        raise RigError(f"{where}: expected a number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:
        raise RigError(f"{where}: {str(value)[:20]}... is too large") from None
    if not math.isfinite(v):
        raise RigError(f"{where}: expected a finite number, got {value!r}")
    return v


def _ros_matrix(
    data: Mapping[str, Any], key: str, shape: tuple[int, int] | None, source: str
) -> np.ndarray:
    """A ``{rows, cols, data}`` block as a (rows, cols) array; RigError naming the file."""
    where = f"{source}: {key}"
    if key not in data:
        raise RigError(f"{where}: missing (camera_calibration_parsers requires it)")
    block = data[key]
    if not isinstance(block, Mapping):
        raise RigError(f"{where}: expected a mapping with rows, cols and data, got {block!r}")
    missing = [k for k in ("rows", "cols", "data") if k not in block]
    if missing:
        raise RigError(f"{where}: missing key(s) {missing}")
    rows, cols, values = block["rows"], block["cols"], block["data"]
    for label, n in (("rows", rows), ("cols", cols)):
        if not is_int(n) or n < 0 or n > 1000:
            raise RigError(f"{where}: {label}: expected a small non-negative integer, got {n!r}")
    if shape is not None and (rows, cols) != shape:
        raise RigError(f"{where}: expected {shape[0]} x {shape[1]}, got {rows} x {cols}")
    if values is None and rows * cols == 0:
        values = []
    if not isinstance(values, list) or len(values) != rows * cols:
        got = f"{len(values)} values" if isinstance(values, list) else repr(values)
        raise RigError(f"{where}: data: expected rows x cols = {rows * cols} numbers, got {got}")
    numbers = [_number(v, f"{where}: data[{i}]") for i, v in enumerate(values)]
    return np.array(numbers, dtype=np.float64).reshape(rows, cols)


def _size(data: Mapping[str, Any], key: str, source: str) -> int:
    """``data[key]`` as a positive integer (pixels), else RigError naming the file."""
    if key not in data:
        raise RigError(f"{source}: {key}: missing (camera_calibration_parsers requires it)")
    value = data[key]
    if not is_int(value) or value <= 0:
        raise RigError(f"{source}: {key}: expected a positive integer, got {value!r}")
    return value


def parse_camera_info(text: str, source: str) -> CameraInfo:
    """Read one camera_info YAML text as ``camera_calibration_parsers`` does, more strictly.

    Unknown keys are ignored (ROS ignores them). A missing ``distortion_model`` is
    ``plumb_bob`` (as ROS assumes); any model other than ``plumb_bob`` or
    ``rational_polynomial`` is refused (trifuse's cameras use OpenCV's radial-tangential
    model).

    Raises:
        RigError naming ``source`` and the key: not YAML, not a mapping, a key ROS
        requires missing, a matrix of the wrong shape or with ``rows * cols`` not the
        number of values, a value that is not a finite number, an unknown distortion
        model or a coefficient count the model does not have.
    """
    try:
        data = parse_yaml(text)
    except YamlError as exc:
        raise RigError(f"{source}: not valid YAML: {exc}") from None
    if not isinstance(data, Mapping):
        raise RigError(
            f"{source}: expected a camera_info mapping (image_width, camera_matrix, ...), "
            f"got {type(data).__name__}"
        )
    width = _size(data, "image_width", source)
    height = _size(data, "image_height", source)
    K = _ros_matrix(data, "camera_matrix", (3, 3), source)
    R = _ros_matrix(data, "rectification_matrix", (3, 3), source)
    P = _ros_matrix(data, "projection_matrix", (3, 4), source)
    D_block = _ros_matrix(data, "distortion_coefficients", None, source)
    model = data.get("distortion_model", PLUMB_BOB)
    if model not in _MODEL_LENGTHS:
        raise RigError(
            f"{source}: distortion_model: expected {PLUMB_BOB!r} or {RATIONAL_POLYNOMIAL!r} "
            f"(OpenCV's radial-tangential model, the one trifuse's cameras use), got {model!r}"
        )
    D = tuple(float(v) for v in D_block.ravel())
    if len(D) not in _MODEL_LENGTHS[model]:
        raise RigError(
            f"{source}: distortion_coefficients: {model} takes "
            f"{' or '.join(str(n) for n in _MODEL_LENGTHS[model] if n)} coefficients, "
            f"got {len(D)}"
        )
    name = data.get("camera_name")
    if name is not None:
        if not (isinstance(name, str) or is_int_or_float(name)):
            raise RigError(f"{source}: camera_name: expected a name, got {name!r}")
        name = str(name)
    stated = "distortion_model" in data
    return CameraInfo(name, width, height, model, stated, K, D, R, P)


def _camera_matrix_problem(K: np.ndarray) -> str | None:
    """Why ``K`` is not a pinhole camera matrix without skew, or None."""
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}"
    fixed = np.array([K[1, 0], K[2, 0], K[2, 1], K[2, 2] - 1.0])
    if not np.all(np.abs(fixed) <= 1e-12):
        return f"expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
    if abs(K[0, 1]) > _SKEW_TOL * K[0, 0]:
        return f"skew K[0][1] = {K[0, 1]!r}; trifuse's cameras have none"
    return None


def import_(
    files: Mapping[str, str],
    *,
    eyes: Mapping[str, Any] | None = None,
    modalities: Mapping[str, str] | None = None,
    reference: str | None = None,
    allow_no_poses: bool = False,
    prefix: str = "",
    link_suffix: str = urdf_format.OPTICAL_SUFFIX,
) -> Imported:
    """A rig from ROS files: camera_info YAMLs (``*.yaml``, ``*.yml``) and at most one URDF
    (``*.urdf``, or ``*.xml`` with a ``<robot>`` root; other ``.xml`` files, such as launch
    files, are ignored and listed in ``lost``) with the poses.

    Each YAML is one sensor, named by its ``camera_name`` (or, where that is not a valid
    sensor name, by the file's stem); its pose is that of link
    ``<prefix><sensor><link_suffix>`` (``<sensor>_optical_frame``) in the URDF. Sensors
    come in the order of the URDF's joints, else of ``files``.

    Args:
        files: relative path -> text.
        eyes: eye name -> (colour sensor, thermal sensor); camera_info has no eyes.
        modalities: sensor -> modality, for names that do not say it
            (``calib.rig.modality_of_name``) or to override them.
        reference: the reference sensor (the rig frame); default: the sensor at the URDF
            common frame's origin (the root link ``rig`` of an export), else the first TOF
            camera, else the first sensor.
        allow_no_poses: without a URDF, accept every sensor at the rig frame's origin
            (listed in ``lost``); refused by default (see the module docstring).
        prefix, link_suffix: the URDF's link names (as given to the export).

    Returns:
        The rig and what the files did not say.

    Raises:
        RigError naming the file: a malformed file (see :func:`parse_camera_info`,
        :func:`calib.rig_formats.urdf_format.joints_from_urdf`), a file that is neither
        YAML nor URDF, two URDFs, a sensor without its link, no poses without
        ``allow_no_poses``, bad options.
    """
    lost: list[str] = []
    infos: list[tuple[str, CameraInfo]] = []
    urdfs: list[str] = []
    for path, text in files.items():
        suffix = PurePosixPath(path).suffix.lower()
        if not isinstance(text, str):
            raise RigError(f"{path}: expected text, got {type(text).__name__}")
        if suffix in (".yaml", ".yml"):
            infos.append((path, parse_camera_info(text, path)))
        elif suffix == ".urdf":
            urdfs.append(path)
        elif suffix == ".xml":
            if urdf_format.is_urdf(text):
                urdfs.append(path)
            else:
                lost.append(f"{path}: not a URDF (no <robot> root element); ignored")
        else:
            raise RigError(
                f"{path}: expected camera_info files (.yaml, .yml) and at most one URDF "
                "(.urdf, or .xml with a <robot> root)"
            )
    if len(urdfs) > 1:
        raise RigError(f"{urdfs[1]}: a second URDF (after {urdfs[0]}); expected at most one")

    named: list[tuple[str, str, CameraInfo]] = []
    counts: dict[str | None, int] = {}
    for _, info in infos:
        counts[info.camera_name] = counts.get(info.camera_name, 0) + 1
    for path, info in infos:
        declared = info.camera_name if counts[info.camera_name] == 1 else None
        name, note = sensor_name_for(declared, path)
        if declared is None and info.camera_name is not None:
            note = (
                f"sensor name of {path}: camera_name {info.camera_name!r} is shared by "
                f"{counts[info.camera_name]} files; the file's stem {name!r} was used"
            )
        if note:
            lost.append(note)
        named.append((name, path, info))
    names = [n for n, _, _ in named]
    check_modalities_option(modalities, names)

    poses: dict[str, np.ndarray | None] = dict.fromkeys(names)
    if urdfs:
        source = urdfs[0]
        joints = urdf_format.joints_from_urdf(files[source], source)
        known = {j.child for j in joints} | {j.parent for j in joints}
        links = {n: urdf_format.sensor_link(n, prefix, link_suffix) for n in names}
        for n, path, _ in named:
            if links[n] not in known:
                raise RigError(
                    f"{source}: no joint places link {links[n]!r} of sensor {n!r} ({path})"
                )
        _, in_frame = urdf_format.common_frame_poses(joints, list(links.values()), source)
        poses = {n: in_frame[links[n]] for n in names}
        order = {j.child: i for i, j in enumerate(joints)}
        named.sort(key=lambda item: order[links[item[0]]] if links[item[0]] in order else -1)
    else:
        lost.append("poses: no URDF among the files")

    cameras: list[ImportedCamera] = []
    for name, path, info in named:
        problem = _camera_matrix_problem(info.K)
        if problem is not None:
            raise RigError(f"{path}: camera_matrix: {problem}")
        if info.K[0, 1] != 0.0:
            lost.append(f"skew of {name}: {path} has K[0][1] = {info.K[0, 1]!r}; dropped")
        if not info.model_stated:
            lost.append(f"distortion model of {name}: {path} has none; plumb_bob assumed (as ROS)")
        if not np.allclose(info.R, np.eye(3), rtol=0.0, atol=_IDENTITY_TOL):
            lost.append(
                f"rectification of {name}: {path}'s rectification_matrix is not the identity "
                "(a stereo pair's rectifying rotation); ignored: trifuse keeps the raw "
                "camera (camera_matrix, distortion_coefficients)"
            )
        P_mono = np.hstack([info.K, np.zeros((3, 1))])
        if not np.allclose(info.P, P_mono, rtol=0.0, atol=_IDENTITY_TOL):
            lost.append(
                f"projection of {name}: {path}'s projection_matrix is not [K | 0] (the "
                "rectified image's camera; a stereo pair's carries the baseline); ignored"
            )
        D = info.D if info.D else (0.0,) * 5
        if not info.D:
            lost.append(f"distortion of {name}: {path} has no coefficients; none assumed")
        cameras.append(
            ImportedCamera(
                name=name,
                source=path,
                modality=modality_for(name, path, modalities),
                image_size=(info.width, info.height),
                K=info.K,
                distortion=D,
                T_frame_sensor=poses[name],
            )
        )
    for cam in cameras:
        if modalities is None or cam.name not in modalities:
            lost.append(
                f"modality of {cam.name}: camera_info has none; {cam.modality} from the name"
            )
    return assemble_rig(
        cameras,
        reference=reference,
        eyes=eyes,
        allow_no_poses=allow_no_poses,
        format_name="ROS camera_info",
        lost=lost,
    )
