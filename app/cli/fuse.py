"""``trifuse fuse``: recordings fused offline into JPEG frames and a video each."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from trifuse.app.cli.args import EXIT_OK, PROG, Commands, UsageError, add_every_argument
from trifuse.app.cli.choices import DISPLAY_MODES
from trifuse.app.cli.cluster import add_cluster_arguments, open_runner, pieces_text
from trifuse.app.cli.files import (
    add_out_dir_argument,
    check_output_dir,
    load_rig_arg,
    recording_paths,
)
from trifuse.app.cli.measure import load_plan, write_table
from trifuse.app.cli.output import err, frame_progress, out

TABLE_NAME = "measurements.csv"
"""The table ``--measure`` writes beside the pictures."""


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``fuse RECORDING [RECORDING ...] --out DIR [--rig] [--mode] [--every] [--ray]
    [--chunk-s]``."""
    fuse = commands.add_parser(
        "fuse",
        help="fuse recordings offline into JPEG frames and a video (here or on a Ray cluster)",
        description=(
            "Replay each RECORDING as fast as possible, update the thermal-to-colour mapping "
            "of both eyes with every TOF frame, compose the side-by-side stereo picture of "
            "every N-th left-colour frame set, and write the pictures as DIR/000000.jpg ... "
            "plus DIR/frames.csv (time stamps) and DIR/fused.mp4 (OpenCV mp4v, if that codec "
            "is available). With several recordings (or a directory of them) each one's "
            "pictures go to DIR/<recording's name>/. Recordings are fused in pieces of "
            "--chunk-s seconds, here one after the other or as Ray tasks (--ray). Progress "
            "goes to stderr."
        ),
    )
    fuse.add_argument(
        "recordings",
        nargs="+",
        metavar="RECORDING",
        help="a recording (.mcap), or a directory: every .mcap in it, by name",
    )
    fuse.add_argument(
        "--rig", metavar="RIG.yaml", help="rig file (default: the rig stored in each recording)"
    )
    add_out_dir_argument(fuse)
    fuse.add_argument(
        "--mode",
        default="blend",
        metavar="MODE",
        help=f"display mode: {', '.join(DISPLAY_MODES[:-1])} or {DISPLAY_MODES[-1]} "
        "(default: %(default)s)",
    )
    add_every_argument(fuse, "compose every N-th colour frame set")
    fuse.add_argument(
        "--measure",
        nargs="?",
        const="",
        metavar="PLAN.yaml",
        help="also read measurement regions on the same frame sets into DIR/measurements.csv "
        "(as `trifuse measure`): those of PLAN.yaml, or without one those the console used "
        "while it recorded (the recording's measurement settings). The recordings keep what "
        "the imagers measured: emissivity and regions may be chosen afterwards",
    )
    fuse.add_argument(
        "--rerun",
        metavar="OUT.rrd",
        help="also log the recording to a rerun file (a new one): the rig's cameras at their "
        "poses, each sensor's images, the TOF's points coloured by temperature and the fused "
        "pair, on the same frame sets (one recording; needs the [rerun] extra)",
    )
    add_cluster_arguments(fuse)
    return fuse


def output_dirs(args: argparse.Namespace, inputs: list[Path]) -> list[Path]:
    """``--out`` for one recording named as a file, else ``--out/<name>`` per recording
    (names must differ)."""
    out_dir = Path(args.out)
    if len(inputs) == 1 and not Path(args.recordings[0]).is_dir():
        return [out_dir]
    named: dict[Path, Path] = {}  # output directory -> its recording
    for p in inputs:
        d = out_dir / p.stem
        if d in named:
            raise UsageError(
                f"{named[d]} and {p}: recordings of the same name would share {d}; fuse them apart"
            )
        named[d] = p
    return list(named)


def run(args: argparse.Namespace) -> int:
    """Fuse the recordings into ``--out``; say what was written and what was skipped."""
    from trifuse.app.recording.fuse import VIDEO_NAME
    from trifuse.app.recording.jobs import plan_fuse_job, run_fuse_job
    from trifuse.app.recording.player import skips_text
    from trifuse.app.recording.rerun_log import require_rerun
    from trifuse.app.storage.atomic import make_dirs
    from trifuse.fusion.compose import DisplaySettings

    if args.mode not in DISPLAY_MODES:  # the console's own modes show nothing offline
        raise ValueError(f"--mode: expected one of {', '.join(DISPLAY_MODES)}, got {args.mode!r}")
    check_output_dir(Path(args.out))  # refusals first: the inputs need not exist for them
    inputs = recording_paths(args.recordings)
    dirs = output_dirs(args, inputs)
    settings = DisplaySettings(mode=args.mode)
    given = load_rig_arg(args.rig, "--rig") if args.rig else None
    rerun_out = None if args.rerun is None else Path(args.rerun)
    if rerun_out is not None:
        if len(inputs) != 1:
            raise UsageError(f"--rerun: takes one recording, got {len(inputs)}")
        if rerun_out.exists():
            raise UsageError(f"--rerun {rerun_out}: exists; refusing to overwrite it")
        require_rerun()  # the extra's line before any work
    wanted = args.measure is not None  # "": the recordings' own plans
    plans = [load_plan(p, args.measure or None, "--measure") for p in inputs if wanted]
    planned = plan_fuse_job(
        list(zip(inputs, dirs, strict=True)), given, settings, args.every, args.chunk_s
    )
    every = "every frame set" if args.every == 1 else f"one frame set in {args.every}"
    pieces = sum(len(p.pieces) for p in planned)
    with open_runner(args) as runner:
        for d in dirs:
            make_dirs(d)
        out(
            f"Fusing {len(inputs)} recording{'s' * (len(inputs) > 1)} in {args.mode} mode "
            f"({every}), {pieces} piece{'s' * (pieces > 1)} ({pieces_text(args.chunk_s)}; "
            f"{runner.name}) into {Path(args.out)}/"
        )
        results = run_fuse_job(planned, settings, args.every, runner, frame_progress())
        if sys.stderr.isatty():  # end the bar's line
            print(file=sys.stderr)
    for plan, result in zip(planned, results, strict=True):
        name = f"{plan.recording}: " if len(planned) > 1 else ""
        written = f"{result.frames} fused frames to {plan.out_dir}/ (000000.jpg ..., frames.csv)"
        out(f"{name}Wrote {written}")
        if result.video is not None:
            out(f"Video: {result.video} ({result.fps:.2f} frames/s, mp4v)")
        else:
            out(f"No video ({VIDEO_NAME}): {result.video_problem}; the JPEG frames are written")
        for reason, n in result.skipped.items():
            out(f"  skipped {n} frame sets: {reason}")
        if result.frames:  # else the error below says it
            for line in skips_text(result.messages_skipped):
                err(f"{PROG}: warning: {name}{line}")
        for damage in result.damage:
            err(f"{PROG}: warning: {damage}; the frames before it were fused")
    empty = [(p, r) for p, r in zip(planned, results, strict=True) if r.frames == 0]
    if empty:
        plan, result = empty[0]
        skipped = "; ".join(
            [f"{n} frame sets: {r}" for r, n in result.skipped.items()]
            + skips_text(result.messages_skipped)
        )
        raise ValueError(
            f"{plan.recording}: no frame set could be fused"
            + (f" ({skipped})" if skipped else " (the recording holds no complete frame set)")
        )
    for plan, measured in zip(planned, plans, strict=False):  # here, after the pictures
        write_table(plan.recording, measured, given, args.every, plan.out_dir / TABLE_NAME)
    if rerun_out is not None:
        write_rerun(inputs[0], given, args.every, settings, rerun_out)
    return EXIT_OK


def write_rerun(recording: Path, rig, every: int, settings, out_path: Path) -> None:
    """Log ``recording`` to the new rerun file ``out_path`` and say so."""
    from trifuse.app.recording.reader import ReplaySource
    from trifuse.app.recording.rerun_export import export_rerun

    with ReplaySource(recording, realtime=False) as source:
        rig = rig or source.rig
        if rig is None:
            raise ValueError(f"{recording}: the recording holds no rig; give one with --rig")
        sets = export_rerun(source, rig, out_path, every, settings)
    size = out_path.stat().st_size / 1e6
    out(f"Rerun: {out_path} ({sets} frame sets, {size:.1f} MB; open it with `rerun {out_path}`)")
