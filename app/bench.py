"""Benchmarks: a tiny registry that ``trifuse bench`` runs.

A benchmark is a function ``run(repeat) -> {figure name: value}``; it times what it measures
``repeat`` times (after its own warm-up) and returns medians. Figure names carry their unit
(``render_ms``). A benchmark may name baselines, pairs ``(figure, baseline figure)`` measured
in the same run, and the CLI prints their ratio ``figure / baseline``: e.g. a fusion mode
against OpenCV's ``remap``, or our calibration against ``cv2.calibrateCamera``.

Add one with the decorator; the CLI lists and runs whatever is registered::

    @register("fuse-remap", "median time of one fused eye vs cv2.remap",
              baselines=(("fuse_ms", "remap_ms"),))
    def _fuse(repeat: int) -> dict[str, float]: ...
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

BenchFn = Callable[[int], dict[str, float]]


@dataclass(frozen=True)
class Benchmark:
    """A registered benchmark.

    Attributes:
        name: what ``--only`` selects.
        description: one line for ``trifuse bench --help`` and the report.
        run: ``run(repeat)`` -> figures (name with unit suffix -> median value).
        baselines: pairs (figure, baseline figure) whose ratio is reported.
        default_repeat: repeats when the user gives none.
    """

    name: str
    description: str
    run: BenchFn
    baselines: tuple[tuple[str, str], ...] = ()
    default_repeat: int = 10


@dataclass(frozen=True)
class BenchResult:
    """Figures of one benchmark run and the ratios against its baselines."""

    name: str
    repeat: int
    figures: dict[str, float]
    ratios: dict[str, float]

    def format(self) -> str:
        """Lines for people: ``name: figure = value`` and ``figure / baseline = ratio``."""
        lines = [f"{self.name} (median of {self.repeat}):"]
        lines += [f"  {k} = {v:.3f}" for k, v in self.figures.items()]
        lines += [f"  {k} = {v:.3f}" for k, v in self.ratios.items()]
        return "\n".join(lines)


REGISTRY: dict[str, Benchmark] = {}


def register(
    name: str,
    description: str,
    *,
    baselines: tuple[tuple[str, str], ...] = (),
    default_repeat: int = 10,
) -> Callable[[BenchFn], BenchFn]:
    """Decorator: add ``fn`` to :data:`REGISTRY` under ``name``; names are unique."""

    def deco(fn: BenchFn) -> BenchFn:
        if name in REGISTRY:
            raise ValueError(f"benchmark {name!r}: registered twice")
        REGISTRY[name] = Benchmark(name, description, fn, baselines, default_repeat)
        return fn

    return deco


def median_ms(fn: Callable[[int], object], repeat: int, warmup: int = 1) -> float:
    """Median wall time in milliseconds of ``fn(i)`` for i in 0..repeat-1.

    ``warmup`` calls (with i = -1, -2 ...) run first and are not counted.
    """
    if repeat < 1:
        raise ValueError(f"repeat: expected a positive integer, got {repeat}")
    for w in range(warmup):
        fn(-1 - w)
    times = []
    for i in range(repeat):
        t0 = time.perf_counter()
        fn(i)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def run_benchmark(name: str, repeat: int | None = None) -> BenchResult:
    """Run one registered benchmark; ValueError for an unknown name or a bad ``repeat``."""
    if name not in REGISTRY:
        raise ValueError(f"unknown benchmark {name!r} (known: {', '.join(sorted(REGISTRY))})")
    bench = REGISTRY[name]
    n = bench.default_repeat if repeat is None else repeat
    if n < 1:
        raise ValueError(f"repeat: expected a positive integer, got {n}")
    figures = bench.run(n)
    ratios: dict[str, float] = {}
    for fig, base in bench.baselines:
        if fig in figures and base in figures and figures[base] != 0:
            ratios[f"{fig} / {base}"] = figures[fig] / figures[base]
    return BenchResult(name, n, figures, ratios)


# -- the benchmarks -------------------------------------------------------------------------


@register(
    "render",
    "simulator: five-sensor frame sets (calibration view, inspection frame, per sensor) (ms)",
    default_repeat=5,
)
def _render(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` renders of the simulated head.

    ``calibration_view_ms``: one view in a stream of ``calibration_views`` (what
    ``trifuse simulate calibration`` pays per view, without writing the PNGs);
    ``inspection_frame_ms``: one five-sensor frame set of the inspection room;
    ``<sensor>_ms``: one sensor of that room alone; ``setup_ms``: a new renderer's first
    frame set (ray grids of all sensors, with undistortion, are built then).
    """
    from app.sources.sim.scenarios import InspectionScenario, calibration_views

    stream = calibration_views(repeat + 1, seed=1000)
    figures = {"calibration_view_ms": median_ms(lambda _i: next(stream), repeat)}
    scenario = InspectionScenario(seed=0)
    figures["inspection_frame_ms"] = median_ms(lambda i: scenario.render(0.1 * i), repeat)
    for name in scenario.rig.names:
        figures[f"{name}_ms"] = median_ms(lambda i, n=name: scenario.render(0.1 * i, [n]), repeat)
    figures["setup_ms"] = median_ms(lambda i: InspectionScenario(seed=0).render(0.0), repeat)
    return figures


@register(
    "calibrate",
    "rig calibration of 30 simulated views: this engine vs OpenCV calibrateMultiview "
    "(pose errors against ground truth, run times)",
    default_repeat=1,
)
def _calibrate(repeat: int) -> dict[str, float]:
    """Calibrate the same simulated captures with both engines and compare to the truth.

    Renders ``trifuse simulate calibration --views 30 --seed 1`` into a temporary capture
    directory (not timed), detects the board once, then times ``calib.rig_calibration``
    (``ours_s``, calibration only; ``detect_s`` for the detection of all 150 images) and
    ``calib.opencv_baseline`` (``opencv_s``) on the same detections, ``repeat`` times each.
    Errors are the worst over the non-reference sensors: rotation (deg), translation (mm),
    focal length (%), and the ratio ours / OpenCV of each.
    """
    import tempfile
    import time
    from pathlib import Path

    import numpy as np

    from app.calibration_run import detect_capture, sensor_specs
    from app.capture import load_capture, write_board, write_view
    from app.sources.sim.head import default_rig
    from app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_views
    from calib.opencv_baseline import calibrate_multiview_opencv
    from calib.rig_calibration import calibrate_rig
    from calib.transforms import pose_error

    truth = default_rig()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        write_board(out, CALIBRATION_BOARD)
        for view in calibration_views(30, seed=1, rig=truth):
            write_view(out, view.name, view.frames, truth)
        capture = load_capture(out)
        specs = sensor_specs(capture)
        t = time.perf_counter()
        detections = detect_capture(capture)
        detect_s = time.perf_counter() - t

    obs = detections.observations
    ours_times, cv_times = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        ours = calibrate_rig(obs, CALIBRATION_BOARD, specs)
        ours_times.append(time.perf_counter() - t)
        t = time.perf_counter()
        cv = calibrate_multiview_opencv(
            obs, CALIBRATION_BOARD, {s: specs[s].image_size for s in specs}, "tof"
        )
        cv_times.append(time.perf_counter() - t)

    def errors(T: dict[str, np.ndarray], intr: dict) -> tuple[float, float, float]:
        rot, trans, focal = [], [], []
        for name in truth.names:
            if name == "tof":
                continue
            r, tr = pose_error(T[name], truth[name].T_rig_sensor)
            rot.append(r)
            trans.append(tr * 1000)
        for name in truth.names:
            f_true = truth[name].intrinsics
            focal.append(100 * abs(intr[name].fx / f_true.fx - 1))
        return max(rot), max(trans), max(focal)

    o = errors(
        {n: s.T_rig_sensor for n, s in ours.sensors.items()},
        {n: s.intrinsics for n, s in ours.sensors.items()},
    )
    c = errors(cv.T_rig_sensor, cv.intrinsics)
    return {
        "detect_s": detect_s,
        "ours_s": float(np.median(ours_times)),
        "opencv_s": float(np.median(cv_times)),
        "ours_rot_deg": o[0],
        "opencv_rot_deg": c[0],
        "rot_ratio": o[0] / c[0],
        "ours_trans_mm": o[1],
        "opencv_trans_mm": c[1],
        "trans_ratio": o[1] / c[1],
        "ours_focal_pct": o[2],
        "opencv_focal_pct": c[2],
        "focal_ratio": o[2] / c[2],
    }
