"""``trifuse record --source sim``: the simulated head's inspection room or survey
(``--scenario``) rendered into a recording, with the head's pose per instant, the
estimated time first and the time left as it goes."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trifuse.app.cli.args import EXIT_OK, PROG, UsageError
from trifuse.app.cli.output import err, out
from trifuse.app.cli.record_output import record_summary, say_where
from trifuse.app.cli.record_video import attach_fused_video, fused_video_cost_s, video_summary

if TYPE_CHECKING:
    from trifuse.app.recording.recording import Recording
    from trifuse.app.recording.video_track import FusedVideoFuser
    from trifuse.calib.rig import Rig


def span(seconds: float) -> str:
    """A duration for people: ``42 s``, ``3.5 min`` or ``2.1 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def record_sim(args: argparse.Namespace, rec_out: Path, rig: Rig | None) -> int:
    """Record ``--duration`` s (default 2) of the simulated head (``rig``, default the
    built-in head) in ``--scenario`` into ``rec_out``, live mode at ``--pose-hz`` or
    ``--exact``."""
    from trifuse.app.recording.simrecord import (
        POSE_HZ,
        SimProgress,
        plan_simulation,
        record_simulation,
    )
    from trifuse.app.sources.sim.head import default_rig

    rig = rig or default_rig()
    duration = 2.0 if args.duration is None else args.duration
    pose_hz = POSE_HZ if args.pose_hz is None else args.pose_hz
    if not (np.isfinite(pose_hz) and pose_hz > 0):
        raise UsageError(
            f"{PROG} record: --pose-hz: expected a positive number of Hz, got {pose_hz:g}"
        )
    if args.exact and args.pose_hz is not None:
        raise UsageError(f"{PROG} record: --pose-hz goes with the live mode, not --exact")
    plan = plan_simulation(rig, duration, exact=args.exact, pose_hz=pose_hz)
    if args.exact:
        how = (
            f"every instant rendered at its own time in the accurate quality "
            f"({plan.renders} images)"
        )
    else:
        how = (
            f"head poses rendered at {pose_hz:g} Hz ({plan.poses} poses, live quality), "
            "each frame turned to its own instant's head pose with fresh noise "
            "(--exact renders every instant)"
        )
    estimate_s = plan.estimate_s
    if args.fused_video:
        video_s = fused_video_cost_s(rig, plan.schedule)
        estimate_s += video_s
        how += f"; the fused video about {span(video_s)} of it"
    out(
        f"Recording {duration:g} s of the simulated head ({args.scenario} scenario, seed "
        f"{args.seed}): {len(plan.schedule)} instants, {plan.frames} frames, time "
        f"stamps at each sensor's rate; {how}. Estimated time: about "
        f"{span(estimate_s)} ({estimate_s / duration:.0f}x real time) on a "
        "quiet 2-core machine, more on a busy one; the progress lines give the time left."
    )

    def progress(p: SimProgress) -> None:
        out(
            f"[{p.index}/{p.total}] t = {p.stamp_ns / 1e9:.4f} s: {', '.join(p.sensors)} "
            f"({p.seconds:.2f} s), elapsed {span(p.elapsed_s)}, ETA {span(p.eta_s)}"
        )

    fusers: list[FusedVideoFuser] = []

    def opened(writer: Recording) -> None:
        say_where(writer)
        if args.fused_video:
            fusers.append(attach_fused_video(writer, args))

    try:
        writer = record_simulation(
            rec_out,
            rig,
            duration,
            seed=args.seed,
            jpeg_quality=args.jpeg_quality,
            progress=progress,
            plan=plan,
            opened=opened,
            scenario=args.scenario,
        )
    except KeyboardInterrupt:
        if rec_out.exists():
            err(f"{PROG}: interrupted; what was recorded so far is in {rec_out}")
        raise
    record_summary(rec_out, writer)
    for fuser in fusers:
        video_summary(fuser)
    return EXIT_OK
