"""The TOF camera's range correction: the model stored in the rig file and applied per frame.

A TOF camera's radial distance has a systematic error made of three parts (the model of
Lindner & Kolb and of Kahlmann, as the method's range calibration uses it):

* ``w(d)``: a smooth function of the measured distance, the periodic "wiggling" of the
  demodulation plus a constant bias: a uniform cubic B-spline over the calibrated distance
  range, clamped to its ends outside it;
* ``o(u, v)``: a per-pixel offset, bilinear between nodes every ``offset_step_px`` pixels
  (the smooth bowl of the optics and the steep rise of the image border);
* ``a(A)``: a function of the amplitude ``A``: a polynomial without constant in
  ``L = log10(A / amplitude_ref)``, ``L`` clamped to the calibrated range (weak returns
  read long, strong ones short).

Corrected distance: ``d - (w(d) + o(u, v) + a(A))``, metres, NaN stays NaN.

Rig file block (``sensors.<tof>.range_correction``, docs/FORMATS.md)::

    model: trifuse-range/1
    distance: {start_m: 0.5, step_m: 0.15, coeffs_m: [...]}      # len = intervals + 3
    offset: {step_px: 8, nodes_m: [[...], ...]}                    # (rows, cols) nodes
    amplitude: {ref: 1000.0, log_range: [-1.2, 1.5], coeffs_m: [c1, c2]}
    fit: {...}                                                     # what it was fitted on
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from trifuse.calib.numbers import check_finite, is_int

MODEL = "trifuse-range/1"
_LUT_STEP_M = 0.001  # resolution of the distance term's lookup table


def bspline_basis(x: np.ndarray, start: float, step: float, n_coeffs: int):
    """Uniform cubic B-spline basis at ``x`` (clamped to the knot range).

    Returns (index (N,) int64 of the first of the 4 non-zero basis functions, weights (N, 4)).
    """
    m = n_coeffs - 3  # intervals
    s = (np.clip(np.asarray(x, np.float64), start, start + m * step) - start) / step
    i = np.minimum(np.floor(s), m - 1).astype(np.int64)
    u = s - i
    u2, u3 = u * u, u * u * u
    w = np.stack(
        [
            (1 - u) ** 3 / 6,
            (3 * u3 - 6 * u2 + 4) / 6,
            (-3 * u3 + 3 * u2 + 3 * u + 1) / 6,
            u3 / 6,
        ],
        axis=1,
    )
    return i, w


def bilinear_weights(u: np.ndarray, v: np.ndarray, step: int, shape: tuple[int, int]):
    """Bilinear weights of pixel centres (u, v) on a node grid ``shape`` = (rows, cols) with
    nodes every ``step`` pixels. Returns (flat node indices (N, 4), weights (N, 4))."""
    rows, cols = shape
    gu = np.clip(np.asarray(u, np.float64) / step, 0, cols - 1)
    gv = np.clip(np.asarray(v, np.float64) / step, 0, rows - 1)
    c0 = np.minimum(np.floor(gu), cols - 2).astype(np.int64)
    r0 = np.minimum(np.floor(gv), rows - 2).astype(np.int64)
    fu, fv = gu - c0, gv - r0
    idx = np.stack(
        [r0 * cols + c0, r0 * cols + c0 + 1, (r0 + 1) * cols + c0, (r0 + 1) * cols + c0 + 1], 1
    )
    w = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=1)
    return idx, w


def offset_grid_shape(width: int, height: int, step: int) -> tuple[int, int]:
    """(rows, cols) of offset nodes covering pixel centres 0..W-1, 0..H-1 every ``step``
    (integer arithmetic: exact, and no overflow for absurd sizes read from a file)."""
    return (max(2, -(-(height - 1) // step) + 1), max(2, -(-(width - 1) // step) + 1))


def amplitude_log(amplitude: np.ndarray, ref: float, log_range: tuple[float, float]) -> np.ndarray:
    """``L = log10(A / ref)`` clamped to ``log_range``; 0 where A is not positive or NaN."""
    a = np.asarray(amplitude, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.log10(a / ref)
    L = np.clip(L, *log_range)
    return np.where(np.isfinite(L), L, 0.0)


@dataclass(frozen=True, eq=False)
class RangeCorrection:
    """A TOF range correction (see the module docstring for the model).

    Attributes:
        image_size: (width, height) of the TOF image it was fitted for.
        distance_start_m, distance_step_m: knots of the distance spline, metres.
        distance_coeffs_m: (intervals + 3,) spline coefficients, metres.
        offset_step_px: spacing of the offset nodes, pixels.
        offset_nodes_m: (rows, cols) offsets at the nodes, metres.
        amplitude_ref: amplitude where ``L = 0``.
        amplitude_log_range: the calibrated (low, high) range of ``L`` (clamped outside).
        amplitude_coeffs_m: c_k of ``sum_k c_k L^k``, k = 1..K, metres.
        fit: what the model was fitted on (views, pixels, residual RMS ...): informative.
    """

    image_size: tuple[int, int]
    distance_start_m: float
    distance_step_m: float
    distance_coeffs_m: np.ndarray
    offset_step_px: int
    offset_nodes_m: np.ndarray
    amplitude_ref: float = 1000.0
    amplitude_log_range: tuple[float, float] = (-2.0, 2.0)
    amplitude_coeffs_m: tuple[float, ...] = ()
    fit: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        coeffs = np.asarray(self.distance_coeffs_m, np.float64)
        nodes = np.asarray(self.offset_nodes_m, np.float64)
        w, h = self.image_size
        if coeffs.ndim != 1 or coeffs.size < 4:
            raise ValueError(
                f"distance.coeffs_m: expected at least 4 numbers, got shape {coeffs.shape}"
            )
        if not self.distance_step_m > 0:
            raise ValueError(f"distance.step_m: expected > 0, got {self.distance_step_m}")
        if not (isinstance(self.offset_step_px, int) and self.offset_step_px >= 1):
            raise ValueError(f"offset.step_px: expected an integer >= 1, got {self.offset_step_px}")
        expected = offset_grid_shape(w, h, self.offset_step_px)
        if nodes.shape != expected:
            raise ValueError(
                f"offset.nodes_m: expected {expected[0]} rows of {expected[1]} numbers for a "
                f"{w}x{h} image at step_px {self.offset_step_px}, got shape {nodes.shape}"
            )
        lo, hi = self.amplitude_log_range
        if not lo < hi:
            raise ValueError(f"amplitude.log_range: expected low < high, got {[lo, hi]}")
        if not self.amplitude_ref > 0:
            raise ValueError(f"amplitude.ref: expected > 0, got {self.amplitude_ref}")
        for name, a in (("distance.coeffs_m", coeffs), ("offset.nodes_m", nodes)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name}: expected finite numbers, got NaN or inf")
        object.__setattr__(self, "distance_coeffs_m", coeffs)
        object.__setattr__(self, "offset_nodes_m", nodes)
        object.__setattr__(self, "amplitude_coeffs_m", tuple(map(float, self.amplitude_coeffs_m)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RangeCorrection):
            return NotImplemented
        return self.to_dict() == other.to_dict() and self.image_size == other.image_size

    @property
    def distance_range_m(self) -> tuple[float, float]:
        """The calibrated distance range (the distance term is constant beyond it)."""
        n = self.distance_coeffs_m.size - 3
        return (self.distance_start_m, self.distance_start_m + n * self.distance_step_m)

    # -- evaluation -------------------------------------------------------------------

    def distance_term(self, d: np.ndarray) -> np.ndarray:
        """``w(d)`` in metres for measured distances ``d`` (any shape)."""
        d = np.asarray(d, np.float64)
        i, w = bspline_basis(
            d.ravel(), self.distance_start_m, self.distance_step_m, self.distance_coeffs_m.size
        )
        c = self.distance_coeffs_m[i[:, None] + np.arange(4)]
        return np.sum(w * c, axis=1).reshape(d.shape)

    def amplitude_term(self, amplitude: np.ndarray) -> np.ndarray:
        """``a(A)`` in metres (any shape)."""
        L = amplitude_log(amplitude, self.amplitude_ref, self.amplitude_log_range)
        out = np.zeros(L.shape)
        for k, c in enumerate(self.amplitude_coeffs_m, start=1):
            out += c * L**k
        return out

    @cached_property
    def pixel_offset_m(self) -> np.ndarray:
        """``o(u, v)`` for every pixel, (H, W) float32 metres."""
        w, h = self.image_size
        vv, uu = np.mgrid[0:h, 0:w]
        idx, wt = bilinear_weights(
            uu.ravel(), vv.ravel(), self.offset_step_px, self.offset_nodes_m.shape
        )
        o = np.sum(self.offset_nodes_m.ravel()[idx] * wt, axis=1)
        return o.reshape(h, w).astype(np.float32)

    @cached_property
    def _lut(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.distance_range_m
        x = np.arange(lo, hi + _LUT_STEP_M, _LUT_STEP_M)
        return x.astype(np.float32), self.distance_term(x).astype(np.float32)

    def error_m(self, distance_m: np.ndarray, amplitude: np.ndarray | None = None) -> np.ndarray:
        """The modelled systematic error (H, W) float32 of a full TOF image, metres."""
        d = np.asarray(distance_m, np.float32)
        if d.shape != self.pixel_offset_m.shape:
            raise ValueError(
                f"distance_m: expected the TOF image's shape {self.pixel_offset_m.shape}, "
                f"got {d.shape}"
            )
        x, y = self._lut
        err = np.interp(np.nan_to_num(d, nan=x[0]), x, y).astype(np.float32)
        err += self.pixel_offset_m
        if amplitude is not None and self.amplitude_coeffs_m:
            a = np.asarray(amplitude)
            if a.shape != d.shape:
                raise ValueError(f"amplitude: expected shape {d.shape}, got {a.shape}")
            err += self.amplitude_term(a).astype(np.float32)
        return err

    def apply(
        self,
        distance_m: np.ndarray,
        amplitude: np.ndarray | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Corrected radial distances (H, W) float32, metres (NaN stays NaN).

        ``amplitude`` (H, W) or None (then the amplitude term is left out: its value at
        ``amplitude_ref``, zero). ``out`` may be a preallocated float32 buffer.
        """
        err = self.error_m(distance_m, amplitude)
        return np.subtract(np.asarray(distance_m, np.float32), err, out=out)

    def error_at(
        self, u: np.ndarray, v: np.ndarray, distance_m: np.ndarray, amplitude: np.ndarray
    ) -> np.ndarray:
        """The modelled error (N,) at pixels (u, v) (integers) for samples (N,)."""
        err = self.distance_term(distance_m) + self.pixel_offset_m[v, u]
        if self.amplitude_coeffs_m:
            err = err + self.amplitude_term(amplitude)
        return err

    # -- rig file ---------------------------------------------------------------------

    def rounded(self) -> RangeCorrection:
        """A copy with the distance, offset and amplitude coefficients rounded to 0.1 um
        (``round(x, 7)`` metres; plenty): what a fitted model is kept as in a rig."""
        return replace(
            self,
            distance_coeffs_m=np.array(_rounded(self.distance_coeffs_m)),
            offset_nodes_m=np.array([_rounded(row) for row in self.offset_nodes_m]),
            amplitude_coeffs_m=tuple(_rounded(self.amplitude_coeffs_m)),
        )

    def to_dict(self) -> dict[str, Any]:
        """The rig file block (plain YAML types; every number as it is, see :meth:`rounded`)."""
        floats = lambda a: [float(x) for x in a]  # noqa: E731
        out: dict[str, Any] = {
            "model": MODEL,
            "distance": {
                "start_m": float(self.distance_start_m),
                "step_m": float(self.distance_step_m),
                "coeffs_m": floats(self.distance_coeffs_m),
            },
            "offset": {
                "step_px": int(self.offset_step_px),
                "nodes_m": [floats(row) for row in self.offset_nodes_m],
            },
            "amplitude": {
                "ref": float(self.amplitude_ref),
                "log_range": floats(self.amplitude_log_range),
                "coeffs_m": floats(self.amplitude_coeffs_m),
            },
        }
        if self.fit:
            out["fit"] = self.fit
        return out

    @classmethod
    def from_dict(cls, data: Any, image_size: tuple[int, int]) -> RangeCorrection:
        """Parse a rig file block for a TOF image of ``image_size``; ValueError names the
        field at fault."""
        block = _mapping(data, "range_correction")
        _keys(block, "range_correction", {"model", "distance", "offset", "amplitude"}, {"fit"})
        if block["model"] != MODEL:
            raise ValueError(f"range_correction.model: expected {MODEL!r}, got {block['model']!r}")
        dist = _mapping(block["distance"], "range_correction.distance")
        _keys(dist, "range_correction.distance", {"start_m", "step_m", "coeffs_m"})
        off = _mapping(block["offset"], "range_correction.offset")
        _keys(off, "range_correction.offset", {"step_px", "nodes_m"})
        amp = _mapping(block["amplitude"], "range_correction.amplitude")
        _keys(amp, "range_correction.amplitude", {"ref", "log_range", "coeffs_m"})
        step_px = off["step_px"]
        if not is_int(step_px):
            raise ValueError(
                f"range_correction.offset.step_px: expected an integer, got {step_px!r}"
            )
        fit = block.get("fit", {})
        if not isinstance(fit, Mapping):
            raise ValueError(f"range_correction.fit: expected a mapping, got {type(fit).__name__}")
        try:
            return cls(
                image_size=image_size,
                distance_start_m=_num(dist["start_m"], "range_correction.distance.start_m"),
                distance_step_m=_num(dist["step_m"], "range_correction.distance.step_m"),
                distance_coeffs_m=_nums(dist["coeffs_m"], "range_correction.distance.coeffs_m"),
                offset_step_px=step_px,
                offset_nodes_m=np.array(
                    [
                        _nums(row, "range_correction.offset.nodes_m")
                        for row in _list(off["nodes_m"], "range_correction.offset.nodes_m")
                    ],
                    dtype=np.float64,
                ),
                amplitude_ref=_num(amp["ref"], "range_correction.amplitude.ref"),
                amplitude_log_range=tuple(
                    _pair(amp["log_range"], "range_correction.amplitude.log_range")
                ),
                amplitude_coeffs_m=tuple(
                    _nums(amp["coeffs_m"], "range_correction.amplitude.coeffs_m")
                ),
                fit=dict(fit),
            )
        except ValueError as exc:
            msg = str(exc)
            raise ValueError(
                msg if msg.startswith("range_correction") else f"range_correction.{msg}"
            ) from None


def _rounded(values: Any) -> list[float]:
    """Each number rounded to 7 decimals (Python's correctly rounded ``round``)."""
    return [round(float(x), 7) for x in values]


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ValueError(f"{where}: expected a mapping, got {type(value).__name__}")
    return value


def _keys(
    block: Mapping[str, Any], where: str, required: set[str], optional: set[str] = frozenset()
) -> None:
    missing = sorted(required - set(block))
    unknown = sorted(set(block) - required - optional)
    if missing:
        raise ValueError(f"{where}: missing {missing}")
    if unknown:
        raise ValueError(
            f"{where}: unknown keys {unknown} (allowed: {sorted(required | optional)})"
        )


def _num(value: Any, where: str) -> float:
    return check_finite(value, where)


def _list(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise ValueError(f"{where}: expected a list, got {type(value).__name__}")
    return value


def _nums(value: Any, where: str) -> list[float]:
    return [_num(x, f"{where}[{i}]") for i, x in enumerate(_list(value, where))]


def _pair(value: Any, where: str) -> list[float]:
    xs = _nums(value, where)
    if len(xs) != 2:
        raise ValueError(f"{where}: expected [low, high], got {value!r}")
    return xs
