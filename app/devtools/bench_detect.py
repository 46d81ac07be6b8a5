"""Benchmark ``thermal-detect``: trifuse's board detector against the plain OpenCV pipeline.

Issue 15: on a real LWIR rig trifuse found 9/16 thermal boards and the plain OpenCV pipeline
(:mod:`calib.detect_baseline`) 14/16. This benchmark renders seeded views of the simulated
head under each real-world condition of :mod:`app.sources.sim.thermal_conditions` (each
alone, all combined, none), runs :func:`calib.detect.detect_board` and
:func:`calib.detect_baseline.detect_board_baseline` on the same images and compares them
with the simulator's exact corner projections:

* thermal imagers (382 x 288), every condition of
  :data:`~app.sources.sim.thermal_conditions.BENCH_CONDITIONS`;
* colour cameras (1280 x 960) under the conditions that change what they see
  (:data:`COLOUR_CONDITIONS`: none, partly out of view, hot objects beside the board);
* the 13 real colour photographs of OpenCV's samples (``tests/data/opencv-left-9x6``, no
  reference corners: found counts, and a ``cv2.calibrateCamera`` with each detector's
  corners against OpenCV's reference focal length).

Figures per condition ``<c>`` (thermal) or ``colour-<c>``, detector ``<d>`` = ``ours`` or
``baseline``: ``<c>_views``, ``<c>_expected`` (views whose every inner corner is in view
with its neighbourhood), ``<c>_found_<d>`` (boards returned), ``<c>_found_expected_<d>``
(of those, on the expected views; the rest are boards whose outer squares the image
border or a hand cuts, which calib.detect declines within half a spacing of the border),
``<c>_wrong_<d>`` (a board returned that is
cut by the border, or corners off by more than half a corner spacing: a misplaced or
misordered grid), ``<c>_rms_mean_px_<d>`` and ``<c>_rms_max_px_<d>`` (per board: RMS
distance of the corners from the truth, canonical order; over the boards found and not
wrong) and ``<c>_ms_<d>`` (median time per image).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from app.devtools.benchmark import benchmark
from calib.board import Board
from calib.detect import Detection, detect_board
from calib.detect_baseline import detect_board_baseline

POSES_PER_SEED = 8
"""Board poses per seed; each is seen by both imagers (16 images per seed)."""
THERMAL_SENSORS = ("thermal_left", "thermal_right")
COLOUR_SENSORS = ("ccd_left", "ccd_right")
COLOUR_CONDITIONS = ("none", "partial-view", "hot-objects")
"""The conditions that change a colour camera's image (the others are thermal physics)."""
REAL_DIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "opencv-left-9x6"
REAL_BOARD = Board(9, 6, 0.025)
REAL_FX_REFERENCE = 536.07
"""OpenCV's reference focal length of its left sample camera (tests/data/.../README.md)."""

Detector = Callable[[np.ndarray, Board, str], Detection]
DETECTORS: dict[str, Detector] = {
    "ours": lambda image, board, modality: detect_board(image, board, modality),
    "baseline": lambda image, board, modality: detect_board_baseline(image, board, modality),
}


@dataclass
class Tally:
    """One detector on one condition: counts, per-board RMS errors (px), times (ms)."""

    found: int = 0
    found_expected: int = 0
    wrong: int = 0
    rms_px: list[float] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)


@dataclass
class ConditionResult:
    """Both detectors on the views of one condition."""

    name: str
    views: int = 0
    expected: int = 0
    tallies: dict[str, Tally] = field(default_factory=lambda: {d: Tally() for d in DETECTORS})

    def figures(self) -> dict[str, float]:
        """The figures of this condition (module docstring)."""
        c = self.name
        out: dict[str, float] = {f"{c}_views": self.views, f"{c}_expected": self.expected}
        for d, t in self.tallies.items():
            out[f"{c}_found_{d}"] = t.found
            out[f"{c}_found_expected_{d}"] = t.found_expected
            out[f"{c}_wrong_{d}"] = t.wrong
            out[f"{c}_rms_mean_px_{d}"] = float(np.mean(t.rms_px)) if t.rms_px else float("nan")
            out[f"{c}_rms_max_px_{d}"] = float(np.max(t.rms_px)) if t.rms_px else float("nan")
            out[f"{c}_ms_{d}"] = statistics.median(t.ms) if t.ms else float("nan")
        return out


def corner_rms(corners: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance (px) between detected ``corners`` and ``truth`` (both (N, 2), same
    order)."""
    return float(np.sqrt(np.mean(np.sum((corners - truth) ** 2, axis=1))))


def median_spacing(truth: np.ndarray, board: Board) -> float:
    """Median distance (px) between neighbouring corners of ``truth`` (N, 2)."""
    G = truth.reshape(board.rows, board.cols, 2)
    d = np.concatenate(
        [
            np.linalg.norm(np.diff(G, axis=1), axis=2).ravel(),
            np.linalg.norm(np.diff(G, axis=0), axis=2).ravel(),
        ]
    )
    return float(np.nanmedian(d))


def score_view(
    result: ConditionResult,
    image: np.ndarray,
    modality: str,
    truth: np.ndarray,
    expected: bool,
    cut: bool,
    board: Board,
) -> dict[str, Detection]:
    """Run every detector on ``image`` and add the outcome to ``result``; returns the
    detections. ``truth``: (N, 2) exact corners, canonical order (NaN if unprojectable)."""
    result.views += 1
    result.expected += expected
    out = {}
    for name, detector in DETECTORS.items():
        t0 = time.perf_counter()
        det = detector(image, board, modality)
        tally = result.tallies[name]
        tally.ms.append((time.perf_counter() - t0) * 1e3)
        out[name] = det
        if not det.found:
            continue
        tally.found += 1
        tally.found_expected += expected
        rms = float("inf") if cut else corner_rms(det.corners, truth)
        if cut or not rms <= 0.5 * median_spacing(truth, board):
            tally.wrong += 1
        else:
            tally.rms_px.append(rms)
    return out


def simulated_results(
    seeds: Iterable[int],
    poses_per_seed: int = POSES_PER_SEED,
    conditions: Iterable[str] | None = None,
    colour_conditions: Iterable[str] = COLOUR_CONDITIONS,
) -> list[ConditionResult]:
    """Both detectors on rendered views of every condition (thermal, then colour)."""
    from app.sources.sim.condition_views import thermal_condition_views
    from app.sources.sim.scenarios import CALIBRATION_BOARD
    from app.sources.sim.thermal_conditions import BENCH_CONDITIONS

    seeds = tuple(seeds)
    names = list(BENCH_CONDITIONS) if conditions is None else list(conditions)
    jobs = [(n, n, THERMAL_SENSORS, "thermal") for n in names]
    jobs += [(f"colour-{n}", n, COLOUR_SENSORS, "color") for n in colour_conditions]
    results = []
    for label, cond, sensors, modality in jobs:
        result = ConditionResult(label)
        for view in thermal_condition_views(
            BENCH_CONDITIONS[cond], poses_per_seed, seeds, sensors=sensors
        ):
            score_view(
                result,
                view.image,
                modality,
                view.corners,
                view.expected,
                view.cut,
                CALIBRATION_BOARD,
            )
        results.append(result)
    return results


def real_figures(directory: Path = REAL_DIR) -> dict[str, float]:
    """Both detectors on the real colour photographs in ``directory`` (9 x 6 board):
    ``real_images``, ``real_found_<d>``, ``real_ms_<d>`` and, from a
    ``cv2.calibrateCamera`` with the corners ``<d>`` found, ``real_calib_rms_px_<d>`` and
    ``real_fx_error_pct_<d>`` (against OpenCV's reference fx)."""
    files = sorted(directory.glob("left*.jpg"))
    out: dict[str, float] = {"real_images": len(files)}
    for name, detector in DETECTORS.items():
        corners, ms = [], []
        for f in files:
            grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if grey is None:
                raise ValueError(f"real image {f}: cannot be read")
            t0 = time.perf_counter()
            det = detector(grey, REAL_BOARD, "color")
            ms.append((time.perf_counter() - t0) * 1e3)
            if det.found:
                corners.append(det.corners.astype(np.float32))
        out[f"real_found_{name}"] = len(corners)
        out[f"real_ms_{name}"] = statistics.median(ms) if ms else float("nan")
        if len(corners) >= 3:
            obj = [REAL_BOARD.object_points().astype(np.float32)] * len(corners)
            rms, K, *_ = cv2.calibrateCamera(obj, corners, (640, 480), None, None)
            out[f"real_calib_rms_px_{name}"] = float(rms)
            out[f"real_fx_error_pct_{name}"] = float(100 * (K[0, 0] / REAL_FX_REFERENCE - 1))
    return out


def markdown_table(figures: dict[str, float]) -> str:
    """The simulated conditions' figures as a Markdown table (ours / baseline)."""
    conds = [k[: -len("_views")] for k in figures if k.endswith("_views")]
    lines = [
        "| condition | views (expected) | found ours / baseline (on expected views) "
        "| wrong ours / baseline "
        "| RMS mean ours / baseline | RMS max ours / baseline | median ms ours / baseline |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in conds:
        f = {k[len(c) + 1 :]: v for k, v in figures.items() if k.startswith(c + "_")}
        lines.append(
            f"| {c} | {f['views']:.0f} ({f['expected']:.0f}) "
            f"| {f['found_ours']:.0f} / {f['found_baseline']:.0f} "
            f"({f['found_expected_ours']:.0f} / {f['found_expected_baseline']:.0f}) "
            f"| {f['wrong_ours']:.0f} / {f['wrong_baseline']:.0f} "
            f"| {f['rms_mean_px_ours']:.3f} / {f['rms_mean_px_baseline']:.3f} px "
            f"| {f['rms_max_px_ours']:.3f} / {f['rms_max_px_baseline']:.3f} px "
            f"| {f['ms_ours']:.0f} / {f['ms_baseline']:.0f} |"
        )
    return "\n".join(lines)


def ratio_pairs() -> tuple[tuple[str, str], ...]:
    """The figures ``thermal-detect`` compares, ours over the baseline: found and RMS per
    condition, and the real images found."""
    from app.sources.sim.thermal_conditions import BENCH_CONDITIONS

    conds = [*BENCH_CONDITIONS, *(f"colour-{c}" for c in COLOUR_CONDITIONS)]
    what = ("found", "rms_mean_px")
    pairs = [(f"{c}_{w}_ours", f"{c}_{w}_baseline") for c in conds for w in what]
    return (*pairs, ("real_found_ours", "real_found_baseline"))


@benchmark(
    "thermal-detect",
    "board detection under real-world thermal conditions (issue 15): calib.detect vs the "
    "plain OpenCV pipeline per condition, found / truth error / time, plus the real colour "
    "images; --repeat N renders N seeds per condition (16 images each)",
    baselines=ratio_pairs(),
    default_repeat=1,
)
def thermal_detect(repeat: int) -> dict[str, float]:
    """``repeat`` seeds (0 .. repeat - 1) of :data:`POSES_PER_SEED` poses per condition,
    both thermal imagers (colour cameras for :data:`COLOUR_CONDITIONS`); each detector runs
    once per image (its time is the median over the images)."""
    figures: dict[str, float] = {}
    for result in simulated_results(range(repeat)):
        figures.update(result.figures())
    figures.update(real_figures())
    return figures
