"""What the joint rig calibration found (:func:`calib.rig_calibration.calibrate_rig`): per
sensor, per view and per outlier, the calibrated rig and the report's plain data."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.board import Board
from calib.camera import Intrinsics
from calib.polarity import SensorPolarity
from calib.rig import Eye, Rig, Sensor


@dataclass
class ViewError:
    """Reprojection error of one sensor in one view (at the final solution)."""

    rms_px: float
    max_px: float
    outlier: bool = False
    reason: str | None = None


@dataclass
class SensorResult:
    """Calibration of one sensor.

    ``sigma`` holds 1-sigma uncertainties: ``fx fy cx cy`` (px), ``distortion`` (list),
    ``rotation_deg`` and ``translation_m`` (3 components each, of ``T_rig_sensor``'s
    rotation vector and translation; zero for the reference).
    """

    name: str
    modality: str
    image_size: tuple[int, int]
    intrinsics: Intrinsics
    T_rig_sensor: np.ndarray
    sigma: dict[str, Any]
    views_detected: int
    views_used: int
    rms_px: float
    worst_view: str | None


@dataclass
class Outlier:
    """An observation left out of the final solution, and why."""

    view: str
    sensor: str
    corner: int | None  # None: the whole view of that sensor
    error_px: float
    reason: str


@dataclass
class CalibrationResult:
    """Everything a calibration found; ``to_report()`` gives it as JSON-able data."""

    reference: str
    board: Board
    sensors: dict[str, SensorResult]
    views: dict[str, dict[str, ViewError]]
    board_poses: dict[str, np.ndarray]
    outliers: list[Outlier]
    excluded_sensors: dict[str, str]
    rms_px: float
    seconds: float
    eyes: dict[str, Eye] = field(default_factory=dict)
    polarity: dict[str, SensorPolarity] = field(default_factory=dict)
    """Per sensor: which squares read dark/cold or bright/hot, and how that was found."""
    notes: list[str] = field(default_factory=list)
    """What the calibration decided on its own (e.g. another reference), in sentences."""

    def rig(self) -> Rig:
        """The calibrated rig (sensors that were calibrated), with ``uncertainty`` blocks."""
        sensors = {}
        for name, s in self.sensors.items():
            unc = {k: v for k, v in s.sigma.items()}
            unc["rms_px"] = s.rms_px
            sensors[name] = Sensor(
                name, s.modality, s.image_size, s.intrinsics, s.T_rig_sensor.copy(), uncertainty=unc
            )  # type: ignore[arg-type]
        eyes = {n: e for n, e in self.eyes.items() if e.color in sensors and e.thermal in sensors}
        return Rig(sensors=sensors, reference=self.reference, eyes=eyes)

    def to_report(self) -> dict[str, Any]:
        """Plain data (lists, floats, strings) for ``report.json``."""
        sensors = {}
        for name, s in self.sensors.items():
            i = s.intrinsics
            sensors[name] = {
                "modality": s.modality,
                "image_size": list(s.image_size),
                "views_detected": s.views_detected,
                "views_used": s.views_used,
                "rms_px": s.rms_px,
                "worst_view": s.worst_view,
                "intrinsics": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
                "distortion": list(i.distortion),
                "T_rig_sensor": s.T_rig_sensor.tolist(),
                "sigma": s.sigma,
            }
        return {
            "format": "trifuse-calibration-report/1",
            "reference": self.reference,
            "board": self.board.to_dict(),
            "rms_px": self.rms_px,
            "seconds": self.seconds,
            "sensors": sensors,
            "excluded_sensors": dict(self.excluded_sensors),
            "polarity": {n: p.as_dict() for n, p in sorted(self.polarity.items())},
            "notes": list(self.notes),
            "views": {
                v: {
                    s: {
                        "rms_px": e.rms_px,
                        "max_px": e.max_px,
                        "outlier": e.outlier,
                        "reason": e.reason,
                    }
                    for s, e in per.items()
                }
                for v, per in self.views.items()
            },
            "outliers": [
                {
                    "view": o.view,
                    "sensor": o.sensor,
                    "corner": o.corner,
                    "error_px": o.error_px,
                    "reason": o.reason,
                }
                for o in self.outliers
            ],
            "board_poses": {v: T.tolist() for v, T in self.board_poses.items()},
        }
