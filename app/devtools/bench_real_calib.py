"""Benchmark ``real-calib`` (issue 30): trifuse's calibration against OpenCV's plain pipeline
on every real set of :mod:`app.devtools.real_sets`, both measured in the same run.

For each set (the committed ones in ``tests/data``; the unlicensed
:data:`~app.devtools.real_sets.UNCOMMITTED_SETS` when their copy exists under
:data:`SCRATCH_DIR` or is given with ``--root NAME=DIR``; nothing is copied into the
checkout) this builds a trifuse capture directory (docs/FORMATS.md) in a temporary directory:
``board.yaml`` from the registry's board, one folder per view id, one image per sensor. The
images are the set's own files byte for byte (palette PNG, 8-bit or 12 MP JPEG, 8- or
16-bit PGM / PPM); a format the capture directory does not take (BMP, TIFF) is written as a
PNG with the same pixel values (16-bit stays 16-bit), and a video's frames as PNGs. A sensor
whose name does not tell trifuse its modality is renamed with a prefix (``visible`` ->
``ccd_visible``).

Then, on the same views:

* trifuse: :func:`app.storage.capture.load_capture`,
  :func:`app.workflows.calibration_run.detect_capture` (per sensor, its default 2 workers)
  and :func:`~app.workflows.calibration_run.calibrate_capture` with the options
  ``trifuse calibrate`` uses by default: the code that command runs;
* OpenCV: :func:`app.devtools.opencv_figures.measure` (detection: classic then sector-based, the
  thermal variants; ``cv2.calibrateCamera`` per sensor; ``cv2.stereoCalibrate`` per pair).

Per sensor: boards found, RMS (trifuse: the sensor alone, Zhang's fit with its own board
poses like ``calibrateCamera``, and in the joint rig result), fx, median detection time per
image (decoding excluded, both), and trifuse's outcome (a result, intrinsics only for a
sensor that shares no view with the rig, or the refusal's line);
per pair, baseline and rotation. The targets of issue 30 are checked per sensor: boards
found >= OpenCV's, a result whenever OpenCV gives one, thermal RMS (alone) at most
:data:`THERMAL_RMS_TOLERANCE` above OpenCV's. A set whose board or images trifuse cannot
load yet (ChArUco, a palette it cannot read) is reported "not supported yet" with trifuse's
own line; it is picked up as soon as ``board.yaml`` / the capture loader accept it.

``python -m trifuse.app.devtools.bench_real_calib [NAME ...] [--quick] [--root NAME=DIR]``
prints the Markdown tables; ``trifuse bench --only real-calib`` prints them too and returns the
figures
(``<set>.<sensor>.<figure>_trifuse`` against ``..._opencv``, with their ratios).
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np
import yaml

from trifuse.app.devtools import opencv_figures
from trifuse.app.devtools.benchmark import benchmark
from trifuse.app.devtools.opencv_figures import Measurement, measure
from trifuse.app.devtools.real_sets import (
    REAL_SETS,
    UNCOMMITTED_SETS,
    Checkerboard,
    RealSet,
    Sensor,
    load_views,
    sensor_files,
)
from trifuse.calib.opencv_reference import CharucoTarget
from trifuse.calib.transforms import rotation_angle_deg

SCRATCH_DIR = Path("/work/scratch")
"""Where the unlicensed sets are kept for measuring (never in the checkout)."""
SCRATCH_ROOTS = {
    "vimslab-thermal-calibration": "vimslab-thermal-calibration/test_imgs",
    "harunrk-lepton35-zed2i": "harunrk-lepton35-zed2i",
}
"""Each unlicensed set's directory under :data:`SCRATCH_DIR`."""
THERMAL_RMS_TOLERANCE = 0.05
"""Issue 30's target: a thermal sensor's RMS within 5 % of OpenCV's."""
QUICK_VIEWS = 6
"""``--quick``: about this many views per set (every k-th view id)."""
PREFIX = {"color": "ccd", "thermal": "thermal", "tof": "tof"}


@dataclass
class SensorRow:
    """One sensor of a set, trifuse against OpenCV (NaN / None where there is no figure).

    ``outcome`` is ``"result"``, ``"intrinsics only: <why>"`` (a result, its pose unknown),
    ``"refused: <line>"`` or ``"not supported yet: <line>"``;
    ``rms_alone_trifuse`` is Zhang's fit of the sensor alone (like calibrateCamera),
    ``rms_trifuse`` the joint rig result's; times are median ms per image."""

    sensor: str
    modality: str
    views: int
    found_trifuse: int | None
    found_opencv: int | None
    rms_trifuse: float = math.nan
    rms_alone_trifuse: float = math.nan
    rms_alone_opencv: float = math.nan
    fx_trifuse: float = math.nan
    fx_opencv: float = math.nan
    ms_trifuse: float = math.nan
    ms_opencv: float = math.nan
    outcome: str = ""
    missed: dict[str, str] = field(default_factory=dict)
    """Views where OpenCV found the board and trifuse did not -> trifuse's reason and the
    OpenCV variant that found it."""
    extra: list[str] = field(default_factory=list)
    """Views where trifuse found the board and OpenCV did not."""

    @property
    def supported(self) -> bool:
        return not self.outcome.startswith("not supported yet")

    @property
    def has_result(self) -> bool:
        """trifuse gave a result (intrinsics only counts: a sensor's own calibration)."""
        return self.outcome == "result" or self.outcome.startswith("intrinsics only")

    def targets(self) -> dict[str, bool | None]:
        """Issue 30's targets for this sensor: True / False, None where not applicable
        (not supported yet; no OpenCV result; not thermal)."""
        if not self.supported:
            return {"found": None, "result": None, "rms": None}
        opencv_result = math.isfinite(self.rms_alone_opencv)
        rms: bool | None = None
        if self.modality == "thermal" and opencv_result and self.has_result:
            rms = self.rms_alone_trifuse <= (1 + THERMAL_RMS_TOLERANCE) * self.rms_alone_opencv
        found = None
        if self.found_opencv is not None:
            found = (self.found_trifuse or 0) >= self.found_opencv
        return {
            "found": found,
            "result": self.has_result if opencv_result else None,
            "rms": rms,
        }


@dataclass
class PairRow:
    """Relative pose of sensor ``b`` to ``a``: trifuse's rig result against stereoCalibrate."""

    a: str
    b: str
    views_opencv: int | None = None
    baseline_mm_trifuse: float = math.nan
    baseline_mm_opencv: float = math.nan
    rotation_deg_trifuse: float = math.nan
    rotation_deg_opencv: float = math.nan


@dataclass
class SetRun:
    """Both pipelines on one set."""

    name: str
    committed: bool
    board: str
    step: int
    sensors: list[SensorRow] = field(default_factory=list)
    pairs: list[PairRow] = field(default_factory=list)
    seconds_trifuse: float = math.nan
    seconds_opencv: float = math.nan
    opencv_error: str = ""
    notes: list[str] = field(default_factory=list)
    load_1min: tuple[float, float] = (math.nan, math.nan)
    """The machine's 1-minute load average before and after the set."""

    def failed_targets(self) -> list[str]:
        """One line with the numbers for every target that does not hold."""
        out = []
        for s in self.sensors:
            t = s.targets()
            if t["found"] is False:
                out.append(
                    f"{s.sensor}: boards found {s.found_trifuse} < OpenCV's {s.found_opencv}"
                )
            if t["result"] is False:
                out.append(f"{s.sensor}: no result where OpenCV has one ({s.outcome})")
            if t["rms"] is False:
                out.append(
                    f"{s.sensor}: thermal RMS {s.rms_alone_trifuse:.3f} px > OpenCV's "
                    f"{s.rms_alone_opencv:.3f} px + {THERMAL_RMS_TOLERANCE:.0%} "
                    f"({s.rms_alone_trifuse / s.rms_alone_opencv - 1:+.1%})"
                )
        return out


# -- the capture directory -----------------------------------------------------------------


def trifuse_name(sensor: Sensor) -> str:
    """The sensor's name in the capture directory: its own when its prefix tells trifuse its
    modality, else prefixed (``visible`` -> ``ccd_visible``, ``cam_0`` -> ``ccd_cam_0``)."""
    from trifuse.calib.rig import modality_of_name

    if modality_of_name(sensor.name) == sensor.modality:
        return sensor.name
    return f"{PREFIX[sensor.modality]}_{sensor.name}"


def board_yaml(board: Checkerboard | CharucoTarget) -> dict[str, Any]:
    """``board.yaml`` content for a registry board (docs/FORMATS.md; ChArUco as agreed for
    issue 30: ``squares``, ``square_size_m``, ``marker_size_m``, ``dictionary``, ``inverted``)."""
    if isinstance(board, CharucoTarget):
        return {
            "pattern": "charuco",
            "squares": list(board.squares),
            "square_size_m": board.square_m,
            "marker_size_m": board.marker_m,
            "dictionary": board.dictionary,
            "inverted": board.inverted,
        }
    return {
        "pattern": "checkerboard",
        "inner_corners": [board.cols, board.rows],
        "square_size_m": board.square_m,
    }


def write_capture(rs: RealSet, root: Path | None, dest: Path) -> list[str]:
    """Write ``rs`` (every ``rs.view_step``-th view id per sensor, as
    :func:`~app.devtools.real_sets.load_views` takes them) as a capture directory ``dest``;
    returns notes on what was converted."""
    from trifuse.app.storage.capture import IMAGE_SUFFIXES

    dest.mkdir(parents=True, exist_ok=True)
    text = yaml.safe_dump(board_yaml(rs.board), sort_keys=False, default_flow_style=None)
    (dest / "board.yaml").write_text(text)
    converted: dict[str, int] = {}
    for sensor in rs.sensors:
        name = trifuse_name(sensor)
        if sensor.is_video:
            frames = load_views(rs, sensor, root)
            for view, image in frames.items():
                (dest / view).mkdir(exist_ok=True)
                cv2.imwrite(
                    str(dest / view / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
                )
            converted["video frames -> PNG"] = converted.get("video frames -> PNG", 0) + len(frames)
            continue
        files = sensor_files(rs, sensor, root)
        for view in sorted(files)[:: rs.view_step]:
            src = files[view]
            (dest / view).mkdir(exist_ok=True)
            if src.suffix.lower() in IMAGE_SUFFIXES:  # the capture directory takes it
                shutil.copyfile(src, dest / view / f"{name}{src.suffix.lower()}")
                continue
            pixels = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
            if pixels is None:
                raise ValueError(f"{src}: expected an image OpenCV can read")
            cv2.imwrite(str(dest / view / f"{name}.png"), pixels)
            what = f"{src.suffix.lower()[1:].upper()} -> {pixels.dtype.itemsize * 8}-bit PNG"
            converted[what] = converted.get(what, 0) + 1
    return [f"{what} (same pixel values): {n} file(s)" for what, n in converted.items()]


# -- timing the detectors where each pipeline calls them ------------------------------------


def timed(fn: Callable[..., Any], calls: list[tuple[float, Any]]) -> Callable[..., Any]:
    """``fn`` that appends (wall time ms, what it returned) to ``calls`` at each call."""

    def call(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        value = fn(*args, **kwargs)
        calls.append(((time.perf_counter() - t0) * 1e3, value))
        return value

    return call


@contextmanager
def timed_calls(module: ModuleType, *names: str) -> Iterator[list[tuple[float, Any]]]:
    """Within the block, calls of ``module.<name>`` (as the module's own code looks them up)
    are timed; yields the list of (wall time ms, what the call returned), in the order the
    calls ended."""
    calls: list[tuple[float, Any]] = []
    saved = {n: getattr(module, n) for n in names if hasattr(module, n)}  # renamed: untimed
    try:
        for n, fn in saved.items():
            setattr(module, n, timed(fn, calls))
        yield calls
    finally:
        for n, fn in saved.items():
            setattr(module, n, fn)


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else math.nan


def view_ids(rs: RealSet, sensor: Sensor, root: Path | None) -> list[str]:
    """The view ids :func:`~app.devtools.real_sets.load_views` gives, in its order."""
    if sensor.is_video:
        cap = cv2.VideoCapture(str(sensor_files(rs, sensor, root)["video"]))
        frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        return [f"{k:04d}" for k in range(0, frames, rs.view_step)]
    return sorted(sensor_files(rs, sensor, root))[:: rs.view_step]


# -- the two pipelines ---------------------------------------------------------------------


@dataclass
class OpenCVRun:
    """What :func:`opencv_figures.measure` gave: its figures (None if it failed: ``error``), and per
    sensor the views with a board and the median detection ms per image."""

    measurement: Measurement | None = None
    error: str = ""
    found: dict[str, dict[str, str]] = field(default_factory=dict)
    """Sensor -> view with a board -> the detector variant that found it ("" for ChArUco)."""
    ms: dict[str, float] = field(default_factory=dict)
    seconds: float = math.nan


def run_opencv(rs: RealSet, root: Path | None) -> OpenCVRun:
    """:func:`opencv_figures.measure` (OpenCV's plain pipeline), its detector calls timed."""
    out = OpenCVRun()
    t0 = time.perf_counter()
    with timed_calls(opencv_figures, "find_chessboard_opencv", "find_charuco_opencv") as calls:
        try:
            out.measurement = measure(rs, root)
        except ValueError as exc:  # e.g. a sensor with < 3 boards (--quick)
            out.error = str(exc)
    out.seconds = time.perf_counter() - t0
    # opencv_figures.detect looks at every sensor's views in turn, one detector call per image;
    # find_chessboard_opencv returns (corners or None, variant), find_charuco_opencv a hit or None.
    k = 0
    for s in rs.sensors:
        ids = view_ids(rs, s, root)
        mine = calls[k : k + len(ids)]
        k += len(ids)
        out.ms[s.name] = _median([ms for ms, _ in mine])
        out.found[s.name] = {}
        for v, (_, hit) in zip(ids, mine, strict=False):
            corners, variant = hit if isinstance(rs.board, Checkerboard) else (hit, "")
            if corners is not None:
                out.found[s.name][v] = variant
    return out


@dataclass
class TrifuseRun:
    """What trifuse's pipeline gave on a capture directory (sensors by capture name)."""

    found: dict[str, list[str]] = field(default_factory=dict)
    """Sensor -> the views with a board."""
    rejected: dict[str, dict[str, str]] = field(default_factory=dict)
    """Sensor -> view -> why no board was used (the detector's reason)."""
    ms: dict[str, float] = field(default_factory=dict)
    """Sensor -> median detection ms per image."""
    result: Any = None
    """The :class:`calib.rig_result.CalibrationResult`, or None."""
    failure: str = ""
    """The line ``trifuse calibrate`` would end with ("refused: ..." / "not supported yet: ...")."""
    seconds: float = math.nan


def run_trifuse(capture_dir: Path, names: list[str]) -> TrifuseRun:
    """``trifuse calibrate``'s code on ``capture_dir``: load, detect (sensor by sensor, to time
    each), calibrate with the default options. ``names``: the sensors, capture names."""
    from trifuse.app.storage.capture import load_capture
    from trifuse.app.workflows.calibration_run import (
        DetectionRun,
        calibrate_capture,
        detect_capture,
    )
    from trifuse.calib.polarity import detect_board_configured
    from trifuse.calib.rig_calibration import CalibrationOptions

    out = TrifuseRun()
    t0 = time.perf_counter()
    try:
        capture = load_capture(capture_dir)
        detections = DetectionRun({}, {}, {})
        for name in names:  # every image searched (no cached detection: it is timed)
            calls: list[tuple[float, Any]] = []
            run = detect_capture(capture, [name], detect=timed(detect_board_configured, calls))
            out.ms[name] = _median([ms for ms, _ in calls])
            out.found[name] = sorted(v for v, per in run.observations.items() if name in per)
            out.rejected[name] = {v: per[name] for v, per in run.rejected.items() if name in per}
            for mine, theirs in (
                (detections.observations, run.observations),
                (detections.rejected, run.rejected),
                (detections.methods, run.methods),
            ):
                for view, per in theirs.items():
                    mine.setdefault(view, {}).update(per)
    except ValueError as exc:  # the board, an image or the capture: not loadable yet
        out.failure = f"not supported yet: {exc}"
        return out
    try:
        out.result, _report = calibrate_capture(
            capture, CalibrationOptions(), detections=detections
        )
    except ValueError as exc:  # CalibrationError: trifuse calibrate's refusal
        out.failure = f"refused: {exc}"
    out.seconds = time.perf_counter() - t0
    return out


def _relative(T_rig_a: np.ndarray, T_rig_b: np.ndarray) -> tuple[float, float]:
    """Baseline (mm) and rotation (deg) between two sensor poses in the rig frame."""
    T = np.linalg.inv(T_rig_a) @ T_rig_b
    return float(np.linalg.norm(T[:3, 3]) * 1000), rotation_angle_deg(T[:3, :3])


def quick_step(rs: RealSet, root: Path | None, views: int = QUICK_VIEWS) -> int:
    """The view step that leaves about ``views`` views of the set's largest sensor."""
    most = max(len(view_ids(rs, s, root)) for s in rs.sensors)
    return rs.view_step * max(1, most // views)


def _sensor_row(
    s: Sensor, name: str, trifuse: TrifuseRun, opencv: OpenCVRun, views: int
) -> SensorRow:
    """One sensor's row from both runs (``name``: its name in the capture directory)."""
    ref = opencv.measurement.sensors.get(s.name) if opencv.measurement else None
    found_cv = opencv.found.get(s.name, {})
    found_tf = trifuse.found.get(name)
    row = SensorRow(
        s.name,
        s.modality,
        views,
        None if found_tf is None else len(found_tf),
        len(found_cv) if s.name in opencv.found else None,
        ms_trifuse=trifuse.ms.get(name, math.nan),
        ms_opencv=opencv.ms.get(s.name, math.nan),
    )
    if found_tf is not None:
        rejected = trifuse.rejected.get(name, {})
        row.missed = {
            v: f"{rejected.get(v, '?')}; OpenCV's variant: {variant or 'ChArUco'}"
            for v, variant in found_cv.items()
            if v not in found_tf
        }
        row.extra = [v for v in found_tf if v not in found_cv]
    if ref is not None:
        row.rms_alone_opencv, row.fx_opencv = ref.rms_px, ref.fx
    result = trifuse.result
    if trifuse.failure:
        row.outcome = trifuse.failure
    elif name in result.sensors or name in result.intrinsics_only:
        sr = result.sensors.get(name) or result.intrinsics_only[name]
        row.outcome = "result" if sr.pose_unknown is None else f"intrinsics only: {sr.pose_unknown}"
        row.rms_trifuse, row.fx_trifuse = sr.rms_px, sr.intrinsics.fx
        row.rms_alone_trifuse = sr.zhang_rms_px if sr.zhang_rms_px is not None else math.nan
    else:
        row.outcome = f"refused: {result.excluded_sensors.get(name, 'not in the result')}"
    return row


def run_set(rs: RealSet, root: Path | None = None, quick: bool = False) -> SetRun:
    """Both pipelines on one set (``root``: where its files are, default tests/data)."""
    if quick:
        rs = replace(rs, view_step=quick_step(rs, root))
    board = rs.board.describe() if isinstance(rs.board, Checkerboard) else str(rs.board)
    out = SetRun(rs.name, rs.name in REAL_SETS, board, rs.view_step)
    load_start = os.getloadavg()[0]
    names = {s.name: trifuse_name(s) for s in rs.sensors}
    with tempfile.TemporaryDirectory(prefix=f"real-calib-{rs.name}-") as tmp:
        trifuse = TrifuseRun()
        try:
            out.notes += write_capture(rs, root, Path(tmp))
        except ValueError as exc:
            trifuse.failure = f"not supported yet: {exc}"
        if not trifuse.failure:
            trifuse = run_trifuse(Path(tmp), list(names.values()))
    out.seconds_trifuse = trifuse.seconds
    opencv = run_opencv(rs, root)
    out.seconds_opencv, out.opencv_error = opencv.seconds, opencv.error
    for s in rs.sensors:
        views = len(view_ids(rs, s, root))
        out.sensors.append(_sensor_row(s, names[s.name], trifuse, opencv, views))
    opencv_pairs = {(p.a, p.b): p for p in opencv.measurement.pairs} if opencv.measurement else {}
    result = trifuse.result
    for a, b in rs.pairs:
        pair = PairRow(a, b)
        if (p := opencv_pairs.get((a, b))) is not None:
            pair.views_opencv = p.views
            pair.baseline_mm_opencv, pair.rotation_deg_opencv = p.baseline_m * 1000, p.rotation_deg
        if result is not None and names[a] in result.sensors and names[b] in result.sensors:
            pair.baseline_mm_trifuse, pair.rotation_deg_trifuse = _relative(
                result.sensors[names[a]].T_rig_sensor, result.sensors[names[b]].T_rig_sensor
            )
        out.pairs.append(pair)
    out.load_1min = (load_start, os.getloadavg()[0])
    return out


# -- which sets, and the report --------------------------------------------------------------


def available_sets(
    roots: dict[str, Path] | None = None, scratch: Path = SCRATCH_DIR
) -> list[tuple[RealSet, Path | None]]:
    """Every committed set (from tests/data, or from ``roots``) and every unlicensed set whose
    copy is given in ``roots`` or exists under ``scratch``."""
    roots = roots or {}
    out: list[tuple[RealSet, Path | None]] = [(rs, roots.get(n)) for n, rs in REAL_SETS.items()]
    for n, rs in UNCOMMITTED_SETS.items():
        root = roots.get(n) or scratch / SCRATCH_ROOTS[n]
        if root.is_dir():
            out.append((rs, root))
    return out


def _f(value: float | int | None, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _pair(a: float | int | None, b: float | int | None, digits: int = 3) -> str:
    return f"{_f(a, digits)} / {_f(b, digits)}"


def _ok(value: bool | None) -> str:
    return {True: "yes", False: "**NO**", None: "—"}[value]


def format_set(run: SetRun) -> str:
    """One set's Markdown: a heading, the sensor table, the pair table, the failed targets."""
    where = "tests/data" if run.committed else "measured from /work/scratch, not committed"
    step = f", 1 view in {run.step}" if run.step > 1 else ""
    lines = [
        f"#### {run.name} ({where}{step})",
        "",
        f"{run.board}. Whole run: trifuse {_f(run.seconds_trifuse, 1)} s, OpenCV "
        f"{_f(run.seconds_opencv, 1)} s (load average {run.load_1min[0]:.1f} -> "
        f"{run.load_1min[1]:.1f} on {os.cpu_count()} cores).",
        "",
        "| sensor | boards found trifuse / OpenCV (of) | RMS px trifuse alone / OpenCV "
        "| RMS px trifuse joint | fx trifuse / OpenCV | ms per image trifuse / OpenCV "
        "| trifuse | found ≥ | result | thermal RMS ≤ +5 % |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for s in run.sensors:
        t = s.targets()
        outcome = s.outcome if len(s.outcome) < 160 else s.outcome[:157] + "..."
        lines.append(
            f"| {s.sensor} ({s.modality}) | {_pair(s.found_trifuse, s.found_opencv)} ({s.views}) "
            f"| {_pair(s.rms_alone_trifuse, s.rms_alone_opencv)} | {_f(s.rms_trifuse)} "
            f"| {_pair(s.fx_trifuse, s.fx_opencv, 1)} | {_pair(s.ms_trifuse, s.ms_opencv, 0)} "
            f"| {outcome.replace('|', '/')} | {_ok(t['found'])} | {_ok(t['result'])} "
            f"| {_ok(t['rms'])} |"
        )
    if run.pairs:
        lines += [
            "",
            "| pair | views (OpenCV) | baseline mm trifuse / OpenCV "
            "| rotation deg trifuse / OpenCV |",
            "| --- | --- | --- | --- |",
        ]
        for p in run.pairs:
            lines.append(
                f"| {p.a} -> {p.b} | {_f(p.views_opencv)} "
                f"| {_pair(p.baseline_mm_trifuse, p.baseline_mm_opencv, 1)} "
                f"| {_pair(p.rotation_deg_trifuse, p.rotation_deg_opencv, 2)} |"
            )
    if run.opencv_error:
        lines += ["", f"OpenCV's pipeline failed: {run.opencv_error}"]
    lines += ["", *(f"note: {n}" for n in run.notes)]
    for s in run.sensors:
        if s.extra:
            lines.append(
                f"{s.sensor}: only trifuse found the board in view(s) {', '.join(s.extra)}"
            )
        for v, why in s.missed.items():
            lines.append(f"{s.sensor}: only OpenCV found the board in view {v} (trifuse: {why})")
    failed = run.failed_targets()
    lines += [f"target failed: {f}" for f in failed] or ["targets: all that apply hold"]
    return "\n".join(lines)


def figures(runs: list[SetRun]) -> dict[str, float]:
    """Flat figures ``<set>.<sensor>.<what>_<trifuse|opencv>`` (and pairs
    ``<set>.<a>-<b>.…``), plus ``targets_failed`` and ``sets_not_supported``."""
    out: dict[str, float] = {}
    for run in runs:
        for s in run.sensors:
            k = f"{run.name}.{s.sensor}"
            for what in ("found", "rms_alone", "fx", "ms"):
                for who in ("trifuse", "opencv"):
                    v = getattr(s, f"{what}_{who}", None)
                    out[f"{k}.{what}_{who}"] = math.nan if v is None else float(v)
            out[f"{k}.rms_joint_trifuse"] = s.rms_trifuse
        for p in run.pairs:
            k = f"{run.name}.{p.a}-{p.b}"
            for what in ("baseline_mm", "rotation_deg"):
                for who in ("trifuse", "opencv"):
                    out[f"{k}.{what}_{who}"] = getattr(p, f"{what}_{who}")
    out["targets_failed"] = sum(len(r.failed_targets()) for r in runs)
    out["sets_not_supported"] = sum(any(not s.supported for s in r.sensors) for r in runs)
    return out


def baseline_pairs() -> tuple[tuple[str, str], ...]:
    """(trifuse figure, OpenCV figure) for every sensor and pair of every registered set."""
    pairs = []
    for rs in (*REAL_SETS.values(), *UNCOMMITTED_SETS.values()):
        keys = [f"{rs.name}.{s.name}" for s in rs.sensors]
        for k in keys:
            pairs += [
                (f"{k}.{w}_trifuse", f"{k}.{w}_opencv") for w in ("found", "rms_alone", "fx", "ms")
            ]
        for a, b in rs.pairs:
            k = f"{rs.name}.{a}-{b}"
            pairs += [
                (f"{k}.{w}_trifuse", f"{k}.{w}_opencv") for w in ("baseline_mm", "rotation_deg")
            ]
    return tuple(pairs)


def run_all(
    sets: list[tuple[RealSet, Path | None]],
    quick: bool = False,
    emit: Callable[[str], None] = print,
) -> list[SetRun]:
    """Both pipelines on every set in turn, each set's tables emitted as it is done."""
    runs = []
    for rs, root in sets:
        run = run_set(rs, root, quick)
        emit(format_set(run) + "\n")
        runs.append(run)
    return runs


@benchmark(
    "real-calib",
    "issue 30's targets on every real set (tests/data, and the unlicensed ones found under "
    "/work/scratch): trifuse calibrate's pipeline vs OpenCV's plain one, per sensor boards "
    "found, RMS, fx, ms per image, result or refusal; per pair baseline and rotation",
    baselines=baseline_pairs(),
    default_repeat=1,
)
def real_calib(repeat: int) -> dict[str, float]:
    """Every available set once (``repeat`` is not used: each run takes minutes; times are
    medians over the images of a sensor)."""
    return figures(run_all(available_sets()))


def _root_arg(text: str) -> tuple[str, Path]:
    name, sep, path = text.partition("=")
    if not sep or name not in REAL_SETS | UNCOMMITTED_SETS:
        raise argparse.ArgumentTypeError(
            f"expected NAME=DIR with NAME among {list(REAL_SETS | UNCOMMITTED_SETS)}, got {text!r}"
        )
    return name, Path(path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="sets to run (default: every available one)")
    parser.add_argument("--quick", action="store_true", help=f"about {QUICK_VIEWS} views a set")
    parser.add_argument(
        "--root",
        type=_root_arg,
        action="append",
        default=[],
        metavar="NAME=DIR",
        help="where a set's files are (an unlicensed set kept outside the checkout)",
    )
    args = parser.parse_args(argv)
    sets = available_sets(dict(args.root))
    if args.names:
        known = {rs.name for rs, _ in sets}
        missing = [n for n in args.names if n not in known]
        if missing:
            print(f"expected set names from {sorted(known)}, got {missing}", file=sys.stderr)
            return 2
        sets = [(rs, root) for rs, root in sets if rs.name in args.names]
    runs = run_all(sets, args.quick)
    failed = sum(len(r.failed_targets()) for r in runs)
    print(f"{len(runs)} set(s); targets failed: {failed}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
