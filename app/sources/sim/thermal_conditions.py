"""Real-world thermal conditions for the simulated heated board and thermal imagers.

What makes real LWIR images of a heated checkerboard hard to detect, each condition
switchable (all off by default: renders are then bit for bit those without this module)
and seeded (the same seed gives the same image):

board (:class:`BoardThermal`, the hook in ``BoardMaterial.temperature``)
    * **uneven heating**: a linear gradient in a random direction plus a small hot spot
      (a heat gun or lamp aimed at one place), ``uneven_heating_k`` peak to peak;
    * **cooling during a session**: the board's excess temperature over the room decays as
      ``exp(-t / cooling_time_constant_s)`` with the view's time ``t``, so the contrast
      falls from view to view;
    * **low contrast**: the board barely warmer than the room, scaled so that the two
      square kinds differ by about ``contrast_k`` (1-3 K) in apparent temperature;
    * **heat diffusion**: a real temperature difference ``square_delta_k`` between the
      square kinds (black squares heated more, e.g. under a lamp), blurred by lateral heat
      conduction over ``diffusion_length_m`` (a Gaussian of that sigma in the board plane):
      the squares' edges and corners wash out, their centres stay warm.

imager (:class:`ImagerThermal`, the hook in ``Renderer._thermal``)
    * **vignetting / narcissus**: an offset growing with the squared distance from a
      (seeded, slightly decentred) centre, ``narcissus_k`` at the image corners;
    * **fixed-pattern stripes**: a fixed offset per column (sigma ``stripe_k``) and per row
      (half of it), the same in every frame of one imager;
    * **raw 14-bit counts**: ``counts = counts_at_room + counts_per_k (T - ROOM_K)``,
      rounded and clipped to 0..16383, uint16 (what a radiometric core streams before its
      own conversion to temperature).

scene (functions in :mod:`app.sources.sim.scenarios`)
    * **partly out of view**: board poses that cut part of the board off
      (:func:`~app.sources.sim.scenarios.partial_view_poses`);
    * **hot objects beside the board**: a 60 C pipe and a person holding the board
      (:func:`~app.sources.sim.scenarios.hot_objects_beside_board`).

app.sources.sim.condition_views renders seeded thermal views under one set of conditions,
with the exact corner projections (the benchmark and the tests use them).
Temperatures in kelvin, lengths in metres, board coordinates in the board frame
(calib.board).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates
from scipy.special import ndtr

from trifuse.calib.board import Board

ROOM_K = 293.15
"""Reference temperature of the raw counts (kelvin) and the default room temperature."""
COUNTS_MAX = 16383
"""Largest 14-bit count."""


@dataclass(frozen=True)
class ImagerSettings:
    """The settings of the imager conditions, shared by :class:`ThermalConditions` (which
    documents them) and :class:`ImagerThermal` (which applies them)."""

    seed: int = 0
    narcissus_k: float = 0.0
    stripe_k: float = 0.0
    raw_counts: bool = False
    counts_per_k: float = 40.0
    counts_at_room: float = 8192.0


@dataclass(frozen=True)
class ThermalConditions(ImagerSettings):
    """Switchable, seeded conditions of the heated board and the thermal imagers.

    Every field's default switches its condition off. Units: kelvin, metres, seconds.

    Attributes:
        seed: seeds every random choice (gradient direction, hot spot, stripe pattern,
            narcissus centre, poses, hot objects).
        uneven_heating_k: peak-to-peak temperature added across the board by a gradient
            and a hot spot (0: off).
        cooling_time_constant_s: the board's excess over the room decays with this time
            constant over the session (0: off).
        view_interval_s: time between two views of a session (for the cooling).
        contrast_k: if set, the board's excess over the room is scaled so that the two
            square kinds differ by about this much in apparent temperature; a pair
            (lo, hi): drawn uniformly per view.
        square_delta_k: real temperature difference black minus white squares (0: off).
        diffusion_length_m: sigma of the lateral heat diffusion that blurs that
            difference (0: sharp).
        narcissus_k: offset at the image corners relative to the centre (0: off; > 0
            corners warmer).
        stripe_k: sigma of the per-column fixed-pattern offsets (rows get half; 0: off).
        raw_counts: deliver uint16 14-bit counts instead of float32 kelvin.
        counts_per_k: gain of the counts.
        counts_at_room: counts at ``ROOM_K``.
        partial_view: board poses that cut the board off at the image border.
        hot_objects: a hot pipe and a person beside the board.
    """

    uneven_heating_k: float = 0.0
    cooling_time_constant_s: float = 0.0
    view_interval_s: float = 20.0
    contrast_k: float | tuple[float, float] | None = None
    square_delta_k: float = 0.0
    diffusion_length_m: float = 0.0
    partial_view: bool = False
    hot_objects: bool = False

    @property
    def board_conditions(self) -> bool:
        """Whether any condition changes the board's temperature."""
        return bool(
            self.uneven_heating_k
            or self.cooling_time_constant_s
            or self.contrast_k is not None
            or self.square_delta_k
        )

    @property
    def imager_conditions(self) -> bool:
        """Whether any condition changes what the imager makes of the temperatures."""
        return bool(self.narcissus_k or self.stripe_k or self.raw_counts)

    def board_thermal(
        self,
        board: Board,
        room_k: float,
        view: int,
        centre_excess_k: float,
        emissivities: tuple[float, float] = (0.95, 0.12),
    ) -> BoardThermal | None:
        """The board's temperature model for view number ``view`` (0-based) of a session,
        or None if no board condition is on.

        Args:
            board: the checkerboard (its size places the gradient and the hot spot).
            room_k: the room's temperature (the board cools towards it).
            view: index of the view in the session (time ``view * view_interval_s``).
            centre_excess_k: the unconditioned board's temperature minus ``room_k`` in
                the middle of the board (for ``contrast_k``).
            emissivities: of the black and the white squares (for ``contrast_k``).
        """
        if not self.board_conditions:
            return None
        rng = np.random.default_rng([self.seed, 15, view])
        scale = 1.0
        if self.contrast_k is not None:
            eps_gap = abs(emissivities[0] - emissivities[1])
            if eps_gap < 1e-3 or abs(centre_excess_k) < 1e-3:
                raise ValueError(
                    "contrast_k: needs square kinds of different emissivity and a board "
                    f"warmer or cooler than the room (emissivities {emissivities}, excess "
                    f"{centre_excess_k:.3g} K)"
                )
            contrast = self.contrast_k
            if isinstance(contrast, tuple):
                contrast = rng.uniform(*contrast)
            scale = contrast / (eps_gap * abs(centre_excess_k))
        if self.cooling_time_constant_s:
            scale *= float(np.exp(-view * self.view_interval_s / self.cooling_time_constant_s))
        x0, y0, w, h = _area(board)
        angle = rng.uniform(0, 2 * np.pi)
        spot = (x0 + rng.uniform(0.15, 0.85) * w, y0 + rng.uniform(0.15, 0.85) * h)
        return BoardThermal(
            room_k=float(room_k),
            excess_scale=float(scale),
            uneven_k=float(self.uneven_heating_k),
            gradient_dir=(float(np.cos(angle)), float(np.sin(angle))),
            spot_xy_m=(float(spot[0]), float(spot[1])),
            spot_sigma_m=float(0.12 * max(w, h)),
            square_delta_k=float(self.square_delta_k),
            diffusion_length_m=float(self.diffusion_length_m),
        )

    def imager(self) -> ImagerThermal | None:
        """The imager model (None if no imager condition is on)."""
        if not self.imager_conditions:
            return None
        return ImagerThermal(
            seed=self.seed,
            narcissus_k=float(self.narcissus_k),
            stripe_k=float(self.stripe_k),
            raw_counts=bool(self.raw_counts),
            counts_per_k=float(self.counts_per_k),
            counts_at_room=float(self.counts_at_room),
        )


# -- the board ------------------------------------------------------------------------------


_FINE = (np.arange(200) + 0.5) / 200
"""Fractions of the patterned area sampled where a pattern's marks are looked for."""
_RASTER_STEP_M = 0.001
"""Grid step (metres) of the marks blurred by :func:`_blurred_marks` (at most a third of
the blur's sigma)."""
_RASTER_SUBSAMPLES = 4
"""Each grid cell holds the fraction of it covered by marks, from this many x this many
samples (the marks' edges then fall between grid points, not on them)."""


def _area(board: Board) -> tuple[float, float, float, float]:
    """``(x0, y0, width, height)`` of the board's patterned area, metres (board frame)."""
    x0, y0, x1, y1 = board.extent_m()
    return float(x0), float(y0), float(x1 - x0), float(y1 - y0)


def _blurred_steps(x: np.ndarray, edges: np.ndarray, jumps: np.ndarray, sigma: float) -> np.ndarray:
    """A piecewise-constant function (0 left of the first edge, ``+jumps[k]`` at
    ``edges[k]``) convolved with a Gaussian of ``sigma`` (same units), at ``x`` (N,)."""
    if sigma <= 0:
        return (x[:, None] >= edges[None, :]).astype(np.float64) @ jumps
    return ndtr((x[:, None] - edges[None, :]) / sigma) @ jumps


def _square_wave(n_squares: int, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Edges and jumps along one board axis of the checkered area ``[-s, (n - 1) s)`` (n
    squares): of its indicator (box) and of the indicator times ``(-1)^k`` on square k
    (k = floor(x / s), so +1 on the square starting at 0)."""
    k = np.arange(-1, n_squares - 1)  # the n squares [k s, (k + 1) s)
    edges = np.arange(-1, n_squares) * s  # their n + 1 edges
    box_jumps = np.zeros(len(edges))
    box_jumps[0], box_jumps[-1] = 1.0, -1.0
    values = np.concatenate([[0.0], np.where(k % 2 == 0, 1.0, -1.0), [0.0]])
    return edges, box_jumps, edges, np.diff(values)


def blurred_black(board: Board, st: np.ndarray, sigma_m: float) -> np.ndarray:
    """Fraction of black square (0..1) at board points ``st`` (N, 2) metres after a
    Gaussian blur of ``sigma_m`` in the board plane (exact: the pattern is separable;
    ``sigma_m`` = 0: ``BoardMaterial``'s black-square indicator itself).

    Black (calib.board): inside the checkered area and ``floor(x/s) + floor(y/s)`` even.
    With f(x) = (-1)^floor(x/s) and g likewise, black = box_x box_y (1 + f g) / 2, and a
    Gaussian blur of a product of functions of x and of y is the product of their blurs.
    Other patterns (ChArUco markers, circles) are not separable: their marks
    (``board.is_black`` inside the patterned area) are sampled on a grid of at most 1 mm,
    blurred there and interpolated (:func:`_blurred_marks`).
    """
    if board.pattern != "checkerboard":
        return _blurred_marks(board, st, sigma_m)
    s = board.square_size_m
    ex, bx, fx_e, fx = _square_wave(board.cols + 1, s)
    ey, by, fy_e, fy = _square_wave(board.rows + 1, s)
    x, y = st[:, 0].astype(np.float64), st[:, 1].astype(np.float64)
    box_x = _blurred_steps(x, ex, bx, sigma_m)
    box_y = _blurred_steps(y, ey, by, sigma_m)
    f = _blurred_steps(x, fx_e, fx, sigma_m)
    g = _blurred_steps(y, fy_e, fy, sigma_m)
    return 0.5 * (box_x * box_y + f * g)


def _blurred_marks(board: Board, st: np.ndarray, sigma_m: float) -> np.ndarray:
    """:func:`blurred_black` of a pattern that is not separable, (N,) in 0..1."""
    x, y = st[:, 0].astype(np.float64), st[:, 1].astype(np.float64)
    if sigma_m <= 0:
        x0, y0, w, h = _area(board)
        inside = (x >= x0) & (x < x0 + w) & (y >= y0) & (y < y0 + h)
        return (inside & board.is_black(x, y)).astype(np.float64)
    blurred, origin, step = _marks_raster(board, float(sigma_m))
    rows = (y - origin[1]) / step - 0.5  # pixel centres at (k + 0.5) step from the origin
    cols = (x - origin[0]) / step - 0.5
    return map_coordinates(blurred, [rows, cols], order=1, mode="constant", cval=0.0)


@lru_cache(maxsize=4)
def _marks_raster(board: Board, sigma_m: float) -> tuple[np.ndarray, tuple[float, float], float]:
    """The board's marks blurred by a Gaussian of ``sigma_m``: (H, W) float64 image, its
    top-left corner (x, y) in the board frame and its step, metres."""
    x0, y0, w, h = _area(board)
    step = min(_RASTER_STEP_M, sigma_m / 3.0)
    pad = 4.0 * sigma_m
    nx, ny = int(np.ceil((w + 2 * pad) / step)), int(np.ceil((h + 2 * pad) / step))
    origin = (x0 - pad, y0 - pad)
    sub = _RASTER_SUBSAMPLES  # each cell: the fraction of it that is a mark
    xs = origin[0] + (np.arange(nx * sub) + 0.5) * step / sub
    ys = origin[1] + (np.arange(ny * sub) + 0.5) * step / sub
    marks = np.empty((ny, nx))
    for r in range(0, ny, 64):  # 64 rows of cells at a time: bounded memory
        X, Y = np.meshgrid(xs, ys[r * sub : (r + 64) * sub])
        inside = (X >= x0) & (X < x0 + w) & (Y >= y0) & (Y < y0 + h)
        black = inside & board.is_black(X, Y)
        marks[r : r + 64] = black.reshape(-1, sub, nx, sub).mean(axis=(1, 3))
    return gaussian_filter(marks, sigma_m / step, mode="constant"), origin, step


@dataclass(frozen=True)
class BoardThermal:
    """The heated board's temperature under the conditions of one view.

    ``T = room + (T_board - room) * excess_scale + uneven + square_delta * black_blurred``
    where ``T_board`` is the unconditioned board's temperature, ``uneven`` a gradient
    plus hot spot of ``uneven_k`` peak to peak, and ``black_blurred`` the black-square
    indicator blurred by ``diffusion_length_m`` (:func:`blurred_black`).
    """

    room_k: float
    excess_scale: float = 1.0
    uneven_k: float = 0.0
    gradient_dir: tuple[float, float] = (1.0, 0.0)
    spot_xy_m: tuple[float, float] = (0.0, 0.0)
    spot_sigma_m: float = 0.1
    square_delta_k: float = 0.0
    diffusion_length_m: float = 0.0

    def temperature(self, board: Board, st: np.ndarray, base_k: np.ndarray) -> np.ndarray:
        """Temperatures (N,) kelvin at board points ``st`` (N, 2) metres, from the
        unconditioned temperatures ``base_k`` (N,) there."""
        t = self.room_k + (np.asarray(base_k, dtype=np.float64) - self.room_k) * self.excess_scale
        if self.uneven_k:
            x0, y0, w, h = _area(board)
            x = st[:, 0] - (x0 + 0.5 * w)
            y = st[:, 1] - (y0 + 0.5 * h)
            half = 0.5 * np.hypot(w, h)
            ramp = (self.gradient_dir[0] * x + self.gradient_dir[1] * y) / half  # -1..1
            dx = st[:, 0] - self.spot_xy_m[0]
            dy = st[:, 1] - self.spot_xy_m[1]
            spot = np.exp(-(dx * dx + dy * dy) / (2 * self.spot_sigma_m**2))
            # Gradient and spot share the peak-to-peak amount half and half.
            t = t + self.uneven_k * (0.25 * np.clip(ramp, -1, 1) + 0.5 * spot)
        if self.square_delta_k:
            t = t + self.square_delta_k * blurred_black(board, st, self.diffusion_length_m)
        return t


def centre_excess_k(material: object, board: Board, room_k: float) -> float:
    """The unconditioned board material's temperature minus ``room_k`` in the middle of
    the checkered area (``material`` is a ``BoardMaterial``)."""
    x0, y0, w, h = _area(board)
    centre = np.array([[x0 + 0.5 * w, y0 + 0.5 * h]])
    return float(material.temperature(centre)[0]) - room_k  # type: ignore[attr-defined]


def square_emissivities(material: object, board: Board) -> tuple[float, float]:
    """Emissivity of a black and of a white square (ChArUco: the white around a marker;
    circle grid: a circle and the plate) of ``material`` (a ``BoardMaterial``)."""
    s = board.square_size_m
    if board.pattern == "checkerboard":
        pts = np.array([[0.5 * s, 0.5 * s], [1.5 * s, 0.5 * s]])  # black (0, 0), white (1, 0)
    else:  # the first mark and the first white point of a fine grid over the pattern
        x0, y0, w, h = _area(board)
        g = np.stack(np.meshgrid(x0 + w * _FINE, y0 + h * _FINE), axis=-1).reshape(-1, 2)
        black = board.is_black(g[:, 0], g[:, 1])
        pts = np.array([g[black][0], g[~black][0]])
    eps = np.asarray(material.emissivity_at(pts), dtype=np.float64)  # type: ignore[attr-defined]
    return float(eps[0]), float(eps[1])


# -- the imager -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImagerThermal(ImagerSettings):
    """What a thermal imager adds to the scene's temperatures: vignetting/narcissus,
    fixed-pattern stripes and the raw-counts output (see :class:`ThermalConditions`)."""

    def _rng(self, sensor: str) -> np.random.Generator:
        return np.random.default_rng([self.seed, 16, zlib.crc32(sensor.encode())])

    def offsets_k(self, sensor: str, width: int, height: int) -> np.ndarray:
        """(H, W) float32 fixed offsets in kelvin of imager ``sensor``: narcissus plus
        stripes (the same for every frame of that imager)."""
        rng = self._rng(sensor)
        out = np.zeros((height, width), dtype=np.float32)
        centre = (
            (width - 1) / 2 + rng.uniform(-0.1, 0.1) * width,
            (height - 1) / 2 + rng.uniform(-0.1, 0.1) * height,
        )
        if self.narcissus_k:
            yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
            r2 = ((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2) / (
                (width / 2) ** 2 + (height / 2) ** 2
            )
            out += np.float32(self.narcissus_k) * r2
        cols = rng.standard_normal(width)
        rows = rng.standard_normal(height)
        if self.stripe_k:
            out += (self.stripe_k * cols[None, :] + 0.5 * self.stripe_k * rows[:, None]).astype(
                np.float32
            )
        return out

    def apply(self, temperature_k: np.ndarray, sensor: str) -> np.ndarray:
        """The image imager ``sensor`` delivers from the temperatures (H, W) float32 K it
        sees (noise included): float32 kelvin, or uint16 counts 0..16383 with
        ``raw_counts``."""
        h, w = temperature_k.shape
        t = temperature_k.astype(np.float32) + self.offsets_k(sensor, w, h)
        if not self.raw_counts:
            return t
        return to_counts(t, self.counts_per_k, self.counts_at_room)


def to_counts(
    temperature_k: np.ndarray, counts_per_k: float = 40.0, counts_at_room: float = 8192.0
) -> np.ndarray:
    """Kelvin (H, W) -> uint16 14-bit counts: ``counts_at_room + counts_per_k (T - ROOM_K)``,
    rounded, clipped to 0..16383."""
    c = counts_at_room + counts_per_k * (np.asarray(temperature_k, dtype=np.float64) - ROOM_K)
    return np.clip(np.rint(c), 0, COUNTS_MAX).astype(np.uint16)


def counts_to_kelvin(
    counts: np.ndarray, counts_per_k: float = 40.0, counts_at_room: float = 8192.0
) -> np.ndarray:
    """The inverse of :func:`to_counts` (float32 kelvin)."""
    return (ROOM_K + (np.asarray(counts, dtype=np.float64) - counts_at_room) / counts_per_k).astype(
        np.float32
    )


BENCH_CONDITIONS: dict[str, ThermalConditions] = {
    "none": ThermalConditions(),
    "uneven-heating": ThermalConditions(uneven_heating_k=15.0),
    "cooling": ThermalConditions(cooling_time_constant_s=60.0),
    "low-contrast": ThermalConditions(contrast_k=(1.0, 3.0)),
    "diffusion": ThermalConditions(square_delta_k=3.0, diffusion_length_m=0.015, contrast_k=0.5),
    "narcissus": ThermalConditions(narcissus_k=6.0),
    "stripes": ThermalConditions(stripe_k=1.0),
    "raw-counts": ThermalConditions(raw_counts=True),
    "partial-view": ThermalConditions(partial_view=True),
    "hot-objects": ThermalConditions(hot_objects=True),
    "combined": ThermalConditions(
        uneven_heating_k=8.0,
        cooling_time_constant_s=200.0,
        contrast_k=3.0,
        square_delta_k=2.0,
        diffusion_length_m=0.012,
        narcissus_k=4.0,
        stripe_k=0.5,
        raw_counts=True,
        partial_view=True,
        hot_objects=True,
    ),
}
"""The conditions of ``trifuse bench --only thermal-detect``, one at a time and all
combined (each with its strength on the scale of real sessions)."""
