"""The ``trifuse`` command line.

Every command is a function ``_cmd_<name>(args) -> int`` registered in :func:`build_parser`.
Bad arguments and bad input (``ValueError`` and its subclasses ``CaptureError``, ``RigError``
...) print one line to stderr and exit 2; operating-system errors (permissions, a full disk)
exit 1 the same way. No traceback reaches the user for either.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np

PROG = "trifuse"
EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2


class UsageError(Exception):
    """Bad command-line arguments; the message is one line for the user."""


class _Parser(argparse.ArgumentParser):
    """argparse, but errors raise UsageError (one line, no usage dump, no sys.exit)."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def _out(msg: str) -> None:
    print(msg, flush=True)


# -- simulate calibration -----------------------------------------------------------------


def _check_output_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        raise UsageError(
            f"--out {out}: directory exists and is not empty; refusing to write into it so "
            "that nothing captured there is overwritten (choose a new directory)"
        )


def _cmd_simulate_calibration(args: argparse.Namespace) -> int:
    from app.capture import write_board, write_ground_truth, write_rig, write_view
    from app.preview import ContactSheet
    from app.rigfile import load_rig
    from app.sources.sim.head import default_rig, nominal_rig
    from app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_views

    out = Path(args.out)
    _check_output_dir(out)
    truth = load_rig(args.rig) if args.rig else default_rig()
    start = nominal_rig(truth)

    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    try:
        write_board(out, CALIBRATION_BOARD)
        write_rig(out, start)
        poses: list[tuple[str, np.ndarray]] = []
        sheet = ContactSheet(truth.names)
        t_view = time.perf_counter()
        for i, view in enumerate(calibration_views(args.views, args.seed, truth), start=1):
            path = write_view(out, view.name, view.frames, truth)
            poses.append((view.name, view.T_rig_board))
            sheet.add(view.name, view.frames)
            now = time.perf_counter()
            _out(
                f"[{i}/{args.views}] view {view.name}: {len(view.frames.frames)} sensors "
                f"-> {path} ({now - t_view:.1f} s)"
            )
            t_view = now
        write_ground_truth(out, truth, poses, CALIBRATION_BOARD)
        sheet.write(out / "overview.png")
    except BaseException:
        print(
            f"{PROG}: partial output left in {out}; delete it before running again", file=sys.stderr
        )
        raise

    elapsed = time.perf_counter() - t_start
    first = poses[0][0] if poses else "0001"
    tof = truth.by_modality("tof")
    files = [f"{s}.png" for s in truth.names] + [f"{s}_distance.png" for s in tof]
    listing = [
        ("board.yaml", "the checkerboard"),
        ("rig.yaml", "a nominal starting rig (where a calibration starts from)"),
        (f"{first}/ ...", f"one folder per view: {', '.join(files)}"),
        ("ground_truth.yaml", "the true board pose of every view"),
        ("ground_truth_rig.yaml", "the rig the views were rendered with"),
        ("overview.png", "every view (rows) in every sensor (columns), contrast-stretched"),
    ]
    width = max(len(name) for name, _ in listing) + len(str(out)) + 3
    _out("")
    _out(f"Wrote {len(poses)} simulated calibration views to {out}/ in {elapsed:.1f} s:")
    for name, what in listing:
        _out(f"  {f'{out}/{name}':<{width}} {what}")
    _out(f"Look at it: open {out}/overview.png (all views, thermal and TOF contrast-stretched),")
    _out("or the per-view PNGs (thermal and TOF files are 16-bit centi-kelvin / amplitude and")
    _out("millimetres, so they look flat in a plain viewer), or list what a calibration reads:")
    _out(
        f'  {sys.executable} -c "from app.capture import load_capture; '
        f"print(load_capture('{out}').summary())\""
    )
    _out("Formats: docs/FORMATS.md")
    return EXIT_OK


# -- calibrate ----------------------------------------------------------------------------


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from app.calibration_run import calibrate_capture, format_summary, write_report
    from app.capture import load_capture
    from app.rigfile import save_rig
    from calib.rig_calibration import CalibrationOptions

    out, report_path = Path(args.out), Path(args.report) if args.report else None
    for path in (out, report_path):
        if path is not None and path.exists():
            raise UsageError(f"{path}: exists; refusing to overwrite it (choose a new name)")
    capture = load_capture(args.capture_dir)
    _out(capture.summary())
    options = CalibrationOptions(
        reference=args.reference, refine_intrinsics=not args.fixed_intrinsics
    )
    last = [-1]

    def progress(stage: str, fraction: float) -> None:
        percent = int(100 * fraction)
        if percent // 10 != last[0] // 10:
            last[0] = percent
            _out(f"[{percent:3d}%] {stage}")

    sensors = args.sensors.split(",") if args.sensors else None
    result, report = calibrate_capture(capture, options, sensors, progress)
    _out("")
    _out(format_summary(result, report))
    save_rig(out, result.rig())
    _out("")
    _out(f"rig written to {out}")
    if report_path is not None:
        write_report(report_path, report)
        _out(f"report written to {report_path}")
    return EXIT_OK


# -- bench --------------------------------------------------------------------------------


def _cmd_bench(args: argparse.Namespace) -> int:
    from app.bench import REGISTRY, run_benchmark

    names = [args.only] if args.only else list(REGISTRY)
    if args.only and args.only not in REGISTRY:
        raise UsageError(
            f"{PROG} bench: --only: unknown benchmark {args.only!r} (known: {', '.join(REGISTRY)})"
        )
    for name in names:
        _out(f"running {name}: {REGISTRY[name].description} ...")
        result = run_benchmark(name, args.repeat)
        _out(result.format())
    return EXIT_OK


# -- parser -------------------------------------------------------------------------------


def _bench_names() -> str:
    from app.bench import REGISTRY

    return ", ".join(f"{n} ({b.description})" for n, b in REGISTRY.items())


def build_parser() -> argparse.ArgumentParser:
    """The ``trifuse`` parser; each command sets ``func`` to its handler."""
    parser = _Parser(
        prog=PROG,
        description="Calibrate and operate a colour / thermal / time-of-flight sensor head.",
        epilog=f"Run '{PROG} COMMAND --help' for a command's options.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    commands = parser.add_subparsers(title="commands", metavar="COMMAND", dest="command")

    # simulate ------------------------------------------------------------------------
    simulate = commands.add_parser(
        "simulate",
        help="write simulated data sets (a calibration capture directory with ground truth)",
        description="Render data sets with the simulated five-imager head.",
        epilog=f"Run '{PROG} simulate WHAT --help' for its options.",
    )
    sim_what = simulate.add_subparsers(title="what to simulate", metavar="WHAT", dest="what")
    calib_p = sim_what.add_parser(
        "calibration",
        help="checkerboard views of every sensor, written as a capture directory",
        description=(
            "Render N views of the heated checkerboard with all sensors of the simulated "
            "head and write them as a capture directory (docs/FORMATS.md): board.yaml, "
            "rig.yaml (a nominal starting rig), one folder per view (colour 8-bit PNG, "
            "thermal 16-bit centi-kelvin, TOF amplitude and distance in millimetres), and the "
            "ground truth (ground_truth.yaml: board poses; ground_truth_rig.yaml: the true rig)."
        ),
    )
    calib_p.add_argument(
        "--views",
        type=_positive_int,
        default=30,
        metavar="N",
        help="number of views to render (default: %(default)s)",
    )
    calib_p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output directory; must not exist or be empty (nothing is ever overwritten)",
    )
    calib_p.add_argument(
        "--seed",
        type=_seed,
        default=1,
        metavar="N",
        help="random seed of the board poses and sensor noise; the same seed "
        "gives the same views (default: %(default)s)",
    )
    calib_p.add_argument(
        "--rig",
        metavar="RIG.yaml",
        help="ground-truth rig file to render with (default: the simulator's "
        "built-in head); the starting rig.yaml is then derived from it",
    )
    calib_p.set_defaults(func=_cmd_simulate_calibration)

    # calibrate -------------------------------------------------------------------------
    cal = commands.add_parser(
        "calibrate",
        help="calibrate every sensor's intrinsics and 6-DOF pose from a capture directory",
        description=(
            "Detect the checkerboard in every image of CAPTURE_DIR (docs/FORMATS.md), "
            "calibrate each sensor's intrinsics (Zhang) and then the whole rig jointly "
            "(every sensor pose, every board pose and the intrinsics, robust loss, outlier "
            "views and corners flagged and left out), and write the calibrated rig file "
            "with 1-sigma uncertainties. Prints a summary: RMS per sensor, parameters with "
            "their uncertainty, coverage of each image, outliers and rejected images."
        ),
    )
    cal.add_argument("capture_dir", metavar="CAPTURE_DIR", help="the capture directory")
    cal.add_argument(
        "--out",
        required=True,
        metavar="RIG.yaml",
        help="calibrated rig file to write (must not exist)",
    )
    cal.add_argument(
        "--report",
        metavar="REPORT.json",
        help="also write the full report as JSON (must not exist): per sensor "
        "RMS, views, intrinsics, distortion, pose and sigma; per view and sensor "
        "the RMS and outlier flag; detections, coverage, outliers",
    )
    cal.add_argument(
        "--reference",
        metavar="NAME",
        help="sensor whose frame is the rig frame (default: the TOF camera, "
        "else the first sensor by name)",
    )
    cal.add_argument(
        "--sensors",
        metavar="A,B,...",
        help="calibrate only these sensors (comma-separated; default: all)",
    )
    cal.add_argument(
        "--fixed-intrinsics",
        action="store_true",
        help="keep each sensor's Zhang intrinsics in the joint refinement "
        "(default: refine them with the poses)",
    )
    cal.set_defaults(func=_cmd_calibrate)

    # bench ---------------------------------------------------------------------------
    bench = commands.add_parser(
        "bench",
        help="run the benchmarks and print median timings (and ratios to baselines)",
        description=(
            "Run the registered benchmarks and print the median of each figure over the "
            "repeats (after a warm-up), and for benchmarks with a baseline measured in the "
            "same run the ratio figure / baseline. Results are recorded in BENCHMARKS.md."
        ),
    )
    bench.add_argument(
        "--only", metavar="NAME", help=f"run one benchmark only; known: {_bench_names()}"
    )
    bench.add_argument(
        "--repeat",
        type=_positive_int,
        metavar="N",
        help="timed repeats per benchmark (default: each benchmark's own, typically 10)",
    )
    bench.set_defaults(func=_cmd_bench)
    return parser


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("trifuse")
    except Exception:  # not installed: running from a source tree
        return "(source tree)"


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``trifuse`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if getattr(args, "func", None) is None:
            sub = f" {args.command}" if getattr(args, "command", None) else ""
            raise UsageError(f"{PROG}{sub}: expected a command (see '{PROG}{sub} --help')")
        return int(args.func(args))
    except SystemExit as exc:  # --help and --version
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    except UsageError as exc:
        print(f"{exc}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as exc:  # CaptureError, RigError, CalibrationError, ...
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (OSError, RuntimeError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
