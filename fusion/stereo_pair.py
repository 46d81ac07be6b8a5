"""The stereo pair of display pictures: :func:`side_by_side` (left | right),
:func:`stereo_halves` (compose each eye straight into its half of a side-by-side buffer),
:func:`anaglyph` (red-cyan). Images are (H, W, 3) uint8 RGB.
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.fusion.compose import describe_array as _describe


def _check_pair(left: np.ndarray, right: np.ndarray) -> tuple[int, int]:
    for name, a in (("left", left), ("right", right)):
        if not isinstance(a, np.ndarray) or a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"{name}: expected a uint8 (H, W, 3) image, got {_describe(a)}")
    if left.shape != right.shape:
        raise ValueError(f"right: expected the shape of left {left.shape}, got {right.shape}")
    return left.shape[0], left.shape[1]


def stereo_halves(sbs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The left and right (H, W, 3) views of a side-by-side (H, 2W, 3) buffer, to compose
    each eye straight into its half (``Composer.compose(..., out=half)``)."""
    if not isinstance(sbs, np.ndarray) or sbs.dtype != np.uint8 or sbs.ndim != 3:
        raise ValueError(f"sbs: expected a uint8 (H, 2W, 3) image, got {_describe(sbs)}")
    if sbs.shape[2] != 3 or sbs.shape[1] % 2:
        raise ValueError(f"sbs: expected shape (H, 2W, 3) with an even width, got {sbs.shape}")
    w = sbs.shape[1] // 2
    return sbs[:, :w], sbs[:, w:]


def side_by_side(left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The stereo pair side by side, left | right: (H, 2W, 3) uint8.

    Args:
        left, right: (H, W, 3) uint8 of the same shape.
        out: (H, 2W, 3) uint8 buffer; allocated if None (pass one per frame).
    """
    h, w = _check_pair(left, right)
    if out is None:
        out = np.empty((h, 2 * w, 3), np.uint8)
    elif not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (h, 2 * w, 3):
        raise ValueError(f"out: expected uint8 ({h}, {2 * w}, 3), got {_describe(out)}")
    lo, ro = stereo_halves(out)
    np.copyto(lo, left)
    np.copyto(ro, right)
    return out


def anaglyph(
    left: np.ndarray, right: np.ndarray, out: np.ndarray | None = None, method: str = "color"
) -> np.ndarray:
    """Red-cyan anaglyph of the pair: (H, W, 3) uint8 RGB (red lens on the left eye).

    Args:
        left, right: (H, W, 3) uint8 RGB of the same shape.
        out: (H, W, 3) uint8 buffer; allocated if None; must not overlap the inputs.
        method: ``"color"``: red from the left image, green and blue from the right;
            ``"grey"``: red = the left's luminance, green = blue = the right's (less
            retinal rivalry, no colour; allocates two grey images).
    """
    h, w = _check_pair(left, right)
    if out is None:
        out = np.empty((h, w, 3), np.uint8)
    elif not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (h, w, 3):
        raise ValueError(f"out: expected uint8 ({h}, {w}, 3), got {_describe(out)}")
    if np.may_share_memory(out, left) or np.may_share_memory(out, right):
        raise ValueError("out: must not overlap left or right")
    if method == "color":
        cv2.mixChannels([left, right], [out], [0, 0, 4, 1, 5, 2])
    elif method == "grey":
        gl = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
        gr = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
        cv2.mixChannels([gl, gr], [out], [0, 0, 1, 1, 1, 2])
    else:
        raise ValueError(f"method: expected 'color' or 'grey', got {method!r}")
    return out
