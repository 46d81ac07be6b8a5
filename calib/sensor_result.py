"""One sensor's calibration (:class:`SensorResult`), on its own so that the verdicts
(:mod:`calib.verdict`) and the whole result (:mod:`calib.rig_result`) can both use it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from trifuse.calib.camera import Intrinsics


@dataclass
class SensorResult:
    """Calibration of one sensor.

    ``sigma`` holds 1-sigma uncertainties: ``fx fy cx cy`` (px), ``distortion`` (list),
    ``rotation_deg`` and ``translation_m`` (3 components each, of ``T_rig_sensor``'s
    rotation vector and translation; zero for the reference; absent when ``pose_unknown``).
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
    zhang_rms_px: float | None = None
    """RMS error of Zhang's fit of this sensor alone (its own board poses), px."""
    intrinsics_source: str | None = None
    """Where the intrinsics come from: "joint refinement" (or "... without <s>'s views" when
    the guard of calib.rig_calibration kept <s>'s own), or "own views" (Zhang's fit of this
    sensor alone: intrinsics fixed, or "own views (<why>)" when the guard kept them), or
    "own views, calibrated alone" (``pose_unknown``)."""
    pose_unknown: str | None = None
    """Why the sensor's pose in the rig is unknown (it shares no view with the reference or a
    sensor placed from it), or None. Such a sensor is calibrated alone, on its own views,
    as a capture of it alone would be: intrinsics, their sigma and RMS only;
    ``T_rig_sensor`` is NaN."""
