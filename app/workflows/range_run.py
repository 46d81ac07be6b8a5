"""TOF range calibration of a capture directory (``trifuse calibrate-range``, the console's
Range panel): detect the board, place it with the rig, fit the correction, validate it.

Each view's board pose comes from the corners every sensor found and the rig's intrinsics
and extrinsics (:func:`calib.board_pose.board_pose`); the TOF pixels on the board get
their reference distances from it (:func:`calib.range_calibration.board_samples`). Every
``holdout_every``-th view is held out of the fit; the error before and after the
correction is reported per accuracy region on the held-out views (the validation) and on
the fitted ones. The stored model is the one validated.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trifuse.app.storage.capture import Capture
from trifuse.app.workflows.calibration_run import DetectionRun, detect_capture
from trifuse.calib.board_pose import board_pose
from trifuse.calib.range_calibration import (
    FitOptions,
    RangeSamples,
    RegionError,
    board_samples,
    fit_range_correction,
    region_errors,
)
from trifuse.calib.range_correction import RangeCorrection
from trifuse.calib.rig import Rig
from trifuse.fusion.geometry import tof_sensor_name

Progress = Callable[[str, float], None]
REPORT_FORMAT = "trifuse-range-report/1"
MAX_POSE_RMS_PX = 1.0
"""A view whose board pose explains some sensor's corners worse than this is skipped: the
rig does not fit that view (a wrong rig file, a board that bent or moved)."""
MIN_VIEW_PIXELS = 50


@dataclass
class RangeRun:
    """What a range calibration did.

    Attributes:
        model: the fitted correction (fitted on ``fit_views`` only).
        fit_views, holdout_views: view names.
        skipped: view -> why it was not used.
        per_view: view -> {pixels, set, pose_rms_px, before_rms_mm, after_rms_mm}.
        holdout, fit: per-region errors (regions 1-4, then 0 = regions 1-3).
    """

    model: RangeCorrection
    fit_views: list[str]
    holdout_views: list[str]
    skipped: dict[str, str]
    per_view: dict[str, dict[str, Any]]
    holdout: list[RegionError]
    fit: list[RegionError]
    tof: str
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


def calibrate_range(
    capture: Capture,
    rig: Rig,
    holdout_every: int = 4,
    options: FitOptions | None = None,
    progress: Progress | None = None,
    detections: DetectionRun | None = None,
) -> RangeRun:
    """Fit and validate the TOF range correction on a capture directory.

    Args:
        capture: views with the TOF's amplitude and distance images and the other sensors.
        rig: a calibrated rig (the board poses come from it).
        holdout_every: every N-th usable view (N >= 2) is held out of the fit.
        options: fit settings.
        progress: called with (stage, fraction 0-1).
        detections: corners already found in the capture (else detected here).

    Raises ValueError (with the reason) when too few views or pixels remain.
    """
    t0 = time.perf_counter()
    if holdout_every < 2:
        raise ValueError(f"holdout_every: expected an integer >= 2, got {holdout_every}")
    tof = tof_sensor_name(rig)
    missing = sorted(set(capture.sensors) - set(rig.names))
    if tof not in capture.sensors:
        raise ValueError(f"{capture.path}: no images of the TOF camera {tof!r}")
    sensors = [s for s in capture.sensors if s in rig]
    capture.check_sizes(rig)
    if detections is None:
        detections = detect_capture(
            capture,
            sensors,
            progress=(lambda s, f: progress(s, 0.8 * f)) if progress else None,
        )
    image_size = rig[tof].image_size
    T_tof_rig = np.linalg.inv(rig[tof].T_rig_sensor)
    samples: dict[str, RangeSamples] = {}
    skipped: dict[str, str] = {}
    pose_rms: dict[str, dict[str, float]] = {}
    views = list(capture.views)
    for k, view in enumerate(views):
        if progress:
            progress(
                f"reference distances ({k + 1}/{len(views)})", 0.8 + 0.1 * (k + 1) / len(views)
            )
        if tof not in view:
            skipped[view.name] = "no TOF image"
            continue
        frame = view.frame(tof)
        if frame.distance_m is None:
            skipped[view.name] = f"no {tof}_distance image"
            continue
        corners = {s: c for s, c in detections.observations.get(view.name, {}).items() if s in rig}
        if not corners:
            skipped[view.name] = "board not found in any sensor"
            continue
        pose = board_pose(rig, corners, capture.board)
        if pose is None:
            skipped[view.name] = "no board pose (PnP failed)"
            continue
        worst = max(pose.rms_px, key=pose.rms_px.get)
        if pose.rms_px[worst] > MAX_POSE_RMS_PX:
            skipped[view.name] = (
                f"the rig does not fit this view: corners of {worst} off by "
                f"{pose.rms_px[worst]:.2f} px RMS (at most {MAX_POSE_RMS_PX} px)"
            )
            continue
        s = board_samples(
            rig[tof].intrinsics,
            image_size,
            T_tof_rig @ pose.T_rig_board,
            capture.board,
            frame.distance_m,
            frame.image,
            view=k,
        )
        if len(s) < MIN_VIEW_PIXELS:
            skipped[view.name] = f"only {len(s)} TOF pixels on the board (need {MIN_VIEW_PIXELS})"
            continue
        samples[view.name] = s
        pose_rms[view.name] = {n: round(v, 3) for n, v in pose.rms_px.items()}
    names = list(samples)
    holdout_views = [n for i, n in enumerate(names) if i % holdout_every == holdout_every - 1]
    fit_views = [n for n in names if n not in holdout_views]
    if not holdout_views or len(fit_views) < 3:
        raise ValueError(
            f"range calibration: {len(names)} usable view(s) (need at least {holdout_every + 3}: "
            f"3 to fit and 1 held out); skipped: "
            + ("; ".join(f"{v}: {r}" for v, r in skipped.items()) or "none")
        )
    if progress:
        progress("fitting", 0.92)
    fitted = RangeSamples.concat([samples[n] for n in fit_views])
    model = fit_range_correction(fitted, image_size, options)
    fit_errors = region_errors(fitted, model, image_size)
    holdout = region_errors(
        RangeSamples.concat([samples[n] for n in holdout_views]), model, image_size
    )
    per_view = {}
    for n in names:
        total = _trusted(region_errors(samples[n], model, image_size))
        per_view[n] = {
            "set": "holdout" if n in holdout_views else "fit",
            "pixels": len(samples[n]),
            "distance_m": round(float(np.median(samples[n].reference_m)), 3),
            "pose_rms_px": pose_rms[n],
            "before_rms_mm": _round(total.before_rms_mm),
            "after_rms_mm": _round(total.after_rms_mm),
        }
    model = dataclasses.replace(
        model,
        fit={
            **model.fit,
            "holdout_views": len(holdout_views),
            "holdout_rms_mm": {
                "before": _round(_trusted(holdout).before_rms_mm),
                "after": _round(_trusted(holdout).after_rms_mm),
            },
            # the distance error left per accuracy region (fusion.registration's range error)
            "holdout_region_rms_mm": {
                str(e.region): _round(e.after_rms_mm) for e in holdout if e.region != 0
            },
        },
    )
    if progress:
        progress("done", 1.0)
    notes = [f"images of sensors not in the rig were ignored: {missing}"] if missing else []
    return RangeRun(
        model,
        fit_views,
        holdout_views,
        skipped,
        per_view,
        holdout,
        fit_errors,
        tof,
        time.perf_counter() - t0,
        notes,
    )


def _trusted(errors: list[RegionError]) -> RegionError:
    return next(e for e in errors if e.region == 0)


def _round(x: float) -> float | None:
    return round(x, 2) if math.isfinite(x) else None


def with_range_correction(rig: Rig, run: RangeRun) -> Rig:
    """A copy of ``rig`` whose TOF carries the run's correction (:meth:`RangeCorrection.
    rounded`, as rig files keep it)."""
    rounded = run.model.rounded()
    return rig.with_sensor(dataclasses.replace(rig[run.tof], range_correction=rounded))


def build_range_report(run: RangeRun, capture: Capture | None = None) -> dict[str, Any]:
    """``range.json`` content."""
    return {
        "format": REPORT_FORMAT,
        "capture": str(capture.path) if capture is not None else None,
        "tof": run.tof,
        "seconds": round(run.seconds, 2),
        "views": {"fit": run.fit_views, "holdout": run.holdout_views, "skipped": run.skipped},
        "regions": {
            "holdout": [e.to_dict() for e in run.holdout],
            "fit": [e.to_dict() for e in run.fit],
        },
        "per_view": run.per_view,
        "model": run.model.fit,
        "notes": run.notes,
    }


def format_range_summary(run: RangeRun) -> str:
    """The terminal summary: RMS distance error per region, before and after."""
    lines = [
        f"TOF range calibration of {run.tof}: fitted on {len(run.fit_views)} view(s), "
        f"validated on {len(run.holdout_views)} held-out view(s) "
        f"({', '.join(run.holdout_views)}) in {run.seconds:.1f} s",
        f"fitted distances {run.model.distance_range_m[0]:.2f}-"
        f"{run.model.distance_range_m[1]:.2f} m (the correction is held constant beyond)",
        "",
        f"{'':<32}{'held-out views':^34}  {'fitted views':^34}",
        f"{'RMS distance error':<32}"
        + f"{'pixels':>8} {'before':>8} {'after':>8} {'ratio':>7}  " * 2,
    ]
    for h, f in zip(run.holdout, run.fit, strict=True):
        cells = []
        for e in (h, f):
            if e.pixels:
                cells.append(
                    f"{e.pixels:>8} {e.before_rms_mm:>5.1f} mm {e.after_rms_mm:>5.1f} mm "
                    f"{e.ratio:>6.1f}x  "
                )
            else:
                cells.append(f"{0:>8} {'-':>8} {'-':>8} {'-':>7}  ")
        lines.append(f"{h.name:<32}" + "".join(cells))
    if run.skipped:
        lines.append("")
        lines.append(f"views not used ({len(run.skipped)}):")
        for v, why in run.skipped.items():
            lines.append(f"  {v}: {why}")
    lines.extend(run.notes)
    return "\n".join(lines)


def region_chart(
    errors: list[RegionError], title: str, size: tuple[int, int] = (640, 360)
) -> np.ndarray:
    """A bar chart (H, W, 3) uint8 RGB of the RMS error per region before (grey) and after
    (blue) the correction: the method's figure 4."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
    left, right, top, bottom = 60, 20, 40, 60
    cv2.putText(img, title, (left, 24), font, 0.5, black, 1, cv2.LINE_AA)
    shown = [e for e in errors if e.pixels]
    if not shown:
        cv2.putText(img, "no pixels", (left, h // 2), font, 0.6, black, 1, cv2.LINE_AA)
        return img
    top_mm = max(max(e.before_rms_mm, e.after_rms_mm) for e in shown)
    step = next(s for s in (1, 2, 5, 10, 20, 50, 100, 200, 500) if top_mm / s <= 6)
    y_max = step * math.ceil(top_mm / step)
    y_of = lambda mm: round(h - bottom - (h - top - bottom) * mm / y_max)  # noqa: E731
    for mm in range(0, int(y_max) + 1, step):
        y = y_of(mm)
        cv2.line(img, (left, y), (w - right, y), (225, 225, 225), 1)
        cv2.putText(img, f"{mm}", (8, y + 4), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.putText(img, "mm", (8, top - 8), font, 0.4, black, 1, cv2.LINE_AA)
    slot = (w - left - right) / len(shown)
    colours = ((170, 170, 170), (40, 110, 220))
    for i, e in enumerate(shown):
        x0 = left + i * slot + 0.15 * slot
        bw = 0.35 * slot
        for j, mm in enumerate((e.before_rms_mm, e.after_rms_mm)):
            xa = round(x0 + j * bw)
            cv2.rectangle(img, (xa, y_of(mm)), (round(xa + bw) - 2, y_of(0)), colours[j], -1)
            cv2.putText(img, f"{mm:.0f}", (xa + 2, y_of(mm) - 4), font, 0.35, black, 1, cv2.LINE_AA)
        label = "1-3" if e.region == 0 else str(e.region)
        cv2.putText(
            img, f"region {label}", (round(x0), h - bottom + 18), font, 0.4, black, 1, cv2.LINE_AA
        )
    for j, text in enumerate(("before", "after")):
        x = left + 140 * j
        cv2.rectangle(img, (x, h - 22), (x + 14, h - 10), colours[j], -1)
        cv2.putText(img, text, (x + 20, h - 11), font, 0.45, black, 1, cv2.LINE_AA)
    return img


def write_png(path: str | Path, rgb: np.ndarray, overwrite: bool = False) -> Path:
    """Write an RGB image as PNG, atomically."""
    from trifuse.app.storage.atomic import atomic_write_bytes

    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"{path}: could not encode the PNG")
    return atomic_write_bytes(path, buf.tobytes(), overwrite=overwrite)
