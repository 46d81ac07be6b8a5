"""Object temperatures in the measurement regions of a fused picture (issue 35): each
region's pixels through the measurement equation (:mod:`fusion.thermography`) with the
distance the TOF measured at each of them.

A region reads the apparent temperatures of its eye's picture (:class:`fusion.spot.
SpotFrame`, the imager's readings on the colour pixels) and corrects them with the object
parameters in force: its own emissivity and reflected temperature where it has them
(:class:`fusion.regions.Region`), the global ones otherwise; the air's transmission over
each pixel's own distance (along its ray from the eye's colour camera; the thermal imager
sits a few centimetres beside it, which changes the transmission by far less than the
model's own uncertainty). Pixels whose depth is the mapping's fallback or none take
``ObjectParameters.default_distance_m`` and are counted (``default_distance_px``).

Pure: a frame, regions and parameters in, readings out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from trifuse.fusion.regions import Region, RegionReading, reading_of
from trifuse.fusion.spot import SpotFrame
from trifuse.fusion.thermography import BandRadiance, ObjectParameters, object_temperature

__all__ = ["Measurement", "measure_regions", "region_parameters"]


@dataclass(frozen=True)
class Measurement:
    """One region on one picture.

    Attributes:
        apparent: the imager's readings (no correction).
        object: the surfaces' temperatures by the measurement equation.
        default_distance_px: pixels with a reading that took the default distance.
    """

    apparent: RegionReading
    object: RegionReading
    default_distance_px: int

    def as_dict(self) -> dict[str, object]:
        return {
            "apparent": self.apparent.as_dict(),
            "object": self.object.as_dict(),
            "default_distance_px": self.default_distance_px,
        }


@lru_cache(maxsize=64)
def _pixels(region: Region, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(xs, ys) of the pixels ``region`` covers (ValueError outside the picture)."""
    ys, xs = np.nonzero(region.mask(width, height))
    xs.flags.writeable = ys.flags.writeable = False
    return xs, ys


def region_parameters(region: Region, params: ObjectParameters) -> ObjectParameters:
    """The object parameters ``region`` is read with: its own surface where it has one."""
    own = {
        k: v
        for k, v in (("emissivity", region.emissivity), ("reflected_k", region.reflected_k))
        if v is not None
    }
    return replace(params, **own) if own else params


def measure_regions(
    frame: SpotFrame,
    regions: Sequence[Region],
    params: ObjectParameters,
    band: BandRadiance | None = None,
) -> dict[str, Measurement]:
    """Each region's apparent and object readings on ``frame`` (name -> :class:`Measurement`).

    ValueError for a region outside its eye's picture (its message names it);
    :class:`fusion.spot.SpotError` for an eye the frame lacks.
    """
    w, h = frame.size
    out: dict[str, Measurement] = {}
    for region in regions:
        xs, ys = _pixels(region, w, h)
        apparent, distance = frame.samples(region.eye, xs, ys)
        corrected = object_temperature(
            apparent, distance, region_parameters(region, params), band=band
        )
        defaulted = int((np.isfinite(apparent) & ~np.isfinite(distance)).sum())
        out[region.name] = Measurement(
            reading_of(region.name, xs, ys, apparent),
            reading_of(region.name, xs, ys, corrected),
            defaulted,
        )
    return out
