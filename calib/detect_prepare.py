"""Sensor images made ready for the checkerboard detectors of :mod:`calib.detect`.

Per modality (calib.detect's module docstring says why each step): colour is linearised
and lightly blurred for the refinement; thermal is destriped, flattened, stretched to 8 bit,
upsampled and also locally normalised (:func:`native_levels` also gives it at its own size);
TOF amplitude is flattened (its log for the detectors), stretched and upsampled; a large
colour image is searched on downscaled copies (:func:`pyramid_levels`). Each comes out as a
:class:`Prepared`: the detection image, the refinement image and the images the square
colours and the fine stage sample. Pure: arrays in, arrays out.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

COLOR_GAMMA = 2.2
"""Colour images are assumed gamma-encoded (sRGB-like); the sub-pixel refinement runs on
intensities linearised with this exponent. On the simulator (gamma 1/2.2) this halves the
corner bias (mean RMS 0.057 -> 0.030 px); on the real OpenCV sample images it lowers the
calibration RMS too (0.196 -> 0.193 px). Use 1.0 for a linear camera."""
COLOR_REFINE_BLUR_PX = 1.0
"""Gaussian sigma applied before the colour refinement; sharp, pixel-integrated edges
otherwise bias ``cornerSubPix`` (measured 0.073 -> 0.057 px mean without linearising)."""
PYRAMID_LEVELS_PX = (1000, 500, 2000)
"""Longer sides of the downscaled copies, in the order they are searched (levels not
smaller than the image are skipped). 1000 and 2000 px are what OpenCV users downscale 12 MP
views to; 500 px catches boards that fill the frame, whose textured surroundings (grass)
break the detectors at 1000 px."""
THERMAL_FLATTEN_SIGMA_PX = 25.0
"""Sigma of the background blur subtracted from thermal images, native pixels."""
THERMAL_UPSAMPLE = 2
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


@dataclass
class Prepared:
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
            squares around the grid are checked (:func:`calib.detect_order.ring_problem`).
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
            what :func:`calib.detect._finish` made of them, or None before it ran]: shared
            by the probe and the level of the same size, so that no detector runs twice on an image.
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


def stretch_u8(x: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray | None:
    """Percentile stretch of a float image to uint8 (the percentiles of the pixels where
    ``mask`` (same shape, bool) is set, if given; the rest clips); None if it has no
    contrast."""
    lo, hi = np.percentile(x if mask is None else x[mask], STRETCH_PERCENTILES)
    if not hi - lo > 1e-6 * max(1.0, abs(float(hi)), abs(float(lo))):
        return None
    y = (x - lo) * (255.0 / (hi - lo)) + 0.5
    return np.clip(y, 0, 255).astype(np.uint8)


def finite_filled(image: np.ndarray) -> np.ndarray | None:
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


def upsample_image(x: np.ndarray, s: int) -> np.ndarray:
    if s == 1:
        return x
    return cv2.resize(x, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)


def prepare(
    image: np.ndarray, modality: str, black_is_hot: bool, upsample: int | None = None
) -> Prepared | str:
    """The prepared image, or the reason there is nothing to detect in; ``upsample``
    overrides the thermal / TOF upsampling factor."""
    if modality == "color":
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if int(grey.max()) - int(grey.min()) < 8:
            return "the image has no contrast (blank image?)"
        lin = np.power(grey.astype(np.float32) * np.float32(1.0 / 255.0), COLOR_GAMMA)
        refine = cv2.GaussianBlur(lin, (0, 0), COLOR_REFINE_BLUR_PX)
        return Prepared(1, grey, False, refine, lin)

    x = finite_filled(image)
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
    u8 = stretch_u8(coarse)
    if u8 is None:
        return "the image has no contrast (blank image?)"
    extra = []
    if modality == "thermal":
        extra.append(("lcn", upsample_image(_local_normalise_u8(coarse), s)))
    return Prepared(
        s, upsample_image(u8, s), modality == "thermal", upsample_image(fine, s), fine, fine, extra
    )


def _upsampled(prep: Prepared, s: int) -> Prepared:
    """``prep`` (prepared at the original size, :func:`prepare` with ``upsample=1``) with
    its detection and refinement images upsampled ``s`` x: the same images as
    ``prepare(..., upsample=s)`` gives, without flattening and normalising again."""
    if s == 1:
        return prep
    return Prepared(
        s,
        upsample_image(prep.detect, s),
        prep.both_polarities,
        upsample_image(prep.refine, s),
        prep.darkness,
        prep.fine,
        [(label, upsample_image(image, s)) for label, image in prep.extra],
    )


def native_levels(image: np.ndarray, modality: str, black_is_hot: bool) -> Iterator[Prepared | str]:
    """The prepared image (:func:`prepare`), then for thermal the same without the
    upsampling. Squares that are large already (czha626's LWIR, 44 px) are found at their
    own size where the upsampled copy can fail: with white text burnt into the image, 2 of
    12 views (OpenCV's plain SB finds all 12 at the original size). Before both, the
    original size is probed (``Prepared.probe``, ``NATIVE_FIRST_SPACING_PX``). All come
    from one preparation at the original size (:func:`_upsampled`)."""
    if modality == "color":
        yield prepare(image, modality, black_is_hot)
        return
    native = prepare(image, modality, black_is_hot, upsample=1)
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


def pyramid_levels(image: np.ndarray) -> Iterator[Prepared | str]:
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
        prep = prepare(cv2.resize(grey, size, interpolation=cv2.INTER_AREA), "color", True)
        if isinstance(prep, str):
            yield prep
            return
        if lin is None:  # the same values as prepare's, at 12 MP in ms (a table lookup)
            grey_levels = np.arange(256, dtype=np.float32) * np.float32(1.0 / 255.0)
            lin = cv2.LUT(grey, np.power(grey_levels, COLOR_GAMMA))
        prep.scale = (size[0] / w, size[1] / h)
        prep.darkness = lin
        prep.pyramid = True
        yield prep
