"""The API documentation pages, ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc), served with
their scripts from the package (fastapi-offline ships them): no CDN, so they work on a robot
without internet, and nothing from another site runs in the signed-in page. The pages have
no inline script (Swagger UI starts from ``static/docs.js``), so they carry a
Content-Security-Policy of ``script-src 'self'``.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import APIRouter, FastAPI
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

ASSETS = Path(fastapi_offline.__file__).parent / "static"
ASSETS_URL = "/docs-assets"
PAGE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; worker-src 'self' blob:; frame-ancestors 'none'"
)
"""The pages' policy: scripts from this server only (ReDoc's search runs in a blob worker)."""

_SWAGGER = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>trifuse API</title>
<link rel="icon" href="/favicon.ico">
<link rel="stylesheet" href="{ASSETS_URL}/swagger-ui.css"></head>
<body><div id="swagger-ui"></div>
<script src="{ASSETS_URL}/swagger-ui-bundle.js"></script>
<script src="/static/docs.js"></script></body></html>"""

_REDOC = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>trifuse API</title>
<link rel="icon" href="/favicon.ico"></head>
<body><redoc spec-url="/openapi.json"></redoc>
<script src="{ASSETS_URL}/redoc.standalone.js"></script></body></html>"""


def add_docs_pages(app: FastAPI) -> None:
    """``/docs``, ``/redoc`` and their assets under :data:`ASSETS_URL` (the app must be
    made with ``docs_url=None, redoc_url=None``)."""
    router = APIRouter()
    headers = {"Content-Security-Policy": PAGE_CSP, "Cache-Control": "no-cache"}

    @router.get("/docs", include_in_schema=False)
    async def _swagger() -> HTMLResponse:
        return HTMLResponse(_SWAGGER, headers=headers)

    @router.get("/redoc", include_in_schema=False)
    async def _redoc() -> HTMLResponse:
        return HTMLResponse(_REDOC, headers=headers)

    app.include_router(router)
    app.mount(ASSETS_URL, StaticFiles(directory=ASSETS), name="docs-assets")
