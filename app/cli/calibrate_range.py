"""``trifuse calibrate-range``: the TOF camera's distance error fitted from a capture
directory, written into the rig."""

from __future__ import annotations

import argparse
from pathlib import Path

from trifuse.app.cli.args import EXIT_OK, Commands, positive_int
from trifuse.app.cli.files import add_rig_out_argument, check_rig_out, write_rig_out
from trifuse.app.cli.output import out, stage_progress


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``calibrate-range CAPTURE_DIR --rig RIG.yaml --out RIG.yaml [--report] [--plot]``."""
    cr = commands.add_parser(
        "calibrate-range",
        help="calibrate the TOF camera's distance error from a capture directory",
        description=(
            "Fit the TOF range correction (distance-dependent wiggling, per-pixel offset, "
            "amplitude term; robust) from the TOF distance images of CAPTURE_DIR: each "
            "view's board pose comes from every sensor's corners and RIG.yaml, every TOF "
            "pixel on the board gets the distance where its ray meets the board. Every N-th "
            "view is held out of the fit to validate it; prints the RMS error before and "
            "after per accuracy region (1: centre 11x11, 2, 3, 4: border, not trusted), and "
            "writes the rig with the correction (range_correction of the TOF)."
        ),
    )
    cr.add_argument("capture_dir", metavar="CAPTURE_DIR", help="the capture directory")
    cr.add_argument("--rig", required=True, metavar="RIG.yaml", help="the calibrated rig")
    add_rig_out_argument(cr)
    cr.add_argument(
        "--report",
        metavar="RANGE.json",
        help="also write the report as JSON (must not exist): per region and per view "
        "errors before and after, views used, held out and skipped",
    )
    cr.add_argument(
        "--plot",
        metavar="RANGE.png",
        help="also write a bar chart of the RMS error per region, before and after "
        "(held-out views; must not exist)",
    )
    cr.add_argument(
        "--holdout-every",
        type=positive_int,
        default=4,
        metavar="N",
        help="hold every N-th usable view out of the fit to validate it (N >= 2; "
        "default: %(default)s)",
    )
    cr.add_argument(
        "--offset-step",
        type=positive_int,
        default=8,
        metavar="PX",
        help="spacing of the per-pixel offset nodes in TOF pixels (default: %(default)s)",
    )
    return cr


def run(args: argparse.Namespace) -> int:
    """Fit the range correction; write the rig with it (and the report and chart)."""
    from trifuse.app.storage.capture import load_capture
    from trifuse.app.storage.rigfile import load_rig
    from trifuse.app.workflows.calibration_run import write_report
    from trifuse.app.workflows.range_run import (
        build_range_report,
        calibrate_range,
        format_range_summary,
        region_chart,
        with_range_correction,
        write_png,
    )
    from trifuse.calib.range_calibration import FitOptions

    rig_path, rig_out = Path(args.rig), Path(args.out)
    check_rig_out(rig_out, rig_path, report=args.report, plot=args.plot)
    rig = load_rig(rig_path)
    capture = load_capture(args.capture_dir)
    out(capture.summary())
    options = FitOptions(offset_step_px=args.offset_step)
    result = calibrate_range(capture, rig, args.holdout_every, options, stage_progress())
    out("")
    out(format_range_summary(result))
    out("")
    write_rig_out(rig_out, rig_path, with_range_correction(rig, result), "range_correction")
    if args.report:
        write_report(Path(args.report), build_range_report(result, capture))
        out(f"report written to {args.report}")
    if args.plot:
        write_png(args.plot, region_chart(result.holdout, "RMS distance error, held-out views"))
        out(f"chart written to {args.plot}")
    return EXIT_OK
