"""``trifuse check``: has a sensor of the rig drifted? Checked on a recording of ordinary
scenes, without a board (:mod:`fusion.drift`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from trifuse.app.cli.args import EXIT_OK, PROG, Commands, bounded_seconds
from trifuse.app.cli.files import check_rig_out, load_rig_arg, write_rig_out
from trifuse.app.cli.output import err, out

if TYPE_CHECKING:
    from trifuse.calib.rig import Rig
    from trifuse.fusion.drift import DriftReport, SensorCheck

EXIT_DRIFTED = 3
"""The exit code when a sensor is ``drifted``."""


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``check RECORDING [--rig RIG.yaml] [--refine OUT.yaml] [--json] [--every-s S]``."""
    check = commands.add_parser(
        "check",
        help="check a recording for a sensor that has turned against the rig (no board)",
        description=(
            "Replay RECORDING as fast as possible and, every --every-s seconds of it, compare "
            "each eye's thermal imager with its colour camera, the two colour cameras and the "
            "two thermal imagers through the TOF depth: the rotation that best aligns their "
            "edges; and the TOF's depth edges with the colour cameras' outlines. Each sensor's "
            "verdict over the recording's last 60 s: ok, drifted (turned "
            "by more than 0.15 degrees, by 4 standard deviations) or undecided (with the "
            "reason). Exit 3 when a sensor is drifted, 0 when none is (ok or undecided), 1 on an "
            "error. "
            "--refine writes the rig with the drifted sensors turned back (never by more "
            "than 2 degrees: that needs a recalibration)."
        ),
    )
    check.add_argument("recording", metavar="RECORDING", help="a recording (.mcap)")
    check.add_argument(
        "--rig", metavar="RIG.yaml", help="rig file to check (default: the recording's rig)"
    )
    check.add_argument(
        "--refine",
        metavar="OUT.yaml",
        help="write the corrected rig here when a sensor is drifted: a new file, or the "
        "--rig file itself (its previous content is then kept as RIG.yaml.~N~)",
    )
    check.add_argument(
        "--json", action="store_true", help="print the result as JSON on stdout instead"
    )
    check.add_argument(
        "--every-s",
        type=bounded_seconds(0.05, 60.0),
        default=1.0,
        metavar="S",
        help="measure at most one frame set in S seconds of the recording (default: %(default)s)",
    )
    return check


def run(args: argparse.Namespace) -> int:
    """Check the recording; print the verdicts; write ``--refine``."""
    from trifuse.app.recording.reader import ReplaySource

    rig_path = Path(args.rig) if args.rig else None
    refine_out = Path(args.refine) if args.refine else None
    if refine_out is not None:
        check_rig_out(refine_out, rig_path)
    given = load_rig_arg(args.rig, "--rig") if args.rig else None
    with ReplaySource(args.recording, realtime=False, on_damage="stop") as src:
        rig = given or src.rig
        if rig is None:
            raise ValueError(f"{args.recording}: the recording holds no rig; give one with --rig")
        src.expect(rig)
        result = check_replay(src, rig, args.every_s)
    report, first, span_s = result
    if args.json:
        print(json.dumps(json_result(report, first, span_s), indent=2))
    else:
        for line in report_lines(args.recording, report, first, span_s):
            out(line)
    if refine_out is not None:
        if report.drifted:
            from trifuse.fusion.drift import refined_rig

            refined = refined_rig(rig, report)  # RefineRefused: a ValueError, exit 1
            what = "the drift of " + ", ".join(report.drifted) + " corrected"
            write_rig_out(refine_out, rig_path, refined, what)
        else:
            err(f"{PROG}: no sensor is drifted: {refine_out} not written")
    return EXIT_DRIFTED if report.drifted else EXIT_OK


def check_replay(src: Any, rig: Rig, every_s: float) -> tuple[DriftReport, dict[str, float], float]:
    """Measure a replay (``frames()``) with :class:`fusion.drift.DriftCheck`: the report over
    its last window, the time (seconds from its first frame set) each sensor was first found
    drifted, and the span measured, seconds."""
    from trifuse.app.sources.base import frame_sets
    from trifuse.fusion.drift import DriftCheck, synchronous

    check = DriftCheck(rig)
    sensors = [n for n in rig.names if n in src.sensors]
    colour = rig.by_modality("color")
    reference = colour[0] if colour and colour[0] in sensors else None
    first: dict[str, float] = {}
    t0: float | None = None
    last_s = -float("inf")
    t_s = 0.0
    for fs in frame_sets(src, sensors, reference=reference):
        t_s = fs.stamp_ns / 1e9
        if t0 is None:
            t0 = t_s
        if t_s - last_s < every_s:
            continue
        if not synchronous(fs.frames):
            continue
        last_s = t_s
        check.measure(t_s, fs.frames)
        for name in check.report().drifted:
            first.setdefault(name, t_s - t0)
    span = 0.0 if t0 is None else t_s - t0
    return check.report(), first, span


def json_result(report: DriftReport, first: dict[str, float], span_s: float) -> dict[str, Any]:
    """``{"sensors": {NAME: {"verdict", "rotation_deg": [x, y, z], "sigma_deg": [x, y, z],
    "angle_deg", "sigma_max_deg", "reason", "pairs", "first_drifted_s"}}, "instants",
    "span_s", "pairs", "problems"}``."""
    d = report.as_dict()
    for name, s in d["sensors"].items():
        s["first_drifted_s"] = first.get(name)
    d["span_s"] = span_s
    return d


def _rotation_text(s: SensorCheck) -> str:
    if s.rotation_deg is None or s.sigma_deg is None:
        return "not estimated"
    rot = ", ".join(f"{x:+.3f}" for x in s.rotation_deg)
    sig = ", ".join(f"{x:.3f}" for x in s.sigma_deg)
    return f"[{rot}]° ± [{sig}]°"


def report_lines(
    recording: str, report: DriftReport, first: dict[str, float], span_s: float
) -> list[str]:
    """The human-readable result: a header, a line per sensor (verdict, rotation and sigma
    in degrees about the sensor's own x, y, z axes, the reason), the last problems met."""
    from trifuse.fusion.drift import WINDOW_S

    lines = [
        f"{recording}: {report.instants} instants measured in the last "
        f"{min(span_s, WINDOW_S):.0f} s of {span_s:.0f} s"
    ]
    width = max(len(n) for n in report.sensors)
    for name, s in report.sensors.items():
        since = f" (first at {first[name]:.0f} s)" if name in first else ""
        lines.append(
            f"  {name:<{width}}  {s.verdict.upper() if s.verdict == 'drifted' else s.verdict:<9}"
            f"  {_rotation_text(s)}  {s.reason}{since}"
        )
    for p in report.problems[-3:]:
        lines.append(f"  note: {p}")
    return lines
