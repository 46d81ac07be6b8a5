"""Measurement regions on an eye's picture (issue 35, items 1 and 3): spots, boxes and
polygons, each optionally a surface of its own (emissivity, reflected temperature), and what
a thermographer reads in them: maximum, minimum, mean and where the extremes are.

Coordinates are the eye's colour-camera pixels (``x`` column, ``y`` row, pixel centres at
integers, as :mod:`fusion.spot`). A box covers the pixels whose centres lie within it
(both ends included); a polygon the pixels ``cv2.fillPoly`` fills (its outline included).

Pure: regions and arrays in, numbers out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from trifuse.fusion.thermography import EMISSIVITY_RANGE, REFLECTED_RANGE_K

__all__ = [
    "Region",
    "RegionReading",
    "line_profile",
    "read_region",
    "reading_of",
    "surface_maps",
]

Shape = Literal["spot", "box", "polygon"]


@dataclass(frozen=True)
class Region:
    """One measurement region.

    Attributes:
        name: how it is called (unique among the regions of a session).
        eye: ``left`` or ``right``: whose colour pixels ``points`` are.
        shape: ``spot`` (one point), ``box`` (two corners) or ``polygon`` (3 or more).
        points: (x, y) pixels, as ``shape`` says.
        emissivity, reflected_k: the region's surface, if not the global one's
            (:class:`fusion.thermography.ObjectParameters` ranges).
    """

    name: str
    eye: Literal["left", "right"]
    shape: Shape
    points: tuple[tuple[float, float], ...]
    emissivity: float | None = None
    reflected_k: float | None = None

    def __post_init__(self) -> None:
        if not self.name or not isinstance(self.name, str):
            raise ValueError("name: expected a non-empty text")
        if self.eye not in ("left", "right"):
            raise ValueError(f"eye: expected left or right, got {self.eye!r}")
        need = {"spot": (1, 1), "box": (2, 2), "polygon": (3, 1000)}.get(self.shape)
        if need is None:
            raise ValueError(f"shape: expected spot, box or polygon, got {self.shape!r}")
        if not need[0] <= len(self.points) <= need[1]:
            count = "1 point" if self.shape == "spot" else f"{need[0]} points"
            raise ValueError(f"{self.name}: a {self.shape} takes {count}, got {len(self.points)}")
        for p in self.points:
            if len(p) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in p):
                raise ValueError(
                    f"{self.name}: expected points (x, y) of finite numbers, got {p!r}"
                )
        for name, (low, high) in (
            ("emissivity", EMISSIVITY_RANGE),
            ("reflected_k", REFLECTED_RANGE_K),
        ):
            value = getattr(self, name)
            if value is not None and not low <= value <= high:
                expected = f"expected {low:g} to {high:g}, got {value:g}"
                raise ValueError(f"{self.name}: {name}: {expected}")

    def mask(self, width: int, height: int) -> np.ndarray:
        """(height, width) bool: the pixels the region covers. ValueError when it covers
        none of the image (outside it)."""
        m = np.zeros((height, width), np.uint8)
        pts = np.asarray(self.points, dtype=np.float64)
        if self.shape == "spot":
            x, y = np.round(pts[0]).astype(int)
            if 0 <= x < width and 0 <= y < height:
                m[y, x] = 1
        elif self.shape == "box":
            (x0, x1), (y0, y1) = np.sort(pts[:, 0]), np.sort(pts[:, 1])
            c0, c1 = max(0, math.ceil(x0)), min(width - 1, math.floor(x1))
            r0, r1 = max(0, math.ceil(y0)), min(height - 1, math.floor(y1))
            if c0 <= c1 and r0 <= r1:
                m[r0 : r1 + 1, c0 : c1 + 1] = 1
        else:
            cv2.fillPoly(m, [np.round(pts).astype(np.int32)], 1)
        if not m.any():
            raise ValueError(f"{self.name}: outside the {width}x{height} image")
        return m.astype(bool)


@dataclass(frozen=True)
class RegionReading:
    """What a region reads on one picture (kelvin; positions as (x, y) pixels).

    ``None`` values when the region has no pixel with a temperature (``pixels`` 0).
    """

    name: str
    pixels: int
    max_k: float | None
    min_k: float | None
    mean_k: float | None
    max_at: tuple[int, int] | None
    min_at: tuple[int, int] | None

    def as_dict(self) -> dict[str, object]:
        return {
            "name": self.name,
            "pixels": self.pixels,
            "max_k": self.max_k,
            "min_k": self.min_k,
            "mean_k": self.mean_k,
            "max_at": self.max_at,
            "min_at": self.min_at,
        }


def reading_of(name: str, xs: np.ndarray, ys: np.ndarray, values: np.ndarray) -> RegionReading:
    """The reading of pixels (``xs``, ``ys``) (N,) with temperatures ``values`` (N,) kelvin,
    over those that have one (finite)."""
    ok = np.isfinite(values)
    if not ok.any():
        return RegionReading(name, 0, None, None, None, None, None)
    xs, ys, values = xs[ok], ys[ok], np.asarray(values[ok], np.float64)
    i_max, i_min = int(np.argmax(values)), int(np.argmin(values))
    return RegionReading(
        name,
        len(values),
        float(values[i_max]),
        float(values[i_min]),
        float(values.mean()),
        (int(xs[i_max]), int(ys[i_max])),
        (int(xs[i_min]), int(ys[i_min])),
    )


def read_region(region: Region, temperature_k: np.ndarray) -> RegionReading:
    """The region's maximum, minimum, mean and where the extremes are, over its pixels that
    have a temperature (finite) in ``temperature_k`` (H, W) kelvin, the eye's picture."""
    h, w = temperature_k.shape
    ys, xs = np.nonzero(region.mask(w, h))
    return reading_of(region.name, xs, ys, temperature_k[ys, xs])


def surface_maps(
    regions: Sequence[Region],
    eye: str,
    width: int,
    height: int,
    emissivity: float,
    reflected_k: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``eye``'s (height, width) picture: the emissivity and reflected
    temperature (float64) of the surface there: the global values, and each of ``eye``'s
    regions that has its own in the pixels it covers (a later region over an earlier one)."""
    eps = np.full((height, width), emissivity, np.float64)
    refl = np.full((height, width), reflected_k, np.float64)
    for r in regions:
        if r.eye != eye or (r.emissivity is None and r.reflected_k is None):
            continue
        m = r.mask(width, height)
        if r.emissivity is not None:
            eps[m] = r.emissivity
        if r.reflected_k is not None:
            refl[m] = r.reflected_k
    return eps, refl


def line_profile(
    temperature_k: np.ndarray, start: tuple[float, float], end: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Temperatures along the segment ``start``-``end`` ((x, y) pixels) of an eye's (H, W)
    picture, one sample a pixel (both ends included, bilinear between pixels; NaN where a
    pixel around has none or outside the picture). Returns (distance along the segment,
    pixels; temperature, kelvin), each (n,)."""
    (x0, y0), (x1, y1) = start, end
    length = math.hypot(x1 - x0, y1 - y0)
    n = max(2, math.ceil(length) + 1)
    s = np.linspace(0.0, 1.0, n)
    xs, ys = x0 + (x1 - x0) * s, y0 + (y1 - y0) * s
    h, w = temperature_k.shape
    values = cv2.remap(
        np.asarray(temperature_k, np.float32),
        xs.astype(np.float32)[None, :],
        ys.astype(np.float32)[None, :],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )[0].astype(np.float64)
    outside = (xs < 0) | (xs > w - 1) | (ys < 0) | (ys > h - 1)
    values[outside] = np.nan
    return s * length, values
