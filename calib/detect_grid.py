"""The geometry of a detector's grid of corners and its sub-pixel refinement
(:mod:`calib.detect`).

Grids are (rows, cols, 2) pixels. Spacing, regularity and bend of a grid; the refinements
of a detector's corners, best first (:func:`refined`): the fine stage (the accurate
sector-based detector again in an upsampled crop, thermal and TOF), ``cornerSubPix`` with a
half-window from the corner spacing (again at full size for a pyramid level), and the
fallbacks (a narrow window, the corners as detected, stray corners repaired). Pure.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.detect_prepare import COLOR_REFINE_BLUR_PX, Prepared, stretch_u8, upsample_image

FINE_TARGET_SPACING_PX = 48.0
"""Thermal and TOF: after the first detection the board is found again with the accurate
sector-based detector (CALIB_CB_ACCURACY) in a crop upsampled so that the corner spacing
is about this many pixels: by the whole factor (1 to ``FINE_MAX_UPSAMPLE``) that rounds
target / spacing up and, when it differs, by the nearest one; of the grids found the
smoother is kept (:func:`_roughness`). Measured on the simulator the fine stage beats
cornerSubPix: thermal 0.062 -> 0.034 px, TOF 0.26 -> 0.054 px mean RMS. Why two factors:
real LWIR squares of about 44 px (tests/data/czha626-thermal-visible, blurred 8-bit JPEG)
doubled calibrated at RMS 0.769 / 0.619 px (12 / 47 views; Img29 not found at 2x, its
cornerSubPix fallback 2 px off) against OpenCV's plain SB corners' 0.445 / 0.457 px, at
their own size at 0.443 / 0.458 px; sharp 16-bit LWIR views (VimsLab, not committed:
BENCHMARKS.md) the other way round: 0.198 / 0.231 px doubled, 0.228 / 0.269 px at their
own size. With the choice: 0.444 / 0.460 px and 0.198 / 0.234 px; on the simulated
thermal conditions (seed 0) one row moved, partial-view 0.030 -> 0.033 px mean."""
FINE_MAX_UPSAMPLE = 4
FINE_MARGIN = 1.6
"""Crop margin around the outer corners, in corner spacings (the outer squares and a bit
of the board's margin must be inside)."""
FINE_HIGHPASS_SIGMA = 0.5
"""Blur (x the corner spacing) subtracted from the crop when the fine stage fails on the
crop as it is: it keeps 1 - exp(-pi^2 0.5^2) = 92 % of the squares' pattern and removes
shading across the board. On the faint boards of the thermal-detect conditions (seeds 0-2,
BENCHMARKS.md, issue 15) the accurate detector then found 11-12 of 14 boards it had missed
(0.6 x: 8, 0.7 x: 6); corners 0.4-0.5 px -> about 0.05-0.1 px from the truth."""
FINE_CHECK_ABOVE_PX = 500_000
"""Fine stage: on an upsampled crop of more pixels than this, the sector-based detector
runs first without CALIB_CB_ACCURACY (a quarter of the time), and with it only where that
finds the board. Measured on every ACCURACY call of the real thermal sets and the simulated
thermal conditions (seeds 0-1, every other view): where the plain detector failed the
accurate one failed too, except on 3 crops of 0.1-0.4 Mpx (harunrk's Lepton, 2; the
simulator, 1); on VimsLab's
16-bit LWIR crops (0.6-1.2 Mpx at 3-4 x) it fails on the crop as it is and the high-passed
one before CALIB_CB_EXHAUSTIVE finds the board, 0.3-0.7 s a call."""
FINE_MAX_SHIFT = 0.25
"""The fine corners must lie within this fraction of the spacing of the first ones (median
over the corners, :func:`_same_grid`)."""

SUBPIX_WINDOW_FRACTION = 0.4
"""cornerSubPix half-window as a fraction of the smallest corner spacing: a window wider
than half the spacing converges to a neighbouring corner (FIELD-NOTES)."""
SUBPIX_HALF_WINDOW_PX = (2, 11)
NARROW_WINDOW_FRACTION = 0.1
"""Half-window of the second cornerSubPix, over the corner spacing, tried when the first
(``SUBPIX_WINDOW_FRACTION``) leaves a bent grid (:func:`refined`)."""
STRAY_FRACTION = 0.25
"""A detected corner this far (over the corner spacing) from a homography fitted to the
others is put back on it before a last refinement (:func:`_repaired`)."""
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


def grid_spacing(raw: np.ndarray, board: Board, shape: tuple[int, ...]) -> float | None:
    """The median corner spacing (pixels) of a detector's corners (any shape holding
    N x 2), or None unless they are the board's, finite and inside an image of ``shape``
    (H, W). The median: the classic detector's corners can be a few pixels astray before
    refinement."""
    pts = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    if len(pts) != board.n_corners or not np.all(np.isfinite(pts)):
        return None
    if np.any(pts < 0) or np.any(pts[:, 0] > shape[1] - 1) or np.any(pts[:, 1] > shape[0] - 1):
        return None
    return float(np.median(corner_spacing(pts.reshape(board.rows, board.cols, 2))))


def corner_spacing(G: np.ndarray) -> np.ndarray:
    """Per-corner local spacing (rows, cols): mean distance to its grid neighbours."""
    dx = np.linalg.norm(np.diff(G, axis=1), axis=2)  # (rows, cols - 1)
    dy = np.linalg.norm(np.diff(G, axis=0), axis=2)  # (rows - 1, cols)
    total = np.zeros(G.shape[:2])
    count = np.zeros(G.shape[:2])
    total[:, :-1] += dx
    total[:, 1:] += dx
    count[:, :-1] += 1
    count[:, 1:] += 1
    total[:-1, :] += dy
    total[1:, :] += dy
    count[:-1, :] += 1
    count[1:, :] += 1
    return total / count


def _min_spacing(G: np.ndarray) -> float:
    dx = np.linalg.norm(np.diff(G, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(G, axis=0), axis=2)
    return float(min(dx.min(), dy.min()))


def regular(G: np.ndarray) -> bool:
    """Every step along a row (column) points the way of the grid's mean row (column) step."""
    sx = np.diff(G, axis=1)
    sy = np.diff(G, axis=0)
    mx = sx.reshape(-1, 2).mean(axis=0)
    my = sy.reshape(-1, 2).mean(axis=0)
    return bool(np.all(sx @ mx > 0) and np.all(sy @ my > 0) and _min_spacing(G) > 0.5)


def _subpix(img: np.ndarray, G: np.ndarray, wide_first: bool = False) -> np.ndarray:
    """cornerSubPix with the half-window from the corner spacing (pixels of ``img``).

    ``wide_first``: start with one pass at 0.45 x the spacing (unclamped) for corners that
    may be several pixels off (the classic detector's, on tilted boards: up to 12 px
    measured), so that the clamped window then starts near the corner.
    """
    lo, hi = SUBPIX_HALF_WINDOW_PX
    pts = np.ascontiguousarray(G.reshape(-1, 1, 2), dtype=np.float32)
    spacing = _min_spacing(G)
    if wide_first:
        hw = max(lo, round(0.45 * spacing))
        cv2.cornerSubPix(img, pts, (hw, hw), (-1, -1), SUBPIX_CRITERIA)
    hw = int(np.clip(round(SUBPIX_WINDOW_FRACTION * spacing), lo, hi))
    cv2.cornerSubPix(img, pts, (hw, hw), (-1, -1), SUBPIX_CRITERIA)
    return pts.reshape(G.shape).astype(np.float64)


def _subpix_full(lin: np.ndarray, G: np.ndarray) -> np.ndarray:
    """The grid ``G`` (rows, cols, 2, original pixels, from a pyramid level) refined at the
    original size: :func:`_subpix` in a crop of ``lin`` (the linearised grey, (H, W)
    float32) around the grid, blurred as :func:`calib.detect_prepare.prepare` blurs its
    refine image. The half-window follows from the spacing at this size (0.4 x, clamped to
    2-11 px), not from the level's: scaling the level's window up would span a whole square
    (FIELD-NOTES)."""
    h, w = lin.shape
    margin = SUBPIX_HALF_WINDOW_PX[1] + 4 * COLOR_REFINE_BLUR_PX + 2
    x0 = max(0, int(np.floor(G[..., 0].min() - margin)))
    x1 = min(w, int(np.ceil(G[..., 0].max() + margin)) + 1)
    y0 = max(0, int(np.floor(G[..., 1].min() - margin)))
    y1 = min(h, int(np.ceil(G[..., 1].max() + margin)) + 1)
    crop = cv2.GaussianBlur(lin[y0:y1, x0:x1], (0, 0), COLOR_REFINE_BLUR_PX)
    offset = np.array([x0, y0], dtype=np.float64)
    return _subpix(crop, G - offset) + offset


def bend(G: np.ndarray) -> float:
    """Largest second difference along rows and columns, each over the local spacing."""
    sp = corner_spacing(G)
    a = np.linalg.norm(G[:, 2:] - 2 * G[:, 1:-1] + G[:, :-2], axis=2) / sp[:, 1:-1]
    b = np.linalg.norm(G[2:] - 2 * G[1:-1] + G[:-2], axis=2) / sp[1:-1]
    return float(max(a.max(initial=0.0), b.max(initial=0.0)))


def _same_grid(F: np.ndarray, G: np.ndarray) -> np.ndarray | None:
    """``F`` re-ordered to correspond to ``G`` (both (rows, cols, 2)), or None if no
    ordering puts F's corners within ``FINE_MAX_SHIFT`` of a spacing of G's (median over
    the corners, median spacing). The orderings: F's rows and columns each as they are or
    reversed, and on a square grid also transposed (a detector may start from any corner
    and run along either side).

    The median, not the largest distance: a first detection with one corner gone a few
    pixels astray (the classic detector on a faint board) must not veto a fine grid that
    is right everywhere; a grid shifted or turned by a square is a whole spacing off at
    every corner. The fine grid's own smoothness is checked afterwards
    (``calib.detect._finish``)."""
    cands = [F, F[::-1, ::-1], F[::-1, :], F[:, ::-1]]
    if F.shape[0] == F.shape[1]:
        cands += [c.transpose(1, 0, 2) for c in cands]
    best, best_d = None, np.inf
    for cand in cands:
        d = float(np.median(np.linalg.norm(cand - G, axis=2)))
        if d < best_d:
            best, best_d = cand, d
    return best if best_d < FINE_MAX_SHIFT * float(np.median(corner_spacing(G))) else None


def extended(G: np.ndarray) -> np.ndarray:
    """The grid ``G`` (rows, cols, 2) extended linearly by one square on every side:
    (rows + 2, cols + 2, 2), the corners of the board's outer squares."""
    E = np.concatenate([2 * G[:1] - G[1:2], G, 2 * G[-1:] - G[-2:-1]], axis=0)
    return np.concatenate([2 * E[:, :1] - E[:, 1:2], E, 2 * E[:, -1:] - E[:, -2:-1]], axis=1)


def _board_mask(G: np.ndarray, shape: tuple[int, int]) -> np.ndarray | None:
    """(H, W) bool: the checkered area of the grid ``G`` (rows, cols, 2), i.e. the inner
    corners' grid extended by one square on every side; None if that covers too few
    pixels to take percentiles of."""
    E = extended(G)
    outline = np.concatenate([E[0], E[1:, -1], E[-1, -2::-1], E[-2:0:-1, 0]])
    mask = np.zeros(shape, dtype=np.uint8)
    hull = cv2.convexHull(np.round(outline).astype(np.int32).reshape(-1, 1, 2))
    cv2.fillConvexPoly(mask, hull, 1)
    on = mask.astype(bool)
    return on if on.sum() >= 64 else None


def _fine(fine: np.ndarray, G: np.ndarray, board: Board) -> np.ndarray | None:
    """Re-detect the board with the accurate sector-based detector in an upsampled crop
    around the grid ``G`` (original pixels), at each upsampling factor of
    ``FINE_TARGET_SPACING_PX`` (the smoother grid wins); None if that fails or disagrees.

    The crop is stretched to 8 bit by the percentiles of the checkered area only (a hot or
    cold object beside the board clips instead of squeezing the board's grey levels). If
    the detector fails on it, it runs again on the crop minus its Gaussian blur of
    ``FINE_HIGHPASS_SIGMA`` x the corner spacing (that blur keeps little of the squares and
    what varies slower: the halo that the first flattening leaves beside a cold window, the
    uneven heating of a faint board), then once more with CALIB_CB_EXHAUSTIVE."""
    h, w = fine.shape
    spacing = float(np.median(corner_spacing(G)))
    margin = FINE_MARGIN * spacing + 2.0
    x0 = max(0, int(np.floor(G[..., 0].min() - margin)))
    x1 = min(w, int(np.ceil(G[..., 0].max() + margin)) + 1)
    y0 = max(0, int(np.floor(G[..., 1].min() - margin)))
    y1 = min(h, int(np.ceil(G[..., 1].max() + margin)) + 1)
    crop = fine[y0:y1, x0:x1]
    mask = _board_mask(G - (x0, y0), (y1 - y0, x1 - x0))
    ratio = FINE_TARGET_SPACING_PX / _min_spacing(G)
    scales = sorted({int(np.clip(r(ratio), 1, FINE_MAX_UPSAMPLE)) for r in (np.ceil, np.rint)})
    sigma = FINE_HIGHPASS_SIGMA * spacing
    highpassed = crop - cv2.GaussianBlur(crop, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    exhaustive = cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE
    images = [
        (stretch_u8(image, mask), flags)
        for image, flags in (
            (crop, cv2.CALIB_CB_ACCURACY),
            (highpassed, cv2.CALIB_CB_ACCURACY),
            (highpassed, exhaustive),
        )
    ]
    grids = []
    for s in scales:
        for u8, flags in images:
            if u8 is None:
                continue
            up = upsample_image(u8, s)
            if (
                up.size > FINE_CHECK_ABOVE_PX
                and not cv2.findChessboardCornersSB(
                    up, board.pattern_size, flags=flags & ~cv2.CALIB_CB_ACCURACY
                )[0]
            ):
                continue  # the accurate detector costs 4x as much and would fail too
            ok, raw = cv2.findChessboardCornersSB(up, board.pattern_size, flags=flags)
            if not ok:
                continue
            F = (np.asarray(raw, dtype=np.float64).reshape(G.shape) + 0.5) / s - 0.5
            F += (x0, y0)
            if np.all(np.isfinite(F)) and (F := _same_grid(F, G)) is not None:
                grids.append(F)
            break
    return min(grids, key=_roughness, default=None)


def _roughness(G: np.ndarray) -> float:
    """RMS (pixels) of the grid's (rows, cols, 2) second differences along rows and
    columns, each less its row's (column's) mean: corner noise, little of the perspective
    and distortion, which vary smoothly."""
    parts = [np.zeros((0, 2))]
    if G.shape[1] > 2:
        a = G[:, 2:] - 2 * G[:, 1:-1] + G[:, :-2]
        parts.append((a - a.mean(axis=1, keepdims=True)).reshape(-1, 2))
    if G.shape[0] > 2:
        b = G[2:] - 2 * G[1:-1] + G[:-2]
        parts.append((b - b.mean(axis=0, keepdims=True)).reshape(-1, 2))
    both = np.concatenate(parts)
    return float(np.sqrt(np.mean(both**2))) if len(both) else 0.0


def refined(
    G: np.ndarray, prep: Prepared, board: Board, classic: bool, fallback: bool
) -> Iterator[tuple[np.ndarray, str]]:
    """Refinements of the detector's grid ``G`` ((rows, cols, 2), pixels of
    ``prep.detect``) in original pixels, with the method suffix of each, best first; the
    caller takes the first that forms a smooth grid.

    1. The fine stage (:func:`_fine`), where the modality has one.
    2. cornerSubPix (:func:`_subpix`; a pyramid level: again at the original size).
    3. With ``fallback`` instead (:func:`calib.detect.detect_board` asks for it only when no
       detector gave a grid that 1 or 2 made smooth), not on pyramid levels: cornerSubPix with a
       half-window of ``NARROW_WINDOW_FRACTION`` x the spacing (``"+narrow"``), then the
       detector's own corners (``"+unrefined"``), as a plain OpenCV script keeps them,
       then the same narrow cornerSubPix after stray corners are put back on the grid
       (:func:`_repaired`, ``"+repaired"``). Squares with a texture of their own (foil,
       glare) pull a wide window's corner to the texture's edges: 9-16 px off on harunrk's
       ZED 2i views (13 of 69 refused before these steps; OpenCV's plain pipeline finds
       all 69).
    """
    s = prep.scale
    if not fallback:
        if prep.fine is not None:
            F = _fine(prep.fine, (G + 0.5) / s - 0.5, board)
            if F is not None:
                yield F, ""
        R = (_subpix(prep.refine, G, wide_first=classic) + 0.5) / s - 0.5
        if prep.pyramid:
            yield _subpix_full(prep.darkness, R), ""
        else:
            yield R, "+subpix" if prep.fine is not None else ""
        return
    if prep.pyramid:
        return
    hw = int(np.clip(round(NARROW_WINDOW_FRACTION * _min_spacing(G)), *SUBPIX_HALF_WINDOW_PX))

    def narrow(G: np.ndarray) -> np.ndarray:
        pts = np.ascontiguousarray(G.reshape(-1, 1, 2), dtype=np.float32)
        cv2.cornerSubPix(prep.refine, pts, (hw, hw), (-1, -1), SUBPIX_CRITERIA)
        return (pts.reshape(G.shape).astype(np.float64) + 0.5) / s - 0.5

    yield narrow(G), "+narrow"
    yield (G + 0.5) / s - 0.5, "+unrefined"
    P = _repaired(G)
    if P is not None:
        yield narrow(P), "+repaired"


def _repaired(G: np.ndarray) -> np.ndarray | None:
    """The grid ``G`` (rows, cols, 2) with its stray corners (farther than
    ``STRAY_FRACTION`` x the spacing from a homography fitted to the others, RANSAC) put
    where that homography puts them; None if there is none, or more than one in ten.
    For a corner the detector misplaced on a blurred, low-contrast square (a 160 x 120
    Lepton view: one corner half a spacing off, where OpenCV's own grid is noisy but
    whole)."""
    rows, cols = G.shape[:2]
    c, r = np.meshgrid(np.arange(cols, dtype=np.float32), np.arange(rows, dtype=np.float32))
    board = np.stack([c.ravel(), r.ravel()], axis=1)
    pts = G.reshape(-1, 2).astype(np.float32)
    limit = STRAY_FRACTION * _min_spacing(G)
    H, _ = cv2.findHomography(board, pts, cv2.RANSAC, limit)
    if H is None:
        return None
    predicted = cv2.perspectiveTransform(board[None], H)[0].astype(np.float64)
    stray = np.linalg.norm(predicted - pts, axis=1) > limit
    if not stray.any() or stray.sum() > 0.1 * len(pts):
        return None
    out = G.reshape(-1, 2).copy()
    out[stray] = predicted[stray]
    return out.reshape(G.shape)
