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
    table = Path(args.out)
    if table.exists():
        raise UsageError(f"--out {table}: exists; refusing to overwrite it (choose a new name)")
    [recording] = recording_paths([args.recording])
    plan = load_plan(recording, args.regions, "--regions")
    given = load_rig_arg(args.rig, "--rig") if args.rig else None
    write_table(recording, plan, given, args.every, table)
    return EXIT_OK


def load_plan(recording: Path, path: str | None, option: str):
    """The plan of file ``path`` (given as ``option``), or without one the recording's
    own (:func:`_recorded_plan`); UsageError in one line for a plan that cannot be used."""
    from trifuse.app.recording.measure import plan_from_yaml

    if path is None:
        return _recorded_plan(recording)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{option} {path}: cannot read it ({exc})") from None
    try:
        return plan_from_yaml(text)
    except ValueError as exc:
        raise UsageError(f"{option} {path}: {exc}") from None


def write_table(recording: Path, plan, rig, every: int, table: Path) -> None:
    """Read ``plan`` over ``recording`` (with ``rig``, else the recording's) into the new
    file ``table``, and say so; ValueError when no frame set makes a picture."""
    from trifuse.app.recording.measure import measure_recording, table_text
    from trifuse.app.recording.reader import ReplaySource
    from trifuse.app.storage.atomic import atomic_write_text

    with ReplaySource(recording, realtime=False) as source:
        rig = rig or source.rig
        if rig is None:
            raise ValueError(f"{recording}: the recording holds no rig; give one with --rig")
        rows = list(measure_recording(source, rig, plan, every))
    if not rows:
        raise ValueError(f"{recording}: no frame set could be fused (both eyes' colour and "
                         "thermal frames after the first TOF frame)")  # fmt: skip
    atomic_write_text(table, table_text(iter(rows)), overwrite=False)
    sets = len(rows) // len(plan.regions)
    out(f"Wrote {len(rows)} rows ({sets} frame sets x {len(plan.regions)} regions) to {table}")


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
