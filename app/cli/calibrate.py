"""``trifuse calibrate``: every sensor's intrinsics and 6-DOF pose from a capture
directory, optionally compared with a true rig."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.cli.args import EXIT_OK, PROG, Commands, checked
from trifuse.app.cli.files import load_rig_arg, refuse_existing
from trifuse.app.cli.output import err, out, stage_progress

if TYPE_CHECKING:
    from trifuse.app.storage.capture import Capture
    from trifuse.calib.rig import Rig


ZHANG_MIN_VIEWS = 3  # calib.verdict.ZHANG_MIN_VIEWS (not imported: the CLI starts fast)
MIN_VIEWS = checked(
    int,
    lambda v: v >= ZHANG_MIN_VIEWS,
    "an integer",
    f"an integer of at least {ZHANG_MIN_VIEWS} (Zhang's method needs {ZHANG_MIN_VIEWS} views)",
    show_value=True,
)


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``calibrate CAPTURE_DIR --out RIG.yaml [--report] [--truth] ...``."""
    cal = commands.add_parser(
        "calibrate",
        help="calibrate every sensor's intrinsics and 6-DOF pose from a capture directory",
        description=(
            "Detect the checkerboard in every image of CAPTURE_DIR (docs/FORMATS.md), "
            "calibrate each sensor's intrinsics (Zhang) and then the whole rig jointly "
            "(every sensor pose, every board pose and the intrinsics, robust loss, outlier "
            "views and corners flagged and left out), and write the calibrated rig file "
            "with 1-sigma uncertainties. Every sensor that sees the board in at least 3 "
            "views (Zhang's minimum) is calibrated; a verdict per sensor and per pair of "
            "sensors (good, usable, poor) judges the uncertainty against the targets and "
            "says which views to capture next. The views are then split into two halves "
            "(alternate views), each calibrated alone, and per eye the summary says how far "
            "apart the two halves' fusions put a thermal value (colour pixels, 0.5-10 m) "
            "against what their uncertainty predicts (--no-cross-validation skips it). "
            "Prints a summary: RMS per sensor, parameters with their uncertainty, the "
            "verdicts and advice, the cross-validation, coverage of each image, outliers "
            "and rejected images."
        ),
    )
    cal.add_argument("capture_dir", metavar="CAPTURE_DIR", help="the capture directory")
    cal.add_argument(
        "--out",
        required=True,
        metavar="RIG.yaml",
        help="calibrated rig file to write (must not exist)",
    )
    cal.add_argument(
        "--report",
        metavar="REPORT.json",
        help="also write the full report as JSON (must not exist): per sensor "
        "RMS, views, intrinsics, distortion, pose and sigma; per view and sensor "
        "the RMS and outlier flag; detections, coverage, outliers",
    )
    cal.add_argument(
        "--report-html",
        metavar="REPORT.html",
        help="also write the report as one self-contained HTML page to read and print "
        "(must not exist): verdict, per sensor intrinsics and pose with 1-sigma, per-view "
        "and per-corner residual plots, coverage, decisions, outliers (docs/FORMATS.md)",
    )
    cal.add_argument(
        "--reference",
        metavar="NAME",
        help="sensor whose frame is the rig frame (default: the TOF camera, "
        "else the first sensor by name)",
    )
    cal.add_argument(
        "--sensors",
        metavar="A,B,...",
        help="calibrate only these sensors (comma-separated; default: all)",
    )
    cal.add_argument(
        "--fixed-intrinsics",
        action="store_true",
        help="keep each sensor's Zhang intrinsics in the joint refinement "
        "(default: refine them with the poses)",
    )
    cal.add_argument(
        "--min-views",
        type=MIN_VIEWS,
        default=ZHANG_MIN_VIEWS,
        metavar="N",
        help="strict mode: leave out (with the reason) every sensor that sees the board in "
        "fewer than N views (default: %(default)s, Zhang's minimum; sensors with few views "
        "are calibrated and their verdict says how well)",
    )
    cal.add_argument(
        "--no-cross-validation",
        action="store_true",
        help="skip the cross-validation (by default the views are split into two halves, "
        "alternate views, each calibrated alone, and the summary and report give how far "
        "apart their fusions put a thermal value, per eye, in colour pixels over 0.5-10 m, "
        "against what the halves' uncertainty predicts; it needs the eyes, the TOF and at "
        "least 3 views of each in each half)",
    )
    cal.add_argument(
        "--truth",
        metavar="TRUTH.yaml",
        help="also compare the result with this rig (e.g. the capture's "
        "ground_truth_rig.yaml), as 'trifuse compare' does; the report gains the comparison",
    )
    return cal


def run(args: argparse.Namespace) -> int:
    """Calibrate ``args.capture_dir``; write the rig (and report); compare with ``--truth``;
    say how long it all took (the summary's time is the calibration's alone)."""
    t_start = time.perf_counter()
    from trifuse.app.storage.capture import load_capture
    from trifuse.app.storage.detection_cache import shared_cache
    from trifuse.app.storage.rigfile import save_rig
    from trifuse.app.workflows.calibration_run import (
        calibrate_capture,
        format_summary,
        write_report,
    )
    from trifuse.app.workflows.cross_validation import skipped
    from trifuse.calib.rig_calibration import CalibrationOptions

    rig_out, report_path = Path(args.out), Path(args.report) if args.report else None
    html_path = Path(args.report_html) if args.report_html else None
    for flag, path in (("--out", rig_out), ("--report", report_path), ("--report-html", html_path)):
        if path is not None and path.exists():
            refuse_existing(flag, path)
    truth = load_rig_arg(args.truth, "--truth") if args.truth else None
    capture = load_capture(args.capture_dir)
    if truth is not None:
        check_truth_fits(truth, capture, args.truth)
    out(capture.summary())
    t_loaded = time.perf_counter()
    options = CalibrationOptions(
        reference=args.reference,
        refine_intrinsics=not args.fixed_intrinsics,
        min_views=args.min_views,
    )
    sensors = args.sensors.split(",") if args.sensors else None
    cache = shared_cache()
    lookups, hits = cache.lookups, cache.hits
    cross_validate = not args.no_cross_validation
    result, report = calibrate_capture(
        capture, options, sensors, stage_progress(), cross_validate=cross_validate
    )
    if not cross_validate:
        report["cross_validation"] = skipped("not run (--no-cross-validation)")
    cross_validation_s = float(report["cross_validation"]["seconds"] or 0.0)
    lookups, hits = cache.lookups - lookups, cache.hits - hits
    t_calibrated = time.perf_counter()
    out("")
    out(format_summary(result, report))
    if truth is not None:
        from trifuse.app.workflows.report_format import comparison_text
        from trifuse.calib.rig_compare import compare_rigs

        try:
            comparison = compare_rigs(result.rig(), truth)
        except ValueError as exc:  # e.g. every sensor in common was left out
            err(f"{PROG}: warning: not compared with --truth {args.truth}: {exc}")
        else:
            report["comparison"] = {"truth": str(args.truth), **comparison.as_dict()}
            out("")
            out(comparison_text(comparison, "the calibration", str(args.truth)))
    save_rig(rig_out, result.rig())
    out("")
    out(f"rig written to {rig_out}")
    if report_path is not None:
        write_report(report_path, report)
        out(f"report written to {report_path}")
    if html_path is not None:
        from trifuse.app.workflows.report_html import command_line, write_report_html

        write_report_html(html_path, report, result.corners, command_line(args))
        out(f"HTML report written to {html_path}")
    out(
        time_text(
            time.perf_counter() - t_start,
            t_loaded - t_start,
            t_calibrated - t_loaded - result.seconds - cross_validation_s,
            result.seconds,
            (hits, lookups),
            cross_validation_s,
        )
    )
    return EXIT_OK


def time_text(
    total_s: float,
    reading_s: float,
    detecting_s: float,
    calibrating_s: float,
    cached: tuple[int, int] = (0, 0),
    cross_validation_s: float = 0.0,
) -> str:
    """``Took 14.2 s in all: starting and reading the capture 0.4 s, detecting the board
    10.6 s, calibrating 2.9 s, cross-validation 1.7 s, the rest 0.3 s`` (starting: the
    imports; the rest: comparing, writing; the cross-validation only when it took a tenth
    of a second or more: it ran). ``cached``: (images whose corners came from the
    detection cache, images); when any did, the detection says so: ``detecting the board
    0.1 s (12 of 14 images searched before)``."""
    rest_s = max(0.0, total_s - reading_s - detecting_s - calibrating_s - cross_validation_s)
    hits, images = cached
    before = f" ({hits} of {images} images searched before)" if hits else ""
    cv = f"cross-validation {cross_validation_s:.1f} s, " if cross_validation_s >= 0.05 else ""
    return (
        f"Took {total_s:.1f} s in all: starting and reading the capture {reading_s:.1f} s, "
        f"detecting the board {detecting_s:.1f} s{before}, calibrating {calibrating_s:.1f} s, "
        f"{cv}the rest {rest_s:.1f} s"
    )


def check_truth_fits(truth: Rig, capture: Capture, path: str) -> None:
    """Before calibrating: ``--truth`` must share a sensor with the capture, of the same
    modality and image size (else the comparison at the end would fail)."""
    from trifuse.app.workflows.calibration_run import sensor_specs

    specs = sensor_specs(capture)
    common = [n for n in truth.names if n in specs]
    if not common:
        raise ValueError(
            f"--truth {path}: no sensor in common with {capture.path} "
            f"(truth: {truth.names}; capture: {sorted(specs)})"
        )
    for n in common:
        t, spec = truth[n], specs[n]
        if (t.modality, t.image_size) != (spec.modality, tuple(spec.image_size)):
            raise ValueError(
                f"--truth {path}: sensor {n!r} is {t.modality} {t.image_size[0]}x"
                f"{t.image_size[1]} there but {spec.modality} {spec.image_size[0]}x"
                f"{spec.image_size[1]} in {capture.path}"
            )
