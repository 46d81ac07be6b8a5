"""``trifuse simulate calibration``: checkerboard views of the simulated head written as a
capture directory with its ground truth."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from app.cli.args import (
    EXIT_OK,
    PROG,
    Commands,
    UsageError,
    board_size,
    positive_float,
    positive_int,
    seed,
    sensor_count,
)
from app.cli.files import add_out_dir_argument, check_output_dir
from app.cli.output import out


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``simulate`` and its one subcommand, ``calibration``."""
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
        type=positive_int,
        default=30,
        metavar="N",
        help="number of views to render (default: %(default)s)",
    )
    add_out_dir_argument(calib_p)
    calib_p.add_argument(
        "--seed",
        type=seed,
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
    calib_p.add_argument(
        "--board",
        type=board_size,
        default=(9, 6),
        metavar="COLSxROWS",
        help="inner corners of the checkerboard (default: 9x6; one odd and one even: the "
        "square colours then fix the ordering, else the calibration decides it per view)",
    )
    calib_p.add_argument(
        "--square-size",
        type=positive_float,
        default=0.06,
        metavar="M",
        help="side of a square, metres (default: %(default)s)",
    )
    calib_p.add_argument(
        "--thermal-board",
        choices=("heated", "cooled", "white-hot"),
        default="heated",
        help="how the board reads in thermal: heated with hot black squares, cooled (black "
        "squares cold), or heated with the high-emissivity paint on the white squares "
        "(white squares hot) (default: %(default)s); board.yaml never says which: the "
        "calibration finds it",
    )
    calib_p.add_argument(
        "--tof-board",
        choices=("dark", "bright"),
        default="dark",
        help="black squares dark in the TOF amplitude, or bright (an ink that reflects the "
        "near infrared) (default: %(default)s)",
    )
    calib_p.add_argument(
        "--sensor-views",
        type=sensor_count,
        action="append",
        metavar="SENSOR=N",
        help="keep SENSOR's images in only N views, spread over the session (repeatable); "
        "the other sensors keep all",
    )
    return calib_p


def run(args: argparse.Namespace) -> int:
    """Render ``--views`` views into the new directory ``--out``, then say what is there."""
    from app.sources.sim.head import default_rig, nominal_rig
    from app.sources.sim.scenarios import board_finish, calibration_views
    from app.storage.capture_writer import write_board, write_rig, write_view
    from app.storage.ground_truth import write_ground_truth
    from app.storage.preview import ContactSheet
    from app.storage.rigfile import load_rig
    from calib.board import Board

    out_dir = Path(args.out)
    check_output_dir(out_dir)
    truth = load_rig(args.rig) if args.rig else default_rig()
    start = nominal_rig(truth)
    cols, rows = args.board
    board = Board(cols, rows, args.square_size)
    finish = board_finish(args.thermal_board, args.tof_board)
    sensor_views = dict(args.sensor_views or [])
    unknown = sorted(set(sensor_views) - set(truth.names))
    if unknown:
        raise UsageError(
            f"--sensor-views: no sensor {', '.join(unknown)} in the rig (sensors: {truth.names})"
        )

    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    try:
        write_board(out_dir, board)
        write_rig(out_dir, start)
        poses: list[tuple[str, np.ndarray]] = []
        sheet = ContactSheet(truth.names)
        t_view = time.perf_counter()
        rendered = calibration_views(
            args.views, args.seed, truth, board=board, finish=finish, sensor_views=sensor_views
        )
        for i, view in enumerate(rendered, start=1):
            path = write_view(out_dir, view.name, view.frames, truth)
            poses.append((view.name, view.T_rig_board))
            sheet.add(view.name, view.frames)
            now = time.perf_counter()
            out(
                f"[{i}/{args.views}] view {view.name}: {len(view.frames.frames)} sensors "
                f"-> {path} ({now - t_view:.1f} s)"
            )
            t_view = now
        write_ground_truth(out_dir, truth, poses, board)
        sheet.write(out_dir / "overview.png")
    except BaseException:
        print(
            f"{PROG}: partial output left in {out_dir}; delete it before running again",
            file=sys.stderr,
        )
        raise

    elapsed = time.perf_counter() - t_start
    first = poses[0][0] if poses else "0001"
    tof = truth.by_modality("tof")
    files = [f"{s}.png" for s in truth.names] + [f"{s}_distance.png" for s in tof]
    listing = [
        (
            "board.yaml",
            f"the checkerboard: {cols}x{rows} inner corners of {args.square_size * 1000:g} mm, "
            f"{args.thermal_board} in thermal, black squares {args.tof_board} in the TOF "
            "(not written down: a calibration finds it)",
        ),
        ("rig.yaml", "a nominal starting rig (where a calibration starts from)"),
        (f"{first}/ ...", f"one folder per view: {', '.join(files)}"),
        ("ground_truth.yaml", "the true board pose of every view"),
        ("ground_truth_rig.yaml", "the rig the views were rendered with"),
        ("overview.png", "every view (rows) in every sensor (columns), contrast-stretched"),
    ]
    width = max(len(name) for name, _ in listing) + len(str(out_dir)) + 3
    out("")
    out(f"Wrote {len(poses)} simulated calibration views to {out_dir}/ in {elapsed:.1f} s:")
    for name, what in listing:
        out(f"  {f'{out_dir}/{name}':<{width}} {what}")
    out(f"Look at it: open {out_dir}/overview.png (all views, thermal and TOF contrast-stretched),")
    out("or the per-view PNGs (thermal and TOF files are 16-bit centi-kelvin / amplitude and")
    out("millimetres, so they look flat in a plain viewer), or list what a calibration reads:")
    out(
        f'  {sys.executable} -c "from app.storage.capture import load_capture; '
        f"print(load_capture('{out_dir}').summary())\""
    )
    out("Formats: docs/FORMATS.md")
    return EXIT_OK
