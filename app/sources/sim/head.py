"""The default sensor head (docs/CONVENTIONS.md): ground-truth rig and a nominal starting rig.

Rig frame = TOF frame (+x right, +y down, +z forward, metres). The colour pair sits 3 cm
above the TOF with a 12 cm baseline, the thermal pair at the TOF's height, 11 cm apart,
1 cm behind it; each sensor is rotated by up to 2 degrees from the nominal.
"""

from __future__ import annotations

import numpy as np

from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Eye, Rig, Sensor
from trifuse.calib.transforms import make_T, rotation_from_euler_deg

COLOR_SIZE = (1280, 960)
THERMAL_SIZE = (382, 288)
TOF_SIZE = (176, 144)

# name: (modality, size, intrinsics, translation m, (roll, pitch, yaw) deg)
_GROUND_TRUTH = {
    "tof": (
        "tof",
        TOF_SIZE,
        Intrinsics(165.5, 165.8, 87.9, 71.2, (-0.12, 0.05, 0.0003, -0.0002, 0.0)),
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
    ),
    "ccd_left": (
        "color",
        COLOR_SIZE,
        Intrinsics(1333.0, 1331.2, 641.3, 478.6, (-0.105, 0.021, 0.0004, -0.0003, 0.0)),
        (-0.0602, -0.0304, 0.0021),
        (0.6, -1.1, 0.3),
    ),
    "ccd_right": (
        "color",
        COLOR_SIZE,
        Intrinsics(1336.4, 1334.9, 637.8, 481.9, (-0.098, 0.018, -0.0002, 0.0005, 0.0)),
        (0.0597, -0.0298, 0.0018),
        (-0.4, 1.3, -0.5),
    ),
    "thermal_left": (
        "thermal",
        THERMAL_SIZE,
        Intrinsics(402.1, 401.5, 191.8, 142.7, (-0.21, 0.11, 0.0006, -0.0004, 0.0)),
        (-0.0551, 0.0012, -0.0098),
        (1.2, 1.6, -0.7),
    ),
    "thermal_right": (
        "thermal",
        THERMAL_SIZE,
        Intrinsics(399.6, 399.9, 189.4, 145.1, (-0.19, 0.09, -0.0005, 0.0003, 0.0)),
        (0.0548, -0.0009, -0.0103),
        (-0.9, -1.8, 0.8),
    ),
}

EYES = {"left": Eye("ccd_left", "thermal_left"), "right": Eye("ccd_right", "thermal_right")}


def default_rig() -> Rig:
    """The simulated head's ground truth: exact intrinsics, distortion and poses."""
    sensors = {
        name: Sensor(name, modality, size, intr, make_T(rotation_from_euler_deg(*rpy), t))
        for name, (modality, size, intr, t, rpy) in _GROUND_TRUTH.items()
    }
    return Rig(sensors=sensors, reference="tof", eyes=dict(EYES))


def nominal_rig(rig: Rig | None = None) -> Rig:
    """What a CAD drawing of ``rig`` (default: the default head) would say.

    Same sensors, modalities and sizes; focal length the rounded mean of fx and fy,
    principal point at the image centre, no distortion, no rotation, translations rounded
    to 1 cm. A plausible starting rig for a calibration, never the answer to it.
    """
    rig = rig or default_rig()
    sensors = {}
    for name, s in rig.sensors.items():
        f = float(round((s.intrinsics.fx + s.intrinsics.fy) / 2.0))
        w, h = s.image_size
        nominal = Intrinsics(f, f, (w - 1) / 2.0, (h - 1) / 2.0)
        t = np.round(s.T_rig_sensor[:3, 3], 2)
        sensors[name] = Sensor(name, s.modality, s.image_size, nominal, make_T(np.eye(3), t))
    return Rig(sensors=sensors, reference=rig.reference, eyes=dict(rig.eyes))
