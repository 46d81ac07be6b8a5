"""Viser behind FastAPI: its client page and its WebSocket under one public prefix.

Viser listens on a loopback-only port and has no authentication or Origin check of its own;
the public server serves Viser's single-file client page at ``<prefix>/`` and relays the
client's WebSocket (same URL, subprotocol ``viser-v<version>``) to the loopback port, so
the public server's authentication and Origin checks guard the 3D console too.
"""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import viser
import websockets
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, RedirectResponse

CLIENT_PAGE = Path(viser.__file__).parent / "client" / "build" / "index.html"


def make_viser_router(viser_port: int, prefix: str = "/console") -> APIRouter:
    """Routes serving Viser's client at ``prefix/`` and relaying its WebSocket."""
    router = APIRouter()
    page = CLIENT_PAGE.read_bytes()
    upstream_url = f"ws://127.0.0.1:{viser_port}/"

    @router.get(prefix, include_in_schema=False)
    async def _redirect() -> RedirectResponse:
        return RedirectResponse(prefix + "/")

    @router.get(prefix + "/", include_in_schema=False)
    async def _page() -> HTMLResponse:
        return HTMLResponse(page, headers={"Cache-Control": "no-cache"})

    async def _relay(client: WebSocket) -> None:
        offered = [
            p.strip()
            for p in client.headers.get("sec-websocket-protocol", "").split(",")
            if p.strip()
        ]
        protocol = next((p for p in offered if p.startswith("viser-v")), None)
        try:
            upstream = await websockets.connect(
                upstream_url,
                subprotocols=[protocol] if protocol else None,
                max_size=None,
                compression=None,
                open_timeout=5,
            )
        except (OSError, websockets.WebSocketException):
            await client.close(code=1011, reason="3D console backend not reachable")
            return
        await client.accept(subprotocol=protocol)

        async def client_to_upstream() -> None:
            while True:
                msg = await client.receive()
                if msg["type"] == "websocket.disconnect":
                    return
                if msg.get("bytes") is not None:
                    await upstream.send(msg["bytes"])
                elif msg.get("text") is not None:
                    await upstream.send(msg["text"])

        async def upstream_to_client() -> None:
            async for data in upstream:
                if isinstance(data, bytes):
                    await client.send_bytes(data)
                else:
                    await client.send_text(data)

        tasks = [
            asyncio.create_task(client_to_upstream()),
            asyncio.create_task(upstream_to_client()),
        ]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            with contextlib.suppress(Exception):
                await upstream.close()
            with contextlib.suppress(RuntimeError, WebSocketDisconnect):
                await client.close()

    # The client derives its WebSocket URL from the page URL without the trailing slash.
    router.add_api_websocket_route(prefix, _relay)
    router.add_api_websocket_route(prefix + "/", _relay)
    return router
