"""``trifuse record --fused-video``: the fused stereo picture kept in the recording as H.264
(``/fused/video``, docs/FORMATS.md "Recordings"), made while the frames are written
(:class:`app.recording.video_track.FusedVideoFuser`, watching the
:class:`~app.recording.recording.Recording` the console's recorder writes with too)."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

from trifuse.app.cli.args import PROG, checked
from trifuse.app.cli.choices import DISPLAY_MODES
from trifuse.app.cli.output import err, out

if TYPE_CHECKING:
    from trifuse.app.recording.recording import Recording
    from trifuse.app.recording.video_track import FusedVideoFuser
    from trifuse.calib.rig import Rig

FUSED_VIDEO_S_PER_MPX = 0.013
"""CPU seconds per megapixel of fused picture on the reference machine (2 cores): fusion
about 23 ms and encoding 9 ms per 2560 x 960 picture."""

video_mbps = checked(
    float,
    lambda v: math.isfinite(v) and 0.1 <= v <= 100,
    "a number of Mbit/s",
    "a number of Mbit/s from 0.1 to 100",
)


def add_video_arguments(parser: argparse.ArgumentParser) -> None:
    """``--fused-video [--video-mbps MBPS] [--video-mode MODE]``."""
    parser.add_argument(
        "--fused-video",
        action="store_true",
        help="also fuse the frames as the console does and keep the stereo picture as H.264 "
        "video on /fused/video (foxglove.CompressedVideo, a key frame every second; "
        "Foxglove's Image panel plays it); costs about 32 ms of CPU per picture at the "
        "full 2560x960 (fusion 23, encoding 9)",
    )
    parser.add_argument(
        "--video-mbps",
        type=video_mbps,
        default=10.0,
        metavar="MBPS",
        help="--fused-video: bitrate, Mbit/s (default: %(default)g)",
    )
    parser.add_argument(
        "--video-mode",
        default="blend",
        choices=DISPLAY_MODES,
        metavar="MODE",
        help=f"--fused-video: display mode, {', '.join(DISPLAY_MODES)} (default: %(default)s, "
        "the console's)",
    )


def fused_video_cost_s(rig: Rig, schedule: list[tuple[int, list[str]]]) -> float:
    """Estimated CPU seconds the fused video adds to a simulated recording of ``schedule``
    ((stamp_ns, sensors due) per instant): a picture per left colour frame."""
    eye = rig.eyes.get("left")
    if eye is None:
        return 0.0
    w, h = rig[eye.color].image_size
    pictures = sum(1 for _, sensors in schedule if eye.color in sensors)
    return pictures * FUSED_VIDEO_S_PER_MPX * len(rig.eyes) * w * h / 1e6


def attach_fused_video(writer: Recording, args: argparse.Namespace) -> FusedVideoFuser:
    """Make ``writer`` fuse the frames written and keep the video (per ``args``)."""
    from trifuse.app.recording.video_track import FusedVideoFuser, VideoSettings
    from trifuse.fusion.compose import DisplaySettings

    settings = VideoSettings(bitrate_bps=round(args.video_mbps * 1e6))
    fuser = FusedVideoFuser(writer, settings, DisplaySettings(mode=args.video_mode))
    writer.observers.append(fuser)
    return fuser


def video_summary(fuser: FusedVideoFuser) -> None:
    """What the fused video holds, or why it stopped (a warning: the frames are kept)."""
    s = fuser.settings
    skipped = f", {fuser.skipped} frame sets without both colour images" if fuser.skipped else ""
    keys = f"{fuser.keyframes} key frame{'' if fuser.keyframes == 1 else 's'}"
    out(
        f"Fused video: {fuser.pictures} pictures of {fuser.sets} frame sets on /fused/video "
        f"(H.264, {s.bitrate_bps / 1e6:g} Mbit/s, {keys}, one every {s.keyint_s:g} s{skipped})"
    )
    if fuser.error is not None:
        err(f"{PROG}: warning: the fused video stopped ({fuser.error}); the frames are recorded")
