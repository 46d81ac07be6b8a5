"""``trifuse simulate calibration``: views of a calibration board (checkerboard, ChArUco or
asymmetric circle grid) seen by the simulated head, written as a capture directory with its
ground truth."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.cli.args import (
    EXIT_OK,
    PROG,
    Commands,
    UsageError,
    board_size_or_file,
    positive_float,
    positive_int,
    seed,
    sensor_count,
)
from trifuse.app.cli.files import add_out_dir_argument, check_output_dir
from trifuse.app.cli.output import out

if TYPE_CHECKING:
    import numpy as np

    from trifuse.calib.board import Board

PATTERNS = ("checkerboard", "charuco", "asymmetric_circles", "symmetric_circles")
"""The ``--pattern`` choices (calib.board.PATTERNS)."""
DEFAULT_POINTS = {
    "checkerboard": (9, 6),
    "charuco": (9, 6),
    "asymmetric_circles": (4, 11),
    "symmetric_circles": (7, 6),
}
"""``--board``'s default per pattern: inner corners, or circles per row x rows."""
CIRCLE_DIAMETER = {"asymmetric_circles": 0.7, "symmetric_circles": 0.5}
"""``--circle-diameter``'s default: this times the spacing."""
CHARUCO_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000")
"""Without ``--dictionary``, the first of these that has a marker for every white square."""


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
        help="board views of every sensor, written as a capture directory",
        description=(
            "Render N views of the heated board (a checkerboard, a ChArUco board or an "
            "asymmetric circle grid: --pattern) with all sensors of the simulated "
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
        "--pattern",
        choices=PATTERNS,
        default="checkerboard",
        help="the board's pattern (default: %(default)s); a ChArUco board leaves the image "
        "in every third view (partial views: the markers name the corners seen, and the "
        "image corners get covered); circles are heated (hot) or cooled like black squares; "
        "a symmetric circle grid looks the same turned half round: the calibration orders it",
    )
    calib_p.add_argument(
        "--board",
        type=board_size_or_file,
        default=None,
        metavar="COLSxROWS|BOARD.yaml",
        help="inner corners of the checkerboard or ChArUco board (default: 9x6; a "
        "checkerboard with one odd and one even: the square colours then fix the ordering, "
        "else the calibration decides it per view), circles per row x rows of a circle "
        "grid (default: 4x11 asymmetric, 7x6 symmetric); or a board.yaml (docs/FORMATS.md) "
        "that says it all",
    )
    calib_p.add_argument(
        "--square-size",
        type=positive_float,
        default=0.06,
        metavar="M",
        help="side of a square, metres; a circle grid's spacing (asymmetric: a row's "
        "circles are 2 x M apart, the next row is M down and shifted by M; symmetric: M "
        "apart both ways) (default: %(default)s)",
    )
    calib_p.add_argument(
        "--marker-size",
        type=positive_float,
        metavar="M",
        help="ChArUco: side of a marker, metres (default: 0.75 x the square)",
    )
    calib_p.add_argument(
        "--dictionary",
        metavar="NAME",
        help="ChArUco: OpenCV's ArUco dictionary (default: the smallest of "
        f"{', '.join(CHARUCO_DICTIONARIES)} with a marker for every white square)",
    )
    calib_p.add_argument(
        "--inverted",
        action="store_true",
        help="ChArUco: white markers on black squares (the print inverted)",
    )
    calib_p.add_argument(
        "--circle-diameter",
        type=positive_float,
        metavar="M",
        help="circle grids: diameter of a circle, metres (default: 0.7 x the spacing, "
        "symmetric 0.5 x)",
    )
    calib_p.add_argument(
        "--thermal-board",
        choices=("heated", "cooled", "white-hot"),
        default="heated",
        help="how the board reads in thermal: heated with hot black squares (markers, "
        "circles), cooled (black squares cold), or heated with the high-emissivity paint on "
        "the white squares (white squares hot) (default: %(default)s); board.yaml never "
        "says which: the calibration finds it",
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


def board_of_args(args: argparse.Namespace) -> Board:
    """The board ``--pattern``, ``--board`` and their options describe; UsageError (one
    line) for a combination that makes no board, or options of another pattern."""
    from trifuse.app.storage.capture import CaptureError, load_board_file
    from trifuse.calib.board import Board, aruco_dictionary

    pattern = args.pattern
    own = {
        "charuco": ("marker_size", "dictionary", "inverted"),
        "circle grids": ("circle_diameter",),
    }
    kind = "circle grids" if pattern in CIRCLE_DIAMETER else pattern
    for other, names in own.items():
        for name in names:
            if other != kind and getattr(args, name) not in (None, False):
                raise UsageError(
                    f"--{name.replace('_', '-')}: for {other} only, not --pattern {pattern}"
                )
    if isinstance(args.board, Path):
        if pattern != "checkerboard" or any(
            getattr(args, n) not in (None, False) for names in own.values() for n in names
        ):
            raise UsageError("--board BOARD.yaml: the file says the pattern and its sizes")
        try:
            return load_board_file(args.board)
        except CaptureError as exc:
            raise UsageError(f"--board: {exc}") from None
    cols, rows = args.board or DEFAULT_POINTS[pattern]
    s = args.square_size
    try:
        if pattern == "checkerboard":
            return Board(cols, rows, s)
        if pattern in CIRCLE_DIAMETER:
            d = args.circle_diameter or CIRCLE_DIAMETER[pattern] * s
            return Board(cols, rows, s, pattern=pattern, circle_diameter_m=d)
        n_markers = ((cols + 1) * (rows + 1)) // 2
        fits = [d for d in CHARUCO_DICTIONARIES if len(aruco_dictionary(d).bytesList) >= n_markers]
        dictionary = args.dictionary or (fits or CHARUCO_DICTIONARIES)[0]
        return Board(
            cols,
            rows,
            s,
            pattern=pattern,
            marker_size_m=args.marker_size or 0.75 * s,
            dictionary=dictionary,
            inverted=args.inverted,
        )
    except ValueError as exc:
        raise UsageError(f"{PROG} simulate calibration: {exc}") from None


def board_text(board: Board) -> str:
    """One line for the listing: what the board is (:meth:`Board.describe`)."""
    return "the " + board.describe()


def run(args: argparse.Namespace) -> int:
    """Render ``--views`` views into the new directory ``--out``, then say what is there."""
    from trifuse.app.sources.sim.head import default_rig, nominal_rig
    from trifuse.app.sources.sim.scenarios import board_finish, calibration_views
    from trifuse.app.storage.capture_writer import write_board, write_rig, write_view
    from trifuse.app.storage.ground_truth import write_ground_truth
    from trifuse.app.storage.preview import ContactSheet
    from trifuse.app.storage.rigfile import load_rig

    out_dir = Path(args.out)
    check_output_dir(out_dir)
    truth = load_rig(args.rig) if args.rig else default_rig()
    start = nominal_rig(truth)
    board = board_of_args(args)
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
            f"{board_text(board)}, {args.thermal_board} in thermal, its black {args.tof_board} "
            "in the TOF (not written down: a calibration finds it)",
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
        f'  {sys.executable} -c "from trifuse.app.storage.capture import load_capture; '
        f"print(load_capture('{out_dir}').summary())\""
    )
    out("Formats: docs/FORMATS.md")
    return EXIT_OK
