"""The ``trifuse`` command line.

Every command is a function ``_cmd_<name>(args) -> int`` registered in :func:`build_parser`.
Bad arguments and bad input (``ValueError`` and its subclasses ``CaptureError``, ``RigError``
...) print one line to stderr and exit 2; operating-system errors (permissions, a full disk)
exit 1 the same way. No traceback reaches the user for either.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn
from urllib.parse import urlsplit

import numpy as np

from app.workflows.report_format import NEVER, limit_distance_cell, pixel_cell, sensor_colour

if TYPE_CHECKING:
    from app.recording.writer import RecordingWriter
    from app.server.routers.auth import AuthConfig
    from app.server.runtime.serve import TLSFiles
    from app.storage.capture import Capture
    from calib.board import Board
    from calib.rig import Rig
    from fusion.precision import PrecisionAnalysis

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


def _bounded_int(low: int, high: int) -> Callable[[str], int]:
    """An argparse type: an integer in ``[low, high]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected an integer from {low} to {high}, got {text!r}"
            )
        return value

    return parse


def _bounded_seconds(low: float, high: float) -> Callable[[str], float]:
    """An argparse type: seconds in ``[low, high]``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected a number of seconds from {low:g} to {high:g}, got {text!r}"
            )
        return value

    return parse


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


def _refuse_existing(flag: str, path: Path) -> NoReturn:
    """The one refusal of every command whose output file or directory exists already."""
    raise UsageError(f"{flag} {path}: exists; refusing to overwrite it (choose a new name)")


def _load_rig_arg(path: str, flag: str = "") -> Rig:
    """A rig file given on the command line; its errors on one line (a YAML error's
    message spans several), naming the option."""
    from app.storage.rigfile import load_rig

    try:
        return load_rig(path)
    except ValueError as exc:  # RigError
        lines = (line.strip() for line in str(exc).splitlines())
        text = " ".join(line for line in lines if line.strip("^"))
        raise ValueError(f"{flag} {text}" if flag else text) from None


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _board_size(text: str) -> tuple[int, int]:
    """``COLSxROWS`` inner corners, one odd and one even (a board the detector can orient)."""
    parts = text.lower().split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected COLSxROWS inner corners such as 9x6, got {text!r}"
        ) from None
    if min(cols, rows) < 2 or (cols + rows) % 2 == 0:
        raise argparse.ArgumentTypeError(
            f"expected at least 2x2 inner corners, one count odd and the other even (e.g. "
            f"9x6: only then do the square colours tell the board from its half turn), got "
            f"{text!r}"
        )
    return cols, rows


def _sensor_count(text: str) -> tuple[str, int]:
    name, sep, count = text.partition("=")
    try:
        n = int(count)
    except ValueError:
        n = -1
    if not sep or not name or n < 0:
        raise argparse.ArgumentTypeError(f"expected SENSOR=N (N >= 0), got {text!r}")
    return name, n


# -- simulate calibration -----------------------------------------------------------------


def _check_output_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise UsageError(
            f"--out {out}: exists and is not a directory; refusing to overwrite it "
            "(choose a new directory)"
        )
    if out.is_dir() and any(out.iterdir()):
        raise UsageError(
            f"--out {out}: directory exists and is not empty; refusing to write into it so "
            "that nothing captured there is overwritten (choose a new directory)"
        )


def _cmd_simulate_calibration(args: argparse.Namespace) -> int:
    from app.sources.sim.head import default_rig, nominal_rig
    from app.sources.sim.scenarios import board_finish, calibration_views
    from app.storage.capture import write_board, write_ground_truth, write_rig, write_view
    from app.storage.preview import ContactSheet
    from app.storage.rigfile import load_rig
    from calib.board import Board

    out = Path(args.out)
    _check_output_dir(out)
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

    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    try:
        write_board(out, board)
        write_rig(out, start)
        poses: list[tuple[str, np.ndarray]] = []
        sheet = ContactSheet(truth.names)
        t_view = time.perf_counter()
        rendered = calibration_views(
            args.views, args.seed, truth, board=board, finish=finish, sensor_views=sensor_views
        )
        for i, view in enumerate(rendered, start=1):
            path = write_view(out, view.name, view.frames, truth)
            poses.append((view.name, view.T_rig_board))
            sheet.add(view.name, view.frames)
            now = time.perf_counter()
            _out(
                f"[{i}/{args.views}] view {view.name}: {len(view.frames.frames)} sensors "
                f"-> {path} ({now - t_view:.1f} s)"
            )
            t_view = now
        write_ground_truth(out, truth, poses, board)
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
    width = max(len(name) for name, _ in listing) + len(str(out)) + 3
    _out("")
    _out(f"Wrote {len(poses)} simulated calibration views to {out}/ in {elapsed:.1f} s:")
    for name, what in listing:
        _out(f"  {f'{out}/{name}':<{width}} {what}")
    _out(f"Look at it: open {out}/overview.png (all views, thermal and TOF contrast-stretched),")
    _out("or the per-view PNGs (thermal and TOF files are 16-bit centi-kelvin / amplitude and")
    _out("millimetres, so they look flat in a plain viewer), or list what a calibration reads:")
    _out(
        f'  {sys.executable} -c "from app.storage.capture import load_capture; '
        f"print(load_capture('{out}').summary())\""
    )
    _out("Formats: docs/FORMATS.md")
    return EXIT_OK


# -- calibrate ----------------------------------------------------------------------------


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from app.storage.capture import load_capture
    from app.storage.rigfile import save_rig
    from app.workflows.calibration_run import calibrate_capture, format_summary, write_report
    from calib.rig_calibration import CalibrationOptions

    out, report_path = Path(args.out), Path(args.report) if args.report else None
    for flag, path in (("--out", out), ("--report", report_path)):
        if path is not None and path.exists():
            _refuse_existing(flag, path)
    truth = _load_rig_arg(args.truth, "--truth") if args.truth else None
    capture = load_capture(args.capture_dir)
    if truth is not None:
        _check_truth_fits(truth, capture, args.truth)
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
    if truth is not None:
        from app.workflows.report_format import comparison_text
        from calib.rig_compare import compare_rigs

        try:
            comparison = compare_rigs(result.rig(), truth)
        except ValueError as exc:  # e.g. every sensor in common was left out
            _err(f"{PROG}: warning: not compared with --truth {args.truth}: {exc}")
        else:
            report["comparison"] = {"truth": str(args.truth), **comparison.as_dict()}
            _out("")
            _out(comparison_text(comparison, "the calibration", str(args.truth)))
    save_rig(out, result.rig())
    _out("")
    _out(f"rig written to {out}")
    if report_path is not None:
        write_report(report_path, report)
        _out(f"report written to {report_path}")
    return EXIT_OK


def _check_truth_fits(truth: Rig, capture: Capture, path: str) -> None:
    """Before calibrating: ``--truth`` must share a sensor with the capture, of the same
    modality and image size (else the comparison at the end would fail)."""
    from app.workflows.calibration_run import sensor_specs

    specs = sensor_specs(capture)
    common = [n for n in truth.names if n in specs]
    if not common:
        raise ValueError(
            f"--truth {path}: no sensor in common with {capture.path} "
            f"(truth: {truth.names}; capture: {sorted(specs)})"
        )
    for n in common:
        t, spec = truth[n], specs[n]
        if (t.modality, t.image_size) != (spec.modality, tuple(spec.image_size)):
            raise ValueError(
                f"--truth {path}: sensor {n!r} is {t.modality} {t.image_size[0]}x"
                f"{t.image_size[1]} there but {spec.modality} {spec.image_size[0]}x"
                f"{spec.image_size[1]} in {capture.path}"
            )


# -- compare ------------------------------------------------------------------------------


def _cmd_compare(args: argparse.Namespace) -> int:
    import json

    from app.workflows.report_format import comparison_text
    from calib.rig_compare import compare_rigs

    estimate = _load_rig_arg(args.rig)
    truth = _load_rig_arg(args.truth)
    try:
        comparison = compare_rigs(estimate, truth)
    except ValueError as exc:
        raise ValueError(f"{args.rig} against {args.truth}: {exc}") from None
    if args.json:
        data = {"rig": str(args.rig), "truth": str(args.truth), **comparison.as_dict()}
        _out(json.dumps(data, indent=1, allow_nan=False))
    else:
        _out(comparison_text(comparison, str(args.rig), str(args.truth)))
    return EXIT_OK if comparison.passed else EXIT_FAILURE


# -- calibrate-range ----------------------------------------------------------------------


def numbered_backup(path: Path) -> Path:
    """``path.~N~`` with the first N not taken (GNU cp's numbered backups)."""
    n = 1
    while True:
        candidate = path.with_name(f"{path.name}.~{n}~")
        if not candidate.exists():
            return candidate
        n += 1


def _same_file(a: Path, b: Path | None) -> bool:
    return b is not None and a.exists() and b.exists() and a.resolve() == b.resolve()


def _check_rig_out(out: Path, rig_path: Path | None, **others: str | None) -> None:
    """``--out`` may be the ``--rig`` file itself (kept as a numbered backup); any other
    existing output (``others``: option name without dashes -> path) is refused."""
    outputs = [] if _same_file(out, rig_path) else [("--out", out)]
    outputs += [(f"--{flag}", Path(p)) for flag, p in others.items() if p]
    for flag, path in outputs:
        if path.exists():
            _refuse_existing(flag, path)


def _write_rig_out(out: Path, rig_path: Path | None, rig: Rig, what: str) -> None:
    """Write the updated rig; when it replaces ``rig_path``, the old file stays as
    ``RIG.yaml.~N~`` first."""
    from app.storage.rigfile import save_rig

    same = _same_file(out, rig_path)
    if same:
        backup = numbered_backup(out)
        os.link(out, backup)  # the rig as it was stays, under a new name
        _out(f"previous rig kept as {backup}")
    save_rig(out, rig, overwrite=same)
    _out(f"rig with {what} written to {out}")


def _cmd_calibrate_range(args: argparse.Namespace) -> int:
    from app.storage.capture import load_capture
    from app.storage.rigfile import load_rig
    from app.workflows.calibration_run import write_report
    from app.workflows.range_run import (
        build_range_report,
        calibrate_range,
        format_range_summary,
        region_chart,
        with_range_correction,
        write_png,
    )
    from calib.range_calibration import FitOptions

    rig_path, out = Path(args.rig), Path(args.out)
    _check_rig_out(out, rig_path, report=args.report, plot=args.plot)
    rig = load_rig(rig_path)
    capture = load_capture(args.capture_dir)
    _out(capture.summary())
    last = [-1]

    def progress(stage: str, fraction: float) -> None:
        percent = int(100 * fraction)
        if percent // 10 != last[0] // 10:
            last[0] = percent
            _out(f"[{percent:3d}%] {stage}")

    options = FitOptions(offset_step_px=args.offset_step)
    run = calibrate_range(capture, rig, args.holdout_every, options, progress)
    _out("")
    _out(format_range_summary(run))
    _out("")
    _write_rig_out(out, rig_path, with_range_correction(rig, run), "range_correction")
    if args.report:
        write_report(Path(args.report), build_range_report(run, capture))
        _out(f"report written to {args.report}")
    if args.plot:
        write_png(args.plot, region_chart(run.holdout, "RMS distance error, held-out views"))
        _out(f"chart written to {args.plot}")
    return EXIT_OK


# -- balance-thermal ----------------------------------------------------------------------


def _cmd_balance_thermal(args: argparse.Namespace) -> int:
    from app.recording import ReplaySource
    from app.storage.rigfile import load_rig
    from app.workflows.thermal_run import balance_source, format_thermal_summary, with_balance

    out = Path(args.out)
    rig_path = Path(args.rig) if args.rig else None
    _check_rig_out(out, rig_path)
    with ReplaySource(args.recording, realtime=False) as src:
        rig = load_rig(rig_path) if rig_path else src.rig
        if rig is None:
            raise ValueError(f"{args.recording}: the recording holds no rig; give one with --rig")
        imagers = [rig.eyes[e].thermal for e in ("left", "right")]
        if args.reference is not None and args.reference not in imagers:
            raise UsageError(f"--reference: expected one of {imagers}, got {args.reference!r}")
        _out(f"Balancing {' and '.join(imagers)} over {args.recording} ({src.duration_s:.1f} s)")
        run = balance_source(src, rig, args.every, reference=args.reference)
    _out(format_thermal_summary(run, rig))
    if run.estimate is None:
        return EXIT_FAILURE
    _write_rig_out(out, rig_path, with_balance(rig, run.terms), "radiometry")
    return EXIT_OK


# -- serve --------------------------------------------------------------------------------


def _load_board_arg(path: str | None) -> Board:
    """The board of ``--board`` (a board.yaml), else the simulated head's board."""
    if path is None:
        from app.sources.sim.scenarios import CALIBRATION_BOARD

        return CALIBRATION_BOARD
    from app.storage.capture import load_board_file

    return load_board_file(path)


def _serve_auth(args: argparse.Namespace) -> AuthConfig:
    """The console's authentication from ``--token`` / ``TRIFUSE_TOKEN`` / ``--no-token``,
    ``--host``, ``--allow-origin`` and TLS; UsageError for an unsafe or unusable choice."""
    from app.server.routers.auth import TOKEN_ENV, AuthConfig, check_token, is_loopback, new_token

    given = args.token if args.token is not None else os.environ.get(TOKEN_ENV)
    if args.no_token:
        if args.token is not None:
            raise UsageError(f"{PROG} serve: --token and --no-token exclude each other")
        if not is_loopback(args.host):
            raise UsageError(
                f"{PROG} serve: --host {args.host} --no-token: refusing to serve without a "
                "token on a non-loopback address (anyone on the network could watch the "
                "cameras and change the calibration); drop --no-token to use a token"
            )
        token = None
    else:
        try:
            network = not is_loopback(args.host)
            token = check_token(given, network) if given is not None else new_token()
        except ValueError as e:
            where = "--token" if args.token is not None else TOKEN_ENV
            raise UsageError(f"{PROG} serve: {where}: {e}") from None
    origins = set()
    for origin in args.allow_origin:
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.netloc or parts.path.strip("/"):
            raise UsageError(
                f"{PROG} serve: --allow-origin {origin!r}: expected scheme://host[:port], "
                "e.g. https://headset.local:8443"
            )
        origins.add(f"{parts.scheme}://{parts.netloc}".lower())
    return AuthConfig(token, args.port, args.certfile is not None, frozenset(origins))


def _serve_tls(args: argparse.Namespace) -> TLSFiles | None:
    """``--certfile``/``--keyfile`` checked by loading them, or None."""
    from app.server.runtime.serve import TLSFiles

    if (args.certfile is None) != (args.keyfile is None):
        raise UsageError(f"{PROG} serve: --certfile and --keyfile go together")
    if args.certfile is None:
        return None
    import ssl

    try:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(
            args.certfile, args.keyfile
        )
    except (OSError, ssl.SSLError) as e:
        raise UsageError(
            f"{PROG} serve: cannot use --certfile {args.certfile} --keyfile {args.keyfile}: {e}"
        ) from None
    return TLSFiles(Path(args.certfile), Path(args.keyfile))


def _cmd_serve(args: argparse.Namespace) -> int:
    from app.server.runtime.serve import bind_public_socket, open_source, serve
    from app.storage.workdir_lock import WorkdirInUse, lock_workdir

    auth = _serve_auth(args)
    tls = _serve_tls(args)
    chosen = [x for x in (args.replay, args.live, args.push or None) if x]
    if len(chosen) > 1:
        raise UsageError(f"{PROG} serve: choose one of --replay, --live, --push")
    if args.scenario != "inspection" and chosen:
        raise UsageError(f"{PROG} serve: --scenario is for the simulated head only")
    if args.scenario != "calibration" and (args.board_poses, args.hold) != (40, 3.0):
        raise UsageError(f"{PROG} serve: --board-poses and --hold are for --scenario calibration")
    board = _load_board_arg(args.board)
    try:  # the port and the work directory first: refusals come before anything starts
        sock = bind_public_socket(args.host, args.port)
    except OSError as e:
        raise UsageError(f"{PROG} serve: {e}") from None
    try:
        workdir = Path(args.workdir)
        try:
            lock = lock_workdir(workdir)
        except WorkdirInUse as e:
            raise UsageError(f"{PROG} serve: --workdir {e}") from None
        with lock:
            opened = open_source(
                args.replay,
                args.live,
                args.push,
                args.rig,
                args.scenario,
                args.board_poses,
                args.hold,
            )
            serve(opened, board, workdir, auth, args.host, tls, sock)
    finally:
        sock.close()
    return EXIT_OK


# -- bench --------------------------------------------------------------------------------


def _cmd_bench(args: argparse.Namespace) -> int:
    from app.devtools.bench import REGISTRY, run_benchmark, run_soak_command

    if args.soak:
        if args.only or args.repeat:
            raise UsageError(f"{PROG} bench: --soak runs alone (no --only, --repeat)")
        return run_soak_command(args.soak_seconds or 600.0, args.viewers or 10)
    if args.soak_seconds or args.viewers:
        raise UsageError(f"{PROG} bench: --soak-seconds and --viewers go with --soak")

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


# -- analyze ------------------------------------------------------------------------------


def _analyze_non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}") from None
    if not np.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def _analyze_positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def _analyze_pixel(text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        u, v = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a TOF pixel as U,V (two numbers, e.g. 87.5,71.5), got {text!r}"
        ) from None
    if not (np.isfinite(u) and np.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected finite pixel coordinates, got {text!r}")
    return u, v


def _analyze_error_names(analysis: PrecisionAnalysis) -> dict[str, str]:
    return {
        "distance_error": f"distance error {analysis.distance_error_m * 1000:g} mm",
        "tof_pixel_error": f"TOF pixel error {analysis.tof_pixel_error_px:g} px",
    }


def _analyze_table(
    analysis: PrecisionAnalysis, labels: dict[str, str], range_m: tuple[float, float]
) -> str:
    """The method's Table 1: radial distance (m) at which the shift reaches the threshold."""
    lo, hi = range_m
    errors = _analyze_error_names(analysis)
    head = ["TOF pixel", "error", "coord", *analysis.sensors]
    rows: list[list[str]] = []
    for (u, v), key in zip(analysis.tof_pixels, analysis.distance_error, strict=True):
        first_column = iter([pixel_cell(u, v), labels.get(key, "")])
        for kind, name in errors.items():
            per_sensor = analysis.results(kind)[key]
            for coord in ("x", "y"):
                cells = [
                    limit_distance_cell(getattr(r, f"{coord}_m"), hi) for r in per_sensor.values()
                ]
                rows.append([next(first_column, ""), name if coord == "x" else "", coord, *cells])
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]

    def line(cells: list[str]) -> str:
        left = [c.ljust(w) for c, w in zip(cells[:3], widths[:3], strict=True)]
        right = [c.rjust(max(w, 6)) for c, w in zip(cells[3:], widths[3:], strict=True)]
        return "  ".join(left + right).rstrip()

    out = [
        f"Radial distance [m] below which the shift in each sensor exceeds "
        f"{analysis.threshold_px:g} px (TOF: {analysis.tof}, range {lo:g}-{hi:g} m)",
        f"{NEVER} = never in the range; ≥{hi:.2f} = over the whole range",
        "",
        line(head),
    ]
    for i, row in enumerate(rows):
        if i and i % 4 == 0:
            out.append("")
        out.append(line(row))
    return "\n".join(out)


def _analyze_plot(
    analysis: PrecisionAnalysis, labels: dict[str, str], range_m: tuple[float, float]
) -> bytes:
    """PNG of the shift curves: a row per (TOF pixel, error), columns |dx| and |dy|.

    Log scale in pixels (the shifts span 1e-3 to 1e2 px); the threshold is a dashed red line
    and a dot marks each sensor's threshold distance. Colours are RGB until the encode.
    """
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    black, grey, light, red = (0, 0, 0), (110, 110, 110), (225, 225, 225), (200, 0, 0)
    pw, ph = 620, 300  # plot area of one panel
    ml, mr, mt, mb = 80, 30, 40, 55  # margins of one panel
    title_h, legend_h = 50, 40
    sub = 4  # fixed-point bits for sub-pixel polylines
    errors = _analyze_error_names(analysis)
    keys = list(analysis.distance_error)
    panels = [(key, kind) for key in keys for kind in errors]
    img = np.full(
        (title_h + legend_h + len(panels) * (mt + ph + mb), 2 * (ml + pw + mr), 3), 255, np.uint8
    )
    hi_m = range_m[1]
    thr = analysis.threshold_px

    def text(s: str, org: tuple[int, int], scale: float = 0.5, colour=black, th: int = 1) -> None:
        cv2.putText(img, s, org, font, scale, colour, th, cv2.LINE_AA)

    def text_w(s: str, scale: float = 0.5) -> int:
        return cv2.getTextSize(s, font, scale, 1)[0][0]

    def dashed(y: int, x0: int, x1: int, colour: tuple[int, int, int]) -> None:
        for xa in range(x0, x1, 12):
            cv2.line(img, (xa, y), (min(xa + 6, x1), y), colour, 1)

    text(
        f"Pixel shift in each sensor caused by TOF errors: {errors['distance_error']}, "
        f"{errors['tof_pixel_error']} (threshold {thr:g} px)",
        (ml, 32),
        0.7,
        black,
        2,
    )
    x, y = ml, title_h + 22
    # Decreasing line widths, so that coinciding curves (a left/right pair) both show.
    widths = [2 + max(len(analysis.sensors) - 1 - i, 0) for i in range(len(analysis.sensors))]
    for i, name in enumerate(analysis.sensors):
        colour = sensor_colour(i)
        cv2.line(img, (x, y - 5), (x + 30, y - 5), colour, widths[i], cv2.LINE_AA)
        text(name, (x + 38, y))
        x += 38 + text_w(name) + 30
    dashed(y - 5, x, x + 30, red)
    text(f"threshold {thr:g} px", (x + 38, y))
    x += 38 + text_w(f"threshold {thr:g} px") + 30
    cv2.circle(img, (x + 5, y - 5), 5, grey, -1, cv2.LINE_AA)
    text("distance where the shift falls to the threshold", (x + 16, y), 0.5, grey)

    steps = [m * 10.0**k for k in range(-3, 4) for m in (1, 2, 5)]
    step = max([s for s in steps if hi_m / s >= 8], default=steps[0])
    x_ticks = np.arange(0.0, hi_m + 1e-9, step)
    for p, (key, kind) in enumerate(panels):
        per_sensor = analysis.results(kind)[key]
        top = title_h + legend_h + p * (mt + ph + mb) + mt
        u, v = analysis.tof_pixels[keys.index(key)]
        where = f"TOF pixel {pixel_cell(u, v)}" + (f", {labels[key]}" if labels.get(key) else "")
        values = np.abs(np.concatenate([np.r_[r.dx_px, r.dy_px] for r in per_sensor.values()]))
        values = values[np.isfinite(values)]
        y_max = max(float(values.max()) if values.size else 0.0, 2 * thr)
        dec_hi = int(np.ceil(np.log10(y_max)))
        dec_lo = int(np.floor(np.log10(thr))) - 2
        for c, coord in enumerate(("x", "y")):
            left = c * (ml + pw + mr) + ml

            def to_px(
                d: np.ndarray,
                s: np.ndarray,
                left: int = left,
                top: int = top,
                lo: int = dec_lo,
                hi: int = dec_hi,
            ) -> np.ndarray:
                ly = np.log10(np.clip(np.abs(s), 10.0**lo, None))
                return np.stack(
                    [left + d / hi_m * pw, top + ph - (ly - lo) / (hi - lo) * ph], axis=-1
                )

            def py(value: float, to_px=to_px) -> int:
                return round(float(to_px(np.array(0.0), np.array(value))[1]))

            for dec in range(dec_lo, dec_hi + 1):
                yy = py(10.0**dec)
                cv2.line(img, (left, yy), (left + pw, yy), light, 1)
                cv2.line(img, (left - 6, yy), (left, yy), black, 1)
                label = f"{10.0**dec:g}"
                text(label, (left - 12 - text_w(label, 0.45), yy + 5), 0.45)
                for m in range(2, 10) if dec < dec_hi else ():
                    cv2.line(img, (left - 3, py(m * 10.0**dec)), (left, py(m * 10.0**dec)), black)
            for t in x_ticks:
                xx = left + round(t / hi_m * pw)
                cv2.line(img, (xx, top), (xx, top + ph), light, 1)
                cv2.line(img, (xx, top + ph), (xx, top + ph + 5), black, 1)
                text(f"{t:g}", (xx - text_w(f"{t:g}", 0.45) // 2, top + ph + 22), 0.45)
            cv2.rectangle(img, (left, top), (left + pw, top + ph), black, 1)
            xl = "radial distance [m]"
            text(xl, (left + (pw - text_w(xl)) // 2, top + ph + 44))
            text(f"|d{coord}| [px]", (left - ml + 4, top - 10))
            text(f"{errors[kind]} at {where}", (left + 90, top - 10), 0.5, black)
            dashed(py(thr), left, left + pw, red)
            for i, r in enumerate(per_sensor.values()):
                colour = sensor_colour(i)
                pts = to_px(r.distance_m, r.dx_px if coord == "x" else r.dy_px)
                good = np.flatnonzero(np.isfinite(pts).all(axis=1))
                for run in np.split(good, np.flatnonzero(np.diff(good) > 1) + 1):
                    if run.size > 1:
                        poly = np.round(pts[run] * (1 << sub)).astype(np.int32)
                        cv2.polylines(img, [poly], False, colour, widths[i], cv2.LINE_AA, sub)
                at = r.x_m if coord == "x" else r.y_m
                if at is not None and at < hi_m:
                    mx, my = to_px(np.array(at), np.array(thr))
                    cv2.circle(
                        img, (round(float(mx)), round(float(my))), 5, colour, -1, cv2.LINE_AA
                    )
                    cv2.circle(img, (round(float(mx)), round(float(my))), 5, black, 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", img[..., ::-1])  # RGB -> BGR at the OpenCV call
    if not ok:
        raise RuntimeError("could not encode the plot as PNG")
    return buf.tobytes()


def _cmd_analyze(args: argparse.Namespace) -> int:
    import json

    from app.storage.atomic import atomic_write_bytes
    from fusion.precision import (
        RANGE_MAX_M,
        RANGE_MIN_M,
        analyze_precision,
        sample_distances,
        tof_pixel_label,
    )

    plot = Path(args.plot) if args.plot else None
    if plot is not None and plot.exists():
        _refuse_existing("--plot", plot)
    rig = _load_rig_arg(args.rig)
    if args.tof is not None and args.tof not in rig:
        raise UsageError(f"--tof: no sensor {args.tof!r} in {args.rig} (sensors: {rig.names})")
    tofs = rig.by_modality("tof")
    if args.tof is None and len(tofs) != 1:
        raise ValueError(
            f"{args.rig}: expected exactly one sensor of modality 'tof', got {tofs}"
            + ("; name the TOF sensor with --tof" if tofs else "")
        )
    try:
        distances = sample_distances(RANGE_MIN_M, RANGE_MAX_M, args.step_m)
    except ValueError as exc:
        raise UsageError(f"{PROG} analyze: --step-m: {exc}") from None
    analysis = analyze_precision(
        rig,
        tof_pixels=args.tof_pixel,
        distance_error_m=args.distance_error_mm / 1000.0,
        tof_pixel_error_px=args.tof_pixel_error,
        threshold_px=args.threshold_px,
        distance_m=distances,
        tof=args.tof,
    )
    labels = {
        key: tof_pixel_label(rig, pixel, analysis.tof)
        for key, pixel in zip(analysis.distance_error, analysis.tof_pixels, strict=True)
    }
    range_m = (float(distances[0]), float(distances[-1]))
    if args.json:
        _out(json.dumps(analysis.as_dict(), allow_nan=False, separators=(",", ":")))
    else:
        _out(_analyze_table(analysis, labels, range_m))
    if plot is not None:
        atomic_write_bytes(plot, _analyze_plot(analysis, labels, range_m), overwrite=False)
        if not args.json:
            _out(f"\nplot written to {plot}")
    return EXIT_OK


# -- record -------------------------------------------------------------------------------


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number of seconds > 0, got {text!r}"
        ) from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds > 0, got {text!r}")
    return value


def _jpeg_quality(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer 1..100, got {text!r}") from None
    if not 1 <= value <= 100:
        raise argparse.ArgumentTypeError(f"expected an integer 1..100, got {value}")
    return value


def _err(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _record_summary(path: Path, writer: object) -> None:
    from app.recording import ReplaySource

    with ReplaySource(path, realtime=False) as rec:
        size_mb = path.stat().st_size / 1e6
        _out(
            f"Wrote {writer.frames_written} frames ({rec.duration_s:.3f} s, "  # type: ignore[attr-defined]
            f"{size_mb:.1f} MB) to {path}:"
        )
        for ch in sorted(rec.index.channels.values(), key=lambda c: c.topic):
            schema = rec.index.schema_of(ch)
            n = (rec.index.message_counts or {}).get(ch.id, 0)
            _out(f"  {ch.topic:<28} {schema.name if schema else '-':<28} {n} messages")
    _out("Open it in Foxglove as it is, or watch it in the console and fuse it offline:")
    _out(f"  {PROG} serve --replay {shlex.quote(str(path))}")
    _out(f"  {PROG} fuse {shlex.quote(str(path))} --out DIR")
    _out("Format: docs/FORMATS.md (Recordings).")


def _say_where(writer: RecordingWriter) -> None:
    _out(
        f"Writing into {writer.temp_path}; it becomes {writer.path} when the recording is "
        "finished (Ctrl-C or SIGTERM finish it too). If this program is killed, that file is "
        "a complete MCAP of everything but about the last second."
    )


def _sigterm_as_interrupt(signum: int, _frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def _cmd_record(args: argparse.Namespace) -> int:
    if threading.current_thread() is threading.main_thread():
        # SIGTERM (kill, systemd, a container stopping) finishes the file like Ctrl-C
        previous = signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
        try:
            return _record(args)
        finally:
            signal.signal(signal.SIGTERM, previous)
    return _record(args)


def _record(args: argparse.Namespace) -> int:
    from app.recording import RecordingDamaged, RecordingWriter, ReplaySource
    from app.storage.rigfile import load_rig

    out = Path(args.out)
    if out.exists() or out.is_symlink():
        _refuse_existing("--out", out)
    rig = load_rig(args.rig) if args.rig else None
    source = args.source
    if source == "sim":
        from app.recording.simrecord import (
            POSE_HZ,
            SimProgress,
            plan_simulation,
            record_simulation,
        )
        from app.sources.sim.head import default_rig

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

        def span(seconds: float) -> str:
            if seconds < 90:
                return f"{seconds:.0f} s"
            return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"

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
        _out(
            f"Recording {duration:g} s of the simulated head (inspection scenario, seed "
            f"{args.seed}): {len(plan.schedule)} instants, {plan.frames} frames, time "
            f"stamps at each sensor's rate; {how}. Estimated time: about "
            f"{span(plan.estimate_s)} ({plan.estimate_s / duration:.0f}x real time) on a "
            "quiet 2-core machine, more on a busy one; the progress lines give the time left."
        )

        def progress(p: SimProgress) -> None:
            _out(
                f"[{p.index}/{p.total}] t = {p.stamp_ns / 1e9:.4f} s: {', '.join(p.sensors)} "
                f"({p.seconds:.2f} s), elapsed {span(p.elapsed_s)}, ETA {span(p.eta_s)}"
            )

        try:
            writer = record_simulation(
                out,
                rig,
                duration,
                seed=args.seed,
                jpeg_quality=args.jpeg_quality,
                progress=progress,
                plan=plan,
                opened=_say_where,
            )
        except KeyboardInterrupt:
            if out.exists():
                _err(f"{PROG}: interrupted; what was recorded so far is in {out}")
            raise
        _record_summary(out, writer)
        return EXIT_OK
    kind, _, arg = source.partition(":")
    if kind not in ("replay", "live") or not arg:
        raise UsageError(
            f"{PROG} record: --source: expected 'sim', 'replay:FILE' or 'live:CONFIG', "
            f"got {source!r}"
        )
    path = Path(arg)
    if kind == "replay":
        if path.resolve() == out.resolve():
            raise UsageError(f"{PROG} record: --out must differ from the recording replayed")
        src = ReplaySource(path, realtime=False)
        rig = rig or src.rig
        if rig is None:
            src.close()
            raise ValueError(f"{path}: the recording holds no rig; give one with --rig")
        _out(f"Re-recording {path} ({src.duration_s:.3f} s, sensors {', '.join(src.sensors)})")
        end_ns = None if args.duration is None else src.start_ns + round(args.duration * 1e9)
    else:
        from app.sources.camera import CameraSource

        if rig is None:
            raise UsageError(
                f"{PROG} record: --source live:CONFIG needs --rig RIG.yaml "
                "(cameras do not know their calibration)"
            )
        src = CameraSource(path, rig=rig)
        end_ns = None
        if args.duration is not None:
            end_ns = time.time_ns() + round(args.duration * 1e9)
        _out(
            f"Recording {', '.join(src.sensors)} from {path}"
            + (f" for {args.duration:g} s" if args.duration else " until Ctrl-C")
        )
    damage = None
    with src, RecordingWriter(out, rig, jpeg_quality=args.jpeg_quality) as writer:
        _say_where(writer)
        try:
            for frame in src.frames():
                if end_ns is not None and frame.stamp_ns >= end_ns:
                    break
                writer.write(frame)
                if writer.frames_written % 100 == 0:
                    _out(f"  {writer.frames_written} frames")
        except RecordingDamaged as exc:
            damage = exc
    _record_summary(out, writer)
    if damage is not None:
        _err(f"{PROG}: warning: {damage}; the frames before it were recorded")
    return EXIT_OK


# -- fuse ---------------------------------------------------------------------------------


def _progress_bar(done: int, total: int | None, width: int = 30) -> str:
    if not total:
        return f"[{'?' * width}] {done} frames"
    filled = min(width, round(width * done / total))
    return f"[{'#' * filled}{'.' * (width - filled)}] {done}/{total} frames"


def _cmd_fuse(args: argparse.Namespace) -> int:
    from app.recording import ReplaySource
    from app.recording.fuse import VIDEO_NAME, fuse_recording
    from app.storage.rigfile import load_rig
    from fusion.compose import DisplaySettings

    out = Path(args.out)
    _check_output_dir(out)
    settings = DisplaySettings(mode=args.mode)
    with ReplaySource(args.recording, realtime=False) as src:
        rig = load_rig(args.rig) if args.rig else src.rig
        if rig is None:
            raise ValueError(f"{args.recording}: the recording holds no rig; give one with --rig")
        out.mkdir(parents=True, exist_ok=True)
        tty = sys.stderr.isatty()
        shown = [-1]

        def progress(done: int, total: int | None) -> None:
            tenth = (10 * done // total) if total else done // 100
            if tty:
                print(f"\r{_progress_bar(done, total)}", end="", file=sys.stderr, flush=True)
            elif tenth != shown[0]:
                shown[0] = tenth
                _err(_progress_bar(done, total))

        _out(
            f"Fusing {args.recording} ({src.duration_s:.3f} s) in {args.mode} mode "
            f"({'every frame set' if args.every == 1 else f'one frame set in {args.every}'}) "
            f"into {out}/"
        )
        result = fuse_recording(src, rig, out, settings, args.every, progress)
        if tty:
            print(file=sys.stderr)
    _out(f"Wrote {result.frames} fused frames to {out}/ (000000.jpg ..., frames.csv)")
    if result.video is not None:
        _out(f"Video: {result.video} ({result.fps:.2f} frames/s, mp4v)")
    else:
        _out(f"No video ({VIDEO_NAME}): {result.video_problem}; the JPEG frames are written")
    for reason, n in result.skipped.items():
        _out(f"  skipped {n} frame sets: {reason}")
    if result.damage is not None:
        _err(f"{PROG}: warning: {result.damage}; the frames before it were fused")
    if result.frames == 0:
        skipped = "; ".join(f"{n} frame sets: {r}" for r, n in result.skipped.items())
        raise ValueError(
            f"{args.recording}: no frame set could be fused"
            + (f" ({skipped})" if skipped else " (the recording holds no complete frame set)")
        )
    return EXIT_OK


# -- parser -------------------------------------------------------------------------------


def _bench_names() -> str:
    from app.devtools.bench import REGISTRY

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
    calib_p.add_argument(
        "--board",
        type=_board_size,
        default=(9, 6),
        metavar="COLSxROWS",
        help="inner corners of the checkerboard, one odd and one even (default: 9x6)",
    )
    calib_p.add_argument(
        "--square-size",
        type=_positive_float,
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
        type=_sensor_count,
        action="append",
        metavar="SENSOR=N",
        help="keep SENSOR's images in only N views, spread over the session (repeatable); "
        "the other sensors keep all",
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
    cal.add_argument(
        "--truth",
        metavar="TRUTH.yaml",
        help="also compare the result with this rig (e.g. the capture's "
        "ground_truth_rig.yaml), as 'trifuse compare' does; the report gains the comparison",
    )
    cal.set_defaults(func=_cmd_calibrate)

    # compare -------------------------------------------------------------------------
    cmp = commands.add_parser(
        "compare",
        help="compare a calibrated rig with the ground truth (errors against the targets)",
        description=(
            "Compare RIG.yaml with TRUTH.yaml (e.g. a simulated capture's "
            "ground_truth_rig.yaml): per sensor the intrinsic errors (fx, fy, cx, cy in px, "
            "fx and fy in %, and how far apart the distortion models put a pixel), and for "
            "every pair of sensors the error of their relative pose inv(T_rig_a) @ T_rig_b "
            "(rotation in degrees, translation in mm; independent of each rig's reference "
            "sensor). Each judged figure is marked pass or FAIL against the calibration "
            "targets: focal lengths within 0.3 % (colour, thermal) and 1 % (TOF); poses "
            "within 0.1 deg and 1 mm, 0.2 deg and 3 mm for pairs with the TOF. Sensors in "
            "one rig only are listed, not compared. Ends with a one-line verdict; the exit "
            "status is 0 when every figure meets its target, 1 when one does not."
        ),
    )
    cmp.add_argument("rig", metavar="RIG.yaml", help="the calibrated rig")
    cmp.add_argument("truth", metavar="TRUTH.yaml", help="the true (or reference) rig")
    cmp.add_argument(
        "--json",
        action="store_true",
        help="print JSON instead of the tables (docs/FORMATS.md, the report's 'comparison' block)",
    )
    cmp.set_defaults(func=_cmd_compare)

    # calibrate-range -----------------------------------------------------------------
    cr = commands.add_parser(
        "calibrate-range",
        help="calibrate the TOF camera's distance error from a capture directory",
        description=(
            "Fit the TOF range correction (distance-dependent wiggling, per-pixel offset, "
            "amplitude term; robust) from the TOF distance images of CAPTURE_DIR: each "
            "view's board pose comes from every sensor's corners and RIG.yaml, every TOF "
            "pixel on the board gets the distance where its ray meets the board. Every N-th "
            "view is held out of the fit to validate it; prints the RMS error before and "
            "after per accuracy region (1: centre 11x11, 2, 3, 4: border, not trusted), and "
            "writes the rig with the correction (range_correction of the TOF)."
        ),
    )
    cr.add_argument("capture_dir", metavar="CAPTURE_DIR", help="the capture directory")
    cr.add_argument("--rig", required=True, metavar="RIG.yaml", help="the calibrated rig")
    cr.add_argument(
        "--out",
        required=True,
        metavar="RIG.yaml",
        help="rig file to write: a new file, or the --rig file itself (its previous "
        "content is then kept as RIG.yaml.~N~)",
    )
    cr.add_argument(
        "--report",
        metavar="RANGE.json",
        help="also write the report as JSON (must not exist): per region and per view "
        "errors before and after, views used, held out and skipped",
    )
    cr.add_argument(
        "--plot",
        metavar="RANGE.png",
        help="also write a bar chart of the RMS error per region, before and after "
        "(held-out views; must not exist)",
    )
    cr.add_argument(
        "--holdout-every",
        type=_positive_int,
        default=4,
        metavar="N",
        help="hold every N-th usable view out of the fit to validate it (N >= 2; "
        "default: %(default)s)",
    )
    cr.add_argument(
        "--offset-step",
        type=_positive_int,
        default=8,
        metavar="PX",
        help="spacing of the per-pixel offset nodes in TOF pixels (default: %(default)s)",
    )
    cr.set_defaults(func=_cmd_calibrate_range)

    # balance-thermal -----------------------------------------------------------------
    bt = commands.add_parser(
        "balance-thermal",
        help="balance the two thermal imagers from a recording (points both see)",
        description=(
            "Replay RECORDING and, on every frame set, compare the two thermal imagers' "
            "readings of the TOF points both see (not occluded, off thermal edges); fit "
            "left = gain x right + offset robustly (the gain only when the scene's "
            "temperatures span enough), filter it over time, and write the rig with each "
            "imager's balance in its radiometry block (split evenly, or onto --reference). "
            "Refuses, leaving the rig unchanged, when the imagers share too few points."
        ),
    )
    bt.add_argument("recording", metavar="RECORDING", help="the recording (.mcap)")
    bt.add_argument("--rig", metavar="RIG.yaml", help="the rig (default: the recording's)")
    bt.add_argument(
        "--out",
        required=True,
        metavar="RIG.yaml",
        help="rig file to write: a new file, or the --rig file itself (its previous "
        "content is then kept as RIG.yaml.~N~)",
    )
    bt.add_argument(
        "--reference",
        metavar="NAME",
        help="the imager left unchanged (default: split the correction evenly)",
    )
    bt.add_argument(
        "--every",
        type=_positive_int,
        default=1,
        metavar="N",
        help="use every N-th frame set (default: %(default)s: all)",
    )
    bt.set_defaults(func=_cmd_balance_thermal)

    # serve ---------------------------------------------------------------------------
    srv = commands.add_parser(
        "serve",
        help="start the console: fused stereo viewer, 3D scene, stream (one URL)",
        description=(
            "Start the console on one port: the operator's fused stereo viewer at /, the "
            "stream (/stream WebSocket, /stream.mjpg), the Viser 3D console at /console/ "
            "(rig frames, sensor frustums, live TOF point cloud) and the API under /api/ "
            "(OpenAPI at /docs). Without a source option it runs on the simulated head."
        ),
    )
    srv.add_argument("--replay", metavar="FILE", help="replay a recording (looping)")
    srv.add_argument(
        "--live",
        metavar="CONFIG",
        help="OpenCV cameras (docs/FORMATS.md 'Live camera configuration'; needs --rig)",
    )
    srv.add_argument(
        "--push",
        action="store_true",
        help="take frames pushed by an on-robot driver at /ingest "
        "(docs/FORMATS.md 'Push ingest protocol')",
    )
    srv.add_argument(
        "--rig",
        metavar="RIG.yaml",
        help="the calibrated rig (default: the recording's or the simulated head's)",
    )
    srv.add_argument(
        "--scenario",
        choices=("inspection", "calibration"),
        default="inspection",
        help="what the simulated head sees: the inspection room, or the heated board "
        "held at --board-poses poses for a calibration session (default: %(default)s)",
    )
    srv.add_argument(
        "--board-poses",
        type=_bounded_int(1, 1000),
        default=40,
        metavar="N",
        help="calibration scenario: how many board poses it cycles through (default: "
        "%(default)s; each is rendered once, about 1.5 s of CPU)",
    )
    srv.add_argument(
        "--hold",
        type=_bounded_seconds(0.5, 3600.0),
        default=3.0,
        metavar="S",
        help="calibration scenario: seconds the board is held at each pose (default: "
        "%(default)s; auto-capture needs it still for two searches)",
    )
    srv.add_argument(
        "--workdir",
        metavar="DIR",
        default="trifuse-work",
        help="where the calibration session keeps its captures and saved rig versions "
        "(created if needed; reopened as it was on restart; default: ./%(default)s)",
    )
    srv.add_argument(
        "--board",
        metavar="BOARD.yaml",
        help="the calibration checkerboard (docs/FORMATS.md; default: the simulated "
        "head's 9 x 6 inner corners, 60 mm squares)",
    )
    srv.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default: %(default)s; e.g. 0.0.0.0 for every interface, "
        "which needs a token)",
    )
    srv.add_argument("--port", type=_positive_int, default=8000, help="port (default: %(default)s)")
    srv.add_argument(
        "--token",
        help="the secret that opens the console (at least 16 characters; default: "
        "$TRIFUSE_TOKEN, else a random one); printed in the console's URL, "
        "exchanged by the browser for a session cookie; scripts send "
        "'Authorization: token TOKEN'. Prefer TRIFUSE_TOKEN: arguments show in ps",
    )
    srv.add_argument(
        "--no-token",
        action="store_true",
        help="no authentication: only on a loopback --host, for a single-user machine",
    )
    srv.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        help="another origin (scheme://host[:port]) allowed to open WebSockets and send "
        "changes, besides the console's own (repeatable)",
    )
    srv.add_argument("--certfile", metavar="PEM", help="TLS certificate (chain): serve HTTPS/WSS")
    srv.add_argument("--keyfile", metavar="PEM", help="the certificate's private key")
    srv.set_defaults(func=_cmd_serve)

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
    bench.add_argument(
        "--soak",
        action="store_true",
        help="instead: the stream soak (BENCHMARKS.md 'Stream soak'): a console, a 1-viewer "
        "baseline, then --viewers viewers plus slow readers for --soak-seconds; frame "
        "rates and the server's memory; exit 1 if a criterion fails",
    )
    bench.add_argument(
        "--soak-seconds",
        type=_positive_int,
        metavar="S",
        help="length of the soak phase (default: 600)",
    )
    bench.add_argument(
        "--viewers",
        type=_positive_int,
        metavar="N",
        help="fast viewers during the soak, besides the slow readers (default: 10)",
    )
    bench.set_defaults(func=_cmd_bench)

    # analyze -------------------------------------------------------------------------
    ana = commands.add_parser(
        "analyze",
        help="how TOF distance and pixel errors shift the fused pixels (the method's Table 1)",
        description=(
            "For TOF pixels (default: the TOF's principal point and the point on its x axis "
            "at the edge of accuracy region 3) and radial distances 0.1-10 m, compute the "
            "pixel shift (dx, dy) that a TOF distance error, and a TOF pixel error along x, "
            "cause in every other sensor of RIG.yaml, and the radial distance below which "
            "that shift exceeds the threshold. Prints a table like the method's Table 1 "
            "('–' = the shift never reaches the threshold in the range), or JSON "
            "(--json), and optionally draws the curves (--plot). Definitions: "
            "fusion/precision.py."
        ),
    )
    ana.add_argument("rig", metavar="RIG.yaml", help="the rig file")
    ana.add_argument(
        "--distance-error-mm",
        type=_analyze_non_negative,
        default=41.0,
        metavar="MM",
        help="TOF radial distance error in millimetres (default: %(default)g, the method's "
        "value before range calibration; 15 after)",
    )
    ana.add_argument(
        "--tof-pixel-error",
        type=_analyze_non_negative,
        default=0.5,
        metavar="PX",
        help="TOF pixel error along the TOF image's x axis, in TOF pixels (default: %(default)g)",
    )
    ana.add_argument(
        "--threshold-px",
        type=_analyze_positive,
        default=0.5,
        metavar="PX",
        help="shift in a sensor's pixels that matters for the fusion (default: %(default)g)",
    )
    ana.add_argument(
        "--tof-pixel",
        type=_analyze_pixel,
        action="append",
        metavar="U,V",
        help="TOF pixel to analyse (repeatable; replaces the defaults: the principal point "
        "and the edge of region 3 on the x axis)",
    )
    ana.add_argument(
        "--step-m",
        type=_analyze_positive,
        default=0.01,
        metavar="M",
        help="radial distance step of the curves in metres (default: %(default)g, "
        "991 samples over 0.1-10 m)",
    )
    ana.add_argument(
        "--tof",
        metavar="NAME",
        help="the TOF sensor (default: the rig's only sensor of modality tof)",
    )
    ana.add_argument(
        "--json",
        action="store_true",
        help="print JSON instead of the table: {distance_error|tof_pixel_error: "
        "{'U,V': {sensor: {x_m, y_m, curve: {distance_m, dx_px, dy_px}}}}}",
    )
    ana.add_argument(
        "--plot",
        metavar="OUT.png",
        help="also draw the curves (|dx|, |dy| against distance, log scale) into this PNG "
        "(must not exist)",
    )
    ana.set_defaults(func=_cmd_analyze)

    # record --------------------------------------------------------------------------
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
            "inspection scenario with time stamps at each sensor's rate (colour 30 Hz, "
            "thermal 27 Hz, TOF 15 Hz): by default head poses rendered at --pose-hz in the "
            "live quality, each frame turned to its own instant's pose with fresh noise "
            "(about 7x slower than real time on 2 cores), with --exact every instant "
            "rendered accurately (about 130x); it says how long at the start and gives the "
            "time left as it goes; --source replay:FILE "
            "re-records a recording (a damaged one up to the damage)."
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
        type=_positive_seconds,
        metavar="S",
        help="seconds to record (sim default: 2; replay default: all of it)",
    )
    rec.add_argument(
        "--rig",
        metavar="RIG.yaml",
        help="rig file: the head to simulate (default: the simulator's built-in head) or "
        "the rig to store (default: the replayed recording's)",
    )
    rec.add_argument(
        "--seed", type=_seed, default=0, metavar="N", help="simulator noise seed (default: 0)"
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
        type=_jpeg_quality,
        default=90,
        metavar="Q",
        help="JPEG quality of the colour images, 1-100 (default: %(default)s)",
    )
    rec.set_defaults(func=_cmd_record)

    # fuse ----------------------------------------------------------------------------
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
    fuse.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output directory; must not exist or be empty (nothing is ever overwritten)",
    )
    fuse.add_argument(
        "--mode",
        default="blend",
        metavar="MODE",
        help="display mode (fusion.compose.MODES): color, blend, edges, thermal, threshold, "
        "isotherm or pip (default: %(default)s)",
    )
    fuse.add_argument(
        "--every",
        type=_positive_int,
        default=1,
        metavar="N",
        help="compose every N-th colour frame set (default: %(default)s: all)",
    )
    fuse.set_defaults(func=_cmd_fuse)
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
        message = str(exc)  # argparse's and some commands' messages name the command
        named = message.startswith((f"{PROG}:", f"{PROG} "))
        print(message if named else f"{PROG}: error: {message}", file=sys.stderr)
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
