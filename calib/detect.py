"""Checkerboard corner detection in colour, thermal and TOF amplitude images.

One entry point, :func:`detect_board`: an image of one sensor in, a :class:`Detection` out
(corners in the original image's pixels, in the board's canonical order, or the reason
why there are none). Pure: no files, no printing, no state.

Pipeline, per modality:

* **colour** (RGB or grey uint8): OpenCV's sector-based detector
  (``findChessboardCornersSB``, no flags) on the grey image, then the same with
  ``CALIB_CB_NORMALIZE_IMAGE``, then the classic detector (``findChessboardCorners``,
  adaptive threshold + normalisation) as the last resort. Whatever found the board, the
  corners are refined with ``cornerSubPix`` (half-window 0.4 x the smallest corner
  spacing, clamped to 2-11 px) on the linearised (gamma ``COLOR_GAMMA``), lightly blurred
  grey image; the classic detector's corners get one wider pass first.
* **large colour images** (longer side over ``PYRAMID_ABOVE_PX``, e.g. 12 MP): the same
  detectors on copies downscaled (``INTER_AREA``) to the longer sides
  ``PYRAMID_LEVELS_PX`` in turn, the corners refined there as above, then refined once
  more at full resolution in a crop around the board (half-window from the corner spacing
  at full resolution, same clamp), and the squares just outside the grid checked
  (:func:`calib.detect_order.ring_problem`). Detection then costs about the same at
  12 MP as at 1 MP.
* **thermal** (temperatures or raw counts, any real dtype, NaN = no reading):
  fixed-pattern column and row offsets removed (:func:`calib.detect_prepare._destripe`),
  background flattening (the image minus a wide Gaussian blur, which removes uneven
  heating, the hot spot, narcissus and the room), a percentile stretch to 8 bit,
  ``THERMAL_UPSAMPLE`` x cubic upsampling, the same three detectors on both polarities
  (the classic detector wants dark squares on a bright margin); then the same on the
  flattened image over its local RMS (``LCN_SIGMA_PX``), for a faint board (1-3 K) beside
  hot or cold objects that take the global stretch's range (issue 15, BENCHMARKS.md
  "Thermal board detection under real-world conditions"); if none gives a board, all of it
  again without the upsampling (:func:`calib.detect_prepare.native_levels`). Before all
  this the three detectors look at the stretched image at its original size, and a board
  of large squares found there (``NATIVE_FIRST_SPACING_PX``) is taken if the fine stage
  refines it: the upsampling is for small squares, and costs several times more.
* **TOF amplitude**: flattened log amplitude (amplitude falls as 1/d^2), a percentile
  stretch, ``TOF_UPSAMPLE`` x cubic upsampling (the squares are 2.5-15 px).
* **fine stage** (thermal and TOF): the board is found again with the sector-based
  detector and ``CALIB_CB_ACCURACY`` in a crop of the flattened image (linear in the
  sensor's signal) around the first corners, upsampled until the corner spacing is about
  ``FINE_TARGET_SPACING_PX`` and stretched by the checkered area's percentiles; failing
  that, in the crop minus its blur at the squares' scale (``FINE_HIGHPASS_SIGMA``). If
  that fails too, ``cornerSubPix`` on the upsampled image. On a large upsampled crop the
  detector runs without ``CALIB_CB_ACCURACY`` first, as a cheap check
  (``FINE_CHECK_ABOVE_PX``).
* **fallback refinements**: a grid that no refinement above made smooth is kept; if no
  detector at any level gives a board, the kept grids are refined with a narrow window,
  taken as the detector gave them, or repaired (:func:`calib.detect_grid.refined`).

Why these choices (measured on 40 simulated views and the 13 OpenCV sample images,
opencv-python-headless 5.0.0.93, 2 cores):

* ``findChessboardCornersSB`` on 1280x960: no flags 0.10-0.16 s, found 66/66 simulated
  boards and 11/13 real; EXHAUSTIVE 0.15 s, 66/66 and 10/13; ACCURACY 0.54 s, 66/66 and
  13/13; NORMALIZE_IMAGE 0.15 s, 56/66 and 13/13; EXHAUSTIVE|ACCURACY|NORMALIZE 0.70 s,
  61/66. No flags then NORMALIZE_IMAGE finds all 79 at ~0.1 s typical. ACCURACY's
  corners (0.055 px mean error) lose to cornerSubPix on the linearised image (0.030 px),
  so it is not worth its 0.4 s on colour.
* cornerSubPix on SB corners: colour yes (0.077 -> 0.030 px mean); thermal and TOF no:
  on their small, upsampled squares it was worse than the SB detector with ACCURACY on
  an upsampled crop (thermal 0.062 vs 0.034 px, TOF 0.26 vs 0.054 px).

Upsampled (or downscaled) coordinates map back with the pixel-centre convention of
docs/CONVENTIONS.md: ``u = (u' + 0.5) / s - 0.5`` (per axis for a downscaled copy, whose
size is rounded to whole pixels).

Canonical order (calib/board.py): row-major, corner ``r * cols + c`` is the board point
``(c * s, r * s, 0)``. The detectors return one of several orderings (the sector-based
one returns the reverse of the classic one); they are normalised by

1. handedness: the board's +x (along a row) and +y (down a column) must form a
   right-handed pair in the image (x right, y down) because the camera sees the board's
   front; otherwise the rows are flipped;
2. square colours: the interior square between corners (r, c) and (r + 1, c + 1) is black
   iff r + c is even. On a board with an odd number of inner corners on one side and an
   even number on the other (``Board.orderings`` 1) a half turn swaps the colours, so
   comparing neighbouring squares decides between the ordering and its half turn; a
   detection whose colours do not clearly decide is rejected, never guessed. "Black"
   means dark in colour and TOF amplitude and, on the heated board, hot in thermal
   (``THERMAL_BLACK_IS_HOT``).

A board that looks the same turned (even x even or odd x odd inner corners: a half turn;
square: quarter turns too) keeps the detector's ordering after step 1: the colours cannot
tell its orderings apart, so they are only checked to alternate
(``COLOUR_PLAUSIBLE_SEPARATION``), and a calibration decides each view's ordering across
sensors from the data (calib.board_ordering.order_views).

Mirrored images: a board with an even number of inner-corner rows (9 x 6) looks the same
in a mirror (flipped top to bottom it has the same colours), so a mirrored image cannot
be told from a real one. It is detected like any other image; the labels are those of the
board seen in the mirror (corner (r, c) of the mirrored image is the mirror image of
corner (rows - 1 - r, c) of the original). Do not feed mirrored images to a calibration.

A detection whose corners come closer to the image border than
``max(BORDER_MIN_PX, BORDER_FRACTION x local corner spacing)`` is rejected: the outer
squares are then cut to slivers and the detectors' corners there are unreliable. A
twentieth of a spacing: real boards with an outer corner 0.07-0.12 of a spacing from the
edge (Pose2Sim's 1088 x 1920 cameras, 4 of 28 views) are found by the plain OpenCV
pipeline, and trifuse's corners there fit like the others (0.24-0.29 px per view); a
quarter of a spacing refused them (at 0.25-0.5 of a spacing, simulated colour views' corners
were as accurate as elsewhere: 0.04 px RMS at most). No simulator view changed between a
quarter and a twentieth (448 views of the detection bench's conditions, seeds 0-1).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.detect_grid import bend, corner_spacing, grid_spacing, refined, regular
from trifuse.calib.detect_order import orient, ring_problem
from trifuse.calib.detect_prepare import (
    THERMAL_UPSAMPLE,
    Prepared,
    native_levels,
    prepare,
    pyramid_levels,
)

MODALITIES = ("color", "thermal", "tof")

THERMAL_BLACK_IS_HOT = True
"""Polarity of the heated board in thermal: the black squares (matte foil, emissivity about
0.95) read hotter than the white ones (bare aluminium, about 0.12, mirroring the cooler
room). Pass ``thermal_black_is_hot=False`` for a board that is the other way round
(e.g. a cooled board, or white squares of a high-emissivity paint on a heated metal)."""

PYRAMID_ABOVE_PX = 2000
"""Colour images whose longer side exceeds this are searched on downscaled copies (module
docstring); smaller ones at their own size, as before."""
NATIVE_FIRST_SPACING_PX = 15.0
"""Thermal: the detectors first run on the image at its original size (one polarity, no
locally normalised copy), and a grid found there whose median corner spacing is at
least this (pixels) is taken when the fine stage refines it; otherwise the search
goes on as before, upsampled first. The fine stage gives the corners either way (it
works at the original size), so the level only decides where the board is. The
upsampling is for small squares; on squares this large the upsampled search costs
several times more and found no board that the original size missed (VimsLab's 16-bit
LWIR, 16-25 px: median CPU time 1.66-1.68 -> 1.0-1.1 s an image, with the cheap check of
``FINE_CHECK_ABOVE_PX``)."""

GRID_MAX_BEND = 0.4
"""Largest second difference of the refined corners along a row or column, as a fraction of
the local spacing. Measured: good grids at most 0.07 (colour, thermal), 0.12 (real OpenCV
samples), 0.18 (TOF, 2.5 px squares); corners gone astray 0.9 and more."""

BORDER_MIN_PX = 2.0
BORDER_FRACTION = 0.05
FALLBACK_BORDER_FRACTION = 0.25
"""The border rule's fraction for the fallback refinements of grids refused as bent
(``+narrow``, ``+unrefined``, ``+repaired``): a quarter of a spacing, because a board cut
at a few pixels from its outer corners can come back from them with a corner half a
spacing astray (simulated thermal, a cut 0.02 of a spacing from the outer corners: 11.5 px)."""

COLOUR_AGREEMENT = 0.9
"""Fraction of neighbouring interior-square pairs that must agree on which colour class is
darker on a board with one ordering (``Board.orderings`` 1); below it the detection is
rejected as ambiguous (never guessed)."""
COLOUR_MIN_SEPARATION = 2.0
"""Minimum separation of the two colour classes: |mean| over standard deviation of the
(signed) differences between neighbouring squares. Measured: at least 5.5 on detected
boards (TOF; colour 45+, thermal 8.6+, real images 7.6+); noise gives about 0."""
COLOUR_PLAUSIBLE_SEPARATION = 0.5
"""Boards that look the same turned (``Board.orderings`` > 1): the colours decide nothing
there, so the two thresholds above do not apply; the squares only have to alternate, with
at least this separation. Measured on synthetic 4 x 6 views (the simulated ccd_left, board
at 1.2 m) with white glare over the centres of k of its 8 black interior squares (3 seeds
each; the corners stay sharp): k = 1: 1.7-2.2, k = 2: 0.74-1.0, k = 3: 0.63-0.74, k = 4:
0.26-0.44; blocky noise in place of the board: median 0.26, 90 % below 0.70 (9 x 6: 0.16
and 0.40). A plausibility check, not a gate: a grid's geometry is checked before, and a
calibration leaves out a view whose corners agree with no ordering."""

_SB_FLAGS = {
    "sb": 0,
    "sb-normalized": cv2.CALIB_CB_NORMALIZE_IMAGE,
}
_CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE


@dataclass(eq=False)
class Detection:
    """Result of :func:`detect_board` (compared by identity: it holds an array).

    Attributes:
        corners: (N, 2) float64 pixels in the original image, canonical board order
            (``r * cols + c``); None if the board was not found or was rejected.
        reason: why there are no corners (human readable); None when found.
        method: what found the corners, e.g. ``"sb"``, ``"classic"``,
            ``"sb-inverted-x2"``; also set for a rejected detection.
    """

    corners: np.ndarray | None
    reason: str | None
    method: str | None

    @property
    def found(self) -> bool:
        return self.corners is not None


class _Rejected(Exception):
    def __init__(self, reason: str, final: bool, bent: bool = False) -> None:
        super().__init__(reason)
        self.reason = reason
        self.final = final  # the same board would be rejected whatever found it
        self.bent = bent  # no refinement tried gave a smooth grid


# -- input checks -----------------------------------------------------------------------


def _check_board(board: Board) -> None:
    """Any checkerboard: one that looks the same turned (``board.orderings`` > 1: even x
    even, odd x odd or square) is detected in one of its orderings, and a calibration
    decides each view's across sensors from the data (calib.board_ordering.order_views)."""
    if not isinstance(board, Board):
        raise ValueError(f"board: expected a calib.board.Board, got {type(board).__name__}")


def _check_image(image: object, modality: str) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{modality} image: expected a numpy array, got {type(image).__name__}")
    if modality == "color":
        ok_shape = image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
        if not ok_shape or image.dtype != np.uint8:
            raise ValueError(
                "color image: expected (H, W, 3) uint8 RGB or (H, W) uint8 grey, got "
                f"shape {image.shape} {image.dtype}"
            )
    elif image.ndim != 2 or image.dtype.kind not in "fiu":
        what = "temperatures or counts" if modality == "thermal" else "amplitude"
        raise ValueError(
            f"{modality} image: expected (H, W) float or integer {what}, got shape "
            f"{image.shape} {image.dtype}"
        )
    if min(image.shape[:2]) < 8:
        raise ValueError(f"{modality} image: expected at least 8x8 pixels, got shape {image.shape}")
    return image


# -- detectors --------------------------------------------------------------------------


def _sb(flags: int) -> Callable[[np.ndarray, Board], np.ndarray | None]:
    def run(img: np.ndarray, board: Board) -> np.ndarray | None:
        ok, corners = cv2.findChessboardCornersSB(img, board.pattern_size, flags=flags)
        return corners if ok else None

    return run


def _classic(img: np.ndarray, board: Board) -> np.ndarray | None:
    ok, corners = cv2.findChessboardCorners(img, board.pattern_size, flags=_CLASSIC_FLAGS)
    return corners if ok else None


_DETECTORS: list[tuple[str, Callable[[np.ndarray, Board], np.ndarray | None]]] = [
    *((name, _sb(flags)) for name, flags in _SB_FLAGS.items()),
    ("classic", _classic),
]


# -- a grid judged, and the search ------------------------------------------------------


def _border_problem(G: np.ndarray, w: int, h: int, fraction: float = BORDER_FRACTION) -> str | None:
    """Why the grid (rows, cols, 2) in original pixels is too close to the border (closer
    than ``max(BORDER_MIN_PX, fraction x local corner spacing)``)."""
    corners = G.reshape(-1, 2)
    # Pixel (u, v) covers [u - 0.5, u + 0.5): the image edges are at -0.5 and W - 0.5.
    dist = np.stack(
        [
            corners[:, 0] + 0.5,
            w - 0.5 - corners[:, 0],
            corners[:, 1] + 0.5,
            h - 0.5 - corners[:, 1],
        ],
        axis=1,
    )
    need = np.maximum(BORDER_MIN_PX, fraction * corner_spacing(G).ravel())
    slack = dist - need[:, None]
    if not (slack < 0).any():
        return None
    k, side = np.unravel_index(np.argmin(slack), slack.shape)
    edge = ("left", "right", "top", "bottom")[side]
    return (
        f"board touches the image border (corner {k} is {dist[k, side]:.1f} px from the "
        f"{edge} edge, at least {need[k]:.1f} px needed)"
    )


def _finish(
    raw: np.ndarray,
    prep: Prepared,
    board: Board,
    shape: tuple[int, int],
    classic: bool,
    fallback: bool = False,
) -> tuple[np.ndarray, str]:
    """Refined corners (N, 2) in original pixels and canonical order, and the method
    suffix (``fallback``: :func:`calib.detect_grid.refined`'s); raises _Rejected."""
    rows, cols = board.rows, board.cols
    pts = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    if len(pts) != board.n_corners:
        raise _Rejected(f"detector returned {len(pts)} corners, expected {board.n_corners}", False)
    if not np.all(np.isfinite(pts)):
        raise _Rejected("detector returned non-finite corners", False)
    G = pts.reshape(rows, cols, 2)
    if not regular(G):
        raise _Rejected("detected corners do not form a regular grid", False)
    h, w = shape
    smooth = (
        (R, sfx)
        for R, sfx in refined(G, prep, board, classic, fallback)
        if np.all(np.isfinite(R)) and regular(R) and bend(R) <= GRID_MAX_BEND
    )
    G, suffix = next(smooth, (None, ""))
    if G is None:
        raise _Rejected(
            "the refined corners do not form a smooth grid (a corner went astray)", False, True
        )
    problem = ring_problem(prep.darkness, G) if prep.pyramid else None
    if problem:
        raise _Rejected(problem, False)
    G, agreement, separation = orient(G, board, prep.darkness)
    if board.orderings == 1 and (
        agreement < COLOUR_AGREEMENT or separation < COLOUR_MIN_SEPARATION
    ):
        raise _Rejected(
            "the square colours are not clearly separated (only "
            f"{100 * agreement:.0f}% of neighbouring squares agree on which colour is "
            f"darker, separation {separation:.1f}); cannot tell the board's orientation",
            False,
        )
    if separation < COLOUR_PLAUSIBLE_SEPARATION:
        raise _Rejected(
            f"the squares do not alternate in colour (separation {separation:.2f}): not a "
            "checkerboard",
            False,
        )
    # Final: whatever finds this board finds it at the border (corner numbers canonical).
    problem = _border_problem(G, w, h, FALLBACK_BORDER_FRACTION if fallback else BORDER_FRACTION)
    if problem:
        raise _Rejected(problem, True)
    return np.ascontiguousarray(G.reshape(-1, 2)), suffix


def detect_board(
    image: np.ndarray,
    board: Board,
    modality: str,
    *,
    thermal_black_is_hot: bool = THERMAL_BLACK_IS_HOT,
    pyramid: bool = True,
) -> Detection:
    """Find the board's inner corners in one sensor image.

    Args:
        image: colour: (H, W, 3) uint8 RGB or (H, W) uint8 grey; thermal: (H, W)
            temperatures in kelvin or raw counts (any float or integer dtype, NaN = no
            reading); tof: (H, W) amplitude (float or integer).
        board: the checkerboard (any: one that looks the same turned comes out in one of
            its orderings, module docstring).
        modality: ``"color"``, ``"thermal"`` or ``"tof"``.
        thermal_black_is_hot: polarity of the board in thermal (``THERMAL_BLACK_IS_HOT``).
        pyramid: search a colour image larger than ``PYRAMID_ABOVE_PX`` on downscaled
            copies (module docstring); False searches it at full size (seconds to tens of
            seconds at 12 MP; for comparisons).

    Returns:
        A :class:`Detection`: corners (N, 2) float64 in the original image's pixels
        (pixel centres at integers), row-major canonical order (corner ``r * cols + c`` is
        the board point ``(c * s, r * s, 0)``), or None with the reason.

    Raises:
        ValueError: unknown modality, not a Board, wrong image shape or dtype.
    """
    if not isinstance(modality, str) or modality not in MODALITIES:
        raise ValueError(f"modality: expected one of {', '.join(MODALITIES)}, got {modality!r}")
    _check_board(board)
    img = _check_image(image, modality)
    if board.pattern != "checkerboard":  # ChArUco, circle grids: their own modules
        from trifuse.calib.detect_charuco import find_charuco
        from trifuse.calib.detect_circles import find_circles

        prep = prepare(img, modality, thermal_black_is_hot)
        if isinstance(prep, str):
            return Detection(None, f"board not found: {prep}", None)
        find = find_charuco if board.pattern == "charuco" else find_circles
        return Detection(*find(prep.detect, int(prep.scale), board, modality != "color"))
    shape = img.shape[:2]

    preps: Iterable[Prepared | str]
    if pyramid and modality == "color" and max(shape) > PYRAMID_ABOVE_PX:
        preps = pyramid_levels(img)
    else:
        preps = native_levels(img, modality, thermal_black_is_hot)
    first_rejection: Detection | None = None
    tried: list[str] = []
    bent: list[tuple[np.ndarray, Prepared, bool, str]] = []  # for refined's fallback
    for prep in preps:
        if isinstance(prep, str):
            return Detection(None, f"board not found: {prep}", None)
        if prep.pyramid:
            level = f"-{max(prep.detect.shape)}px"
        else:
            level = f"-x{prep.scale}" if prep.scale != 1 else ""
        attempts = [
            (label, inverted, image)
            for label, image in [("", prep.detect), *prep.extra]
            for inverted in ((False, True) if prep.both_polarities else (False,))
        ]
        probe = prep.probe
        for label, inverted, image in attempts[:1] if probe is not None else attempts:
            for name, finder in _DETECTORS:
                method = name + (f"-{label}" if label else "") + ("-inverted" if inverted else "")
                method += level
                if probe is None:
                    tried.append(method)
                key = (label, inverted, name)
                if key not in prep.memo:
                    prep.memo[key] = [finder(255 - image if inverted else image, board), None]
                memo = prep.memo[key]
                raw = memo[0]
                if raw is None:
                    continue
                if probe is not None:
                    spacing = grid_spacing(raw, board, image.shape)
                    if spacing is None or spacing < NATIVE_FIRST_SPACING_PX:
                        if spacing is not None and name != "classic":  # small squares
                            up = (np.asarray(raw, dtype=np.float32) + 0.5) * THERMAL_UPSAMPLE
                            probe.setdefault(key, [up - 0.5, None])
                        break
                if memo[1] is None:
                    try:
                        memo[1] = _finish(raw, prep, board, shape, name == "classic")
                    except _Rejected as rej:
                        memo[1] = rej
                if probe is not None:  # only a board whose corners the fine stage gave
                    if not isinstance(memo[1], _Rejected) and memo[1][1] == "":
                        return Detection(memo[1][0], None, method)
                    continue
                if isinstance(memo[1], _Rejected):
                    rej = memo[1]
                    if rej.final:
                        return Detection(None, rej.reason, method)
                    if first_rejection is None:
                        first_rejection = Detection(None, rej.reason, method)
                    if rej.bent:
                        bent.append((raw, prep, name == "classic", method))
                    continue
                corners, suffix = memo[1]
                return Detection(corners, None, method + suffix)
    for raw, prep, classic, method in bent:
        try:
            corners, suffix = _finish(raw, prep, board, shape, classic, fallback=True)
        except _Rejected as rej:
            if rej.final:
                return Detection(None, rej.reason, method)
            continue
        return Detection(corners, None, method + suffix)
    if first_rejection is not None:
        return first_rejection
    return Detection(
        None,
        f"board ({board.cols}x{board.rows} inner corners) not found (tried {', '.join(tried)})",
        None,
    )
