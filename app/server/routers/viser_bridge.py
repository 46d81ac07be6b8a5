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

The relay also checks the client's uploads before Viser buffers them (:class:`UploadGate`):
Viser keeps every part of an upload in memory and trusts the size the client declares.

Viser's markdown reads every ``![alt](path)`` it is given as an image file on the server
and sends it to every browser; the panels escape outside text (app.server.markdown_text),
and :func:`start_guarded_viser` also turns that reading off for the whole process (the
console's markdown never shows images), so a string that escaped the escaping still reads
no file.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import http
import io
import secrets
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import viser
import viser._gui_handles
import websockets
import websockets.asyncio.server
from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse, RedirectResponse

CLIENT_PAGE = Path(viser.__file__).parent / "client" / "build" / "index.html"
RELAY_HEADER = "X-Trifuse-Relay"
"""Header holding the per-process secret that Viser's port requires."""
_PATCH_LOCK = threading.Lock()
VISER_IMAGE_READER = viser._gui_handles._get_data_url
"""Viser's own ``_get_data_url(url, image_root)`` (reads ``url`` as an image file), as it
was before :func:`start_guarded_viser` replaced it with :func:`_no_file_reads`."""

MAX_UPLOAD_BYTES = 4 << 20
"""The largest file the console's upload buttons take (the Rig files': rig files are
small, app.server.panels.rig_files.MAX_UPLOAD_BYTES)."""
MAX_UPLOAD_PARTS = 64
"""Parts one upload may declare (Viser's client sends 512 KiB parts: 8 for 4 MiB)."""
MAX_UPLOAD_BYTES_IN_FLIGHT = 16 << 20
"""Declared bytes of all unfinished uploads through the relay, all connections together."""
MAX_UPLOAD_NAME_CHARS = 1024
"""An upload's file name (shown in the panels) has at most this many characters."""


class UploadRefused(ValueError):
    """A client's upload message the relay does not pass to Viser; ``code`` is the
    WebSocket close code the relay closes that client's connection with."""

    def __init__(self, message: str, code: int = 1008) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class _Transfer:
    owner: object
    size: int
    parts: int
    received: int = 0
    seen: set[int] = field(default_factory=set)


class UploadGate:
    """Viser's uploads, checked message by message before Viser sees them.

    Viser's client sends a file as ``FileTransferStartUpload`` (``filename``,
    ``size_bytes``, ``part_count``, ``transfer_uuid``) and then ``FileTransferPart``
    messages, msgpack. Viser's server keeps every part in memory until the last one has
    come and trusts what the start declared: a client could declare 4 MiB and send
    gigabytes, a billion empty parts, or parts of another client's upload. The gate starts
    a transfer only within ``max_bytes``, ``max_parts`` and, over all connections,
    ``budget_bytes`` of unfinished uploads; then it passes only the owning connection's
    parts, each index once and at most the declared bytes in all. One gate serves every
    relay connection (all on one event loop: no lock).
    """

    def __init__(
        self,
        max_bytes: int = MAX_UPLOAD_BYTES,
        max_parts: int = MAX_UPLOAD_PARTS,
        budget_bytes: int = MAX_UPLOAD_BYTES_IN_FLIGHT,
    ) -> None:
        self.max_bytes, self.max_parts, self.budget_bytes = max_bytes, max_parts, budget_bytes
        self._transfers: dict[str, _Transfer] = {}

    @property
    def in_flight_bytes(self) -> int:
        """Declared bytes of the unfinished uploads."""
        return sum(t.size for t in self._transfers.values())

    def check(self, owner: object, data: bytes) -> None:
        """Pass ``data``, a message from the client of connection ``owner``, or raise
        :class:`UploadRefused`. Only upload messages are decoded."""
        if b"FileTransfer" not in data:  # msgpack holds the type name as it is
            return
        try:
            message = msgspec.msgpack.decode(data)
        except msgspec.DecodeError:
            return  # Viser cannot read it either
        if isinstance(message, dict) and message.get("type") == "FileTransferStartUpload":
            self._start(owner, message)
        elif isinstance(message, dict) and message.get("type") == "FileTransferPart":
            self._part(owner, message)

    def forget(self, owner: object) -> None:
        """Drop the unfinished uploads of a closed connection (Viser drops them too)."""
        for uuid in [u for u, t in self._transfers.items() if t.owner is owner]:
            del self._transfers[uuid]

    def _start(self, owner: object, m: dict) -> None:
        size, parts, uuid, name = (
            m.get(k) for k in ("size_bytes", "part_count", "transfer_uuid", "filename")
        )
        if not (isinstance(size, int) and isinstance(parts, int)):
            raise UploadRefused("upload: size and part count must be integers")
        if size > self.max_bytes:
            raise UploadRefused(f"upload of {size} bytes refused: at most {self.max_bytes}", 1009)
        if size < 0 or not (0 < parts <= self.max_parts if size else parts == 0):
            raise UploadRefused(
                f"upload: {parts} parts for {size} bytes; expected 1 to {self.max_parts}"
            )
        if not isinstance(name, str) or len(name) > MAX_UPLOAD_NAME_CHARS:
            raise UploadRefused(
                f"upload: a file name of at most {MAX_UPLOAD_NAME_CHARS} characters"
            )
        if not isinstance(uuid, str) or uuid in self._transfers:
            raise UploadRefused("upload: a transfer id that is not new")
        if self.in_flight_bytes + size > self.budget_bytes:
            raise UploadRefused("upload refused: the console is receiving others, try again", 1013)
        if parts:
            self._transfers[uuid] = _Transfer(owner, size, parts)

    def _part(self, owner: object, m: dict) -> None:
        uuid, index, content = (m.get(k) for k in ("transfer_uuid", "part_index", "content"))
        t = self._transfers.get(uuid) if isinstance(uuid, str) else None
        if t is None or t.owner is not owner:
            raise UploadRefused("upload: a part of no upload of this connection")
        if not isinstance(index, int) or not 0 <= index < t.parts or index in t.seen:
            raise UploadRefused(f"upload: part {index!r} of {t.parts} (or again)")
        if not isinstance(content, bytes):
            raise UploadRefused("upload: a part without bytes")
        t.received += len(content)
        if t.received > t.size:
            raise UploadRefused(f"upload: more than the {t.size} bytes declared", 1009)
        t.seen.add(index)
        if len(t.seen) == t.parts:
            del self._transfers[uuid]


def start_guarded_viser() -> tuple[viser.ViserServer, str]:
    """Viser on a free loopback port that answers only requests carrying the returned
    secret in :data:`RELAY_HEADER` and no ``Origin``; ``(server, secret)``.

    Viser 1.1.1 builds its server with ``websockets.asyncio.server.serve`` in its own
    thread and returns once the port is bound; for that moment the function is wrapped so
    that the check comes before Viser's own request handling.
    """
    viser._gui_handles._get_data_url = _no_file_reads
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


def _no_file_reads(url: str, image_root: Path | None) -> str:
    """Viser's markdown image URL as it is: nothing is read on the server."""
    return url


CONSOLE_SCRIPT = b'<script src="/static/console-gpu.js" defer></script>'
"""Added to Viser's client page: a note suggesting the low bandwidth mode where WebGL is
drawn in software (``static/console-gpu.js``)."""


def with_console_script(page: bytes) -> bytes:
    """Viser's client page with :data:`CONSOLE_SCRIPT` before ``</body>`` (at the end if it
    has none)."""
    at = page.rfind(b"</body>")
    return page + CONSOLE_SCRIPT if at < 0 else page[:at] + CONSOLE_SCRIPT + page[at:]


def make_viser_router(
    viser_port: int,
    secret: str | None = None,
    prefix: str = "/console",
    uploads: UploadGate | None = None,
) -> APIRouter:
    """Routes serving Viser's client at ``prefix/`` and relaying its WebSocket to the
    loopback ``viser_port`` (with ``secret``, see :func:`start_guarded_viser`); client
    messages pass ``uploads`` (a new :class:`UploadGate` if None) on the way, and a
    refused upload closes that client's connection with the reason."""
    router = APIRouter()
    gate = uploads if uploads is not None else UploadGate()
    page = with_console_script(CLIENT_PAGE.read_bytes())
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
                    try:
                        gate.check(client, msg["bytes"])
                    except UploadRefused as exc:
                        await client.close(code=exc.code, reason=str(exc)[:120])
                        return
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
            gate.forget(client)
            for t in tasks:
                t.cancel()
            with contextlib.suppress(Exception):
                try:
                    await upstream.close()
                except asyncio.CancelledError:
                    # Cancelled while closing (the server stopping, a test client
                    # leaving): drop the TCP connection, or Viser keeps counting the
                    # client until its next keepalive ping, 20 s on.
                    upstream.transport.abort()
                    raise
            with contextlib.suppress(RuntimeError, WebSocketDisconnect):
                await client.close()

    # The client derives its WebSocket URL from the page URL without the trailing slash.
    router.add_api_websocket_route(prefix, _relay)
    router.add_api_websocket_route(prefix + "/", _relay)
    return router
