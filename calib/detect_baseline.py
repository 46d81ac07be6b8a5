"""The plain OpenCV pipeline for thermal and colour boards: the baseline of calib.detect.

What a careful user would write with OpenCV alone (issue 15): subtract a Gaussian blur
with sigma ``FLATTEN_SIGMA_PX`` (25 px), stretch the ``STRETCH_PERCENTILES`` (1 and
99.5) to 8 bit, then for each polarity (as is, inverted) the classic detector
(``findChessboardCorners``, OpenCV's default flags ADAPTIVE_THRESH | NORMALIZE_IMAGE)
and then the sector-based one (``findChessboardCornersSB``, no flags). The first grid
found is returned with the corners as that detector gives them (the classic detector's
own small sub-pixel pass, no further refinement).

Only the corner order is normalised exactly as :func:`calib.detect.detect_board` does
(:func:`calib.detect_order.canonical_order`: handedness, then the square colours' vote, never a
rejection), so that the corners compare with the truth corner for corner. Pure: arrays
in, a :class:`~calib.detect.Detection` out.
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.detect import (
    THERMAL_BLACK_IS_HOT,
    Detection,
    _check_board,
    _check_image,
)
from trifuse.calib.detect_order import canonical_order
from trifuse.calib.detect_prepare import finite_filled

FLATTEN_SIGMA_PX = 25.0
"""Sigma of the Gaussian blur subtracted from the image, pixels."""
STRETCH_PERCENTILES = (1.0, 99.5)
"""Percentiles of the flattened image mapped to 0 and 255."""
MODALITIES = ("color", "thermal")


def _stretch(x: np.ndarray) -> np.ndarray | None:
    lo, hi = np.percentile(x, STRETCH_PERCENTILES)
    if not hi - lo > 1e-6 * max(1.0, abs(float(hi)), abs(float(lo))):
        return None
    return np.clip((x - lo) * (255.0 / (hi - lo)) + 0.5, 0, 255).astype(np.uint8)


def detect_board_baseline(
    image: np.ndarray,
    board: Board,
    modality: str,
    *,
    thermal_black_is_hot: bool = THERMAL_BLACK_IS_HOT,
) -> Detection:
    """Find the board with the plain OpenCV pipeline (module docstring).

    Args:
        image: colour (H, W, 3) uint8 RGB or (H, W) uint8 grey; thermal (H, W) kelvin or
            counts, any real dtype, NaN = no reading.
        board: the checkerboard.
        modality: ``"color"`` or ``"thermal"``.
        thermal_black_is_hot: the board's thermal polarity (orders the corners only).

    Returns:
        A Detection: corners (N, 2) float64 pixels in canonical order, or None and the
        reason; ``method`` names the detector and polarity, e.g. ``"classic-inverted"``.
    """
    if modality not in MODALITIES:
        raise ValueError(f"modality: expected one of {', '.join(MODALITIES)}, got {modality!r}")
    _check_board(board)
    img = _check_image(image, modality)
    if modality == "color":
        grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        x = grey.astype(np.float32)
    else:
        filled = finite_filled(img)
        if filled is None:
            return Detection(None, "board not found: the image has no finite pixels", None)
        x = filled
    flat = x - cv2.GaussianBlur(x, (0, 0), FLATTEN_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
    u8 = _stretch(flat)
    if u8 is None:
        return Detection(None, "board not found: the image has no contrast", None)
    darkness = flat if (modality == "color" or not thermal_black_is_hot) else -flat
    for inverted in (False, True):
        det = 255 - u8 if inverted else u8
        suffix = "-inverted" if inverted else ""
        ok, raw = cv2.findChessboardCorners(det, board.pattern_size)
        method = "classic" + suffix
        if not ok:
            ok, raw = cv2.findChessboardCornersSB(det, board.pattern_size, flags=0)
            method = "sb" + suffix
        if ok and raw is not None and np.all(np.isfinite(raw)):
            corners, _agreement, _separation = canonical_order(raw, board, darkness)
            return Detection(corners, None, method)
    return Detection(
        None, f"board ({board.cols}x{board.rows} inner corners) not found (plain pipeline)", None
    )
