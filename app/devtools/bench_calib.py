"""Benchmarks of the rig calibration: ``calibrate`` (30 rendered views, this engine against
OpenCV's ``calibrateMultiview``, errors against the truth) and ``calib-scale`` (how it scales
with views, and on a busy machine)."""

from __future__ import annotations

import time
from typing import Any

from trifuse.app.devtools.benchmark import benchmark


@benchmark(
    "calibrate",
    "rig calibration of 30 simulated views: this engine vs OpenCV calibrateMultiview "
    "(pose errors against ground truth, run times)",
    default_repeat=1,
)
def calibrate(repeat: int) -> dict[str, float]:
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

    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_views
    from trifuse.app.storage.capture import load_capture
    from trifuse.app.storage.capture_writer import write_board, write_view
    from trifuse.app.workflows.calibration_run import detect_capture, sensor_specs
    from trifuse.calib.opencv_baseline import calibrate_multiview_opencv
    from trifuse.calib.polarity import detect_board_configured
    from trifuse.calib.rig_calibration import calibrate_rig
    from trifuse.calib.transforms import pose_error

    truth = default_rig()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        write_board(out, CALIBRATION_BOARD)
        for view in calibration_views(30, seed=1, rig=truth):
            write_view(out, view.name, view.frames, truth)
        capture = load_capture(out)
        specs = sensor_specs(capture)
        t = time.perf_counter()
        detections = detect_capture(capture, detect=detect_board_configured)  # no cache
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
# detectors achieve on the simulated head (tests/calib/test_rig_calibration.py uses the same).
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

    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
    from trifuse.calib.transforms import transform_points

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


@benchmark(
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
def calib_scale(repeat: int) -> dict[str, float]:
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

    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
    from trifuse.calib.opencv_baseline import calibrate_multiview_opencv
    from trifuse.calib.rig_calibration import SensorSpec, calibrate_rig
    from trifuse.calib.transforms import pose_error

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
