"""Calibrating a capture directory: detection in every image, the joint calibration,
coverage, and the report (``trifuse calibrate`` and, later, the console use this).

An image file that cannot be read (empty, not an image, cut short, corrupted:
:class:`~app.storage.capture.UnreadableImageError`) is skipped: its view keeps its other
sensors, and the file is named where images without a board are (the detections' reasons,
the summary's list, the report's ``detections``) and in the report's ``unreadable_images``.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.storage.atomic import atomic_write_text
from trifuse.app.storage.capture import Capture, CaptureError, UnreadableImageError
from trifuse.app.storage.detection_cache import detect_cached
from trifuse.app.workflows.cross_validation import (
    cross_validate,
    cross_validation_lines,
    skipped,
)
from trifuse.app.workflows.report_format import (
    POLARITY_HEAD,
    coverage_sentence,
    polarity_caption,
    polarity_rows,
    text_table,
    verdict_lines,
)
from trifuse.calib.board import Board
from trifuse.calib.coverage import coverage
from trifuse.calib.detect import Detection
from trifuse.calib.errors import CalibrationError
from trifuse.calib.rig_calibration import CalibrationOptions, SensorSpec, calibrate_rig
from trifuse.calib.rig_result import CalibrationResult
from trifuse.calib.verdict import ZHANG_MIN_VIEWS

Progress = Callable[[str, float], None]


@dataclass
class DetectionRun:
    """Corners found in a capture, and why the other images gave none.

    Attributes:
        observations: view -> sensor -> (N, 2) corners in canonical board order.
        rejected: view -> sensor -> reason the board was not used.
        methods: view -> sensor -> detector that found it.
    """

    observations: dict[str, dict[str, np.ndarray]]
    rejected: dict[str, dict[str, str]]
    methods: dict[str, dict[str, str]]

    def only(self, sensors: list[str]) -> DetectionRun:
        """The same run restricted to ``sensors`` (views left without any are dropped)."""

        def keep(part: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
            out = {v: {s: x for s, x in per.items() if s in sensors} for v, per in part.items()}
            return {v: per for v, per in out.items() if per}

        return DetectionRun(keep(self.observations), keep(self.rejected), keep(self.methods))


def sensor_specs(capture: Capture) -> dict[str, SensorSpec]:
    """Modality and image size of every sensor of the capture.

    Sizes come from ``rig.yaml`` when there is one (load_capture has checked every image
    against it), else from the images, which must then agree across views.
    """
    specs: dict[str, SensorSpec] = {}
    for view in capture.views:
        for name, files in view.files.items():
            size = (files.image.width, files.image.height)
            if capture.rig is not None and name in capture.rig:
                size = capture.rig[name].image_size
            known = specs.get(name)
            if known is not None and known.image_size != size:
                raise CaptureError(
                    f"{files.image.path}: image is {size[0]}x{size[1]} but {name}'s images in "
                    f"earlier views are {known.image_size[0]}x{known.image_size[1]}"
                )
            specs[name] = SensorSpec(name, files.modality, size)
    return specs


def detect_capture(
    capture: Capture,
    sensors: list[str] | None = None,
    workers: int = 2,
    progress: Progress | None = None,
    detect: Callable[[np.ndarray, Board, str], Detection] = detect_cached,
) -> DetectionRun:
    """Detect the board in every image (threads: OpenCV releases the GIL).

    ``detect`` searches one image (default: an image searched before, by a console's
    session or an earlier run, is not searched again: :mod:`app.storage.detection_cache`;
    the benchmarks pass :func:`calib.polarity.detect_board_configured` itself).

    Thermal and TOF images are searched with the board's polarity overrides when
    ``board.yaml`` sets them (:func:`calib.polarity.detect_board_configured`), else as the
    detector assumes; the calibration then finds each sensor's polarity from the data.

    An image that cannot be read (set aside when the capture was indexed, or failing to
    decode now) is rejected with its reason, ``unreadable image <file>, skipped: <why>``
    (:meth:`app.storage.capture.UnreadableImage.describe`); TOF distance images are not
    read (the board is found in the amplitude)."""
    jobs = [(v, s) for v in capture.views for s in v.sensors if sensors is None or s in sensors]
    if not jobs:
        unreadable = [u for _v, u in capture.unreadable if sensors is None or u.sensor in sensors]
        raise CaptureError(
            f"{capture.path}: no images to calibrate ({len(capture.views)} view folders"
            + (f"; {len(unreadable)} unreadable image(s) skipped" if unreadable else "")
            + ")"
        )

    def one(job: tuple[Any, str]) -> tuple[str, str, Detection | None]:
        view, sensor = job
        try:
            frame = view.frame(sensor, distance=False)
        except UnreadableImageError:  # set aside by frame(): rejected below
            return view.name, sensor, None
        return (
            view.name,
            sensor,
            detect(frame.image, capture.board, capture.modalities[sensor]),
        )

    run = DetectionRun({}, {}, {})
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        for k, (view, sensor, det) in enumerate(pool.map(one, jobs)):
            if det is not None and det.found:
                run.observations.setdefault(view, {})[sensor] = det.corners
                run.methods.setdefault(view, {})[sensor] = det.method or ""
            elif det is not None:
                run.rejected.setdefault(view, {})[sensor] = det.reason or "not found"
            if progress:
                progress(f"detecting the board ({k + 1}/{len(jobs)})", (k + 1) / len(jobs))
    for v, u in capture.unreadable:
        if not u.distance and (sensors is None or u.sensor in sensors):
            run.rejected.setdefault(v.name, {})[u.sensor] = u.describe()
    return run


def calibrate_capture(
    capture: Capture,
    options: CalibrationOptions | None = None,
    sensors: list[str] | None = None,
    progress: Progress | None = None,
    detections: DetectionRun | None = None,
    cross_validate: bool = False,
) -> tuple[CalibrationResult, dict[str, Any]]:
    """Detect (unless ``detections`` of every view are given), calibrate and build the
    report of a capture directory.

    With ``cross_validate``, the report's ``cross_validation`` also holds the two halves of
    the views calibrated alone and compared (:mod:`app.workflows.cross_validation`): never
    an error of the calibration, whatever goes wrong there is its ``skipped`` reason."""
    specs = sensor_specs(capture)
    if sensors is not None:
        unknown = sorted(set(sensors) - set(specs))
        if unknown:
            raise CaptureError(
                f"--sensors: no images of {unknown} in {capture.path} (sensors: {sorted(specs)})"
            )
    if len(capture.views) < ZHANG_MIN_VIEWS:
        raise CalibrationError(
            f"{capture.path}: {len(capture.views)} view(s); a calibration needs the board "
            f"in at least {ZHANG_MIN_VIEWS} views per sensor (Zhang's method; about 20 for "
            "a good one)"
        )

    def stage(offset: float, span: float) -> Progress | None:
        if progress is None:
            return None
        return lambda what, frac: progress(what, offset + span * frac)

    if detections is None:
        detections = detect_capture(capture, sensors, progress=stage(0.0, 0.6))
    elif sensors is not None:
        detections = detections.only(sensors)
    if not detections.observations:
        reasons = Counter(r for per in detections.rejected.values() for r in per.values())
        common = "; ".join(f"{n}x {r}" for r, n in reasons.most_common(3))
        raise CalibrationError(
            f"the board ({capture.board.describe()}) was not found in any image: {common}"
        )
    eyes = capture.rig.eyes if capture.rig is not None else {}
    span = 0.3 if cross_validate else 0.4  # the cross-validation: the last tenth
    result = calibrate_rig(
        detections.observations, capture.board, specs, options, progress=stage(0.6, span), eyes=eyes
    )
    # false-colour thermal images: say, wherever notes are shown, that they are not kelvin
    result.notes += [p["note"] for p in capture.palette_report().values()]
    result.excluded_sensors = excluded_with_detection_reasons(result, detections)
    report = build_report(result, detections, capture)
    if cross_validate:
        report["cross_validation"] = _finite(
            cross_validated(result, detections, capture, specs, options, stage(0.9, 0.1))
        )
    return result, report


def cross_validated(
    result: CalibrationResult,
    detections: DetectionRun,
    capture: Capture,
    specs: dict[str, SensorSpec],
    options: CalibrationOptions | None,
    progress: Progress | None,
) -> dict[str, Any]:
    """:func:`app.workflows.cross_validation.cross_validate` of the calibration, on its
    detections; an exception it raises (a defect) becomes its ``skipped`` reason: the
    calibration stands without it."""
    t0 = time.perf_counter()
    try:
        return cross_validate(
            result, detections.observations, capture.board, specs, options, progress
        )
    except Exception as exc:  # a defect: say so in the report, keep the calibration
        cv = skipped(f"failed: {describe_error(exc)}")
        cv["seconds"] = time.perf_counter() - t0
        return cv


def excluded_with_detection_reasons(
    result: CalibrationResult, detections: DetectionRun
) -> dict[str, str]:
    """``result.excluded_sensors`` with what the detection says of each sensor left out:
    when most of its views failed for one reason (e.g. "ChArUco markers not resolvable"),
    that reason, summed over those views, comes first; a sensor found in no view at all
    (so unknown to the calibration) is added."""
    out = dict(result.excluded_sensors)
    views: Counter[str] = Counter()
    failed: dict[str, list[str]] = {}
    for part in (detections.observations, detections.rejected):
        for per in part.values():
            views.update(list(per))  # sensor names, not their values
    for per in detections.rejected.values():
        for s, reason in per.items():
            failed.setdefault(s, []).append(reason)
    for s in sorted(views):
        if s in result.sensors or s in result.intrinsics_only or s not in failed:
            continue
        why = dominant_failure(failed[s], views[s])
        if s in out:
            out[s] = f"{why}; {out[s]}" if why else out[s]
        else:  # found in no view: all failed
            common = Counter(failed[s]).most_common(1)[0][0]
            out[s] = why or f"board not found in any of its {views[s]} views (e.g. {common})"
    return out


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _reason_kind(reason: str) -> str:
    """What a detection reason says without its details: the text before its first ``:``
    or ``;``, bracketed parts dropped, numbers as ``#`` ("board not found", "ChArUco
    markers not resolvable", "ChArUco board seen but only # corner of #")."""
    head = re.split(r"[:;]", reason, maxsplit=1)[0]
    return " ".join(_NUMBER.sub("#", re.sub(r"\([^)]*\)", "", head)).split())


def dominant_failure(reasons: list[str], n_views: int) -> str | None:
    """The reason most of a sensor's ``n_views`` views failed for, as one line, or None
    when no one kind of reason (:func:`_reason_kind`) covers more than half of them.

    The reasons of that kind worded alike are summed up: each number that differs
    between them becomes its range, e.g. "ChArUco markers not resolvable in 15 of 18
    views: quads of about 1.8-7.9 px seen, marker cells of at most 0.3-1.3 px, under the
    2 px ...".
    """
    kinds = Counter(_reason_kind(r) for r in reasons)
    if not kinds:
        return None
    kind, n = kinds.most_common(1)[0]
    if 2 * n <= n_views:
        return None
    group = [r for r in reasons if _reason_kind(r) == kind]
    wording = Counter(_NUMBER.sub("#", r) for r in group).most_common(1)[0][0]
    alike = [r for r in group if _NUMBER.sub("#", r) == wording]
    texts = _NUMBER.split(alike[0])
    numbers = list(zip(*(_NUMBER.findall(r) for r in alike), strict=True))
    merged = texts[0]
    for values, text in zip(numbers, texts[1:], strict=True):
        lo, hi = min(values, key=float), max(values, key=float)
        merged += (lo if float(lo) == float(hi) else f"{lo}-{hi}") + text
    head, colon, tail = merged.partition(": ")
    where = f"in {n} of {n_views} views"
    return f"{head} {where}: {tail}" if colon else f"{merged} ({where})"


def build_report(
    result: CalibrationResult, detections: DetectionRun, capture: Capture
) -> dict[str, Any]:
    """``report.json`` content: the calibration plus detection results and coverage."""
    report = result.to_report()
    report["capture"] = str(capture.path)
    if palettes := capture.palette_report():  # false-colour thermal images, not kelvin
        report["palette_images"] = palettes
    report["detections"] = {
        v: {s: {"found": True, "method": m} for s, m in per.items()}
        for v, per in detections.methods.items()
    }
    for v, per in detections.rejected.items():
        for s, reason in per.items():
            report["detections"].setdefault(v, {})[s] = {"found": False, "reason": reason}
    report["detections"] = dict(sorted(report["detections"].items()))
    report["unreadable_images"] = unreadable_images(capture)
    for name, entry in report["sensors"].items():
        used = [
            detections.observations[v][name]
            for v in sorted(detections.observations)
            if name in detections.observations[v]
            and not result.views.get(v, {}).get(name, _NOT_OUTLIER).outlier
        ]
        cov = coverage(used, capture.board, tuple(entry["image_size"]))
        entry["coverage"] = {
            "x": cov.x,
            "y": cov.y,
            "size": cov.size,
            "skew": cov.skew,
            "good_enough": cov.good_enough,
            "empty_regions": cov.empty_regions,
            "reached": cov.reached,
            "corner_counts": cov.corner_counts.tolist(),
        }
    return _finite(report)


def unreadable_images(capture: Capture) -> list[dict[str, Any]]:
    """The report's ``unreadable_images``: every image file of the capture set aside so
    far, as ``view``, ``sensor``, ``file`` (the path in the capture directory, e.g.
    ``0003/thermal_left.png``), ``why`` and ``distance`` (a TOF distance image: not read by
    the calibration, its sensor kept its amplitude image)."""
    return [
        {
            "view": view.name,
            "sensor": u.sensor,
            "file": f"{view.name}/{u.path.name}",
            "why": u.why,
            "distance": u.distance,
        }
        for view, u in capture.unreadable
    ]


class _NotOutlier:
    outlier = False


_NOT_OUTLIER = _NotOutlier()


def _finite(value: Any) -> Any:
    """JSON cannot hold NaN or infinity: they become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def write_report(path: str | Path, report: dict[str, Any], overwrite: bool = False) -> Path:
    """Write the report as JSON, atomically; an existing file is kept unless ``overwrite``."""
    return atomic_write_text(path, json.dumps(report, indent=1) + "\n", overwrite=overwrite)


def format_summary(result: CalibrationResult, report: dict[str, Any]) -> str:
    """A human-readable summary of a calibration, for the terminal."""
    alone = result.intrinsics_only
    also = f" and the intrinsics of {len(alone)} more (pose unknown)" if alone else ""
    lines = [
        f"Calibrated {len(result.sensors)} sensor(s){also} in {result.seconds:.1f} s, "
        f"reference {result.reference}, overall RMS {result.rms_px:.3f} px",
        "",
    ]
    head = (
        f"{'sensor':<14} {'views':>7} {'RMS px':>7} {'fx':>16} {'fy':>16} {'cx':>15} "
        f"{'cy':>15}  {'t (mm)':>22} {'sigma t':>7} {'sigma R':>8}"
    )
    lines.append(head)
    for name, s in result.sensors.items():
        i, sg = s.intrinsics, s.sigma
        t = s.T_rig_sensor[:3, 3] * 1000
        st = float(np.linalg.norm(sg["translation_m"])) * 1000
        sr = float(np.linalg.norm(sg["rotation_deg"]))
        lines.append(
            f"{name:<14} {s.views_used:>3}/{s.views_detected:<3} {s.rms_px:>7.3f} "
            f"{i.fx:>9.2f}±{sg['fx']:<6.2f} {i.fy:>9.2f}±{sg['fy']:<6.2f} "
            f"{i.cx:>8.2f}±{sg['cx']:<6.2f} {i.cy:>8.2f}±{sg['cy']:<6.2f} "
            f"({t[0]:6.1f},{t[1]:6.1f},{t[2]:6.1f}) {st:6.2f}mm {sr:7.3f}°"
        )
    for name, s in alone.items():
        i, sg = s.intrinsics, s.sigma
        lines.append(
            f"{name:<14} {s.views_used:>3}/{s.views_detected:<3} {s.rms_px:>7.3f} "
            f"{i.fx:>9.2f}±{sg['fx']:<6.2f} {i.fy:>9.2f}±{sg['fy']:<6.2f} "
            f"{i.cx:>8.2f}±{sg['cx']:<6.2f} {i.cy:>8.2f}±{sg['cy']:<6.2f}  pose unknown"
        )
    if result.verdict is not None:
        lines += ["", *verdict_lines(report["verdict"])]
    if cv := cross_validation_lines(report.get("cross_validation")):
        lines += ["", *cv]
    lines.append("")
    for name, entry in report["sensors"].items():
        c = entry["coverage"]
        bars = "  ".join(f"{k} {_bar(c[k])}" for k in ("x", "y", "size", "skew"))
        worst = entry["worst_view"]
        lines.append(f"{name:<14} coverage {bars}  worst view {worst}")
        lines.append(f"{'':<14} {coverage_sentence(np.asarray(c['corner_counts']))}")
    if report.get("polarity"):
        lines += ["", polarity_caption(report["polarity"]) + ":"]
        lines += [
            "  " + line for line in text_table(POLARITY_HEAD, polarity_rows(report["polarity"]))
        ]
    if alone:
        lines.append("")
        for name, s in alone.items():
            lines.append(f"intrinsics only: {name}: {s.pose_unknown}")
    if result.excluded_sensors:
        lines.append("")
        for name, why in result.excluded_sensors.items():
            lines.append(f"not calibrated: {name}: {why}")
    if result.notes:
        lines.append("")
        lines += [f"note: {note}" for note in result.notes]
    view_outliers = [o for o in result.outliers if o.corner is None]
    corner_outliers = [o for o in result.outliers if o.corner is not None]
    if result.outliers:
        lines.append("")
        lines.append(
            f"outliers left out: {len(view_outliers)} view(s), {len(corner_outliers)} corner(s)"
        )
        for o in view_outliers:
            lines.append(f"  view {o.view} of {o.sensor}: {o.reason}")
        for o in corner_outliers[:10]:
            lines.append(f"  view {o.view} of {o.sensor}, corner {o.corner}: {o.reason}")
        if len(corner_outliers) > 10:
            lines.append(f"  ... and {len(corner_outliers) - 10} more corners (report.json)")
    rejected: dict[tuple[str, str], list[str]] = {}
    for view, per in report["detections"].items():
        for sensor, d in per.items():
            if not d["found"]:
                rejected.setdefault((sensor, d["reason"]), []).append(view)
    if rejected:
        lines.append("")
        lines.append("images without a usable board (sensor, view folder: why):")
        for (sensor, reason), views in sorted(rejected.items(), key=lambda i: (i[0][0], i[1])):
            lines.append(f"  {sensor}, {_views_text(views)}: {reason}")
    distances = [u for u in report.get("unreadable_images") or [] if u["distance"]]
    if distances:
        lines.append("")
        lines.append("unreadable TOF distance images, skipped (not needed to calibrate):")
        lines += [f"  {u['file']}: {u['why']}" for u in distances]
    return "\n".join(lines)


def _views_text(views: list[str], at_most: int = 6) -> str:
    """``view 0004`` or ``views 0004, 0011`` (the first ``at_most``, then how many more)."""
    if len(views) == 1:
        return f"view {views[0]}"
    shown = ", ".join(views[:at_most])
    more = f" and {len(views) - at_most} more" if len(views) > at_most else ""
    return f"views {shown}{more}"


def _bar(fraction: float, width: int = 10) -> str:
    n = round(max(0.0, min(1.0, fraction)) * width)
    return "[" + "#" * n + "." * (width - n) + "]"
