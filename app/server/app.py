"""The console's FastAPI application: viewer, stream, 3D console, status."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from app.server.api import make_api_router
from app.server.pipeline import FusionPipeline
from app.server.source_api import make_source_router
from app.server.source_control import SourceControl
from app.server.stream import FrameHub, make_stream_router
from app.server.viser_bridge import make_viser_router

STATIC = Path(__file__).resolve().parents[2] / "static"


def create_app(
    hub: FrameHub,
    viser_port: int | None = None,
    pipeline: FusionPipeline | None = None,
    source_control: SourceControl | None = None,
) -> FastAPI:
    """The app: ``/`` viewer, ``/stream`` + ``/stream.mjpg``, ``/console/`` (Viser),
    ``/api/status`` and the source and recording controls (``source_control``; default:
    one over ``pipeline`` without recording), ``/docs`` (OpenAPI)."""
    app = FastAPI(title="trifuse", summary="Calibration and fused stereo telepresence")
    app.include_router(make_stream_router(hub))
    if viser_port is not None:
        app.include_router(make_viser_router(viser_port))
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    if pipeline is not None:
        app.include_router(make_api_router(pipeline))
    # /api/status, /api/source/*, /api/recording/* (source_api.py)
    app.include_router(make_source_router(hub, pipeline, source_control))

    @app.get("/", include_in_schema=False)
    async def _viewer() -> FileResponse:
        return FileResponse(STATIC / "viewer.html")

    return app
