"""Cross-validation of a rig calibration (issue 34): the views split into two halves, each
half calibrated alone, and how far apart the two calibrations' fusions put the same thermal
value, per eye, in colour pixels over the working range. mrcal's cross-validation is the
anchor; ours is in the units the operator sees.

The halves are alternate views in capture order (0001, 0003, ... and 0002, 0004, ...), so
that a slow drift of the capture (the light, the board's heating) is in both (so is a
sensor that moved once, halfway: the residuals show that, not this), and each is
calibrated from the detections the full run used (no second detection) with the full run's
options and reference sensor. Per eye, :func:`fusion.registration.mapping_difference`
lets each half's rig fuse the same TOF measurements of a wall facing the colour camera at
0.5-10 m (:data:`DISTANCES_M`) and gives, per distance, the median, 95th percentile and
largest distance between the two thermal values' colour pixels.

**What the halves should differ by.** Each half's own covariance gives the registration's
1-sigma at each distance (:func:`fusion.registration.sigma_vs_distance`, its calibration
share: the semi-major axis of the landing point's 1-sigma ellipse, median over the wall).
Two independent halves differ by a vector whose covariance is the sum of theirs, so the
predicted difference is ``sqrt(sigma_A^2 + sigma_B^2)``. With halves each sqrt(2) times as
uncertain as the full calibration this would be ``2 sigma_full``; measured on the
simulator's 30 views (seed 1) the halves' sigmas are 1.4-2.3 times the full one and their
combination 2.4-2.8 ``sigma_full``, on 16 projected views (30 seeds) 2.3-6.7 (median 3.6):
half the views carry less than half the information (fewer poses of each kind, a
cluster-robust estimate from fewer images), so the halves' own sigmas are used, and the
full calibration's is reported beside them.

**When the halves disagree** (:data:`CONSISTENT_FACTOR`). At one colour pixel the
difference is a 2-D Gaussian vector; its length over the ellipse's semi-major axis
follows, between a half-normal (a flat ellipse) and a Rayleigh law (a round one), with
99th percentiles of 2.58 and 3.03. A difference more than 3 times the prediction at any
distance therefore happens about once in a hundred calibrations whose halves agree with
their covariance: the halves are then said to disagree (a loose mount, frames out of step,
a few views that pull the solution, or a covariance that understates the error). A systematic
error that every view shares (the simulator's thermal corners, docs/FINDINGS.md) is in
both halves and does not show here. Measured on the simulator's 30 views: the halves
differ by 0.55-1.7 times the prediction (worst at 0.5 m, 0.35 and 0.43 colour px); on 16
projected views with only random corner noise (30 seeds, both eyes) the largest ratio was
0.69 in the median, 1.06 at the 90th percentile and 1.30 at most (the cluster-robust
covariance errs on the cautious side): never near 3.

Nothing here fails the calibration: a capture that cannot be halved, an eye without
enough views in a half, a half that cannot be calibrated give a ``skipped`` reason.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.errors import CalibrationError
from trifuse.calib.rig import Rig
from trifuse.calib.rig_calibration import CalibrationOptions, SensorSpec, calibrate_rig
from trifuse.calib.rig_result import CalibrationResult
from trifuse.calib.verdict import ZHANG_MIN_VIEWS
from trifuse.fusion.registration import mapping_difference, sigma_vs_distance

Progress = Callable[[str, float], None]

DISTANCES_M = np.arange(0.5, 10.0 + 1e-9, 0.5)
"""Where the halves' mappings are compared: the working range, every 0.5 m (metres)."""
MAPPING_CELL_PX = 32
"""Colour pixels between the compared pixels (:func:`mapping_difference`)."""
SIGMA_CELL_PX = 64
"""Colour pixels between the predicted sigmas (the Precision panel's: medians to 1 %,
0.07 s an eye and rig against 0.4 s at 32)."""
CONSISTENT_FACTOR = 3.0
"""The halves agree when their difference is at most this times what their sigmas
predict, at every distance (the module's docstring derives it)."""
HALVES = ("A", "B")


def split_views(views: Sequence[str]) -> tuple[list[str], list[str]]:
    """Alternate views in capture order (their names sorted): the 1st, 3rd, ... and the
    2nd, 4th, ..."""
    ordered = sorted(views)
    return ordered[0::2], ordered[1::2]


def skipped(reason: str, halves: tuple[list[str], list[str]] = ([], [])) -> dict[str, Any]:
    """The report's ``cross_validation`` when it was not run, with the reason."""
    return {
        "skipped": reason,
        "views": dict(zip(HALVES, (list(h) for h in halves), strict=True)),
        "tof": None,
        "eyes": {},
        "seconds": 0.0,
        "factor": CONSISTENT_FACTOR,
    }


def cross_validate(
    result: CalibrationResult,
    observations: Mapping[str, Mapping[str, np.ndarray]],
    board: Board,
    specs: Mapping[str, SensorSpec],
    options: CalibrationOptions | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Calibrate two halves of the views and compare their fused mappings, per eye.

    Args:
        result: the calibration of every view (its reference, eyes and sensors).
        observations: view -> sensor -> (N, 2) corners, pixels: the detections ``result``
            was calibrated from.
        board, specs, options: as the full calibration had them.
        progress: called with (stage, fraction done 0-1).

    Returns:
        Plain data (the report's ``cross_validation``, docs/FORMATS.md): ``skipped`` (None,
        or why it was not run), ``views`` (``A``, ``B``: each half's views), ``tof``,
        ``factor``, ``seconds``, and ``eyes``: per eye ``color``, ``thermal``,
        ``skipped`` (None or why), and when compared ``distance_m``, ``median_px``,
        ``p95_px``, ``max_px`` (difference of the halves' mappings per distance, colour
        px), ``worst_median_px`` and ``at_m``, ``predicted_sigma_px`` (the full
        calibration's 1-sigma), ``half_sigma_px`` (``A``, ``B``),
        ``predicted_difference_px``, ``ratio`` and ``ratio_at_m`` (the largest difference
        over prediction and where), ``consistent`` and ``verdict``.
    """
    t0 = time.perf_counter()
    report = progress or (lambda _stage, _fraction: None)
    opts = options or CalibrationOptions()
    sensors = set(result.sensors)
    obs = {v: {s: c for s, c in per.items() if s in sensors} for v, per in observations.items()}
    halves = split_views([v for v, per in obs.items() if per])
    out = skipped("", halves)

    def done(why: str | None = None) -> dict[str, Any]:
        out["skipped"], out["seconds"] = why, time.perf_counter() - t0
        report("cross-validation skipped" if why else "cross-validation done", 1.0)
        return out

    if not result.eyes:
        return done("no eyes to compare (the capture's rig.yaml names no colour + thermal pair)")
    tofs = [n for n, s in result.sensors.items() if s.modality == "tof"]
    if not tofs:
        return done("no TOF calibrated: the fusion takes its depth from the TOF")
    tof = out["tof"] = result.reference if result.reference in tofs else tofs[0]
    per_half = max(opts.min_views, ZHANG_MIN_VIEWS)
    n_views = len(halves[0]) + len(halves[1])
    if n_views < 2 * per_half:
        return done(
            f"{n_views} views: two halves need at least {per_half} views each "
            f"({2 * per_half} in all)"
        )
    eyes: dict[str, dict[str, Any]] = {}
    for name, eye in result.eyes.items():
        eyes[name] = {"color": eye.color, "thermal": eye.thermal, "skipped": None}
        eyes[name]["skipped"] = _too_few(eye.color, eye.thermal, tof, result, obs, halves)
    out["eyes"] = eyes
    if all(e["skipped"] for e in eyes.values()):
        return done(None)

    rigs: list[Rig] = []
    for k, (half, views) in enumerate(zip(HALVES, halves, strict=True)):
        stage = f"cross-validation: calibrating half {half} ({len(views)} views)"
        try:
            sub = calibrate_rig(
                {v: obs[v] for v in views},
                board,
                specs,
                replace(opts, reference=result.reference),
                lambda _what, f, k=k, stage=stage: report(stage, 0.4 * (k + f)),
                result.eyes,
                judge=False,
            )
        except (CalibrationError, ValueError) as exc:
            return done(f"half {half} ({_views_text(views)}) cannot be calibrated: {exc}")
        for e in eyes.values():
            if e["skipped"] is None:
                e["skipped"] = _not_calibrated(e, tof, sub, half)
        rigs.append(sub.rig())

    full = result.rig()
    for k, e in enumerate(eyes.values()):
        report("cross-validation: the halves' mappings", 0.8 + 0.2 * k / len(eyes))
        if e["skipped"] is None:
            e.update(_compare(full, rigs, e["color"], e["thermal"], tof))
    return done(None)


def _too_few(
    color: str,
    thermal: str,
    tof: str,
    result: CalibrationResult,
    obs: Mapping[str, Mapping[str, np.ndarray]],
    halves: tuple[list[str], list[str]],
) -> str | None:
    """Why an eye cannot be compared before calibrating the halves (a sensor not
    calibrated, or seen in too few views of a half), or None."""
    for s in (color, thermal, tof):
        if s not in result.sensors:
            why = result.excluded_sensors.get(s) or (
                result.intrinsics_only[s].pose_unknown if s in result.intrinsics_only else ""
            )
            return f"{s} is not calibrated" + (f": {why}" if why else "")
    need = max(result.min_views, ZHANG_MIN_VIEWS)  # what a half's calibration asks
    for s in (color, thermal, tof):
        for half, views in zip(HALVES, halves, strict=True):
            n = sum(1 for v in views if s in obs[v])
            if n < need:
                return (
                    f"{s} sees the board in {n} of half {half}'s {len(views)} views; a half "
                    f"needs {need}"
                )
    return None


def _not_calibrated(
    eye: Mapping[str, Any], tof: str, sub: CalibrationResult, half: str
) -> str | None:
    """Why a half's calibration leaves an eye out (one of its sensors or the TOF not
    calibrated from that half), or None."""
    for s in (eye["color"], eye["thermal"], tof):
        if s not in sub.sensors:
            why = sub.excluded_sensors.get(s) or (
                "pose unknown" if s in sub.intrinsics_only else "not calibrated"
            )
            return f"{s} not calibrated from half {half}: {why}"
    return None


def _compare(full: Rig, rigs: Sequence[Rig], color: str, thermal: str, tof: str) -> dict[str, Any]:
    """One eye's figures: the halves' mapping difference, the predicted sigmas, the
    verdict (or ``skipped`` when no distance has the wall in all three sensors)."""
    diff = mapping_difference(rigs[0], rigs[1], color, thermal, tof, DISTANCES_M, MAPPING_CELL_PX)
    if not np.isfinite(diff.median_px).any():
        return {
            "skipped": f"no distance of {DISTANCES_M[0]:g}-{DISTANCES_M[-1]:g} m at which "
            f"{color}, {thermal} and {tof} all see a wall facing {color}"
        }

    def sigma(rig: Rig) -> np.ndarray:
        curve = sigma_vs_distance(rig, color, thermal, tof, DISTANCES_M, cell_px=SIGMA_CELL_PX)
        return curve.median_px["calibration"]

    half_sigma = [sigma(r) for r in rigs]
    predicted = np.hypot(*half_sigma)
    worst, at_m = diff.worst()
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(predicted > 0, diff.median_px / predicted, np.nan)
    entry: dict[str, Any] = {
        "distance_m": DISTANCES_M.tolist(),
        "median_px": diff.median_px.tolist(),
        "p95_px": diff.p95_px.tolist(),
        "max_px": diff.max_px.tolist(),
        "worst_median_px": worst,
        "at_m": at_m,
        "predicted_sigma_px": sigma(full).tolist(),
        "half_sigma_px": {h: s.tolist() for h, s in zip(HALVES, half_sigma, strict=True)},
        "predicted_difference_px": predicted.tolist(),
        "ratio": None,
        "ratio_at_m": None,
        "consistent": None,
        "verdict": "not judged: the halves' calibrations have no covariance",
    }
    if np.isfinite(ratio).any():
        i = int(np.nanargmax(ratio))
        r, d = float(ratio[i]), float(DISTANCES_M[i])
        entry.update(ratio=r, ratio_at_m=d, consistent=r <= CONSISTENT_FACTOR)
        entry["verdict"] = (
            "consistent"
            if r <= CONSISTENT_FACTOR
            else f"halves disagree: {r:.1f}x the difference their sigmas predict at {d:g} m "
            f"({_px(diff.median_px[i])} against {_px(predicted[i])} px): the halves' views "
            "do not describe one rig (a loose mount, frames out of step, a few views that "
            "pull the solution) or the covariance understates the error"
        )
    return entry


def cross_validation_lines(cv: Mapping[str, Any] | None) -> list[str]:
    """The summary's lines (the terminal, the Calibration panel): one per eye,
    ``cross-validation (2 halves of 30 views): left eye worst 0.35 px at 0.5 m, predicted
    0.25 px: consistent`` (:func:`eye_line`), or why it was skipped; none without a
    cross-validation."""
    if not cv:
        return []
    if cv.get("skipped"):
        return [f"cross-validation skipped: {cv['skipped']}"]
    n = sum(len(v) for v in (cv.get("views") or {}).values())
    return [
        f"cross-validation (2 halves of {n} views): {eye_line(name, e)}"
        for name, e in (cv.get("eyes") or {}).items()
    ]


def eye_line(name: str, e: Mapping[str, Any]) -> str:
    """One eye's result in words: ``left eye worst 0.35 px at 0.5 m, predicted 0.25 px:
    consistent`` (the largest median difference of the halves' mappings, where, and the
    difference their sigmas predict there, then the verdict), or ``left eye skipped: <why>``."""
    if e.get("skipped"):
        return f"{name} eye skipped: {e['skipped']}"
    at = e["at_m"]
    i = int(np.argmin(np.abs(np.asarray(e["distance_m"], dtype=float) - at)))
    predicted = e["predicted_difference_px"][i]
    pred = f", predicted {_px(predicted)} px" if predicted is not None else ""
    return f"{name} eye worst {_px(e['worst_median_px'])} px at {at:g} m{pred}: {e['verdict']}"


def _px(value: float | None) -> str:
    """A pixel figure: two decimals, two significant digits below 0.1 (``0.35``,
    ``0.047``); ``–`` for none."""
    if value is None or not np.isfinite(value):
        return "–"
    return f"{value:.2f}" if abs(value) >= 0.1 else f"{value:.2g}"


def _views_text(views: Sequence[str], at_most: int = 4) -> str:
    """``views 0001, 0003, 0005 and 12 more``."""
    shown = ", ".join(views[:at_most])
    more = f" and {len(views) - at_most} more" if len(views) > at_most else ""
    return f"views {shown}{more}"
