"""The fusion geometry (docs/CONVENTIONS.md, "The geometry of the fusion"), vectorised in numpy.

A TOF pixel (u, v) with measured *radial* distance d (metres along the ray, not z):

1. undistort (u, v) with the TOF intrinsics to normalised (x, y); the unit ray is
   ``r = (x, y, 1) / sqrt(x^2 + y^2 + 1)`` in the TOF frame: :func:`tof_rays`;
2. the point is ``P = d * r`` (TOF frame, metres): :func:`tof_points`;
3. into a sensor: ``P' = R P + t`` with ``[R | t] = rig.T(sensor, tof)``: ``transform_points``;
4. perspective projection with the sensor's intrinsics and distortion: :func:`project_to_sensor`.

:func:`tof_to_sensor_pixels` runs the whole chain. Frames follow OpenCV (+x right, +y down,
+z forward); pixel centres are at integer coordinates. Invalid values are NaN throughout:
NaN in, NaN out, never a point at the origin or a pixel at (0, 0).
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from trifuse.calib.camera import MAX_RAY_RADIUS, Intrinsics, monotonic_radius, pixel_rays
from trifuse.calib.numbers import is_integer
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import transform_points

__all__ = [
    "Projector32",
    "in_image",
    "monotonic_radius",
    "project_to_sensor",
    "tof_points",
    "tof_rays",
    "tof_sensor_name",
    "tof_to_sensor_pixels",
    "transform_points",
]


def _positive_int(value: object, name: str) -> int:
    if not is_integer(value) or value <= 0:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")
    return int(value)


def _check_last_dim(a: np.ndarray, n: int, name: str) -> None:
    if a.ndim < 1 or a.shape[-1] != n:
        raise ValueError(f"{name}: expected shape (..., {n}), got {a.shape}")


def tof_rays(intrinsics: Intrinsics, width: int, height: int) -> np.ndarray:
    """Unit rays through every pixel centre of the TOF image (step 1).

    Args:
        intrinsics: the TOF camera's intrinsics and distortion.
        width, height: TOF image size in pixels.

    Returns:
        (height, width, 3) float64 unit vectors in the TOF frame (z > 0); ``rays[v, u]`` is
        the ray through pixel (u, v). NaN where the distortion model cannot be inverted
        within its one-to-one zone (see :func:`monotonic_radius`).
    """
    return pixel_rays(intrinsics, _positive_int(width, "width"), _positive_int(height, "height"))


def tof_points(
    distance_m: npt.ArrayLike,
    rays: npt.ArrayLike,
    min_range_m: float = 0.1,
    max_range_m: float = 10.0,
) -> np.ndarray:
    """TOF-frame points ``P = d * r`` from radial distances along unit rays (step 2).

    The TOF measures the distance along the ray (radial), not the z coordinate, so
    ``|P| = d``.

    Args:
        distance_m: (H, W) radial distances in metres (any float dtype).
        rays: (H, W, 3) unit rays in the TOF frame, e.g. from :func:`tof_rays`.
        min_range_m, max_range_m: the valid range, inclusive, in metres.

    Returns:
        (H, W, 3) float64 points in the TOF frame, metres. Distances that are NaN,
        infinite, zero or negative, below ``min_range_m`` or beyond ``max_range_m`` (and
        NaN rays) give NaN points.
    """
    d = np.asarray(distance_m, dtype=np.float64)
    r = np.asarray(rays, dtype=np.float64)
    _check_last_dim(r, 3, "rays")
    if d.shape != r.shape[:-1]:
        raise ValueError(
            f"distance_m: expected shape {r.shape[:-1]} to match rays {r.shape}, got {d.shape}"
        )
    if not (np.isfinite(min_range_m) and np.isfinite(max_range_m)) or not (
        0.0 <= min_range_m < max_range_m
    ):
        raise ValueError(
            "range: expected finite 0 <= min_range_m < max_range_m, "
            f"got min_range_m={min_range_m}, max_range_m={max_range_m}"
        )
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(d) & (d > 0.0) & (d >= min_range_m) & (d <= max_range_m)
    points = d[..., None] * r
    points[~valid] = np.nan
    return points


def tof_sensor_name(rig: Rig, tof: str | None = None) -> str:
    """The name of the TOF sensor: ``tof`` if given (it must be in the rig), else the
    rig's only sensor of modality ``"tof"``.

    Raises:
        KeyError: ``tof`` is not a sensor of the rig.
        ValueError: ``tof`` is None and the rig has no or several TOF sensors.
    """
    if tof is not None:
        rig[tof]  # raises KeyError naming it
        return tof
    names = rig.by_modality("tof")
    if len(names) != 1:
        raise ValueError(
            f"tof: expected exactly one sensor of modality 'tof' in the rig, got {names}; "
            "name the TOF sensor explicitly"
        )
    return names[0]


def project_to_sensor(
    points_tof: npt.ArrayLike, rig: Rig, sensor: str, tof: str | None = None
) -> np.ndarray:
    """Pixel coordinates in ``sensor`` of points in the TOF frame (steps 3 and 4).

    Args:
        points_tof: (..., 3) points in the TOF frame, metres; NaN allowed.
        rig: the calibrated rig.
        sensor: name of the target sensor.
        tof: name of the TOF sensor; default the rig's only sensor of modality "tof".

    Returns:
        (..., 2) float64 pixel coordinates (u, v) in ``sensor``, with its distortion.
        NaN for NaN points, for points on or behind the sensor's image plane (z <= 0, or
        beyond :data:`calib.camera.MAX_RAY_RADIUS`), and for points beyond the fold of the
        sensor's distortion model (where the polynomial would map them back into the image,
        see :func:`monotonic_radius`).
        Points outside the image are *not* NaN: see :func:`in_image`.
    """
    P = np.asarray(points_tof, dtype=np.float64)
    _check_last_dim(P, 3, "points_tof")
    P_sensor = transform_points(rig.T(sensor, tof_sensor_name(rig, tof)), P)
    return rig[sensor].intrinsics.project(P_sensor)


def tof_to_sensor_pixels(
    distance_m: npt.ArrayLike,
    rig: Rig,
    sensor: str,
    tof: str | None = None,
    rays: npt.ArrayLike | None = None,
    *,
    min_range_m: float = 0.1,
    max_range_m: float = 10.0,
) -> np.ndarray:
    """Where every TOF pixel lands in ``sensor``: the whole chain, steps 1-4.

    Args:
        distance_m: (H, W) radial distances in metres from the TOF sensor.
        rig: the calibrated rig.
        sensor: name of the target sensor.
        tof: name of the TOF sensor; default the rig's only sensor of modality "tof".
        rays: (H, W, 3) precomputed :func:`tof_rays`; computed from the TOF sensor's
            intrinsics and image size if None (then (H, W) must be that image size).
        min_range_m, max_range_m: the valid distance range, see :func:`tof_points`.

    Returns:
        (H, W, 2) float64 pixel coordinates in ``sensor``; NaN where the distance is
        invalid or the point does not project (see :func:`project_to_sensor`).
    """
    tof_name = tof_sensor_name(rig, tof)
    if rays is None:
        s = rig[tof_name]
        rays = tof_rays(s.intrinsics, s.width, s.height)
    points = tof_points(distance_m, rays, min_range_m=min_range_m, max_range_m=max_range_m)
    return project_to_sensor(points, rig, sensor, tof_name)


def in_image(pixels: npt.ArrayLike, width: int, height: int) -> np.ndarray:
    """Which pixel coordinates fall inside a ``width`` x ``height`` image.

    Pixel centres are at integers, so inside means ``-0.5 <= u < width - 0.5`` and
    ``-0.5 <= v < height - 0.5``; rounding an inside coordinate gives a valid index.

    Args:
        pixels: (..., 2) pixel coordinates (u, v); NaN is outside.
        width, height: image size in pixels.

    Returns:
        (...) bool array.
    """
    uv = np.asarray(pixels, dtype=np.float64)
    _check_last_dim(uv, 2, "pixels")
    w = _positive_int(width, "width")
    h = _positive_int(height, "height")
    u = uv[..., 0]
    v = uv[..., 1]
    with np.errstate(invalid="ignore"):
        return (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)


class Projector32:
    """Steps 3 and 4 for many points per frame, in float32: points of a source frame into
    a sensor's pixels, as :func:`project_to_sensor` (to float32 precision, a few
    thousandths of a pixel), about three times faster (the thermal map's per-frame work).

    Args:
        intrinsics: the sensor's intrinsics and distortion.
        T_sensor_src: (4, 4) from the points' frame to the sensor's.
    """

    def __init__(self, intrinsics: Intrinsics, T_sensor_src: npt.ArrayLike) -> None:
        self.intrinsics = intrinsics
        self._M = np.asarray(T_sensor_src, dtype=np.float32)[:3, :]  # [R | t]
        # Coefficients as Python floats, so that float32 arrays stay float32 (NEP 50).
        self._k = [float(c) for c in intrinsics._coeffs]
        self._r2_max = float(min(monotonic_radius(intrinsics), MAX_RAY_RADIUS) ** 2)

    def __call__(
        self, points: npt.ArrayLike, min_z: float = 0.05
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The points (N, 3) (source frame, metres) at least ``min_z`` in front of the
        sensor and inside the fold of its distortion: their pixels (M, 2) float32, their
        rows (M,) in ``points`` and their depths (M,) along the sensor's axis, metres.
        Pixels outside the image are kept (see :func:`in_image`)."""
        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 1, 3)
        P = cv2.transform(pts, self._M).reshape(-1, 3)  # numpy's 3-wide matmul is slower
        z = P[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            inv = 1.0 / z
            x, y = P[:, 0] * inv, P[:, 1] * inv
            r2 = x * x + y * y
            rows = np.flatnonzero((z > min_z) & (r2 <= self._r2_max))
        x, y, r2 = x[rows], y[rows], r2[rows]
        # calib.camera.Intrinsics.distort: radial (k1 k2 k3 / k4 k5 k6) and tangential
        k1, k2, p1, p2, k3, k4, k5, k6 = self._k
        rad = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xy2 = 2.0 * x * y
        intr = self.intrinsics
        uv = np.empty((len(rows), 2), np.float32)
        uv[:, 0] = (x * rad + p1 * xy2 + p2 * (r2 + 2.0 * x * x)) * intr.fx + intr.cx
        uv[:, 1] = (y * rad + p1 * (r2 + 2.0 * y * y) + p2 * xy2) * intr.fy + intr.cy
        return uv, rows, z[rows]
