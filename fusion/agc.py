"""Automatic gain control (AGC): how the temperatures of a stereo frame become palette indices.

A thermal camera's AGC decides which palette entry (0 = cold end .. 255 = hot end) each
temperature gets. The modes (:data:`AGC_MODES`, the ``agc`` of
:class:`fusion.compose.DisplaySettings`):

``linear``
    ``index = round(255 (T - low) / (high - low))``, saturated to [0, 255], over the span
    ``(low, high)`` (:func:`fusion.palettes.temperature_index`; the mapping before AGC
    existed). One hot object stretches the span and flattens everything else.
``plateau``
    plateau histogram equalization (the default): the histogram of both eyes' fused kelvin
    values in bins of :data:`BIN_K` over the span, every bin capped at ``plateau`` times
    the number of samples (so that no temperature, however many pixels show it, takes more
    than that share of the palette: a wall does not eat the palette, a small hot pipe does
    not flatten the rest), its cumulative sum normalised to [0, 1] is the palette position
    of each temperature. :data:`LINEAR_SHARE` of the position is linear in temperature, so
    the mapping is strictly increasing (every temperature has one position and the tick
    temperatures are unique) and a temperature range empty in this frame still has a few
    palette steps. ``plateau`` 1 is plain histogram equalization. The table's slope is then
    capped at ``max_gain`` palette steps per kelvin (:func:`cap_gain`, a thermal camera's
    "max gain"): a temperature range that fills much of the picture (the walls) is not
    stretched over the palette, so neither the imagers' noise (NETD 0.08 K) nor an offset
    between the two imagers is magnified beyond ``max_gain`` steps per kelvin; the share
    the cap takes from those ranges goes to the temperatures near those the picture shows
    (the shares smoothed over :data:`GAIN_SPREAD_K`). With an automatic span the span is at
    least ``255 / max_gain`` wide (:func:`gain_span`), so a flat scene takes the middle of
    the palette at ``max_gain`` steps per kelvin.
``dde``
    digital detail enhancement (local contrast, as FLIR's DDE): the kelvin image is split
    into a base layer (an edge-preserving bilateral filter at 1/:data:`DDE_SCALE` of the
    resolution, about the thermal imager's own, brought back to full resolution) and a
    detail layer (image - base); the base goes through the ``plateau`` table (gain capped
    as there), the detail is
    added amplified (:data:`DDE_GAIN_PER_K` palette steps per kelvin, at most
    :data:`DDE_DETAIL_MAX` steps either way). Fine texture a wide span would hide shows.

One table serves both eyes: it is computed over both eyes' images together (the method's
colour-balance requirement: one temperature, one colour, in both eyes), so the same
temperature gets the same index in both (in ``dde``, the same temperature with the same
surroundings). :class:`ToneMapper` smooths the table over frame time (the time constant of
the span smoothing, on the frames' ``stamp_ns``) so the picture does not pump as objects
come and go; :class:`ToneMap` is one frame's table, with the temperature at every palette
position (:meth:`ToneMap.temperatures_k`, the viewer's tick labels: non-linear under
equalization). :class:`PaletteIndexer` applies a table to one eye's (H, W) kelvin image
with preallocated buffers (no per-pixel Python).

Temperatures are kelvin; images (H, W) float32 (or float64) on the colour camera's pixels,
NaN where no thermal imager sees the point (their index is unspecified: the composer
restores the colour image there).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal, get_args

import cv2
import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter1d

from trifuse.calib.numbers import check_finite, is_integer, is_integral
from trifuse.fusion.palettes import _index_into, check_span

__all__ = [
    "AGC_MODES",
    "BIN_K",
    "DEFAULT_MAX_GAIN",
    "DEFAULT_PLATEAU",
    "AgcMode",
    "PaletteIndexer",
    "ToneMap",
    "ToneMapper",
    "cap_gain",
    "check_max_gain",
    "check_plateau",
    "gain_span",
    "index_entropy_bits",
    "kelvin_histogram",
    "plateau_cap",
    "plateau_positions",
    "tone_map",
]

AgcMode = Literal["linear", "plateau", "dde"]
"""An AGC mode (the module's docstring describes each), in the order a menu lists them."""
#: The AGC modes, in the order of :data:`AgcMode`.
AGC_MODES: tuple[AgcMode, ...] = get_args(AgcMode)

BIN_K = 0.1
"""Width of a histogram bin, kelvin (about the imagers' NETD of 0.08 K)."""
MAX_BINS = 4096
"""At most this many bins over a span; a wider span gets wider bins."""
LUT_PER_BIN = 8
"""Look-up table entries per bin: a pixel's temperature is rounded to BIN_K / 8 (0.0125 K)
before the look-up, so the mapping is smooth within a bin."""
HIST_STEP = 4
"""The histogram takes every 4th pixel of every 4th row (1/16 of the pixels; the thermal
imagers have about 1/11 of the colour camera's pixels, so nothing is lost)."""
LINEAR_SHARE = 0.05
"""Share of the palette position that is linear in temperature under equalization."""
DEFAULT_PLATEAU = 0.005
"""Default plateau: a 0.1 K bin counts with at most 0.5 % of the samples. A larger plateau
lets the most common temperatures (the walls) spread over more of the palette: people
stand out a little more; without :data:`DEFAULT_MAX_GAIN` the walls' noise (NETD 0.08 K)
was amplified with it and the stream needed more bitrate for the same quality; with the
cap holding the walls' slope is the cap's (BENCHMARKS.md, ``trifuse bench --only agc``)."""
MIN_PLATEAU = 1e-4
"""Smallest plateau share accepted (below 1 / MAX_BINS every occupied bin is capped)."""
DEFAULT_MAX_GAIN = 12.0
"""Default maximum gain of the ``plateau``/``dde`` table, palette steps per kelvin. Chosen
on the simulated room with its hot pipe (BENCHMARKS.md, ``trifuse bench --only agc``):
at 12 the cooler person stands 0.251 of the palette apart from the walls (target 0.25;
0.247 at 10), the imagers' 1.5 K offset is 18 palette steps on the walls (53 uncapped) and
the H.264 stream at preset 8 keeps SSIM 0.954 (0.939 uncapped; target 0.95)."""
GAIN_SPREAD_K = 3.0
"""Where the palette share the maximum gain takes goes (:func:`cap_gain`): to the bins
under the cap in proportion to the shares smoothed by a Gaussian of this sigma, kelvin."""
MIN_MAX_GAIN = 1.0
"""Smallest maximum gain accepted, palette steps per kelvin (a 255 K span)."""
MAX_MAX_GAIN = 1000.0
"""Largest maximum gain accepted, palette steps per kelvin (100 steps per 0.1 K bin: in
effect no cap)."""
SETTLED_POSITION = 0.5 / 255.0
"""A smoothed table within half a palette step of its target is settled."""

DDE_SCALE = 4
"""Downsampling of the base layer (the colour camera has 3.35x the thermal imagers'
pixels per degree: at 1/4 the base is at about the imager's own resolution)."""
DDE_RANGE_K = 1.5
"""Range sigma of the base layer's bilateral filter, kelvin: steps larger than this are
edges (kept in the base), smaller variations are detail."""
DDE_SPACE_PX = 2.0
"""Space sigma of the bilateral filter in base-layer pixels (8 colour pixels)."""
DDE_GAIN_PER_K = 24.0
"""Palette steps per kelvin of detail (a linear 60 K span gives 4.25 steps per kelvin)."""
DDE_DETAIL_MAX = 40.0
"""The detail adds at most this many palette steps either way (edges the base blurs)."""
_DDE_FILL_PX = 31  # box (base-layer px) that fills blocks with no reading from neighbours
_TAKE_ROWS = 32  # rows per band of the table look-up


def check_plateau(value: object, name: str = "plateau") -> float:
    """A plateau share: a finite number in [MIN_PLATEAU, 1]; ValueError otherwise."""
    p = check_finite(value, name)
    if not MIN_PLATEAU <= p <= 1.0:
        raise ValueError(f"{name}: expected a share in [{MIN_PLATEAU:g}, 1], got {p:g}")
    return p


def check_max_gain(value: object, name: str = "max_gain") -> float:
    """A maximum gain: a finite number of palette steps per kelvin in [MIN_MAX_GAIN,
    MAX_MAX_GAIN]; ValueError otherwise."""
    g = check_finite(value, name)
    if not MIN_MAX_GAIN <= g <= MAX_MAX_GAIN:
        raise ValueError(
            f"{name}: expected palette steps per kelvin in [{MIN_MAX_GAIN:g}, "
            f"{MAX_MAX_GAIN:g}], got {g:g}"
        )
    return g


def gain_span(span: tuple[float, float], max_gain: float) -> tuple[float, float]:
    """``span`` widened about its middle to at least ``255 / max_gain`` kelvin: the
    narrowest automatic span whose table can keep to the maximum gain (a flat, low-contrast
    scene then takes the middle of the palette instead of being stretched over all of it).
    A wider span is returned as it is."""
    low, high = check_span(span)
    width = 255.0 / check_max_gain(max_gain)
    if high - low >= width:
        return low, high
    mid = 0.5 * (low + high)
    return mid - 0.5 * width, mid + 0.5 * width


def _check_mode(mode: object) -> AgcMode:
    if mode not in AGC_MODES:
        raise ValueError(f"agc: expected one of {', '.join(AGC_MODES)}, got {mode!r}")
    return mode  # type: ignore[return-value]


def _bins(span: tuple[float, float]) -> int:
    """The number of bins over ``span``: BIN_K wide, at most MAX_BINS."""
    return max(1, min(MAX_BINS, math.ceil((span[1] - span[0]) / BIN_K - 1e-9)))


def kelvin_histogram(
    thermal_images: np.ndarray | Sequence[np.ndarray],
    span: tuple[float, float],
    step: int = HIST_STEP,
) -> tuple[np.ndarray, np.ndarray]:
    """The histogram of several kelvin images together (both eyes) over ``span``.

    Args:
        thermal_images: one or several (H, W) float kelvin images; NaN and inf are ignored,
            and so are temperatures outside the span (they saturate at the palette's ends).
        span: ``(low_k, high_k)``, low < high: split into ``n`` bins of BIN_K (wider when
            the span is wider than MAX_BINS * BIN_K).
        step: every ``step``-th pixel of every ``step``-th row is counted.

    Returns:
        ``(counts, edges_k)``: (n,) int64 samples per bin and (n + 1,) float64 bin edges,
        kelvin, ``edges_k[0] = low``, ``edges_k[-1] = high``.
    """
    low, high = check_span(span)
    if not is_integer(step) or step < 1:
        raise ValueError(f"step: expected a positive integer, got {step!r}")
    n = _bins((low, high))
    edges = np.linspace(low, high, n + 1)
    images = [thermal_images] if isinstance(thermal_images, np.ndarray) else list(thermal_images)
    counts = np.zeros(n, np.int64)
    scale = n / (high - low)
    for i, image in enumerate(images):
        a = np.asarray(image)
        if a.dtype.kind != "f" or a.ndim != 2:
            raise ValueError(
                f"thermal_images[{i}]: expected a (H, W) float image in kelvin, "
                f"got {a.dtype} of shape {a.shape}"
            )
        sub = a[::step, ::step]
        v = sub[(sub >= low) & (sub <= high)]  # NaN compares false
        b = ((v - low) * scale).astype(np.intp)
        np.minimum(b, n - 1, out=b)  # high itself is in the last bin
        counts += np.bincount(b, minlength=n)
    return counts, edges


def plateau_cap(counts: npt.ArrayLike, plateau: float) -> np.ndarray:
    """Each bin capped at ``plateau`` times the number of samples: (n,) float64."""
    c = np.asarray(counts, dtype=np.float64)
    return np.minimum(c, check_plateau(plateau) * float(c.sum()))


def plateau_positions(
    counts: npt.ArrayLike, plateau: float, linear_share: float = LINEAR_SHARE
) -> np.ndarray:
    """Palette positions of the bin edges under plateau equalization: (n + 1,) float64,
    strictly increasing from 0 to 1.

    ``(1 - linear_share) * cumsum(plateau_cap(counts)) / total + linear_share * k / n``;
    with no sample at all, linear.
    """
    capped = plateau_cap(counts, plateau)
    n = capped.size
    if n == 0:
        raise ValueError("counts: expected at least one bin, got none")
    ramp = np.linspace(0.0, 1.0, n + 1)
    total = float(capped.sum())
    if total <= 0.0:
        return ramp
    cdf = np.concatenate(([0.0], np.cumsum(capped))) / total
    cdf[-1] = 1.0
    return (1.0 - linear_share) * cdf + linear_share * ramp


def cap_gain(positions: npt.ArrayLike, bin_k: float, max_gain: float) -> np.ndarray:
    """Palette positions of evenly spaced nodes (``bin_k`` kelvin apart) with the slope
    capped at ``max_gain`` palette steps per kelvin: (n + 1,) float64 from 0 to 1.

    Each bin's share of the palette ``s_i = positions[i + 1] - positions[i]`` is capped at
    ``c = max_gain * bin_k / 255``, and the share the cap takes is handed to the bins under
    the cap in proportion to ``w``, the shares smoothed over temperature (a Gaussian of
    :data:`GAIN_SPREAD_K`): ``min(s_i + lam * w_i, c)`` with the one ``lam >= 0`` that makes
    them sum to 1 (the plateau's clip iterated to its end: a bin the hand-out fills is
    capped too). So the freed palette goes to the temperatures near those the picture
    shows (a person a few kelvin above the capped walls stands apart from them), not evenly
    over empty stretches of the span (between the people and a hot pipe). Shares all within
    the cap come back unchanged; when even a linear mapping is steeper than the cap
    (``max_gain * n * bin_k <= 255``: a span narrower than ``255 / max_gain``, see
    :func:`gain_span`) the result is linear, the flattest there is. Strictly increasing
    positions stay strictly increasing.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 1 or pos.size < 2:
        raise ValueError(f"positions: expected (n + 1,) positions, n >= 1, got shape {pos.shape}")
    step = check_finite(bin_k, "bin_k")
    if step <= 0.0:
        raise ValueError(f"bin_k: expected a positive width in kelvin, got {bin_k!r}")
    n = pos.size - 1
    cap = check_max_gain(max_gain) * step / 255.0
    shares = np.diff(pos)
    total = float(shares.sum())
    if cap * n <= 1.0 + 1e-9 or total <= 0.0 or not np.all(shares >= 0.0):
        return np.linspace(0.0, 1.0, n + 1)
    shares = shares / total
    if shares.max() <= cap:
        out = (pos - pos[0]) / total
        out[-1] = 1.0
        return out
    weight = gaussian_filter1d(shares, GAIN_SPREAD_K / step, mode="nearest", truncate=3.0)
    weight = np.maximum(weight, 1e-12)
    # Water-filling: bin i (under the cap) reaches it at lam = t_i = (c - s_i) / w_i; with
    # the bins sorted by t, on [t_(j-1), t_j) the sum is (bins capped) * c + the rest's
    # s + lam * w, linear in lam: the first piece whose solution lies within it.
    under = shares < cap
    s_u, w_u = shares[under], weight[under]
    t = (cap - s_u) / w_u
    order = np.argsort(t)
    t, s_u, w_u = t[order], s_u[order], w_u[order]
    m = t.size
    capped_before = (n - m) + np.arange(m)  # bins at the cap on piece j
    rest_s = np.cumsum(s_u[::-1])[::-1]
    rest_w = np.cumsum(w_u[::-1])[::-1]
    lam = (1.0 - capped_before * cap - rest_s) / rest_w
    j = int(np.argmax(lam <= t)) if np.any(lam <= t) else m - 1
    out = np.minimum(shares + max(float(lam[j]), 0.0) * weight, cap)
    positions_out = np.concatenate(([0.0], np.cumsum(out)))
    positions_out /= positions_out[-1]
    positions_out[-1] = 1.0
    return positions_out


class ToneMap:
    """One stereo frame's mapping from kelvin to palette index, shared by both eyes.

    The palette position (0 = first entry, 1 = last) is piecewise linear in temperature
    between the nodes ``nodes_k`` (evenly spaced over the span; ``linear``: just its two
    ends), 0 at and below ``low``, 1 at and above ``high``; the index is
    ``round(255 * position)`` (``dde`` adds the detail layer per pixel).

    Attributes:
        mode: the AGC mode that made it.
        span_k: ``(low_k, high_k)``.
        nodes_k: (n + 1,) float64 node temperatures, kelvin (read-only).
        positions: (n + 1,) float64 palette positions at the nodes, strictly increasing,
            0 first and 1 last (read-only).
        lut: the per-pixel look-up table (65536,) uint8: the index of the temperature
            ``low + j * lut_step_k`` (255 beyond the span); None for ``linear``.
        lut_step_k: kelvin per look-up entry (BIN_K / LUT_PER_BIN), or None.
    """

    __slots__ = ("lut", "lut_step_k", "mode", "nodes_k", "positions", "span_k")

    def __init__(
        self, mode: AgcMode, span_k: tuple[float, float], nodes_k: np.ndarray, positions: np.ndarray
    ) -> None:
        self.mode = _check_mode(mode)
        self.span_k = check_span(span_k, "span_k")
        nodes = np.array(nodes_k, dtype=np.float64)
        pos = np.array(positions, dtype=np.float64)
        if nodes.ndim != 1 or nodes.shape != pos.shape or nodes.size < 2:
            raise ValueError(
                f"nodes_k, positions: expected two (n + 1,) arrays, n >= 1, got shapes "
                f"{nodes.shape} and {pos.shape}"
            )
        nodes.flags.writeable = pos.flags.writeable = False
        self.nodes_k, self.positions = nodes, pos
        self.lut: np.ndarray | None = None
        self.lut_step_k: float | None = None
        if mode != "linear":
            low = self.span_k[0]
            n = nodes.size - 1
            m = n * LUT_PER_BIN + 1
            self.lut_step_k = (nodes[-1] - low) / (m - 1)
            lut = np.full(65536, 255, np.uint8)
            fine = np.interp(np.arange(m) / LUT_PER_BIN, np.arange(n + 1), pos)
            lut[:m] = np.rint(255.0 * fine)
            lut.flags.writeable = False
            self.lut = lut

    @classmethod
    def linear(cls, span_k: tuple[float, float]) -> ToneMap:
        """The linear mapping over ``span_k`` (today's :func:`temperature_index`)."""
        low, high = check_span(span_k, "span_k")
        return cls("linear", (low, high), np.array([low, high]), np.array([0.0, 1.0]))

    def index_of(self, temperature_k: npt.ArrayLike) -> np.ndarray:
        """The palette index (..., ) uint8 of temperatures (any shape, kelvin), exactly as
        :class:`PaletteIndexer` maps an image (without ``dde``'s detail layer). Non-finite
        values get 0."""
        t = np.asarray(temperature_k, dtype=np.float64)
        low, high = self.span_k
        t = np.where(np.isfinite(t), t, low)
        if self.lut is None:
            idx = np.rint((t - low) * (255.0 / (high - low)))
            return np.clip(idx, 0, 255).astype(np.uint8)
        j = np.clip(np.rint((t - low) / self.lut_step_k), 0, 65535).astype(np.intp)
        return self.lut[j]

    def temperatures_k(self, positions: npt.ArrayLike) -> np.ndarray:
        """The temperature (kelvin, float64, the shape of ``positions``) at palette
        positions in [0, 1] (0 = the first entry, 1 = the last): the inverse mapping,
        e.g. the labels of a colour bar's ticks."""
        p = np.asarray(positions, dtype=np.float64)
        return np.interp(p, self.positions, self.nodes_k)

    def ticks_k(self, count: int) -> list[float]:
        """Temperatures (kelvin) at ``count`` >= 2 evenly spaced palette positions, from the
        first entry (position 0) to the last (position 1)."""
        if not is_integer(count) or count < 2:
            raise ValueError(f"count: expected an integer >= 2, got {count!r}")
        return [float(t) for t in self.temperatures_k(np.linspace(0.0, 1.0, int(count)))]


def tone_map(
    thermal_images: np.ndarray | Sequence[np.ndarray],
    mode: AgcMode,
    span: tuple[float, float],
    plateau: float = DEFAULT_PLATEAU,
    max_gain: float = DEFAULT_MAX_GAIN,
) -> ToneMap:
    """One frame's :class:`ToneMap` over both eyes' kelvin images (no smoothing over time).

    Args:
        thermal_images: the eyes' (H, W) kelvin images on their colour pixels (NaN: none).
        mode: one of :data:`AGC_MODES`.
        span: ``(low_k, high_k)``: the palette's ends; equalization works within it.
        plateau: the largest share of the samples a bin counts with (``plateau``, ``dde``).
        max_gain: the table's steepest slope, palette steps per kelvin (:func:`cap_gain`;
            ``plateau``, ``dde``).
    """
    mode = _check_mode(mode)
    span = check_span(span)
    max_gain = check_max_gain(max_gain)
    if mode == "linear":
        return ToneMap.linear(span)
    counts, edges = kelvin_histogram(thermal_images, span)
    positions = cap_gain(plateau_positions(counts, plateau), edges[1] - edges[0], max_gain)
    return ToneMap(mode, span, edges, positions)


class ToneMapper:
    """The tone map of a stream of stereo frames, smoothed over frame time.

    Each update computes the frame's own table (:func:`tone_map`); the palette positions
    shown move ``alpha = 1 - exp(-dt / time_constant_s)`` of the way to it (``dt`` from the
    frames' ``stamp_ns``), as :class:`fusion.span.SpanSmoother` moves the span. The
    previous positions are taken as a function of temperature (interpolated onto the new
    frame's nodes, so a span that moves keeps the colours where they were) and renormalised
    to 0 .. 1 over the new span, and capped at the maximum gain again (:func:`cap_gain`:
    the renormalisation of a span that grew may steepen it). The first update, one without
    ``stamp_ns``, one whose time stamp is not later than the previous one (a replay that
    looped), one with time constant 0 and a change from ``linear`` all snap to the frame's
    own table.

    Attributes:
        tone: the last :class:`ToneMap` (None before the first update).
        settled: whether the table shown is within SETTLED_POSITION of the frame's own.
    """

    def __init__(self) -> None:
        self.tone: ToneMap | None = None
        self.settled = True
        self._stamp_ns: int | None = None

    def reset(self) -> None:
        """Forget the state: the next update snaps."""
        self.tone, self._stamp_ns, self.settled = None, None, True

    def update(
        self,
        thermal_images: np.ndarray | Sequence[np.ndarray],
        mode: AgcMode,
        span: tuple[float, float],
        plateau: float = DEFAULT_PLATEAU,
        time_constant_s: float = 1.0,
        stamp_ns: int | None = None,
        max_gain: float = DEFAULT_MAX_GAIN,
    ) -> ToneMap:
        """The table for one stereo frame (arguments of :func:`tone_map`; the time
        constant in seconds, >= 0; the frame's time in int nanoseconds or None)."""
        tau = check_finite(time_constant_s, "time_constant_s")
        if tau < 0.0:
            raise ValueError(f"time_constant_s: expected >= 0 seconds, got {time_constant_s!r}")
        if stamp_ns is not None and not is_integral(stamp_ns):
            raise ValueError(
                f"stamp_ns: expected an integer (nanoseconds) or None, got {stamp_ns!r}"
            )
        target = tone_map(thermal_images, mode, span, plateau, max_gain)
        prev, prev_stamp = self.tone, self._stamp_ns
        self._stamp_ns = None if stamp_ns is None else int(stamp_ns)
        if (
            target.mode == "linear"
            or prev is None
            or prev.mode == "linear"
            or stamp_ns is None
            or prev_stamp is None
            or stamp_ns <= prev_stamp
            or tau == 0.0
        ):
            self.tone, self.settled = target, True
            return target
        alpha = -math.expm1(-(int(stamp_ns) - prev_stamp) * 1e-9 / tau)
        before = np.interp(target.nodes_k, prev.nodes_k, prev.positions)
        pos = before + alpha * (target.positions - before)
        span_pos = pos[-1] - pos[0]
        pos = (pos - pos[0]) / span_pos if span_pos > 0 else target.positions
        nodes = target.nodes_k
        pos = cap_gain(pos, (nodes[-1] - nodes[0]) / (nodes.size - 1), max_gain)
        self.settled = bool(np.abs(pos - target.positions).max() < SETTLED_POSITION)
        self.tone = ToneMap(target.mode, target.span_k, target.nodes_k, pos)
        return self.tone


class PaletteIndexer:
    """Palette indices of one eye's kelvin images through a :class:`ToneMap`, with
    preallocated buffers (the ``dde`` ones on first use); not re-entrant.

    Args:
        width, height: the image size in pixels (the colour camera's).
    """

    def __init__(self, width: int, height: int) -> None:
        for n, v in (("width", width), ("height", height)):
            if not is_integer(v) or v <= 0:
                raise ValueError(f"{n}: expected a positive integer, got {v!r}")
        self.width, self.height = int(width), int(height)
        self._nodes = np.zeros((self.height, self.width), np.uint16)
        self._rows = np.zeros((_TAKE_ROWS, self.width), np.intp)
        self._dde: dict[str, np.ndarray] | None = None

    def index(
        self,
        thermal_k: np.ndarray,
        tone: ToneMap,
        out: np.ndarray | None = None,
        sl: tuple[slice, slice] = (slice(None), slice(None)),
    ) -> np.ndarray:
        """Write the palette index of every pixel of ``thermal_k[sl]`` into ``out[sl]``.

        Args:
            thermal_k: (H, W) float32/float64 kelvin (NaN: no reading, unspecified index).
            tone: the frame's mapping.
            out: (H, W) uint8 (rows may be strided); allocated if None.
            sl: the (rows, columns) slices to work on (a picture-in-picture box).
        Returns:
            ``out``.
        """
        h, w = self.height, self.width
        if (
            not isinstance(thermal_k, np.ndarray)
            or thermal_k.dtype not in (np.float32, np.float64)
            or thermal_k.shape != (h, w)
        ):
            got = getattr(thermal_k, "dtype", type(thermal_k).__name__)
            raise ValueError(f"thermal_k: expected float32 (or float64) ({h}, {w}), got {got}")
        if not isinstance(tone, ToneMap):
            raise ValueError(f"tone: expected a ToneMap, got {type(tone).__name__}")
        if out is None:
            out = np.empty((h, w), np.uint8)
        elif not isinstance(out, np.ndarray) or out.dtype != np.uint8 or out.shape != (h, w):
            raise ValueError(f"out: expected uint8 ({h}, {w}), got {getattr(out, 'shape', out)}")
        self.index_into(thermal_k, tone, out, sl)
        return out

    def index_into(
        self, thermal_k: np.ndarray, tone: ToneMap, out: np.ndarray, sl: tuple[slice, slice]
    ) -> None:
        """Unchecked :meth:`index` (the composer checks its inputs once)."""
        t, o = thermal_k[sl], out[sl]
        if tone.lut is None:
            _index_into(t, tone.span_k[0], tone.span_k[1], o)
        elif tone.mode == "dde":
            self._detail(t, tone, o, sl)
        else:
            self._lookup(t, tone, self._nodes[sl], o)

    def _lookup(self, t: np.ndarray, tone: ToneMap, nodes: np.ndarray, o: np.ndarray) -> None:
        """``o = lut[round((t - low) / lut_step)]`` (saturating: below low 0, above 255).
        ``np.take`` wants machine-size indices: the uint16 nodes are widened a band of
        rows at a time in a preallocated buffer (a whole frame would be 10 MB per call)."""
        step = tone.lut_step_k
        low = tone.span_k[0]
        cv2.addWeighted(t, 1.0 / step, t, 0.0, -low / step, dst=nodes, dtype=cv2.CV_16U)
        h, w = nodes.shape
        for r in range(0, h, _TAKE_ROWS):
            rows = self._rows[: min(_TAKE_ROWS, h - r), :w]
            np.copyto(rows, nodes[r : r + _TAKE_ROWS])
            np.take(tone.lut, rows, out=o[r : r + _TAKE_ROWS], mode="clip")

    def _buffers(self) -> dict[str, np.ndarray]:
        if self._dde is None:
            h, w = self.height, self.width
            hs, ws = -(-h // DDE_SCALE), -(-w // DDE_SCALE)
            f32 = np.float32
            self._dde = {
                "value": np.zeros((h, w), f32),  # the image, NaN -> 0; then the detail
                "base": np.zeros((h, w), f32),
                "valid": np.zeros((h, w), np.uint8),
                **{k: np.zeros((hs, ws), f32) for k in ("sum", "w", "num", "den", "low", "bil")},
                "w8": np.zeros((hs, ws), np.uint8),
            }
        return self._dde

    def _detail(self, t: np.ndarray, tone: ToneMap, o: np.ndarray, sl: tuple[slice, slice]) -> None:
        """``dde``: base layer through the table plus the amplified detail layer."""
        b = self._buffers()
        h, w = t.shape
        hs, ws = -(-h // DDE_SCALE), -(-w // DDE_SCALE)
        value, base, valid = b["value"][sl], b["base"][sl], b["valid"][sl]
        s = {k: b[k][:hs, :ws] for k in ("sum", "w", "num", "den", "low", "bil", "w8")}
        np.copyto(value, t, casting="same_kind")
        cv2.compare(value, value, cv2.CMP_EQ, dst=valid)  # 255 with a reading, 0 for NaN
        cv2.patchNaNs(value, 0.0)
        # low resolution: the mean of the readings of each block (sum / share valid)
        cv2.resize(value, (ws, hs), dst=s["sum"], interpolation=cv2.INTER_AREA)
        cv2.resize(valid, (ws, hs), dst=s["w8"], interpolation=cv2.INTER_AREA)
        np.multiply(s["w8"], np.float32(1.0 / 255.0), out=s["w"])
        # blocks without a reading take their neighbours' mean (no false edge at the border
        # of the thermal view), or the span's middle far from any reading
        cv2.blur(s["sum"], (_DDE_FILL_PX, _DDE_FILL_PX), dst=s["num"])
        cv2.blur(s["w"], (_DDE_FILL_PX, _DDE_FILL_PX), dst=s["den"])
        np.maximum(s["den"], np.float32(1e-6), out=s["den"])
        np.divide(s["num"], s["den"], out=s["low"])
        s["low"][s["den"] < 1e-3] = 0.5 * (tone.span_k[0] + tone.span_k[1])
        has = s["w"] > 0.0
        np.divide(s["sum"], s["w"], out=s["low"], where=has)
        cv2.bilateralFilter(s["low"], 5, DDE_RANGE_K, DDE_SPACE_PX, dst=s["bil"])
        cv2.resize(s["bil"], (w, h), dst=base, interpolation=cv2.INTER_LINEAR)
        self._lookup(base, tone, self._nodes[sl], o)
        cv2.subtract(value, base, dst=value)  # the detail layer, kelvin (garbage on NaN)
        np.multiply(value, np.float32(DDE_GAIN_PER_K), out=value)
        np.clip(value, -DDE_DETAIL_MAX, DDE_DETAIL_MAX, out=value)
        cv2.add(o, value, dst=o, dtype=cv2.CV_8U)


def index_entropy_bits(index: npt.ArrayLike, mask: npt.ArrayLike | None = None) -> float:
    """Shannon entropy (bits, 0 .. 8) of palette indices (uint8, any shape) where ``mask``
    (bool, same shape) is True: how many palette levels the picture really uses."""
    idx = np.asarray(index)
    if idx.dtype != np.uint8:
        raise ValueError(f"index: expected uint8 palette indices, got {idx.dtype}")
    values = idx[np.asarray(mask, bool)] if mask is not None else idx.ravel()
    if values.size == 0:
        return 0.0
    p = np.bincount(values, minlength=256) / values.size
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum())
