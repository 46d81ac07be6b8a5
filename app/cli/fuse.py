"""``trifuse fuse``: a whole recording fused offline into JPEG frames and a video."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from app.cli.args import EXIT_OK, PROG, Commands, add_every_argument
from app.cli.files import add_out_dir_argument, check_output_dir
from app.cli.output import err, frame_progress, out
from fusion.compose import DISPLAY_MODES


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``fuse RECORDING --out DIR [--rig] [--mode] [--every]``."""
    fuse = commands.add_parser(
        "fuse",
        help="fuse a whole recording offline into JPEG frames and a video",
        description=(
            "Replay RECORDING as fast as possible, update the thermal-to-colour mapping of "
            "both eyes with every TOF frame, compose the side-by-side stereo picture of "
            "every N-th left-colour frame set, and write the pictures as DIR/000000.jpg ... "
            "plus DIR/frames.csv (time stamps) and DIR/fused.mp4 (OpenCV mp4v, if that codec "
            "is available). Progress goes to stderr."
        ),
    )
    fuse.add_argument("recording", metavar="RECORDING", help="the recording (.mcap)")
    fuse.add_argument(
        "--rig", metavar="RIG.yaml", help="rig file (default: the rig stored in the recording)"
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
    return fuse


def run(args: argparse.Namespace) -> int:
    """Fuse the recording into ``--out``; say what was written and what was skipped."""
    from app.recording.fuse import VIDEO_NAME, fuse_recording
    from app.recording.open_source import open_source
    from app.storage.rigfile import load_rig
    from fusion.compose import DisplaySettings

    out_dir = Path(args.out)
    check_output_dir(out_dir)
    settings = DisplaySettings(mode=args.mode)
    given = load_rig(args.rig) if args.rig else None
    opened = open_source(args.recording, rig=given, realtime=False)
    with opened.source as src:
        out_dir.mkdir(parents=True, exist_ok=True)
        progress = frame_progress()

        out(
            f"Fusing {args.recording} ({src.duration_s:.3f} s) in {args.mode} mode "
            f"({'every frame set' if args.every == 1 else f'one frame set in {args.every}'}) "
            f"into {out_dir}/"
        )
        result = fuse_recording(src, opened.rig, out_dir, settings, args.every, progress)
        if sys.stderr.isatty():  # end the bar's line
            print(file=sys.stderr)
    out(f"Wrote {result.frames} fused frames to {out_dir}/ (000000.jpg ..., frames.csv)")
    if result.video is not None:
        out(f"Video: {result.video} ({result.fps:.2f} frames/s, mp4v)")
    else:
        out(f"No video ({VIDEO_NAME}): {result.video_problem}; the JPEG frames are written")
    for reason, n in result.skipped.items():
        out(f"  skipped {n} frame sets: {reason}")
    if result.damage is not None:
        err(f"{PROG}: warning: {result.damage}; the frames before it were fused")
    if result.frames == 0:
        skipped = "; ".join(f"{n} frame sets: {r}" for r, n in result.skipped.items())
        raise ValueError(
            f"{args.recording}: no frame set could be fused"
            + (f" ({skipped})" if skipped else " (the recording holds no complete frame set)")
        )
    return EXIT_OK
