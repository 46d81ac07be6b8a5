"""A detected grid's square colours (:mod:`calib.detect`): the board's canonical order
they decide, and whether the squares around the grid continue the checkerboard.

Grids are (rows, cols, 2) pixels; ``darkness`` is an (H, W) float32 image in which the
board's black squares are low. The canonical order and its two steps (handedness, square
colours) are described in calib.detect's module docstring. Pure.
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.detect_grid import extended

RING_WRONG_FRACTION = 1 / 3
"""Pyramid levels: a side of the grid is wrong when at least this fraction (and at least 2)
of the squares just outside it, in view, read as the other colour class than the
checkerboard demands (:func:`ring_problem`)."""


def _right_handed(G: np.ndarray) -> bool:
    """Whether the grid's +x (along a row) and +y (down a column) are right-handed in the
    image (x right, y down), judged from the mean row and column directions."""
    ax = (G[:, -1] - G[:, 0]).mean(axis=0)
    ay = (G[-1, :] - G[0, :]).mean(axis=0)
    return float(ax[0] * ay[1] - ax[1] * ay[0]) > 0


def _sample(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at points (..., 2)."""
    flat = np.ascontiguousarray(pts.reshape(-1, 1, 2), dtype=np.float32)
    out = cv2.remap(
        img, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return out.reshape(pts.shape[:-1]).astype(np.float64)


def _square_values(darkness: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Mean of ``darkness`` inside each interior square, (rows - 1, cols - 1): samples at
    the square's centre (mean of its 4 corners) and 30% of the way to each corner."""
    quad = np.stack([G[:-1, :-1], G[:-1, 1:], G[1:, :-1], G[1:, 1:]], axis=0)
    centre = quad.mean(axis=0)
    pts = np.concatenate([centre[None], centre[None] + 0.3 * (quad - centre[None])], axis=0)
    return _sample(darkness, pts).mean(axis=0)


def _colour_order(darkness: np.ndarray, G: np.ndarray) -> tuple[bool, float, float]:
    """Whether the (r + c)-even interior squares are the dark ones, with the agreement
    (fraction of neighbouring square pairs voting that way) and the separation
    (|mean| / std of the neighbour differences)."""
    v = _square_values(darkness, G)
    r, c = np.indices(v.shape)
    sign = np.where((r + c) % 2 == 0, 1.0, -1.0)
    # Odd minus even over horizontal and vertical neighbour pairs: > 0 where the even
    # square is the darker one.
    d = np.concatenate(
        [
            ((v[:, 1:] - v[:, :-1]) * sign[:, :-1]).ravel(),
            ((v[1:, :] - v[:-1, :]) * sign[:-1, :]).ravel(),
        ]
    )
    # Ties (both squares clipped, e.g. by glare) vote for neither ordering.
    even_dark, odd_dark = float(np.mean(d > 0)), float(np.mean(d < 0))
    even_is_dark = even_dark >= odd_dark
    agreement = max(even_dark, odd_dark)
    spread = float(np.std(d))
    separation = abs(float(np.mean(d))) / spread if spread > 0 else float("inf")
    return even_is_dark, agreement, separation


def canonical_order(
    corners: np.ndarray, board: Board, darkness: np.ndarray
) -> tuple[np.ndarray, float, float]:
    """Put a detector's corners into the board's canonical order, without any rejection.

    Args:
        corners: (N, 2) or (N, 1, 2) pixels in any of the detectors' orderings.
        board: the checkerboard (``cols x rows`` inner corners).
        darkness: (H, W) float32 image in which the black squares are low.

    Returns:
        The corners (N, 2) float64 in canonical order (handedness, then the square
        colours' vote), the colour agreement and the separation (see
        :data:`calib.detect.COLOUR_AGREEMENT`, :data:`calib.detect.COLOUR_MIN_SEPARATION`),
        for a caller to judge.
    """
    G = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    G, agreement, separation = orient(G, board, darkness)
    return np.ascontiguousarray(G.reshape(-1, 2)), agreement, separation


def orient(G: np.ndarray, board: Board, darkness: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The grid ``G`` (rows, cols, 2) made right-handed, then (boards with one ordering)
    turned half round if the square colours say so; with the colours' agreement and
    separation. On a board that looks the same turned (``board.orderings`` > 1) the colours
    cannot tell its orderings apart, so the grid keeps the detector's ordering."""
    if not _right_handed(G):
        G = G[::-1]
    even_is_dark, agreement, separation = _colour_order(darkness, G)
    if board.orderings == 1 and not even_is_dark:
        G = G[::-1, ::-1]
    return G, agreement, separation


def ring_problem(darkness: np.ndarray, G: np.ndarray) -> str | None:
    """Why the grid ``G`` (rows, cols, 2, pixels of ``darkness``, (H, W) with the board's
    black squares low) is not the board's inner corners, judged by the squares around it.

    Every inner corner has squares on all four sides, so the ring of squares just outside
    the grid (extrapolated by one spacing) continues the checkerboard. A grid shifted by
    one row onto the board's margin has a side whose ring squares all show the margin (2
    of 47 views of tests/data/czha626-thermal-visible at 1000 px: a white frame brighter
    than the light squares, so the detectors took its edge for a row of corners). Each
    ring square in view is classed against the mean of the two interior colour classes;
    a side is wrong when at least ``RING_WRONG_FRACTION`` (and at least 2) of its squares
    in view read as the other class. Measured on those views (0 = the dark class's mean,
    1 = the light one's): ring squares of correct grids at most 0.23 away from their
    class, the margin's 1.8-1.9."""
    rows, cols = G.shape[:2]
    E = extended(G)
    v = _square_values(darkness, E)  # (rows + 1, cols + 1); ring: first/last row/column
    i, j = np.indices(v.shape)
    even = (i + j) % 2 == 0
    inner = (i > 0) & (i < rows) & (j > 0) & (j < cols)
    if not (inner & even).any() or not (inner & ~even).any():
        return None
    m_even, m_odd = float(v[inner & even].mean()), float(v[inner & ~even].mean())
    wrong = (v < 0.5 * (m_even + m_odd)) != (even == (m_even < m_odd))
    h, w = darkness.shape
    quads = np.stack([E[:-1, :-1], E[:-1, 1:], E[1:, :-1], E[1:, 1:]])
    in_view = np.all(
        (quads[..., 0] >= -0.5)
        & (quads[..., 0] <= w - 0.5)
        & (quads[..., 1] >= -0.5)
        & (quads[..., 1] <= h - 0.5),
        axis=0,
    )
    sides = {"top": i == 0, "bottom": i == rows, "left": j == 0, "right": j == cols}
    for side, on_side in sides.items():
        n = int((on_side & in_view).sum())
        k = int((on_side & in_view & wrong).sum())
        if k >= 2 and k >= RING_WRONG_FRACTION * n:
            return (
                f"the squares beyond the grid's {side} side do not continue the checkerboard "
                f"({k} of {n} in view have the wrong colour): the grid is shifted onto the "
                "board's margin"
            )
    return None
