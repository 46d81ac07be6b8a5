"""How TOF errors move the fused pixels: the method's section 4.1 and Table 1, vectorised.

The fusion (docs/CONVENTIONS.md, :mod:`fusion.geometry`) puts a TOF pixel (u, v) with radial
distance d into every other sensor s:

    P(d) = d * r(u, v)                     unit ray r with undistortion, TOF frame, metres
    p_s(u, v, d) = project_s(T_s_tof P(d)) pixel in sensor s, with its distortion

Two errors of the TOF move that pixel:

**Distance error** (the TOF's radial distance is off by ``Δd`` metres, e.g. 41 mm before
range calibration, 15 mm after)::

    (dx, dy)(d) = p_s(u, v, d + Δd) - p_s(u, v, d)

**TOF pixel error** (the TOF pixel is off by ``δ`` pixels along the TOF image's x axis, e.g.
half a pixel from its low resolution), at the same radial distance d::

    (dx, dy)(d) = p_s(u + δ, v, d) - p_s(u, v, d)

Both are in pixels of sensor s and signed (+x right, +y down, OpenCV). They are sampled over
the TOF's range, 0.1-10 m (:func:`sample_distances`, 0.01 m step by default).

**Threshold distance.** A shift below ``threshold_px`` (0.5 px in the method) does not matter
for the fusion. For each sensor and image coordinate separately (|dx| and |dy|):

- ``x_m`` (``y_m``) is the *largest* radial distance of the sampled range at which
  ``|dx| >= threshold_px`` (``|dy|``). The distance-error shift falls with distance, so this
  is the distance *below which* the shift exceeds the threshold (Table 1's entry). Between
  the last sample at or above the threshold and the next one, the crossing is refined by
  bisection on the exact shift to within 1e-7 m (far better than the 1 mm asked for).
- ``None`` where the shift never reaches the threshold in the range (Table 1's "–").
- If the shift reaches the threshold at the far end of the range itself, the answer is
  that end (10.0 m by default): the shift exceeds the threshold over the whole range as far
  as the range goes (e.g. the TOF pixel error in the colour cameras, about
  ``f_s / f_tof * δ`` = 4 px at any distance). Reports show it as ``>= 10``.
- Samples where a shift is NaN (the point does not project into the sensor: behind it or
  beyond the fold of its distortion) count as below the threshold.

**Default TOF pixels** (:func:`default_tof_pixels`), the method's two "significant image
points": the TOF's principal point (cx, cy) (the point on the optical axis), and the point on
the TOF image's x axis at the edge of accuracy region 3 (:mod:`calib.tof`):
``u = calib.tof.region3_edge_pixel(W, H)[0]`` (the last pixel column inside region 3, right
of centre; regions are defined on the pixel grid) and ``v = cy`` (not the image centre row
``(H - 1) / 2`` that ``region3_edge_pixel`` returns): the camera's x axis is the row through
the principal point, where the normalised y is 0, as in the method.

Everything here is pure: arrays and dataclasses in, new values out.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from trifuse.calib.rig import Rig
from trifuse.calib.tof import region3_edge_pixel
from trifuse.fusion.geometry import in_image, monotonic_radius, project_to_sensor, tof_sensor_name

__all__ = [
    "DEFAULT_DISTANCE_ERROR_M",
    "DEFAULT_THRESHOLD_PX",
    "DEFAULT_TOF_PIXEL_ERROR_PX",
    "PrecisionAnalysis",
    "SensorShift",
    "analyze_precision",
    "default_tof_pixels",
    "distance_error_shifts",
    "pixel_key",
    "sample_distances",
    "threshold_distance",
    "tof_pixel_error_shifts",
    "tof_pixel_label",
]

DEFAULT_DISTANCE_ERROR_M = 0.041  # the method's TOF distance error before range calibration
DEFAULT_TOF_PIXEL_ERROR_PX = 0.5  # half a TOF pixel
DEFAULT_THRESHOLD_PX = 0.5  # the method's "not significant for data fusion"
RANGE_MIN_M = 0.1  # the TOF's range
RANGE_MAX_M = 10.0
DEFAULT_STEP_M = 0.01
MAX_SAMPLES = 1_000_000
REFINE_TOL_M = 1e-7

KINDS = ("distance_error", "tof_pixel_error")

# shifts(d) for every sensor: (M,) radial distances in metres -> (S, M, 2) pixels.
ShiftFunction = Callable[[np.ndarray], np.ndarray]


# -- inputs -------------------------------------------------------------------------------


def _finite(value: float, name: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(x):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return x


def _non_negative(value: float, name: str) -> float:
    x = _finite(value, name)
    if x < 0.0:
        raise ValueError(f"{name}: expected a number >= 0, got {x:g}")
    return x


def _positive(value: float, name: str) -> float:
    x = _finite(value, name)
    if x <= 0.0:
        raise ValueError(f"{name}: expected a number > 0, got {x:g}")
    return x


def sample_distances(
    min_m: float = RANGE_MIN_M, max_m: float = RANGE_MAX_M, step_m: float = DEFAULT_STEP_M
) -> np.ndarray:
    """Radial distances ``min_m, min_m + step_m, ...`` up to and including ``max_m``.

    Args:
        min_m, max_m: the range in metres, ``0 < min_m < max_m``.
        step_m: the spacing in metres, > 0; if it does not divide the range, the last
            interval is shorter (``max_m`` is always the last sample).

    Returns:
        (N,) float64 ascending distances in metres, N >= 2 (991 for the defaults), rounded
        to 1e-9 m so that 0.1 + 0.2 prints as 0.3.
    """
    lo = _positive(min_m, "min_m")
    hi = _positive(max_m, "max_m")
    step = _positive(step_m, "step_m")
    if not lo < hi:
        raise ValueError(f"range: expected min_m < max_m, got {lo:g} and {hi:g}")
    n = int(np.floor((hi - lo) / step + 1e-9)) + 1
    if n > MAX_SAMPLES:
        raise ValueError(
            f"step_m: {step:g} m gives {n} samples over {lo:g}-{hi:g} m; "
            f"expected at most {MAX_SAMPLES}"
        )
    d = np.round(lo + step * np.arange(n), 9)
    if d[-1] < hi - 1e-9:
        d = np.append(d, hi)
    d[-1] = hi
    return d


def _tof_ray(rig: Rig, tof: str, pixel: Sequence[float], require_inside: bool = True) -> np.ndarray:
    """(3,) unit ray through TOF pixel ``pixel`` = (u, v); ValueError if it has none (or,
    with ``require_inside``, if the pixel is outside the TOF image)."""
    s = rig[tof]
    uv = np.array([_finite(pixel[0], "tof pixel u"), _finite(pixel[1], "tof pixel v")])
    if require_inside and not in_image(uv, s.width, s.height):
        raise ValueError(
            f"tof pixel: ({uv[0]:g}, {uv[1]:g}) is outside the {s.width} x {s.height} image "
            f"of TOF sensor {tof!r} (u in [-0.5, {s.width - 0.5:g}), v in "
            f"[-0.5, {s.height - 0.5:g}))"
        )
    ray = s.intrinsics.unproject(uv)
    xy = ray[:2] / ray[2]
    if not np.all(np.isfinite(ray)) or np.hypot(*xy) > monotonic_radius(s.intrinsics):
        raise ValueError(
            f"tof pixel: ({uv[0]:g}, {uv[1]:g}) has no ray: the distortion model of TOF "
            f"sensor {tof!r} cannot be inverted there"
        )
    return ray


def _other_sensors(rig: Rig, tof: str, sensors: Sequence[str] | None) -> list[str]:
    if sensors is None:
        names = [n for n, s in rig.sensors.items() if s.modality != "tof" and n != tof]
    else:
        names = list(sensors)
        for n in names:
            rig[n]  # KeyError naming it
    if not names:
        raise ValueError(f"rig: expected sensors besides the TOF {tof!r}, got {rig.names}")
    return names


# -- shifts -------------------------------------------------------------------------------


def _shift_function(
    rig: Rig,
    tof: str,
    sensors: Sequence[str],
    ray0: np.ndarray,
    ray1: np.ndarray,
    distance_offset_m: float,
) -> ShiftFunction:
    """``shifts(d) = p_s((d + offset) * ray1) - p_s(d * ray0)`` for every sensor s."""

    def shifts(distance_m: np.ndarray) -> np.ndarray:
        d = np.asarray(distance_m, dtype=np.float64)[:, None]
        p0 = d * ray0
        p1 = (d + distance_offset_m) * ray1
        out = np.empty((len(sensors), d.shape[0], 2))
        for i, name in enumerate(sensors):
            out[i] = project_to_sensor(p1, rig, name, tof) - project_to_sensor(p0, rig, name, tof)
        return out

    return shifts


def _distance_error_function(
    rig: Rig, tof: str, sensors: Sequence[str], pixel: Sequence[float], distance_error_m: float
) -> ShiftFunction:
    ray = _tof_ray(rig, tof, pixel)
    return _shift_function(rig, tof, sensors, ray, ray, distance_error_m)


def _pixel_error_function(
    rig: Rig, tof: str, sensors: Sequence[str], pixel: Sequence[float], pixel_error_px: float
) -> ShiftFunction:
    ray0 = _tof_ray(rig, tof, pixel)
    moved = (float(pixel[0]) + pixel_error_px, float(pixel[1]))
    ray1 = _tof_ray(rig, tof, moved, require_inside=False)
    return _shift_function(rig, tof, sensors, ray0, ray1, 0.0)


def distance_error_shifts(
    rig: Rig,
    tof_pixel: Sequence[float],
    distance_m: npt.ArrayLike,
    distance_error_m: float,
    sensors: Sequence[str] | None = None,
    tof: str | None = None,
) -> dict[str, np.ndarray]:
    """Pixel shift in each sensor caused by a TOF distance error.

    Args:
        rig: the calibrated rig.
        tof_pixel: (u, v) TOF pixel, pixels.
        distance_m: (N,) true radial distances in metres.
        distance_error_m: Δd in metres, >= 0 (the measured distance is d + Δd).
        sensors: sensors to report; default every sensor that is not a TOF, in rig order.
        tof: the TOF sensor; default the rig's only sensor of modality "tof".

    Returns:
        sensor name -> (N, 2) float64 signed shift ``p_s(d + Δd) - p_s(d)`` in that
        sensor's pixels (dx, dy).
    """
    return _shifts(
        _distance_error_function,
        rig,
        tof,
        sensors,
        tof_pixel,
        distance_m,
        distance_error_m,
        "distance_error_m",
    )


def tof_pixel_error_shifts(
    rig: Rig,
    tof_pixel: Sequence[float],
    distance_m: npt.ArrayLike,
    tof_pixel_error_px: float,
    sensors: Sequence[str] | None = None,
    tof: str | None = None,
) -> dict[str, np.ndarray]:
    """Pixel shift in each sensor caused by a TOF pixel error along the TOF's x axis.

    Args:
        rig: the calibrated rig.
        tof_pixel: (u, v) TOF pixel, pixels.
        distance_m: (N,) radial distances in metres.
        tof_pixel_error_px: δ in TOF pixels, >= 0 (the pixel taken is (u + δ, v)).
        sensors, tof: as in :func:`distance_error_shifts`.

    Returns:
        sensor name -> (N, 2) float64 signed shift ``p_s(u + δ, v, d) - p_s(u, v, d)`` in
        that sensor's pixels (dx, dy).
    """
    return _shifts(
        _pixel_error_function,
        rig,
        tof,
        sensors,
        tof_pixel,
        distance_m,
        tof_pixel_error_px,
        "tof_pixel_error_px",
    )


def _shifts(
    function_of: Callable[[Rig, str, Sequence[str], Sequence[float], float], ShiftFunction],
    rig: Rig,
    tof: str | None,
    sensors: Sequence[str] | None,
    tof_pixel: Sequence[float],
    distance_m: npt.ArrayLike,
    error: float,
    error_name: str,
) -> dict[str, np.ndarray]:
    """sensor name -> (N, 2) pixel shifts at ``distance_m`` (N,) metres of the shift
    function ``function_of`` builds for an ``error`` (checked >= 0, named ``error_name``)."""
    tof_name = tof_sensor_name(rig, tof)
    names = _other_sensors(rig, tof_name, sensors)
    err = _non_negative(error, error_name)
    d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
    shifts = function_of(rig, tof_name, names, tof_pixel, err)(d)
    return dict(zip(names, shifts, strict=True))


# -- threshold distances ------------------------------------------------------------------


def _above(shift: np.ndarray, threshold_px: float) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.abs(shift) >= threshold_px  # NaN -> False


def _threshold_distances(
    distance_m: np.ndarray,
    shifts: np.ndarray,
    threshold_px: float,
    shift_at: Callable[[np.ndarray], np.ndarray] | None,
) -> list[float | None]:
    """Threshold distance of K series at once.

    Args:
        distance_m: (N,) ascending radial distances, metres.
        shifts: (N, K) signed shifts in pixels.
        threshold_px: > 0.
        shift_at: (K,) distances -> (K,) shifts of series k at distance k (for the
            bisection), or None to interpolate linearly between the samples.

    Returns:
        K threshold distances in metres, or None.
    """
    n, k = shifts.shape
    above = _above(shifts, threshold_px)
    result: list[float | None] = [None] * k
    any_above = above.any(axis=0)
    last = n - 1 - np.argmax(above[::-1], axis=0)  # last sample at or above, per series
    refine = np.flatnonzero(any_above & (last < n - 1))
    for j in np.flatnonzero(any_above & (last == n - 1)):
        result[j] = float(distance_m[-1])
    if refine.size == 0:
        return result
    lo = distance_m[last[refine]].astype(np.float64)
    hi = distance_m[last[refine] + 1].astype(np.float64)
    if shift_at is not None:
        while np.max(hi - lo) > REFINE_TOL_M:
            mid = 0.5 * (lo + hi)
            at = np.full(k, np.nan)
            at[refine] = mid
            ok = _above(shift_at(at)[refine], threshold_px)
            lo = np.where(ok, mid, lo)
            hi = np.where(ok, hi, mid)
        values = 0.5 * (lo + hi)
    else:
        a = np.abs(shifts[last[refine], refine])
        b = np.abs(shifts[last[refine] + 1, refine])
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(np.isfinite(b) & (a > b), (a - threshold_px) / (a - b), 0.0)
        values = lo + np.clip(frac, 0.0, 1.0) * (hi - lo)
    for j, value in zip(refine, values, strict=True):
        result[j] = float(value)
    return result


def threshold_distance(
    distance_m: npt.ArrayLike,
    shift_px: npt.ArrayLike,
    threshold_px: float,
    shift_at: Callable[[np.ndarray], np.ndarray] | None = None,
) -> float | None:
    """The largest radial distance at which ``|shift| >= threshold_px`` (module docstring).

    Args:
        distance_m: (N,) ascending radial distances in metres.
        shift_px: (N,) signed shift in pixels at those distances (NaN = below).
        threshold_px: the threshold in pixels, > 0.
        shift_at: optional exact shift, (M,) distances -> (M,) pixels; with it the crossing
            is refined by bisection to 1e-7 m, without it interpolated linearly in |shift|.

    Returns:
        The distance in metres (the last sample if the shift is at or above the threshold
        there), or None if ``|shift|`` stays below the threshold at every sample.
    """
    d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
    s = np.asarray(shift_px, dtype=np.float64).reshape(-1)
    if d.shape != s.shape or d.size < 1:
        raise ValueError(
            f"shift_px: expected the shape {d.shape} of distance_m (at least one sample), "
            f"got {s.shape}"
        )
    if d.size > 1 and not np.all(np.diff(d) > 0):
        raise ValueError("distance_m: expected strictly ascending distances")
    t = _positive(threshold_px, "threshold_px")
    return _threshold_distances(d, s[:, None], t, shift_at)[0]


# -- the analysis -------------------------------------------------------------------------


def pixel_key(pixel: Sequence[float]) -> str:
    """``"<u>,<v>"``, the JSON key of a TOF pixel: up to 10 significant digits, e.g.
    ``"87.9,71.2"``, ``"157,71.2"``; ``--tof-pixel`` reads it back."""
    return f"{float(pixel[0]):.10g},{float(pixel[1]):.10g}"


def default_tof_pixels(rig: Rig, tof: str | None = None) -> list[tuple[float, float]]:
    """The method's two TOF pixels: the principal point and the edge of region 3.

    Returns:
        ``[(cx, cy), (u3, cy)]`` in TOF pixels, with ``u3`` the last column of region 3 right
        of the centre (``calib.tof.region3_edge_pixel``) and ``cy`` the principal point's
        row, i.e. on the TOF's x axis (see the module docstring).
    """
    s = rig[tof_sensor_name(rig, tof)]
    i = s.intrinsics
    u3, _ = region3_edge_pixel(s.width, s.height)
    return [(i.cx, i.cy), (float(u3), i.cy)]


def tof_pixel_label(rig: Rig, pixel: Sequence[float], tof: str | None = None) -> str:
    """``"principal point"`` or ``"region 3 edge"`` for the default pixels, else ``""``."""
    labels = ("principal point", "region 3 edge")
    for label, p in zip(labels, default_tof_pixels(rig, tof), strict=True):
        if pixel_key(p) == pixel_key(pixel):
            return label
    return ""


@dataclass(frozen=True, eq=False)
class SensorShift:
    """The shift curve of one sensor for one TOF pixel and one kind of error.

    Attributes:
        sensor: the sensor's name.
        distance_m: (N,) radial distances in metres (the true distance).
        dx_px, dy_px: (N,) signed shift in the sensor's pixels (+x right, +y down).
        x_m, y_m: threshold distances in metres for |dx| and |dy| (module docstring);
            None where the shift never reaches the threshold.
    """

    sensor: str
    distance_m: np.ndarray
    dx_px: np.ndarray
    dy_px: np.ndarray
    x_m: float | None
    y_m: float | None


@dataclass(frozen=True, eq=False)
class PrecisionAnalysis:
    """Shift curves and threshold distances for both kinds of error.

    Attributes:
        tof: the TOF sensor's name.
        sensors: the sensors analysed (every non-TOF sensor by default), rig order.
        tof_pixels: the TOF pixels (u, v), in order; keys are :func:`pixel_key`.
        distance_error_m: Δd, metres.
        tof_pixel_error_px: δ, TOF pixels.
        threshold_px: the threshold, pixels of each sensor.
        distance_error, tof_pixel_error: pixel key -> sensor -> :class:`SensorShift`.
    """

    tof: str
    sensors: tuple[str, ...]
    tof_pixels: tuple[tuple[float, float], ...]
    distance_error_m: float
    tof_pixel_error_px: float
    threshold_px: float
    distance_error: dict[str, dict[str, SensorShift]]
    tof_pixel_error: dict[str, dict[str, SensorShift]]

    def results(self, kind: str) -> dict[str, dict[str, SensorShift]]:
        """``"distance_error"`` or ``"tof_pixel_error"`` -> its results."""
        if kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
        return getattr(self, kind)

    def as_dict(self, decimals: int | None = 6) -> dict[str, Any]:
        """Plain data (JSON-ready) in the ``trifuse analyze --json`` shape::

            {"distance_error": {"<u>,<v>": {"<sensor>": {"x_m": float|null,
              "y_m": float|null, "curve": {"distance_m": [...], "dx_px": [...],
              "dy_px": [...]}}}}, "tof_pixel_error": {...same...}}

        Args:
            decimals: round shifts (pixels) and threshold distances (metres) to this many
                decimals (default 1e-6) to keep the output small; None keeps full precision.
                NaN shifts become None (JSON null).
        """

        def num(x: float | None) -> float | None:
            if x is None or not np.isfinite(x):
                return None
            return float(x) if decimals is None else round(float(x), decimals)

        def arr(a: np.ndarray) -> list[float | None]:
            b = a if decimals is None else np.round(a, decimals)
            return [None if not np.isfinite(x) else float(x) for x in b]

        return {
            kind: {
                key: {
                    name: {
                        "x_m": num(r.x_m),
                        "y_m": num(r.y_m),
                        "curve": {
                            "distance_m": [float(x) for x in r.distance_m],
                            "dx_px": arr(r.dx_px),
                            "dy_px": arr(r.dy_px),
                        },
                    }
                    for name, r in per_sensor.items()
                }
                for key, per_sensor in self.results(kind).items()
            }
            for kind in KINDS
        }


def _analyze_one(
    shifts_at: ShiftFunction, names: Sequence[str], distance_m: np.ndarray, threshold_px: float
) -> dict[str, SensorShift]:
    shifts = shifts_at(distance_m)  # (S, N, 2)
    s_count = len(names)
    series = shifts.transpose(1, 0, 2).reshape(distance_m.size, 2 * s_count)  # (N, S*2)
    sensor_of = np.repeat(np.arange(s_count), 2)
    axis_of = np.tile(np.arange(2), s_count)

    def shift_at(d: np.ndarray) -> np.ndarray:
        # series k at distance d[k]; every sensor is evaluated at every d (K is tiny)
        good = np.isfinite(d)
        out = np.full(d.shape, np.nan)
        if good.any():
            all_shifts = shifts_at(d[good])  # (S, M, 2)
            idx = np.flatnonzero(good)
            out[idx] = all_shifts[sensor_of[idx], np.arange(idx.size), axis_of[idx]]
        return out

    thresholds = _threshold_distances(distance_m, series, threshold_px, shift_at)
    return {
        name: SensorShift(
            sensor=name,
            distance_m=distance_m,
            dx_px=shifts[i, :, 0],
            dy_px=shifts[i, :, 1],
            x_m=thresholds[2 * i],
            y_m=thresholds[2 * i + 1],
        )
        for i, name in enumerate(names)
    }


def analyze_precision(
    rig: Rig,
    tof_pixels: Sequence[Sequence[float]] | None = None,
    distance_error_m: float = DEFAULT_DISTANCE_ERROR_M,
    tof_pixel_error_px: float = DEFAULT_TOF_PIXEL_ERROR_PX,
    threshold_px: float = DEFAULT_THRESHOLD_PX,
    distance_m: npt.ArrayLike | None = None,
    sensors: Sequence[str] | None = None,
    tof: str | None = None,
) -> PrecisionAnalysis:
    """Shift curves and threshold distances for both kinds of TOF error (section 4.1).

    Args:
        rig: the calibrated rig.
        tof_pixels: TOF pixels (u, v); default :func:`default_tof_pixels`. Duplicates
            (same :func:`pixel_key`) are analysed once.
        distance_error_m: Δd in metres, >= 0 (default 0.041, the method's value before range
            calibration).
        tof_pixel_error_px: δ in TOF pixels, >= 0 (default 0.5).
        threshold_px: the threshold in each sensor's pixels, > 0 (default 0.5).
        distance_m: (N,) ascending radial distances in metres, N >= 2; default
            :func:`sample_distances` (0.1-10 m in 0.01 m steps).
        sensors: sensors to analyse; default every sensor that is not a TOF, rig order.
        tof: the TOF sensor; default the rig's only sensor of modality "tof".

    Returns:
        A :class:`PrecisionAnalysis`.

    Raises:
        ValueError: no (or several) TOF sensors, a negative error, a threshold <= 0, a
            pixel outside the TOF image or without a ray, bad distances.
        KeyError: an unknown sensor name.
    """
    tof_name = tof_sensor_name(rig, tof)
    names = _other_sensors(rig, tof_name, sensors)
    dist_err = _non_negative(distance_error_m, "distance_error_m")
    pix_err = _non_negative(tof_pixel_error_px, "tof_pixel_error_px")
    thr = _positive(threshold_px, "threshold_px")
    if distance_m is None:
        d = sample_distances()
    else:
        d = np.asarray(distance_m, dtype=np.float64).reshape(-1)
        if d.size < 2 or not np.all(np.isfinite(d)) or not np.all(np.diff(d) > 0) or d[0] <= 0:
            raise ValueError(
                "distance_m: expected at least 2 finite, positive, strictly ascending "
                f"distances, got {d.size} values"
            )
    pixels: dict[str, tuple[float, float]] = {}
    for p in default_tof_pixels(rig, tof_name) if tof_pixels is None else tof_pixels:
        if len(p) != 2:
            raise ValueError(f"tof pixel: expected (u, v), got {tuple(p)!r}")
        pixel = (_finite(p[0], "tof pixel u"), _finite(p[1], "tof pixel v"))
        pixels.setdefault(pixel_key(pixel), pixel)
    if not pixels:
        raise ValueError("tof_pixels: expected at least one TOF pixel, got none")

    by_distance: dict[str, dict[str, SensorShift]] = {}
    by_pixel: dict[str, dict[str, SensorShift]] = {}
    for key, pixel in pixels.items():
        f_dist = _distance_error_function(rig, tof_name, names, pixel, dist_err)
        f_pix = _pixel_error_function(rig, tof_name, names, pixel, pix_err)
        by_distance[key] = _analyze_one(f_dist, names, d, thr)
        by_pixel[key] = _analyze_one(f_pix, names, d, thr)
    return PrecisionAnalysis(
        tof=tof_name,
        sensors=tuple(names),
        tof_pixels=tuple(pixels.values()),
        distance_error_m=dist_err,
        tof_pixel_error_px=pix_err,
        threshold_px=thr,
        distance_error=by_distance,
        tof_pixel_error=by_pixel,
    )
