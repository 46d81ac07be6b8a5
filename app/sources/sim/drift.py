"""A sensor that moves during a simulated run (issue 34 item 3): calibration drift without a
board, e.g. a thermal imager bumped by a few tenths of a degree.

:class:`SensorDrift` names one sensor of the head, a small rotation and the scenario time
from which on it applies. The convention, which the drift checker's tests take as ground
truth:

* ``rotation_deg = (rx, ry, rz)`` is a rotation vector (axis times angle) in **degrees**,
  expressed in the sensor's **own** frame (OpenCV camera axes: +x right, +y down, +z
  forward), applied on the **right** of the sensor's pose::

      R = cv2.Rodrigues(np.radians(rotation_deg))[0]          # (3, 3)
      T_rig_sensor_moved = T_rig_sensor @ [[R, 0], [0, 1]]    # (4, 4), metres

  so the sensor turns about its own optical centre (its position in the rig frame does
  not change) by ``|rotation_deg|`` degrees about the axis ``rotation_deg / |rotation_deg|``
  of its own frame. ``[[R, 0], [0, 1]]`` is ``T_sensor_moved``: it maps points from the
  moved sensor's frame into the sensor's frame as calibrated. Example: ``(0, 0.3, 0)``
  turns the sensor 0.3 degrees about its own +y (down) axis, i.e. its view to the right,
  and the scene moves to the left in its image (by about ``fx * tan(0.3 deg)`` pixels).
* From scenario time ``at_s`` on (``t_s >= at_s``, seconds) the sensor is rendered from
  ``T_rig_sensor_moved``; before it, from the rig as calibrated. The drift does not undo
  itself: a simulated head whose motion loops keeps the sensor moved once the drift began.

The command line spells a drift ``SENSOR:RX,RY,RZ[@AT_S]`` (:func:`parse_drift`, ``str()``
gives it back), e.g. ``thermal_left:0,0.3,0@20``. :func:`moved_rig` is the rig with that
sensor moved. Pure: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from trifuse.calib.rig import Rig

DRIFT_SYNTAX = "SENSOR:RX,RY,RZ[@AT_S]"
"""How the command line spells a :class:`SensorDrift`."""
_EXAMPLE = "thermal_left:0,0.3,0@20"
_EXPECTED = (
    f"expected {DRIFT_SYNTAX}: a sensor of the rig, a rotation vector in degrees about its "
    "own x, y, z axes and the scenario time in seconds from which on it applies (default "
    f"0), e.g. {_EXAMPLE}"
)


def _refused(text: str, problem: str) -> ValueError:
    """``sensor drift 'TEXT': PROBLEM; expected ...``."""
    return ValueError(f"sensor drift {text!r}: {problem}; {_EXPECTED}")


@dataclass(frozen=True)
class SensorDrift:
    """One sensor rendered from a moved pose from scenario time ``at_s`` on (the module
    docstring gives the convention).

    Attributes:
        sensor: the sensor's name in the rig.
        rotation_deg: (rx, ry, rz) rotation vector, degrees, in the sensor's own frame,
            applied on the right: ``T_rig_sensor_moved = T_rig_sensor @ [[R, 0], [0, 1]]``,
            ``R = cv2.Rodrigues(np.radians(rotation_deg))[0]``.
        at_s: scenario time from which on the sensor is moved, seconds (>= 0).
    """

    sensor: str
    rotation_deg: tuple[float, float, float]
    at_s: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.sensor, str) or not self.sensor:
            raise ValueError(f"sensor drift: expected a sensor name, got {self.sensor!r}")
        try:
            rotation = tuple(float(x) for x in self.rotation_deg)
        except (TypeError, ValueError):
            rotation = ()
        if len(rotation) != 3 or not all(math.isfinite(x) for x in rotation):
            raise ValueError(
                "sensor drift: rotation_deg: expected three finite numbers (degrees about "
                f"the sensor's x, y, z), got {self.rotation_deg!r}"
            )
        try:
            at_s = float(self.at_s)
        except (TypeError, ValueError):
            at_s = math.nan
        if not (math.isfinite(at_s) and at_s >= 0):
            raise ValueError(
                f"sensor drift: at_s: expected a finite number of seconds >= 0, got {self.at_s!r}"
            )
        object.__setattr__(self, "rotation_deg", rotation)
        object.__setattr__(self, "at_s", at_s)

    def active(self, t_s: float) -> bool:
        """Whether the sensor is moved at scenario time ``t_s`` (seconds): ``t_s >= at_s``."""
        return t_s >= self.at_s

    @property
    def angle_deg(self) -> float:
        """The size of the turn, degrees (the rotation vector's length)."""
        return float(np.linalg.norm(self.rotation_deg))

    def R_sensor_moved(self) -> np.ndarray:
        """(3, 3) ``R = cv2.Rodrigues(np.radians(rotation_deg))[0]``: turns directions from
        the moved sensor's frame into the sensor's frame as calibrated."""
        R, _ = cv2.Rodrigues(np.radians(np.asarray(self.rotation_deg, dtype=np.float64)))
        return R

    def T_sensor_moved(self) -> np.ndarray:
        """(4, 4) ``[[R, 0], [0, 1]]`` (:meth:`R_sensor_moved`): maps points from the moved
        sensor's frame into the sensor's frame as calibrated (no translation)."""
        T = np.eye(4)
        T[:3, :3] = self.R_sensor_moved()
        return T

    def __str__(self) -> str:
        """The command line's spelling (:data:`DRIFT_SYNTAX`), which :func:`parse_drift`
        reads back to an equal drift."""
        text = f"{self.sensor}:{','.join(_number(x) for x in self.rotation_deg)}"
        return text if self.at_s == 0 else f"{text}@{_number(self.at_s)}"


def _number(x: float) -> str:
    """``x`` in the shortest text that reads back as the same float (``0.3``, ``20``)."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def parse_drift(text: str) -> SensorDrift:
    """A :class:`SensorDrift` from its command-line spelling ``SENSOR:RX,RY,RZ[@AT_S]``
    (degrees, seconds), e.g. ``thermal_left:0,0.3,0@20``; ``AT_S`` defaults to 0.

    Raises:
        ValueError: the text is not that (no ``:``, no sensor name, not three finite
            numbers, more than one ``@``, an ``AT_S`` that is not a finite number >= 0);
            the message says what was expected and what arrived.
    """
    given = text
    sensor, colon, rest = text.strip().partition(":")
    sensor = sensor.strip()
    if not colon:
        raise _refused(given, "no ':' after the sensor's name")
    if not sensor:
        raise _refused(given, "no sensor name before ':'")
    angles, *at = rest.split("@")
    if len(at) > 1:
        raise _refused(given, "more than one '@'")
    parts = angles.split(",")
    try:
        rotation = tuple(float(p) for p in parts)
    except ValueError:
        rotation = ()
    if len(parts) != 3 or len(rotation) != 3 or not all(math.isfinite(x) for x in rotation):
        raise _refused(given, f"the rotation {angles.strip()!r} is not three finite numbers")
    at_s = 0.0
    if at:
        try:
            at_s = float(at[0])
        except ValueError:
            at_s = math.nan
        if not (math.isfinite(at_s) and at_s >= 0):
            raise _refused(given, f"the start {at[0].strip()!r} is not a number of seconds >= 0")
    return SensorDrift(sensor, rotation, at_s)  # type: ignore[arg-type]


def moved_rig(rig: Rig, drift: SensorDrift) -> Rig:
    """``rig`` with ``drift.sensor``'s pose moved by the drift (whatever ``at_s``):
    ``T_rig_sensor_moved = T_rig_sensor @ drift.T_sensor_moved()`` (module docstring).

    The other sensors, the reference and the eyes are kept (shared, not copied); the rig's
    calibration covariance is dropped (:meth:`~calib.rig.Rig.with_sensor`: it described the
    old geometry). Moving the reference sensor moves it in the rig frame (that frame stays
    the head's as calibrated).

    Raises:
        ValueError: the rig has no sensor of that name (the message names the rig's sensors).
    """
    if drift.sensor not in rig:
        raise ValueError(
            f"sensor drift: no sensor {drift.sensor!r} in the rig (sensors: {', '.join(rig.names)})"
        )
    sensor = rig[drift.sensor]
    T = np.asarray(sensor.T_rig_sensor, dtype=np.float64) @ drift.T_sensor_moved()
    return rig.with_sensor(replace(sensor, T_rig_sensor=T))
