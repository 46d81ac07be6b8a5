"""Viser behind FastAPI: its client page and its WebSocket under one public prefix.

Viser listens on a loopback port and has no authentication or Origin check of its own:
any local process, or a web page scanning localhost ports, could otherwise open it and
press its buttons. :func:`start_guarded_viser` therefore starts it with a check in front
of every handshake on that port (HTTP and WebSocket alike): the request must carry the
console's per-process secret in :data:`RELAY_HEADER` and no ``Origin`` header (browsers
always send one; the relay never does), else 403. The public server serves Viser's
single-file client page at ``<prefix>/`` itself and relays the client's WebSocket (same
URL, subprotocol ``viser-v<version>``) to the loopback port with the secret, so the public
server's authentication and Origin checks are the only way in to the 3D console.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import http
import io
import secrets
import threading
from pathlib import Path
from typing import Any

import viser
import websockets
import websockets.asyncio.server
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, RedirectResponse

CLIENT_PAGE = Path(viser.__file__).parent / "client" / "build" / "index.html"
RELAY_HEADER = "X-Trifuse-Relay"
"""Header holding the per-process secret that Viser's port requires."""
_PATCH_LOCK = threading.Lock()


def start_guarded_viser() -> tuple[viser.ViserServer, str]:
    """Viser on a free loopback port that answers only requests carrying the returned
    secret in :data:`RELAY_HEADER` and no ``Origin``; ``(server, secret)``.

    Viser 1.1.1 builds its server with ``websockets.asyncio.server.serve`` in its own
    thread and returns once the port is bound; for that moment the function is wrapped so
    that the check comes before Viser's own request handling.
    """
    secret = secrets.token_urlsafe(32)
    expected = secret.encode()
    original = websockets.asyncio.server.serve

    def guarded(handler: Any, *args: Any, process_request: Any = None, **kwargs: Any) -> Any:
        def check(connection: Any, request: Any) -> Any:
            given = request.headers.get(RELAY_HEADER, "").encode("utf-8", "replace")
            if "Origin" in request.headers or not hmac.compare_digest(given, expected):
                return connection.respond(
                    http.HTTPStatus.FORBIDDEN, "trifuse: open the console's public URL\n"
                )
            return None if process_request is None else process_request(connection, request)

        return original(handler, *args, process_request=check, **kwargs)

    with _PATCH_LOCK:
        websockets.asyncio.server.serve = guarded
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # its banner shows the inner port
                server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        finally:
            websockets.asyncio.server.serve = original
    return server, secret


def make_viser_router(
    viser_port: int, secret: str | None = None, prefix: str = "/console"
) -> APIRouter:
    """Routes serving Viser's client at ``prefix/`` and relaying its WebSocket to the
    loopback ``viser_port`` (with ``secret``, see :func:`start_guarded_viser`)."""
    router = APIRouter()
    page = CLIENT_PAGE.read_bytes()
    upstream_url = f"ws://127.0.0.1:{viser_port}/"
    relay_headers = {RELAY_HEADER: secret} if secret is not None else None

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
                additional_headers=relay_headers,
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
