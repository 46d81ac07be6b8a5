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

import os
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from trifuse.app.devtools.benchmark import benchmark
from trifuse.calib.board import Board
from trifuse.calib.detect import Detection, detect_board
from trifuse.calib.detect_baseline import detect_board_baseline

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
    from trifuse.app.sources.sim.condition_views import thermal_condition_views
    from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
    from trifuse.app.sources.sim.thermal_conditions import BENCH_CONDITIONS

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
    from trifuse.app.sources.sim.thermal_conditions import BENCH_CONDITIONS

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


# -- real 12 MP views (issue 30) ---------------------------------------------------------

REAL_12MP_DIR = Path(__file__).resolve().parents[2] / "tests" / "data" / "czha626-thermal-visible"
REAL_12MP_BOARD = Board(6, 5, 0.1)
"""The board of czha626-thermal-visible: 6 x 5 inner corners, 0.1 m squares (its README)."""
OPENCV_SIDES = {"full": None, "2000": 2000, "1000": 1000}
"""OpenCV's plain variants: the detector at full size or on a copy downscaled (INTER_AREA) to
this longer side, its corners scaled back, no refinement."""


def _opencv_plain(grey: np.ndarray, board: Board, detector: str, side: int | None):
    """OpenCV's ``detector`` (``"sb"``: findChessboardCornersSB, no flags; ``"classic"``:
    findChessboardCorners, default flags) on ``grey`` (H, W) uint8, downscaled to the
    longer side ``side`` if given; (N, 2) float64 pixels of ``grey`` or None."""
    h, w = grey.shape
    img, sx, sy = grey, 1.0, 1.0
    if side is not None and max(h, w) > side:
        f = side / max(h, w)
        size = (round(w * f), round(h * f))
        img = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        sx, sy = w / size[0], h / size[1]
    if detector == "sb":
        ok, raw = cv2.findChessboardCornersSB(img, board.pattern_size)
    else:
        ok, raw = cv2.findChessboardCorners(img, board.pattern_size)
    if not ok or raw is None:
        return None
    return (np.asarray(raw, dtype=np.float64).reshape(-1, 2) + 0.5) * (sx, sy) - 0.5


def _real_12mp_detectors(
    modality: str, full_size: bool = True
) -> dict[str, Callable[[np.ndarray], np.ndarray | None]]:
    """name -> detector of one grey image ((N, 2) corners or None) for ``real-12mp``;
    ``full_size`` False leaves out the colour detectors that search the whole 12 MP image
    (ours without the pyramid, OpenCV's at full size and 2000 px: 1-22 s a view)."""
    from trifuse.calib.opencv_reference import find_chessboard_opencv

    board = REAL_12MP_BOARD
    thermal = modality == "thermal"

    def ours(pyramid: bool) -> Callable[[np.ndarray], np.ndarray | None]:
        return lambda g: detect_board(g, board, modality, pyramid=pyramid).corners

    out: dict[str, Callable[[np.ndarray], np.ndarray | None]] = {"ours": ours(True)}
    if thermal:
        out["baseline"] = lambda g: detect_board_baseline(g, board, "thermal").corners
    elif full_size:
        out["ours_fullres"] = ours(False)
    sides = OPENCV_SIDES if full_size else {"1000": 1000}
    for det in ("sb", "classic"):
        for label, side in sides.items() if not thermal else [("full", None)]:
            out[f"opencv_{det}_{label}"] = lambda g, det=det, side=side: _opencv_plain(
                g, board, det, side
            )
    out["opencv_reference"] = lambda g: find_chessboard_opencv(
        g, board.pattern_size, thermal=thermal, max_side_px=None if thermal else 1000
    )[0]
    return out


def _calibration(corners: list[np.ndarray], size: tuple[int, int]) -> tuple[float, float, float]:
    """calibrateCamera (5 coefficients) on per-view corners (N, 2) in the board's order:
    (RMS px, worst view's RMS px, fx px); NaNs with fewer than 3 views."""
    if len(corners) < 3:
        return float("nan"), float("nan"), float("nan")
    obj = REAL_12MP_BOARD.object_points().astype(np.float32)
    img = [c.astype(np.float32) for c in corners]
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera([obj] * len(img), img, size, None, None)
    worst = 0.0
    for c, r, t in zip(img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj, r, t, K, dist)
        worst = max(worst, float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - c) ** 2, 1)))))
    return float(rms), worst, float(K[0, 0])


def _in_order(corners: np.ndarray, grey: np.ndarray) -> np.ndarray:
    """A detector's corners (N, 2) in the board's canonical order (handedness, then the
    square colours: :func:`calib.detect_order.canonical_order`), so that views calibrate
    together and compare corner for corner."""
    from trifuse.calib.detect_order import canonical_order

    return canonical_order(corners, REAL_12MP_BOARD, grey.astype(np.float32))[0]


def _agreement(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (px) between corresponding corners of two detections (N, 2), taking the
    ordering of ``b`` (of the four a grid has) that lies closest to ``a``."""
    A = a.reshape(REAL_12MP_BOARD.rows, REAL_12MP_BOARD.cols, 2)
    B = b.reshape(A.shape)
    cands = (B, B[::-1, ::-1], B[::-1, :], B[:, ::-1])
    best = min(cands, key=lambda c: float(np.median(np.linalg.norm(c - A, axis=2))))
    return np.linalg.norm(best - A, axis=2).ravel()


def real_12mp_figures(
    directory: Path = REAL_12MP_DIR, repeat: int = 1, full_size: bool = True
) -> dict[str, float]:
    """Every detector of :func:`_real_12mp_detectors` (``full_size`` passed on) on
    ``directory``'s ``visible/*.jpg`` (12 MP) and ``thermal/*.jpg``: view by view, every
    detector in turn, ``repeat`` times (times: median over views and repeats; ours runs once
    on the first view before, untimed).

    Figures per sensor ``<s>`` (``visible``, ``thermal``) and detector ``<d>``:

    * ``<s>_views``, ``<s>_found_<d>``, ``<s>_s_<d>`` (median seconds per view);
    * ``<s>_calib_rms_px_<d>``, ``<s>_worst_view_px_<d>``, ``<s>_fx_<d>``:
      cv2.calibrateCamera on the views ``<d>`` found (RMS, the largest per-view RMS, which a
      misplaced grid drives up, and fx); ``<s>_calib_rms_px_ours_on_<d>_views``: ours
      calibrated on the views that ``<d>`` and ours both found;
    * ``<s>_best_opencv_found``: the most boards any OpenCV variant found;
    * visible only: ``visible_s_ours_at_1000`` and ``visible_found_ours_at_1000`` (ours on the
      same views downscaled to 1000 px), ``visible_vs_fullres_px_max`` (largest distance
      between our corners and ours at full resolution, on the views both found),
      ``visible_opencv_1000_vs_ours_px_median`` (OpenCV's sector-based corners found at
      1000 px against ours);
    * ``load_1min_start``, ``load_1min_end``: the machine's load average."""
    out: dict[str, float] = {"load_1min_start": os.getloadavg()[0]}
    found: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for sensor, modality in (("visible", "color"), ("thermal", "thermal")):
        files = sorted((directory / sensor).glob("*.jpg"))
        greys = {}
        for f in files:
            grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if grey is None:
                raise ValueError(f"real image {f}: cannot be read")
            greys[f.stem] = grey
        out[f"{sensor}_views"] = len(greys)
        if not greys:
            continue
        size = next(iter(greys.values())).shape[::-1]
        detectors = _real_12mp_detectors(modality, full_size)
        if sensor == "visible":
            detectors["ours_at_1000"] = detectors["ours"]
        detectors["ours"](next(iter(greys.values())))  # warm-up
        corners: dict[str, dict[str, np.ndarray]] = {name: {} for name in detectors}
        seconds: dict[str, list[float]] = {name: [] for name in detectors}
        for view, grey in greys.items():
            f = 1000 / max(grey.shape)
            small = cv2.resize(grey, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
            for _ in range(repeat):
                # Every detector on this view in turn: a change of load hits them alike.
                for name, detect in detectors.items():
                    image = small if name == "ours_at_1000" else grey
                    t0 = time.perf_counter()
                    c = detect(image)
                    seconds[name].append(time.perf_counter() - t0)
                    if c is not None and np.all(np.isfinite(c)):
                        corners[name][view] = _in_order(c, image)
        found[sensor] = corners
        for name in detectors:
            out[f"{sensor}_found_{name}"] = len(corners[name])
            out[f"{sensor}_s_{name}"] = statistics.median(seconds[name])
            if name == "ours_at_1000":
                continue
            rms, worst, fx = _calibration(list(corners[name].values()), size)
            out[f"{sensor}_calib_rms_px_{name}"] = rms
            out[f"{sensor}_worst_view_px_{name}"] = worst
            out[f"{sensor}_fx_{name}"] = fx
            if name != "ours":
                same = [corners["ours"][v] for v in corners[name] if v in corners["ours"]]
                out[f"{sensor}_calib_rms_px_ours_on_{name}_views"] = _calibration(same, size)[0]
        out[f"{sensor}_best_opencv_found"] = max(
            v for k, v in out.items() if k.startswith(f"{sensor}_found_opencv_")
        )
    vis = found.get("visible", {})
    if vis:
        ours, full, cv1000 = vis["ours"], vis.get("ours_fullres", {}), vis["opencv_sb_1000"]
        d = [_agreement(ours[v], full[v]).max() for v in ours if v in full]
        out["visible_vs_fullres_px_max"] = max(d) if d else float("nan")
        d = [np.median(_agreement(ours[v], cv1000[v])) for v in ours if v in cv1000]
        out["visible_opencv_1000_vs_ours_px_median"] = float(np.median(d)) if d else float("nan")
    out["load_1min_end"] = os.getloadavg()[0]
    return out


@benchmark(
    "real-12mp",
    "real 12 MP colour views and their 640 x 480 thermal pairs (issue 30, "
    "tests/data/czha626-thermal-visible): boards found, seconds per view and calibration "
    "RMS for calib.detect (pyramid, and at full resolution as before) against OpenCV's plain "
    "detectors at full size, 2000 and 1000 px; --repeat N times each view N times",
    baselines=(
        ("visible_found_ours", "visible_found_opencv_sb_1000"),
        ("visible_found_ours", "visible_best_opencv_found"),
        ("visible_s_ours", "visible_s_ours_fullres"),
        ("visible_s_ours", "visible_s_ours_at_1000"),
        ("thermal_found_ours", "thermal_best_opencv_found"),
    ),
    default_repeat=1,
)
def real_12mp(repeat: int) -> dict[str, float]:
    """:func:`real_12mp_figures` on tests/data/czha626-thermal-visible."""
    return real_12mp_figures(REAL_12MP_DIR, repeat)


def real_12mp_markdown(figures: dict[str, float]) -> str:
    """``real-12mp``'s figures as the Markdown table of BENCHMARKS.md (one row per sensor
    and detector; ``-`` where there is no figure)."""

    def fmt(x: float | None, spec: str) -> str:
        return "-" if x is None or not np.isfinite(x) else format(x, spec)

    lines = [
        "| sensor | detector | found | median s per view | calibration RMS px (ours on the "
        "same views) | worst view px | fx px |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for sensor in ("visible", "thermal"):
        views = figures.get(f"{sensor}_views", 0)
        names = [k[len(f"{sensor}_found_") :] for k in figures if k.startswith(f"{sensor}_found_")]
        for d in names:
            f = {k: figures.get(f"{sensor}_{k}_{d}") for k in ("found", "s", "worst_view_px")}
            rms = fmt(figures.get(f"{sensor}_calib_rms_px_{d}"), ".3f")
            same = figures.get(f"{sensor}_calib_rms_px_ours_on_{d}_views")
            rms += f" ({fmt(same, '.3f')})" if same is not None else ""
            lines.append(
                f"| {sensor} | {_DETECTOR_LABELS.get(d, d)} | {f['found']:.0f}/{views:.0f} "
                f"| {fmt(f['s'], '.2f')} | {rms} | {fmt(f['worst_view_px'], '.2f')} "
                f"| {fmt(figures.get(f'{sensor}_fx_{d}'), '.0f')} |"
            )
    return "\n".join(lines)


_DETECTOR_LABELS = {
    "ours": "calib.detect (colour: pyramid)",
    "ours_fullres": "calib.detect at full size (before)",
    "ours_at_1000": "calib.detect on the view downscaled to 1000 px",
    "baseline": "calib.detect_baseline (issue 15)",
    "opencv_reference": "calib.opencv_reference (visible: 1000 px, then cornerSubPix 11x11)",
    **{
        f"opencv_{d}_{side}": f"OpenCV {name}, {'full size' if side == 'full' else side + ' px'}"
        for d, name in (("sb", "findChessboardCornersSB"), ("classic", "findChessboardCorners"))
        for side in OPENCV_SIDES
    },
}


def main(argv: list[str] | None = None) -> int:
    """``python -m trifuse.app.devtools.bench_detect --root DIR [--no-full-size]``: ``real-12mp``'s
    figures and table on another directory laid out as tests/data/czha626-thermal-visible
    (e.g. all 47 pairs of the source repository, which are not committed)."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--root", type=Path, default=REAL_12MP_DIR)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--no-full-size", dest="full_size", action="store_false")
    args = parser.parse_args(argv)
    if not (args.root / "visible").is_dir() or args.repeat < 1:
        parser.error(f"expected a directory with visible/ and thermal/, got {args.root}")
    figures = real_12mp_figures(args.root, args.repeat, args.full_size)
    for key, value in figures.items():
        print(f"{key} = {value:.3f}")
    print(real_12mp_markdown(figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
