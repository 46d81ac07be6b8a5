"""``trifuse record``: the sensor head (simulated, or live cameras) or a recording,
(re-)recorded into an MCAP file."""

from __future__ import annotations

import argparse
import signal
import threading
import time
from pathlib import Path

from trifuse.app.cli.args import (
    EXIT_OK,
    PROG,
    Commands,
    UsageError,
    jpeg_quality,
    positive_seconds,
    seed,
)
from trifuse.app.cli.choices import SIM_SCENARIOS
from trifuse.app.cli.files import refuse_existing
from trifuse.app.cli.output import err, out
from trifuse.app.cli.record_output import record_summary, say_where
from trifuse.app.cli.record_sim import DEFAULT_DURATION_S
from trifuse.app.cli.record_video import add_video_arguments, attach_fused_video, video_summary


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``record --source sim|replay:FILE|live:CONFIG --out FILE.mcap [--duration] ...``."""
    rec = commands.add_parser(
        "record",
        help="record the sensor head (simulated) or re-record a recording into an MCAP file",
        description=(
            "Record frames into an MCAP file with Foxglove's schemas (docs/FORMATS.md, "
            "Recordings): colour as JPEG foxglove.CompressedImage on /<sensor>/image, thermal "
            "as 16UC1 centi-kelvin foxglove.RawImage on /<sensor>/temperature, TOF distance "
            "(16UC1 mm, 0 = invalid) and amplitude on /tof/distance and /tof/amplitude, "
            "calibration per sensor, the rig as /tf transforms and as the attachment rig.yaml. "
            "Foxglove opens it as it is. --source sim renders the simulated head's "
            "--scenario (the inspection room, or the survey: pan and tilt, then a 3 m "
            "drive), with the head's pose per frame set (/tf, world -> rig), time stamps at "
            "each sensor's rate (colour 30 Hz, "
            "thermal 27 Hz, TOF 15 Hz): by default head poses rendered at --pose-hz in the "
            "live quality, each frame turned to its own instant's pose with fresh noise "
            "(about 7x slower than real time on 2 cores), with --exact every instant "
            "rendered accurately (about 130x); it says how long at the start and gives the "
            "time left as it goes; --source replay:FILE "
            "re-records a recording (a damaged one up to the damage). --fused-video also "
            "keeps the fused stereo picture as H.264 video on /fused/video "
            "(foxglove.CompressedVideo), which Foxglove plays."
        ),
    )
    rec.add_argument(
        "--source",
        required=True,
        metavar="SOURCE",
        help="'sim' (the simulated head), 'replay:FILE' (a recording) or 'live:CONFIG' "
        "(OpenCV cameras, docs/FORMATS.md 'Live camera configuration'; needs --rig)",
    )
    rec.add_argument(
        "--out", required=True, metavar="FILE.mcap", help="recording to write (must not exist)"
    )
    rec.add_argument(
        "--duration",
        type=positive_seconds,
        metavar="S",
        help="seconds to record (sim default: "
        f"{', '.join(f'{s} {d:g}' for s, d in DEFAULT_DURATION_S.items())}; "
        "replay default: all of it)",
    )
    rec.add_argument(
        "--rig",
        metavar="RIG.yaml",
        help="rig file: the head to simulate (default: the simulator's built-in head) or "
        "the rig to store (default: the replayed recording's)",
    )
    rec.add_argument(
        "--scenario",
        choices=SIM_SCENARIOS,
        help="sim: what the simulated head sees: the inspection room (panning) or the "
        "survey of it (pan and tilt, then a drive; 36 s in all) (default: inspection)",
    )
    rec.add_argument(
        "--seed", type=seed, default=0, metavar="N", help="simulator noise seed (default: 0)"
    )
    rec.add_argument(
        "--drift",
        metavar="SENSOR:RX,RY,RZ[@AT_S]",
        help="sim: one sensor moves during the recording (calibration drift): from AT_S "
        "seconds of scenario time on (default 0) it is rendered turned by the rotation "
        "vector RX,RY,RZ in degrees about its own axes, applied on the right of its pose "
        "(T_rig_sensor @ [[R, 0], [0, 1]]); the recording's rig stays the calibrated one, "
        "its trifuse.simulation metadata says the drift, e.g. thermal_left:0,0.3,0@20",
    )
    rec.add_argument(
        "--exact",
        action="store_true",
        help="sim: render every instant at its own time in the accurate quality (edge "
        "supersampling), about 130x slower than real time; default: the live mode, head "
        "poses rendered at --pose-hz and every frame turned to its own instant with fresh "
        "noise, about 7x",
    )
    rec.add_argument(
        "--pose-hz",
        type=float,
        metavar="HZ",
        help="sim, live mode: head poses rendered per simulated second (default: 5); time "
        "stamps stay at the sensors' rates",
    )
    rec.add_argument(
        "--jpeg-quality",
        type=jpeg_quality,
        default=90,
        metavar="Q",
        help="JPEG quality of the colour images, 1-100 (default: %(default)s)",
    )
    add_video_arguments(rec)
    return rec


def _sigterm_as_interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def run(args: argparse.Namespace) -> int:
    """Record; on the main thread SIGTERM (kill, systemd, a container stopping) finishes
    the file like Ctrl-C."""
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
        try:
            return _record(args)
        finally:
            signal.signal(signal.SIGTERM, previous)
    return _record(args)


def _record(args: argparse.Namespace) -> int:
    """Record from ``--source`` into ``--out``; the simulated head in :mod:`app.cli.record_sim`."""
    from trifuse.app.recording import RecordingDamaged
    from trifuse.app.recording.open_source import NeedsRig, open_source
    from trifuse.app.recording.poses import read_poses
    from trifuse.app.recording.recording import Recording
    from trifuse.app.storage.rigfile import load_rig

    rec_out = Path(args.out)
    if rec_out.exists() or rec_out.is_symlink():
        refuse_existing("--out", rec_out)
    rig = load_rig(args.rig) if args.rig else None
    source = args.source
    if source == "sim":
        from trifuse.app.cli.record_sim import record_sim

        args.scenario = args.scenario or "inspection"
        return record_sim(args, rec_out, rig)
    if args.scenario is not None:
        raise UsageError(f"{PROG} record: --scenario goes with --source sim")
    if args.drift is not None:
        raise UsageError(f"{PROG} record: --drift goes with --source sim")
    kind, _, arg = source.partition(":")
    if kind not in ("replay", "live") or not arg:
        raise UsageError(
            f"{PROG} record: --source: expected 'sim', 'replay:FILE' or 'live:CONFIG', "
            f"got {source!r}"
        )
    path = Path(arg)
    if kind == "replay":
        if path.resolve() == rec_out.resolve():
            raise UsageError(f"{PROG} record: --out must differ from the recording replayed")
        opened = open_source(replay=path, rig=rig, realtime=False)
        src = opened.source
        out(f"Re-recording {path} ({src.duration_s:.3f} s, sensors {', '.join(src.sensors)})")
        end_ns = None if args.duration is None else src.start_ns + round(args.duration * 1e9)
    else:
        try:
            opened = open_source(live=path, rig=rig, live_flag="--source live:CONFIG")
        except NeedsRig as exc:
            raise UsageError(f"{PROG} record: {exc}") from None
        src = opened.source
        end_ns = None
        if args.duration is not None:
            end_ns = time.time_ns() + round(args.duration * 1e9)
        out(
            f"Recording {', '.join(src.sensors)} from {path}"
            + (f" for {args.duration:g} s" if args.duration else " until Ctrl-C")
        )
    damage = None
    fuser = None
    # A replay keeps the recording's head poses (world -> rig), each before the frames of
    # its time.
    poses = read_poses(path, opened.rig.reference) if kind == "replay" else None
    pose_list = [] if poses is None else list(zip(poses.stamps_ns, poses.T_world_rig, strict=True))
    next_pose = 0
    with src, Recording(opened.rig, path=rec_out, jpeg_quality=args.jpeg_quality) as writer:
        say_where(writer)
        if args.fused_video:
            fuser = attach_fused_video(writer, args)
        try:
            for frame in src.frames():
                if end_ns is not None and frame.stamp_ns >= end_ns:
                    break
                while next_pose < len(pose_list) and pose_list[next_pose][0] <= frame.stamp_ns:
                    writer.write_pose(int(pose_list[next_pose][0]), pose_list[next_pose][1])
                    next_pose += 1
                writer.write(frame)
                if writer.frames_written % 100 == 0:
                    out(f"  {writer.frames_written} frames")
        except RecordingDamaged as exc:
            damage = exc
    record_summary(rec_out, writer)
    if fuser is not None:
        video_summary(fuser)
    if kind == "replay":
        from trifuse.app.recording.player import skips_text

        for line in skips_text(src.skipped):  # type: ignore[attr-defined]
            err(f"{PROG}: warning: {line}; the other frames were recorded")
    if damage is not None:
        err(f"{PROG}: warning: {damage}; the frames before it were recorded")
    return EXIT_OK
