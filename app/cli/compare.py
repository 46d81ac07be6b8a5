"""``trifuse compare``: a calibrated rig against the true one, judged against the
calibration targets."""

from __future__ import annotations

import argparse

from trifuse.app.cli.args import EXIT_FAILURE, EXIT_OK, Commands
from trifuse.app.cli.files import load_rig_arg
from trifuse.app.cli.output import out


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``compare RIG.yaml TRUTH.yaml [--json]``."""
    cmp = commands.add_parser(
        "compare",
        help="compare a calibrated rig with the ground truth (errors against the targets)",
        description=(
            "Compare RIG.yaml with TRUTH.yaml (e.g. a simulated capture's "
            "ground_truth_rig.yaml): per sensor the intrinsic errors (fx, fy, cx, cy in px, "
            "fx and fy in %, and how far apart the distortion models put a pixel), and for "
            "every pair of sensors the error of their relative pose inv(T_rig_a) @ T_rig_b "
            "(rotation in degrees, translation in mm; independent of each rig's reference "
            "sensor). Each judged figure is marked pass or FAIL against the calibration "
            "targets: focal lengths within 0.3 % (colour, thermal) and 1 % (TOF); poses "
            "within 0.1 deg and 1 mm, 0.2 deg and 3 mm for pairs with the TOF. Sensors in "
            "one rig only are listed, not compared. Ends with a one-line verdict; the exit "
            "status is 0 when every figure meets its target, 1 when one does not."
        ),
    )
    cmp.add_argument("rig", metavar="RIG.yaml", help="the calibrated rig")
    cmp.add_argument("truth", metavar="TRUTH.yaml", help="the true (or reference) rig")
    cmp.add_argument(
        "--json",
        action="store_true",
        help="print JSON instead of the tables (docs/FORMATS.md, the report's 'comparison' block)",
    )
    return cmp


def run(args: argparse.Namespace) -> int:
    """Print the comparison; exit 0 when every figure meets its target, else 1."""
    import json

    from trifuse.app.workflows.report_format import comparison_text
    from trifuse.calib.rig_compare import compare_rigs

    estimate = load_rig_arg(args.rig)
    truth = load_rig_arg(args.truth)
    try:
        comparison = compare_rigs(estimate, truth)
    except ValueError as exc:
        raise ValueError(f"{args.rig} against {args.truth}: {exc}") from None
    if args.json:
        data = {"rig": str(args.rig), "truth": str(args.truth), **comparison.as_dict()}
        out(json.dumps(data, indent=1, allow_nan=False))
    else:
        out(comparison_text(comparison, str(args.rig), str(args.truth)))
    return EXIT_OK if comparison.passed else EXIT_FAILURE
