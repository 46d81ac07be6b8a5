"""Who may use the console: a token, a session cookie, and Origin checks (docs/SECURITY.md).

Modelled on Jupyter's token authentication. ``trifuse serve`` starts with a random token
(or the one given with ``--token`` / ``TRIFUSE_TOKEN``) and prints the console's URL with
it (``/?token=...``). A browser that opens that URL gets a session cookie (``HttpOnly``,
``SameSite=Strict``, ``Secure`` under TLS) and is redirected to the same page without the
token, so the token stays out of the address bar, the history and ``Referer`` headers.
Scripts send ``Authorization: token <token>`` (or ``Bearer``). Every route, the stream, the
push ingest and the relayed Viser WebSocket go through :class:`AuthMiddleware`; only
``/login`` (a form that takes the token) is open.

Origin checks: a WebSocket upgrade, and any request that may change state (not GET, HEAD
or OPTIONS), that carries an ``Origin`` header must come from the console's own origin or
one given with ``--allow-origin``; otherwise 403, even with a valid cookie (cross-site
WebSocket hijacking, CSRF). Without a token (``--no-token``, loopback only) the ``Host``
header must name a loopback address too (DNS rebinding).

Tokens and cookies are compared in constant time (:func:`hmac.compare_digest`). A client
(by address) that presents wrong tokens is slowed down: after
:data:`FAILURES_BEFORE_THROTTLE` failures every further attempt within the back-off (doubling
from 1 s up to :data:`MAX_BACKOFF_S`) is answered 429 without looking at the token.
Every redirect target passes the same local-path check (never another site).
"""

from __future__ import annotations

import hmac
import html
import ipaddress
import json
import secrets
import threading
import time
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, quote, urlencode, urlsplit

from starlette.datastructures import Headers
from starlette.requests import HTTPConnection

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

MIN_TOKEN_CHARS = 16
"""Shortest token accepted on a loopback address."""
MIN_NETWORK_TOKEN_CHARS = 22
"""Shortest token accepted when the console serves the network: 22 characters of a random
URL-safe token carry 132 bits (at least 128)."""
FAILURES_BEFORE_THROTTLE = 5
MAX_BACKOFF_S = 60.0
LOGIN_PATH = "/login"
MAX_LOGIN_BODY = 4096
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SECURITY_HEADERS = (
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"same-origin"),  # "no-referrer" makes forms send Origin: null
    (b"x-frame-options", b"DENY"),
    (b"content-security-policy", b"frame-ancestors 'none'"),
)


def new_token() -> str:
    """A random token: 32 bytes, URL-safe base64 (43 characters)."""
    return secrets.token_urlsafe(32)


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (``127.0.0.0/8``, ``::1``; IPv6 with or
    without brackets) or exactly the name ``localhost``. Other names are not, whatever
    they start with (``127.evil.com`` and ``127.0.0.1.nip.io`` are DNS names that anyone
    can point anywhere: DNS rebinding)."""
    host = host.strip().lower().removeprefix("[").removesuffix("]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_token(token: str, network: bool = False) -> str:
    """``token`` if it is usable, else ValueError saying why. ``network``: the console
    serves more than loopback, and the token must carry at least 128 bits."""
    least = MIN_NETWORK_TOKEN_CHARS if network else MIN_TOKEN_CHARS
    if len(token) < least:
        where = " for a console on the network" if network else ""
        raise ValueError(
            f"the token must have at least {least} characters{where} (got {len(token)}); "
            "leave it out and a random one is generated"
        )
    if not token.isascii() or not token.isprintable() or any(c in token for c in " ;,\"'"):
        raise ValueError("the token must be printable ASCII without spaces, quotes, ';' or ','")
    return token


@dataclass(frozen=True)
class AuthConfig:
    """How the console authenticates.

    Attributes:
        token: the secret; ``None`` means no authentication (loopback only, asked for
            with ``--no-token``).
        port: the public port; it names the cookie (cookies ignore ports, so two consoles
            on one host would otherwise overwrite each other's).
        secure: the server speaks TLS: the cookie is ``Secure``.
        allowed_origins: origins (``scheme://host[:port]``) besides the console's own that
            may open WebSockets and send state-changing requests.
    """

    token: str | None
    port: int
    secure: bool = False
    allowed_origins: frozenset[str] = frozenset()
    session: str = field(default_factory=new_token, repr=False)
    """The session cookie's value: random per server process (restarts sign everyone out)."""

    @property
    def cookie_name(self) -> str:
        return f"trifuse-session-{self.port}"

    def set_cookie(self) -> bytes:
        attrs = "; Path=/; HttpOnly; SameSite=Strict" + ("; Secure" if self.secure else "")
        return f"{self.cookie_name}={self.session}{attrs}".encode("latin-1")

    def token_ok(self, given: str | None) -> bool:
        """Constant-time comparison of a presented token."""
        if self.token is None or not given:
            return False
        return hmac.compare_digest(given.encode("utf-8"), self.token.encode("utf-8"))

    def cookie_ok(self, given: str | None) -> bool:
        if not given:
            return False
        return hmac.compare_digest(given.encode("utf-8"), self.session.encode("utf-8"))


def _authorization_token(headers: Headers) -> str | None:
    scheme, _, value = headers.get("authorization", "").partition(" ")
    return value.strip() if scheme.lower() in ("token", "bearer") else None


def _own_origin(scope: Scope, headers: Headers) -> str:
    scheme = {"ws": "http", "wss": "https"}.get(scope.get("scheme", "http"), scope.get("scheme"))
    return f"{scheme}://{headers.get('host', '')}".lower()


def _host_name(host_header: str) -> str:
    """The host part of a ``Host`` header (without the port)."""
    return urlsplit(f"//{host_header}").hostname or ""


def _login_page(message: str, next_path: str) -> bytes:
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>trifuse: sign in</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{{font:16px system-ui,sans-serif;background:#111;color:#ddd;margin:3em auto;
max-width:36em;padding:0 1em}}input{{font:inherit;width:100%;margin:.5em 0;padding:.4em}}
button{{font:inherit;padding:.4em 1.2em}}p.msg{{color:#f96}}</style></head>
<body><h1>trifuse console</h1>
<p class="msg">{html.escape(message)}</p>
<p>Open the URL that <code>trifuse serve</code> printed (it ends with
<code>?token=...</code>), or paste its token here.</p>
<form method="post" action="{LOGIN_PATH}">
<input type="hidden" name="next" value="{html.escape(next_path, quote=True)}">
<label>Token <input type="password" name="token" autocomplete="current-password"
autofocus></label>
<button type="submit">Sign in</button></form></body></html>""".encode()


def _safe_next(path: str) -> str:
    """A local path to go to after signing in or dropping the token (never another site:
    ``//host``, ``/\\host`` and control characters, which browsers strip, fall back to
    ``/``)."""
    if (
        not path.startswith("/")
        or path.startswith("//")
        or "\\" in path
        or any(ord(c) < 32 or ord(c) == 127 for c in path)
    ):
        return "/"
    return path


class SignInThrottle:
    """Failed token attempts per client address, and how long each must wait.

    After :data:`FAILURES_BEFORE_THROTTLE` failures a client waits 1 s, then 2, 4, ... up to
    :data:`MAX_BACKOFF_S` after each further failure; a success forgets it. Thread-safe;
    at most ``max_clients`` addresses are remembered (the oldest go first).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, max_clients: int = 4096):
        self._clock = clock
        self._max = max_clients
        self._lock = threading.Lock()
        self._failures: dict[str, tuple[int, float]] = {}  # client -> (count, blocked until)

    def wait_s(self, client: str) -> float:
        """Seconds ``client`` must still wait before its next attempt is looked at."""
        with self._lock:
            _n, until = self._failures.get(client, (0, 0.0))
        return max(0.0, until - self._clock())

    def failed(self, client: str) -> None:
        with self._lock:
            n, _ = self._failures.pop(client, (0, 0.0))
            n += 1
            extra = n - FAILURES_BEFORE_THROTTLE
            wait = 0.0 if extra < 0 else min(MAX_BACKOFF_S, 2.0**extra)
            self._failures[client] = (n, self._clock() + wait)
            while len(self._failures) > self._max:
                del self._failures[next(iter(self._failures))]

    def succeeded(self, client: str) -> None:
        with self._lock:
            self._failures.pop(client, None)


class AuthMiddleware:
    """ASGI middleware: Origin checks and authentication of every HTTP request and
    WebSocket (see the module docstring); adds security headers to every answer."""

    def __init__(self, app: ASGIApp, config: AuthConfig) -> None:
        self.app = app
        self.config = config
        self.throttle = SignInThrottle()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        conn = HTTPConnection(scope)
        headers = conn.headers
        refusal = self._origin_refusal(scope, headers)
        if refusal:
            await self._deny(conn, send, 403, refusal)
            return
        cfg = self.config
        if kind == "http" and scope["path"] == LOGIN_PATH and cfg.token is not None:
            await self._login(scope, receive, send)
            return
        if cfg.token is None or cfg.cookie_ok(conn.cookies.get(cfg.cookie_name)):
            await self.app(scope, receive, _with_headers(send))
            return
        client = conn.client.host if conn.client else ""
        presented = _authorization_token(headers) or conn.query_params.get("token")
        if presented and (wait := self.throttle.wait_s(client)) > 0:
            await self._too_many(conn, send, wait)
            return
        if cfg.token_ok(_authorization_token(headers)):
            self.throttle.succeeded(client)
            await self.app(scope, receive, _with_headers(send))
            return
        if cfg.token_ok(conn.query_params.get("token")):
            self.throttle.succeeded(client)
            if kind == "http" and scope["method"] == "GET" and _navigation(headers):
                # a browser opened the token URL: cookie, then the same page without it
                rest = urlencode([kv for kv in conn.query_params.multi_items() if kv[0] != "token"])
                target = _safe_next(scope["path"])
                await _redirect(send, target + (f"?{rest}" if rest else ""), cfg)
                return
            await self.app(scope, receive, _with_headers(send, cfg.set_cookie()))
            return
        if presented:
            self.throttle.failed(client)
        what = "a token or a session cookie" if kind == "http" else "a session"
        await self._deny(conn, send, 401, f"authentication required: {what}")

    async def _too_many(self, conn: HTTPConnection, send: Send, wait_s: float) -> None:
        """429 (a WebSocket: closed before accepting) while a client's back-off lasts."""
        if conn.scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008, "reason": "too many attempts"})
            return
        retry = str(max(1, round(wait_s))).encode()
        body = json.dumps(
            {"detail": f"too many wrong tokens from this address; try again in {retry.decode()} s"}
        ).encode()
        await _respond(send, 429, body, b"application/json", [(b"retry-after", retry)])

    def _origin_refusal(self, scope: Scope, headers: Headers) -> str | None:
        """Why the request is refused for where it comes from, or None."""
        if self.config.token is None:
            host = _host_name(headers.get("host", ""))
            if host and not is_loopback(host):
                return (
                    f"host {host!r} is not loopback; this console runs without a token and "
                    "answers loopback names only"
                )
        origin = headers.get("origin")
        unsafe = scope["type"] == "websocket" or scope.get("method") not in SAFE_METHODS
        if origin is None or not unsafe:
            return None
        origin = origin.lower().rstrip("/")
        if origin == _own_origin(scope, headers) or origin in self.config.allowed_origins:
            return None
        return f"origin {origin!r} is not allowed (cross-site request)"

    async def _deny(self, conn: HTTPConnection, send: Send, status: int, message: str) -> None:
        if conn.scope["type"] == "websocket":
            # closing before accepting: the server answers the upgrade with 403
            await send({"type": "websocket.close", "code": 1008, "reason": message[:120]})
            return
        if status == 401 and _navigation(conn.headers):
            path = conn.scope["path"]
            qs = conn.scope.get("query_string", b"").decode("latin-1")
            next_path = path + (f"?{qs}" if qs and "token=" not in qs else "")
            body = _login_page("Sign in to use this console.", next_path)
            await _respond(send, status, body, b"text/html; charset=utf-8")
            return
        hint = (
            " (open the URL printed by trifuse serve, or send 'Authorization: token <token>')"
            if status == 401
            else ""
        )
        body = json.dumps({"detail": message + hint}).encode()
        extra = [(b"www-authenticate", b"Token")] if status == 401 else []
        await _respond(send, status, body, b"application/json", extra)

    async def _login(self, scope: Scope, receive: Receive, send: Send) -> None:
        """``GET /login``: the form; ``POST /login`` (``token``, ``next``): cookie and
        redirect, or the form again with 401."""
        if scope["method"] != "POST":
            await _respond(send, 200, _login_page("", "/"), b"text/html; charset=utf-8")
            return
        body = b""
        while True:
            message = await receive()
            body += message.get("body", b"")
            if len(body) > MAX_LOGIN_BODY:
                too_large = b'{"detail": "login form too large"}'
                await _respond(send, 413, too_large, b"application/json")
                return
            if not message.get("more_body"):
                break
        form = dict(parse_qsl(body.decode("utf-8", "replace"), keep_blank_values=True))
        next_path = _safe_next(form.get("next", "/"))
        client = scope["client"][0] if scope.get("client") else ""
        if (wait := self.throttle.wait_s(client)) > 0:
            page = _login_page(f"Too many wrong tokens: wait {max(1, round(wait))} s.", next_path)
            extra = [(b"retry-after", str(max(1, round(wait))).encode())]
            await _respond(send, 429, page, b"text/html; charset=utf-8", extra)
            return
        if self.config.token_ok(form.get("token")):
            self.throttle.succeeded(client)
            await _redirect(send, next_path, self.config)
            return
        self.throttle.failed(client)
        page = _login_page("Wrong token.", next_path)
        await _respond(send, 401, page, b"text/html; charset=utf-8")


def _navigation(headers: Headers) -> bool:
    """Whether a browser is loading a page (rather than a script fetching data)."""
    mode = headers.get("sec-fetch-mode")
    if mode is not None:
        return mode == "navigate"
    return "text/html" in headers.get("accept", "")


def _with_headers(send: Send, cookie: bytes | None = None) -> Send:
    """``send`` adding the security headers (and a Set-Cookie) to an HTTP answer."""

    async def wrapped(message: Message) -> None:
        if message["type"] == "http.response.start":
            extra = list(SECURITY_HEADERS)
            if cookie is not None:
                extra.append((b"set-cookie", cookie))
            message = {**message, "headers": [*message.get("headers", ()), *extra]}
        await send(message)

    return wrapped


async def _respond(
    send: Send,
    status: int,
    body: bytes,
    content_type: bytes,
    extra: Iterable[tuple[bytes, bytes]] = (),
) -> None:
    headers = [
        (b"content-type", content_type),
        (b"content-length", str(len(body)).encode()),
        (b"cache-control", b"no-store"),
        *SECURITY_HEADERS,
        *extra,
    ]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


async def _redirect(send: Send, location: str, config: AuthConfig) -> None:
    await _respond(
        send,
        303,
        b"",
        b"text/plain",
        [
            (b"location", quote(location, safe="/?&=%:+,;@!$'()*~-._").encode("ascii")),
            (b"set-cookie", config.set_cookie()),
        ],
    )
