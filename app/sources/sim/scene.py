"""Scene description for the simulated head: solids with optical, thermal and NIR surfaces.

World frame: +x right, +y down, +z forward (the head's rig frame when it looks straight
ahead), metres. Every solid answers two vectorised questions:

* ``intersect(origin, dirs)``: the ray parameter ``t`` (metres along unit ``dirs``) of the
  first hit in front of the shared ``origin``, ``inf`` on a miss;
* ``surface(points)``: the outward normal and 2-D surface coordinates (metres) at hit
  points, which the material turns into colour, temperature, emissivity and NIR
  reflectivity.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from trifuse.calib.board import Board

if TYPE_CHECKING:
    from trifuse.app.sources.sim.thermal_conditions import BoardThermal

_EPS = 1e-9


# -- materials --------------------------------------------------------------------------


@dataclass
class Material:
    """Surface properties, constant or patterned in surface coordinates (metres).

    Attributes:
        albedo_rgb: linear RGB reflectance in [0, 1].
        temperature_k: surface temperature in kelvin.
        emissivity: thermal emissivity in [0, 1] (the rest reflects the surroundings).
        nir_reflectivity: reflectance at the TOF's near-infrared wavelength, [0, 1].
        pattern: optional ``(period_m, contrast)``: a soft stripe texture in colour so
            surfaces are not featureless.
        temperature_gradient_k_per_m: linear temperature change along the second surface
            coordinate (e.g. a wall warmer towards the ceiling).
    """

    albedo_rgb: tuple[float, float, float]
    temperature_k: float
    emissivity: float = 0.95
    nir_reflectivity: float = 0.5
    pattern: tuple[float, float] | None = None
    temperature_gradient_k_per_m: float = 0.0

    def albedo(self, st: np.ndarray) -> np.ndarray:
        """Linear RGB (N, 3) at surface coordinates ``st`` (N, 2)."""
        rgb = np.broadcast_to(np.asarray(self.albedo_rgb, dtype=np.float32), (len(st), 3))
        if self.pattern is None:
            return rgb.copy()
        period, contrast = self.pattern
        s, t = st[:, 0], st[:, 1]
        wave = (
            0.5
            + 0.25 * np.sin(2 * np.pi * s / period)
            + 0.25
            * np.sin(2 * np.pi * t / (0.7 * period) + 0.5 * np.sin(2 * np.pi * s / (3.1 * period)))
        )
        return rgb * (1.0 - contrast + 2.0 * contrast * wave)[:, None].astype(np.float32)

    def temperature(self, st: np.ndarray) -> np.ndarray:
        """Surface temperature (N,) in kelvin."""
        return self.temperature_k + self.temperature_gradient_k_per_m * st[:, 1]

    def emissivity_at(self, st: np.ndarray) -> np.ndarray:
        return np.full(len(st), self.emissivity)

    def nir(self, st: np.ndarray) -> np.ndarray:
        return np.full(len(st), self.nir_reflectivity)

    def edge_key(self, st: np.ndarray) -> np.ndarray:
        """Integer label that changes across sharp pattern edges (for anti-aliasing)."""
        return np.zeros(len(st), dtype=np.int32)


@dataclass
class BlotchMaterial(Material):
    """A soft-edged blotch on a surface, e.g. a wet, evaporatively cooled patch of wall.

    Inside an irregular ellipse of half axes ``half_axes_m`` (surface coordinates, metres,
    centred at ``centre_st_m``) the surface has ``temperature_k`` and ``albedo_rgb``; over
    the outer ``edge_fraction`` of the radius it fades to ``surround_k`` and
    ``surround_rgb`` (the surface it lies on), which it has outside the ellipse, so a quad
    with this material blends into the wall behind it. The ellipse's rim wobbles by up to
    ``wobble`` of its radius (a fixed sum of sines of the angle: no straight edge).
    """

    surround_k: float = 293.15
    surround_rgb: tuple[float, float, float] = (0.62, 0.6, 0.55)
    centre_st_m: tuple[float, float] = (0.0, 0.0)
    half_axes_m: tuple[float, float] = (0.3, 0.3)
    edge_fraction: float = 0.35
    wobble: float = 0.12

    def weight(self, st: np.ndarray) -> np.ndarray:
        """(N,) float in [0, 1]: 1 inside the blotch, 0 outside, smooth over its edge."""
        u = (st[:, 0] - self.centre_st_m[0]) / self.half_axes_m[0]
        v = (st[:, 1] - self.centre_st_m[1]) / self.half_axes_m[1]
        r = np.hypot(u, v)
        a = np.arctan2(v, u)
        rim = 1.0 + self.wobble * (0.6 * np.sin(3 * a + 0.4) + 0.4 * np.sin(5 * a + 1.9))
        x = np.clip((rim - r) / (self.edge_fraction * rim), 0.0, 1.0)
        return x * x * (3.0 - 2.0 * x)  # smoothstep

    def albedo(self, st: np.ndarray) -> np.ndarray:
        w = self.weight(st)[:, None].astype(np.float32)
        inner = np.asarray(self.albedo_rgb, dtype=np.float32)
        outer = np.asarray(self.surround_rgb, dtype=np.float32)
        return outer + w * (inner - outer)

    def temperature(self, st: np.ndarray) -> np.ndarray:
        w = self.weight(st)
        return self.surround_k + w * (self.temperature_k - self.surround_k)


@dataclass
class BoardMaterial(Material):
    """The heated calibration board: a laser-cut aluminium plate over black matte foil.

    Black squares (foil): dark in colour, high emissivity so they read hot in thermal,
    low NIR reflectance so they are dark in TOF amplitude. White squares and the margin
    (bare aluminium): bright, low emissivity (they mirror the cooler room), bright in
    TOF amplitude. A ChArUco board's black squares and marker cells and a circle grid's
    circles are the foil in the same way (the board's :meth:`~calib.board.Board.is_black`
    says where). The heating is uneven: a hot spot off-centre and a cooler far edge.
    Surface coordinates are the board frame's (x, y) in metres (calib.board).
    """

    board: Board = field(default_factory=lambda: Board(9, 6, 0.06))
    hot_spot_xy_m: tuple[float, float] = (0.12, 0.08)
    hot_spot_sigma_m: float = 0.25
    heating_k: float = 22.0
    black_emissivity: float = 0.95
    """Thermal emissivity of the black squares (foil); the white squares' is
    ``white_emissivity`` (bare aluminium). Heated (``heating_k`` > 0) the higher one reads
    hot, cooled the colder one reads cold."""
    white_emissivity: float = 0.12
    black_nir: float = 0.06
    """Near-infrared reflectance of the black squares (TOF amplitude); ``white_nir`` that of
    the white squares and the margin."""
    white_nir: float = 0.75
    thermal: BoardThermal | None = None
    """Real-world conditions of this view (app.sources.sim.thermal_conditions); None: off."""

    def _black(self, st: np.ndarray) -> np.ndarray:
        """Whether board points ``st`` (N, 2) metres lie on a mark: a black square or a
        black marker cell (ChArUco), a circle (circle grids); only inside the patterned
        area (``board.extent_m()``), the margin around it is bare plate."""
        b = self.board
        x, y = st[:, 0], st[:, 1]
        x0, y0, x1, y1 = b.extent_m()
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        return inside & b.is_black(x, y)

    def albedo(self, st: np.ndarray) -> np.ndarray:
        black = self._black(st)
        out = np.empty((len(st), 3), dtype=np.float32)
        out[:] = (0.80, 0.80, 0.78)
        out[black] = (0.045, 0.045, 0.05)
        return out

    def temperature(self, st: np.ndarray) -> np.ndarray:
        dx = st[:, 0] - self.hot_spot_xy_m[0]
        dy = st[:, 1] - self.hot_spot_xy_m[1]
        spot = np.exp(-(dx * dx + dy * dy) / (2 * self.hot_spot_sigma_m**2))
        slope = 0.5 - 0.5 * np.clip(st[:, 0] / (self.board.size_m[0]), -0.2, 1.2)
        t = self.temperature_k + self.heating_k * (0.35 + 0.45 * spot + 0.2 * slope)
        return t if self.thermal is None else self.thermal.temperature(self.board, st, t)

    def emissivity_at(self, st: np.ndarray) -> np.ndarray:
        return np.where(self._black(st), self.black_emissivity, self.white_emissivity)

    def nir(self, st: np.ndarray) -> np.ndarray:
        return np.where(self._black(st), self.black_nir, self.white_nir)

    def edge_key(self, st: np.ndarray) -> np.ndarray:
        return self._black(st).astype(np.int32) + 1


# -- solids -----------------------------------------------------------------------------


@dataclass
class Solid(ABC):
    """A solid in the world frame with a material and a name (for ground truth)."""

    name: str
    material: Material

    @abstractmethod
    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter (...,) of the first hit of rays ``origin + t * dirs``; inf on a miss.

        Args:
            origin: (3,) shared ray origin, world frame, metres.
            dirs: (..., 3) unit directions, world frame.
        """

    @abstractmethod
    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Outward normals (N, 3) and surface coordinates (N, 2), metres, at hit points."""

    @abstractmethod
    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and radius (metres) of a sphere enclosing the solid."""

    @abstractmethod
    def closest(self, points: np.ndarray) -> np.ndarray:
        """The point (N, 3) of the solid's surface nearest to each of ``points`` (N, 3),
        world frame, metres (from inside or outside the solid)."""

    def hull_points(self) -> np.ndarray:
        """(N, 3) world points whose convex hull encloses the solid (the renderer's screen
        boxes come from them); by default the corners of the bounding sphere's cube."""
        c, r = self.bounding_sphere()
        return np.asarray(c, dtype=np.float64) + r * _CUBE


_CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)


def _corners_world(T: np.ndarray, lo: tuple[float, ...], hi: tuple[float, ...]) -> np.ndarray:
    """The 8 corners (world) of the local box ``lo <= p <= hi`` of frame ``T``."""
    local = np.where(_CUBE > 0, np.asarray(hi, dtype=np.float64), np.asarray(lo, dtype=np.float64))
    return local @ T[:3, :3].T + T[:3, 3]


def apply_affine(M: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``X @ M[:, :3].T + M[:, 3]`` for points/vectors ``(..., 3)``, in X's dtype.

    ``M`` is (3, 3) or (3, 4). OpenCV's ``transform`` is used: numpy's matmul with a
    3-wide inner dimension is several times slower on millions of rows.
    """
    shape = X.shape
    Xc = np.ascontiguousarray(X).reshape(-1, 1, 3)
    return cv2.transform(Xc, np.ascontiguousarray(M, dtype=X.dtype)).reshape(shape)


def _local(T_world_local: np.ndarray, origin: np.ndarray, dirs: np.ndarray):
    """Ray origin (as Python floats, so float32 arrays stay float32) and directions in the
    solid's local frame."""
    R = T_world_local[:3, :3]
    o = tuple(float(x) for x in R.T @ (origin - T_world_local[:3, 3]))
    return o, apply_affine(R.T, dirs)


def _to_world(T_world_local: np.ndarray, local: np.ndarray) -> np.ndarray:
    return apply_affine(T_world_local[:3, :], local)


def _to_local(T_world_local: np.ndarray, points: np.ndarray) -> np.ndarray:
    R, c = T_world_local[:3, :3], T_world_local[:3, 3]
    M = np.hstack([R.T, (-R.T @ c)[:, None]])
    return apply_affine(M, points)


@dataclass
class Quad(Solid):
    """A rectangle ``x0 <= x <= x1, y0 <= y <= y1`` in the plane z = 0 of ``T_world_quad``.

    Both sides are hit; the normal returned faces local -z. Surface coordinates are the
    local (x, y) in metres.
    """

    T_world_quad: np.ndarray = field(default_factory=lambda: np.eye(4))
    extent: tuple[float, float, float, float] = (-0.5, 0.5, -0.5, 0.5)

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        o, d = _local(self.T_world_quad, origin, dirs)
        dz = d[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[2] / dz
        x = o[0] + t * d[..., 0]
        y = o[1] + t * d[..., 1]
        x0, x1, y0, y1 = self.extent
        hit = (t > _EPS) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        return np.where(hit, t, np.inf)

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = self.T_world_quad[:3, :3]
        local = _to_local(self.T_world_quad, points)
        normals = np.broadcast_to(-R[:, 2].astype(points.dtype), points.shape).copy()
        return normals, local[:, :2]

    def closest(self, points: np.ndarray) -> np.ndarray:
        local = _to_local(self.T_world_quad, points)
        x0, x1, y0, y1 = self.extent
        local[:, 0] = np.clip(local[:, 0], x0, x1)
        local[:, 1] = np.clip(local[:, 1], y0, y1)
        local[:, 2] = 0.0
        return _to_world(self.T_world_quad, local)

    def hull_points(self) -> np.ndarray:
        x0, x1, y0, y1 = self.extent
        local = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
        return local @ self.T_world_quad[:3, :3].T + self.T_world_quad[:3, 3]

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        x0, x1, y0, y1 = self.extent
        centre_local = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
        c = self.T_world_quad[:3, :3] @ centre_local + self.T_world_quad[:3, 3]
        return c, float(np.hypot(x1 - x0, y1 - y0) / 2)


@dataclass
class Box(Solid):
    """An oriented box centred at the origin of ``T_world_box`` with ``half_size`` (m)."""

    T_world_box: np.ndarray = field(default_factory=lambda: np.eye(4))
    half_size: tuple[float, float, float] = (0.5, 0.5, 0.5)

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        o, d = _local(self.T_world_box, origin, dirs)
        t_near = np.full(d.shape[:-1], -np.inf, dtype=d.dtype)
        t_far = np.full(d.shape[:-1], np.inf, dtype=d.dtype)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k, h in enumerate(self.half_size):
                inv = 1.0 / d[..., k]
                ta = (-h - o[k]) * inv
                tb = (h - o[k]) * inv
                np.maximum(t_near, np.minimum(ta, tb), out=t_near)
                np.minimum(t_far, np.maximum(ta, tb), out=t_far)
        t = np.where(t_near > _EPS, t_near, t_far)
        return np.where((t_near <= t_far) & (t > _EPS), t, np.inf)

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = self.T_world_box[:3, :3]
        local = _to_local(self.T_world_box, points)
        h = np.asarray(self.half_size)
        axis = np.argmax(np.abs(local) / h, axis=1)
        n_local = np.zeros_like(local)
        n_local[np.arange(len(local)), axis] = np.sign(local[np.arange(len(local)), axis])
        # Surface coordinates: the two in-face axes (horizontal run + vertical).
        st = np.where(
            axis[:, None] == 1,
            local[:, [0, 2]],
            np.stack([local[:, 0] + local[:, 2], local[:, 1]], axis=1),
        )
        return apply_affine(R, n_local), st

    def closest(self, points: np.ndarray) -> np.ndarray:
        local = _to_local(self.T_world_box, points)
        h = np.asarray(self.half_size, dtype=local.dtype)
        inside = (np.abs(local) <= h).all(axis=1)
        out = np.clip(local, -h, h)
        # From inside: onto the nearest face.
        p = local[inside]
        axis = np.argmin(h - np.abs(p), axis=1)
        rows = np.arange(len(p))
        p[rows, axis] = np.where(p[rows, axis] >= 0, 1.0, -1.0) * h[axis]
        out[inside] = p
        return _to_world(self.T_world_box, out)

    def hull_points(self) -> np.ndarray:
        h = tuple(float(x) for x in self.half_size)
        return _corners_world(self.T_world_box, tuple(-x for x in h), h)

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return self.T_world_box[:3, 3].copy(), float(np.linalg.norm(self.half_size))


@dataclass
class Cylinder(Solid):
    """A capped cylinder of ``radius`` around the local y axis, ``y0 <= y <= y1``."""

    T_world_cylinder: np.ndarray = field(default_factory=lambda: np.eye(4))
    radius: float = 0.2
    y_range: tuple[float, float] = (-1.0, 0.0)

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        o, d = _local(self.T_world_cylinder, origin, dirs)
        dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
        a = dx * dx + dz * dz
        b = 2.0 * (o[0] * dx + o[2] * dz)
        c = o[0] ** 2 + o[2] ** 2 - self.radius**2  # a Python float
        disc = b * b - 4 * a * c
        y0, y1 = self.y_range
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.sqrt(np.maximum(disc, 0.0))
            t_best = np.full(d.shape[:-1], np.inf, dtype=d.dtype)
            for sign in (-1.0, 1.0):
                t = (-b + sign * sq) / (2 * a)
                y = o[1] + t * dy
                ok = (disc >= 0) & (t > _EPS) & (y >= y0) & (y <= y1)
                t_best = np.where(ok & (t < t_best), t, t_best)
            for yc in (y0, y1):
                t = (yc - o[1]) / dy
                x = o[0] + t * dx
                z = o[2] + t * dz
                ok = (t > _EPS) & (x * x + z * z <= self.radius**2)
                t_best = np.where(ok & (t < t_best), t, t_best)
        return t_best

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = self.T_world_cylinder[:3, :3]
        local = _to_local(self.T_world_cylinder, points)
        y0, y1 = self.y_range
        n_local = np.zeros_like(local)
        cap0 = local[:, 1] <= y0 + 1e-6
        cap1 = local[:, 1] >= y1 - 1e-6
        side = ~(cap0 | cap1)
        n_local[side, 0] = local[side, 0]
        n_local[side, 2] = local[side, 2]
        n_local[side] /= np.linalg.norm(n_local[side], axis=1, keepdims=True) + 1e-12
        n_local[cap0, 1] = -1.0
        n_local[cap1, 1] = 1.0
        st = np.stack([np.arctan2(local[:, 0], local[:, 2]) * self.radius, local[:, 1]], axis=1)
        return apply_affine(R, n_local), st

    def closest(self, points: np.ndarray) -> np.ndarray:
        local = _to_local(self.T_world_cylinder, points)
        y0, y1 = self.y_range
        r = self.radius
        x, y, z = local[:, 0], local[:, 1], local[:, 2]
        rho = np.hypot(x, z)
        safe = np.where(rho > 1e-12, rho, 1.0)
        ux = np.where(rho > 1e-12, x / safe, 1.0)
        uz = np.where(rho > 1e-12, z / safe, 0.0)
        side = np.stack([r * ux, np.clip(y, y0, y1), r * uz], axis=1)
        disc = np.minimum(rho, r)
        candidates = [side] + [
            np.stack([disc * ux, np.full_like(y, yc), disc * uz], axis=1) for yc in (y0, y1)
        ]
        d2 = np.stack([((c - local) ** 2).sum(axis=1) for c in candidates], axis=1)
        best = np.argmin(d2, axis=1)
        out = np.choose(best[:, None], candidates)
        return _to_world(self.T_world_cylinder, out)

    def hull_points(self) -> np.ndarray:
        r = self.radius
        y0, y1 = self.y_range
        return _corners_world(self.T_world_cylinder, (-r, y0, -r), (r, y1, r))

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        y0, y1 = self.y_range
        c = (
            self.T_world_cylinder[:3, :3] @ np.array([0, (y0 + y1) / 2, 0])
            + self.T_world_cylinder[:3, 3]
        )
        return c, float(np.hypot(self.radius, (y1 - y0) / 2))


@dataclass
class Sphere(Solid):
    """A sphere of ``radius`` (m) at ``centre`` (world)."""

    centre: tuple[float, float, float] = (0.0, 0.0, 2.0)
    radius: float = 0.2

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        oc = origin - np.asarray(self.centre)
        b = dirs[..., 0] * float(oc[0]) + dirs[..., 1] * float(oc[1]) + dirs[..., 2] * float(oc[2])
        c = float(oc @ oc) - self.radius**2
        disc = b * b - c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0 = -b - sq
        t1 = -b + sq
        t = np.where(t0 > _EPS, t0, t1)
        return np.where((disc >= 0) & (t > _EPS), t, np.inf)

    def surface(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = (points - np.asarray(self.centre, dtype=points.dtype)) / self.radius
        st = (
            np.stack([np.arctan2(n[:, 0], n[:, 2]), np.arcsin(np.clip(n[:, 1], -1, 1))], axis=1)
            * self.radius
        )
        return n, st

    def bounding_sphere(self) -> tuple[np.ndarray, float]:
        return np.asarray(self.centre, dtype=np.float64), self.radius

    def closest(self, points: np.ndarray) -> np.ndarray:
        c = np.asarray(self.centre, dtype=np.float64)
        v = points - c
        n = np.linalg.norm(v, axis=1, keepdims=True)
        v = np.where(n > 1e-12, v / np.where(n > 1e-12, n, 1.0), (1.0, 0.0, 0.0))
        return c + self.radius * v


@dataclass(frozen=True)
class Atmosphere:
    """A scene's thermal surroundings as a thermographer models them (issue 35): what the
    surfaces reflect and the air between them and the imager, in 7-14 um band radiance
    (:mod:`fusion.thermography`).

    Attributes:
        reflected_k: the apparent temperature of what every surface mirrors (and of what a
            ray that hits nothing sees: a sky, a far room), kelvin.
        air_k: the air's temperature, kelvin.
        humidity_pct: the air's relative humidity, percent.
    """

    reflected_k: float = 293.15
    air_k: float = 293.15
    humidity_pct: float = 50.0

    def apparent_k(
        self, emissivity: np.ndarray, temperature_k: np.ndarray, distance_m: np.ndarray
    ) -> np.ndarray:
        """What an ideal imager reads (kelvin, (N,)) of surfaces of ``emissivity`` and
        ``temperature_k`` at ``distance_m`` (> 0) along the ray (each (N,)): the measurement
        equation forward (:func:`fusion.thermography.apparent_temperature`)."""
        from trifuse.fusion.thermography import ObjectParameters, apparent_temperature

        air = ObjectParameters(
            reflected_k=self.reflected_k, air_k=self.air_k, humidity_pct=self.humidity_pct
        )
        return apparent_temperature(temperature_k, distance_m, air, emissivity=emissivity)


@dataclass
class Scene:
    """Solids plus the surroundings that reflective surfaces mirror (thermal).

    Thermal radiometry: with no ``atmosphere`` (the simulated head's scenes), a proxy of
    radiance, ``T^4``: a surface reads ``(eps T^4 + (1 - eps) ambient_k^4)^(1/4)`` at any
    distance, and a ray that hits nothing ``(0.9 ambient_k^4)^(1/4)`` (a cold room). With an
    :class:`Atmosphere`, the measurement equation in band radiance through the air over each
    ray's own length (:meth:`Atmosphere.apparent_k`); ``ambient_k`` is then unused by the
    thermal images.
    """

    solids: list[Solid]
    ambient_k: float = 293.15
    light_dir_world: tuple[float, float, float] = (0.3, 1.0, 0.4)  # towards +y = down
    atmosphere: Atmosphere | None = None

    def __post_init__(self) -> None:
        names = [s.name for s in self.solids]
        if len(set(names)) != len(names):
            raise ValueError(f"scene: solid names must be unique, got {names}")

    def surface_apparent_k(
        self, emissivity: np.ndarray, temperature_k: np.ndarray, distance_m: np.ndarray
    ) -> np.ndarray:
        """What an ideal thermal imager reads (kelvin, (N,)) of surface samples of
        ``emissivity`` and ``temperature_k`` hit ``distance_m`` along their rays (each
        (N,)), by the scene's radiometry (class docstring)."""
        if self.atmosphere is not None:
            return self.atmosphere.apparent_k(emissivity, temperature_k, distance_m)
        eps = np.asarray(emissivity, np.float64)
        t = np.asarray(temperature_k, np.float64)
        return (eps * t**4 + (1.0 - eps) * self.ambient_k**4) ** 0.25

    def miss_apparent_k(self) -> float:
        """What an ideal thermal imager reads (kelvin) along a ray that hits nothing."""
        if self.atmosphere is not None:
            return self.atmosphere.reflected_k
        return (0.9 * self.ambient_k**4) ** 0.25

    def nearest_surface(
        self, points: np.ndarray, chunk: int = 200_000
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The nearest surface of any solid to each of ``points`` (N, 3), world, metres.

        Returns:
            (distance (N,) metres, solid index (N,) int32 into ``solids``, the nearest
            surface point (N, 3) world).
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(points)
        dist = np.full(n, np.inf)
        index = np.full(n, -1, dtype=np.int32)
        nearest = np.zeros((n, 3))
        for a in range(0, n, chunk):
            p = points[a : a + chunk]
            d, i, q = dist[a : a + chunk], index[a : a + chunk], nearest[a : a + chunk]
            for k, solid in enumerate(self.solids):
                c = solid.closest(p)
                dk = np.linalg.norm(c - p, axis=1)
                better = dk < d
                d[better], i[better], q[better] = dk[better], k, c[better]
        return dist, index, nearest

    def apparent_temperature_k(
        self,
        index: np.ndarray,
        surface_points: np.ndarray,
        distance_m: np.ndarray | None = None,
    ) -> np.ndarray:
        """What an ideal thermal imager reads (kelvin, (N,)) at ``surface_points`` (N, 3)
        of the solids ``index`` (N,) seen from ``distance_m`` (N,) metres away (needed only
        with an :attr:`atmosphere`): the renderer's radiometry (:meth:`surface_apparent_k`)
        without noise, blur or the imager's offset."""
        if self.atmosphere is not None and distance_m is None:
            raise ValueError("apparent_temperature_k: a scene with an atmosphere needs distance_m")
        out = np.full(len(index), np.nan)
        for k in np.unique(index):
            if k < 0:
                continue
            sel = index == k
            solid = self.solids[int(k)]
            _, st = solid.surface(surface_points[sel])
            eps = solid.material.emissivity_at(st)
            t = solid.material.temperature(st)
            d = np.zeros(int(sel.sum())) if distance_m is None else np.asarray(distance_m)[sel]
            out[sel] = self.surface_apparent_k(eps, t, d)
        return out
