"""``trifuse measure``: a recording's measurement regions read with chosen object parameters
into a CSV table (issue 35; app/recording/measure.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from trifuse.app.cli.args import EXIT_OK, Commands, UsageError, add_every_argument
from trifuse.app.cli.files import load_rig_arg, recording_paths
from trifuse.app.cli.output import out


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``measure RECORDING [--regions PLAN.yaml] --out TABLE.csv [--rig] [--every]``."""
    measure = commands.add_parser(
        "measure",
        help="read measurement regions over a recording into a CSV table",
        description=(
            "Replay RECORDING as fast as possible, fuse every N-th frame set as the console "
            "does, and read the regions of PLAN.yaml on each picture with its object "
            "parameters (emissivity, reflected temperature, the air) and the TOF's distance "
            "at every pixel: one row per frame set and region (time, corrected maximum, "
            "minimum and mean with where the extremes are, the apparent mean, alarm events "
            "and the alarms active) in TABLE.csv. The recording keeps what the imagers "
            "measured, so the parameters and regions may be chosen afterwards. PLAN.yaml: "
            "see docs/FORMATS.md."
        ),
    )
    measure.add_argument("recording", metavar="RECORDING", help="a recording (.mcap)")
    measure.add_argument(
        "--regions",
        metavar="PLAN.yaml",
        help="parameters, regions, alarms (default: those the console used while it recorded, "
        "from the recording's last measurement settings note)",
    )
    measure.add_argument(
        "--out", required=True, metavar="TABLE.csv", help="the table to write (a new file)"
    )
    measure.add_argument(
        "--rig", metavar="RIG.yaml", help="rig file (default: the rig stored in the recording)"
    )
    add_every_argument(measure, "read every N-th colour frame set")
    return measure


def run(args: argparse.Namespace) -> int:
    """Write the table; say how many frame sets and rows."""
    from trifuse.app.recording.measure import measure_recording, plan_from_yaml, table_text
    from trifuse.app.recording.reader import ReplaySource
    from trifuse.app.storage.atomic import atomic_write_text

    table = Path(args.out)
    if table.exists():
        raise UsageError(f"--out {table}: exists; refusing to overwrite it (choose a new name)")
    [recording] = recording_paths([args.recording])
    if args.regions is None:
        plan = _recorded_plan(recording)
    else:
        try:
            plan_text = Path(args.regions).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise UsageError(f"--regions {args.regions}: cannot read it ({exc})") from None
        try:
            plan = plan_from_yaml(plan_text)
        except ValueError as exc:
            raise UsageError(f"--regions {args.regions}: {exc}") from None
    given = load_rig_arg(args.rig, "--rig") if args.rig else None
    with ReplaySource(recording, realtime=False) as source:
        rig = given or source.rig
        if rig is None:
            raise ValueError(f"{recording}: the recording holds no rig; give one with --rig")
        rows = list(measure_recording(source, rig, plan, args.every))
    if not rows:
        raise ValueError(f"{recording}: no frame set could be fused (both eyes' colour and "
                         "thermal frames after the first TOF frame)")  # fmt: skip
    atomic_write_text(table, table_text(iter(rows)), overwrite=False)
    sets = len(rows) // len(plan.regions)
    out(f"Wrote {len(rows)} rows ({sets} frame sets x {len(plan.regions)} regions) to {table}")
    return EXIT_OK


def _recorded_plan(recording: Path):
    """The plan of the recording's last measurement settings note (what the console read
    with when it stopped recording); UsageError without one."""
    from trifuse.app.recording.layout import SETTINGS_NOTE
    from trifuse.app.recording.measure import plan_from_mapping
    from trifuse.app.recording.notes import read_notes

    notes = [n for n in read_notes(recording) if n.name == SETTINGS_NOTE]
    if not notes:
        raise UsageError(
            f"{recording}: holds no measurement settings (a console recording with regions "
            "has them); give --regions PLAN.yaml"
        )
    try:
        return plan_from_mapping(notes[-1].body)
    except ValueError as exc:
        raise UsageError(f"{recording}: its measurement settings: {exc}") from None
