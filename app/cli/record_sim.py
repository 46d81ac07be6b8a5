"""``trifuse record --source sim``: the simulated head's inspection room or survey
(``--scenario``, one sensor moving with ``--drift``) rendered into a recording, with the
head's pose per instant, the estimated time first and the time left as it goes, from the
rate measured (:mod:`app.cli.progress`)."""

from __future__ import annotations

import argparse
import math
import os
from itertools import accumulate
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.cli.args import EXIT_OK, PROG, UsageError, sim_drift_arg
from trifuse.app.cli.output import err, out
from trifuse.app.cli.progress import ProgressLine, span
from trifuse.app.cli.record_output import record_summary, say_where
from trifuse.app.cli.record_video import attach_fused_video, fused_video_cost_s, video_summary

if TYPE_CHECKING:
    from trifuse.app.recording.recording import Recording
    from trifuse.app.recording.video_track import FusedVideoFuser
    from trifuse.calib.rig import Rig

DEFAULT_DURATION_S = {"inspection": 2.0, "survey": 12.0}
"""``--duration``'s default per scenario, seconds: the survey's is about a minute's work on
a quiet 2-core machine (it is 36 s long: pan and tilt, then the drive from 22 s)."""


def busy_note(cores: int | None = None, load: float | None = None) -> str:
    """``; this machine is busy (load 9.6 on 2 cores): expect longer`` when the load
    average over the last minute exceeds the cores, else ``""``; ``cores`` and ``load``
    default to this machine's."""
    try:
        cores = cores or os.cpu_count() or 1
        load = os.getloadavg()[0] if load is None else load
    except (AttributeError, OSError):  # no load average on this system
        return ""
    if load <= cores:
        return ""
    return f"; this machine is busy (load {load:.1f} on {cores} cores): expect longer"


def record_sim(args: argparse.Namespace, rec_out: Path, rig: Rig | None) -> int:
    """Record ``--duration`` s (default :data:`DEFAULT_DURATION_S`) of the simulated head
    (``rig``, default the built-in head) in ``--scenario`` into ``rec_out``, live mode at
    ``--pose-hz`` or ``--exact``, with ``--drift`` moving a sensor."""
    from trifuse.app.recording.simrecord import (
        POSE_HZ,
        SimProgress,
        plan_simulation,
        record_simulation,
    )
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.sources.sim.survey import SURVEY_S

    rig = rig or default_rig()
    drift = sim_drift_arg(args.drift, rig, "record", "--drift")
    duration = DEFAULT_DURATION_S[args.scenario] if args.duration is None else args.duration
    pose_hz = POSE_HZ if args.pose_hz is None else args.pose_hz
    if not (math.isfinite(pose_hz) and pose_hz > 0):
        raise UsageError(
            f"{PROG} record: --pose-hz: expected a positive number of Hz, got {pose_hz:g}"
        )
    if args.exact and args.pose_hz is not None:
        raise UsageError(f"{PROG} record: --pose-hz goes with the live mode, not --exact")
    plan = plan_simulation(rig, duration, exact=args.exact, pose_hz=pose_hz, drift=drift)
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
    if drift is not None:
        how += (
            f"; {drift.sensor} turned by ({', '.join(f'{x:g}' for x in drift.rotation_deg)}) "
            f"deg about its own axes from {drift.at_s:g} s on"
        )
    part = ""
    if args.scenario == "survey" and duration < SURVEY_S:
        part = f"; the survey lasts {SURVEY_S:g} s, --duration {SURVEY_S:g} records all of it"
    out(
        f"Recording {duration:g} s of the simulated head ({args.scenario} scenario, seed "
        f"{args.seed}{part}): {len(plan.schedule)} instants, {plan.frames} frames, time "
        f"stamps at each sensor's rate; {how}. Estimated time: about "
        f"{span(estimate_s)} ({estimate_s / duration:.0f}x real time) on a "
        f"quiet 2-core machine, more on a busy one{busy_note()}; the progress gives the time "
        "left at the rate measured as it goes."
    )
    # the work done after each instant, in planned seconds (the fused video's share spread)
    done = [c * estimate_s / plan.estimate_s for c in accumulate(plan.costs_s)]
    shown = ProgressLine(estimate_s)

    def progress(p: SimProgress) -> None:
        shown.update(
            done[p.index - 1],
            f"[{p.index}/{p.total}] t = {p.stamp_ns / 1e9:.2f} of {duration:g} s",
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
            drift=drift,
        )
    except KeyboardInterrupt:
        shown.close()
        if rec_out.exists():
            err(f"{PROG}: interrupted; what was recorded so far is in {rec_out}")
        raise
    shown.close()
    record_summary(rec_out, writer)
    for fuser in fusers:
        video_summary(fuser)
    return EXIT_OK
