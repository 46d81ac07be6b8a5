"""The console's FastAPI application: viewer, stream, 3D console, status."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from app.server.api import make_api_router
from app.server.pipeline import FusionPipeline
from app.server.stream import FrameHub, make_stream_router
from app.server.viser_bridge import make_viser_router

STATIC = Path(__file__).resolve().parents[2] / "static"


def create_app(
    hub: FrameHub, viser_port: int | None = None, pipeline: FusionPipeline | None = None
) -> FastAPI:
    """The app: ``/`` viewer, ``/stream`` + ``/stream.mjpg``, ``/console/`` (Viser),
    ``/api/status``, ``/docs`` (OpenAPI)."""
    app = FastAPI(title="trifuse", summary="Calibration and fused stereo telepresence")
    app.include_router(make_stream_router(hub))
    if viser_port is not None:
        app.include_router(make_viser_router(viser_port))
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    if pipeline is not None:
        app.include_router(make_api_router(pipeline))

    @app.get("/", include_in_schema=False)
    async def _viewer() -> FileResponse:
        return FileResponse(STATIC / "viewer.html")

    @app.get("/api/status")
    async def _status() -> dict:
        s = pipeline.status if pipeline is not None else None
        return {
            "viewers": hub.viewers,
            "frames_out": s.frames_out if s else 0,
            "fps": s.fps if s else 0.0,
            "missing": s.missing if s else {},
            "error": s.error if s else None,
        }

    return app
