"""``/api/map``: the console's thermal 3D map (issue 20; map_worker.py).

``GET /api/map`` gives its figures (voxels, frames, cost per frame, pose source);
``PUT /api/map`` turns building on or off and pauses it; ``POST /api/map/reset`` empties
it; ``POST /api/map/save`` writes the map file and PLY into the work directory's ``maps/``
(never over an existing one). The "Thermal map" folder of ``/console/`` does the same.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.errors import describe_error
from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.runtime.map_worker import MapWorker


class MapStatus(BaseModel):
    """The map's figures."""

    enabled: bool = Field(description="the map is being built from the live frames")
    paused: bool = Field(description="building is paused (the map is kept)")
    frames: int = Field(description="TOF frames mapped")
    skipped: int = Field(description="TOF frames skipped for a newer one (a busy machine)")
    failed: int = Field(description="TOF frames that failed (last_error says why)")
    voxels: int = Field(description="voxels held (occupied or free)")
    occupied: int = Field(description="voxels whose evidence says occupied")
    voxel_m: float = Field(description="voxel edge, metres")
    memory_mb: float = Field(description="memory of the map's arrays, MB")
    ms_per_frame: float | None = Field(description="median cost of the last 30 frames, ms")
    pose_source: str | None = Field(description="given (by the source) or estimated")
    path_points: int = Field(description="poses on the head's path")
    last_error: str | None = None


class MapControl(BaseModel):
    """What to change (fields left out stay)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool | None = None
    paused: bool | None = None


class MapSave(BaseModel):
    """The saved map's name (default: map-<UTC time>)."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(default=None, max_length=100, pattern=r"^[A-Za-z0-9][\w.-]*$")


class MapSaved(BaseModel):
    map_file: str
    ply: str


def make_map_router(worker: MapWorker) -> APIRouter:
    """The routes over the console's map ``worker``."""
    router = APIRouter(prefix="/api/map", tags=["map"])

    @router.get("")
    def get_map() -> MapStatus:
        """The map's figures."""
        return MapStatus(**worker.status())

    @router.put("", dependencies=[Depends(require_json)])
    def put_map(body: MapControl) -> MapStatus:
        """Turn building on or off, pause or resume."""
        if body.enabled is not None:
            worker.set_enabled(body.enabled)
        if body.paused is not None:
            worker.set_paused(body.paused)
        return MapStatus(**worker.status())

    @router.post("/reset")
    def reset_map() -> MapStatus:
        """Empty the map."""
        worker.reset()
        return MapStatus(**worker.status())

    @router.post("/save", dependencies=[Depends(require_json)])
    def save_map(body: MapSave) -> MapSaved:
        """Save the map (map file and PLY) in the work directory's maps/."""
        try:
            path, ply = worker.save(body.name)
        except (OSError, ValueError) as exc:
            raise HTTPException(status_code=409, detail=describe_error(exc)) from None
        return MapSaved(map_file=str(path), ply=str(ply))

    return router
