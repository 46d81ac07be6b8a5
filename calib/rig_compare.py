"""A calibrated rig against a reference rig (the simulator's ground truth, or another
calibration): per-sensor intrinsic errors and pairwise pose errors, judged against targets.

Frames: two rigs may use different rig frames (each is its reference sensor's frame), so
single poses ``T_rig_sensor`` are not comparable between them. The relative pose of two
sensors, ``T_a_b = inv(T_rig_a) @ T_rig_b``, does not depend on the rig frame: every pair of
sensors in both rigs is compared that way. Units: pixels for intrinsics, degrees and metres
for poses (the report formats show millimetres).

The default targets are the calibration issue's: focal lengths within 0.3 % of the truth
for colour and thermal imagers and 1 % for the TOF camera; relative poses within 0.1 deg and
1 mm between colour and thermal imagers, 0.2 deg and 3 mm for pairs that involve the TOF.
A pair's target is the looser of its two sensors' targets. The principal point and the
distortion have no target: their errors are reported, not judged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.transforms import pose_error

FOCAL_TARGET: Mapping[str, float] = {"color": 0.003, "thermal": 0.003, "tof": 0.01}
"""Largest relative focal-length error |f_est / f_true - 1| per modality."""

POSE_TARGET: Mapping[str, tuple[float, float]] = {
    "color": (0.1, 0.001),
    "thermal": (0.1, 0.001),
    "tof": (0.2, 0.003),
}
"""Largest (rotation deg, translation m) error of a relative pose, per modality; a pair
takes the looser of its two sensors' values."""

DISTORTION_GRID = (25, 33)
"""(rows, cols) of pixels, spread over the whole image including its border, at which two
distortion models are compared."""


@dataclass(frozen=True)
class IntrinsicsError:
    """One sensor's intrinsics, estimate minus truth.

    Attributes:
        sensor, modality: the sensor (modality as in the truth).
        fx_px, fy_px, cx_px, cy_px: estimate - truth, pixels.
        fx_rel, fy_rel: ``estimate / truth - 1`` (0.001 = 0.1 %).
        distortion: estimate - truth per coefficient, OpenCV's order (the shorter list is
            zero-padded).
        distortion_px: how far apart the two distortion models put a point, at most, over
            the image: pixels of the truth's image are undistorted with the truth's model
            and distorted again with the estimate's (both with the truth's camera matrix,
            so that only the distortion differs); the largest displacement, pixels. NaN
            when no pixel could be compared (beyond the fold of a model).
        focal_target_rel: the relative focal-length target (``FOCAL_TARGET``).
    """

    sensor: str
    modality: str
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    fx_rel: float
    fy_rel: float
    distortion: tuple[float, ...]
    distortion_px: float
    focal_target_rel: float

    @property
    def fx_ok(self) -> bool:
        """fx within its target."""
        return abs(self.fx_rel) <= self.focal_target_rel

    @property
    def fy_ok(self) -> bool:
        """fy within its target."""
        return abs(self.fy_rel) <= self.focal_target_rel

    @property
    def ok(self) -> bool:
        """Both focal lengths within their target."""
        return self.fx_ok and self.fy_ok


@dataclass(frozen=True)
class PairError:
    """The relative pose of sensors ``a`` and ``b``, estimate against truth.

    Attributes:
        a, b: the sensors (``a`` comes first in the truth's order).
        rotation_deg: angle of ``R_est^T R_true`` of ``T_a_b`` (the same for ``T_b_a``).
        translation_m: the translation error of ``T_a_b`` (``b``'s position in ``a``'s
            frame) or of ``T_b_a``, whichever is larger (they differ by the rotation error
            times the baseline), metres.
        target_deg, target_m: the pair's targets (``POSE_TARGET``, the looser of the two).
    """

    a: str
    b: str
    rotation_deg: float
    translation_m: float
    target_deg: float
    target_m: float

    @property
    def rotation_ok(self) -> bool:
        return self.rotation_deg <= self.target_deg

    @property
    def translation_ok(self) -> bool:
        return self.translation_m <= self.target_m

    @property
    def ok(self) -> bool:
        """Rotation and translation within their targets."""
        return self.rotation_ok and self.translation_ok

    def involves(self, sensor: str) -> bool:
        """``sensor`` is one of the pair."""
        return sensor in (self.a, self.b)


@dataclass
class RigComparison:
    """An estimated rig against a true one (``compare_rigs``).

    Attributes:
        intrinsics: per sensor in both rigs (truth's order), its :class:`IntrinsicsError`.
        pairs: every unordered pair of sensors in both rigs (truth's order), its
            :class:`PairError`.
        only_in_estimate, only_in_truth: sensors in one rig only (not compared).
        estimate_reference, truth_reference: each rig's reference sensor (its frame is
            that rig's frame; the comparison does not depend on it).
    """

    intrinsics: dict[str, IntrinsicsError]
    pairs: list[PairError]
    only_in_estimate: list[str] = field(default_factory=list)
    only_in_truth: list[str] = field(default_factory=list)
    estimate_reference: str = ""
    truth_reference: str = ""

    @property
    def failures(self) -> list[str]:
        """What misses its target, e.g. ``"ccd_left fx"``, ``"tof-ccd_left rotation"``."""
        out = []
        for name, e in self.intrinsics.items():
            out += [f"{name} {f}" for f, ok in (("fx", e.fx_ok), ("fy", e.fy_ok)) if not ok]
        for p in self.pairs:
            out += [f"{p.a}-{p.b} rotation"] if not p.rotation_ok else []
            out += [f"{p.a}-{p.b} translation"] if not p.translation_ok else []
        return out

    @property
    def n_figures(self) -> int:
        """Number of judged figures: fx and fy per sensor, rotation and translation per pair."""
        return 2 * len(self.intrinsics) + 2 * len(self.pairs)

    @property
    def passed(self) -> bool:
        """Every judged figure meets its target."""
        return not self.failures

    def pair(self, a: str, b: str) -> PairError:
        """The pair of ``a`` and ``b`` in either order; KeyError if not compared."""
        for p in self.pairs:
            if {p.a, p.b} == {a, b}:
                return p
        raise KeyError(f"no compared pair {a!r}, {b!r}")

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-ready values (``null`` for NaN): the ``comparison`` block of a report."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {
            "passed": self.passed,
            "failures": self.failures,
            "estimate_reference": self.estimate_reference,
            "truth_reference": self.truth_reference,
            "only_in_estimate": list(self.only_in_estimate),
            "only_in_truth": list(self.only_in_truth),
            "sensors": {
                n: {
                    "modality": e.modality,
                    "fx_px": e.fx_px,
                    "fy_px": e.fy_px,
                    "cx_px": e.cx_px,
                    "cy_px": e.cy_px,
                    "fx_percent": 100 * e.fx_rel,
                    "fy_percent": 100 * e.fy_rel,
                    "focal_target_percent": 100 * e.focal_target_rel,
                    "fx_ok": e.fx_ok,
                    "fy_ok": e.fy_ok,
                    "distortion": list(e.distortion),
                    "distortion_px": num(e.distortion_px),
                }
                for n, e in self.intrinsics.items()
            },
            "pairs": [
                {
                    "a": p.a,
                    "b": p.b,
                    "rotation_deg": p.rotation_deg,
                    "translation_mm": 1000 * p.translation_m,
                    "target_deg": p.target_deg,
                    "target_mm": 1000 * p.target_m,
                    "rotation_ok": p.rotation_ok,
                    "translation_ok": p.translation_ok,
                }
                for p in self.pairs
            ],
        }


def distortion_difference_px(
    estimate: Intrinsics, truth: Intrinsics, size: tuple[int, int]
) -> float:
    """Largest pixel displacement between two distortion models over a ``size`` = (W, H)
    image (see ``IntrinsicsError.distortion_px``); NaN if no pixel could be compared."""
    rows, cols = DISTORTION_GRID
    w, h = size
    u, v = np.meshgrid(np.linspace(-0.5, w - 0.5, cols), np.linspace(-0.5, h - 0.5, rows))
    pixels = np.stack([u, v], axis=-1)
    xy = truth.normalized(pixels)
    same_k = Intrinsics(truth.fx, truth.fy, truth.cx, truth.cy, estimate.distortion)
    xy_d = same_k.distort(xy)
    du = xy_d[..., 0] * truth.fx + truth.cx - u
    dv = xy_d[..., 1] * truth.fy + truth.cy - v
    moved = np.hypot(du, dv)
    if not np.any(np.isfinite(moved)):
        return math.nan
    return float(np.nanmax(moved))


def _intrinsics_error(
    est: Sensor, true: Sensor, focal_target: Mapping[str, float]
) -> IntrinsicsError:
    a, b = est.intrinsics, true.intrinsics
    n = max(len(a.distortion), len(b.distortion))
    da = np.zeros(n)
    db = np.zeros(n)
    da[: len(a.distortion)] = a.distortion
    db[: len(b.distortion)] = b.distortion
    return IntrinsicsError(
        sensor=true.name,
        modality=true.modality,
        fx_px=a.fx - b.fx,
        fy_px=a.fy - b.fy,
        cx_px=a.cx - b.cx,
        cy_px=a.cy - b.cy,
        fx_rel=a.fx / b.fx - 1.0,
        fy_rel=a.fy / b.fy - 1.0,
        distortion=tuple(float(x) for x in da - db),
        distortion_px=distortion_difference_px(a, b, true.image_size),
        focal_target_rel=float(focal_target[true.modality]),
    )


def compare_rigs(
    estimate: Rig,
    truth: Rig,
    focal_target: Mapping[str, float] = FOCAL_TARGET,
    pose_target: Mapping[str, tuple[float, float]] = POSE_TARGET,
) -> RigComparison:
    """Compare ``estimate`` with ``truth`` sensor by sensor and pair by pair.

    Args:
        estimate: the calibrated rig.
        truth: the reference rig (e.g. ``ground_truth_rig.yaml``).
        focal_target: relative focal-length target per modality.
        pose_target: (rotation deg, translation m) target per modality.

    Returns:
        A :class:`RigComparison`; sensors in only one rig are listed, not compared.

    Raises:
        ValueError: no sensor in common, or a sensor in both rigs with a different modality
            or image size (its intrinsics would not be comparable).
    """
    common = [n for n in truth.names if n in estimate]
    if not common:
        raise ValueError(
            f"the rigs have no sensor in common (estimate: {estimate.names}; truth: {truth.names})"
        )
    for n in common:
        e, t = estimate[n], truth[n]
        if e.modality != t.modality:
            raise ValueError(
                f"sensor {n!r} is a {e.modality} sensor in the estimate but {t.modality} in "
                "the truth"
            )
        if e.image_size != t.image_size:
            raise ValueError(
                f"sensor {n!r} has {e.image_size[0]}x{e.image_size[1]} images in the estimate "
                f"but {t.image_size[0]}x{t.image_size[1]} in the truth; its intrinsics are "
                "not comparable"
            )
    intrinsics = {n: _intrinsics_error(estimate[n], truth[n], focal_target) for n in common}
    pairs = []
    for i, a in enumerate(common):
        for b in common[i + 1 :]:
            rot, t_ab = pose_error(estimate.T(a, b), truth.T(a, b))
            _, t_ba = pose_error(estimate.T(b, a), truth.T(b, a))
            ta, tb = pose_target[truth[a].modality], pose_target[truth[b].modality]
            pairs.append(
                PairError(a, b, rot, max(t_ab, t_ba), max(ta[0], tb[0]), max(ta[1], tb[1]))
            )
    return RigComparison(
        intrinsics=intrinsics,
        pairs=pairs,
        only_in_estimate=[n for n in estimate.names if n not in truth],
        only_in_truth=[n for n in truth.names if n not in estimate],
        estimate_reference=estimate.reference,
        truth_reference=truth.reference,
    )
