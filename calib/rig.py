"""The rig: named sensors with intrinsics and poses, and the rig file (``trifuse-rig/1``).

The rig frame is the frame of the reference sensor (the TOF camera on the default head).
Each sensor stores ``T_rig_sensor``, its pose in the rig frame (4x4, metres); any pair
is derived with ``rig.T(dst, src)``.

This module parses and produces the rig file's *text* (YAML); reading and writing files is
the app's job (``app.storage.rigfile``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal, get_args

import numpy as np
import yaml

from trifuse.calib.camera import COEFFICIENT_NAMES, DISTORTION_LENGTHS, Intrinsics, physical_problem
from trifuse.calib.errors import RigError
from trifuse.calib.numbers import check_finite, is_int
from trifuse.calib.parameter_covariance import (
    DISTORTION_PARAMETERS,
    POSE_PARAMETERS,
    ParameterCovariance,
    split_name,
)
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.range_correction import RangeCorrection
from trifuse.calib.transforms import invert, rigidity_problem, rotation_from_rvec
from trifuse.calib.yaml_text import YamlError, parse_yaml

Modality = Literal["color", "thermal", "tof"]
MODALITIES: tuple[str, ...] = get_args(Modality)
RIG_FORMAT = "trifuse-rig/1"

MODALITY_PREFIXES: tuple[tuple[str, Modality], ...] = (
    ("ccd", "color"),
    ("color", "color"),
    ("rgb", "color"),
    ("thermal", "thermal"),
    ("lwir", "thermal"),
    ("tof", "tof"),
    ("depth", "tof"),
)
"""Name prefixes (case-insensitive) that give a sensor's modality where nothing says it."""


def modality_of_name(sensor: str) -> Modality | None:
    """Modality of a sensor from its name prefix (:data:`MODALITY_PREFIXES`), or None.

    ``ccd*``/``color*``/``rgb*`` -> color, ``thermal*``/``lwir*`` -> thermal,
    ``tof*``/``depth*`` -> tof (case-insensitive).
    """
    lower = sensor.lower()
    return next((m for prefix, m in MODALITY_PREFIXES if lower.startswith(prefix)), None)


_TOP_KEYS = {"format", "reference", "eyes", "sensors"}
MAX_IMAGE_PIXELS = 50_000_000
"""Largest sensor image a rig may describe (width x height): 50 megapixels."""
MIN_IMAGE_SIDE = 8
"""Smallest width and height of a sensor image a rig may describe, pixels."""
_SENSOR_REQUIRED = ("modality", "image_size", "intrinsics", "distortion", "T_rig_sensor")
_SENSOR_OPTIONAL = ("uncertainty", "range_correction", "radiometry")
_INTRINSIC_KEYS = ("fx", "fy", "cx", "cy")
_SENSOR_NAME_RE = re.compile(r"[A-Za-z0-9._-]+")
"""Sensor names are file names too (capture directories name images after them)."""


@dataclass
class Sensor:
    """One imager of the head.

    Attributes:
        name: sensor id, e.g. ``ccd_left``.
        modality: ``color``, ``thermal`` or ``tof``.
        image_size: (width, height) in pixels.
        intrinsics: focal lengths, principal point (pixels) and distortion.
        T_rig_sensor: (4, 4) float64 pose of the sensor in the rig frame, metres.
        uncertainty: the rig calibration's 1-sigma block (a plain YAML-compatible
            mapping), or None.
        range_correction: a TOF camera's range correction, or None.
        radiometry: a thermal imager's raw -> kelvin model, or None.
    """

    name: str
    modality: Modality
    image_size: tuple[int, int]
    intrinsics: Intrinsics
    T_rig_sensor: np.ndarray
    uncertainty: dict[str, Any] | None = None
    range_correction: RangeCorrection | None = None
    radiometry: Radiometry | None = None

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sensor):
            return NotImplemented
        return (
            self.name == other.name
            and self.modality == other.modality
            and self.image_size == other.image_size
            and self.intrinsics == other.intrinsics
            and np.array_equal(self.T_rig_sensor, other.T_rig_sensor)
            and self.uncertainty == other.uncertainty
            and self.range_correction == other.range_correction
            and self.radiometry == other.radiometry
        )


@dataclass(frozen=True)
class Eye:
    """One eye of the stereo display: a colour camera and a thermal imager."""

    color: str
    thermal: str


@dataclass
class Rig:
    """A set of named sensors, the reference sensor and the eye pairs."""

    sensors: dict[str, Sensor]
    reference: str
    eyes: dict[str, Eye] = field(default_factory=dict)
    covariance: ParameterCovariance | None = None
    """The joint covariance of the sensors' parameters (calib.parameter_covariance), or None."""

    def __post_init__(self) -> None:
        if self.reference not in self.sensors:
            raise RigError(
                f"reference: sensor {self.reference!r} is not in the rig "
                f"(sensors: {sorted(self.sensors)})"
            )
        for eye_name, eye in self.eyes.items():
            for role, wanted in (("color", "color"), ("thermal", "thermal")):
                sid = getattr(eye, role)
                if sid not in self.sensors:
                    raise RigError(f"eyes.{eye_name}.{role}: unknown sensor {sid!r}")
                if self.sensors[sid].modality != wanted:
                    raise RigError(
                        f"eyes.{eye_name}.{role}: sensor {sid!r} has modality "
                        f"{self.sensors[sid].modality!r}, expected {wanted!r}"
                    )
        for n in self.covariance.names if self.covariance is not None else ():
            sensor, param = split_name(n)
            if sensor not in self.sensors:
                raise RigError(f"covariance: parameter {n!r} of unknown sensor {sensor!r}")
            if sensor == self.reference and param in POSE_PARAMETERS:
                raise RigError(
                    f"covariance: parameter {n!r}: the reference sensor's pose defines the "
                    "rig frame and has no uncertainty"
                )

    def __getitem__(self, name: str) -> Sensor:
        try:
            return self.sensors[name]
        except KeyError:
            known = sorted(self.sensors)
            raise KeyError(f"no sensor {name!r} in the rig (sensors: {known})") from None

    def __contains__(self, name: object) -> bool:
        return name in self.sensors

    @property
    def names(self) -> list[str]:
        """Sensor names in file order."""
        return list(self.sensors)

    def by_modality(self, modality: str) -> list[str]:
        """Names of the sensors of one modality, in file order."""
        return [n for n, s in self.sensors.items() if s.modality == modality]

    def T(self, dst: str, src: str) -> np.ndarray:
        """``T_dst_src`` (4, 4): maps points from sensor ``src``'s frame into ``dst``'s."""
        return invert(self[dst].T_rig_sensor) @ self[src].T_rig_sensor

    def with_sensor(self, sensor: Sensor) -> Rig:
        """A copy of the rig with ``sensor`` in place of the rig's sensor of that name.

        The sensor order, the reference and the eyes are kept (and checked again, e.g. an
        eye's modalities); the other sensors are shared with this rig, not copied. KeyError
        when the rig has no sensor of that name.
        """
        old = self[sensor.name]  # KeyError naming the rig's sensors
        moved = old.intrinsics != sensor.intrinsics or not np.array_equal(
            old.T_rig_sensor, sensor.T_rig_sensor
        )
        covariance = None if moved else self.covariance  # it described the old geometry
        return replace(self, sensors={**self.sensors, sensor.name: sensor}, covariance=covariance)

    def perturbed(self, covariance: ParameterCovariance, delta: np.ndarray) -> Rig:
        """A copy with the parameters of ``covariance`` moved by ``delta`` (p,), in its
        names' order and units (calib.parameter_covariance): a rotation about the sensor's
        own axes on the right of its pose, a shift of its position in the rig frame, added
        intrinsics (distortion lengthened to 5 or 8 coefficients if needed). The copy's
        moved sensors have no ``uncertainty`` and the copy no covariance."""
        sensors = dict(self.sensors)
        for name, moves in covariance.moves(delta).items():
            sensors[name] = _moved_sensor(self[name], moves)
        return replace(self, sensors=sensors, covariance=None)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Rig):
            return NotImplemented
        return (
            self.reference == other.reference
            and self.eyes == other.eyes
            and list(self.sensors) == list(other.sensors)
            and all(self.sensors[k] == other.sensors[k] for k in self.sensors)
            and self.covariance == other.covariance
        )


def _moved_sensor(sensor: Sensor, moves: Mapping[str, float]) -> Sensor:
    """A copy of ``sensor`` with its parameters moved (:meth:`Rig.perturbed`)."""
    T = sensor.T_rig_sensor.copy()
    T[:3, :3] = T[:3, :3] @ rotation_from_rvec([moves.get(k, 0.0) for k in ("rx", "ry", "rz")])
    T[:3, 3] += [moves.get(k, 0.0) for k in ("tx", "ty", "tz")]
    intr = moved_intrinsics(sensor.intrinsics, moves)
    return replace(sensor, intrinsics=intr, T_rig_sensor=T, uncertainty=None)


def moved_intrinsics(intrinsics: Intrinsics, moves: Mapping[str, float]) -> Intrinsics:
    """``intrinsics`` with ``fx fy cx cy k1 ... k6`` (names of ``moves``, others ignored)
    moved by the given amounts; the distortion lengthened to 5 or 8 coefficients if needed."""
    i = intrinsics
    coeffs = [k for k in DISTORTION_PARAMETERS if k in moves]
    needed = max([DISTORTION_PARAMETERS.index(k) + 1 for k in coeffs], default=0)
    length = next(n for n in (len(i.distortion), 5, 8) if n >= needed)
    dist = np.zeros(length)
    dist[: len(i.distortion)] = i.distortion
    for k in coeffs:
        dist[DISTORTION_PARAMETERS.index(k)] += moves[k]
    return Intrinsics(
        i.fx + moves.get("fx", 0.0),
        i.fy + moves.get("fy", 0.0),
        i.cx + moves.get("cx", 0.0),
        i.cy + moves.get("cy", 0.0),
        tuple(dist),
    )


# -- parsing ---------------------------------------------------------------------------


def _where(sensor: str | None, fieldname: str) -> str:
    return f"sensor {sensor!r}: field {fieldname!r}" if sensor else f"field {fieldname!r}"


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise RigError(f"{where}: expected a mapping, got {type(value).__name__}")
    return value


def _number(value: Any, where: str) -> float:
    return check_finite(value, where, RigError)


def _check_keys(
    data: Mapping[str, Any], required: tuple[str, ...], optional: tuple[str, ...], where: str
) -> None:
    missing = [k for k in required if k not in data]
    if missing:
        raise RigError(f"{where}: missing key(s) {missing}")
    unknown = sorted(set(data) - set(required) - set(optional), key=str)
    if unknown:
        raise RigError(
            f"{where}: unknown key(s) {unknown} (allowed: {list(required) + list(optional)})"
        )


def _plain(value: Any, where: str) -> Any:
    """Check that an optional block holds only plain YAML values (maps, lists, numbers)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v, f"{where}[]") for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise RigError(f"{where}: unsupported value {value!r}")


def _check_image_size(name: str, size: tuple[int, int]) -> None:
    """RigError unless both sides are at least MIN_IMAGE_SIDE and the image has at most
    MAX_IMAGE_PIXELS."""
    shown = f"{size[0]}x{size[1]}"
    shown = shown if len(shown) <= 24 else shown[:21] + "..."
    if min(size) < MIN_IMAGE_SIDE:
        raise RigError(
            f"{_where(name, 'image_size')}: {shown}; expected at least {MIN_IMAGE_SIDE} pixels "
            "each way"
        )
    if size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise RigError(
            f"{_where(name, 'image_size')}: {shown} is {size[0] * size[1] // 1_000_000} "
            f"megapixels; expected at most {MAX_IMAGE_PIXELS // 1_000_000} (every per-frame "
            "buffer of the fusion and the simulator is that large)"
        )


def _check_intrinsics(name: str, intrinsics: Intrinsics, size: tuple[int, int]) -> None:
    """RigError naming the field, its value and the bound unless the intrinsics are
    physical for that image size (:func:`calib.camera.physical_problem`)."""
    problem = physical_problem(intrinsics, size)
    if problem is not None:
        parameter, why = problem
        field = "distortion" if parameter in COEFFICIENT_NAMES else f"intrinsics.{parameter}"
        raise RigError(f"{_where(name, field)}: {why}")


def check_physical(sensor: Sensor) -> None:
    """RigError naming the sensor, the field, its value and the bound unless the sensor's
    image size (MIN_IMAGE_SIDE each way, at most MAX_IMAGE_PIXELS) and intrinsics
    (:func:`calib.camera.physical_problem`) are a real camera's.

    Every rig file and imported rig is checked so (:func:`sensor_from_dict`); a rig that a
    calibration computes is not refused for them (calib.diagnosis judges Zhang's results
    and excludes a sensor with the reason).
    """
    _check_image_size(sensor.name, sensor.image_size)
    _check_intrinsics(sensor.name, sensor.intrinsics, sensor.image_size)


def sensor_from_dict(name: str, data: Any) -> Sensor:
    """Build a :class:`Sensor` from its rig-file mapping; raise RigError naming the field."""
    d = _mapping(data, f"sensor {name!r}")
    _check_keys(d, _SENSOR_REQUIRED, _SENSOR_OPTIONAL, f"sensor {name!r}")

    modality = d["modality"]
    if modality not in MODALITIES:
        raise RigError(
            f"{_where(name, 'modality')}: expected one of {list(MODALITIES)}, got {modality!r}"
        )

    size = d["image_size"]
    if (
        not isinstance(size, list | tuple)
        or len(size) != 2
        or not all(is_int(s) and s > 0 for s in size)
    ):
        raise RigError(
            f"{_where(name, 'image_size')}: expected [width, height] as two positive "
            f"integers, got {size!r}"
        )
    image_size = (size[0], size[1])
    _check_image_size(name, image_size)

    intr = _mapping(d["intrinsics"], _where(name, "intrinsics"))
    _check_keys(intr, _INTRINSIC_KEYS, (), _where(name, "intrinsics"))
    vals = {k: _number(intr[k], _where(name, f"intrinsics.{k}")) for k in _INTRINSIC_KEYS}
    for k in ("fx", "fy"):
        if vals[k] <= 0:
            raise RigError(
                f"{_where(name, f'intrinsics.{k}')}: focal length must be positive, got {vals[k]}"
            )

    dist = d["distortion"]
    if not isinstance(dist, list | tuple) or len(dist) not in DISTORTION_LENGTHS:
        raise RigError(
            f"{_where(name, 'distortion')}: expected a list of 4, 5 or 8 numbers "
            f"(k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {dist!r}"
        )
    dist_vals = tuple(_number(c, _where(name, "distortion")) for c in dist)
    intrinsics = Intrinsics(vals["fx"], vals["fy"], vals["cx"], vals["cy"], dist_vals)
    _check_intrinsics(name, intrinsics, image_size)

    T_raw = d["T_rig_sensor"]
    if not (
        isinstance(T_raw, list | tuple)
        and len(T_raw) == 4
        and all(isinstance(row, list | tuple) and len(row) == 4 for row in T_raw)
    ):
        raise RigError(
            f"{_where(name, 'T_rig_sensor')}: expected a 4x4 list of numbers, got {T_raw!r}"
        )
    T = np.array([[_number(x, _where(name, "T_rig_sensor")) for x in row] for row in T_raw])
    problem = rigidity_problem(T)
    if problem is not None:
        raise RigError(f"{_where(name, 'T_rig_sensor')}: not a rigid transform: {problem}")

    extras = {
        k: _plain(_mapping(d[k], _where(name, k)), _where(name, k))
        if d.get(k) is not None
        else None
        for k in _SENSOR_OPTIONAL
    }
    return Sensor(
        name,
        modality,
        image_size,
        intrinsics,
        T,
        uncertainty=extras["uncertainty"],
        range_correction=_range_correction(name, modality, image_size, extras["range_correction"]),
        radiometry=_radiometry(name, modality, extras["radiometry"]),
    )


def _range_correction(
    name: str, modality: str, size: tuple[int, int], block: Mapping[str, Any] | None
) -> RangeCorrection | None:
    """A TOF camera's ``range_correction`` block as its model (RigError naming the field)."""
    if block is None:
        return None
    if modality != "tof":
        raise RigError(f"{_where(name, 'range_correction')}: only a TOF camera has one")
    try:
        return RangeCorrection.from_dict(block, size)
    except ValueError as exc:
        raise RigError(f"sensor {name!r}: {exc}") from None


def _radiometry(name: str, modality: str, block: Mapping[str, Any] | None) -> Radiometry | None:
    """A thermal imager's ``radiometry`` block as its model (RigError naming the field)."""
    if block is None:
        return None
    if modality != "thermal":
        raise RigError(f"{_where(name, 'radiometry')}: only a thermal imager has one")
    try:
        return Radiometry.from_dict(block, "radiometry")
    except ValueError as exc:
        raise RigError(f"sensor {name!r}: {exc}") from None


def rig_from_dict(data: Any) -> Rig:
    """Build a :class:`Rig` from the parsed rig file; raise RigError on any defect."""
    d = _mapping(data, "rig file")
    _check_keys(d, ("format", "reference", "sensors"), ("eyes", "covariance"), "rig file")
    if d["format"] != RIG_FORMAT:
        raise RigError(f"field 'format': expected {RIG_FORMAT!r}, got {d['format']!r}")
    sensors_raw = _mapping(d["sensors"], "field 'sensors'")
    if not sensors_raw:
        raise RigError("field 'sensors': the rig has no sensors")
    sensors: dict[str, Sensor] = {}
    for n, s in sensors_raw.items():
        name = str(n)
        if not _SENSOR_NAME_RE.fullmatch(name) or name.endswith("_distance"):
            raise RigError(
                f"field 'sensors': sensor name {name!r}: expected letters, digits, '.', '_' or "
                "'-' (it names image files), not ending in '_distance'"
            )
        if name in sensors:
            raise RigError(f"field 'sensors': sensor {name!r} is listed twice")
        sensors[name] = sensor_from_dict(name, s)

    reference = d["reference"]
    if not isinstance(reference, str):
        raise RigError(f"field 'reference': expected a sensor name, got {reference!r}")
    if reference not in sensors:
        raise RigError(
            f"field 'reference': sensor {reference!r} is not in the rig "
            f"(sensors: {sorted(sensors)})"
        )
    if not np.allclose(sensors[reference].T_rig_sensor, np.eye(4), atol=1e-9):
        raise RigError(
            f"{_where(reference, 'T_rig_sensor')}: the reference sensor defines the "
            "rig frame, so its pose must be the identity"
        )

    eyes: dict[str, Eye] = {}
    eyes_raw = d.get("eyes")
    eyes_raw = {} if eyes_raw is None else _mapping(eyes_raw, "field 'eyes'")
    for eye_name, eye_raw in eyes_raw.items():
        e = _mapping(eye_raw, f"field 'eyes.{eye_name}'")
        _check_keys(e, ("color", "thermal"), (), f"field 'eyes.{eye_name}'")
        eyes[str(eye_name)] = Eye(str(e["color"]), str(e["thermal"]))
    covariance = None
    if d.get("covariance") is not None:
        try:
            covariance = ParameterCovariance.from_dict(d["covariance"])
        except ValueError as exc:
            raise RigError(f"field 'covariance': {exc}") from None
    return Rig(sensors=sensors, reference=str(reference), eyes=eyes, covariance=covariance)


def _floats(a: np.ndarray) -> list[Any]:
    return np.asarray(a, dtype=np.float64).tolist()


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    """The rig as plain data in rig-file layout (inverse of :func:`rig_from_dict`)."""
    sensors: dict[str, Any] = {}
    for name, s in rig.sensors.items():
        i = s.intrinsics
        entry: dict[str, Any] = {
            "modality": s.modality,
            "image_size": [int(s.image_size[0]), int(s.image_size[1])],
            "intrinsics": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
            "distortion": [float(c) for c in i.distortion],
            "T_rig_sensor": _floats(s.T_rig_sensor),
        }
        if s.uncertainty is not None:
            entry["uncertainty"] = s.uncertainty
        if s.range_correction is not None:
            entry["range_correction"] = s.range_correction.to_dict()
        if s.radiometry is not None:
            entry["radiometry"] = s.radiometry.to_dict()
        sensors[name] = entry
    out = {
        "format": RIG_FORMAT,
        "reference": rig.reference,
        "eyes": {n: {"color": e.color, "thermal": e.thermal} for n, e in rig.eyes.items()},
        "sensors": sensors,
    }
    if rig.covariance is not None:
        out["covariance"] = rig.covariance.to_dict()
    return out


def rig_from_yaml(text: str) -> Rig:
    """Parse rig-file text; raise RigError for YAML errors and invalid content."""
    try:
        data = parse_yaml(text)
    except YamlError as exc:
        raise RigError(f"rig file is not valid YAML: {exc}") from None
    return rig_from_dict(data)


def rig_to_yaml(rig: Rig) -> str:
    """Rig-file text of ``rig``; floats are written with full precision (exact round trip)."""
    return yaml.safe_dump(rig_to_dict(rig), sort_keys=False, default_flow_style=None, width=100)
