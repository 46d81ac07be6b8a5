"""Measurements over REST (issue 35; OpenAPI at /docs): object parameters, measurement regions,
their readings, the difference between two, and alarms.

- ``GET``/``PUT /api/object-parameters``: emissivity (or a ``material`` of
  :data:`fusion.thermography.MATERIALS`), reflected apparent temperature, the air's
  temperature and humidity, the distance used where the TOF has none.
- ``GET``/``PUT /api/regions``: the regions (spot, box, polygon on either eye, each with its
  own emissivity and reflected temperature if given); ``PATCH /api/regions/{name}``
  (rename, move, another surface; the alarms follow a new name); ``DELETE
  /api/regions/{name}``. ``GET /api/materials``: the short table of emissivities.
- ``GET /api/measurements``: what each region reads on the newest picture read (max, min,
  mean and where the extremes are; apparent and corrected), ``GET /api/measurements/delta``:
  one region's value minus another's.
- ``GET``/``PUT /api/alarms``: rules above, below or on a rate of rise, the active ones and
  the events (``after``: only the newer).
- ``GET /api/profile``: temperatures along a line (a profile plot's data).
- ``GET /api/snapshot``: the last picture's files in a ZIP (app/server/runtime/snapshot.py).

Bad input (emissivity outside 0.01-1, humidity outside 0-100 %, a region outside the
picture, a name given twice, an alarm on no region) gets a 422 with one line saying what
was expected, and changes nothing. A region with no pixel with a temperature reads null
values (``pixels`` 0); the delta of one is a 422.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Response
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.runtime.measurements import Readings
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.snapshot import snapshot_zip
from trifuse.fusion.alarms import AlarmRule
from trifuse.fusion.regions import Region, line_profile
from trifuse.fusion.thermography import (
    EMISSIVITY_RANGE,
    MATERIALS,
    ObjectParameters,
    object_temperature,
)

_Point = tuple[float, float]


class ObjectParametersModel(BaseModel):
    """The surfaces' and the air's parameters the readings are corrected with."""

    model_config = ConfigDict(extra="forbid")

    emissivity: float = Field(1.0, ge=EMISSIVITY_RANGE[0], le=EMISSIVITY_RANGE[1])
    material: str | None = Field(
        None,
        description="a material of the short table (its emissivity replaces `emissivity`): "
        + ", ".join(MATERIALS),
    )
    reflected_k: float = Field(293.15, ge=150.0, le=1200.0, description="kelvin")
    air_k: float = Field(293.15, ge=200.0, le=350.0, description="kelvin")
    humidity_pct: float = Field(50.0, ge=0.0, le=100.0, description="relative, percent")
    default_distance_m: float = Field(
        3.0, ge=0.0, le=10_000.0, description="metres, where the TOF has no distance"
    )


class RegionModel(BaseModel):
    """A measurement region: points are colour pixels (x, y) of its eye."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=64)
    eye: Literal["left", "right"] = "left"
    shape: Literal["spot", "box", "polygon"]
    points: list[_Point] = Field(min_length=1, max_length=1000)
    emissivity: float | None = Field(None, ge=EMISSIVITY_RANGE[0], le=EMISSIVITY_RANGE[1])
    reflected_k: float | None = Field(None, ge=150.0, le=1200.0)


class RegionEdit(BaseModel):
    """What to change of a region: the fields given (``null`` for ``emissivity`` or
    ``reflected_k``: the global parameter's again)."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, min_length=1, max_length=64)
    eye: Literal["left", "right"] | None = None
    points: list[_Point] | None = Field(None, min_length=1, max_length=1000)
    emissivity: float | None = Field(None, ge=EMISSIVITY_RANGE[0], le=EMISSIVITY_RANGE[1])
    material: str | None = Field(
        None, description="a material of the short table: its emissivity for `emissivity`"
    )
    reflected_k: float | None = Field(None, ge=150.0, le=1200.0)


class AlarmModel(BaseModel):
    """An alarm on a region: its maximum above, its minimum below, or the rate of rise of
    its maximum (kelvin a second over ``window_s``) above ``threshold``."""

    model_config = ConfigDict(extra="forbid")

    region: str
    kind: Literal["above", "below", "rise"]
    threshold: float = Field(description="kelvin (rise: kelvin a second)")
    hysteresis: float = Field(0.5, ge=0.0, description="cleared this far back")
    window_s: float = Field(10.0, gt=0.0, le=3600.0)


def _params_model(p: ObjectParameters) -> ObjectParametersModel:
    return ObjectParametersModel(
        emissivity=p.emissivity,
        reflected_k=p.reflected_k,
        air_k=p.air_k,
        humidity_pct=p.humidity_pct,
        default_distance_m=p.default_distance_m,
    )


def _region_model(r: Region) -> RegionModel:
    return RegionModel(
        name=r.name,
        eye=r.eye,
        shape=r.shape,
        points=[tuple(p) for p in r.points],
        emissivity=r.emissivity,
        reflected_k=r.reflected_k,
    )


def _unprocessable(exc: Exception) -> HTTPException:
    return HTTPException(422, str(exc))


def _material(name: str) -> float:
    """The emissivity of material ``name`` of the short table; 422 if there is none."""
    if name not in MATERIALS:
        raise HTTPException(422, f"material: expected one of {', '.join(MATERIALS)}, got {name!r}")
    return MATERIALS[name]


def make_measure_router(pipeline: FusionPipeline) -> APIRouter:
    """The routes of the module's docstring over ``pipeline.measurements``."""
    router = APIRouter(prefix="/api", tags=["measurements"])
    m = pipeline.measurements

    @router.get("/object-parameters")
    def get_params() -> ObjectParametersModel:
        """The object parameters in force."""
        return _params_model(m.params)

    @router.put("/object-parameters", dependencies=[Depends(require_json)])
    def put_params(body: ObjectParametersModel) -> ObjectParametersModel:
        """Set the object parameters (every field; a ``material`` sets the emissivity)."""
        emissivity = body.emissivity if body.material is None else _material(body.material)
        values = body.model_dump(exclude={"material"}) | {"emissivity": emissivity}
        try:
            m.set_params(ObjectParameters(**values))
        except ValueError as exc:
            raise _unprocessable(exc) from None
        return _params_model(m.params)

    @router.get("/materials")
    def get_materials() -> dict[str, float]:
        """The short table of materials: name -> emissivity (long-wave band)."""
        return dict(MATERIALS)

    @router.get("/regions")
    def get_regions() -> list[RegionModel]:
        """The measurement regions."""
        return [_region_model(r) for r in m.regions]

    @router.put("/regions", dependencies=[Depends(require_json)])
    def put_regions(body: list[RegionModel]) -> list[RegionModel]:
        """Replace the measurement regions (all of them; ``[]`` removes every one)."""
        try:
            regions = [
                Region(
                    r.name,
                    r.eye,
                    r.shape,
                    tuple((float(x), float(y)) for x, y in r.points),
                    r.emissivity,
                    r.reflected_k,
                )
                for r in body
            ]
            m.set_regions(regions, pipeline.fusion.size)
        except ValueError as exc:
            raise _unprocessable(exc) from None
        pipeline.touch_demand()  # someone measures: keep fusing
        return [_region_model(r) for r in m.regions]

    @router.patch("/regions/{name}", dependencies=[Depends(require_json)])
    def patch_region(name: str, body: RegionEdit) -> list[RegionModel]:
        """Change one region: its name (the alarms watching it follow), eye, points, or
        surface (``emissivity`` or a ``material``; ``reflected_k``; null: the global one's
        again). 404 if there is no region of that name."""
        old = next((r for r in m.regions if r.name == name), None)
        if old is None:
            raise HTTPException(404, f"no region named {name!r}")
        given = body.model_fields_set
        if "material" in given and "emissivity" in given:
            raise HTTPException(422, "give an emissivity or a material, not both")
        changes = {k: getattr(body, k) for k in given - {"material", "points"}}
        if body.material is not None:
            changes["emissivity"] = _material(body.material)
        if body.points is not None:
            changes["points"] = tuple((float(x), float(y)) for x, y in body.points)
        if changes.get("name", "") is None or changes.get("eye", "") is None:
            raise HTTPException(422, "name and eye: expected a value, got null")
        try:
            m.edit_region(name, dataclasses.replace(old, **changes), pipeline.fusion.size)
        except ValueError as exc:
            raise _unprocessable(exc) from None
        except KeyError:
            raise HTTPException(404, f"no region named {name!r}") from None
        pipeline.touch_demand()
        return [_region_model(r) for r in m.regions]

    @router.delete("/regions/{name}")
    def delete_region(name: str) -> list[RegionModel]:
        """Remove one region (404 if there is none of that name; 422 while an alarm
        watches it)."""
        kept = [r for r in m.regions if r.name != name]
        if len(kept) == len(m.regions):
            raise HTTPException(404, f"no region named {name!r}")
        try:
            m.set_regions(kept, pipeline.fusion.size)
        except ValueError as exc:
            raise _unprocessable(exc) from None
        return [_region_model(r) for r in m.regions]

    def readings() -> Readings | None:
        """The last readings (the last picture read now if the fusion thread has not read
        one with these regions yet); None without a region; 503 before the first picture."""
        pipeline.touch_demand()
        r = m.readings
        if r is None and m.regions and pipeline.spots is not None:
            r = m.read_now(pipeline.spots)
        if r is None and m.regions:
            raise HTTPException(
                503,
                "no reading yet (the console fuses while someone watches; it has started "
                "now: ask again in a moment)",
            )
        return r

    @router.get("/measurements")
    def get_readings() -> dict:
        """Each region's reading on the newest picture read: ``apparent`` (what the imager
        reads) and ``object`` (corrected with the parameters in force, which are given),
        kelvin; ``errors``: regions that could not be read, one line each. Without a
        region: no stamp, no regions."""
        r = readings()
        if r is None:
            params = _params_model(m.params).model_dump(exclude={"material"})
            return {"stamp_ns": None, "params": params, "regions": {}, "errors": {}}
        return {
            "stamp_ns": r.stamp_ns,
            "params": _params_model(r.params).model_dump(exclude={"material"}),
            "regions": {n: v.as_dict() for n, v in r.regions.items()},
            "errors": r.errors,
        }

    @router.get("/measurements/delta")
    def get_delta(
        a: str | None = None,
        b: str | None = None,
        stat: Literal["mean", "max", "min"] = "mean",
        corrected: bool = True,
    ) -> dict:
        """Region ``a``'s ``stat`` minus region ``b``'s (kelvin; by default the first two
        regions) on the newest picture read: object temperatures (``corrected``) or the
        imager's apparent ones. 404 for a region that does not exist, 422 for one that could
        not be read or has no pixel with a temperature."""
        names = [r.name for r in m.regions]
        a = a if a is not None else (names[0] if names else None)
        b = b if b is not None else (names[1] if len(names) > 1 else None)
        if a is None or b is None:
            raise HTTPException(404, "a delta needs two regions (PUT /api/regions)")
        for name in (a, b):
            if name not in names:
                raise HTTPException(404, f"no region named {name!r}")
        r = readings()
        values = []
        for name in (a, b):
            if r is None or name not in r.regions:
                why = (r.errors if r else {}).get(name, "not read yet")
                raise HTTPException(422, f"{name}: {why}")
            reading = r.regions[name].object if corrected else r.regions[name].apparent
            value = getattr(reading, f"{stat}_k")
            if value is None or not math.isfinite(value):
                raise HTTPException(422, f"{name}: no pixel with a temperature")
            values.append(value)
        return {"a": a, "b": b, "stat": stat, "delta_k": values[0] - values[1],
                "stamp_ns": r.stamp_ns}  # fmt: skip

    @router.get("/profile")
    def get_profile(
        x0: float | None = None,
        y0: float | None = None,
        x1: float | None = None,
        y1: float | None = None,
        eye: Literal["left", "right"] = "left",
    ) -> dict:
        """The temperatures along the segment (``x0``, ``y0``)-(``x1``, ``y1``) (colour pixels
        of ``eye``; by default the picture's middle row) of the last picture, one sample a
        pixel: ``distance_px`` along it, ``apparent_k`` (bilinear) and ``object_k``
        (corrected with the global parameters and the TOF's distance at the nearest pixel;
        null where there is none)."""
        pipeline.touch_demand()
        frame = pipeline.spots
        if frame is None:
            raise HTTPException(503, "no fused picture yet (ask again in a moment)")
        w, h = frame.size
        x0 = 0.0 if x0 is None else x0
        x1 = float(w - 1) if x1 is None else x1
        y0 = float((h - 1) // 2) if y0 is None else y0
        y1 = y0 if y1 is None else y1
        for name, v, n in (("x0", x0, w), ("x1", x1, w), ("y0", y0, h), ("y1", y1, h)):
            if not (math.isfinite(v) and 0 <= v <= n - 1):
                raise HTTPException(422, f"{name}: expected a pixel 0..{n - 1}, got {v:g}")
        along, apparent = line_profile(frame.kelvin(eye), (x0, y0), (x1, y1))
        t = np.linspace(0.0, 1.0, len(along))
        xs = np.rint(x0 + (x1 - x0) * t).astype(np.int64)
        ys = np.rint(y0 + (y1 - y0) * t).astype(np.int64)
        _, distance = frame.samples(eye, xs, ys)
        corrected = object_temperature(apparent, distance, m.params)

        def listed(a: np.ndarray) -> list[float | None]:
            return [round(float(v), 3) if np.isfinite(v) else None for v in a]

        return {"eye": eye, "distance_px": listed(along), "apparent_k": listed(apparent),
                "object_k": listed(corrected), "stamp_ns": frame.stamp_ns}  # fmt: skip

    @router.get("/snapshot", response_class=Response)
    def get_snapshot() -> Response:
        """A ZIP of the last picture: the fused pair (PNG), each eye's apparent and object
        temperatures (16-bit PNG, centi-kelvin, 0 = none), the parameters (JSON) and the
        regions' readings (CSV); 503 before the first fused picture."""
        pipeline.touch_demand()
        frame = pipeline.spots
        if frame is None:
            raise HTTPException(
                503, "no fused picture yet (the console fuses while someone watches; ask again)"
            )
        latest = pipeline.hub.latest
        readings = m.read_now(frame)
        data = snapshot_zip(
            frame,
            None if latest is None else latest.bgr,
            None if latest is None else latest.jpeg,
            {} if latest is None else latest.meta,
            m.params,
            m.regions,
            m.settings(),
            {} if readings is None else readings.regions,
        )
        name = f"trifuse-snapshot-{frame.stamp_ns}.zip"
        return Response(
            data,
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{name}"'},
        )

    @router.get("/alarms")
    def get_alarms(after: int = 0) -> dict:
        """The alarm rules, the active ones and the events numbered above ``after``."""
        return {
            "rules": [AlarmModel(**dataclasses.asdict(a)) for a in m.rules],
            "active": m.status()["active_alarms"],
            "events": m.events(after),
        }

    @router.put("/alarms", dependencies=[Depends(require_json)])
    def put_alarms(body: list[AlarmModel]) -> dict:
        """Replace the alarm rules (a raised alarm still among them stays raised)."""
        try:
            m.set_rules([AlarmRule(**a.model_dump()) for a in body])
        except ValueError as exc:
            raise _unprocessable(exc) from None
        pipeline.touch_demand()
        return get_alarms()

    return router
