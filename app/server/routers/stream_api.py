"""``GET/PUT /api/stream/settings``: the video stream's console-wide default preset.

The preset (``auto``, ``8``, ``4``, ``2``, ``1``: app/server/runtime/video_presets.py) of
``/stream.video`` viewers that ask for none; the Fusion panel's dropdown shows the same
setting (``ctx.stream_settings``). An unknown preset gets a 422 naming the choices.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.runtime.video_presets import VideoPreset


class StreamSettingsBody(BaseModel):
    """The video stream's settings."""

    model_config = ConfigDict(extra="forbid")

    preset: VideoPreset = Field(
        description="the preset of viewers that ask for none: auto (the ladder follows "
        "the link) or a cap in Mbit/s (8: 2560x960 30 fps, 4: 1920x720 30, 2: 1280x480 "
        "25, 1: 1280x480 15)"
    )


def make_stream_settings_router(hub: FrameHub) -> APIRouter:
    """The routes over ``hub.stream_settings``."""
    router = APIRouter(prefix="/api/stream", tags=["stream"])

    @router.get("/settings")
    def get_settings() -> StreamSettingsBody:
        """The default video preset of new viewers."""
        return StreamSettingsBody(preset=hub.stream_settings.preset)

    @router.put("/settings", dependencies=[Depends(require_json)])
    def put_settings(body: StreamSettingsBody) -> StreamSettingsBody:
        """Set the default video preset of viewers connecting from now on (422 for an
        unknown preset); viewers already connected keep theirs."""
        hub.stream_settings.preset = body.preset
        return StreamSettingsBody(preset=hub.stream_settings.preset)

    return router
