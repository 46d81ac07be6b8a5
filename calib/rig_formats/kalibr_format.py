"""The rig as a Kalibr camera chain (``camchain.yaml``), the file Kalibr's
``kalibr_calibrate_cameras`` writes and its ``kalibr_calibrate_imu_camera`` and many
visual-inertial pipelines read (docs/FORMATS.md, "Rig formats").

One top-level key per camera, ``cam0``, ``cam1``, ... and nothing else (Kalibr counts the
cameras as the number of top-level keys: ``CameraChainParameters.numCameras`` in
``kalibr_common/ConfigReader.py``). Each camera::

    cam1:
      T_cn_cnm1: [[...], [...], [...], [0.0, 0.0, 0.0, 1.0]]  # cam1..: see below
      cam_overlaps: [0, 2]
      camera_model: pinhole
      distortion_coeffs: [k1, k2, r1, r2]   # radtan: OpenCV's k1 k2 p1 p2
      distortion_model: radtan
      intrinsics: [fu, fv, pu, pv]          # fx, fy, cx, cy in pixels
      resolution: [width, height]           # pixels
      rostopic: /thermal_left/image_raw

``T_cn_cnm1`` of camera n > 0 maps points from camera n-1's frame into camera n's
(``T_{cn <- cn-1}``, metres; both OpenCV optical frames, like trifuse's sensor frames): Kalibr
writes the baseline of camera pair (n-1, n) as ``T_cB_cA`` with A = n-1, B = n
(``IccCalibrator.saveCamChainParametersYaml``: ``getResultBaseline(camNr-1, camNr)`` ->
``setExtrinsicsLastCamToHere``), and its maplab exporter derives it as
``T_cn_cnm1 = T_cn_imu * T_cnm1_imu.inverse()`` (``exporters/kalibr_maplab_config``). The
voxblox EuRoC camchain in ``tests/data/rig_formats/kalibr/`` shows the same on real data:
its cam1 ``T_cn_cnm1`` equals ``T_cam_imu(cam1) @ inv(T_cam_imu(cam0))`` to 1e-15.

So with trifuse's ``T_rig_<sensor>`` (CONVENTIONS.md): ``T_cn_cnm1 = rig.T(cn, cn-1) =
inv(T_rig_cn) @ T_rig_cn-1``, and back, ``T_rig_cn = T_rig_cn-1 @ inv(T_cn_cnm1)`` with
``T_rig_c0`` the identity (cam0 is the rig's reference sensor both ways).

What a camchain cannot hold (listed in ``Exported.lost``): k3 and the rational k4-k6 (Kalibr's
``radtan`` has four coefficients: the export drops them and says how far that moves the
sensor's farthest image corner, or refuses with ``strict=True``), the modality (the
sensor's name in the ``rostopic``, ``/<sensor>/image_raw``, gives it back where its prefix
says it: :func:`calib.rig.modality_of_name`), the eye pairs, a thermal imager's radiometry,
a TOF camera's range correction and the calibration's uncertainty.

Pure text in, text out: no files are read or written here.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml

from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import RigError
from trifuse.calib.numbers import finite_float, is_int
from trifuse.calib.rig import RIG_FORMAT, Eye, Rig, Sensor, modality_of_name, rig_from_dict
from trifuse.calib.rig_formats import Exported, Imported
from trifuse.calib.rig_formats.common import extras_lost
from trifuse.calib.transforms import invert, rigidity_problem
from trifuse.calib.yaml_text import YamlError, parse_yaml

CAMCHAIN_NAME = "camchain.yaml"
"""The file :func:`export` writes (Kalibr names its own ``<bag>-camchain.yaml``)."""

RADTAN_NAMES = ("k1", "k2", "p1", "p2")
"""Kalibr's four ``radtan`` coefficients in OpenCV's names (Kalibr's documentation calls
p1 and p2 r1 and r2)."""
DROPPED_NAMES = ("k3", "k4", "k5", "k6")
"""OpenCV's coefficients beyond the fourth, which a camchain cannot hold."""

_CAM_KEY_RE = re.compile(r"cam(0|[1-9][0-9]*)")
_ROS_TOPIC_RE = re.compile(r"(/[A-Za-z][A-Za-z0-9_]*)+")
"""A global ROS topic name: '/'-separated tokens of letters, digits and '_' (ROS 1 graph
resource names; a token starts with a letter)."""
_REQUIRED = ("camera_model", "intrinsics", "distortion_model", "resolution")
_IGNORED = {
    "cam_overlaps": "",  # derived: every camera overlaps every other on a trifuse head
    "T_cam_imu": "a trifuse rig has no IMU",
    "timeshift_cam_imu": "a trifuse rig has no IMU",
    "line_delay": "trifuse's cameras are global shutter",  # Kalibr's rolling-shutter model
}
_DISTORTION_COUNTS = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}
"""The distortion models Kalibr knows and their numbers of coefficients
(``CameraParameters.checkDistortion``)."""


# -- export -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class DistortionLoss:
    """What writing a sensor's distortion as Kalibr's four-coefficient ``radtan`` loses.

    Attributes:
        sensor: the sensor's name.
        dropped: the non-zero coefficients dropped, name (``k3`` ... ``k6``) -> value.
        corner_px: (u, v) the image corner (pixel centre) farthest from the principal point.
        shift_px: how far the dropped terms move that corner, pixels: the distance between
            where the full model and the four-coefficient one project the ray that the
            full model sends to the corner; NaN where the full model cannot be inverted
            there (the corner is beyond the distortion's one-to-one zone).
    """

    sensor: str
    dropped: dict[str, float]
    corner_px: tuple[float, float]
    shift_px: float

    def describe(self) -> str:
        """One sentence for ``lost`` (or the strict refusal)."""
        terms = ", ".join(f"{k} = {v:.6g}" for k, v in self.dropped.items())
        u, v = self.corner_px
        where = f"its farthest image corner ({u:g}, {v:g})"
        if np.isfinite(self.shift_px):
            moved = f"which moves {where} by {self.shift_px:.3g} px"
        else:
            moved = f"how far that moves {where} cannot be computed (beyond the model's fold)"
        return (
            f"distortion of {self.sensor}: Kalibr's radtan has only k1 k2 p1 p2; "
            f"{terms} dropped, {moved}"
        )


def radtan_loss(sensor: Sensor) -> DistortionLoss | None:
    """What writing ``sensor``'s distortion as Kalibr's ``radtan`` (k1 k2 p1 p2) loses, or
    None when its k3 ... k6 are all zero (or absent).

    The shift is measured at the image corner (pixel centre) farthest from the principal
    point: the corner is undistorted with the full model to its normalised position
    (x, y), which is distorted again with the full model and with the first four
    coefficients only (:meth:`Intrinsics.distort`); the distance between the two, scaled
    by fx and fy, is the shift in pixels.
    """
    intr = sensor.intrinsics
    extra = intr.distortion[4:]
    dropped = {n: float(c) for n, c in zip(DROPPED_NAMES, extra, strict=False) if c != 0.0}
    if not dropped:
        return None
    w, h = sensor.image_size
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    far = corners[int(np.argmax(np.hypot(corners[:, 0] - intr.cx, corners[:, 1] - intr.cy)))]
    xy = intr.normalized(far)
    four = Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy, intr.distortion[:4])
    d = intr.distort(xy) - four.distort(xy)
    shift = float(np.hypot(intr.fx * d[0], intr.fy * d[1]))
    return DistortionLoss(sensor.name, dropped, (float(far[0]), float(far[1])), shift)


def camchain_order(rig: Rig) -> list[str]:
    """The sensors in camchain order: the reference (cam0), then the others in rig order."""
    return [rig.reference] + [n for n in rig.names if n != rig.reference]


def default_topic(sensor: str) -> str:
    """The ``rostopic`` :func:`export` writes for a sensor: ``/<sensor>/image_raw``."""
    return f"/{sensor}/image_raw"


def export(rig: Rig, *, topics: Mapping[str, str] | None = None, strict: bool = False) -> Exported:
    """``rig`` as a Kalibr camchain: the file :data:`CAMCHAIN_NAME` and what it lost.

    Args:
        rig: the rig; its reference sensor becomes cam0, the others follow in rig order.
        topics: sensor -> ``rostopic`` (default ``/<sensor>/image_raw``, which keeps the
            sensor's name, and with it the modality where the name's prefix tells it).
        strict: refuse (ValueError naming the sensor, the dropped coefficients and the
            pixel shift) instead of dropping a non-zero k3 ... k6.

    Returns:
        ``Exported`` with ``files = {"camchain.yaml": text}``: keys sorted and short lists
        inline, as Kalibr's ``yaml.dump`` writes them, every number at full precision (a
        round trip through :func:`import_` reproduces the poses to 1e-12 m and the
        intrinsics exactly).

    Raises:
        ValueError: ``topics`` names a sensor the rig does not have or is not a string
            starting with ``/``; with ``strict``, a sensor's k3 ... k6 are not all zero.
    """
    topics = dict(topics or {})
    unknown = sorted(set(topics) - set(rig.names))
    if unknown:
        raise ValueError(f"topics: no sensor(s) {unknown} in the rig (sensors: {rig.names})")
    for name, topic in topics.items():
        if not isinstance(topic, str) or not topic.startswith("/") or len(topic) < 2:
            raise ValueError(f"topics: {name}: expected a ROS topic such as /a/b, got {topic!r}")

    order = camchain_order(rig)
    lost: list[str] = []
    losses = [loss for n in order if (loss := radtan_loss(rig[n])) is not None]
    if strict and losses:
        raise ValueError(
            "strict: "
            + "; ".join(loss.describe() for loss in losses)
            + " (without strict they are dropped and listed in lost)"
        )
    lost += [loss.describe() for loss in losses]

    data: dict[str, Any] = {}
    for i, name in enumerate(order):
        s = rig[name]
        intr = s.intrinsics
        topic = topics.get(name, default_topic(name))
        cam: dict[str, Any] = {
            "camera_model": "pinhole",
            "intrinsics": [float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy)],
            "distortion_model": "radtan",
            "distortion_coeffs": [float(c) for c in intr.distortion[:4]],
            "resolution": [int(s.image_size[0]), int(s.image_size[1])],
            "rostopic": topic,
            "cam_overlaps": [j for j in range(len(order)) if j != i],
        }
        if i > 0:
            T = rig.T(name, order[i - 1])  # T_{cn <- cn-1}
            T[3] = (0.0, 0.0, 0.0, 1.0)
            cam["T_cn_cnm1"] = [[float(x) for x in row] for row in T]
        data[f"cam{i}"] = cam
        lost += _sensor_losses(s, topic)
    lost += extras_lost(rig, "a camchain has none")

    kept = [n for n in order if _keeps_modality(rig[n], topics.get(n, default_topic(n)))]
    if kept:
        lost.append(
            "modality: a camchain has none; the sensor names in the rostopics give it back "
            f"({', '.join(f'{n}: {rig[n].modality}' for n in kept)})"
        )
    if rig.eyes:
        pairs = ", ".join(f"{e}: {p.color} + {p.thermal}" for e, p in rig.eyes.items())
        lost.append(f"eyes ({pairs}): a camchain has no eye pairs")
    text = yaml.safe_dump(data, default_flow_style=None, sort_keys=True)
    return Exported(files={CAMCHAIN_NAME: text}, lost=lost)


def _keeps_modality(s: Sensor, topic: str) -> bool:
    """Whether the sensor's name survives in ``topic`` and its prefix gives the modality."""
    return _first_element(topic) == s.name and modality_of_name(s.name) == s.modality


def _sensor_losses(s: Sensor, topic: str) -> list[str]:
    """What a camchain cannot say about ``s`` beyond its distortion."""
    lost = []
    if not _ROS_TOPIC_RE.fullmatch(topic):
        lost.append(
            f"rostopic of {s.name}: {topic} is not a valid ROS topic name (letters, digits "
            "and '_' between '/'), which Kalibr reads as text but a bag cannot hold; give "
            "topics to record under another"
        )
    named = _first_element(topic)
    if named != s.name:
        lost.append(
            f"name of {s.name}: its rostopic {topic} does not start with /{s.name}/; "
            "give it when importing (names / --names)"
        )
    if not _keeps_modality(s, topic):
        lost.append(
            f"modality of {s.name} ({s.modality}): a camchain has none and the name does "
            "not tell it; give it when importing (modalities / --modalities)"
        )
    return lost


# -- import -----------------------------------------------------------------------------------


def import_(
    files: Mapping[str, str],
    *,
    eyes: Mapping[str, Eye | tuple[str, str]] | None = None,
    names: Mapping[int, str] | None = None,
    modalities: Mapping[str, str] | None = None,
    reference: str | None = None,
) -> Imported:
    """A rig from a Kalibr camchain, and what the file did not say.

    Args:
        files: file name -> text; the camchain is the only file, else the only ``.yaml``
            / ``.yml`` one, else the only one of those whose name contains ``camchain``.
        eyes: eye -> (colour sensor, thermal sensor) (or :class:`calib.rig.Eye`); a
            camchain has none.
        names: camera index -> sensor name (e.g. ``{0: "ccd_left"}``); default: the first
            element of the camera's ``rostopic`` (``/thermal_left/image_raw`` ->
            ``thermal_left``).
        modalities: sensor name -> ``color``, ``thermal`` or ``tof``; default: from the
            name's prefix (:func:`calib.rig.modality_of_name`), else ``color`` (said in
            ``lost``).
        reference: the sensor whose frame is the rig frame (default: cam0's, the chain's
            base); the poses are re-expressed in its frame.

    Returns:
        ``Imported``: the rig (sensors in camchain order, cam0's pose the identity, each
        next one ``T_rig_cn = T_rig_cn-1 @ inv(T_cn_cnm1)``, metres; distortion as
        OpenCV's five coefficients k1 k2 p1 p2 0, ``none`` as five zeros) and the notes.

    Raises:
        RigError: not a camchain trifuse can use, naming the file and the key (e.g.
            ``camchain.yaml: cam1.distortion_model: 'equidistant' ...``), or options that
            do not fit it.
    """
    fname, text = _pick_file(files)
    try:
        data = parse_yaml(text)
    except YamlError as exc:
        raise RigError(f"{fname}: not valid YAML: {exc}") from None
    try:
        return _import(data, eyes, names, modalities, reference)
    except RigError as exc:
        raise RigError(f"{fname}: {exc}") from None


def _pick_file(files: Mapping[str, str]) -> tuple[str, str]:
    """(name, text) of the camchain among ``files``; RigError when there is none or it is
    ambiguous."""
    if len(files) == 1:
        return next(iter(files.items()))
    yamls = sorted(n for n in files if n.lower().endswith((".yaml", ".yml")))
    if len(yamls) == 1:
        return yamls[0], files[yamls[0]]
    chains = [n for n in yamls if "camchain" in n.lower()]
    if len(chains) == 1:
        return chains[0], files[chains[0]]
    if not yamls:
        raise RigError(f"no camchain: expected one .yaml file, got {sorted(files) or 'none'}")
    raise RigError(f"which camchain? {chains or yamls} (give the one file to import)")


def _import(
    data: Any,
    eyes: Mapping[str, Eye | tuple[str, str]] | None,
    names: Mapping[int, str] | None,
    modalities: Mapping[str, str] | None,
    reference: str | None,
) -> Imported:
    if not isinstance(data, Mapping) or not data:
        raise RigError(f"expected a mapping of cameras cam0, cam1, ..., got {type(data).__name__}")
    count = _camera_count(data)
    lost: list[str] = []
    names = dict(names or {})
    bad = sorted(i for i in names if not (isinstance(i, int) and 0 <= i < count))
    if bad:
        raise RigError(f"names: no camera {bad} in the camchain (cam0 .. cam{count - 1})")

    cams = [_camera(data[f"cam{i}"], i) for i in range(count)]
    sensor_names: list[str] = []
    from_topics = []
    for i, cam in enumerate(cams):
        if i in names:
            sensor_names.append(str(names[i]))
        elif cam.topic is not None:
            sensor_names.append(_topic_name(cam.topic, i))
            from_topics.append(f"cam{i} {sensor_names[-1]} <- {cam.topic}")
        else:
            sensor_names.append(f"cam{i}")
            lost.append(f"name of cam{i}: no rostopic; named cam{i} (give names / --names)")
        lost += [f"{key} of cam{i}: {why}" for key, why in cam.ignored]
    if from_topics:
        lost.append("sensor names from the rostopics: " + ", ".join(from_topics))
    twice = sorted({n for n in sensor_names if sensor_names.count(n) > 1})
    if twice:
        raise RigError(
            f"sensor name(s) {twice} given to more than one camera ({sensor_names}); "
            "give the names by camera index (names / --names 0=NAME,1=NAME)"
        )

    modalities = dict(modalities or {})
    unknown = sorted(set(modalities) - set(sensor_names))
    if unknown:
        raise RigError(f"modalities: no sensor(s) {unknown} (sensors: {sensor_names})")
    sensors: dict[str, Any] = {}
    from_names: list[str] = []
    T_rig = np.eye(4)
    for name, cam in zip(sensor_names, cams, strict=True):
        if cam.T_cn_cnm1 is not None:  # every camera but cam0 has one (_camera)
            T_rig = T_rig @ invert(cam.T_cn_cnm1)
        modality = modalities.get(name) or modality_of_name(name)
        if modality is None:
            modality = "color"
            lost.append(
                f"modality of {name}: a camchain has none and the name does not tell it; "
                "assumed color (give modalities / --modalities)"
            )
        elif name not in modalities:
            from_names.append(f"{name} {modality}")
        if modality == "thermal":
            lost.append(f"radiometry of {name}: a camchain has none; raw values read as kelvin")
        if modality == "tof":
            lost.append(f"range_correction of {name}: a camchain has none; distances as measured")
        sensors[name] = {
            "modality": modality,
            "image_size": list(cam.resolution),
            "intrinsics": dict(zip(("fx", "fy", "cx", "cy"), cam.intrinsics, strict=True)),
            "distortion": list(cam.distortion),
            "T_rig_sensor": T_rig.tolist(),
        }

    if from_names:
        lost.append("modalities (a camchain has none) from the names: " + ", ".join(from_names))
    ref = sensor_names[0]
    if reference is not None and reference != ref:
        if reference not in sensors:
            raise RigError(f"reference: no sensor {reference!r} (sensors: {sensor_names})")
        T_ref_rig = invert(np.asarray(sensors[reference]["T_rig_sensor"]))
        for s in sensors.values():
            s["T_rig_sensor"] = (T_ref_rig @ np.asarray(s["T_rig_sensor"])).tolist()
        sensors[reference]["T_rig_sensor"] = np.eye(4).tolist()
        ref = reference
    eye_map = {
        str(e): {"color": p.color, "thermal": p.thermal} if isinstance(p, Eye) else _eye_pair(e, p)
        for e, p in (eyes or {}).items()
    }
    if not eye_map:
        lost.append(
            "eyes: a camchain has none; the rig has no eye pairs, which the fusion needs "
            "(give eyes / --eyes left=COLOR:THERMAL,right=COLOR:THERMAL)"
        )
    rig = rig_from_dict(
        {"format": RIG_FORMAT, "reference": ref, "eyes": eye_map, "sensors": sensors}
    )
    return Imported(rig=rig, lost=lost)


def _eye_pair(eye: Any, pair: Any) -> dict[str, str]:
    if not (isinstance(pair, tuple | list) and len(pair) == 2):
        raise RigError(f"eyes.{eye}: expected (colour sensor, thermal sensor), got {pair!r}")
    return {"color": str(pair[0]), "thermal": str(pair[1])}


def _camera_count(data: Mapping[Any, Any]) -> int:
    """The number of cameras: the top-level keys must be exactly cam0 .. cam<N-1>."""
    indices = []
    for key in data:
        m = _CAM_KEY_RE.fullmatch(key) if isinstance(key, str) else None
        if m is None:
            raise RigError(
                f"key {key!r}: expected only cam0, cam1, ... at the top level of a camchain"
            )
        indices.append(int(m.group(1)))
    missing = sorted(set(range(len(indices))) - set(indices))
    if missing:
        raise RigError(f"cam{missing[0]}: missing (cameras: {sorted(map(str, data))})")
    return len(indices)


@dataclass(frozen=True)
class _Camera:
    """One camera of a camchain, checked."""

    intrinsics: tuple[float, float, float, float]
    distortion: tuple[float, ...]
    resolution: tuple[int, int]
    topic: str | None
    T_cn_cnm1: np.ndarray | None
    ignored: list[tuple[str, str]]


def _camera(raw: Any, i: int) -> _Camera:
    """Check camera ``i``'s mapping; RigError naming ``cam<i>.<key>``."""
    at = f"cam{i}"
    if not isinstance(raw, Mapping):
        raise RigError(f"{at}: expected a mapping, got {type(raw).__name__}")
    missing = [k for k in (*_REQUIRED, *(("T_cn_cnm1",) if i else ())) if k not in raw]
    if missing:
        raise RigError(f"{at}: missing key(s) {missing}")

    model = raw["camera_model"]
    if model != "pinhole":
        raise RigError(
            f"{at}.camera_model: {model!r} cannot be imported: trifuse's cameras are pinhole "
            "with radial-tangential distortion (Kalibr's pinhole-radtan)"
        )
    intr = _numbers(raw["intrinsics"], 4, f"{at}.intrinsics", "[fu, fv, pu, pv]")
    if intr[0] <= 0 or intr[1] <= 0:
        raise RigError(f"{at}.intrinsics: focal lengths must be positive, got {list(intr)}")

    dist_model = raw["distortion_model"]
    if dist_model not in ("radtan", "none"):
        known = dist_model in _DISTORTION_COUNTS
        raise RigError(
            f"{at}.distortion_model: {dist_model!r} cannot be imported: trifuse's lens model "
            "is radial-tangential (OpenCV's k1 k2 p1 p2 [k3 ...]); "
            + (
                "calibrate the camera with Kalibr's pinhole-radtan model"
                if known
                else f"Kalibr's models are {sorted(_DISTORTION_COUNTS)}"
            )
        )
    if dist_model == "radtan":
        dist = (*_numbers(raw.get("distortion_coeffs"), 4, f"{at}.distortion_coeffs",
                          "[k1, k2, r1, r2]"), 0.0)  # fmt: skip
    else:
        coeffs = raw.get("distortion_coeffs", [])
        if coeffs not in ([], None):
            raise RigError(
                f"{at}.distortion_coeffs: distortion_model 'none' takes none, got {coeffs!r}"
            )
        dist = (0.0,) * 5

    res = raw["resolution"]
    if not (
        isinstance(res, list | tuple) and len(res) == 2 and all(is_int(v) and v > 0 for v in res)
    ):
        raise RigError(f"{at}.resolution: expected [width, height] in pixels, got {res!r}")

    topic = raw.get("rostopic")
    if topic is not None and not (isinstance(topic, str) and topic.strip("/")):
        raise RigError(
            f"{at}.rostopic: expected a ROS topic such as /cam0/image_raw, got {topic!r}"
        )

    T = None
    if i > 0:
        T = _matrix(raw["T_cn_cnm1"], f"{at}.T_cn_cnm1")
    ignored = []
    known_keys = {*_REQUIRED, "distortion_coeffs", "rostopic", *(("T_cn_cnm1",) if i else ())}
    for key in raw:
        if key in known_keys:
            continue
        if key == "T_cn_cnm1":  # on cam0
            ignored.append((key, "ignored (cam0 is the chain's base)"))
            continue
        if key in _IGNORED:
            if _IGNORED[key]:
                ignored.append((str(key), f"ignored ({_IGNORED[key]})"))
        else:
            ignored.append((str(key), "not a key of Kalibr's camchain; ignored"))
    return _Camera(
        intrinsics=(intr[0], intr[1], intr[2], intr[3]),
        distortion=tuple(dist),
        resolution=(res[0], res[1]),
        topic=topic,
        T_cn_cnm1=T,
        ignored=ignored,
    )


def _numbers(value: Any, n: int, at: str, shape: str) -> tuple[float, ...]:
    if not isinstance(value, list | tuple) or len(value) != n:
        raise RigError(f"{at}: expected {n} numbers {shape}, got {value!r}")
    out = tuple(finite_float(v) for v in value)
    if any(v is None for v in out):
        raise RigError(f"{at}: expected {n} finite numbers {shape}, got {value!r}")
    return out  # type: ignore[return-value]


def _matrix(value: Any, at: str) -> np.ndarray:
    rows = value if isinstance(value, list | tuple) else None
    if rows is None or len(rows) != 4 or not all(isinstance(r, list | tuple) for r in rows):
        raise RigError(f"{at}: expected a 4x4 list of numbers, got {value!r}")
    T = np.array([_numbers(r, 4, at, "per row") for r in rows])
    problem = rigidity_problem(T)
    if problem is not None:
        raise RigError(f"{at}: not a rigid transform: {problem}")
    return T


def _first_element(topic: str) -> str:
    return topic.strip("/").split("/")[0]


def _topic_name(topic: str, i: int) -> str:
    name = _first_element(topic)
    if not name:
        raise RigError(f"cam{i}.rostopic: no name in {topic!r}")
    return name


__all__ = [
    "CAMCHAIN_NAME",
    "DROPPED_NAMES",
    "RADTAN_NAMES",
    "DistortionLoss",
    "camchain_order",
    "default_topic",
    "export",
    "import_",
    "radtan_loss",
]
