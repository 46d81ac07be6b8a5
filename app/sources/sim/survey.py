"""A survey of the inspection room for the thermal 3D map (issue 20): the head pans and
tilts over the room, then the robot drives a short way along it.

Timeline (keyframes of :data:`SURVEY_KEYS`, eased between them):

* 0-22 s: the head, at the origin, pans from 0 to -60 degrees (left), sweeps to +60, tilts
  up 20 degrees and sweeps back to -60, then returns to straight ahead;
* 22-36 s: the robot turns left, drives 1 m left, turns back and drives 2 m forward along
  the room's left side (past the ice ball, stopping short of the first person), the head
  looking where it drives.

World frame = the inspection room's (+x right, +y down, +z forward, metres); the head's
rig frame at time 0 is the world frame.
"""

from __future__ import annotations

import hashlib

import numpy as np

from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.calib.rig import rig_to_yaml
from trifuse.calib.transforms import make_T, rotation_from_euler_deg

# (time s, x m, z m, pan deg (about the vertical, + right), tilt deg (+ up))
SURVEY_KEYS = np.array(
    [
        (0.0, 0.0, 0.0, 0.0, 0.0),
        (3.0, 0.0, 0.0, -60.0, 0.0),
        (9.0, 0.0, 0.0, 60.0, 0.0),
        (11.0, 0.0, 0.0, 60.0, 20.0),
        (17.0, 0.0, 0.0, -60.0, 20.0),
        (20.0, 0.0, 0.0, 0.0, 0.0),
        (22.0, 0.0, 0.0, -80.0, 0.0),
        (26.0, -1.0, 0.2, -80.0, 0.0),
        (28.0, -1.0, 0.2, 0.0, 0.0),
        (36.0, -1.0, 2.2, 0.0, 0.0),
    ]
)
SURVEY_S = float(SURVEY_KEYS[-1, 0])
"""The survey's length, seconds."""


def survey_state(t_s: float) -> np.ndarray:
    """(x, z, pan, tilt) at time ``t_s`` (clamped to the survey), eased (smoothstep)
    between keyframes so that the head starts and stops smoothly."""
    t = float(np.clip(t_s, 0.0, SURVEY_S))
    k = int(
        np.clip(np.searchsorted(SURVEY_KEYS[:, 0], t, side="right") - 1, 0, len(SURVEY_KEYS) - 2)
    )
    a, b = SURVEY_KEYS[k], SURVEY_KEYS[k + 1]
    x = (t - a[0]) / (b[0] - a[0])
    s = x * x * (3.0 - 2.0 * x)
    return a[1:] + s * (b[1:] - a[1:])


def survey_pose(t_s: float) -> np.ndarray:
    """(4, 4) ``T_world_rig`` of the survey at ``t_s``."""
    x, z, pan, tilt = survey_state(t_s)
    # Pan about the vertical (y, down) then tilt about the head's own x; up is -y, so a
    # positive tilt (up) is a negative rotation about x.
    R = rotation_from_euler_deg(0.0, pan, 0.0) @ rotation_from_euler_deg(-tilt, 0.0, 0.0)
    return make_T(R, (x, 0.0, z))


class SurveyScenario(InspectionScenario):
    """The inspection room surveyed by :func:`survey_pose` (see the module docstring).

    ``pan_period_s`` is the survey's length, so a simulated head loops over the whole
    survey.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.pan_period_s = SURVEY_S

    def T_world_rig(self, t_s: float) -> np.ndarray:
        return survey_pose(t_s % SURVEY_S if t_s != SURVEY_S else t_s)

    def cache_key(self) -> str:
        """What identifies this scenario's pictures (the simulated head's disk cache:
        ``trifuse serve --scenario survey`` renders each pose once per machine), the sensor
        drift included."""
        rig = hashlib.sha256(rig_to_yaml(self.rig).encode()).hexdigest()[:16]
        key = f"seed={self.seed} live={self.live} rig={rig} {self.renderer.model!r}"
        return key if self.drift is None else f"{key} drift={self.drift!r}"

    def max_turn_rad(self, dt_s: float) -> float:
        """The largest angle (radians) the head turns in ``dt_s`` seconds: the fastest
        keyframe stretch at the middle of its easing (1.5 times its mean rate)."""
        return float(min(_MAX_RATE_RAD_S * abs(dt_s), np.pi))


_steps = np.diff(SURVEY_KEYS, axis=0)
_MAX_RATE_RAD_S = float(
    np.radians(np.max(np.hypot(_steps[:, 3], _steps[:, 4]) / _steps[:, 0])) * 1.5
)
