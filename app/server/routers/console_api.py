"""``GET/PUT /api/console/settings``: the 3D console's console-wide bandwidth mode.

``full`` (every cloud point, images at 2 Hz: about 6 Mbit/s per browser on the simulated
head) or ``low`` (a decimated cloud at 2 Hz, small images once a second: about 1 Mbit/s),
for every browser on ``/console/`` (Viser sends the same scene to all). The "3D scene"
folder's Bandwidth dropdown shows the same setting (``ctx.bandwidth``); ``trifuse serve
--console-bandwidth`` sets it at the start. An unknown mode gets a 422 naming the choices.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.runtime.context import BandwidthMode, ConsoleBandwidth


class ConsoleSettingsBody(BaseModel):
    """The 3D console's settings."""

    model_config = ConfigDict(extra="forbid")

    bandwidth: BandwidthMode = Field(
        description="what /console/ sends to each browser: full (every TOF point, 320 px "
        "images at 2 Hz) or low (every 2nd TOF pixel at 2 Hz, 160 px images and feeds at "
        "1 Hz: for a radio link shared with the viewer's video)"
    )


def make_console_settings_router(bandwidth: ConsoleBandwidth) -> APIRouter:
    """The routes over the console's ``bandwidth`` setting (``ctx.bandwidth``)."""
    router = APIRouter(prefix="/api/console", tags=["console"])

    @router.get("/settings")
    def get_settings() -> ConsoleSettingsBody:
        """The 3D console's bandwidth mode."""
        return ConsoleSettingsBody(bandwidth=bandwidth.mode)

    @router.put("/settings", dependencies=[Depends(require_json)])
    def put_settings(body: ConsoleSettingsBody) -> ConsoleSettingsBody:
        """Set the 3D console's bandwidth mode (422 for an unknown one); the scene and the
        feeds take it at their next update, for every browser."""
        bandwidth.mode = body.bandwidth
        return ConsoleSettingsBody(bandwidth=bandwidth.mode)

    return router
