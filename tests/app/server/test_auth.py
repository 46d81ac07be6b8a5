"""Authentication and Origin checks of the console (app/server/middleware/auth.py,
``trifuse serve``).

The app under test is built as ``trifuse serve`` builds it (every router, the push ingest
and the Viser relay), so a route added later without protection fails here.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import ssl
import subprocess
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from tests.browser_support import start_console
from tests.support import ListSource, serve
from trifuse.app.cli import main
from trifuse.app.devtools.console_process import free_port, stop_process
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.middleware.auth import AuthConfig, SignInThrottle, check_token, is_loopback
from trifuse.app.server.routers.drift_api import make_drift_router
from trifuse.app.server.routers.session_api import make_session_router
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.push.router import make_push_router
from trifuse.app.sources.push.source import PushSource
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.workflows.calib_session import CalibrationSession

TOKEN = "test-token-0123456789abcdef"
HOST = "testserver"  # TestClient's Host header; its origin is http://testserver
OWN = "http://testserver"
FOREIGN = "https://evil.example"
AUTH = {"Authorization": f"token {TOKEN}"}


def console_app(tmp_path: Path, token: str | None = TOKEN, **auth_kw) -> FastAPI:
    """The console's app with every router ``trifuse serve`` adds."""
    rig = default_rig()
    pipeline = FusionPipeline(ListSource(), rig, FrameHub())
    auth = AuthConfig(token, 8000, **auth_kw)
    app = create_app(FrameHub(), free_port(), pipeline, auth=auth)
    session = CalibrationSession(tmp_path / "work", rig, CALIBRATION_BOARD)
    app.include_router(make_session_router(session, lambda: None, lambda _rig: None))
    app.include_router(make_drift_router(DriftWatch(pipeline), session.save_rig, lambda _rig: None))
    app.include_router(make_push_router(PushSource(rig)))
    return app


@pytest.fixture
def client(tmp_path) -> Iterator[TestClient]:
    with TestClient(console_app(tmp_path), follow_redirects=False) as c:
        yield c


HIDDEN = [("GET", p) for p in ("/", "/console", "/console/", "/static/viewer.js", "/docs")]
"""Routes left out of the OpenAPI schema."""
WEBSOCKETS = ("/stream", "/stream.video", "/ingest", "/console", "/console/")


def _requests(app: FastAPI) -> list[tuple[str, str]]:
    """(method, path) of every HTTP route (path parameters filled in)."""
    out = [*HIDDEN, ("GET", "/openapi.json")]
    for path, ops in app.openapi()["paths"].items():
        out += [(m.upper(), re.sub(r"\{[^}]+\}", "x", path)) for m in ops]
    return out


def test_every_route_and_websocket_needs_the_token(client) -> None:
    requests = _requests(client.app)
    paths = {p for _, p in requests}
    assert {"/", "/api/status", "/api/captures", "/console/", "/docs", "/stream.mjpg"} <= paths
    assert {("POST", "/api/rigs/x/use"), ("PUT", "/api/fusion")} <= set(requests)
    assert len(requests) >= 35  # 37 when this was written
    for method, path in requests:
        r = client.request(method, path)
        assert r.status_code == 401, (method, path, r.status_code)
        assert "authentication required" in r.json()["detail"]
        r = client.request(method, path, headers={"Authorization": "token wrong-token-0123456"})
        # refused; after a few wrong tokens the address must wait (429) before it may try
        assert r.status_code in (401, 429), (method, path)
    for path in WEBSOCKETS:
        with pytest.raises(WebSocketDisconnect) as refused:
            with client.websocket_connect(path):
                pass
        assert refused.value.code == 1008, path


def test_token_header_query_and_cookie(client) -> None:
    for scheme in ("token", "Bearer"):
        r = client.get("/api/status", headers={"Authorization": f"{scheme} {TOKEN}"})
        assert r.status_code == 200 and "viewers" in r.json()
        assert r.headers["x-frame-options"] == "DENY"
        assert r.headers["referrer-policy"] == "same-origin"
    # a script may put the token in the query; it gets a cookie along
    r = client.get(f"/api/status?token={TOKEN}")
    assert r.status_code == 200
    assert "trifuse-session-8000" in r.headers["set-cookie"]
    client.cookies.clear()


def test_browser_exchanges_the_token_for_a_cookie(client) -> None:
    page = {"Accept": "text/html", "Sec-Fetch-Mode": "navigate"}
    r = client.get("/console/", headers=page)
    assert r.status_code == 401 and "paste its token" in r.text  # the sign-in page
    r = client.get(f"/console/?token={TOKEN}&x=1", headers=page)
    assert r.status_code == 303
    assert r.headers["location"] == "/console/?x=1"  # the token leaves the address bar
    cookie = r.headers["set-cookie"]
    for attr in ("HttpOnly", "SameSite=Strict", "Path=/"):
        assert attr in cookie
    assert "Secure" not in cookie and TOKEN not in cookie
    assert client.get("/console/", headers=page).status_code == 200
    assert client.get("/api/status").status_code == 200
    assert client.post("/api/source/pause").status_code in (200, 409)
    with client.websocket_connect("/stream") as ws:  # the viewer's stream, same origin
        ws.close()
    client.cookies.clear()
    client.cookies.set("trifuse-session-8000", "forged-cookie-value")
    assert client.get("/api/status").status_code == 401


def test_login_form(client) -> None:
    assert "Sign in" in client.get("/login").text
    r = client.post("/login", data={"token": "wrong-token-0123456", "next": "/console/"})
    assert r.status_code == 401 and "Wrong token" in r.text
    assert "set-cookie" not in r.headers
    r = client.post("/login", data={"token": TOKEN, "next": "//evil.example/"})
    assert r.status_code == 303 and r.headers["location"] == "/"  # never off-site
    r = client.post("/login", data={"token": TOKEN, "next": "/console/"})
    assert r.status_code == 303 and r.headers["location"] == "/console/"
    assert client.get("/api/status").status_code == 200
    r = client.post("/login", content=b"token=" + b"x" * 10000)
    assert r.status_code == 413


def test_foreign_origin_is_refused_even_when_signed_in(client) -> None:
    auth = {"Authorization": f"token {TOKEN}"}
    for path in ("/stream", "/ingest", "/console/"):
        with pytest.raises(WebSocketDisconnect) as refused:
            with client.websocket_connect(path, headers={**auth, "Origin": FOREIGN}):
                pass
        assert refused.value.code == 1008
    with client.websocket_connect("/stream", headers={**auth, "Origin": OWN}) as ws:
        assert isinstance(ws.receive, object)
    # cross-site request forgery: a change from another site, with the victim's cookie
    client.get(f"/api/status?token={TOKEN}")
    r = client.post("/api/source/pause", headers={"Origin": FOREIGN})
    assert r.status_code == 403 and "not allowed" in r.json()["detail"]
    r = client.put("/api/thermal", json={"offset_k": {}}, headers={"Origin": FOREIGN})
    assert r.status_code == 403
    assert client.get("/api/status", headers={"Origin": FOREIGN}).status_code == 200  # reading


def test_allowed_origin(tmp_path) -> None:
    app = console_app(tmp_path, allowed_origins=frozenset({"https://headset.local:8443"}))
    with TestClient(app) as c:
        headers = {"Authorization": f"token {TOKEN}", "Origin": "https://headset.local:8443"}
        with c.websocket_connect("/stream", headers=headers):
            pass
        with pytest.raises(WebSocketDisconnect):
            with c.websocket_connect("/stream", headers={**headers, "Origin": FOREIGN}):
                pass


def test_without_a_token_only_loopback_names_and_own_origin(tmp_path) -> None:
    with TestClient(console_app(tmp_path, token=None), base_url="http://127.0.0.1:8000") as c:
        assert c.get("/api/status").status_code == 200
        assert c.get("/login").status_code == 404  # nothing to sign in to
        # DNS rebinding: a site whose name resolves to 127.0.0.1
        r = c.get("/api/status", headers={"Host": "evil.example:8000"})
        assert r.status_code == 403 and "not loopback" in r.json()["detail"]
        r = c.post("/api/source/pause", headers={"Origin": FOREIGN})
        assert r.status_code == 403
        with pytest.raises(WebSocketDisconnect):
            with c.websocket_connect("/stream", headers={"Origin": FOREIGN}):
                pass


def test_token_rules() -> None:
    assert check_token(TOKEN) == TOKEN
    for bad in (
        "short",
        "has space 0123456789",
        "x" * 15,
        "quote'0123456789abc",
        "ünïcode-0123456789",
    ):
        with pytest.raises(ValueError, match="token"):
            check_token(bad)
    assert is_loopback("127.0.0.1") and is_loopback("[::1]") and is_loopback("localhost")
    assert is_loopback("127.1.2.3") and is_loopback("LOCALHOST") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2")
    # DNS names anyone can point at 127.0.0.1 (or elsewhere): not loopback
    for name in ("127.evil.com", "127.0.0.1.nip.io", "localhost.evil.com", "127.0.0.1.", ""):
        assert not is_loopback(name), name
    # on the network a token must carry 128 bits: 22 characters of a random URL-safe token
    with pytest.raises(ValueError, match="at least 22 characters for a console on the network"):
        check_token("x" * 21, network=True)
    assert check_token("x" * 22, network=True) == "x" * 22


@pytest.mark.parametrize("host", ["127.evil.com", "127.0.0.1.nip.io", "localhost.evil.com"])
def test_without_a_token_rebinding_names_are_refused(tmp_path, host) -> None:
    with TestClient(console_app(tmp_path, token=None), base_url="http://127.0.0.1:8000") as c:
        r = c.get("/api/status", headers={"Host": f"{host}:8000"})
        assert r.status_code == 403 and "not loopback" in r.json()["detail"]
        for path in ("/stream", "/console"):
            with pytest.raises(WebSocketDisconnect) as refused:
                with c.websocket_connect(path, headers={"Host": f"{host}:8000"}):
                    pass
            assert refused.value.code == 1008
        assert c.get("/api/status", headers={"Host": "127.0.0.1:8000"}).status_code == 200


@pytest.mark.parametrize("path", ["/%2F%2Fevil.com", "//evil.com", "/%5Cevil.com", "/%09/evil.com"])
def test_token_redirects_stay_on_the_console(client, path) -> None:
    r = client.get(f"{path}?token={TOKEN}", headers={"Sec-Fetch-Mode": "navigate"})
    assert r.status_code == 303
    assert r.headers["location"] == "/"


def test_wrong_tokens_slow_the_client_down(client) -> None:
    assert client.get(f"/api/status?token={TOKEN}").status_code == 200
    signed_in = dict(client.cookies)
    client.cookies.clear()
    wrong = {"Authorization": "token wrong-token-0123456"}
    for _ in range(5):  # FAILURES_BEFORE_THROTTLE: the fifth starts a 1 s wait
        assert client.get("/api/status", headers=wrong).status_code == 401
    assert client.get("/api/status", headers=wrong).status_code == 429
    r = client.get("/api/status", headers=AUTH)  # even the right token waits its turn
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    assert "too many wrong tokens" in r.json()["detail"]
    r = client.post("/login", data={"token": TOKEN, "next": "/"})
    assert r.status_code == 429 and "Too many wrong tokens" in r.text
    # a session cookie is not a token attempt: a signed-in browser is not held up
    client.cookies.update(signed_in)
    assert client.get("/api/status").status_code == 200


def test_sign_in_throttle_backs_off_and_forgets_on_success() -> None:
    now = [0.0]
    t = SignInThrottle(clock=lambda: now[0])
    for _ in range(4):
        t.failed("a")
    assert t.wait_s("a") == 0.0  # four failures: no wait yet
    t.failed("a")
    assert t.wait_s("a") == 1.0 and t.wait_s("b") == 0.0  # per address
    t.failed("a")
    assert t.wait_s("a") == 2.0
    for _ in range(20):
        t.failed("a")
    assert t.wait_s("a") == 60.0  # MAX_BACKOFF_S
    now[0] += 60.0
    assert t.wait_s("a") == 0.0
    t.succeeded("a")
    t.failed("a")
    assert t.wait_s("a") == 0.0  # forgotten: counting starts again


# -- trifuse serve ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--host", "0.0.0.0", "--no-token"], "refusing to serve without a token"),
        (["--host", "192.168.7.7", "--no-token"], "non-loopback"),
        (["--token", "short"], "at least 16 characters"),
        (["--host", "0.0.0.0", "--token", "x" * 16], "at least 22 characters"),
        (["--token", TOKEN, "--no-token"], "exclude each other"),
        (["--certfile", "cert.pem"], "go together"),
        (["--certfile", "missing.pem", "--keyfile", "missing.pem"], "cannot use"),
        (["--allow-origin", "evil.example"], "scheme://host"),
    ],
)
def test_serve_refuses_unsafe_or_broken_settings(args, message, tmp_path, capsys) -> None:
    assert main(["serve", "--workdir", str(tmp_path / "w"), *args]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "w").exists()  # refused before anything was created


def test_serve_refuses_a_short_token_from_the_environment(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setenv("TRIFUSE_TOKEN", "short")
    assert main(["serve", "--workdir", str(tmp_path / "w")]) == 2
    assert "TRIFUSE_TOKEN: the token must have at least 16" in capsys.readouterr().err


@pytest.fixture(scope="module")
def certificate(tmp_path_factory) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 (openssl; .ci/run installs it)."""
    if shutil.which("openssl") is None:
        pytest.skip("the TLS test needs the openssl command")
    d = tmp_path_factory.mktemp("tls")
    cert, key = d / "cert.pem", d / "key.pem"
    subprocess.run(
        [
            *("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2"),
            *("-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1"),
            *("-keyout", str(key), "-out", str(cert)),
        ],
        check=True,
        capture_output=True,
    )
    return cert, key


@pytest.mark.slow
def test_serve_over_tls_with_a_token_from_the_environment(certificate, tmp_path) -> None:
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    cert, key = certificate
    args = ["--workdir", str(tmp_path / "w"), "--certfile", str(cert), "--keyfile", str(key)]
    proc, console = start_console(args, env={**os.environ, "TRIFUSE_TOKEN": TOKEN})
    tls = ssl.create_default_context(cafile=str(cert))
    base = console.url
    port = base.rsplit(":", 1)[1]
    try:
        assert base.startswith("https://") and console.token == TOKEN
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(base + "/api/status", context=tls, timeout=5)
        assert refused.value.code == 401
        req = urllib.request.Request(
            base + "/api/status", headers={"Authorization": f"token {TOKEN}"}
        )
        with urllib.request.urlopen(req, context=tls, timeout=5) as r:
            assert "viewers" in json.loads(r.read())
        # the browser's exchange: a Secure cookie
        nav = urllib.request.Request(f"{base}/?token={TOKEN}", headers={"Accept": "text/html"})
        opener = urllib.request.build_opener(
            urllib.request.HTTPSHandler(context=tls), _NoRedirect()
        )
        with pytest.raises(urllib.error.HTTPError) as redirect:
            opener.open(nav, timeout=5)
        assert redirect.value.code == 303
        assert "Secure" in redirect.value.headers["set-cookie"]
        wss = f"wss://127.0.0.1:{port}/stream"
        with pytest.raises(InvalidStatus) as hijack:
            connect(wss, ssl=tls, additional_headers={**AUTH, "Origin": FOREIGN}, proxy=None)
        assert hijack.value.response.status_code == 403
        with connect(wss, ssl=tls, additional_headers=AUTH, proxy=None) as ws:
            meta = json.loads(ws.recv(timeout=60))
            assert "seq" in meta
    finally:
        stop_process(proc)


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args, **kwargs):
        return None


def test_push_driver_without_the_token_stops_with_a_message(tmp_path, capsys) -> None:
    from trifuse.app.drivers import push_sim

    with serve(console_app(tmp_path)) as port:
        url = f"ws://127.0.0.1:{port}/ingest"
        args = ["--url", url, "--sensors", "tof", "--frames", "1", "--quiet"]
        assert push_sim.main([*args, "--token", "wrong-token-0123456"]) == 2
        assert "wrong --token" in capsys.readouterr().err
        assert push_sim.main([*args, "--token", TOKEN]) == 0
