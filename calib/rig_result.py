"""What the joint rig calibration found (:func:`calib.rig_calibration.calibrate_rig`): per
sensor, per view and per outlier, the calibrated rig and the report's plain data."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.board_ordering import BoardOrdering
from trifuse.calib.parameter_covariance import from_calibration
from trifuse.calib.polarity import SensorPolarity
from trifuse.calib.rig import Eye, Rig, Sensor
from trifuse.calib.rig_uncertainty import RigCovariance
from trifuse.calib.sensor_result import SensorResult
from trifuse.calib.verdict import ZHANG_MIN_VIEWS, RigVerdict


@dataclass
class ViewError:
    """Reprojection error of one sensor in one view (at the final solution)."""

    rms_px: float
    max_px: float
    outlier: bool = False
    reason: str | None = None


@dataclass
class Outlier:
    """An observation left out of the final solution, and why."""

    view: str
    sensor: str
    corner: int | None  # None: the whole view of that sensor
    error_px: float
    reason: str


@dataclass
class CornerResiduals:
    """Every corner the joint calibration was given, at the final solution (outliers too).

    Attributes:
        views: view names; ``v_idx`` indexes them.
        sensors: sensor names; ``s_idx`` indexes them.
        v_idx, s_idx, c_idx: (M,) int view, sensor and board corner index of each corner.
        uv_px: (M, 2) the detected corner (u, v), pixels, in the order the calibration used.
        residual_px: (M, 2) detected minus reprojected (du, dv), pixels.
        inlier: (M,) bool, the corner was used in the final pass (not an outlier corner,
            not in an outlier view).
    """

    views: list[str]
    sensors: list[str]
    v_idx: np.ndarray
    s_idx: np.ndarray
    c_idx: np.ndarray
    uv_px: np.ndarray
    residual_px: np.ndarray
    inlier: np.ndarray


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
    ordering: BoardOrdering | None = None
    """A board that looks the same turned: how each view's ordering was decided."""
    notes: list[str] = field(default_factory=list)
    """What the calibration decided on its own (e.g. another reference), in sentences."""
    corners: CornerResiduals | None = None
    """Per corner residuals (not in ``to_report()``: the HTML report plots them)."""
    covariance: RigCovariance | None = None
    """The joint covariance of the sensors' poses and intrinsics (not in ``to_report()``)."""
    verdict: RigVerdict | None = None
    """Verdicts per sensor and pair from that covariance (calib.verdict)."""
    min_views: int = ZHANG_MIN_VIEWS
    """The fewest views a sensor needed to be calibrated (the option used)."""
    intrinsics_only: dict[str, SensorResult] = field(default_factory=dict)
    """Sensors whose intrinsics were calibrated but whose pose is unknown: each shares no
    view with the reference or a sensor placed from it (``SensorResult.pose_unknown``
    says so). Not in ``sensors`` nor in the rig (a pose is required there); their verdicts
    are in ``verdict.intrinsics_only``."""

    def rig(self) -> Rig:
        """The calibrated rig (sensors that were calibrated), with ``uncertainty`` blocks and
        the joint ``covariance`` of their parameters."""
        sensors = {}
        for name, s in self.sensors.items():
            unc = {k: v for k, v in s.sigma.items()}
            unc["rms_px"] = s.rms_px
            sensors[name] = Sensor(
                name, s.modality, s.image_size, s.intrinsics, s.T_rig_sensor.copy(), uncertainty=unc
            )  # type: ignore[arg-type]
        eyes = {n: e for n, e in self.eyes.items() if e.color in sensors and e.thermal in sensors}
        covariance = None
        if self.covariance is not None:
            covariance = from_calibration(self.covariance, self.sensors)
        return Rig(sensors=sensors, reference=self.reference, eyes=eyes, covariance=covariance)

    def to_report(self) -> dict[str, Any]:
        """Plain data (lists, floats, strings) for ``report.json``."""
        sensors = {name: _sensor_entry(s) for name, s in self.sensors.items()}
        intrinsics_only = {}
        for name, s in self.intrinsics_only.items():
            entry = _sensor_entry(s)
            del entry["T_rig_sensor"]
            entry["pose_unknown"] = s.pose_unknown
            intrinsics_only[name] = entry
        return {
            "format": "trifuse-calibration-report/1",
            "reference": self.reference,
            "board": self.board.to_dict(),
            "rms_px": self.rms_px,
            "seconds": self.seconds,
            "sensors": sensors,
            "sensors_intrinsics_only": intrinsics_only,
            "excluded_sensors": dict(self.excluded_sensors),
            "polarity": {n: p.as_dict() for n, p in sorted(self.polarity.items())},
            "board_ordering": self.ordering.as_dict() if self.ordering is not None else None,
            "notes": list(self.notes),
            "min_views": self.min_views,
            "verdict": self.verdict.as_dict() if self.verdict is not None else None,
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


def _sensor_entry(s: SensorResult) -> dict[str, Any]:
    """One sensor's ``report.json`` entry (plain data)."""
    i = s.intrinsics
    return {
        "modality": s.modality,
        "image_size": list(s.image_size),
        "views_detected": s.views_detected,
        "views_used": s.views_used,
        "rms_px": s.rms_px,
        "worst_view": s.worst_view,
        "zhang_rms_px": s.zhang_rms_px,
        "intrinsics_source": s.intrinsics_source,
        "intrinsics": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
        "distortion": list(i.distortion),
        "T_rig_sensor": s.T_rig_sensor.tolist(),
        "sigma": s.sigma,
    }
