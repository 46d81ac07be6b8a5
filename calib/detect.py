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
  (:func:`_ring_problem`). Detection then costs about the same at 12 MP as at 1 MP.
* **thermal** (temperatures or raw counts, any real dtype, NaN = no reading): fixed-pattern
  column and row offsets removed (:func:`_destripe`), background flattening (the image
  minus a wide Gaussian blur, which removes uneven heating, the hot spot, narcissus and
  the room), a percentile stretch to 8 bit, ``THERMAL_UPSAMPLE`` x cubic upsampling, the
  same three detectors on both polarities (the classic detector wants dark squares on a
  bright margin); then the same on the flattened image over its local RMS
  (``LCN_SIGMA_PX``), for a faint board (1-3 K) beside hot or cold objects that take the
  global stretch's range (issue 15, BENCHMARKS.md "Thermal board detection under
  real-world conditions"); if none gives a board, all of it again without the upsampling
  (:func:`_native_levels`). Before all this the three detectors look at the stretched
  image at its original size, and a board of large squares found there
  (``NATIVE_FIRST_SPACING_PX``) is taken if the fine stage refines it: the upsampling is
  for small squares, and costs several times more.
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
  taken as the detector gave them, or repaired (:func:`_refined`).

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
sensors from the data (calib.polarity.order_views).

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

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from trifuse.calib.board import Board

MODALITIES = ("color", "thermal", "tof")

THERMAL_BLACK_IS_HOT = True
"""Polarity of the heated board in thermal: the black squares (matte foil, emissivity about
0.95) read hotter than the white ones (bare aluminium, about 0.12, mirroring the cooler
room). Pass ``thermal_black_is_hot=False`` for a board that is the other way round
(e.g. a cooled board, or white squares of a high-emissivity paint on a heated metal)."""

COLOR_GAMMA = 2.2
"""Colour images are assumed gamma-encoded (sRGB-like); the sub-pixel refinement runs on
intensities linearised with this exponent. On the simulator (gamma 1/2.2) this halves the
corner bias (mean RMS 0.057 -> 0.030 px); on the real OpenCV sample images it lowers the
calibration RMS too (0.196 -> 0.193 px). Use 1.0 for a linear camera."""
COLOR_REFINE_BLUR_PX = 1.0
"""Gaussian sigma applied before the colour refinement; sharp, pixel-integrated edges
otherwise bias ``cornerSubPix`` (measured 0.073 -> 0.057 px mean without linearising)."""

PYRAMID_ABOVE_PX = 2000
"""Colour images whose longer side exceeds this are searched on downscaled copies (module
docstring); smaller ones at their own size, as before."""
PYRAMID_LEVELS_PX = (1000, 500, 2000)
"""Longer sides of the downscaled copies, in the order they are searched (levels not
smaller than the image are skipped). 1000 and 2000 px are what OpenCV users downscale 12 MP
views to; 500 px catches boards that fill the frame, whose textured surroundings (grass)
break the detectors at 1000 px."""
RING_WRONG_FRACTION = 1 / 3
"""Pyramid levels: a side of the grid is wrong when at least this fraction (and at least 2)
of the squares just outside it, in view, read as the other colour class than the
checkerboard demands (:func:`_ring_problem`)."""

THERMAL_FLATTEN_SIGMA_PX = 25.0
"""Sigma of the background blur subtracted from thermal images, native pixels."""
THERMAL_UPSAMPLE = 2
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
NATIVE_FIRST_ABOVE_PX = 50_000
"""Only images of more pixels than this are probed at their original size first: on a
160 x 120 Lepton a failing sector-based search costs 25-40 ms, as much as the upsampled
search that finds the board (harunrk's Lepton 3.5: 44 -> 58 ms a view with the probe)."""
DESTRIPE_WINDOW_PX = 7
"""Thermal: width of the box whose mean a pixel's column (row) offset is measured
against (:func:`_destripe`)."""
LCN_SIGMA_PX = 6.0
"""Thermal: window (Gaussian sigma, native pixels) of the local RMS that the second
detection image (``"lcn"``) is normalised by: about one square of a distant board, so that
a faint board (1-3 K) right beside a cold window or a hot radiator gets its own contrast.
Measured on the thermal-detect conditions, seeds 0-2 (BENCHMARKS.md, issue 15): with 25 px
the low-contrast boards found were 28/48, with 10 px 35/48, with 6 px 36/48 (diffusion
30 -> 39 -> 39 of 48); boards found before the LCN image is tried are unchanged."""
LCN_RANGE = 2.5
LCN_NOISE_FLOOR = 3.0
"""The local RMS is at least this many noise sigmas (noise-only regions stay grey)."""
TOF_FLATTEN_SIGMA_PX = 12.0
"""Sigma of the background blur subtracted from the TOF log amplitude, native pixels."""
TOF_UPSAMPLE = 4
STRETCH_PERCENTILES = (0.5, 99.5)

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
(``SUBPIX_WINDOW_FRACTION``) leaves a bent grid (:func:`_refined`)."""
STRAY_FRACTION = 0.25
"""A detected corner this far (over the corner spacing) from a homography fitted to the
others is put back on it before a last refinement (:func:`_repaired`)."""
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)

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


@dataclass
class _Prepared:
    """A sensor image made ready for the detectors.

    Attributes:
        scale: ``detect`` and ``refine`` are ``scale`` x the original size: an integer
            upsampling, or per axis ``(sx, sy)`` below 1 for a pyramid level.
        detect: uint8 image for the detectors, the board's black squares dark.
        both_polarities: whether to try the inverted ``detect`` image too.
        refine: float32 image (``scale`` x) for cornerSubPix.
        darkness: float32 image at the original size in which the board's black squares
            are low (the colour check samples it).
        fine: None, or a float32 image at the original size, linear in the sensor's
            signal, black squares low: the fine stage re-detects the board in an
            upsampled crop of it.
        extra: more (label, uint8 image) pairs like ``detect``, tried after it when it
            gives no board (thermal: the locally normalised image, label ``"lcn"``).
        pyramid: a downscaled copy of a large colour image: the corners are refined once
            more at the original size, in ``darkness`` (the linearised grey), and the
            squares around the grid are checked (:func:`_ring_problem`).
        probe: None, or (thermal) the memo of the upsampled level, when this is the
            original size searched before it: only ``detect`` at one polarity, and only a
            grid of large squares (median corner spacing at least
            ``NATIVE_FIRST_SPACING_PX``) whose corners the fine stage gave is taken; a
            sector-based detector's grid of smaller squares is handed, scaled, to the
            upsampled level as if the same detector had found it there (it does not search
            again). Not the classic detector's: its corners, unrefined, can be pixels off
            on small squares, and the fine stage then failed on 1 of 448 simulated views
            (corners 0.07 -> 0.22 px from the truth).
        memo: (label, inverted, detector) -> [the detector's raw corners or None, then
            what :func:`_finish` made of them, or None before it ran]: shared by the probe
            and the level of the same size, so that no detector runs twice on an image.
    """

    scale: int | tuple[float, float]
    detect: np.ndarray
    both_polarities: bool
    refine: np.ndarray
    darkness: np.ndarray
    fine: np.ndarray | None = None
    extra: list[tuple[str, np.ndarray]] = field(default_factory=list)
    pyramid: bool = False
    probe: dict[tuple[str, bool, str], list] | None = None
    memo: dict[tuple[str, bool, str], list] = field(default_factory=dict)


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
    decides each view's across sensors from the data (calib.polarity.order_views)."""
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


# -- per-modality preparation -----------------------------------------------------------


def _stretch_u8(x: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray | None:
    """Percentile stretch of a float image to uint8 (the percentiles of the pixels where
    ``mask`` (same shape, bool) is set, if given; the rest clips); None if it has no
    contrast."""
    lo, hi = np.percentile(x if mask is None else x[mask], STRETCH_PERCENTILES)
    if not hi - lo > 1e-6 * max(1.0, abs(float(hi)), abs(float(lo))):
        return None
    y = (x - lo) * (255.0 / (hi - lo)) + 0.5
    return np.clip(y, 0, 255).astype(np.uint8)


def _finite_filled(image: np.ndarray) -> np.ndarray | None:
    """float32 copy with non-finite pixels replaced by the median; None if none is finite."""
    x = image.astype(np.float32)
    bad = ~np.isfinite(x)
    if bad.all():
        return None
    if bad.any():
        x[bad] = np.median(x[~bad])
    return x


def _flatten(x: np.ndarray, sigma: float) -> np.ndarray:
    return x - cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def _destripe(x: np.ndarray) -> np.ndarray:
    """``x`` without fixed-pattern column and row offsets: each column's (row's) median
    of the horizontally (vertically) high-passed image (``DESTRIPE_WINDOW_PX`` box)
    subtracted. Scene edges rarely run along a whole column, and a checkerboard's edges
    change sign from one square to the next, so their medians stay near zero."""
    k = DESTRIPE_WINDOW_PX
    x = x - np.median(x - cv2.blur(x, (k, 1), borderType=cv2.BORDER_REFLECT), axis=0)[None, :]
    return x - np.median(x - cv2.blur(x, (1, k), borderType=cv2.BORDER_REFLECT), axis=1)[:, None]


def _noise_sigma(x: np.ndarray) -> float:
    """Robust per-pixel noise sigma of ``x`` from horizontal neighbour differences."""
    d = np.abs(np.diff(x, axis=1))
    return float(1.4826 * np.median(d) / np.sqrt(2.0))


def _local_normalise_u8(flat: np.ndarray) -> np.ndarray:
    """The flattened image over its local RMS (Gaussian window ``LCN_SIGMA_PX``), mapped
    to 8 bit with +-``LCN_RANGE`` local RMS at 0 and 255. Regions of noise only (RMS near
    the noise floor) stay near mid-grey; a faint board beside hot objects gets the full
    range that a global stretch gives to the hot objects."""
    var = cv2.GaussianBlur(flat * flat, (0, 0), LCN_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
    floor = LCN_NOISE_FLOOR * _noise_sigma(flat)
    n = flat / np.sqrt(var + np.float32(floor * floor + 1e-12))
    return np.clip(n * (127.5 / LCN_RANGE) + 128.0, 0, 255).astype(np.uint8)


def _upsample(x: np.ndarray, s: int) -> np.ndarray:
    if s == 1:
        return x
    return cv2.resize(x, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)


def _prepare(
    image: np.ndarray, modality: str, black_is_hot: bool, upsample: int | None = None
) -> _Prepared | str:
    """The prepared image, or the reason there is nothing to detect in; ``upsample``
    overrides the thermal / TOF upsampling factor."""
    if modality == "color":
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if int(grey.max()) - int(grey.min()) < 8:
            return "the image has no contrast (blank image?)"
        lin = np.power(grey.astype(np.float32) * np.float32(1.0 / 255.0), COLOR_GAMMA)
        refine = cv2.GaussianBlur(lin, (0, 0), COLOR_REFINE_BLUR_PX)
        return _Prepared(1, grey, False, refine, lin)

    x = _finite_filled(image)
    if x is None:
        return "the image has no finite pixels"
    if modality == "thermal":
        flat = _flatten(_destripe(x), THERMAL_FLATTEN_SIGMA_PX)
        dark = -flat if black_is_hot else flat  # black squares low
        coarse, fine, s = dark, dark, THERMAL_UPSAMPLE
    else:
        # Amplitude falls as 1/d^2: detect in the flattened log amplitude; refine and
        # sample in the flattened linear amplitude (pixel integration is linear in it;
        # refining in log biased the corners, 0.085 -> 0.054 px mean).
        coarse = _flatten(np.log(np.maximum(x, 1.0)), TOF_FLATTEN_SIGMA_PX)
        fine = _flatten(x, TOF_FLATTEN_SIGMA_PX)
        s = TOF_UPSAMPLE
    s = s if upsample is None else upsample
    u8 = _stretch_u8(coarse)
    if u8 is None:
        return "the image has no contrast (blank image?)"
    extra = []
    if modality == "thermal":
        extra.append(("lcn", _upsample(_local_normalise_u8(coarse), s)))
    return _Prepared(
        s, _upsample(u8, s), modality == "thermal", _upsample(fine, s), fine, fine, extra
    )


def _upsampled(prep: _Prepared, s: int) -> _Prepared:
    """``prep`` (prepared at the original size, :func:`_prepare` with ``upsample=1``) with
    its detection and refinement images upsampled ``s`` x: the same images as
    ``_prepare(..., upsample=s)`` gives, without flattening and normalising again."""
    if s == 1:
        return prep
    return _Prepared(
        s,
        _upsample(prep.detect, s),
        prep.both_polarities,
        _upsample(prep.refine, s),
        prep.darkness,
        prep.fine,
        [(label, _upsample(image, s)) for label, image in prep.extra],
    )


def _native_levels(
    image: np.ndarray, modality: str, black_is_hot: bool
) -> Iterator[_Prepared | str]:
    """The prepared image (:func:`_prepare`), then for thermal the same without the
    upsampling. Squares that are large already (czha626's LWIR, 44 px) are found at their
    own size where the upsampled copy can fail: with white text burnt into the image, 2 of
    12 views (OpenCV's plain SB finds all 12 at the original size). Before both, the
    original size is probed (``_Prepared.probe``, ``NATIVE_FIRST_SPACING_PX``). All come
    from one preparation at the original size (:func:`_upsampled`)."""
    if modality == "color":
        yield _prepare(image, modality, black_is_hot)
        return
    native = _prepare(image, modality, black_is_hot, upsample=1)
    if isinstance(native, str):
        yield native
        return
    s = TOF_UPSAMPLE if modality == "tof" else THERMAL_UPSAMPLE
    if modality == "tof" or s == 1:
        yield _upsampled(native, s)
        return
    up = _upsampled(native, s)
    if native.detect.size > NATIVE_FIRST_ABOVE_PX:
        yield replace(native, probe=up.memo)  # large squares at their own size first
    yield up
    yield native


def _pyramid_levels(image: np.ndarray) -> Iterator[_Prepared | str]:
    """The prepared pyramid levels of a large colour image ((H, W, 3) RGB or (H, W) grey
    uint8), in the order ``PYRAMID_LEVELS_PX`` lists them, built as they are asked for; or
    the reason there is nothing to detect in."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    h, w = grey.shape
    long_side = max(h, w)
    lin = None
    for side in PYRAMID_LEVELS_PX:
        if side >= long_side:
            continue
        f = side / long_side
        size = (max(8, round(w * f)), max(8, round(h * f)))
        prep = _prepare(cv2.resize(grey, size, interpolation=cv2.INTER_AREA), "color", True)
        if isinstance(prep, str):
            yield prep
            return
        if lin is None:  # the same values as _prepare's, at 12 MP in ms (a table lookup)
            grey_levels = np.arange(256, dtype=np.float32) * np.float32(1.0 / 255.0)
            lin = cv2.LUT(grey, np.power(grey_levels, COLOR_GAMMA))
        prep.scale = (size[0] / w, size[1] / h)
        prep.darkness = lin
        prep.pyramid = True
        yield prep


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


# -- geometry of a detected grid ----------------------------------------------------------


def _grid_spacing(raw: np.ndarray, board: Board, shape: tuple[int, ...]) -> float | None:
    """The median corner spacing (pixels) of a detector's corners (any shape holding
    N x 2), or None unless they are the board's, finite and inside an image of ``shape``
    (H, W). The median: the classic detector's corners can be a few pixels astray before
    refinement."""
    pts = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    if len(pts) != board.n_corners or not np.all(np.isfinite(pts)):
        return None
    if np.any(pts < 0) or np.any(pts[:, 0] > shape[1] - 1) or np.any(pts[:, 1] > shape[0] - 1):
        return None
    return float(np.median(_spacing(pts.reshape(board.rows, board.cols, 2))))


def _spacing(G: np.ndarray) -> np.ndarray:
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


def _regular(G: np.ndarray) -> bool:
    """Every step along a row (column) points the way of the grid's mean row (column) step."""
    sx = np.diff(G, axis=1)
    sy = np.diff(G, axis=0)
    mx = sx.reshape(-1, 2).mean(axis=0)
    my = sy.reshape(-1, 2).mean(axis=0)
    return bool(np.all(sx @ mx > 0) and np.all(sy @ my > 0) and _min_spacing(G) > 0.5)


def _right_handed(G: np.ndarray) -> bool:
    """Whether the grid's +x (along a row) and +y (down a column) are right-handed in the
    image (x right, y down), judged from the mean row and column directions."""
    ax = (G[:, -1] - G[:, 0]).mean(axis=0)
    ay = (G[-1, :] - G[0, :]).mean(axis=0)
    return float(ax[0] * ay[1] - ax[1] * ay[0]) > 0


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
    float32) around the grid, blurred as :func:`_prepare` blurs its refine image. The
    half-window follows from the spacing at this size (0.4 x, clamped to 2-11 px), not from
    the level's: scaling the level's window up would span a whole square (FIELD-NOTES)."""
    h, w = lin.shape
    margin = SUBPIX_HALF_WINDOW_PX[1] + 4 * COLOR_REFINE_BLUR_PX + 2
    x0 = max(0, int(np.floor(G[..., 0].min() - margin)))
    x1 = min(w, int(np.ceil(G[..., 0].max() + margin)) + 1)
    y0 = max(0, int(np.floor(G[..., 1].min() - margin)))
    y1 = min(h, int(np.ceil(G[..., 1].max() + margin)) + 1)
    crop = cv2.GaussianBlur(lin[y0:y1, x0:x1], (0, 0), COLOR_REFINE_BLUR_PX)
    offset = np.array([x0, y0], dtype=np.float64)
    return _subpix(crop, G - offset) + offset


def _bend(G: np.ndarray) -> float:
    """Largest second difference along rows and columns, each over the local spacing."""
    sp = _spacing(G)
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
    every corner. The fine grid's own smoothness is checked afterwards (``_finish``)."""
    cands = [F, F[::-1, ::-1], F[::-1, :], F[:, ::-1]]
    if F.shape[0] == F.shape[1]:
        cands += [c.transpose(1, 0, 2) for c in cands]
    best, best_d = None, np.inf
    for cand in cands:
        d = float(np.median(np.linalg.norm(cand - G, axis=2)))
        if d < best_d:
            best, best_d = cand, d
    return best if best_d < FINE_MAX_SHIFT * float(np.median(_spacing(G))) else None


def _extended(G: np.ndarray) -> np.ndarray:
    """The grid ``G`` (rows, cols, 2) extended linearly by one square on every side:
    (rows + 2, cols + 2, 2), the corners of the board's outer squares."""
    E = np.concatenate([2 * G[:1] - G[1:2], G, 2 * G[-1:] - G[-2:-1]], axis=0)
    return np.concatenate([2 * E[:, :1] - E[:, 1:2], E, 2 * E[:, -1:] - E[:, -2:-1]], axis=1)


def _board_mask(G: np.ndarray, shape: tuple[int, int]) -> np.ndarray | None:
    """(H, W) bool: the checkered area of the grid ``G`` (rows, cols, 2), i.e. the inner
    corners' grid extended by one square on every side; None if that covers too few
    pixels to take percentiles of."""
    E = _extended(G)
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
    spacing = float(np.median(_spacing(G)))
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
        (_stretch_u8(image, mask), flags)
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
            up = _upsample(u8, s)
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
        :data:`COLOUR_AGREEMENT`, :data:`COLOUR_MIN_SEPARATION`), for a caller to judge.
    """
    G = np.asarray(corners, dtype=np.float64).reshape(board.rows, board.cols, 2)
    G, agreement, separation = _orient(G, board, darkness)
    return np.ascontiguousarray(G.reshape(-1, 2)), agreement, separation


def _orient(G: np.ndarray, board: Board, darkness: np.ndarray) -> tuple[np.ndarray, float, float]:
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
    need = np.maximum(BORDER_MIN_PX, fraction * _spacing(G).ravel())
    slack = dist - need[:, None]
    if not (slack < 0).any():
        return None
    k, side = np.unravel_index(np.argmin(slack), slack.shape)
    edge = ("left", "right", "top", "bottom")[side]
    return (
        f"board touches the image border (corner {k} is {dist[k, side]:.1f} px from the "
        f"{edge} edge, at least {need[k]:.1f} px needed)"
    )


def _ring_problem(darkness: np.ndarray, G: np.ndarray) -> str | None:
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
    E = _extended(G)
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


def _refined(
    G: np.ndarray, prep: _Prepared, board: Board, classic: bool, fallback: bool
) -> Iterator[tuple[np.ndarray, str]]:
    """Refinements of the detector's grid ``G`` ((rows, cols, 2), pixels of
    ``prep.detect``) in original pixels, with the method suffix of each, best first; the
    caller takes the first that forms a smooth grid.

    1. The fine stage (:func:`_fine`), where the modality has one.
    2. cornerSubPix (:func:`_subpix`; a pyramid level: again at the original size).
    3. With ``fallback`` instead (:func:`detect_board` asks for it only when no detector
       gave a grid that 1 or 2 made smooth), not on pyramid levels: cornerSubPix with a
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


def _finish(
    raw: np.ndarray,
    prep: _Prepared,
    board: Board,
    shape: tuple[int, int],
    classic: bool,
    fallback: bool = False,
) -> tuple[np.ndarray, str]:
    """Refined corners (N, 2) in original pixels and canonical order, and the method
    suffix (``fallback``: :func:`_refined`'s); raises _Rejected."""
    rows, cols = board.rows, board.cols
    pts = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
    if len(pts) != board.n_corners:
        raise _Rejected(f"detector returned {len(pts)} corners, expected {board.n_corners}", False)
    if not np.all(np.isfinite(pts)):
        raise _Rejected("detector returned non-finite corners", False)
    G = pts.reshape(rows, cols, 2)
    if not _regular(G):
        raise _Rejected("detected corners do not form a regular grid", False)
    h, w = shape
    smooth = (
        (R, sfx)
        for R, sfx in _refined(G, prep, board, classic, fallback)
        if np.all(np.isfinite(R)) and _regular(R) and _bend(R) <= GRID_MAX_BEND
    )
    G, suffix = next(smooth, (None, ""))
    if G is None:
        raise _Rejected(
            "the refined corners do not form a smooth grid (a corner went astray)", False, True
        )
    problem = _ring_problem(prep.darkness, G) if prep.pyramid else None
    if problem:
        raise _Rejected(problem, False)
    G, agreement, separation = _orient(G, board, prep.darkness)
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

        prep = _prepare(img, modality, thermal_black_is_hot)
        if isinstance(prep, str):
            return Detection(None, f"board not found: {prep}", None)
        find = find_charuco if board.pattern == "charuco" else find_circles
        return Detection(*find(prep.detect, int(prep.scale), board, modality != "color"))
    shape = img.shape[:2]

    preps: Iterable[_Prepared | str]
    if pyramid and modality == "color" and max(shape) > PYRAMID_ABOVE_PX:
        preps = _pyramid_levels(img)
    else:
        preps = _native_levels(img, modality, thermal_black_is_hot)
    first_rejection: Detection | None = None
    tried: list[str] = []
    bent: list[tuple[np.ndarray, _Prepared, bool, str]] = []  # for _refined's fallback
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
                    spacing = _grid_spacing(raw, board, image.shape)
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
