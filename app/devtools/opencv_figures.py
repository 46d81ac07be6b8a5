"""OpenCV's reference figures on the real calibration captures of :mod:`app.devtools.real_sets`.

:func:`measure` is the plain OpenCV pipeline of :mod:`calib.opencv_reference`: detection per
sensor (checkerboard: classic then sector-based detector, thermal also inverted and
flattened, large images on a copy downscaled to ``max_side_px``, the corner order turned
so that the first corner is the one nearer the image's top-left; ChArUco:
``cv2.aruco.CharucoDetector``), ``cv2.calibrateCamera`` per sensor (5 distortion
coefficients) and ``cv2.stereoCalibrate`` (intrinsics fixed) for each registered pair on
the views both sensors saw. The figures are written into each set's README and kept in its
registry entry (``RealSet.reference``).

Run ``python -m trifuse.app.devtools.opencv_figures [NAME ...]`` to print the figures as the
README table (``--root DIR`` measures a copy of a set kept elsewhere, e.g. one whose licence
forbids committing it).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from trifuse.app.devtools.real_sets import (
    REAL_SETS,
    UNCOMMITTED_SETS,
    Checkerboard,
    PairFigures,
    RealSet,
    SensorFigures,
    load_views,
)
from trifuse.calib.opencv_reference import (
    CharucoTarget,
    calibrate_camera_opencv,
    find_charuco_opencv,
    find_chessboard_opencv,
    stereo_calibrate_opencv,
)

MIN_COMMON_CORNERS = 6
"""A ChArUco view counts for a pair when both sensors found at least this many same corners."""


@dataclass(frozen=True)
class Measurement:
    sensors: dict[str, SensorFigures]
    pairs: tuple[PairFigures, ...]


def detect(
    rs: RealSet, root: Path | None = None
) -> tuple[dict[str, dict[str, tuple[np.ndarray, np.ndarray]]], dict[str, int]]:
    """Detect the board in every measured view of every sensor.

    Returns:
        (sensor -> view id -> (corner ids (N,), image points (N, 2) pixels), sensor ->
        number of views looked at). A checkerboard's ids are 0 .. cols * rows - 1 in
        OpenCV's row-major order (after :func:`top_left_first`); a ChArUco board's are
        OpenCV's corner ids. Object points: ``board points[ids]``.
    """
    found: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    looked: dict[str, int] = {}
    for sensor in rs.sensors:
        views = load_views(rs, sensor, root)
        looked[sensor.name] = len(views)
        found[sensor.name] = {}
        for view, image in views.items():
            size = (image.shape[1], image.shape[0])
            if size != tuple(sensor.image_size):
                raise ValueError(
                    f"set {rs.name!r} sensor {sensor.name!r} view {view}: expected "
                    f"{sensor.image_size[0]}x{sensor.image_size[1]} pixels, got {size[0]}x{size[1]}"
                )
            if isinstance(rs.board, CharucoTarget):
                hit = find_charuco_opencv(image, rs.board)
                if hit is not None:
                    found[sensor.name][view] = hit
            else:
                corners, _variant = find_chessboard_opencv(
                    image,
                    (rs.board.cols, rs.board.rows),
                    thermal=sensor.modality == "thermal",
                    max_side_px=sensor.max_side_px,
                )
                if corners is not None:
                    ids = np.arange(rs.board.cols * rs.board.rows)
                    found[sensor.name][view] = (ids, top_left_first(corners))
    return found, looked


def top_left_first(corners: np.ndarray) -> np.ndarray:
    """A checkerboard's corners (N, 2) turned by a half turn if needed so that the first
    corner is nearer the image's top-left than the last (the usual fix in plain OpenCV
    scripts, so that two sensors mounted the same way up agree on the order)."""
    if corners[0].sum() > corners[-1].sum():
        return corners[::-1].copy()
    return corners


def _board_points(rs: RealSet) -> np.ndarray:
    if isinstance(rs.board, CharucoTarget):
        return rs.board.corner_points()
    return rs.board.points()


def measure(rs: RealSet, root: Path | None = None) -> Measurement:
    """OpenCV's reference figures for a set (module docstring)."""
    obj = _board_points(rs)
    found, looked = detect(rs, root)
    sensors: dict[str, SensorFigures] = {}
    cams = {}
    for s in rs.sensors:
        det = found[s.name]
        ref = calibrate_camera_opencv(
            [obj[ids] for ids, _ in det.values()], [uv for _, uv in det.values()], s.image_size
        )
        cams[s.name] = ref
        k = ref.intrinsics
        sensors[s.name] = SensorFigures(
            len(det), looked[s.name], ref.rms_px, k.fx, k.fy, k.cx, k.cy, k.distortion
        )
    pairs = []
    for a, b in rs.pairs:
        objs, pa, pb = [], [], []
        for view in sorted(set(found[a]) & set(found[b])):
            ids_a, uv_a = found[a][view]
            ids_b, uv_b = found[b][view]
            common, ia, ib = np.intersect1d(ids_a, ids_b, return_indices=True)
            if len(common) >= MIN_COMMON_CORNERS:
                objs.append(obj[common])
                pa.append(uv_a[ia])
                pb.append(uv_b[ib])
        st = stereo_calibrate_opencv(
            objs, pa, pb, cams[a].intrinsics, cams[b].intrinsics, rs.sensor(a).image_size
        )
        pairs.append(PairFigures(a, b, st.n_views, st.rms_px, st.baseline_m, st.rotation_deg))
    return Measurement(sensors, tuple(pairs))


def reference_table(sensors: dict[str, SensorFigures], pairs: Iterable[PairFigures]) -> str:
    """The figures as the markdown table the set's README carries."""
    lines = [
        "| sensor | boards found | RMS px | fx | fy | cx | cy | k1 k2 p1 p2 k3 |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, f in sensors.items():
        dist = " ".join(f"{d:.4f}" for d in f.dist)
        lines.append(
            f"| {name} | {f.found}/{f.views} | {f.rms_px:.3f} | {f.fx:.2f} | {f.fy:.2f} | "
            f"{f.cx:.2f} | {f.cy:.2f} | {dist} |"
        )
    pairs = list(pairs)
    if pairs:
        lines += [
            "",
            "| pair (stereoCalibrate, intrinsics fixed) | views | RMS px | baseline mm "
            "| rotation deg |",
            "| --- | --- | --- | --- | --- |",
        ]
        for p in pairs:
            lines.append(
                f"| {p.a} -> {p.b} | {p.views} | {p.rms_px:.3f} | {p.baseline_m * 1000:.2f} | "
                f"{p.rotation_deg:.3f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "names", nargs="*", help=f"sets to measure (default all: {list(REAL_SETS)})"
    )
    parser.add_argument("--root", type=Path, help="measure the (single) set from this directory")
    args = parser.parse_args(argv)
    known = REAL_SETS | UNCOMMITTED_SETS
    names = args.names or list(REAL_SETS)
    unknown = [n for n in names if n not in known]
    if unknown or (args.root and len(names) != 1):
        print(
            f"expected set names from {list(known)} (one with --root), got {names}",
            file=sys.stderr,
        )
        return 2
    for n in names:
        rs = known[n]
        if n in UNCOMMITTED_SETS and not args.root:
            print(f"{n} is not in tests/data (no licence): give --root DIR", file=sys.stderr)
            return 2
        m = measure(rs, args.root)
        print(f"## {n}: {rs.board.describe() if isinstance(rs.board, Checkerboard) else rs.board}")
        print(reference_table(m.sensors, m.pairs))
        for key, value in rs.published.items():
            print(f"published {key} = {value:.6g}")
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
