"""Pinhole camera intrinsics with OpenCV's distortion model, vectorised in numpy.

Frames follow OpenCV: +x right, +y down, +z forward; the centre of the top-left pixel is
(0, 0). Distortion coefficients follow OpenCV's order ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``:

    r2 = x^2 + y^2
    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx xd + cx,   v = fy yd + cy

``project`` and ``unproject`` are exact inverses (Newton iteration, not OpenCV's
fixed-point ``undistortPoints``) wherever the model is invertible; elsewhere the result
is NaN, never a wrong ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np
import numpy.typing as npt

from trifuse.calib.numbers import check_finite

DISTORTION_LENGTHS = (4, 5, 8)

MAX_RAY_RADIUS = 1e4
"""Largest normalised radius ``sqrt(x^2 + y^2)`` (x = X/Z, y = Y/Z) that projects: a ray
within 0.006 degrees of the image plane (or a point on it, where ``Z`` is a rounding error
such as 1e-17) is seen by no lens, and its powers overflow the distortion polynomial."""

PHYSICAL_FOV_DEG = (0.1, 179.0)
"""The field of view across the image that a focal length may give, degrees, as the pinhole
model reads it (``2 atan(width / (2 fx))``, likewise height and fy): from a long
telephoto's to beyond a fisheye's (whose rational model has a focal length of about a
quarter of the image's width: 127 degrees by this reading). A rig file beyond is refused
(:func:`physical_problem`)."""
MAX_PRINCIPAL_POINT_OFFSET = 1.0
"""How far outside the image the principal point may lie, in image widths (cx) and heights
(cy): a crop of a larger sensor can move it off the image, not further. Or else within
:data:`MAX_AXIS_ANGLE_DEG` of the image centre's direction."""
MAX_AXIS_ANGLE_DEG = 30.0
"""How far the optical axis may point from the image centre's direction, degrees, as the
pinhole model reads it (``atan(|cx - (width - 1) / 2| / fx)``, likewise cy): a telephoto's
principal point is barely observable, and OpenCV puts it up to about 6 image sizes away
from two views (up to about 7 degrees) of a 0.5- to 2-degree lens."""
MAX_DISTORTION_TERM = 1e6
"""The largest magnitude of a distortion term at the image's farthest corner: ``|k1| r^2``,
``|k2| r^4``, ``|k3| r^6`` (likewise k4 k5 k6 of the denominator) and ``|p1| r``, ``|p2| r``
(the tangential shift over the radius), ``r`` that corner's normalised radius as the pinhole
model reads it. Dimensionless, so it means the same for every lens; a coefficient's size
alone does not: a narrow lens's coefficients grow as its corner radius shrinks (OpenCV
gives a 2-degree telephoto k's beyond 1e6 from two views, and there a k3 of 1e6 moves the
corner by a tenth of a pixel). OpenCV's fits keep every term below about 6e3, also where
the rational model's numerator and denominator terms nearly cancel (OpenCV's sample
photographs, tests/data/opencv-left-9x6, two at a time). k1 = 1e300 overflows."""
_TERM_POWERS = (2, 4, 1, 1, 6, 2, 4, 6)
"""The power of the corner radius in each coefficient's term (OpenCV's order)."""
COEFFICIENT_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
"""The distortion coefficients in OpenCV's order."""

# Normalised radii scanned for the fold of the distortion: step 1e-3 up to 2 (63 degrees off
# axis), then geometric up to MAX_RAY_RADIUS.
PROJECT_CHUNK = 8192
"""Points projected at a time by :meth:`Intrinsics.project`: its float64 temporaries stay
at 64 KiB, which the allocator reuses; larger ones are mapped and unmapped at each call, and
their page faults took 3-4 times the arithmetic (76,800 points: 3.5-4.5 ms whole, 1.0 ms in
chunks)."""

_FOLD_SCAN = np.concatenate(
    [np.linspace(0.0, 2.0, 2001), np.geomspace(2.0, MAX_RAY_RADIUS, 2001)[1:]]
)


def _one_plus_cubic(r2: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    """``1 + r2 (a + r2 (b + r2 c))`` (a new array), in place after the first product: the
    operations and their order of the distortion model's expression, so the same bits."""
    out = r2 * c
    out += b
    out *= r2
    out += a
    out *= r2
    out += 1.0
    return out


@dataclass(frozen=True)
class Intrinsics:
    """Focal lengths and principal point in pixels, distortion in OpenCV's order.

    Hashable and comparable (plain floats and a tuple). ``K`` is the (3, 3) camera matrix.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, check_finite(getattr(self, name), name))
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal length must be positive, got fx={self.fx}, fy={self.fy}")
        dist = tuple(float(d) for d in self.distortion)
        if len(dist) not in DISTORTION_LENGTHS:
            raise ValueError(
                f"distortion: expected {', '.join(map(str, DISTORTION_LENGTHS))} coefficients "
                f"(k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {len(dist)}"
            )
        if not all(np.isfinite(dist)):
            raise ValueError(f"distortion: expected finite numbers, got {list(dist)}")
        object.__setattr__(self, "distortion", dist)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @cached_property
    def _coeffs(self) -> np.ndarray:
        """The 8 coefficients k1 k2 p1 p2 k3 k4 k5 k6, zero-padded."""
        c = np.zeros(8)
        c[: len(self.distortion)] = self.distortion
        return c

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients as a float64 array, for OpenCV calls."""
        return np.asarray(self.distortion, dtype=np.float64)

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the same camera with the image resampled by ``factor``.

        Pixel centres stay consistent: ``u' = factor * (u + 0.5) - 0.5``.
        """
        return Intrinsics(
            self.fx * factor,
            self.fy * factor,
            factor * (self.cx + 0.5) - 0.5,
            factor * (self.cy + 0.5) - 0.5,
            self.distortion,
        )

    # -- distortion in normalised coordinates ------------------------------------------

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply distortion to normalised coordinates ``(..., 2)`` -> ``(..., 2)``."""
        xd, _ = self._distort_with_jacobian(xy, jacobian=False)
        return xd

    def _radial(self, r2: np.ndarray) -> np.ndarray:
        """The radial factor ``(1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + ...)`` at the
        squared normalised radii ``r2`` (a new array). The division is left out when k4-k6
        are zero (a division by exactly 1)."""
        k1, k2, _p1, _p2, k3, k4, k5, k6 = self._coeffs
        rad = _one_plus_cubic(r2, k1, k2, k3)
        if k4 or k5 or k6:
            rad /= _one_plus_cubic(r2, k4, k5, k6)
        return rad

    def _distorted(
        self, x: np.ndarray, y: np.ndarray, r2: np.ndarray, rad: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates (new arrays) of ``x``, ``y`` (any shape, the
        same), with ``r2 = x^2 + y^2`` and ``rad`` its :meth:`_radial` factor. In place
        where it can: a per-frame path (:meth:`project`)."""
        _k1, _k2, p1, p2 = self._coeffs[:4]
        xd = x * rad
        t = (2.0 * p1) * x
        t *= y
        xd += t
        t = 2.0 * x
        t *= x
        t += r2
        t *= p2
        xd += t
        yd = y * rad
        t = 2.0 * y
        t *= y
        t += r2
        t *= p1
        yd += t
        t = (2.0 * p2) * x
        t *= y
        yd += t
        return xd, yd

    def _distort_with_jacobian(
        self, xy: np.ndarray, jacobian: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        k1, k2, p1, p2, k3, k4, k5, k6 = self._coeffs
        x = xy[..., 0]
        y = xy[..., 1]
        r2 = x * x + y * y
        rad = self._radial(r2)
        out = np.empty(xy.shape, dtype=np.float64)
        out[..., 0], out[..., 1] = self._distorted(x, y, r2, rad)
        if not jacobian:
            return out, None
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        drad = (dnum * den - num * dden) / (den * den)  # d rad / d r2
        J = np.empty((*xy.shape[:-1], 2, 2), dtype=np.float64)
        J[..., 0, 0] = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        J[..., 0, 1] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        J[..., 1, 0] = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        J[..., 1, 1] = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        return out, J

    def _radial_and_slope(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radial factor and ``d(r * radial) / dr`` at normalised points ``(..., 2)``."""
        k1, k2, _p1, _p2, k3, k4, k5, k6 = self._coeffs
        r2 = xy[..., 0] ** 2 + xy[..., 1] ** 2
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        rad = num / den
        return rad, rad + 2.0 * r2 * (dnum * den - num * dden) / (den * den)

    def undistort(self, xy_d: np.ndarray, max_iter: int = 30, tol: float = 1e-13) -> np.ndarray:
        """Invert ``distort`` by Newton's method; ``(..., 2)`` -> ``(..., 2)``.

        Points where the model is not invertible (or the iteration does not converge
        to ``tol``) come back as NaN.
        """
        xy_d = np.asarray(xy_d, dtype=np.float64)
        if not any(self.distortion):
            return xy_d.copy()
        xy = xy_d.copy()
        for _ in range(max_iter):
            f, J = self._distort_with_jacobian(xy)
            r = f - xy_d
            if np.nanmax(np.abs(r), initial=0.0) < tol:
                break
            a, b, c, d = J[..., 0, 0], J[..., 0, 1], J[..., 1, 0], J[..., 1, 1]
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                xy[..., 0] -= (d * r[..., 0] - b * r[..., 1]) / det
                xy[..., 1] -= (-c * r[..., 0] + a * r[..., 1]) / det
        f, J = self._distort_with_jacobian(xy)
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        # Beyond the fold of the radial model the solution is a wrong ray: require the
        # radial factor and the derivative of the distorted radius to stay positive.
        rad, drad_dr = self._radial_and_slope(xy)
        bad = ~(np.max(np.abs(f - xy_d), axis=-1) < 1e-9) | ~(det > 0)
        bad |= ~(rad > 0) | ~(drad_dr > 0)
        xy[bad] = np.nan
        return xy

    # -- pixels <-> points / rays -------------------------------------------------------

    def project(self, points: npt.ArrayLike) -> np.ndarray:
        """Project camera-frame points ``(..., 3)`` in metres to pixels ``(..., 2)``.

        NaN for NaN points, for points on or behind the image plane (z <= 0, or so close
        to it that the normalised radius exceeds :data:`MAX_RAY_RADIUS`), and for points
        beyond the fold of the distortion model, where the polynomial would map them back
        into the image (:func:`monotonic_radius`). Points outside the image are not NaN.
        """
        P = np.asarray(points, dtype=np.float64)
        if P.shape[-1] != 3:
            raise ValueError(f"points: expected shape (..., 3), got {P.shape}")
        flat = P.reshape(-1, 3)
        uv = np.empty((flat.shape[0], 2), dtype=np.float64)
        for i in range(0, flat.shape[0], PROJECT_CHUNK):
            self._project_into(flat[i : i + PROJECT_CHUNK], uv[i : i + PROJECT_CHUNK])
        return uv.reshape(*P.shape[:-1], 2)

    def _project_into(self, P: np.ndarray, uv: np.ndarray) -> None:
        """:meth:`project` of points (N, 3) float64 into ``uv`` (N, 2)."""
        r_max = min(monotonic_radius(self), MAX_RAY_RADIUS)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            z = np.where(P[:, 2] > 0, P[:, 2], np.nan)
            x = P[:, 0] / z
            y = P[:, 1] / z
            r2 = x * x
            r2 += y * y
            # Beyond r_max (or NaN): hypot decides where r2 is too close to r_max^2 to tell.
            beyond = ~(r2 <= r_max * r_max * (1.0 - 1e-9))
            if beyond.any():
                i = np.flatnonzero(beyond)
                beyond[i] = ~(np.hypot(x[i], y[i]) <= r_max)
            u, v = self._distorted(x, y, r2, self._radial(r2))
        u *= self.fx
        u += self.cx
        v *= self.fy
        v += self.cy
        uv[:, 0] = u
        uv[:, 1] = v
        uv[beyond] = np.nan

    def normalized(self, pixels: npt.ArrayLike) -> np.ndarray:
        """Undistorted normalised coordinates ``(..., 2)`` of pixels ``(..., 2)``."""
        uv = np.asarray(pixels, dtype=np.float64)
        if uv.shape[-1] != 2:
            raise ValueError(f"pixels: expected shape (..., 2), got {uv.shape}")
        xy_d = np.empty(uv.shape, dtype=np.float64)
        xy_d[..., 0] = (uv[..., 0] - self.cx) / self.fx
        xy_d[..., 1] = (uv[..., 1] - self.cy) / self.fy
        return self.undistort(xy_d)

    def unproject(self, pixels: npt.ArrayLike) -> np.ndarray:
        """Unit rays ``(..., 3)`` (camera frame, z > 0) through pixels ``(..., 2)``."""
        xy = self.normalized(pixels)
        rays = np.empty((*xy.shape[:-1], 3), dtype=np.float64)
        rays[..., :2] = xy
        rays[..., 2] = 1.0
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        return rays


def corner_radius(intrinsics: Intrinsics, image_size: tuple[int, int]) -> float:
    """The normalised radius ``hypot((u - cx) / fx, (v - cy) / fy)`` of the image corner
    (the outer edge of a corner pixel) farthest from the principal point, as the pinhole
    model reads it (no distortion applied): the scale of the distortion terms
    (:data:`MAX_DISTORTION_TERM`).

    Args:
        intrinsics: the camera.
        image_size: (width, height), pixels.
    """
    width, height = image_size
    i = intrinsics
    dx = max(abs(-0.5 - i.cx), abs(width - 0.5 - i.cx)) / i.fx
    dy = max(abs(-0.5 - i.cy), abs(height - 0.5 - i.cy)) / i.fy
    return math.hypot(dx, dy)


def physical_problem(intrinsics: Intrinsics, image_size: tuple[int, int]) -> tuple[str, str] | None:
    """The first parameter that no real camera with an image of ``image_size`` has, and why.

    Bounds: the field of view of fx across the width and of fy across the height within
    :data:`PHYSICAL_FOV_DEG`; the principal point at most
    :data:`MAX_PRINCIPAL_POINT_OFFSET` image sizes outside the image or
    :data:`MAX_AXIS_ANGLE_DEG` off the image centre's direction; every distortion
    term at most :data:`MAX_DISTORTION_TERM` at the image's farthest corner. Beyond them a
    projection overflows or every pixel's ray is a rounding error.

    Args:
        intrinsics: the camera.
        image_size: (width, height), pixels (positive).

    Returns:
        ``(parameter, reason)``: the parameter's name (``fx``, ``fy``, ``cx``, ``cy`` or a
        coefficient's, e.g. ``k1``) and a sentence giving its value and the bound; None
        when every parameter is within the bounds.
    """
    i = intrinsics
    width, height = image_size
    lo, hi = PHYSICAL_FOV_DEG
    for name, f, side, across in (("fx", i.fx, width, "width"), ("fy", i.fy, height, "height")):
        fov = math.degrees(2.0 * math.atan2(side / 2.0, f))
        if not lo <= fov <= hi:
            f_lo, f_hi = (side / (2.0 * math.tan(math.radians(a) / 2.0)) for a in (hi, lo))
            return name, (
                f"{f:g} px gives a field of view of {fov:.4g} degrees across the {side}-pixel "
                f"{across}; expected {lo:g} to {hi:g} degrees ({name} from {f_lo:.4g} to "
                f"{f_hi:.4g} px)"
            )
    m, angle = MAX_PRINCIPAL_POINT_OFFSET, MAX_AXIS_ANGLE_DEG
    for name, c, f, side, across in (
        ("cx", i.cx, i.fx, width, "width"),
        ("cy", i.cy, i.fy, height, "height"),
    ):
        centre = (side - 1) / 2.0
        reach = max((m + 0.5) * side, f * math.tan(math.radians(angle)))
        if not abs(c - centre) <= reach:
            return name, (
                f"{c:g} px; expected {centre - reach:.6g} to {centre + reach:.6g} px (at most "
                f"{m:g} image {across} outside the image, or {angle:g} degrees off the image "
                "centre's direction)"
            )
    r = corner_radius(intrinsics, image_size)
    for name, k, power in zip(COEFFICIENT_NAMES, intrinsics.distortion, _TERM_POWERS, strict=False):
        scale = r**power
        if not abs(k) * scale <= MAX_DISTORTION_TERM:
            return name, (
                f"{name} = {k:g} makes a term of {abs(k) * scale:.3g} at the image's farthest "
                f"corner (normalised radius {r:.4g}); expected at most {MAX_DISTORTION_TERM:g} "
                f"(|{name}| at most {MAX_DISTORTION_TERM / scale:.4g})"
            )
    return None


@lru_cache(maxsize=64)
def monotonic_radius(intrinsics: Intrinsics) -> float:
    """Normalised radius up to which the radial distortion is one-to-one.

    The distorted radius ``r_d = r * radial(r^2)`` must grow with ``r`` and ``radial``
    must stay positive; beyond the first fold the polynomial maps points back into the
    image (wrong pixels) and its inverse is not the camera's ray. Found on a grid up to
    :data:`MAX_RAY_RADIUS`, conservatively: the last sample before the fold. The
    tangential terms (p1, p2) are ignored. ``inf`` if there is no fold.

    Args:
        intrinsics: the camera (cached per value; ``Intrinsics`` is hashable).

    Returns:
        The radius ``sqrt(x^2 + y^2)`` in normalised coordinates (x = X/Z, y = Y/Z).
    """
    if not any(intrinsics.distortion):
        return float("inf")
    k1, k2, _, _, k3, k4, k5, k6 = intrinsics._coeffs
    r = _FOLD_SCAN
    r2 = r * r
    with np.errstate(all="ignore"):
        radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        good = (radial > 0.0) & np.isfinite(radial)
        good[1:] &= np.diff(r * radial) > 0.0
    if good.all():
        return float("inf")
    first_bad = int(np.argmin(good))
    return float(r[max(first_bad - 2, 0)])


def pixel_grid(width: int, height: int) -> np.ndarray:
    """Pixel centres ``(height, width, 2)`` as (u, v) float64, u along columns."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([u, v], axis=-1)


def pixel_rays(intrinsics: Intrinsics, width: int, height: int) -> np.ndarray:
    """Unit rays through every pixel centre of a ``width`` x ``height`` image.

    Returns:
        (height, width, 3) float64 unit vectors in the camera frame (z > 0); ``rays[v, u]``
        is the ray through pixel (u, v). NaN where the distortion model cannot be inverted
        within its one-to-one zone (beyond :func:`monotonic_radius`).
    """
    rays = intrinsics.unproject(pixel_grid(width, height))
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = rays[..., :2] / rays[..., 2:3]
        rays[np.hypot(xy[..., 0], xy[..., 1]) > monotonic_radius(intrinsics)] = np.nan
    return rays
