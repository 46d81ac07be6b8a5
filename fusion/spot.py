"""The spot meter: temperature and distance at a point of the fused picture, the hottest
and coldest pixels of a box, and the hot and cold spots of the whole picture.

A :class:`SpotMeter` reads a :class:`fusion.stereo.StereoFusion` right after
:meth:`~fusion.stereo.StereoFusion.compose` and freezes what a reading needs into a
:class:`SpotFrame` (one per fused picture, immutable, safe to query from any thread):

* each eye's temperatures on its colour pixels (``thermal_on_color``, kelvin, NaN where
  the thermal imager does not see the point), copied;
* each eye's depth per colour pixel: the z (along the colour camera's optical axis) of the
  TOF z-buffer cell the forward mapping used, and whether that cell had TOF depth
  (``measured``) or the mapping's fallback depth (``fallback``); the mapping's coarse cells
  themselves (:meth:`fusion.mapping.ViewMapping.coarse_depth`, never written again), a
  pixel read from the cell the mapping's full-resolution maps give it
  (:func:`nearest_cells`); taken again only when a new TOF frame changed the mapping.

Coordinates are the eye's colour-camera pixels (``x`` column 0..W-1, ``y`` row 0..H-1,
pixel centres at integers, OpenCV's convention). The distance of a pixel is measured from
the eye's colour camera along that pixel's own ray: ``z * |(x_n, y_n, 1)|`` with
``(x_n, y_n)`` its undistorted normalised coordinates (the radial distance a TOF camera in
the colour camera's place would report). A fallback depth is a guess (the scene's median
depth), not a measurement: such pixels report ``distance_m`` None and ``depth``
``"fallback"``.

Hot and cold spots (:attr:`SpotFrame.hot`, :attr:`SpotFrame.cold`) are robust to single
noisy or dead pixels: the picture is averaged over cells of ``cell_px`` x ``cell_px``
colour pixels (a cell with any pixel without a thermal view is left out), the cell means
are median-filtered over 3 x 3 cells (about 12 x 12 colour pixels, 3.6 x 3.6 thermal pixels
of the default head: a single outlying thermal pixel never wins), then the arg-max /
arg-min is taken. Its position is the winning cell's centre pixel, its temperature that
median. A spot stays in its cell while that is within ``hold_k`` (0.3 K) of the extreme,
so that the marker rests on a uniform hot pipe instead of wandering along it with the noise.

A box's extremes (:meth:`SpotFrame.area`) are the plain maximum and minimum of its pixels,
as a thermal camera's box tool shows them.

Cost, measured on a 2-core machine busy with other work (load average 4.4; default head,
two eyes of 1280 x 960): :meth:`SpotMeter.capture` 2.5 ms a picture (median; the hot and
cold spots 0.5 ms an eye, the copies 0.08 ms an eye, the four spots' readings about 1 ms);
after a new TOF frame nothing more since the depth is kept at the mapping's coarse cells
(it was 0.9 ms for full-resolution copies); a spot query 0.2 ms, a 161 x 101
box 0.3 ms, a whole eye 4.8 ms. Composing the picture itself took 23 ms.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from trifuse.calib.camera import Intrinsics
from trifuse.calib.numbers import is_integer
from trifuse.fusion.stereo import StereoFusion

DepthKind = Literal["measured", "fallback"]
"""Where a pixel's depth came from: the TOF (``measured``) or the mapping's fallback."""

KELVIN_AT_0C = 273.15

Extreme = tuple[int, int, float]
"""A hot or cold spot: colour pixel ``x``, ``y`` and its robust temperature, kelvin."""


class SpotError(ValueError):
    """A spot or box outside the picture, or an eye the rig does not have."""


@dataclass(frozen=True)
class SpotReading:
    """What the spot meter reads at one colour pixel of one eye.

    Attributes:
        eye: the eye (``left``/``right``).
        x, y: the colour-camera pixel (column, row).
        temperature_k: the fused temperature there, kelvin; None where the thermal imager
            does not see the point.
        distance_m: distance from the eye's colour camera to the point along the pixel's
            ray, metres; None without TOF depth there.
        depth: ``measured`` (TOF), ``fallback`` (no TOF depth: the mapping guessed), or
            None (no depth at all: no TOF frame yet).
        eyes_px: eye -> (x, y) float colour pixel where the same 3D point lies in that
            eye's picture (this eye's own pixel included), None where it falls outside
            or there is no depth; from the fallback depth where that is all there is.
    """

    eye: str
    x: int
    y: int
    temperature_k: float | None
    distance_m: float | None
    depth: DepthKind | None
    eyes_px: Mapping[str, tuple[float, float] | None] = field(default_factory=dict)

    @property
    def temperature_c(self) -> float | None:
        """The temperature in degrees Celsius (for people), None without one."""
        return None if self.temperature_k is None else self.temperature_k - KELVIN_AT_0C

    def as_dict(self) -> dict[str, Any]:
        """JSON-able: the attributes plus ``temperature_c``; ``eyes_px`` as lists."""
        return {
            "eye": self.eye,
            "x": self.x,
            "y": self.y,
            "temperature_k": self.temperature_k,
            "temperature_c": self.temperature_c,
            "distance_m": self.distance_m,
            "depth": self.depth,
            "eyes_px": {e: None if p is None else list(p) for e, p in self.eyes_px.items()},
        }


@dataclass(frozen=True)
class AreaReading:
    """A box of one eye: its hottest and coldest pixels and its mean temperature.

    Attributes:
        eye: the eye.
        box: (x0, y0, x1, y1) colour pixels, corners included, x0 <= x1, y0 <= y1.
        pixels: pixels in the box.
        thermal_pixels: of these, pixels with a temperature (the thermal imager sees them).
        max, min: the readings at the hottest and coldest pixel (the first in row order
            on a tie); None when no pixel of the box has a temperature.
        mean_k: mean temperature over ``thermal_pixels``, kelvin; None without any.
    """

    eye: str
    box: tuple[int, int, int, int]
    pixels: int
    thermal_pixels: int
    max: SpotReading | None
    min: SpotReading | None
    mean_k: float | None

    def as_dict(self) -> dict[str, Any]:
        """JSON-able, temperatures also in Celsius (``mean_c``)."""
        x0, y0, x1, y1 = self.box
        return {
            "eye": self.eye,
            "x0": x0,
            "y0": y0,
            "x1": x1,
            "y1": y1,
            "pixels": self.pixels,
            "thermal_pixels": self.thermal_pixels,
            "max": None if self.max is None else self.max.as_dict(),
            "min": None if self.min is None else self.min.as_dict(),
            "mean_k": self.mean_k,
            "mean_c": None if self.mean_k is None else self.mean_k - KELVIN_AT_0C,
        }


@dataclass(frozen=True)
class _EyeState:
    """One eye's frozen picture: kelvin (H, W) float32 (NaN: no thermal view); the depth of
    the mapping's coarse cells (:meth:`fusion.mapping.ViewMapping.coarse_depth`): z_m (hc,
    wc) float32 metres along the colour camera's axis (fallback included) and fallback (hc,
    wc) bool; arrays nobody writes."""

    kelvin: np.ndarray
    z_m: np.ndarray | None
    fallback: np.ndarray | None


def nearest_cells(
    xs: np.ndarray, ys: np.ndarray, size: tuple[int, int], cells: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """The (row, column) of the coarse cell whose value full-resolution pixels (``xs``,
    ``ys``) get from ``cv2.resize(..., size, interpolation=cv2.INTER_NEAREST)`` of a
    ``cells`` (hc, wc) grid to ``size`` (W, H): ``floor(x * (1 / (W / wc)))``, clipped,
    as OpenCV computes it."""
    w, h = size
    hc, wc = cells
    cols = np.minimum(np.floor(xs * (1.0 / (w / wc))).astype(np.int64), wc - 1)
    rows = np.minimum(np.floor(ys * (1.0 / (h / hc))).astype(np.int64), hc - 1)
    return rows, cols


class _Geometry:
    """The eyes' colour cameras: intrinsics and the transforms between them."""

    def __init__(self, fusion: StereoFusion) -> None:
        rig = fusion.rig
        self.eyes = fusion.eyes
        self.color = {e: rig.eyes[e].color for e in self.eyes}
        self.intrinsics: dict[str, Intrinsics] = {
            e: rig[self.color[e]].intrinsics for e in self.eyes
        }
        self.T = {
            (dst, src): rig.T(self.color[dst], self.color[src])
            for dst in self.eyes
            for src in self.eyes
        }
        self.size = fusion.size
        self._ray_length: dict[str, np.ndarray] = {}

    def ray_length(self, eye: str) -> np.ndarray:
        """(H, W) float32: ``|(x_n, y_n, 1)|`` of every colour pixel of ``eye`` (distance
        along its ray per metre of z), made on first use."""
        if eye not in self._ray_length:
            w, h = self.size
            xy = np.stack(np.meshgrid(np.arange(w), np.arange(h)), axis=-1).reshape(-1, 2)
            n = self.intrinsics[eye].normalized(xy)
            length = np.sqrt(1.0 + (n * n).sum(axis=1)).reshape(h, w).astype(np.float32)
            length.flags.writeable = False
            self._ray_length[eye] = length
        return self._ray_length[eye]

    def rays(self, eye: str, xy: np.ndarray) -> np.ndarray:
        """(N, 3) rays ``(x_n, y_n, 1)`` (camera frame, z = 1) of colour pixels (N, 2)."""
        n = self.intrinsics[eye].normalized(xy)
        return np.concatenate([n, np.ones((len(xy), 1))], axis=1)

    def eyes_px(self, eye: str, points: np.ndarray) -> list[dict[str, tuple[float, float] | None]]:
        """Per point (N, 3) of ``eye``'s colour frame (NaN rows: none), the pixel of every
        eye's colour camera it projects to (None outside the image or behind it)."""
        w, h = self.size
        out: list[dict[str, tuple[float, float] | None]] = [{} for _ in range(len(points))]
        for other in self.eyes:
            T = self.T[(other, eye)]
            P = points @ T[:3, :3].T + T[:3, 3]
            with np.errstate(invalid="ignore"):
                uv = self.intrinsics[other].project(P)
                ok = np.isfinite(uv).all(axis=1) & (P[:, 2] > 0)
                ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5)
                ok &= (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
            uv = np.round(uv, 2)
            for k, seen in enumerate(out):  # one entry per point read (a handful)
                seen[other] = (float(uv[k, 0]), float(uv[k, 1])) if ok[k] else None
        return out


class SpotFrame:
    """The spot meter's view of one fused picture (immutable; any thread may query it).

    Attributes:
        stamp_ns: the picture's time stamp.
        eyes: the eyes, in the picture's order (left half first).
        size: (width, height) of each eye's colour picture, pixels.
        hot, cold: eye -> the hot / cold spot of that eye's picture (robust, see the
            module doc), None where the eye has no thermal view at all.
    """

    def __init__(
        self,
        stamp_ns: int,
        geometry: _Geometry,
        states: Mapping[str, _EyeState],
        extremes: Mapping[str, tuple[Extreme | None, Extreme | None]],
    ) -> None:
        self.stamp_ns = int(stamp_ns)
        self._geo = geometry
        self._states = dict(states)
        self.eyes = geometry.eyes
        self.size = geometry.size
        self.hot: dict[str, SpotReading | None] = {}
        self.cold: dict[str, SpotReading | None] = {}
        for e, (hot, cold) in extremes.items():
            spots = [s for s in (hot, cold) if s is not None]
            readings = self._readings(e, [(x, y) for x, y, _ in spots], [t for *_, t in spots])
            it = iter(readings)
            self.hot[e] = next(it) if hot is not None else None
            self.cold[e] = next(it) if cold is not None else None

    # -- validation -------------------------------------------------------------------------

    def _check_eye(self, eye: str) -> _EyeState:
        if eye not in self._states:
            raise SpotError(f"eye: expected one of {list(self.eyes)}, got {eye!r}")
        return self._states[eye]

    def _check_pixel(self, name: str, value: int, limit: int) -> int:
        if not is_integer(value):
            raise SpotError(f"{name}: expected an integer pixel, got {value!r}")
        if not 0 <= value < limit:
            raise SpotError(f"{name}: expected a colour pixel 0..{limit - 1}, got {value}")
        return int(value)

    # -- readings ---------------------------------------------------------------------------

    def _readings(
        self, eye: str, xy: list[tuple[int, int]], temps: list[float] | None = None
    ) -> list[SpotReading]:
        """Readings at integer pixels ``xy`` of ``eye`` (vectorised over the few points);
        ``temps`` replaces the picture's temperature at each (the spots' robust values)."""
        if not xy:
            return []
        st = self._states[eye]
        px = np.asarray(xy, dtype=np.int64).reshape(-1, 2)
        xs, ys = px[:, 0], px[:, 1]
        kelvin = st.kelvin[ys, xs].astype(np.float64) if temps is None else np.asarray(temps)
        if st.z_m is None or st.fallback is None:
            z = np.full(len(px), np.nan)
            kinds: list[DepthKind | None] = [None] * len(px)
        else:
            rows, cols = nearest_cells(xs, ys, self.size, st.z_m.shape)
            z = st.z_m[rows, cols].astype(np.float64)
            fb = st.fallback[rows, cols]
            kinds = ["fallback" if f else "measured" for f in fb]
        rays = self._geo.rays(eye, px.astype(np.float64))
        points = rays * z[:, None]  # NaN rows without depth
        seen = self._geo.eyes_px(eye, points)
        dist = np.linalg.norm(rays, axis=1) * z
        out = []
        for k in range(len(px)):
            t = float(kelvin[k])
            d = float(dist[k]) if kinds[k] == "measured" and np.isfinite(dist[k]) else None
            out.append(
                SpotReading(
                    eye,
                    int(xs[k]),
                    int(ys[k]),
                    round(t, 3) if np.isfinite(t) else None,
                    None if d is None else round(d, 4),
                    kinds[k],
                    seen[k],
                )
            )
        return out

    def kelvin(self, eye: str) -> np.ndarray:
        """``eye``'s apparent temperatures (H, W) float32 kelvin (NaN: no thermal view),
        read-only."""
        return self._check_eye(eye).kelvin

    def samples(self, eye: str, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """At integer colour pixels (``xs``, ``ys``) (N,) of ``eye`` (inside the picture):
        the apparent temperature (N,) kelvin (NaN: no thermal view) and the distance (N,)
        metres from the eye's colour camera along each pixel's ray, NaN where the depth is
        the mapping's fallback or there is none yet (float64 each)."""
        st = self._check_eye(eye)
        kelvin = st.kelvin[ys, xs].astype(np.float64)
        if st.z_m is None or st.fallback is None:
            return kelvin, np.full(len(kelvin), np.nan)
        rows, cols = nearest_cells(xs, ys, self.size, st.z_m.shape)
        z = np.where(st.fallback[rows, cols], np.nan, st.z_m[rows, cols]).astype(np.float64)
        return kelvin, z * self._geo.ray_length(eye)[ys, xs]

    def spot(self, eye: str, x: int, y: int) -> SpotReading:
        """The reading at colour pixel (``x``, ``y``) of ``eye``; SpotError outside the
        picture or for an unknown eye."""
        self._check_eye(eye)
        w, h = self.size
        x = self._check_pixel("x", x, w)
        y = self._check_pixel("y", y, h)
        return self._readings(eye, [(x, y)])[0]

    def area(self, eye: str, x0: int, y0: int, x1: int, y1: int) -> AreaReading:
        """The box with corners (``x0``, ``y0``) and (``x1``, ``y1``) (colour pixels of
        ``eye``, in any order, both included): its hottest and coldest pixels (plain
        extremes) with their distances, and its mean temperature."""
        st = self._check_eye(eye)
        w, h = self.size
        xa, xb = sorted((self._check_pixel("x0", x0, w), self._check_pixel("x1", x1, w)))
        ya, yb = sorted((self._check_pixel("y0", y0, h), self._check_pixel("y1", y1, h)))
        patch = st.kelvin[ya : yb + 1, xa : xb + 1]
        valid = np.isfinite(patch)
        n = int(valid.sum())
        box = (xa, ya, xb, yb)
        if n == 0:
            return AreaReading(eye, box, patch.size, 0, None, None, None)
        hot = np.where(valid, patch, -np.inf).argmax()
        cold = np.where(valid, patch, np.inf).argmin()
        pw = patch.shape[1]
        at = [(xa + int(i % pw), ya + int(i // pw)) for i in (hot, cold)]
        r_max, r_min = self._readings(eye, at)
        mean = float(patch[valid].astype(np.float64).mean())
        return AreaReading(eye, box, patch.size, n, r_max, r_min, round(mean, 3))

    def extremes(self) -> dict[str, dict[str, dict[str, Any] | None]]:
        """The hot and cold spots for the stream's metadata (JSON-able):
        ``{"hot": {eye: {x, y, temperature_k, distance_m, depth} | None}, "cold": ...}``."""
        keys = ("x", "y", "temperature_k", "distance_m", "depth")

        def brief(r: SpotReading | None) -> dict[str, Any] | None:
            return None if r is None else {k: getattr(r, k) for k in keys}

        return {
            "hot": {e: brief(self.hot.get(e)) for e in self.eyes},
            "cold": {e: brief(self.cold.get(e)) for e in self.eyes},
        }


def robust_extremes(
    kelvin: np.ndarray,
    cell_px: int = 4,
    previous: tuple[tuple[int, int] | None, tuple[int, int] | None] = (None, None),
    hold_k: float = 0.0,
) -> tuple[Extreme | None, Extreme | None]:
    """The hot and cold spot of one picture: ``(x, y, temperature_k)`` each, or None
    where no cell has a thermal view.

    Args:
        kelvin: (H, W) float32 temperatures, kelvin, NaN where there is none.
        cell_px: cell size in pixels; the picture is averaged over cells (any NaN in a
            cell leaves it out), the cell means median-filtered over 3 x 3 cells, and the
            extreme cell's centre pixel and median returned.
        previous: the last picture's hot and cold spot pixels (x, y), or None.
        hold_k: a spot stays in the previous one's cell while that cell is within this
            many kelvin of the extreme (on a uniform hot pipe the extreme would wander
            along it from picture to picture with the noise), kelvin >= 0.
    """
    h, w = kelvin.shape
    hc, wc = max(1, h // cell_px), max(1, w // cell_px)
    cells = cv2.resize(kelvin, (wc, hc), interpolation=cv2.INTER_AREA)
    missing = np.isnan(cells)
    if missing.all():
        return None, None
    out: list[Extreme] = []
    kinds = ((-np.inf, np.argmax, 1.0), (np.inf, np.argmin, -1.0))
    for (fill, pick, sign), before in zip(kinds, previous, strict=True):
        filled = np.where(missing, np.float32(fill), cells).astype(np.float32, copy=False)
        med = cv2.medianBlur(filled, 3) if min(hc, wc) >= 3 else filled
        med[missing] = fill  # a cell without a view never wins, whatever its neighbours
        i = int(pick(med))
        value = float(med.flat[i])
        if not np.isfinite(value):  # only isolated cells: their own means
            med = filled
            i = int(pick(med))
            value = float(med.flat[i])
        if before is not None:
            px, py = before
            j = min(hc - 1, max(0, py * hc // h)) * wc + min(wc - 1, max(0, px * wc // w))
            held = float(med.flat[j])
            if np.isfinite(held) and sign * (value - held) <= hold_k:
                i, value = j, held
        cy, cx = divmod(i, wc)
        x = min(w - 1, int((cx + 0.5) * w / wc))
        y = min(h - 1, int((cy + 0.5) * h / hc))
        out.append((x, y, value))
    return out[0], out[1]


class SpotMeter:
    """Takes a :class:`SpotFrame` of a :class:`StereoFusion` after each composed picture.

    Args:
        fusion: the stereo fusion it reads (its ``thermal_on_color`` and forward mappings).
        cell_px: the hot/cold spots' cell size, colour pixels (:func:`robust_extremes`).
        hold_k: a hot or cold spot stays where it was while it is within this of the
            picture's extreme, kelvin (:func:`robust_extremes`; default 0.3 K, about four
            times the imagers' noise: the marker rests on a uniform hot object and follows
            it as it moves).
    """

    def __init__(self, fusion: StereoFusion, cell_px: int = 4, hold_k: float = 0.3) -> None:
        if cell_px < 1:
            raise ValueError(f"cell_px: expected an integer >= 1, got {cell_px}")
        if not hold_k >= 0:
            raise ValueError(f"hold_k: expected kelvin >= 0, got {hold_k}")
        self.fusion = fusion
        self.cell_px = cell_px
        self.hold_k = hold_k
        self._last: dict[str, tuple[tuple[int, int] | None, tuple[int, int] | None]] = {}
        self._geo = _Geometry(fusion)
        self._depth_of: object | None = None  # the TOF points the depth was taken from
        self._depth: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def _depth_now(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each eye's coarse (z, fallback) of the current mapping
        (:meth:`fusion.mapping.ViewMapping.coarse_depth`: arrays of its own that no later
        update writes), taken again after a new TOF frame (:attr:`StereoFusion.points` is a
        new array then)."""
        f = self.fusion
        if not f.ready:
            return {}
        points = f.points
        if points is not self._depth_of:
            self._depth = {e: f.fusion[e].forward.coarse_depth() for e in f.eyes}
            self._depth_of = points
        return self._depth

    def capture(self, stamp_ns: int) -> SpotFrame:
        """Freeze the fusion's last composed picture (call right after ``compose``):
        each eye's temperatures (copied), depths (taken when they changed) and its hot
        and cold spots (each eye through the fusion's ``map_eyes``: on both cores in the
        console). Returns the :class:`SpotFrame`."""
        f = self.fusion
        depth = self._depth_now()

        def eye(e: str) -> tuple[_EyeState, tuple[Extreme | None, Extreme | None]]:
            kelvin = f.thermal_on_color[e].copy()
            kelvin.flags.writeable = False
            z, fb = depth.get(e, (None, None))
            hot, cold = robust_extremes(
                kelvin, self.cell_px, self._last.get(e, (None, None)), self.hold_k
            )
            return _EyeState(kelvin, z, fb), (hot, cold)

        states, extremes = {}, {}
        for e, (state, (hot, cold)) in zip(f.eyes, f.map_eyes(eye, f.eyes), strict=True):
            states[e], extremes[e] = state, (hot, cold)
            self._last[e] = (None if hot is None else hot[:2], None if cold is None else cold[:2])
        return SpotFrame(stamp_ns, self._geo, states, extremes)
