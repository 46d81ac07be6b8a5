"""What the rig formats share (calib.rig_formats): the parts no format holds
(:func:`extras_lost`), and, for the importers of ROS and OpenCV files, the way from the
cameras a file describes (:class:`ImportedCamera`) to a rig (:func:`assemble_rig`: names,
modalities, the reference, the eyes)."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Any

import numpy as np

from trifuse.calib.errors import RigError
from trifuse.calib.numbers import is_int
from trifuse.calib.rig import (
    MODALITIES,
    Eye,
    Modality,
    Rig,
    Sensor,
    modality_of_name,
    sensor_from_dict,
)
from trifuse.calib.rig_formats import Imported
from trifuse.calib.transforms import invert

_SENSOR_NAME_RE = re.compile(r"[A-Za-z0-9._-]+")

EXTRAS = (
    ("radiometry", "radiometry"),
    ("range_correction", "range correction"),
    ("uncertainty", "uncertainty"),
)
"""A sensor's parts beyond geometry: (attribute, words), none of which a format holds."""


def extras_lost(rig: Rig, why: str) -> list[str]:
    """One ``lost`` line per sensor part of :data:`EXTRAS` the rig has: "<words> of
    <sensor>: <why>", and one for the rig's joint covariance."""
    lost = [
        f"{words} of {name}: {why}"
        for name, s in rig.sensors.items()
        for attr, words in EXTRAS
        if getattr(s, attr) is not None
    ]
    if rig.covariance is not None:
        lost.append(f"the joint covariance of the sensors' parameters: {why}")
    return lost


# -- import: from the cameras a file describes to a rig ---------------------------------


@dataclass
class ImportedCamera:
    """One sensor as a file described it, before the rig is assembled.

    Attributes:
        name: the sensor's name.
        source: the file it came from (for messages).
        modality: ``color``, ``thermal`` or ``tof``.
        image_size: (width, height) in pixels.
        K: (3, 3) camera matrix, pixels.
        distortion: coefficients in OpenCV's order ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``.
        T_frame_sensor: (4, 4) pose of the sensor in a frame common to all the files'
            sensors (metres), or None where the files give no pose.
    """

    name: str
    source: str
    modality: Modality
    image_size: tuple[int, int]
    K: np.ndarray
    distortion: tuple[float, ...]
    T_frame_sensor: np.ndarray | None


def eyes_from_option(eyes: Mapping[str, Any] | None) -> dict[str, Eye]:
    """The ``eyes`` option (eye name -> ``Eye`` or ``(color sensor, thermal sensor)``) as
    eyes; RigError for anything else. The rig checks the sensors and their modalities."""
    if eyes is None:
        return {}
    if not isinstance(eyes, Mapping):
        raise RigError(f"option eyes: expected a mapping of eye -> (color, thermal), got {eyes!r}")
    out: dict[str, Eye] = {}
    for eye, pair in eyes.items():
        if isinstance(pair, Eye):
            out[str(eye)] = pair
        elif (
            isinstance(pair, Sequence)
            and not isinstance(pair, str)
            and len(pair) == 2
            and all(isinstance(p, str) for p in pair)
        ):
            out[str(eye)] = Eye(pair[0], pair[1])
        else:
            raise RigError(
                f"option eyes: eye {eye!r}: expected (color sensor, thermal sensor), got {pair!r}"
            )
    return out


def check_modalities_option(modalities: Mapping[str, str] | None, names: Sequence[str]) -> None:
    """RigError when the ``modalities`` option names a sensor not in ``names`` or a
    modality not in ``calib.rig.MODALITIES``."""
    if modalities is None:
        return
    if not isinstance(modalities, Mapping):
        raise RigError(
            f"option modalities: expected a mapping sensor -> modality, got {modalities!r}"
        )
    for name, modality in modalities.items():
        if name not in names:
            raise RigError(
                f"option modalities: no sensor {name!r} in the files (sensors: {list(names)})"
            )
        if modality not in MODALITIES:
            raise RigError(
                f"option modalities: sensor {name!r}: expected one of {list(MODALITIES)}, "
                f"got {modality!r}"
            )


def modality_for(
    name: str, source: str, modalities: Mapping[str, str] | None, stated: str | None = None
) -> Modality:
    """A sensor's modality: the ``modalities`` option, else what the file ``stated``, else
    the name's prefix (``calib.rig.modality_of_name``); RigError naming the file when none
    gives one."""
    if modalities is not None and name in modalities:
        return modalities[name]  # type: ignore[return-value]  # checked by the caller
    if stated is not None:
        if stated not in MODALITIES:
            raise RigError(
                f"{source}: modality: expected one of {list(MODALITIES)}, got {stated!r}"
            )
        return stated  # type: ignore[return-value]
    found = modality_of_name(name)
    if found is None:
        raise RigError(
            f"{source}: sensor {name!r}: the file has no modality and the name does not "
            "start with a known prefix (ccd, color, rgb -> color; thermal, lwir -> thermal; "
            f"tof, depth -> tof); pass modalities={{{name!r}: 'color'}} (or 'thermal', 'tof')"
        )
    return found


def assemble_rig(
    cameras: Sequence[ImportedCamera],
    *,
    reference: str | None,
    eyes: Mapping[str, Any] | None,
    allow_no_poses: bool,
    format_name: str,
    lost: list[str],
    eyes_source: str = "option eyes",
) -> Imported:
    """A rig from the cameras the files described.

    The rig frame is the reference sensor's: ``reference`` if given, else the one sensor
    whose pose is the identity in the files' common frame, else the first TOF camera, else
    the first sensor (``lost`` says which rule chose it). Each pose becomes
    ``T_rig_sensor = inv(T_frame_reference) @ T_frame_sensor``; the reference's is exactly
    the identity.

    Args:
        cameras: the sensors in rig order.
        reference: the ``reference`` option, or None.
        eyes: the ``eyes`` option (see :func:`eyes_from_option`), or None when the files
            said nothing of eyes (noted in ``lost``).
        allow_no_poses: place sensors without a pose at the rig frame's origin (each is
            listed in ``lost``) instead of raising RigError.
        format_name: e.g. "ROS camera_info", for messages.
        lost: what the files did not say so far; extended and returned in ``Imported``.
        eyes_source: where ``eyes`` came from, for messages.

    Raises:
        RigError: no cameras, a sensor named twice, a missing pose without
            ``allow_no_poses``, an unknown reference, a malformed camera (the message
            names its file) or eyes that do not fit the rig.
    """
    if not cameras:
        raise RigError(f"{format_name}: no camera files among the files")
    seen: dict[str, str] = {}
    for cam in cameras:
        if cam.name in seen:
            raise RigError(
                f"{cam.source}: sensor {cam.name!r} is also described by {seen[cam.name]}"
            )
        seen[cam.name] = cam.source
    without = [c for c in cameras if c.T_frame_sensor is None]
    if without and not allow_no_poses:
        raise RigError(
            f"{format_name}: no pose for sensor(s) {[c.name for c in without]}; a rig needs "
            "every sensor's pose (placing them all at one point would fuse with no parallax "
            "correction): give the poses, or pass allow_no_poses=True to accept them at the "
            "rig frame's origin"
        )
    for cam in without:
        lost.append(
            f"pose of {cam.name}: {cam.source} has none; set to the rig frame's origin "
            "(identity), which is wrong for any real rig: calibrate it"
        )
    poses = {c.name: (np.eye(4) if c.T_frame_sensor is None else c.T_frame_sensor) for c in cameras}
    names = [c.name for c in cameras]
    if reference is not None:
        if reference not in poses:
            raise RigError(f"option reference: no sensor {reference!r} (sensors: {names})")
        ref = reference
    else:
        at_origin = [n for n in names if np.allclose(poses[n], np.eye(4), rtol=0.0, atol=1e-12)]
        tofs = [c.name for c in cameras if c.modality == "tof"]
        if len(at_origin) == 1 and not without:
            ref = at_origin[0]
        elif tofs:
            ref = tofs[0]
            lost.append(f"reference: not stated; the first TOF camera, {ref}, was chosen")
        else:
            ref = names[0]
            lost.append(f"reference: not stated; the first sensor, {ref}, was chosen")
    T_ref_frame = invert(poses[ref])
    sensors: dict[str, Sensor] = {}
    for cam in cameras:
        T = np.eye(4) if cam.name == ref else T_ref_frame @ poses[cam.name]
        K = cam.K
        block = {
            "modality": cam.modality,
            "image_size": [cam.image_size[0], cam.image_size[1]],
            "intrinsics": {
                "fx": float(K[0, 0]),
                "fy": float(K[1, 1]),
                "cx": float(K[0, 2]),
                "cy": float(K[1, 2]),
            },
            "distortion": list(cam.distortion),
            "T_rig_sensor": T.tolist(),
        }
        try:
            sensors[cam.name] = sensor_from_dict(cam.name, block)
        except RigError as exc:
            raise RigError(f"{cam.source}: {exc}") from None
    eye_map = eyes_from_option(eyes)
    if eyes is None:
        lost.append(
            f"eyes: {format_name} has no eye pairs; the rig has none (pass eyes= to pair "
            "a colour camera with a thermal imager)"
        )
    try:
        rig = Rig(sensors=sensors, reference=ref, eyes=eye_map)
    except RigError as exc:
        raise RigError(f"{eyes_source}: {exc}") from None
    return Imported(rig=rig, lost=lost)


def sensor_name_for(declared: Any, path: str) -> tuple[str, str | None]:
    """The sensor name of a camera file: ``declared`` (its camera name) when that is a
    valid sensor name, else the file's stem. Returns (name, a ``lost`` note or None);
    RigError naming the file when neither is valid."""
    stem = PurePosixPath(path).stem
    if isinstance(declared, str) or is_int(declared):
        text = str(declared)
        if _SENSOR_NAME_RE.fullmatch(text) and not text.endswith("_distance"):
            return text, None
    if _SENSOR_NAME_RE.fullmatch(stem) and not stem.endswith("_distance"):
        note = (
            f"sensor name of {path}: camera_name {declared!r} is not a sensor name "
            f"(letters, digits, '.', '_', '-'); the file's stem {stem!r} was used"
            if declared is not None
            else None
        )
        return stem, note
    raise RigError(
        f"{path}: no sensor name: camera_name {declared!r} and the file's stem {stem!r} "
        "are not names of letters, digits, '.', '_' or '-'"
    )


# -- export ---------------------------------------------------------------------------------
