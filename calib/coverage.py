"""How well a sensor's image has been covered by checkerboard views.

Two complementary measures, both computed from detected corners only (pure numpy):

* **ROS-style bars** (after ROS ``camera_calibration``'s ``get_parameters`` and
  ``compute_goodenough``; re-derived here, not copied). Every detection is summarised by four
  numbers in [0, 1] (``view_params``):

  - ``X``: horizontal position of the board. The image is shrunk on every side by half the
    board's apparent size ``b = sqrt(area)``, so that a board touching the left edge gives
    about 0 and one touching the right edge about 1, whatever its size:
    ``X = clip((mean(u) - b / 2) / (W - b), 0, 1)``.
  - ``Y``: the same vertically, ``Y = clip((mean(v) - b / 2) / (H - b), 0, 1)``.
  - ``size``: ``sqrt(area / (W * H))``, the side of a square of the board's image area as a
    fraction of the image (1 = the board fills the image).
  - ``skew``: ``min(1, 2 * |90 deg - angle|)`` (angle in radians) where ``angle`` is the
    image angle at the board's top-right outer corner between the top row and the right
    column. 0 for a board seen square-on; it grows with tilt (perspective and foreshortening
    make the board's image a non-rectangular quadrilateral).

  ``area`` is the area of the quadrilateral of the four outer corners (first and last corner
  of the first and last row, in canonical board order, see ``calib.board``).

  The **progress** of each bar is how much of a target spread has been seen
  (``PARAM_RANGES`` = 0.7, 0.7, 0.4, 0.5 as in ROS): ``X`` and ``Y`` progress is
  ``(max - min) / range``; ``size`` and ``skew`` progress is ``max / range`` (small boards
  and square-on views are not rewarded: their lower end counts as 0), each clipped to 1.
  The coverage is ``good_enough`` when all four bars are full. (ROS also accepts any set
  of 40 or more samples; we do not, as many similar views do not make coverage.)

* **A region map**: the image is cut into a grid (default 6 rows x 8 columns) and every
  corner of every view is counted in the cell it falls in. Cells never reached are what an
  operator has to fill next; ``empty_regions`` names them (see ``Coverage``).

Pixel convention (docs/CONVENTIONS.md): the centre of the top-left pixel is (0, 0), a
W x H image spans ``[-0.5, W - 0.5) x [-0.5, H - 0.5)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from trifuse.calib.board import Board
from trifuse.calib.numbers import is_integer

PARAM_NAMES = ("X", "Y", "size", "skew")
PARAM_RANGES = (0.7, 0.7, 0.4, 0.5)
"""Spread of each parameter that fills its bar (ROS ``param_ranges``)."""

NOVELTY_THRESHOLD = 0.2
"""ROS's default: a view is worth keeping when its ``pose_novelty`` exceeds this."""

COARSE_NAMES = (
    ("top-left corner", "top edge", "top-right corner"),
    ("left edge", "centre", "right edge"),
    ("bottom-left corner", "bottom edge", "bottom-right corner"),
)
"""Names of the 3 x 3 coarse regions, indexed [row][col]."""

WHOLE_IMAGE = "the whole image"


@dataclass
class Coverage:
    """Coverage of one sensor's image by a set of board detections.

    Attributes:
        x, y, size, skew: progress of each ROS bar in [0, 1] (1 = enough spread seen).
        x_range, y_range, size_range, skew_range: (min, max) of that parameter over the
            views (the raw ``view_params``; NaN, NaN when there are no views).
        grid_shape: (rows, cols) of the region grid.
        corner_counts: (rows, cols) int array, corners of all views seen in each cell.
        empty_regions: cells never seen, named for an operator. A coarse 3 x 3 region
            (``COARSE_NAMES``: "top-left corner", "top edge", ..., "centre", ...) whose
            cells are all empty is named as a whole; empty cells of a partly covered
            coarse region are listed one by one as ``"row r, col c (top edge)"`` (0-based,
            row 0 at the top). ``["the whole image"]`` when nothing was seen; ``[]`` when
            every cell was reached. A cell belongs to the coarse region that holds its
            centre.
        good_enough: all four bars are full (ROS's criterion).
        n_views: number of views counted.
    """

    x: float
    y: float
    size: float
    skew: float
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    size_range: tuple[float, float]
    skew_range: tuple[float, float]
    grid_shape: tuple[int, int]
    corner_counts: np.ndarray
    empty_regions: list[str]
    good_enough: bool
    n_views: int = 0

    @property
    def progress(self) -> tuple[float, float, float, float]:
        """(x, y, size, skew) bars, in ``PARAM_NAMES`` order."""
        return (self.x, self.y, self.size, self.skew)

    @property
    def reached(self) -> float:
        """Fraction of the region grid's cells with at least one corner, in [0, 1]."""
        return reached_fraction(self.corner_counts)


# -- one view --------------------------------------------------------------------------------


def _check_image_size(image_size: Sequence[int]) -> tuple[int, int]:
    try:
        w, h = image_size
    except (TypeError, ValueError):
        raise ValueError(
            f"image_size: expected (width, height) in pixels, got {image_size!r}"
        ) from None
    for name, v in (("width", w), ("height", h)):
        if not is_integer(v) or v < 1:
            raise ValueError(f"image_size {name}: expected a positive integer, got {v!r}")
    return int(w), int(h)


def _check_corners(corners: npt.ArrayLike, board: Board, where: str = "corners") -> np.ndarray:
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (board.n_corners, 2):
        raise ValueError(
            f"{where}: expected shape ({board.n_corners}, 2) for a {board.cols}x{board.rows} "
            f"board (all corners, canonical order), got {c.shape}"
        )
    seen = np.isfinite(c).all(axis=1)
    if np.isinf(c).any() or not (seen.all() or (board.partial_views and seen.sum() >= 4)):
        raise ValueError(f"{where}: contains NaN or infinity")  # a partial view: NaN rows
    return c


def _outer_corners(c: np.ndarray, board: Board) -> tuple[np.ndarray, ...]:
    """(up_left, up_right, down_right, down_left) outer corners in canonical board order;
    of a partial view (NaN rows), the corners seen that are outermost that way."""
    cols = board.cols
    if np.isfinite(c).all():
        return c[0], c[cols - 1], c[-1], c[-cols]
    i = np.flatnonzero(np.isfinite(c).all(axis=1))
    u, v = i % cols, i // cols
    return tuple(c[i[np.argmax(k)]] for k in (-u - v, u - v, u + v, v - u))


def _quad_area(ul: np.ndarray, ur: np.ndarray, dr: np.ndarray, dl: np.ndarray) -> float:
    """Area of a quadrilateral, half the cross product of its diagonals (pixels^2)."""
    d1 = dr - ul
    d2 = dl - ur
    return abs(float(d1[0] * d2[1] - d1[1] * d2[0])) / 2.0


def _skew(ul: np.ndarray, ur: np.ndarray, dr: np.ndarray) -> float:
    a = ul - ur
    b = dr - ur
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if na == 0.0 or nb == 0.0:
        return 1.0  # degenerate detection: as skewed as it gets
    cos = float(np.clip(a @ b / (na * nb), -1.0, 1.0))
    return min(1.0, 2.0 * abs(math.pi / 2.0 - math.acos(cos)))


def view_params(
    corners: npt.ArrayLike, board: Board, image_size: Sequence[int]
) -> tuple[float, float, float, float]:
    """(X, Y, size, skew) of one detection, each in [0, 1] (module docstring).

    Args:
        corners: (N, 2) pixels, all ``board.n_corners`` corners in canonical board order
            (a board with ``partial_views``: NaN rows for corners not seen, at least 4 seen).
        board: the checkerboard.
        image_size: (width, height) of the image in pixels.

    Raises:
        ValueError: wrong corner array shape, NaN corners (but a partial view's), or a bad
            image size.
    """
    w, h = _check_image_size(image_size)
    c = _check_corners(corners, board)
    ul, ur, dr, dl = _outer_corners(c, board)
    area = _quad_area(ul, ur, dr, dl)
    border = math.sqrt(area)

    def position(mean: float, extent: int) -> float:
        span = extent - border
        if span <= 0.0:  # the board is as large as the image: no room to move
            return 0.5
        return min(1.0, max(0.0, (mean - border / 2.0) / span))

    x = position(float(np.nanmean(c[:, 0])), w)
    y = position(float(np.nanmean(c[:, 1])), h)
    size = math.sqrt(area / (w * h))
    return (x, y, size, _skew(ul, ur, dr))


def pose_novelty(params: Sequence[float], previous_params: Sequence[Sequence[float]]) -> float:
    """How different a view is from those kept so far (ROS ``is_good_sample``).

    The smallest L1 distance ``sum(|p_i - q_i|)`` between ``params`` (X, Y, size, skew)
    and any of ``previous_params``; ``inf`` when there is none. ROS keeps a view when this
    exceeds ``NOVELTY_THRESHOLD`` (0.2). Identical views give 0.
    """
    p = np.asarray(params, dtype=np.float64)
    if p.shape != (4,):
        raise ValueError(f"params: expected (X, Y, size, skew), got shape {p.shape}")
    prev = np.asarray(previous_params, dtype=np.float64)
    if prev.size == 0:
        return math.inf
    if prev.ndim != 2 or prev.shape[1] != 4:
        raise ValueError(
            f"previous_params: expected a sequence of (X, Y, size, skew), got shape {prev.shape}"
        )
    return float(np.min(np.sum(np.abs(prev - p), axis=1)))


# -- a set of views --------------------------------------------------------------------------


def _check_grid_shape(grid_shape: Sequence[int]) -> tuple[int, int]:
    try:
        rows, cols = grid_shape
    except (TypeError, ValueError):
        raise ValueError(f"grid_shape: expected (rows, cols), got {grid_shape!r}") from None
    for name, v in (("rows", rows), ("cols", cols)):
        if not is_integer(v) or v < 1:
            raise ValueError(f"grid_shape {name}: expected a positive integer, got {v!r}")
    return int(rows), int(cols)


def _cells(points: np.ndarray, image_size: tuple[int, int], grid: tuple[int, int]) -> np.ndarray:
    """(rows, cols) counts of the points that lie inside the image."""
    w, h = image_size
    rows, cols = grid
    counts = np.zeros(grid, dtype=np.int64)
    if len(points) == 0:
        return counts
    fx = (points[:, 0] + 0.5) / w  # 0..1 across the image (pixel edges, not centres)
    fy = (points[:, 1] + 0.5) / h
    inside = (fx >= 0.0) & (fx < 1.0) & (fy >= 0.0) & (fy < 1.0)
    ci = np.minimum((fx[inside] * cols).astype(np.int64), cols - 1)
    ri = np.minimum((fy[inside] * rows).astype(np.int64), rows - 1)
    np.add.at(counts, (ri, ci), 1)
    return counts


def _coarse_index(i: int, n: int) -> int:
    """Which third (0, 1, 2) holds the centre of cell ``i`` of ``n``."""
    return min(2, int(3 * (i + 0.5) / n))


def name_empty_regions(corner_counts: np.ndarray) -> list[str]:
    """Operator-readable names of the cells of ``corner_counts`` that are zero.

    See ``Coverage.empty_regions`` for the rule. Coarse regions come in reading order
    (top-left first), then the single cells, row by row.
    """
    counts = np.asarray(corner_counts)
    if counts.ndim != 2:
        raise ValueError(f"corner_counts: expected a 2-D array, got shape {counts.shape}")
    rows, cols = counts.shape
    empty = counts == 0
    if empty.all():
        return [WHOLE_IMAGE]
    cr = [_coarse_index(r, rows) for r in range(rows)]
    cc = [_coarse_index(c, cols) for c in range(cols)]
    names: list[str] = []
    whole: set[tuple[int, int]] = set()
    for R in range(3):
        for C in range(3):
            cells = [(r, c) for r in range(rows) for c in range(cols) if cr[r] == R and cc[c] == C]
            if cells and all(empty[r, c] for r, c in cells):
                whole.add((R, C))
                names.append(COARSE_NAMES[R][C])
    for r in range(rows):
        for c in range(cols):
            if empty[r, c] and (cr[r], cc[c]) not in whole:
                names.append(f"row {r}, col {c} ({COARSE_NAMES[cr[r]][cc[c]]})")
    return names


def reached_fraction(corner_counts: np.ndarray) -> float:
    """Fraction of the cells of ``corner_counts`` (rows, cols) holding a corner, in [0, 1]."""
    counts = np.asarray(corner_counts)
    if counts.ndim != 2 or counts.size == 0:
        raise ValueError(f"corner_counts: expected a non-empty 2-D array, got shape {counts.shape}")
    return float(np.count_nonzero(counts) / counts.size)


def coarse_reached(corner_counts: np.ndarray) -> np.ndarray:
    """(3, 3) fraction of each coarse region's cells holding a corner (``COARSE_NAMES``
    order; a cell belongs to the region that holds its centre). NaN for a region without
    cells (a grid with fewer than 3 rows or columns)."""
    counts = np.asarray(corner_counts)
    if counts.ndim != 2 or counts.size == 0:
        raise ValueError(f"corner_counts: expected a non-empty 2-D array, got shape {counts.shape}")
    rows, cols = counts.shape
    cr = np.array([_coarse_index(r, rows) for r in range(rows)])
    cc = np.array([_coarse_index(c, cols) for c in range(cols)])
    region = 3 * cr[:, None] + cc[None, :]  # (rows, cols) -> 0..8
    cells = np.bincount(region.ravel(), minlength=9).astype(np.float64)
    seen = np.bincount(region.ravel(), weights=(counts > 0).ravel(), minlength=9)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (seen / np.where(cells > 0, cells, np.nan)).reshape(3, 3)


def coverage(
    corner_sets: Sequence[npt.ArrayLike],
    board: Board,
    image_size: Sequence[int],
    grid_shape: Sequence[int] = (6, 8),
) -> Coverage:
    """Coverage of one sensor's image by the detections ``corner_sets``.

    Args:
        corner_sets: one (N, 2) array per view, all ``board.n_corners`` corners in canonical
            order (pixels). May be empty.
        board: the checkerboard.
        image_size: (width, height) of the sensor's image in pixels.
        grid_shape: (rows, cols) of the region grid.

    Returns:
        A ``Coverage`` (bars, ranges, region counts and names, ``good_enough``).

    Raises:
        ValueError: a corner array of the wrong shape or with NaN, a bad image size or grid.
    """
    size = _check_image_size(image_size)
    grid = _check_grid_shape(grid_shape)
    checked = [_check_corners(c, board, f"corner_sets[{i}]") for i, c in enumerate(corner_sets)]
    params = np.array([view_params(c, board, size) for c in checked], dtype=np.float64)
    if len(checked):
        points = np.concatenate(checked)
        counts = _cells(points[np.isfinite(points).all(axis=1)], size, grid)
        lo, hi = params.min(axis=0), params.max(axis=0)
        # Don't reward small boards or square-on views: their spread starts at 0.
        base = np.array([lo[0], lo[1], 0.0, 0.0])
        progress = np.minimum((hi - base) / np.asarray(PARAM_RANGES), 1.0)
        ranges = [(float(a), float(b)) for a, b in zip(lo, hi, strict=True)]
    else:
        counts = np.zeros(grid, dtype=np.int64)
        progress = np.zeros(4)
        ranges = [(math.nan, math.nan)] * 4
    return Coverage(
        x=float(progress[0]),
        y=float(progress[1]),
        size=float(progress[2]),
        skew=float(progress[3]),
        x_range=ranges[0],
        y_range=ranges[1],
        size_range=ranges[2],
        skew_range=ranges[3],
        grid_shape=grid,
        corner_counts=counts,
        empty_regions=name_empty_regions(counts),
        good_enough=bool(np.all(progress >= 1.0)),
        n_views=len(checked),
    )
