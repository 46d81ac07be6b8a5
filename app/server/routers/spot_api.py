"""The spot meter over REST: ``GET /api/spot`` and ``GET /api/area`` (OpenAPI at /docs).

Both read the last fused picture (:attr:`FusionPipeline.spots
<app.server.runtime.pipeline.FusionPipeline.spots>`, :mod:`fusion.spot`): the temperature
the picture shows at a colour pixel of one eye and the distance to the point from the TOF
depth mapped there. Coordinates are that eye's colour-camera pixels (``x`` 0..W-1, ``y``
0..H-1: 0..1279 and 0..959 on the default head; in the side-by-side picture the right eye's
pixel x is at column W + x). An unknown eye or a pixel outside the picture gets a 422 that
says what was expected; before the first fused picture (or while the console rests with
nobody watching) a 503 says so, and the request itself makes the console fuse again for
the next few seconds (as any REST client of the status does).
"""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, Field

from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.fusion.spot import SpotError, SpotFrame, SpotReading


class Spot(BaseModel):
    """The spot meter's reading at one colour pixel of one eye."""

    eye: str = Field(description="the eye: left or right")
    x: int = Field(description="colour-camera pixel column of that eye")
    y: int = Field(description="colour-camera pixel row of that eye")
    temperature_k: float | None = Field(
        description="the fused temperature there, kelvin (null: the thermal imager does not "
        "see the point)"
    )
    temperature_c: float | None = Field(description="the same in degrees Celsius")
    distance_m: float | None = Field(
        description="distance from the eye's colour camera to the point along the pixel's "
        "ray, metres, from the TOF (null: no TOF depth there)"
    )
    depth: Literal["measured", "fallback"] | None = Field(
        description="measured: TOF depth; fallback: none there, the mapping used its "
        "fallback depth (distance null); null: no TOF frame yet"
    )
    eyes_px: dict[str, tuple[float, float] | None] = Field(
        description="eye -> [x, y]: where the same 3D point lies in each eye's colour "
        "picture (null: outside it, or no depth)"
    )
    stamp_ns: int = Field(description="time stamp of the fused picture read")


class Area(BaseModel):
    """A box of one eye's picture: its hottest and coldest pixels and its mean."""

    eye: str
    x0: int = Field(description="left column of the box (corners included)")
    y0: int = Field(description="top row")
    x1: int = Field(description="right column")
    y1: int = Field(description="bottom row")
    pixels: int = Field(description="pixels in the box")
    thermal_pixels: int = Field(description="of these, pixels with a temperature")
    max: Spot | None = Field(description="the reading at the hottest pixel (null: none)")
    min: Spot | None = Field(description="the reading at the coldest pixel (null: none)")
    mean_k: float | None = Field(description="mean temperature of the box, kelvin")
    mean_c: float | None = Field(description="the same in degrees Celsius")
    stamp_ns: int = Field(description="time stamp of the fused picture read")


def _spot(r: SpotReading, stamp_ns: int) -> Spot:
    return Spot(**r.as_dict(), stamp_ns=stamp_ns)


def make_spot_router(pipeline: FusionPipeline) -> APIRouter:
    """``/api/spot`` and ``/api/area`` over ``pipeline``'s last fused picture."""
    router = APIRouter(prefix="/api", tags=["spot meter"])

    def frame() -> SpotFrame:
        pipeline.touch_demand()  # someone is reading: keep fusing
        spots = pipeline.spots
        if spots is None:
            raise HTTPException(
                503,
                "no fused picture yet (the console fuses while someone watches; it has "
                "started now: ask again in a moment)",
            )
        return spots

    @router.get("/spot")
    def get_spot(eye: str = "left", x: int | None = None, y: int | None = None) -> Spot:
        """Temperature and distance at colour pixel (``x``, ``y``) of ``eye`` (left or
        right) in the last fused picture; without ``x`` or ``y``, the picture's middle
        column or row (``(W - 1) // 2``, ``(H - 1) // 2``: where a head-mounted display's
        gaze points)."""
        spots = frame()
        w, h = spots.size
        x = (w - 1) // 2 if x is None else x
        y = (h - 1) // 2 if y is None else y
        try:
            return _spot(spots.spot(eye, x, y), spots.stamp_ns)
        except SpotError as exc:
            raise HTTPException(422, str(exc)) from None

    @router.get("/area")
    def get_area(
        eye: str = "left",
        x0: int = 0,
        y0: int = 0,
        x1: int | None = None,
        y1: int | None = None,
    ) -> Area:
        """The hottest and coldest pixel (with their distances) and the mean temperature
        of the box with corners (``x0``, ``y0``) and (``x1``, ``y1``) (colour pixels of
        ``eye``, in any order, both included) in the last fused picture; by default the
        whole picture of the eye (``x1``, ``y1``: its last column and row)."""
        spots = frame()
        w, h = spots.size
        try:
            a = spots.area(eye, x0, y0, w - 1 if x1 is None else x1, h - 1 if y1 is None else y1)
        except SpotError as exc:
            raise HTTPException(422, str(exc)) from None
        d = a.as_dict()
        d["max"] = None if a.max is None else _spot(a.max, spots.stamp_ns)
        d["min"] = None if a.min is None else _spot(a.min, spots.stamp_ns)
        return Area(**d, stamp_ns=spots.stamp_ns)

    return router
