"""``trifuse analyze``: how TOF distance and pixel errors shift the fused pixels (the
method's Table 1), as a table, JSON or curves."""

from __future__ import annotations

import argparse
from pathlib import Path

from trifuse.app.cli.args import (
    EXIT_OK,
    PROG,
    Commands,
    UsageError,
    non_negative,
    positive,
    tof_pixel,
)
from trifuse.app.cli.files import load_rig_arg, refuse_existing
from trifuse.app.cli.output import out


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``analyze RIG.yaml [--distance-error-mm] [--tof-pixel U,V ...] [--json] [--plot]``."""
    ana = commands.add_parser(
        "analyze",
        help="how TOF distance and pixel errors shift the fused pixels (the method's Table 1)",
        description=(
            "For TOF pixels (default: the TOF's principal point and the point on its x axis "
            "at the edge of accuracy region 3) and radial distances 0.1-10 m, compute the "
            "pixel shift (dx, dy) that a TOF distance error, and a TOF pixel error along x, "
            "cause in every other sensor of RIG.yaml, and the radial distance below which "
            "that shift exceeds the threshold. Prints a table like the method's Table 1 "
            "('–' = the shift never reaches the threshold in the range), or JSON "
            "(--json), and optionally draws the curves (--plot). Definitions: "
            "fusion/precision.py."
        ),
    )
    ana.add_argument("rig", metavar="RIG.yaml", help="the rig file")
    ana.add_argument(
        "--distance-error-mm",
        type=non_negative,
        default=41.0,
        metavar="MM",
        help="TOF radial distance error in millimetres (default: %(default)g, the method's "
        "value before range calibration; 15 after)",
    )
    ana.add_argument(
        "--tof-pixel-error",
        type=non_negative,
        default=0.5,
        metavar="PX",
        help="TOF pixel error along the TOF image's x axis, in TOF pixels (default: %(default)g)",
    )
    ana.add_argument(
        "--threshold-px",
        type=positive,
        default=0.5,
        metavar="PX",
        help="shift in a sensor's pixels that matters for the fusion (default: %(default)g)",
    )
    ana.add_argument(
        "--tof-pixel",
        type=tof_pixel,
        action="append",
        metavar="U,V",
        help="TOF pixel to analyse (repeatable; replaces the defaults: the principal point "
        "and the edge of region 3 on the x axis)",
    )
    ana.add_argument(
        "--step-m",
        type=positive,
        default=0.01,
        metavar="M",
        help="radial distance step of the curves in metres (default: %(default)g, "
        "991 samples over 0.1-10 m)",
    )
    ana.add_argument(
        "--tof",
        metavar="NAME",
        help="the TOF sensor (default: the rig's only sensor of modality tof)",
    )
    ana.add_argument(
        "--json",
        action="store_true",
        help="print JSON instead of the table: {distance_error|tof_pixel_error: "
        "{'U,V': {sensor: {x_m, y_m, curve: {distance_m, dx_px, dy_px}}}}}",
    )
    ana.add_argument(
        "--plot",
        metavar="OUT.png",
        help="also draw the curves (|dx|, |dy| against distance, log scale) into this PNG "
        "(must not exist)",
    )
    return ana


def run(args: argparse.Namespace) -> int:
    """Analyse the rig's TOF; print the table (or JSON); draw the curves into ``--plot``."""
    import json

    from trifuse.app.cli.analyze_plot import analysis_plot
    from trifuse.app.cli.analyze_table import analysis_table
    from trifuse.app.storage.atomic import atomic_write_bytes
    from trifuse.fusion.precision import (
        RANGE_MAX_M,
        RANGE_MIN_M,
        analyze_precision,
        sample_distances,
        tof_pixel_label,
    )

    plot = Path(args.plot) if args.plot else None
    if plot is not None and plot.exists():
        refuse_existing("--plot", plot)
    rig = load_rig_arg(args.rig)
    if args.tof is not None and args.tof not in rig:
        raise UsageError(f"--tof: no sensor {args.tof!r} in {args.rig} (sensors: {rig.names})")
    tofs = rig.by_modality("tof")
    if args.tof is None and len(tofs) != 1:
        raise ValueError(
            f"{args.rig}: expected exactly one sensor of modality 'tof', got {tofs}"
            + ("; name the TOF sensor with --tof" if tofs else "")
        )
    try:
        distances = sample_distances(RANGE_MIN_M, RANGE_MAX_M, args.step_m)
    except ValueError as exc:
        raise UsageError(f"{PROG} analyze: --step-m: {exc}") from None
    analysis = analyze_precision(
        rig,
        tof_pixels=args.tof_pixel,
        distance_error_m=args.distance_error_mm / 1000.0,
        tof_pixel_error_px=args.tof_pixel_error,
        threshold_px=args.threshold_px,
        distance_m=distances,
        tof=args.tof,
    )
    labels = {
        key: tof_pixel_label(rig, pixel, analysis.tof)
        for key, pixel in zip(analysis.distance_error, analysis.tof_pixels, strict=True)
    }
    range_m = (float(distances[0]), float(distances[-1]))
    if args.json:
        out(json.dumps(analysis.as_dict(), allow_nan=False, separators=(",", ":")))
    else:
        out(analysis_table(analysis, labels, range_m))
    if plot is not None:
        atomic_write_bytes(plot, analysis_plot(analysis, labels, range_m), overwrite=False)
        if not args.json:
            out(f"\nplot written to {plot}")
    return EXIT_OK
