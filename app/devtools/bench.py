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

import itertools
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.devtools.processes import stop_process

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

    from app.sources.sim.head import default_rig
    from app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_views
    from app.storage.capture import load_capture, write_board, write_view
    from app.workflows.calibration_run import detect_capture, sensor_specs
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


# Per-axis corner noise (px) of the projected detections of ``calib-scale``: about what the
# detectors achieve on the simulated head (tests/test_rig_calibration.py uses the same).
_SCALE_NOISE_PX = {"color": 0.08, "thermal": 0.06, "tof": 0.05}
# Two CPU-bound neighbours for ``calib-scale``'s busy figure: a numpy matrix product with
# OpenBLAS's default threads (one per core) and a pure-Python loop.
_BUSY_CODE = (
    "import numpy as np\na = np.random.default_rng(0).random((1000, 1000))\n"
    "while True:\n    a @ a\n",
    "x = 0\nwhile True:\n    x = (x * 31 + 7) % 1000003\n",
)


def projected_detections(views: int, seed: int) -> dict[str, dict[str, Any]]:
    """Corners of the simulated head's calibration views, projected from the ground truth.

    The board poses of ``trifuse simulate calibration --views N --seed 1`` (so view i is
    the same pose as there), every corner projected with the true rig and intrinsics, plus
    seeded Gaussian noise of the detectors' level (:data:`_SCALE_NOISE_PX`, per axis); a
    sensor sees the board in a view when all its corners fall inside the image (3 px
    margin). Returns view -> sensor -> (54, 2) float64 pixels, canonical corner order.
    """
    import numpy as np

    from app.sources.sim.head import default_rig
    from app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
    from calib.transforms import transform_points

    rig = default_rig()
    rng = np.random.default_rng(seed)
    obj = CALIBRATION_BOARD.object_points()
    obs: dict[str, dict[str, Any]] = {}
    for i, T_rig_board in enumerate(calibration_poses(views, seed=1, rig=rig)):
        for s in rig.names:
            uv = rig[s].intrinsics.project(
                transform_points(rig.T(s, rig.reference) @ T_rig_board, obj)
            )
            w, h = rig[s].image_size
            if np.isfinite(uv).all() and (uv > 3).all() and (uv < (w - 4, h - 4)).all():
                noise = _SCALE_NOISE_PX[rig[s].modality]
                obs.setdefault(f"{i + 1:04d}", {})[s] = uv + rng.normal(0, noise, uv.shape)
    return obs


@register(
    "calib-scale",
    "joint rig calibration of 40 and 150 five-sensor views (projected ground truth + noise): "
    "time per view, ratio to OpenCV calibrateMultiview, 40 views beside two busy processes",
    baselines=(
        ("ours_40_s", "opencv_40_s"),
        ("ours_150_s", "opencv_150_s"),
        ("per_view_150_ms", "per_view_40_ms"),
        ("joint_per_view_150_ms", "joint_per_view_40_ms"),
        ("busy_ours_40_s", "ours_40_s"),
    ),
    default_repeat=3,
)
def _calib_scale(repeat: int) -> dict[str, float]:
    """How the rig calibration scales with views, against OpenCV, on a loaded machine.

    Detections: :func:`projected_detections` of 40 and 150 views (seed 1), not rendered
    and detected: a 150-view render takes minutes and its detections would change with
    the detector, while the calibration's cost depends only on how many corners and views
    it solves for. Each repeat runs ``calib.rig_calibration.calibrate_rig`` (``ours_N_s``:
    Zhang per sensor, the pre-stage, the joint refinement and its covariance;
    ``joint_N_s``: from the joint refinement's start to the end, timed with the progress
    callback) and ``calib.opencv_baseline`` (``opencv_N_s``) on the same detections, after
    one warm-up of each on 40 views. ``per_view_N_ms`` and ``joint_per_view_N_ms``: those
    times divided by the views. Then two CPU-bound processes start (a numpy matrix product
    with default BLAS threads, a pure-Python loop; :data:`_BUSY_CODE`) and the 40-view
    calibration is timed ``repeat`` times beside them (``busy_ours_40_s``,
    ``busy_joint_40_s``; ``busy_opencv_40_s`` for OpenCV). ``load_1min``: the machine's
    load average before the first timing (2 cores; other users' work shows there).
    Medians of ``repeat``; worst errors against the truth (``ours_N_rot_deg``,
    ``ours_N_trans_mm``, ``ours_N_focal_pct``) show the solutions are the calibrations'.
    """
    import os
    import statistics
    import subprocess
    import sys

    from app.sources.sim.head import default_rig
    from app.sources.sim.scenarios import CALIBRATION_BOARD
    from calib.opencv_baseline import calibrate_multiview_opencv
    from calib.rig_calibration import SensorSpec, calibrate_rig
    from calib.transforms import pose_error

    truth = default_rig()
    specs = {n: SensorSpec(n, truth[n].modality, truth[n].image_size) for n in truth.names}
    sizes = {n: truth[n].image_size for n in truth.names}
    detections = {n: projected_detections(n, seed=1) for n in (40, 150)}

    def ours(obs: dict) -> tuple[float, float, Any]:
        marks: dict[str, float] = {}
        t0 = time.perf_counter()
        result = calibrate_rig(
            obs,
            CALIBRATION_BOARD,
            specs,
            progress=lambda stage, _f: marks.setdefault(stage, time.perf_counter()),
        )
        t1 = time.perf_counter()
        return t1 - t0, t1 - marks.get("joint refinement (robust)", t0), result

    def opencv(obs: dict) -> float:
        t0 = time.perf_counter()
        calibrate_multiview_opencv(obs, CALIBRATION_BOARD, sizes, truth.reference)
        return time.perf_counter() - t0

    ours(detections[40])  # warm-up: imports, first allocations
    opencv(detections[40])
    figures: dict[str, float] = {"load_1min": os.getloadavg()[0]}
    for n, obs in detections.items():
        runs, cv_runs = [], []
        for _ in range(repeat):
            runs.append(ours(obs))
            cv_runs.append(opencv(obs))
        total = statistics.median(r[0] for r in runs)
        joint = statistics.median(r[1] for r in runs)
        figures |= {
            f"ours_{n}_s": total,
            f"joint_{n}_s": joint,
            f"opencv_{n}_s": statistics.median(cv_runs),
            f"per_view_{n}_ms": 1e3 * total / n,
            f"joint_per_view_{n}_ms": 1e3 * joint / n,
        }
        result = runs[-1][2]
        rot, trans, focal = [], [], []
        for name, s in result.sensors.items():
            r, t = pose_error(s.T_rig_sensor, truth.T(truth.reference, name))
            rot.append(r)
            trans.append(1e3 * t)
            focal.append(100 * abs(s.intrinsics.fx / truth[name].intrinsics.fx - 1))
        figures |= {
            f"ours_{n}_rot_deg": max(rot),
            f"ours_{n}_trans_mm": max(trans),
            f"ours_{n}_focal_pct": max(focal),
        }

    busy = [
        subprocess.Popen(
            [sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        for code in _BUSY_CODE
    ]
    try:
        time.sleep(2.0)  # both running at full speed
        runs, cv_runs = [], []
        for _ in range(repeat):
            runs.append(ours(detections[40]))
            cv_runs.append(opencv(detections[40]))
    finally:
        for proc in busy:
            proc.kill()
            proc.wait(10)
    figures |= {
        "busy_ours_40_s": statistics.median(r[0] for r in runs),
        "busy_joint_40_s": statistics.median(r[1] for r in runs),
        "busy_opencv_40_s": statistics.median(cv_runs),
    }
    return figures


_COMPOSE_MODES = ("color", "blend", "edges", "thermal", "threshold", "isotherm", "pip")


@register(
    "compose",
    "display composition of one 1280x960 eye per mode vs one cv2.addWeighted (ms per eye)",
    baselines=tuple((f"{m}_ms", "addweighted_ms") for m in _COMPOSE_MODES),
    default_repeat=30,
)
def _compose(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` calls of ``fusion.compose.Composer.compose`` per mode.

    Synthetic eye (seeded): a colour image with gradients and noise; a thermal image of
    290-310 K with a hot blob, NaN on the left 10 % and top 5 % (outside the thermal
    field of view) and a fallback block of 20 % of the pixels, ``mark_fallback`` on;
    span from ``auto_span`` of both eyes. ``<mode>_ms``: one eye in that mode (``blend``
    at opacity 0.6, ``edges`` at strength 1, ``threshold`` above, ``isotherm`` on grey
    with palette colours, ``pip`` half-size centred); ``addweighted_ms``: the baseline, a
    plain ``cv2.addWeighted`` of two prepared 1280x960x3 images into a preallocated
    buffer; ``palette_ms``: ``apply_palette`` alone; ``auto_span_ms``: the shared span
    of two eyes; ``stereo_blend_ms``: a whole stereo frame in blend mode (shared span,
    both eyes composed into the halves of one side-by-side buffer); ``anaglyph_ms``.
    """
    import cv2
    import numpy as np

    from fusion.compose import (
        Composer,
        DisplaySettings,
        anaglyph,
        auto_span,
        resolve_span,
        stereo_halves,
    )
    from fusion.palettes import apply_palette

    w, h = 1280, 960
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    color = np.empty((h, w, 3), np.uint8)
    for k in range(3):
        ramp = 60 + 120 * ((xx * (k + 1) / w + yy / h) % 1.0)
        color[..., k] = np.clip(ramp + rng.normal(0, 8, (h, w)), 0, 255)
    blob = 15 * np.exp(-((xx - 800) ** 2 + (yy - 400) ** 2) / (2 * 150**2))
    thermal = (290 + 10 * xx / w + blob + rng.normal(0, 0.1, (h, w))).astype(np.float32)
    thermal[:, : w // 10] = np.nan
    thermal[: h // 20] = np.nan
    thermal_r = thermal + np.float32(1.5)
    fallback = np.zeros((h, w), bool)
    fallback[600:900, 200:800] = True
    span = auto_span([thermal, thermal_r])

    out = np.empty((h, w, 3), np.uint8)
    pal = np.empty((h, w, 3), np.uint8)
    index = np.empty((h, w), np.uint8)
    apply_palette(thermal, span, "iron", out=pal, index_out=index)
    figures = {
        "addweighted_ms": median_ms(
            lambda _i: cv2.addWeighted(pal, 0.6, color, 0.4, 0.0, dst=out), repeat
        ),
        "palette_ms": median_ms(
            lambda _i: apply_palette(thermal, span, "iron", out=pal, index_out=index), repeat
        ),
    }
    composer = Composer(w, h)
    for mode in _COMPOSE_MODES:
        settings = DisplaySettings(
            mode=mode, threshold_k=300.0, isotherm_k=(298.0, 302.0), mark_fallback=True
        )
        figures[f"{mode}_ms"] = median_ms(
            lambda _i, s=settings: composer.compose(color, thermal, fallback, s, span, out=out),
            repeat,
        )
    figures["auto_span_ms"] = median_ms(lambda _i: auto_span([thermal, thermal_r]), repeat)

    blend = DisplaySettings(mode="blend")
    right = Composer(w, h)
    sbs = np.empty((h, 2 * w, 3), np.uint8)
    left_half, right_half = stereo_halves(sbs)

    def stereo(_i: int) -> None:
        s = resolve_span(blend, [thermal, thermal_r])
        composer.compose(color, thermal, fallback, blend, s, out=left_half)
        right.compose(color, thermal_r, fallback, blend, s, out=right_half)

    figures["stereo_blend_ms"] = median_ms(stereo, repeat)
    ana = np.empty((h, w, 3), np.uint8)
    figures["anaglyph_ms"] = median_ms(lambda _i: anaglyph(left_half, right_half, ana), repeat)
    return figures


@register(
    "fuse",
    "full-resolution stereo fusion per frame, per display mode, against a fixed-homography "
    "fusion (ms)",
    default_repeat=30,
)
def _fuse(repeat: int) -> dict[str, float]:
    """Median time of one fused stereo frame (two 1280 x 960 eyes) of the inspection scene.

    ``<mode>_ms``: warp both thermal images into their colour cameras, one shared span,
    compose both eyes into the side-by-side buffer, with the depth mapping as it is (a TOF
    frame arrives less often than a colour frame). ``tof_update_ms``: recomputing both eyes'
    mappings from a new TOF frame. ``blend_tof_every_frame_ms``: blend with a new TOF frame
    for every stereo frame (the worst case). ``range_correction_ms``: the TOF range
    correction of one TOF frame (before its mapping update). ``homography_ms``: the naive
    fusion, one fixed homography per eye (3 m) through the same warp and blend: the
    baseline, and
    ``blend_ratio`` / ``blend_tof_every_frame_ratio`` against it.
    """
    import cv2
    import numpy as np

    from app.sources.sim.scenarios import InspectionScenario
    from fusion.accuracy import fixed_depth_mapping
    from fusion.compose import Composer, DisplaySettings, resolve_span, stereo_halves
    from fusion.stereo import StereoFusion

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    eyes = ("left", "right")
    colors = {e: frames[rig.eyes[e].color].image for e in eyes}
    thermals = {e: frames[rig.eyes[e].thermal].image for e in eyes}
    distance = frames["tof"].distance_m
    fusion = StereoFusion(rig)
    fusion.update_depth(distance)

    settings = {
        "blend": DisplaySettings(mode="blend"),
        "edges": DisplaySettings(mode="edges"),
        "thermal": DisplaySettings(mode="thermal"),
        "threshold": DisplaySettings(mode="threshold", threshold_k=(300.0, 400.0)),
        "isotherm": DisplaySettings(mode="isotherm", isotherm_k=(305.0, 312.0)),
        "pip": DisplaySettings(mode="pip"),
        "color": DisplaySettings(mode="color"),
    }
    figures = {}
    for mode, s in settings.items():
        figures[f"{mode}_ms"] = median_ms(
            lambda _i, s=s: fusion.compose(colors, thermals, s), repeat
        )
    figures["tof_update_ms"] = median_ms(lambda _i: fusion.update_depth(distance), repeat)

    def every_frame(_i: int) -> None:
        fusion.update_depth(distance)
        fusion.compose(colors, thermals, settings["blend"])

    figures["blend_tof_every_frame_ms"] = median_ms(every_frame, repeat)

    # The TOF range correction (rig file ``range_correction``) on each TOF frame.
    from calib.range_correction import RangeCorrection, offset_grid_shape

    w_t, h_t = rig["tof"].image_size
    correction = RangeCorrection(
        image_size=(w_t, h_t),
        distance_start_m=0.5,
        distance_step_m=0.15,
        distance_coeffs_m=np.linspace(0.03, -0.01, 40),
        offset_step_px=8,
        offset_nodes_m=np.full(offset_grid_shape(w_t, h_t, 8), 0.002),
        amplitude_ref=1500.0,
        amplitude_log_range=(-1.5, 1.5),
        amplitude_coeffs_m=(0.004, -0.001),
    )
    amplitude = frames["tof"].image
    out = np.empty_like(distance)
    figures["range_correction_ms"] = median_ms(
        lambda _i: correction.apply(distance, amplitude, out=out), repeat
    )

    # Baseline: a fixed homography per eye, warped and blended the same way.
    w, h = fusion.size
    maps = {}
    for e in eyes:
        m = fixed_depth_mapping(rig, rig.eyes[e].color, rig.eyes[e].thermal, 3.0)
        maps[e] = cv2.convertMaps(
            m[..., 0].astype(np.float32), m[..., 1].astype(np.float32), cv2.CV_32FC1
        )
    composers = {e: Composer(w, h) for e in eyes}
    warped = {e: np.empty((h, w), np.float32) for e in eyes}
    frame = np.zeros((h, 2 * w, 3), np.uint8)
    no_fallback = np.zeros((h, w), bool)

    def homography(_i: int) -> None:
        for e in eyes:
            cv2.remap(
                thermals[e],
                maps[e][0],
                maps[e][1],
                cv2.INTER_LINEAR,
                dst=warped[e],
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=np.nan,
            )
        span = resolve_span(settings["blend"], list(warped.values()))
        for e, half in zip(eyes, stereo_halves(frame), strict=True):
            composers[e].compose(
                colors[e], warped[e], no_fallback, settings["blend"], span, out=half
            )

    figures["homography_ms"] = median_ms(homography, repeat)
    figures["blend_ratio"] = figures["blend_ms"] / figures["homography_ms"]
    figures["blend_tof_every_frame_ratio"] = (
        figures["blend_tof_every_frame_ms"] / figures["homography_ms"]
    )
    return figures


@register(
    "fuse-accuracy",
    "fused mapping against the simulator's exact mapping per distance band, TOF as "
    "simulated and range-corrected, against one fixed homography (thermal px)",
    default_repeat=1,
)
def _fuse_accuracy(repeat: int) -> dict[str, float]:
    """Median and 95th percentile of |mapped - exact| in thermal pixels per distance band,
    both eyes of the inspection scene at t = 0, 5, 10, 20 s, more than 16 colour pixels
    (two TOF pixels) from depth edges, where the exact point is visible to the thermal
    imager and inside the TOF's view, and the TOF gave depth (no fallback).

    ``raw_*``: the TOF with its simulated systematic range error (about 40 mm RMS);
    ``corrected_*``: that error removed, as a range calibration would (noise stays);
    ``homography_*``: one fixed homography per eye for an assumed 3 m.
    """
    import numpy as np

    from app.sources.sim.render import HeadModel
    from app.sources.sim.scenarios import InspectionScenario
    from app.sources.sim.tof_error import RangeErrorModel
    from fusion.accuracy import (
        BANDS_M,
        band_errors,
        depth_edges,
        exact_mapping,
        fixed_depth_mapping,
    )
    from fusion.mapping import ViewMapping

    no_error = RangeErrorModel(
        bias_m=0.0, wiggle=(), radial_m=0.0, border_m=0.0, pixel_sigma_m=0.0, amplitude_m=0.0
    )
    figures: dict[str, float] = {}
    for label, model in (("raw", None), ("corrected", HeadModel(range_error=no_error))):
        scenario = InspectionScenario(model=model, seed=0)
        rig = scenario.rig
        ours, naive = [], []
        for t_s in (0.0, 5.0, 10.0, 20.0):
            for eye in ("left", "right"):
                tgt, src = rig.eyes[eye].color, rig.eyes[eye].thermal
                frames, truth = scenario.render(t_s, [tgt, src, "tof"])
                m = ViewMapping(rig, tgt, src)
                m.update(frames["tof"].distance_m)
                exact = exact_mapping(rig, tgt, src, truth[tgt].range_m, truth[src].range_m)
                mask = ~depth_edges(exact.depth_m, 16) & m.visible & ~m.fallback
                ours.append(band_errors(np.stack([m.map_x, m.map_y], -1), exact, mask))
                if label == "raw":
                    naive.append(band_errors(fixed_depth_mapping(rig, tgt, src, 3.0), exact, mask))
        sets = [(label, ours)] + ([("homography", naive)] if naive else [])
        for name, results in sets:
            for k, (lo, hi) in enumerate(BANDS_M):
                rows = [r[k] for r in results if r[k].pixels]
                weights = [r.pixels for r in rows]
                key = f"{name}_{lo:g}-{hi:g}m"
                figures[f"{key}_median_px"] = float(
                    np.average([r.median_px for r in rows], weights=weights)
                )
                figures[f"{key}_p95_px"] = float(
                    np.average([r.p95_px for r in rows], weights=weights)
                )
                figures[f"{key}_pixels"] = float(sum(weights))
    return figures


@register(
    "recording",
    "MCAP recording of full-resolution five-sensor frame sets: write and replay throughput "
    "(sets/s; 30 needed for real time)",
    baselines=(("write_ms_per_set", "jpeg_encode_ms"), ("read_ms_per_set", "jpeg_decode_ms")),
    default_repeat=5,
)
def _recording(repeat: int) -> dict[str, float]:
    """Write and replay 30 frame sets of the inspection scene (two 1280 x 960 colour, two
    382 x 288 thermal, one 176 x 144 TOF frame with distance and amplitude; rendered once
    at t = 3 s, not timed) per repeat.

    ``write_sets_per_s`` / ``write_ms_per_set``: :class:`app.recording.RecordingWriter`
    (JPEG q90, 16-bit thermal and TOF, zstd chunks) including opening and closing the file;
    ``read_sets_per_s`` / ``read_ms_per_set``: :class:`app.recording.ReplaySource` as fast
    as possible (``realtime=False``), decoding every frame back to the program's arrays;
    ``mb_per_set``: file size per set; baselines: one colour frame's ``cv2.imencode``
    (``jpeg_encode_ms``) and ``cv2.imdecode`` (``jpeg_decode_ms``).
    """
    import tempfile
    from pathlib import Path

    import cv2
    import numpy as np

    from app.recording import RecordingWriter, ReplaySource
    from app.sources.frames import Frame
    from app.sources.sim.scenarios import InspectionScenario

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    sets = 30
    period_ns = 1_000_000_000 // 30
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths: list[Path] = []

        def write(i: int) -> None:
            path = Path(tmp) / f"rec{i + 1}.mcap"
            with RecordingWriter(path, rig) as w:
                for k in range(sets):
                    for name, f in frames.frames.items():
                        w.write(Frame(name, k * period_ns, f.image, f.distance_m))
            paths.append(path)

        write_ms = median_ms(write, repeat)

        def read(i: int) -> None:
            with ReplaySource(paths[-1], realtime=False) as src:
                n = sum(1 for _ in src.frames())
            if n != sets * len(frames.frames):
                raise RuntimeError(f"replayed {n} frames, expected {sets * len(frames.frames)}")

        read_ms = median_ms(read, repeat)
        figures["write_sets_per_s"] = sets / (write_ms / 1e3)
        figures["read_sets_per_s"] = sets / (read_ms / 1e3)
        figures["write_ms_per_set"] = write_ms / sets
        figures["read_ms_per_set"] = read_ms / sets
        figures["mb_per_set"] = paths[-1].stat().st_size / 1e6 / sets
    bgr = cv2.cvtColor(frames["ccd_left"].image, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, 90]
    figures["jpeg_encode_ms"] = median_ms(lambda _i: cv2.imencode(".jpg", bgr, params), repeat)
    jpg = cv2.imencode(".jpg", bgr, params)[1]
    figures["jpeg_decode_ms"] = median_ms(
        lambda _i: cv2.imdecode(np.asarray(jpg), cv2.IMREAD_COLOR_RGB), repeat
    )
    return figures


# -- the console stream, end to end in a browser -------------------------------------------

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)

# Injected into the viewer page before its own script: per drawn frame, the time it was
# drawn, the latency from the frame's source time stamp (``stamp_ns``: when the simulated
# head released its left colour image) and from the server's send time (``sent_ns``, what
# the viewer's overlay shows), and the bytes received over the stream's WebSocket.
_VIEWER_PROBE = """
(() => {
  const rec = { frames: [], bytes: 0, meta: null };
  window.__trifuseBench = rec;
  const Native = window.WebSocket;
  window.WebSocket = class extends Native {
    constructor(...args) {
      super(...args);
      this.addEventListener("message", (ev) => {
        if (typeof ev.data !== "string") { rec.bytes += ev.data.size; return; }
        rec.meta = JSON.parse(ev.data);
        rec.bytes += ev.data.length;
      });
    }
  };
  const draw = CanvasRenderingContext2D.prototype.drawImage;
  CanvasRenderingContext2D.prototype.drawImage = function (...args) {
    const out = draw.apply(this, args);
    const m = rec.meta, now = Date.now();
    if (m) rec.frames.push([performance.now(), now - m.stamp_ns / 1e6, now - m.sent_ns / 1e6]);
    return out;
  };
})();
"""


def _inspection_pose_count(render_hz: float = 2.0) -> int:
    """Distinct head poses the console's simulated head renders (its cache, as
    ``SimulatedHeadSource`` counts them: one pan period sampled at ``render_hz``)."""
    import numpy as np

    from app.sources.sim.scenarios import InspectionScenario

    scenario = InspectionScenario(seed=0)
    k = max(1, round(scenario.pan_period_s * render_hz))
    poses = {tuple(np.round(scenario.T_world_rig(i / render_hz), 9).ravel()) for i in range(k)}
    return len(poses)


class _Console:
    """``trifuse serve`` on the simulated inspection room in a subprocess, with its own
    work directory and ``XDG_CACHE_HOME`` (so the disk cache of rendered poses is
    ``cache_home/trifuse/sim``), and one viewer page in headless Chromium."""

    def __init__(self, browser: Any, cache_home: Path, workdir: Path) -> None:
        import os
        import socket
        import subprocess
        import sys

        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        env = {**os.environ, "XDG_CACHE_HOME": str(cache_home)}
        env.pop("TRIFUSE_SIM_CACHE", None)
        self.t_start = time.monotonic()
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import sys; from app.cli import main; sys.exit(main(sys.argv[1:]))",
                "serve",
                "--port",
                str(port),
                "--workdir",
                str(workdir),
            ],
            cwd=Path(__file__).resolve().parents[2],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        line = self.proc.stdout.readline() if self.proc.stdout else ""
        signin = next((w for w in line.split() if w.startswith(f"http://127.0.0.1:{port}/")), "")
        if not signin:
            self.close()
            raise RuntimeError(f"trifuse serve did not start: {line}")
        self.url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:  # the line comes before the server listens
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    self.close()
                    raise RuntimeError(f"trifuse serve does not listen on port {port}") from None
                time.sleep(0.1)
        try:
            self.page = browser.new_page()
            self.page.add_init_script(_VIEWER_PROBE)
            self.page.goto(signin)  # the printed URL, with the token
        except BaseException:
            self.close()
            raise

    def first_frame_s(self, timeout_s: float = 300.0) -> float:
        """Seconds from starting the server to the viewer's first drawn frame."""
        self.page.wait_for_function(
            "() => window.__trifuseBench && window.__trifuseBench.frames.length > 0",
            timeout=timeout_s * 1e3,
        )
        return time.monotonic() - self.t_start

    def window(self, seconds: float) -> dict[str, float]:
        """The viewer over the next ``seconds``: frames drawn per second, median latencies
        (ms), megabytes per second received, and the viewer's own fps figure."""
        import statistics

        js = "() => [window.__trifuseBench.frames.length, window.__trifuseBench.bytes]"
        n0, b0 = self.page.evaluate(js)
        t0 = time.monotonic()
        viewer_fps = []
        while time.monotonic() - t0 < seconds:
            self.page.wait_for_timeout(1000)
            viewer_fps.append(self.page.evaluate("() => window.trifuseStats.fps"))
        dt = time.monotonic() - t0
        n1, b1 = self.page.evaluate(js)
        frames = self.page.evaluate(f"() => window.__trifuseBench.frames.slice({n0}, {n1})")
        return {
            "fps": (n1 - n0) / dt,
            "viewer_fps": statistics.median(viewer_fps) if viewer_fps else 0.0,
            "latency_ms": statistics.median(f[1] for f in frames) if frames else float("nan"),
            "send_latency_ms": statistics.median(f[2] for f in frames) if frames else float("nan"),
            "mb_per_s": (b1 - b0) / dt / 1e6,
        }

    def close(self) -> None:
        page = getattr(self, "page", None)
        if page is not None:
            page.close()
            self.page = None
        stop_process(self.proc)


def _phase(console: _Console, windows: list[dict[str, float]], prefix: str) -> dict[str, float]:
    import statistics

    out = {}
    for key in ("fps", "viewer_fps", "latency_ms", "send_latency_ms", "mb_per_s"):
        values = [w[key] for w in windows if w[key] == w[key]]  # NaN: no frame
        out[f"{prefix}_{key}"] = statistics.median(values) if values else float("nan")
    out[f"{prefix}_min_fps"] = min((w["fps"] for w in windows), default=float("nan"))
    return out


@register(
    "stream",
    "the console's fused stream on the simulated head, end to end in headless Chromium: "
    "frames/s at the viewer, latency, bandwidth; while the pose cache fills, once it is "
    "full, and after a restart (minutes)",
    baselines=(("warm_frame_interval_ms", "compose_encode_ms"),),
    default_repeat=10,
)
def _stream(repeat: int) -> dict[str, float]:
    """``trifuse serve`` (default: the inspection room, with everything the console runs:
    3D scene, panels, live board detection) and its viewer page in headless Chromium
    (``/usr/bin/chromium``, Playwright), all on this machine.

    Three phases, each reported as medians over windows of ``WINDOW_S`` seconds:

    - ``fill_*``: a fresh disk cache (a temporary ``XDG_CACHE_HOME``), from the viewer's
      first frame until every head pose is rendered (``fill_poses_rendered`` of ``poses``;
      at most 300 s, ``fill_s``);
    - ``warm_*``: then ``repeat`` windows on the same console;
    - ``restart_*``: a second console on the now full disk cache, ``repeat`` windows from
      its first frame; ``restart_first_frame_s``: start to first frame drawn (the first
      console's: ``fill_first_frame_s``).

    Per window: ``fps`` frames drawn by the viewer per second (``min_fps``: the worst
    window), ``viewer_fps`` what the viewer's own overlay (``window.trifuseStats``)
    showed, ``latency_ms`` from the frame leaving the source (its time stamp; the
    simulated head's clock is the host's) to the viewer drawing it, ``send_latency_ms``
    from the server publishing it, ``mb_per_s`` megabytes received per second.

    Baseline, same run, before the consoles: ``compose_encode_ms``, the pipeline's own
    work per frame when every frame is new (blend of both eyes, RGB to BGR, JPEG q80 of
    the 2560 x 960 pair), and ``warm_frame_interval_ms`` (1000 / ``warm_fps``) against it.
    """
    import os
    import tempfile

    import cv2
    import numpy as np

    from app.sources.sim.scenarios import InspectionScenario
    from fusion.compose import DisplaySettings
    from fusion.stereo import StereoFusion

    if not os.path.exists(CHROMIUM):
        raise RuntimeError(f"the stream benchmark needs Debian's chromium at {CHROMIUM}")
    from playwright.sync_api import sync_playwright

    window_s = 3.0
    figures: dict[str, float] = {}
    fill_max_s = 300.0

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    colors = {e: frames[rig.eyes[e].color].image for e in ("left", "right")}
    thermals = {e: frames[rig.eyes[e].thermal].image for e in ("left", "right")}
    fusion = StereoFusion(rig)
    fusion.update_depth(frames["tof"].distance_m)
    blend = DisplaySettings(mode="blend")
    bgr = np.empty((*fusion.frame.shape[:2], 3), np.uint8)

    def compose_encode(_i: int) -> None:
        rgb = fusion.compose(colors, thermals, blend)
        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR, dst=bgr)
        cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 80])

    figures["compose_encode_ms"] = median_ms(compose_encode, max(repeat, 20))
    poses = _inspection_pose_count()

    with tempfile.TemporaryDirectory(prefix="trifuse-bench-stream-") as tmp, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_FLAGS))
        try:
            cache = Path(tmp) / "cache"
            console = _Console(browser, cache, Path(tmp) / "work1")
            try:
                figures["fill_first_frame_s"] = console.first_frame_s()
                t_fill = time.monotonic()
                fill = []

                def rendered() -> int:
                    return len(list(cache.glob("trifuse/sim/*/pose-*.npz")))

                while rendered() < poses and time.monotonic() - t_fill < fill_max_s:
                    fill.append(console.window(window_s))
                figures["fill_s"] = time.monotonic() - t_fill
                figures["fill_poses_rendered"] = rendered()
                figures["poses"] = poses
                figures.update(_phase(console, fill, "fill"))
                warm = [console.window(window_s) for _ in range(repeat)]
                figures.update(_phase(console, warm, "warm"))
            finally:
                console.close()
            console = _Console(browser, cache, Path(tmp) / "work2")
            try:
                figures["restart_first_frame_s"] = console.first_frame_s()
                restart = [console.window(window_s) for _ in range(repeat)]
                figures.update(_phase(console, restart, "restart"))
            finally:
                console.close()
        finally:
            browser.close()
    figures["warm_frame_interval_ms"] = 1e3 / figures["warm_fps"] if figures["warm_fps"] else 0
    return figures


# -- the console's first minute on the simulated head --------------------------------------

# Injected into the viewer page: every binary stream message (one JPEG of the fused pair,
# drawn by the viewer) as [performance.now() ms, size in bytes]. The pipeline publishes the
# very same JPEG again while its inputs are unchanged, so equal consecutive sizes mean the
# picture stood still.
_PICTURE_PROBE = """
(() => {
  const rec = { pictures: [] };
  window.__trifuseMotion = rec;
  const Native = window.WebSocket;
  window.WebSocket = class extends Native {
    constructor(...args) {
      super(...args);
      this.addEventListener("message", (ev) => {
        if (typeof ev.data !== "string") rec.pictures.push([performance.now(), ev.data.size]);
      });
    }
  };
})();
"""

MOTION_MERGE_S = 0.15
"""Picture changes closer than this (seconds) count as one move: when the head's pose
changes, the colour, thermal and TOF images switch a few frames apart."""


def motion_figures(pictures: list[tuple[float, int]], t0_s: float, span_s: float) -> dict:
    """How the picture moved in ``[t0_s, t0_s + span_s)``: ``pictures`` are (time s, JPEG
    size) of the stream's pictures in arrival order; a size different from the previous
    picture's is a change (changes within :data:`MOTION_MERGE_S` are one move).

    Returns ``moves_per_s``, ``longest_still_s`` (the longest time between moves, the
    window's ends included), ``pictures_per_s`` and ``distinct`` (distinct pictures).
    """
    inside = [(t, s) for t, s in pictures if t0_s <= t < t0_s + span_s]
    moves: list[float] = []
    prev = None
    for t, size in inside:
        if prev is not None and size != prev and (not moves or t - moves[-1] > MOTION_MERGE_S):
            moves.append(t)
        prev = size
    edges = [t0_s, *moves, t0_s + span_s]
    return {
        "moves_per_s": len(moves) / span_s,
        "longest_still_s": max(b - a for a, b in itertools.pairwise(edges)),
        "pictures_per_s": len(inside) / span_s,
        "distinct": float(len({s for _, s in inside})),
    }


@register(
    "sim-first-minute",
    "the console's first minute on the simulated head with an empty pose cache, against "
    "the same console once every pose is cached: picture moves per second and the longest "
    "time it stood still, in headless Chromium (minutes)",
    baselines=(
        ("first_longest_still_s", "full_longest_still_s"),
        ("first_moves_per_s", "full_moves_per_s"),
    ),
    default_repeat=1,
)
def _sim_first_minute(repeat: int) -> dict[str, float]:
    """``trifuse serve`` (default: the inspection room) with its viewer page in headless
    Chromium, as in the ``stream`` benchmark, watched picture by picture.

    ``first_*``: a console on an empty disk cache (a temporary ``XDG_CACHE_HOME``), the
    ``SPAN_S`` seconds from the viewer's first picture (median over ``repeat`` consoles,
    each on a new empty cache). Then the last console's cache is left to fill (at most 600
    s; ``fill_s`` from its first picture, ``fill_poses_rendered`` of ``poses``) and
    ``full_*`` is a console restarted on that full cache, its first ``SPAN_S`` seconds:
    the baseline, how the picture moves once every pose is rendered.

    Per console: ``moves_per_s`` picture changes per second (:func:`motion_figures`: the
    JPEG the viewer receives changes), ``longest_still_s`` the longest time without one,
    ``pictures_per_s`` the pictures the viewer received per second, ``distinct`` distinct
    pictures, ``first_picture_s`` from the start of the server to the first picture.
    """
    import os
    import statistics
    import tempfile

    if not os.path.exists(CHROMIUM):
        raise RuntimeError(f"the sim-first-minute benchmark needs Debian's chromium at {CHROMIUM}")
    from playwright.sync_api import sync_playwright

    span_s = 60.0
    fill_max_s = 600.0
    poses = _inspection_pose_count()

    def watch(console: _Console) -> tuple[dict[str, float], float]:
        console.page.add_init_script(_PICTURE_PROBE)
        console.page.reload()
        console.page.wait_for_function(
            "() => window.__trifuseMotion && window.__trifuseMotion.pictures.length > 0",
            timeout=300e3,
        )
        first_s = time.monotonic() - console.t_start
        js = "() => window.__trifuseMotion.pictures"
        t0 = console.page.evaluate(js)[0][0] / 1e3
        console.page.wait_for_timeout(span_s * 1e3)
        console.page.wait_for_function(
            f"() => performance.now() >= {(t0 + span_s) * 1e3 + 500}", timeout=60e3
        )
        pictures = [(t / 1e3, int(s)) for t, s in console.page.evaluate(js)]
        out = motion_figures(pictures, t0, span_s)
        out["first_picture_s"] = first_s
        return out, time.monotonic() - (first_s + console.t_start)

    figures: dict[str, float] = {"poses": float(poses)}
    with tempfile.TemporaryDirectory(prefix="trifuse-bench-motion-") as tmp, sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=list(CHROMIUM_FLAGS))
        try:
            firsts = []
            cache = Path(tmp) / "cache-0"
            for i in range(repeat):
                cache = Path(tmp) / f"cache-{i}"
                console = _Console(browser, cache, Path(tmp) / f"work-{i}")
                try:
                    first, elapsed = watch(console)
                    firsts.append(first)
                    if i == repeat - 1:  # let its cache fill, for the baseline

                        def rendered(c: Path = cache) -> int:
                            return len(list(c.glob("trifuse/sim/*/pose-*.npz")))

                        t_fill = time.monotonic() - elapsed
                        while rendered() < poses and time.monotonic() - t_fill < fill_max_s:
                            time.sleep(1.0)
                        figures["fill_s"] = time.monotonic() - t_fill
                        figures["fill_poses_rendered"] = float(rendered())
                finally:
                    console.close()
            for key in firsts[0]:
                figures[f"first_{key}"] = statistics.median(f[key] for f in firsts)
            console = _Console(browser, cache, Path(tmp) / "work-full")
            try:
                full, _ = watch(console)
            finally:
                console.close()
            figures.update({f"full_{k}": v for k, v in full.items()})
        finally:
            browser.close()
    return figures


@register(
    "sim-live",
    "simulated head: the live quality against the accurate one per image and per pose, one "
    "frame from a live render, and a 3 s `trifuse record --source sim` against 3 s of real "
    "time",
    baselines=(
        ("live_ccd_left_ms", "accurate_ccd_left_ms"),
        ("live_thermal_left_ms", "accurate_thermal_left_ms"),
        ("live_tof_ms", "accurate_tof_ms"),
        ("live_pose_ms", "accurate_pose_ms"),
        ("record_s", "recorded_s"),
    ),
    default_repeat=5,
)
def _sim_live(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` renders of the inspection room at distinct moments (warm:
    ray grids built), the accurate quality (``InspectionScenario``) against the live one
    (``live=True``), frames with noise included: ``<sensor>_ms`` one sensor,
    ``pose_ms`` all five. ``frame_<sensor>_ms``: one frame from a live render with a margin,
    turned by 0.2 degrees, with fresh noise (what the recording pays per frame besides
    encoding). ``record_s``: one ``record_simulation`` of ``recorded_s`` = 3 s in the
    default (live) mode, wall time, new scenario included; the ratio is "x real time".
    """
    import tempfile

    import numpy as np

    from app.recording.simrecord import record_simulation
    from app.sources.sim.scenarios import InspectionScenario

    sensors = ("ccd_left", "thermal_left", "tof")
    figures: dict[str, float] = {}
    for label, live in (("accurate", False), ("live", True)):
        scenario = InspectionScenario(seed=0, live=live)
        scenario.render(0.0)
        for name in sensors:
            figures[f"{label}_{name}_ms"] = median_ms(
                lambda i, n=name, s=scenario: s.render(1.0 + 0.37 * i, [n]), repeat
            )
        figures[f"{label}_pose_ms"] = median_ms(
            lambda i, s=scenario: s.render(2.0 + 0.41 * i), repeat
        )
    assert scenario.developer is not None
    dev = scenario.developer
    rng = np.random.default_rng(0)
    margins = dict.fromkeys(sensors, 15)
    clean = scenario.render_clean(5.0, list(sensors), margins)
    T = scenario.T_world_rig(5.07)  # 0.2 degrees on
    for name in sensors:
        T_sensor = T @ scenario.rig[name].T_rig_sensor
        figures[f"frame_{name}_ms"] = median_ms(
            lambda _i, n=name, Ts=T_sensor: dev.frame(clean[n], 0, rng, Ts), max(repeat, 20)
        )
    from app.sources.sim.head import default_rig

    with tempfile.TemporaryDirectory(prefix="trifuse-bench-simrec-") as tmp:
        t0 = time.perf_counter()
        record_simulation(Path(tmp) / "sim.mcap", default_rig(), 3.0)
        figures["record_s"] = time.perf_counter() - t0
    figures["recorded_s"] = 3.0
    return figures


# -- the stream soak (app/devtools/bench_soak.py) --------------------------------------------------
# Not in REGISTRY: it runs for minutes, has its own options and passes or fails.


def run_soak_command(soak_s: float, viewers: int) -> int:
    """``trifuse bench --soak``: ``viewers`` fast viewers plus slow readers on a console for
    ``soak_s`` seconds (app/devtools/bench_soak.py); prints the table, returns the exit code (1 if
    a criterion fails)."""
    from app.devtools.bench_soak import SoakConfig, run_soak_cli

    return run_soak_cli(SoakConfig(soak_s=soak_s, viewers=viewers))


from app.devtools import bench_detect  # noqa: E402  (after REGISTRY; imports nothing from here)

register(
    "thermal-detect",
    bench_detect.DESCRIPTION,
    baselines=bench_detect.ratio_pairs(),
    default_repeat=1,
)(bench_detect.thermal_detect)
