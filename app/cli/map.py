"""``trifuse map``: the thermal 3D map of one or more recordings, as a PLY point cloud and a
map file the console loads."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.cli.args import EXIT_OK, PROG, Commands, UsageError, positive_float
from trifuse.app.cli.choices import POSE_MODES
from trifuse.app.cli.cluster import add_cluster_arguments, open_runner, pieces_text
from trifuse.app.cli.files import load_rig_arg, recording_paths
from trifuse.app.cli.output import err, frame_progress, out

if TYPE_CHECKING:
    import numpy as np

DEFAULT_VOXEL_M = 0.03


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``map RECORDING [RECORDING ...] --out MAP.ply [--rig] [--voxel] [--pose]
    [--map-file] [--force]``."""
    cmd = commands.add_parser(
        "map",
        help="build the thermal 3D map of recordings: a PLY point cloud and a map file",
        description=(
            "Replay the recordings as fast as they are read, one run in the order given, and "
            "add every TOF frame to a voxel map with the temperature (the thermal imagers "
            "through the rig's radiometry, kelvin) and colour of what its points show, at "
            "the head's pose: the recording's world -> rig transforms (written by 'trifuse "
            "record' when the source knows the pose), else estimated from the TOF clouds "
            "(KISS-ICP). Writes the occupied voxels as a binary PLY (x y z in metres, red "
            "green blue, temperature and temperature_max in degrees Celsius, observations; "
            "CloudCompare, MeshLab and Open3D open it) and the whole map as a map file the "
            "console loads (docs/FORMATS.md, 'Thermal 3D map'). Progress goes to stderr."
        ),
    )
    cmd.add_argument(
        "recordings",
        nargs="+",
        metavar="RECORDING",
        help="a recording (.mcap), or a directory: every .mcap in it, by name",
    )
    cmd.add_argument(
        "--out",
        required=True,
        metavar="MAP.ply",
        help="the PLY point cloud to write (must not exist, unless --force)",
    )
    cmd.add_argument(
        "--rig", metavar="RIG.yaml", help="rig file (default: the rig stored in the recordings)"
    )
    cmd.add_argument(
        "--voxel",
        type=positive_float,
        default=DEFAULT_VOXEL_M,
        metavar="M",
        help="voxel edge, metres (default: %(default)s)",
    )
    cmd.add_argument(
        "--pose",
        choices=POSE_MODES,
        default="auto",
        help="the head's pose: 'recording' (the recordings' world -> rig transforms; frames "
        "without one are skipped), 'estimate' (from the TOF clouds, KISS-ICP: the world is "
        "the rig frame at the first frame) or 'auto': the recordings' when every one has "
        "them, else estimated (default: %(default)s)",
    )
    cmd.add_argument(
        "--map-file",
        metavar="PATH",
        help="the map file to write (default: --out with the suffix .map.npz, e.g. "
        "map.ply -> map.map.npz)",
    )
    cmd.add_argument(
        "--force",
        action="store_true",
        help="replace the PLY and the map file if they exist (never a recording)",
    )
    cmd.add_argument(
        "--rerun",
        metavar="OUT.rrd",
        help="also write the map to a rerun file (a new one): its points coloured by "
        "temperature, the head's path and the rig's cameras at its last pose (needs the "
        "[rerun] extra)",
    )
    add_cluster_arguments(cmd)
    return cmd


def output_paths(args: argparse.Namespace) -> tuple[Path, Path]:
    """(PLY, map file): distinct, not directories, new unless ``--force``."""
    from trifuse.app.storage.map_file import MAP_SUFFIX

    ply = Path(args.out)
    map_file = Path(args.map_file) if args.map_file else ply.with_suffix(MAP_SUFFIX)
    if map_file.resolve() == ply.resolve():
        raise UsageError(f"--map-file {map_file}: the same file as --out")
    for flag, path in (("--out", ply), ("--map-file", map_file)):
        if path.is_dir():
            raise UsageError(f"{flag} {path}: a directory; expected a file name")
        if (path.exists() or path.is_symlink()) and not args.force:
            raise UsageError(
                f"{flag} {path}: exists; refusing to overwrite it (choose a new name, or --force)"
            )
    return ply, map_file


def check_not_inputs(outputs: tuple[Path, Path], inputs: list[Path]) -> None:
    """No output may be one of the recordings (not even with ``--force``)."""
    for flag, path in zip(("--out", "--map-file"), outputs, strict=True):
        if path.exists() and any(path.resolve() == p.resolve() for p in inputs):
            raise UsageError(f"{flag} {path}: is one of the recordings; refusing to overwrite it")


def extent_text(centres: np.ndarray) -> str:
    """The bounding box of (N, 3) points: ``x -1.20..3.40, y ..., z ... m (4.60 x ... m)``."""
    if len(centres) == 0:
        return "empty"
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    axes = ", ".join(f"{a} {lo[i]:.2f}..{hi[i]:.2f}" for i, a in enumerate("xyz"))
    size = " x ".join(f"{v:.2f}" for v in hi - lo)
    return f"{axes} m ({size} m)"


def run(args: argparse.Namespace) -> int:
    """Build the map of the recordings; write the PLY and the map file; say what was done."""
    from trifuse.app.recording.jobs import run_map_job
    from trifuse.app.recording.map3d import MAX_IMAGE_AGE_S, open_recordings
    from trifuse.app.recording.player import skips_text
    from trifuse.app.storage.map_file import save_map, write_ply
    from trifuse.fusion.voxel_map import MapSettings

    ply, map_file = output_paths(args)  # refusals first: inputs need not exist for them
    if args.rerun is not None:
        from trifuse.app.recording.rerun_log import require_rerun

        if Path(args.rerun).exists():
            raise UsageError(f"--rerun {args.rerun}: exists; refusing to overwrite it")
        require_rerun()
    inputs = recording_paths(args.recordings)
    check_not_inputs((ply, map_file), inputs)
    settings = MapSettings(voxel_m=args.voxel)
    rig = load_rig_arg(args.rig, "--rig") if args.rig else None
    sources, rig = open_recordings(inputs, rig)
    progress = frame_progress()

    try:
        with open_runner(args) as runner:
            total_s = sum(src.duration_s for src in sources)
            names = ", ".join(str(p) for p in inputs)
            pose = "as --pose auto finds it" if args.pose == "auto" else f"by --pose {args.pose}"
            out(
                f"Mapping {names} ({total_s:.3f} s) with {args.voxel:g} m voxels, the head's "
                f"pose {pose}, in pieces ({pieces_text(args.chunk_s)}; {runner.name})"
            )
            result = run_map_job(sources, rig, settings, args.pose, args.chunk_s, runner, progress)
            if sys.stderr.isatty():  # end the bar's line
                print(file=sys.stderr)
    finally:
        for src in sources:
            src.close()
    m = result.map
    for damage in result.damage:
        err(f"{PROG}: warning: {damage}; the frames before it were mapped")
    if result.integrated == 0:
        skipped = "; ".join(
            [f"{n} frames: {r}" for r, n in result.skipped.items()]
            + skips_text(result.messages_skipped)
        )
        raise ValueError(
            f"{names}: no TOF frame could be mapped"
            + (f" ({skipped})" if skipped else " (no TOF frame with distances)")
        )
    for line in skips_text(result.messages_skipped):
        err(f"{PROG}: warning: {line}")
    pose = (
        f"the recordings' poses ({result.pose_frames})"
        if result.pose_source == "recording"
        else "estimated from the TOF clouds (KISS-ICP)"
    )
    comments = (f"made by {PROG} map from {names}", f"head pose: {pose}")
    write_ply(ply, m, overwrite=args.force, comments=comments)
    info = {
        "made_by": f"{PROG} map",
        "recordings": [str(p) for p in inputs],
        "pose_source": result.pose_source,
        "pose_frames": result.pose_frames,
        "tof_frames": result.integrated,
    }
    save_map(map_file, m, overwrite=args.force, info=info)
    occupied = m.occupied()
    out(
        f"Mapped {result.integrated} of {result.tof_frames} TOF frames in "
        f"{result.seconds:.1f} s; head pose: {pose}"
    )
    for reason, n in result.skipped.items():
        out(f"  skipped {n} TOF frames: {reason}")
    for sensor, n in result.images_missing.items():
        out(f"  {n} TOF frames without an image of {sensor} within {MAX_IMAGE_AGE_S:g} s")
    out(
        f"Voxels: {len(m)} ({occupied.sum()} occupied, {args.voxel:g} m); extent of the "
        f"occupied: {extent_text(m['centre'][occupied])}"
    )
    out(f"Wrote {ply} ({occupied.sum()} points) and the map file {map_file}")
    if args.rerun is not None:
        from trifuse.app.recording.rerun_export import export_map_rerun

        points = export_map_rerun(rig, m, args.rerun)
        out(f"Rerun: {args.rerun} ({points} points, the head's path; `rerun {args.rerun}`)")
    for note in result.notes:
        err(f"{PROG}: note: {note}")
    if not occupied.any():
        err(f"{PROG}: warning: no voxel is occupied (seen in enough frames): the PLY is empty")
    return EXIT_OK
