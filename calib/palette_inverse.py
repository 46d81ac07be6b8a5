"""False-colour (palette) thermal images mapped back to one scalar per pixel, for geometry.

Cheap thermal cores and vendor tools save what the operator saw: an 8-bit RGB picture in
which a palette (iron, rainbow, jet, ...) stands for the temperature. The temperature
itself is gone (the span and the tool's contrast curve are unknown), but the palette's
*position* of every pixel is not: it is monotonic in temperature within the picture, and
that is all board detection needs. :func:`invert_palette` recovers it:

1. **Known palettes.** Every candidate table (256 RGB entries, entry 0 the cold end) is
   tried on the image's distinct colours: each colour goes to its nearest point on the
   polyline through the table's entries (the nearest entry, then the projection onto the
   segment before or after it, so the position is fractional), and the table *fits* when
   at least :data:`FIT_SHARE` of the pixels lie within :data:`FIT_TOLERANCE_RGB` of it. Of
   the tables that fit, the one with the smallest mean distance wins (on a tie, the one
   listed first). The candidates are the caller's tables (``app`` passes the project's own
   from :mod:`fusion.palettes`) followed by :func:`builtin_palettes`: a grey ramp and
   OpenCV's colour maps (``cv2.applyColorMap``: jet, inferno, turbo, hot, ...), which tools
   built on OpenCV apply.
2. **The image's own curve.** When no table fits, the colours may still lie on one curve
   through RGB (an unknown vendor palette). The distinct colours are binned
   (:data:`CURVE_BIN_RGB`), the rarest bins holding :data:`CURVE_PRUNE_SHARE` of the
   pixels are set aside (text, JPEG fringes), and the longest path of the bins' minimum
   spanning tree is taken as the curve. Links between bins that never meet in
   neighbouring pixels cost :data:`UNSEEN_LINK_FACTOR` times more: the curve follows the
   picture's gradients rather than a shortcut between two branches of a palette that
   pass close to each other. The curve is then lengthened at its ends to reach the
   extreme colours and refined twice (a principal-curve step: the mean colour of each of
   :data:`CURVE_REFINE_SECTIONS` sections along it), resampled to 256 entries by arc
   length and oriented so that entry 0 is the darker end (luma): "brighter is hotter", as
   in grey, iron and most palettes (a guess; the board polarity is found from the data
   later anyway). It is refused when it comes back on itself (:data:`FOLD_CLOSE_RGB`: a
   cyclic palette such as HSV), when more than ``1 - FIT_SHARE`` of the pixels lie off
   it, or when its order tears the picture apart (:data:`TEAR_SHARE`: neighbouring
   pixels of nearly one colour far apart along it). Positions along it are monotonic in
   the palette's, not proportional to them.

Black-hot grey cannot be told from white-hot grey (the same colours in reverse): a grey
image reads white-hot. Which squares of the board are hot is found from the data later
(:mod:`calib.polarity`), so this costs nothing for geometry.

The result is **not radiometric**: palette positions 0-255, not kelvin. Pure: arrays in,
arrays and a :class:`PaletteFit` out; no loops over pixels (one ``np.unique`` of the packed
colours, then matrix products over the distinct colours, in chunks).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import Literal

import cv2
import numpy as np

__all__ = [
    "CURVE_BIN_RGB",
    "CURVE_PRUNE_SHARE",
    "CURVE_REFINE_SECTIONS",
    "FIT_SHARE",
    "FIT_TOLERANCE_RGB",
    "FOLD_CLOSE_RGB",
    "TEAR_SHARE",
    "UNSEEN_LINK_FACTOR",
    "PaletteError",
    "PaletteFit",
    "builtin_palettes",
    "invert_palette",
    "palette_positions",
]

FIT_TOLERANCE_RGB = 12.0
"""A pixel lies on a palette when its colour is within this Euclidean RGB distance (0-255
units) of the palette's polyline."""
FIT_SHARE = 0.9
"""Share of the pixels that must lie on a palette for it to fit (the rest: overlaid text,
JPEG's colour fringes at sharp edges)."""
SELECT_BIN_RGB = 8
"""The tables are ranked on the image's colours binned in cubes of this size (RGB units),
then the best that fits is judged on every distinct colour."""
CURVE_BIN_RGB = 16
"""Bin size (RGB units per channel) of the colours the image's own curve is built from."""
CURVE_PRUNE_SHARE = 0.03
"""The rarest colour bins holding together at most this share of the pixels are left out
when the image's own curve is built (they are still inverted and counted by the fit)."""
FOLD_APART_RGB = 128.0
FOLD_CLOSE_RGB = 48.0
"""The image's own curve is refused when two of its points at least ``FOLD_APART_RGB``
apart along it (arc length, RGB units) are closer than ``FOLD_CLOSE_RGB`` in colour: no
position can be read there. On every known palette such points are at least 66 apart
(lava)."""
CURVE_REFINE_PASSES = 2
CURVE_REFINE_SECTIONS = 64
"""The image's own curve is refined this many times by the mean colour of each of this
many sections along it (a principal-curve step), which follows the colours more closely
than the bins it was first built from."""
UNSEEN_LINK_FACTOR = 3.0
"""In the image's own curve, a link between two colour bins that never meet in adjacent
pixels counts this many times its colour distance."""
TEAR_STEP = 64.0
TEAR_SHARE = 1e-4
"""The image's own curve is refused when more than ``TEAR_SHARE`` of the neighbouring
pixel pairs are nearly the same colour but ``TEAR_STEP`` or more apart on it (0-255)."""
CURVE_MAX_BINS = 1500
"""At most this many bins enter the spanning tree (else the bins are made twice as big)."""
_CHUNK = 8192
_LUMA = np.array([0.299, 0.587, 0.114])

#: OpenCV's colour maps offered as known palettes; the cyclic ones (hsv, twilight) are
#: left out: their two ends are the same colour, so no position can be read from them.
_OPENCV_MAPS = (
    "jet",
    "inferno",
    "turbo",
    "hot",
    "magma",
    "plasma",
    "viridis",
    "cividis",
    "parula",
    "rainbow",
    "bone",
    "ocean",
    "pink",
    "deepgreen",
    "autumn",
    "cool",
    "spring",
    "summer",
    "winter",
)


class PaletteError(ValueError):
    """A false-colour image whose colours follow no known palette and no single curve."""


@dataclass(frozen=True)
class PaletteFit:
    """How a false-colour image was mapped back to a scalar.

    Attributes:
        palette: the known palette's name, or ``"own curve"`` (the image's colours).
        method: ``"known"`` (a listed table) or ``"curve"`` (the image's own curve).
        mean_distance_rgb: mean distance of the pixels' colours from the palette's
            polyline, RGB units (0-255): about 0 for a lossless file, 2-5 after JPEG.
        share_on_palette: share of the pixels within :data:`FIT_TOLERANCE_RGB` of it.
        colours: distinct colours in the image.
    """

    palette: str
    method: Literal["known", "curve"]
    mean_distance_rgb: float
    share_on_palette: float
    colours: int

    @property
    def what(self) -> str:
        """The palette in words: ``"palette iron"``, or for the image's own curve
        ``"an unknown palette, read along the image's own colour curve (dark = cold)"``."""
        if self.method == "known":
            return f"palette {self.palette}"
        return "an unknown palette, read along the image's own colour curve (dark = cold)"


@cache
def builtin_palettes() -> dict[str, np.ndarray]:
    """The palettes known without the caller's: ``grey`` (a 0-255 ramp, white-hot) and
    OpenCV's non-cyclic colour maps as ``opencv_<name>``. Each table is (256, 3) uint8 RGB,
    read-only, entry 0 the palette's first colour (what the tool gives its lowest value)."""
    ramp = np.arange(256, dtype=np.uint8)
    tables = {"grey": np.repeat(ramp[:, None], 3, axis=1)}
    for name in _OPENCV_MAPS:
        code = getattr(cv2, f"COLORMAP_{name.upper()}", None)
        if code is None:  # an older OpenCV without this map
            continue
        bgr = cv2.applyColorMap(ramp.reshape(256, 1), code).reshape(256, 3)
        tables[f"opencv_{name}"] = np.ascontiguousarray(bgr[:, ::-1])
    for t in tables.values():
        t.flags.writeable = False
    return tables


def _check_table(name: str, table: object) -> np.ndarray:
    if (
        not isinstance(table, np.ndarray)
        or table.ndim != 2
        or table.shape[1] != 3
        or table.shape[0] < 2
        or not np.all(np.isfinite(table))
    ):
        got = (
            f"shape {table.shape}, dtype {table.dtype}"
            if isinstance(table, np.ndarray)
            else type(table).__name__
        )
        raise ValueError(f"palette {name!r}: expected an (N >= 2, 3) RGB table, got {got}")
    return table.astype(np.float32)


def palette_positions(colours: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position of every colour along a palette, and its distance from the palette.

    Args:
        colours: (K, 3) RGB, any real dtype.
        table: (M, 3) RGB, the palette's entries in order (M >= 2).

    Returns:
        ``(position, distance)``, both (K,) float32: the fractional entry index in
        [0, M - 1] of the nearest point on the polyline through the entries (nearest
        entry, then the segment to the previous or next entry, whichever is closer), and
        the Euclidean RGB distance to that point.
    """
    t = _check_table("table", table)
    c_all = np.ascontiguousarray(colours, dtype=np.float32).reshape(-1, 3)
    m = len(t)
    tt = np.einsum("ij,ij->i", t, t)
    seg = np.diff(t, axis=0)  # (M-1, 3): entry i -> i+1
    seg_len2 = np.einsum("ij,ij->i", seg, seg)
    pos = np.empty(len(c_all), np.float32)
    dist = np.empty(len(c_all), np.float32)
    tt_rows = np.repeat(tt[None, :], min(_CHUNK, len(c_all)), axis=0)
    for start in range(0, len(c_all), _CHUNK):
        c = c_all[start : start + _CHUNK]
        # |c - t|^2 - |c|^2, (k, M). cv2.gemm rather than numpy's matmul: BLAS's threads
        # made it 8 times slower on a busy 2-core machine.
        d2 = cv2.gemm(c, t, -2.0, tt_rows[: len(c)], 1.0, flags=cv2.GEMM_2_T)
        i = np.argmin(d2, axis=1)
        best_pos = i.astype(np.float32)
        best_d2 = np.einsum("ij,ij->i", c - t[i], c - t[i])
        for side in (0, 1):  # segment after (i -> i+1) and before (i-1 -> i)
            j = np.clip(i if side == 0 else i - 1, 0, m - 2)
            valid = (i < m - 1) if side == 0 else (i > 0)
            a, s, s2 = t[j], seg[j], seg_len2[j]
            with np.errstate(invalid="ignore", divide="ignore"):
                u = np.where(s2 > 0, np.einsum("ij,ij->i", c - a, s) / s2, 0.0)
            u = np.clip(u, 0.0, 1.0)
            q = a + u[:, None] * s
            d2s = np.einsum("ij,ij->i", c - q, c - q)
            better = valid & (d2s < best_d2)
            best_d2 = np.where(better, d2s, best_d2)
            best_pos = np.where(better, j + u, best_pos)
        pos[start : start + len(c)] = best_pos
        dist[start : start + len(c)] = np.sqrt(np.maximum(best_d2, 0.0))
    return pos, dist


@dataclass(frozen=True, eq=False)
class _Colours:
    """The distinct colours of an image: (K, 3) float32 RGB, (K,) pixel counts, and the
    (H*W,) index of every pixel's colour."""

    rgb: np.ndarray
    counts: np.ndarray
    inverse: np.ndarray


def _distinct(rgb: np.ndarray) -> _Colours:
    packed = (
        (rgb[:, :, 0].astype(np.uint32) << 16)
        | (rgb[:, :, 1].astype(np.uint32) << 8)
        | rgb[:, :, 2].astype(np.uint32)
    ).ravel()
    keys, inverse, counts = np.unique(packed, return_inverse=True, return_counts=True)
    cols = np.stack([(keys >> 16) & 255, (keys >> 8) & 255, keys & 255], axis=1)
    return _Colours(cols.astype(np.float32), counts, inverse.ravel())


def _score(dist: np.ndarray, counts: np.ndarray) -> tuple[float, float]:
    """(share of pixels within the tolerance, mean distance of the pixels)."""
    total = float(counts.sum())
    share = float(counts[dist <= FIT_TOLERANCE_RGB].sum()) / total
    return share, float(np.dot(dist, counts)) / total


def _bins(colours: _Colours, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct colours binned in cubes of ``step`` RGB units: the bins' (n, 3) mean
    colours (pixel-weighted), their (n,) pixel counts, and the (K,) bin of every colour."""
    cell = (colours.rgb // step).astype(np.int64)
    key = (cell[:, 0] * 256 + cell[:, 1]) * 256 + cell[:, 2]
    _, which = np.unique(key, return_inverse=True)
    which = which.ravel()
    w = np.bincount(which, weights=colours.counts)
    sums = [np.bincount(which, weights=colours.rgb[:, k] * colours.counts) for k in range(3)]
    return np.stack(sums, axis=1) / w[:, None], w, which


def _neighbours(pixel_bin: np.ndarray, n: int) -> np.ndarray:
    """(n, n) bool: which bins meet in horizontally or vertically adjacent pixels (at
    least twice). ``pixel_bin`` is (H, W), -1 for pixels of bins left out."""
    pairs = []
    for a, b in (
        (pixel_bin[:, :-1], pixel_bin[:, 1:]),
        (pixel_bin[:-1, :], pixel_bin[1:, :]),
    ):
        m = (a != b) & (a >= 0) & (b >= 0)
        lo, hi = np.minimum(a[m], b[m]), np.maximum(a[m], b[m])
        pairs.append(lo.astype(np.int64) * n + hi)
    keys, counts = np.unique(np.concatenate(pairs), return_counts=True)
    keys = keys[counts >= 2]
    adjacent = np.zeros((n, n), bool)
    adjacent[keys // n, keys % n] = True
    return adjacent | adjacent.T


def _own_curve(colours: _Colours, shape: tuple[int, int]) -> np.ndarray | str:
    """The image's colour curve as a (256, 3) float32 table, darker end first, or the
    reason there is none. ``shape`` is the image's (H, W)."""
    # Imported here: scipy.sparse takes 0.1-0.4 s to import, and only this path needs it.
    from scipy.sparse.csgraph import minimum_spanning_tree, shortest_path

    step = CURVE_BIN_RGB
    while True:
        mean, w, which = _bins(colours, step)
        order = np.argsort(w, kind="stable")
        rare = np.cumsum(w[order]) <= CURVE_PRUNE_SHARE * w.sum()
        keep = np.sort(order[~rare])
        if len(keep) <= CURVE_MAX_BINS or step >= 64:
            break
        step *= 2
    points = mean[keep]
    if len(points) < 2:
        return np.repeat(points[:1], 256, axis=0).astype(np.float32)
    compact = np.full(len(mean), -1, np.int64)
    compact[keep] = np.arange(len(keep))
    pixel_bin = compact[which[colours.inverse]].reshape(shape)
    dist = np.sqrt(((points[:, None, :] - points[None, :, :]) ** 2).sum(-1))
    # Colours next to each other in the picture are next to each other on the palette:
    # links between bins never seen side by side cost UNSEEN_LINK_FACTOR times more, so
    # the tree follows the image's gradients, not a shortcut between two branches of the
    # palette that happen to be close in colour.
    dist[~_neighbours(pixel_bin, len(points))] *= UNSEEN_LINK_FACTOR
    tree = minimum_spanning_tree(dist)
    from_any = shortest_path(tree, directed=False, indices=0)
    a = int(np.argmax(from_any))
    from_a, pred = shortest_path(tree, directed=False, indices=a, return_predecessors=True)
    b = int(np.argmax(from_a))
    path = [b]
    while path[-1] != a:
        path.append(int(pred[path[-1]]))
    table = _resample(points[path], smooth=True)
    for _ in range(CURVE_REFINE_PASSES):
        table = _refine(_extend_ends(table, colours), colours)
    if table[0] @ _LUMA > table[-1] @ _LUMA:
        table = table[::-1]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(table, axis=0), axis=1))])
    # A fold: two points of the curve close in colour but far apart along it (a closed
    # loop, as a cyclic palette makes, is one: its two ends meet).
    apart = np.abs(np.subtract.outer(s, s))
    close = np.sqrt(((table[:, None, :] - table[None, :, :]) ** 2).sum(-1))
    fold = (close < FOLD_CLOSE_RGB) & (apart >= FOLD_APART_RGB)
    if fold.any():
        i, j = np.argwhere(fold)[0]
        return (
            f"the curve through its colours comes back on itself: RGB {_rgb_text(table[i])} "
            f"and {_rgb_text(table[j])} are {apart[i, j]:.0f} apart along it, "
            f"{close[i, j]:.0f} in colour (a cyclic palette such as HSV, or crossing colours)"
        )
    return table.astype(np.float32)


def _resample(curve: np.ndarray, smooth: bool = False) -> np.ndarray:
    """A polyline (L, 3) resampled to 256 points evenly spaced along its length (a
    moving average of 3 first if ``smooth``: it takes out the zig-zag between bins)."""
    if smooth and len(curve) >= 3:
        inner = (curve[:-2] + curve[1:-1] + curve[2:]) / 3.0
        curve = np.vstack([curve[:1], inner, curve[-1:]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    if arc[-1] <= 0:
        return np.repeat(curve[:1], 256, axis=0)
    s = np.linspace(0.0, arc[-1], 256)
    return np.stack([np.interp(s, arc, curve[:, k]) for k in range(3)], axis=1)


def _extend_ends(table: np.ndarray, colours: _Colours) -> np.ndarray:
    """The curve lengthened at each end, straight along its last few entries, as far as
    the colours beyond that end reach (those within ``2 * FIT_TOLERANCE_RGB`` of the
    line): the curve is built from bins, whose means lie inside the extreme bins, and
    from the common colours only, so the rarest extreme colours (the hottest and coldest
    pixels) would otherwise all sit on the end. The ends stay inside the RGB cube."""
    pos, _ = palette_positions(colours.rgb, table)
    ends = []
    for end, inner, at in ((0, 8, 0.0), (-1, -9, 255.0)):
        direction = table[end] - table[inner]
        norm = np.linalg.norm(direction)
        beyond = colours.rgb[pos == at] - table[end]
        if norm == 0 or len(beyond) == 0:
            ends.append(table[end])
            continue
        direction = direction / norm
        along = beyond @ direction
        perp = np.linalg.norm(beyond - along[:, None] * direction, axis=1)
        reach = along[(along > 0) & (perp <= 2.0 * FIT_TOLERANCE_RGB)]
        ends.append(table[end] + (reach.max() if len(reach) else 0.0) * direction)
    # a colour cannot leave the RGB cube, however far the line goes
    return _resample(np.clip(np.vstack([ends[0], table, ends[1]]), 0.0, 255.0))


def _refine(table: np.ndarray, colours: _Colours) -> np.ndarray:
    """One principal-curve step: every colour near the curve goes to its position along
    it, and the curve becomes the pixel-weighted mean colour of each of
    ``CURVE_REFINE_SECTIONS`` equal sections of positions (empty sections dropped)."""
    pos, dist = palette_positions(colours.rgb, table)
    near = dist <= 2.0 * FIT_TOLERANCE_RGB
    section = np.minimum(
        (pos[near] * (CURVE_REFINE_SECTIONS / 255.0)).astype(np.int64), CURVE_REFINE_SECTIONS - 1
    )
    w = np.bincount(section, weights=colours.counts[near], minlength=CURVE_REFINE_SECTIONS)
    sums = [
        np.bincount(
            section,
            weights=colours.rgb[near, k] * colours.counts[near],
            minlength=CURVE_REFINE_SECTIONS,
        )
        for k in range(3)
    ]
    filled = w > 0
    if filled.sum() < 2:
        return table
    means = np.stack(sums, axis=1)[filled] / w[filled, None]
    # keep the curve's ends where they were: a section's mean pulls them inwards
    return _resample(np.vstack([table[:1], means, table[-1:]]))


def _tear_share(rgb: np.ndarray, scalar: np.ndarray) -> float:
    """Share of the horizontally or vertically neighbouring pixel pairs whose colours are
    within FIT_TOLERANCE_RGB of each other but whose scalars (0-255) differ by at least
    TEAR_STEP: places where the order along the curve tears what the picture joins."""
    c = rgb.astype(np.float32)
    torn = total = 0
    for axis in (0, 1):
        dc = np.sqrt((np.diff(c, axis=axis) ** 2).sum(-1))
        ds = np.abs(np.diff(scalar, axis=axis))
        torn += int(np.count_nonzero((dc <= FIT_TOLERANCE_RGB) & (ds >= TEAR_STEP)))
        total += dc.size
    return torn / max(total, 1)


def _rgb_text(c: np.ndarray) -> str:
    return "(" + ", ".join(f"{round(float(v))}" for v in c) + ")"


def invert_palette(
    rgb: np.ndarray, palettes: Mapping[str, np.ndarray] | None = None, *, builtin: bool = True
) -> tuple[np.ndarray, PaletteFit]:
    """Map a false-colour image back to its palette position (module docstring).

    Args:
        rgb: (H, W, 3) uint8 RGB (not BGR).
        palettes: known palettes to try first, name -> (N, 3) RGB table, cold end first;
            :func:`builtin_palettes` are tried after them unless ``builtin`` is False.

    Returns:
        ``(scalar, fit)``: (H, W) float32 palette position scaled to 0-255 (0 = the
        palette's first entry; for the image's own curve, its darker end), and how it was
        found. Not kelvin.

    Raises:
        PaletteError: the colours follow no known palette and no single curve (the message
            says which palette came closest and why the curve failed).
        ValueError: ``rgb`` or a table is malformed.
    """
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3:
        got = f"{rgb.dtype} {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise ValueError(f"rgb: expected an (H, W, 3) uint8 RGB image, got {got}")
    if rgb.shape[2] != 3 or rgb.size == 0:
        raise ValueError(f"rgb: expected an (H, W, 3) uint8 RGB image, got shape {rgb.shape}")
    candidates = {**(palettes or {}), **(builtin_palettes() if builtin else {})}
    tables = {name: _check_table(name, t) for name, t in candidates.items()}
    colours = _distinct(rgb)
    # Rank the tables on the binned colours (fast): those that fit first, then by mean
    # distance, then in the order given; judge them on every distinct colour.
    bin_rgb, bin_counts, _ = _bins(colours, SELECT_BIN_RGB)
    ranked = []
    for k, (name, t) in enumerate(tables.items()):
        share, mean = _score(palette_positions(bin_rgb, t)[1], bin_counts)
        ranked.append((share < FIT_SHARE, mean, k, name, share))
    ranked.sort()
    closest = (ranked[0][3], ranked[0][4]) if ranked else None
    for name in (r[3] for r in ranked if not r[0]):
        pos, dist = palette_positions(colours.rgb, tables[name])
        share, mean = _score(dist, colours.counts)
        if share >= FIT_SHARE:
            pos *= 255.0 / (len(tables[name]) - 1)
            fit = PaletteFit(name, "known", mean, share, len(colours.rgb))
            break
    else:  # no table fits every colour: the image's own curve
        pos, fit = _along_own_curve(rgb, colours, closest)
    return pos[colours.inverse].reshape(rgb.shape[:2]), fit


def _along_own_curve(
    rgb: np.ndarray, colours: _Colours, closest: tuple[str, float] | None
) -> tuple[np.ndarray, PaletteFit]:
    """(K,) float32 positions 0-255 of the distinct colours along the image's own curve,
    and the fit; PaletteError when there is no such curve (``closest``: the known palette
    that came closest, for the message)."""
    table = _own_curve(colours, rgb.shape[:2])
    if isinstance(table, str):
        raise PaletteError(_refusal(closest, table))
    pos, dist = palette_positions(colours.rgb, table)
    share, mean = _score(dist, colours.counts)
    if share < FIT_SHARE:
        raise PaletteError(
            _refusal(
                closest,
                f"{100 * (1 - share):.0f} % of its pixels lie farther than "
                f"{FIT_TOLERANCE_RGB:g} from the best single curve through its colours",
            )
        )
    torn = _tear_share(rgb, pos[colours.inverse].reshape(rgb.shape[:2]))
    if torn > TEAR_SHARE:
        raise PaletteError(
            _refusal(
                closest,
                f"{100 * torn:.2f} % of the neighbouring pixels have nearly the same colour "
                "but far apart places on the best curve through its colours: the curve "
                "misses the palette's order",
            )
        )
    return pos, PaletteFit("own curve", "curve", mean, share, len(colours.rgb))


def _refusal(closest: tuple[str, float] | None, why_not_curve: str) -> str:
    known = "no palette was given"
    if closest is not None:
        name, share = closest
        known = (
            f"closest: {name}, {100 * share:.0f} % of the pixels within "
            f"{FIT_TOLERANCE_RGB:g} RGB of it, {100 * FIT_SHARE:.0f} % needed"
        )
    return (
        f"its colours follow no known palette ({known}) and no single curve "
        f"({why_not_curve}); save the thermal image as grey or 16-bit"
    )
