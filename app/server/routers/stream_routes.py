"""The stream's routes: ``/stream`` and ``/stream.mjpg`` (the fused picture as JPEG,
:class:`~trifuse.app.server.runtime.stream.FrameHub`), ``/stream.video`` (H.264 over a
WebSocket, :mod:`trifuse.app.server.runtime.video_stream`) and, for benchmarks,
``/api/stream/frame/{seq}.png`` (:mod:`trifuse.app.server.runtime.kept_frames`)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import cv2
from fastapi import APIRouter, HTTPException, WebSocket, WebSocketDisconnect
from fastapi.responses import Response, StreamingResponse

from trifuse.app.server.runtime.kept_frames import ENV, KeptFrames
from trifuse.app.server.runtime.stream import (
    POLICY_VIOLATION,
    FrameHub,
    ViewerMessageRefused,
    ViewerMessages,
    close_quietly,
)
from trifuse.app.server.runtime.video_presets import PRESETS
from trifuse.app.server.runtime.video_stream import VideoSession


def make_stream_router(hub: FrameHub) -> APIRouter:
    """``/stream`` (WebSocket: per frame a JSON text message, then the JPEG as binary; the
    viewer answers each frame with a message, ``"ack"``, before the next is sent; one over
    :data:`MAX_MESSAGE_CHARS` closes the socket with 1009) and ``/stream.mjpg``
    (multipart/x-mixed-replace for a plain ``<img>``)."""
    router = APIRouter()

    @router.websocket("/stream")
    async def _ws(ws: WebSocket) -> None:
        # Flow control: one frame in flight. The viewer acknowledges each frame (any
        # message) once drawn; only then is the newest frame sent. Transport buffers
        # cannot fill up with stale frames however slow the viewer or its network is, and
        # a viewer's messages are read no faster than frames are sent.
        await ws.accept()
        limits = ViewerMessages()
        with hub.watching():
            try:
                async for frame, jpeg in hub.jpeg_frames():
                    await ws.send_text(frame.header_text)
                    await ws.send_bytes(jpeg)
                    message = await ws.receive()
                    if message["type"] == "websocket.disconnect":
                        return
                    limits.admit(message)
            except ViewerMessageRefused as exc:
                await close_quietly(ws, exc.code, str(exc))
            except (WebSocketDisconnect, RuntimeError):
                pass

    @router.get("/stream.mjpg")
    async def _mjpeg() -> StreamingResponse:
        async def parts() -> AsyncIterator[bytes]:
            with hub.watching():
                async for _frame, jpeg in hub.jpeg_frames():
                    yield (
                        b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                        + str(len(jpeg)).encode()
                        + b"\r\n\r\n"
                        + jpeg
                        + b"\r\n"
                    )

        return StreamingResponse(parts(), media_type="multipart/x-mixed-replace; boundary=frame")

    return router


def make_video_router(hub: FrameHub) -> APIRouter:
    """``/stream.video`` (WebSocket; see the module doc)."""
    router = APIRouter()

    @router.websocket("/stream.video")
    async def _video(ws: WebSocket) -> None:
        await ws.accept()
        preset = ws.query_params.get("preset") or hub.stream_settings.preset
        if preset not in PRESETS:
            reason = f"unknown preset {preset[:40]!r}: expected one of {', '.join(PRESETS)}"
            await ws.close(code=POLICY_VIOLATION, reason=reason)
            return
        await VideoSession(hub, ws, preset).run()

    return router


def make_kept_frames_router(kept: KeptFrames | None) -> APIRouter:
    """``GET /api/stream/frame/{seq}.png``: a picture of ``kept`` (the hub's
    ``FrameHub.kept``; None: off), see the module docstring."""
    router = APIRouter()

    @router.get("/api/stream/frame/{seq}.png", include_in_schema=False)
    def _frame(seq: int) -> Response:
        if kept is None:
            raise HTTPException(404, f"pictures are not kept: the console runs without {ENV}")
        bgr = kept.get(seq)
        if bgr is None:
            raise HTTPException(404, f"frame {seq}: not among the last {kept.size} kept")
        ok, png = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise HTTPException(500, f"frame {seq}: could not be encoded as PNG")
        return Response(png.tobytes(), media_type="image/png")

    return router
