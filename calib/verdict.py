"""How good is a calibration, and what would make it better: the verdicts, per sensor and
per pair of sensors, and their words and JSON (computed from the calibration's own
uncertainty by :mod:`calib.verdict_judge`).

**Figures.** Per sensor: the 1-sigma of its focal lengths (relative, %), of its principal
point (px; reported, not judged) and of its pose relative to the reference sensor
(rotation in degrees, translation in mm). Per pair, each eye (colour camera - thermal
imager) and the stereo pair (the two eyes' colour cameras): the 1-sigma of their relative
pose ``T_a_b = inv(T_rig_a) @ T_rig_b``, rotation and translation (the baseline). A pose's
rotation and translation errors are taken in the first sensor's frame (x right, y down,
z forward: rotations about the horizontal, vertical and optical axes); their sigma is the
root of the summed variances of the three components (the expected size of the error
vector). Every sigma is the larger of the independent-errors and the cluster-robust
estimate, as the parameters' own.

**Targets.** The calibration's accuracy targets (calib.rig_compare: focal lengths 0.3 %,
1 % for the TOF; relative poses 0.1 deg and 1 mm, 0.2 deg and 3 mm with the TOF) apply to
the error; a sigma meets its target when it is at most half of it (:data:`SIGMA_SHARE`),
so that the error stays within the accuracy target at two sigma. A verdict is **good** when
every judged sigma meets its target, **poor** when one exceeds it :data:`POOR_FACTOR` times
(the error is then likely beyond twice the accuracy target), **usable** in between.

**Advice**: how many more views of which kinds (:data:`KINDS`) would make a verdict good,
found from the information matrix (calib.verdict_judge's module docstring).

Pure: values in, values out.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

ZHANG_MIN_VIEWS = 3
"""Views of the board Zhang's method needs for a sensor's intrinsics (OpenCV's
``calibrateCamera`` with the focal lengths, principal point and distortion free)."""
GOOD, USABLE, POOR = "good", "usable", "poor"
GRADES = (GOOD, USABLE, POOR)
SIGMA_SHARE = 0.5
"""A sigma meets its target when it is at most this share of the accuracy target."""
POOR_FACTOR = 4.0
"""A verdict is poor when a sigma exceeds its target (half the accuracy target) this many
times: twice the accuracy target."""
MAX_MORE_VIEWS = 40
"""The search for more views stops here (the advice then says "more than")."""
DISAGREEMENT = (2.0, 0.5)
"""A sensor's joint RMS error beyond this factor times, and this many pixels above, its RMS
alone (Zhang's fit with its own board poses): its views disagree with the other sensors'
(a mount that moved, captures not at the same moment), which more views cannot fix."""
DOMINANT_SHARE = 0.6
"""An axis holding this share of a figure's variance is named ("mostly about ...")."""

KINDS: Mapping[str, str] = {
    "tilt_vertical": "tilted about the vertical axis",
    "tilt_horizontal": "tilted about the horizontal axis",
    "corners": "in the image corners of {sensors}",
    "nearer": "nearer, filling most of the image of {sensors}",
    "farther": "farther from {sensors}",
}
"""Kinds of candidate views, and how the advice names them."""


@dataclass(frozen=True)
class Figure:
    """One 1-sigma figure of a verdict.

    Attributes:
        what: e.g. ``focal length``, ``principal point``, ``rotation to tof``,
            ``baseline``.
        sigma: 1-sigma in ``unit``.
        unit: ``%``, ``px``, ``°`` or ``mm``.
        target: the sigma's target (half the accuracy target) in ``unit``; None when the
            figure is reported, not judged.
        axes: per-axis 1-sigma (x, y, z of the first sensor's frame) of a rotation or
            translation, else None.
        axis_names: what the axes are called (``horizontal vertical optical`` for
            rotations, ``sideways vertical depth`` for translations).
    """

    what: str
    sigma: float
    unit: str
    target: float | None
    axes: tuple[float, float, float] | None = None
    axis_names: tuple[str, str, str] | None = None

    @property
    def ratio(self) -> float:
        """sigma / target (0 for a figure without target)."""
        return self.sigma / self.target if self.target else 0.0

    @property
    def dominant_axis(self) -> str | None:
        """The axis holding :data:`DOMINANT_SHARE` of the variance, or None."""
        if self.axes is None or self.axis_names is None:
            return None
        var = np.square(self.axes)
        k = int(np.argmax(var))
        total = float(var.sum())
        return self.axis_names[k] if total > 0 and var[k] >= DOMINANT_SHARE * total else None

    def text(self, with_target: bool = False) -> str:
        """``σ of the rotation to tof 0.14°`` (``(good at ≤ 0.05°, mostly about the
        vertical axis)`` added with ``with_target``: the target is the sigma's, half the
        accuracy target)."""
        s = f"σ of the {self.what} {_number(self.sigma)}{_space(self.unit)}"
        if not with_target:
            return s
        notes = []
        if self.target is not None:
            notes.append(f"good at ≤ {_number(self.target)}{_space(self.unit)}")
        axis = self.dominant_axis
        if axis is not None:
            notes.append(f"mostly about the {axis} axis" if self.unit == "°" else f"mostly {axis}")
        return s + (f" ({', '.join(notes)})" if notes else "")

    def as_dict(self) -> dict[str, Any]:
        return {
            "what": self.what,
            "sigma": self.sigma,
            "unit": self.unit,
            "target": self.target,
            "ratio": self.ratio if self.target else None,
            "axes": list(self.axes) if self.axes is not None else None,
            "axis_names": list(self.axis_names) if self.axis_names is not None else None,
            "dominant_axis": self.dominant_axis,
        }


@dataclass(frozen=True)
class Verdict:
    """The verdict on a sensor or a pair of sensors.

    Attributes:
        label: ``ccd_left``, ``left eye (ccd_left – thermal_left)``, ``stereo (ccd_left –
            ccd_right)``.
        sensors: the sensor, or the pair (first: the frame of its pose figures).
        grade: ``good``, ``usable`` or ``poor``.
        figures: every figure, judged or not.
        more_views: views that would make it good (predicted), 0 when good, None when
            :data:`MAX_MORE_VIEWS` do not suffice.
        advice_views: (kind, sensors, views) of the kinds of those views chosen most
            often (at most two, most first; kind a :data:`KINDS` key, sensors those the
            board was placed in front of).
        predicted: the judged figure with the worst sigma / target ratio after the views
            the search added, with its predicted sigma (None when good).
        baseline_mm: length of the pair's translation, mm (pairs only).
        sigma_baseline_length_mm: 1-sigma of that length, mm (pairs only).
        next_poses: (4, 4) ``T_rig_board`` of the views the search added, in the order it
            added them (metres; not in the report).
        disagreement: why the sensor's views disagree with the other sensors' (see
            :data:`DISAGREEMENT`), or None; it replaces the advice.
        pose_unknown: why the sensor's pose in the rig is unknown (a sensor calibrated
            alone: its verdict judges its intrinsics only), or None; the line ends with it.
    """

    label: str
    sensors: tuple[str, ...]
    grade: str
    figures: tuple[Figure, ...]
    more_views: int | None = 0
    advice_views: tuple[tuple[str, tuple[str, ...], int], ...] = ()
    predicted: Figure | None = None
    baseline_mm: float | None = None
    sigma_baseline_length_mm: float | None = None
    next_poses: tuple[np.ndarray, ...] = ()
    disagreement: str | None = None
    pose_unknown: str | None = None

    @property
    def judged(self) -> list[Figure]:
        return [f for f in self.figures if f.target is not None]

    @property
    def advice(self) -> str | None:
        """What to capture next, in a sentence; None when good."""
        if self.grade == GOOD:
            return None
        if self.disagreement is not None:
            return self.disagreement
        kinds = " and ".join(
            KINDS[k].format(sensors=" and ".join(s)) for k, s, _ in self.advice_views
        )
        if self.more_views is None and not self.next_poses:
            return (
                "no candidate view of the board helps (none fits or none lowers the sigma): "
                "lower the corner noise (sharper, better lit or better heated images)"
            )
        if self.more_views is None:
            p = self.predicted
            after = ""
            if p is not None and p.target is not None:
                after = (
                    f" ({len(self.next_poses)} would bring σ of the {p.what} to "
                    f"{_number(p.sigma)}{_space(p.unit)}, good at ≤ {_number(p.target)}"
                    f"{_space(p.unit)})"
                )
            tried = f", {kinds}" if kinds else ""
            return (
                f"capture more than {len(self.next_poses)} more views{tried}{after}, or lower "
                "the corner noise (sharper, better lit or better heated images; a larger or "
                "nearer board)"
            )
        n = self.more_views
        return f"capture about {n} more view{'s' if n > 1 else ''}: {kinds}"

    @property
    def line(self) -> str:
        """``usable: σ of the rotation to tof 0.14° (good at ≤ 0.05°, mostly about the
        vertical axis); capture about 6 more views: tilted about the vertical axis``; a
        sensor calibrated alone adds ``; pose not linked: <why>``."""
        line = self._line()
        return (
            line if self.pose_unknown is None else f"{line}; pose not linked: {self.pose_unknown}"
        )

    def _line(self) -> str:
        if self.grade == GOOD:
            shown = [f.text() for f in self.judged]
            if self.baseline_mm is not None and self.sigma_baseline_length_mm is not None:
                shown.append(
                    f"baseline {self.baseline_mm:.1f} ± {_number(self.sigma_baseline_length_mm)} mm"
                )
            return f"{GOOD}: " + ", ".join(shown) if shown else GOOD
        over = sorted(
            (f for f in self.judged if f.ratio > 1.0), key=lambda f: f.ratio, reverse=True
        )
        head = f"{self.grade}: " + "; ".join(f.text(with_target=True) for f in over[:2])
        if len(over) > 2:
            head += f" and {len(over) - 2} more above target"
        advice = self.advice
        return head + (f"; {advice}" if advice else "")

    def as_dict(self) -> dict[str, Any]:
        return {
            "label": self.label,
            "sensors": list(self.sensors),
            "grade": self.grade,
            "line": self.line,
            "figures": [f.as_dict() for f in self.figures],
            "advice": self.advice,
            "advice_views": [
                {"kind": k, "sensors": list(s), "views": n} for k, s, n in self.advice_views
            ],
            "more_views": self.more_views,
            "predicted": self.predicted.as_dict() if self.predicted is not None else None,
            "baseline_mm": self.baseline_mm,
            "sigma_baseline_length_mm": self.sigma_baseline_length_mm,
            "disagreement": self.disagreement,
        } | ({} if self.pose_unknown is None else {"pose_unknown": self.pose_unknown})


@dataclass(frozen=True)
class RigVerdict:
    """Verdicts on every calibrated sensor and on the eye and stereo pairs; and on the
    intrinsics of each sensor calibrated alone (its pose unknown: ``Verdict.pose_unknown``)."""

    sensors: dict[str, Verdict]
    pairs: list[Verdict] = field(default_factory=list)
    intrinsics_only: dict[str, Verdict] = field(default_factory=dict)

    @property
    def grade(self) -> str:
        """The worst grade of all."""
        grades = [
            v.grade for v in [*self.sensors.values(), *self.pairs, *self.intrinsics_only.values()]
        ]
        return max(grades, key=GRADES.index) if grades else GOOD

    def as_dict(self) -> dict[str, Any]:
        return {
            "grade": self.grade,
            "sigma_share": SIGMA_SHARE,
            "poor_factor": POOR_FACTOR,
            "sensors": {n: v.as_dict() for n, v in self.sensors.items()},
            "pairs": [v.as_dict() for v in self.pairs],
            "sensors_intrinsics_only": {n: v.as_dict() for n, v in self.intrinsics_only.items()},
        }


def _number(x: float) -> str:
    """Two significant digits, at most three decimals: 0.14, 1.2, 36, 0.012."""
    if x == 0 or not np.isfinite(x):
        return f"{x:g}"
    digits = max(0, min(3, 1 - int(np.floor(np.log10(abs(x))))))
    return f"{x:.{digits}f}"


def _space(unit: str) -> str:
    return unit if unit == "°" else f" {unit}"
