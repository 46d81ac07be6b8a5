"""The push ingest WebSocket endpoint for the console's FastAPI app, and the uvicorn
message limit that lets oversize messages be answered.

FastAPI is imported inside :func:`make_push_router` only, so that drivers, which import
the protocol and the clients, do not need it.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from trifuse.app.sources.push.protocol import INGEST_PATH, PushError, identify
from trifuse.app.sources.push.source import PushSource

if TYPE_CHECKING:
    from fastapi import APIRouter


def uvicorn_ws_max_size(source: PushSource) -> int:
    """A ``ws_max_size`` for uvicorn that lets messages somewhat above the source's limit
    reach it (so that they are answered with an error instead of closing the connection)."""
    return source.max_message_bytes + max(1 << 20, source.max_message_bytes // 4)


def make_push_router(
    source: PushSource,
    *,
    path: str = INGEST_PATH,
) -> APIRouter:
    """A FastAPI router with the push ingest WebSocket endpoint at ``path``. The console's
    authentication and Origin checks (app/server/middleware/auth.py) guard it like every route.

    Each binary message is decoded in a worker thread (the event loop stays free) and its
    frame stored in the source; messages of one connection are handled in order. A bad
    message gets a text reply ``{"seq", "ok": false, "error", "sensor"?, "stamp_ns"?}`` and
    the connection goes on; ``"ack": true`` in a header gets ``{"seq", "ok": true, "sensor",
    "stamp_ns", "replaced"}``.
    """
    from fastapi import APIRouter, WebSocket, WebSocketDisconnect
    from starlette.concurrency import run_in_threadpool

    router = APIRouter()

    async def ingest(websocket: WebSocket) -> None:
        await websocket.accept()
        source.count_connection(+1)
        seq = 0
        last_stamps: dict[str, int] = {}
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                seq += 1
                data = message.get("bytes")
                if source.closed:
                    await websocket.close(code=1001, reason="console push source closed")
                    return
                if data is None:
                    await websocket.send_text(
                        json.dumps(
                            {
                                "seq": seq,
                                "ok": False,
                                "error": "expected binary push messages (magic TFP1), got text",
                            }
                        )
                    )
                    continue
                try:
                    header, frame, replaced = await run_in_threadpool(
                        source.accept, data, last_stamps
                    )
                except PushError as exc:
                    reply: dict[str, Any] = {"seq": seq, "ok": False, "error": str(exc)}
                    reply.update(identify(data))
                    await websocket.send_text(json.dumps(reply))
                    continue
                if header.ack:
                    await websocket.send_text(
                        json.dumps(
                            {
                                "seq": seq,
                                "ok": True,
                                "sensor": frame.sensor,
                                "stamp_ns": frame.stamp_ns,
                                "replaced": replaced,
                            }
                        )
                    )
        except WebSocketDisconnect:
            return
        finally:
            source.count_connection(-1)

    # This module postpones annotations (strings); FastAPI resolves them in the module's
    # globals, where WebSocket is not imported (drivers do not need FastAPI): give it the class.
    ingest.__annotations__ = {"websocket": WebSocket, "return": None}
    router.add_api_websocket_route(path, ingest, name="push_ingest")
    return router
