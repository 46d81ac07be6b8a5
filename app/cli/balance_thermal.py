"""``trifuse balance-thermal``: the two thermal imagers balanced against each other from a
recording, written into the rig's radiometry."""

from __future__ import annotations

import argparse
from pathlib import Path

from trifuse.app.cli.args import EXIT_FAILURE, EXIT_OK, Commands, UsageError, add_every_argument
from trifuse.app.cli.files import add_rig_out_argument, check_rig_out, write_rig_out
from trifuse.app.cli.output import out


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``balance-thermal RECORDING --out RIG.yaml [--rig] [--reference] [--every]``."""
    bt = commands.add_parser(
        "balance-thermal",
        help="balance the two thermal imagers from a recording (points both see)",
        description=(
            "Replay RECORDING and, on every frame set, compare the two thermal imagers' "
            "readings of the TOF points both see (not occluded, off thermal edges); fit "
            "left = gain x right + offset robustly (the gain only when the scene's "
            "temperatures span enough), filter it over time, and write the rig with each "
            "imager's balance in its radiometry block (split evenly, or onto --reference). "
            "Refuses, leaving the rig unchanged, when the imagers share too few points."
        ),
    )
    bt.add_argument("recording", metavar="RECORDING", help="the recording (.mcap)")
    bt.add_argument("--rig", metavar="RIG.yaml", help="the rig (default: the recording's)")
    add_rig_out_argument(bt)
    bt.add_argument(
        "--reference",
        metavar="NAME",
        help="the imager left unchanged (default: split the correction evenly)",
    )
    add_every_argument(bt, "use every N-th frame set")
    return bt


def run(args: argparse.Namespace) -> int:
    """Balance the imagers over the recording; write the rig, or exit 1 when refused."""
    from trifuse.app.recording.open_source import open_source
    from trifuse.app.storage.rigfile import load_rig
    from trifuse.app.workflows.thermal_run import (
        balance_source,
        format_thermal_summary,
        with_balance,
    )

    rig_out = Path(args.out)
    rig_path = Path(args.rig) if args.rig else None
    check_rig_out(rig_out, rig_path)
    given = load_rig(rig_path) if rig_path else None
    opened = open_source(args.recording, rig=given, realtime=False)
    with opened.source as src:
        rig = opened.rig
        imagers = [rig.eyes[e].thermal for e in ("left", "right")]
        if args.reference is not None and args.reference not in imagers:
            raise UsageError(f"--reference: expected one of {imagers}, got {args.reference!r}")
        out(f"Balancing {' and '.join(imagers)} over {args.recording} ({src.duration_s:.1f} s)")
        result = balance_source(src, rig, args.every, reference=args.reference)
    out(format_thermal_summary(result, rig))
    if result.estimate is None:
        return EXIT_FAILURE
    write_rig_out(rig_out, rig_path, with_balance(rig, result.terms), "radiometry")
    return EXIT_OK
