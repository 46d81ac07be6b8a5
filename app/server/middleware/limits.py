"""Request limits of the console's HTTP API: body size and JSON bodies.

:class:`BodyLimitMiddleware` (a pure ASGI middleware; :func:`add_body_limit` adds it to an
app) refuses a request whose body is larger than ``max_bytes`` with 413 and a JSON
``detail``: at once when its ``Content-Length`` says so (the body is never read), and while
a body without one (chunked) streams in, as soon as more than ``max_bytes`` arrived. Only
HTTP requests are limited: WebSocket messages have their own limits (push ingest:
``app.sources.push.protocol.DEFAULT_MAX_MESSAGE_BYTES`` and uvicorn's ``ws_max_size``).

:func:`require_json` is a route dependency: a route taking a JSON body answers 415 with
what it expected when the body is sent as something else (form data, text, no type), and
422 when a JSON string holds a lone surrogate (FastAPI's 422 would echo either and fail).
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import HTTPException, Request
from fastapi.responses import JSONResponse

from trifuse.calib.numbers import is_int

DEFAULT_MAX_BODY_BYTES = 1 << 20  # 1 MiB: the API's JSON bodies are a few hundred bytes


def _size(n: int) -> str:
    if n >= 1 << 20 and n % (1 << 20) == 0:
        return f"{n} bytes ({n >> 20} MiB)"
    if n >= 1 << 10 and n % (1 << 10) == 0:
        return f"{n} bytes ({n >> 10} KiB)"
    return f"{n} bytes"


class BodyTooLarge(HTTPException):
    """Raised from ``receive`` when a streamed body passes the limit. An HTTPException, so
    that FastAPI's body reading passes it on and its handler answers 413 with the detail."""

    def __init__(self, detail: str) -> None:
        super().__init__(413, detail, headers={"Connection": "close"})


class BodyLimitMiddleware:
    """Refuse HTTP request bodies larger than ``max_bytes`` (413, JSON ``detail``).

    Args:
        app: the ASGI app to guard.
        max_bytes: the largest body accepted, bytes (default 1 MiB).
    """

    def __init__(self, app: Any, max_bytes: int = DEFAULT_MAX_BODY_BYTES) -> None:
        if not is_int(max_bytes) or max_bytes < 0:
            raise ValueError(f"max_bytes: expected a non-negative integer, got {max_bytes!r}")
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes
        lengths = {v.strip() for k, v in scope.get("headers", ()) if k.lower() == b"content-length"}
        if lengths:
            if len(lengths) > 1 or not all(v.isdigit() for v in lengths):
                shown = b", ".join(sorted(lengths)).decode("latin-1")
                await _reply(send, 400, f"invalid Content-Length header: {shown!r:.80}")
                return
            declared = int(lengths.pop())
            if declared > limit:
                await _reply(
                    send,
                    413,
                    f"request body too large: {_size(declared)}; the limit is {_size(limit)}",
                )
                return

        received = 0
        started = False

        async def limited_receive() -> dict:
            nonlocal received
            if received > limit:  # asked again after the refusal
                raise BodyTooLarge(_streamed(limit))
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise BodyTooLarge(_streamed(limit))
            return message

        async def tracked_send(message: dict) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracked_send)
        except BodyTooLarge as exc:  # an app that does not turn it into a response
            if started:
                raise
            await _reply(send, 413, str(exc.detail))
        except BaseExceptionGroup as group:  # raised inside a task group
            match, rest = group.split(BodyTooLarge)
            if match is None or rest is not None or started:
                raise
            await _reply(send, 413, _streamed(limit))


def _streamed(limit: int) -> str:
    return f"request body too large: more than {_size(limit)} sent; the limit is {_size(limit)}"


async def _reply(send: Any, status: int, detail: str) -> None:
    response = JSONResponse({"detail": detail}, status_code=status)
    if status == 413:  # the rest of the body is not read: do not reuse the connection
        response.headers["Connection"] = "close"
    await send({"type": "http.response.start", "status": status, "headers": response.raw_headers})
    await send({"type": "http.response.body", "body": response.body})


def add_body_limit(app: Any, max_bytes: int = DEFAULT_MAX_BODY_BYTES) -> None:
    """Limit the request bodies of ``app`` (a FastAPI/Starlette app, before it starts)."""
    app.add_middleware(BodyLimitMiddleware, max_bytes=max_bytes)


async def require_json(request: Request) -> None:
    """Dependency of routes taking a JSON body: 415 naming the expected type when a body
    is sent as something else (FastAPI would try to validate the raw bytes), 422 when a
    string of the JSON holds a lone UTF-16 surrogate (``"\\ud800"``: valid JSON, but no
    text; it could not even be echoed back in an error message)."""
    body = await request.body()
    if not body:
        return
    ctype = request.headers.get("content-type", "")
    media = ctype.split(";", 1)[0].strip().lower()
    if media != "application/json" and not (
        media.startswith("application/") and media.endswith("+json")
    ):
        shown = f"{ctype[:60]!r}" if ctype else "no Content-Type"
        raise HTTPException(
            415,
            f"{request.method} {request.url.path} takes a JSON body "
            f"(Content-Type: application/json), got {shown}",
        )
    try:
        value = await request.json()  # parsed (and kept) by FastAPI already
    except ValueError:
        return  # FastAPI answers malformed JSON itself
    bad = _lone_surrogate(value)
    if bad is not None:
        raise HTTPException(
            422,
            f"{request.method} {request.url.path}: the JSON body holds a string with a lone "
            f"UTF-16 surrogate ({bad[:40]!r}), which is not text",
        )


_SURROGATE = re.compile("[\ud800-\udfff]")


def _lone_surrogate(value: Any) -> str | None:
    """The first string (key or value) in ``value`` with a lone surrogate, or None."""
    stack = [value]
    while stack:
        v = stack.pop()
        if isinstance(v, str):
            if _SURROGATE.search(v):
                return v
        elif isinstance(v, dict):
            stack.extend(v)
            stack.extend(v.values())
        elif isinstance(v, list):
            stack.extend(v)
    return None
