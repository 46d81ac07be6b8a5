"""The console's FastAPI application (:func:`create_app`): its middleware (authentication,
body limit) and its routers (viewer pages, streams, 3D console, status and controls)."""

from __future__ import annotations

import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from trifuse.app.server.middleware.auth import AuthConfig, AuthMiddleware
from trifuse.app.server.middleware.limits import add_body_limit
from trifuse.app.server.routers.api import make_api_router
from trifuse.app.server.routers.docs_pages import add_docs_pages
from trifuse.app.server.routers.measure_api import make_measure_router
from trifuse.app.server.routers.pages import STATIC, make_pages_router
from trifuse.app.server.routers.source_api import make_source_router
from trifuse.app.server.routers.spot_api import make_spot_router
from trifuse.app.server.routers.stream_api import make_stream_settings_router
from trifuse.app.server.routers.stream_routes import (
    make_kept_frames_router,
    make_stream_router,
    make_video_router,
)
from trifuse.app.server.routers.threads_api import make_threads_router
from trifuse.app.server.routers.viser_bridge import make_viser_router
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.registration_watch import RegistrationWatch
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.runtime.thermal_balance import ThermalBalancer


def _json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as strings (``"nan"``): JSON has no NaN."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


async def _invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 naming what was wrong, also when the body held NaN or Infinity (FastAPI's own
    handler echoes the input and fails to encode those: a 500)."""
    errors = jsonable_encoder(  # undecodable bytes echoed from the body must not fail here
        exc.errors(), custom_encoder={bytes: lambda b: b.decode("utf-8", "replace")}
    )
    return JSONResponse({"detail": _json_safe(errors)}, status_code=422)


def create_app(
    hub: FrameHub,
    viser_port: int | None = None,
    pipeline: FusionPipeline | None = None,
    source_control: SourceControl | None = None,
    balancer: ThermalBalancer | None = None,
    auth: AuthConfig | None = None,
    viser_secret: str | None = None,
    registration: RegistrationWatch | None = None,
    drift: DriftWatch | None = None,
) -> FastAPI:
    """The app: ``/`` viewer, ``/stream`` + ``/stream.mjpg``, ``/console/`` (Viser),
    ``/api/status`` and the source and recording controls (``source_control``; default:
    one over ``pipeline`` without recording), ``/docs`` (OpenAPI). With ``auth`` every
    request and WebSocket, also of routers added later, is authenticated (middleware/auth.py);
    ``trifuse serve`` always passes one, and ``viser_secret`` (viser_bridge.start_guarded_viser)
    and ``registration`` (the status's registration sigma, registration_watch.py); with
    ``drift`` the status's calibration health (drift_watch.py)."""
    app = FastAPI(
        title="trifuse",
        summary="Calibration and fused stereo telepresence",
        docs_url=None,  # docs_pages.py: the same pages without a CDN
        redoc_url=None,
    )
    add_docs_pages(app)
    add_body_limit(app)  # 413 over 1 MiB (middleware/limits.py)
    if auth is not None:  # added last: the outermost, nothing is read before it passes
        app.add_middleware(AuthMiddleware, config=auth)
    app.add_exception_handler(RequestValidationError, _invalid_request)
    app.include_router(make_stream_router(hub))  # /stream, /stream.mjpg (stream_routes.py)
    app.include_router(make_kept_frames_router(hub.kept))  # benchmarks only
    app.include_router(make_video_router(hub))  # /stream.video
    app.include_router(make_stream_settings_router(hub))  # /api/stream/settings
    if viser_port is not None:
        app.include_router(make_viser_router(viser_port, viser_secret))
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    if pipeline is not None:
        app.include_router(make_api_router(pipeline, balancer))
        app.include_router(make_spot_router(pipeline))  # /api/spot, /api/area (spot_api.py)
        app.include_router(make_measure_router(pipeline))  # /api/regions, ... (measure_api.py)
    # /api/status, /api/source/*, /api/recording/* (source_api.py)
    app.include_router(make_source_router(hub, pipeline, source_control, registration, drift))
    app.include_router(make_threads_router())  # /api/threads (threads_api.py)
    app.include_router(make_pages_router())  # / (the viewer), /favicon.ico (pages.py)
    return app
