"""The console's pages: ``/`` (the viewer) and ``/favicon.ico``, from the static files
(:data:`STATIC`, mounted at ``/static`` by :func:`~trifuse.app.server.app_factory.create_app`)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

STATIC = Path(__file__).resolve().parents[3] / "static"
"""The console's static files (installed as ``trifuse/static``)."""
FAVICON = "favicon.svg"


def make_pages_router() -> APIRouter:
    """``/``: the viewer (a Content-Security-Policy lets only this server's scripts run in
    it); ``/favicon.ico``: the console's icon (SVG). Neither is in the OpenAPI schema."""
    router = APIRouter()

    @router.get("/", include_in_schema=False)
    async def _viewer() -> FileResponse:
        # the viewer has no inline script: nothing but this server's scripts may run in it
        csp = "script-src 'self'; object-src 'none'; base-uri 'self'; frame-ancestors 'none'"
        return FileResponse(STATIC / "viewer.html", headers={"Content-Security-Policy": csp})

    @router.get("/favicon.ico", include_in_schema=False)
    async def _favicon() -> FileResponse:
        """Browsers ask for it whatever the page links: the console's icon (SVG)."""
        return FileResponse(STATIC / FAVICON, media_type="image/svg+xml")

    return router
