"""Viser's console served and relayed by FastAPI under /console/ (no browser needed), and
Viser's own loopback port closed to everyone but the relay (viser_bridge.py)."""

from __future__ import annotations

import urllib.error
import urllib.request

import pytest
import viser
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.server.routers.viser_bridge import RELAY_HEADER, make_viser_router, start_guarded_viser
from tests.support import direct_websocket

PROTOCOL = f"viser-v{viser.__version__}"


@pytest.fixture
def guarded():
    server, secret = start_guarded_viser()
    try:
        server.scene.add_box("box", color=(255, 0, 0), dimensions=(1.0, 1.0, 1.0))
        yield server, secret
    finally:
        server.stop()


def test_console_page_and_websocket_relay(guarded) -> None:
    server, secret = guarded
    app = FastAPI()
    app.include_router(make_viser_router(server.get_port(), secret))
    client = TestClient(app)
    page = client.get("/console/")
    assert page.status_code == 200 and page.content.startswith(b"<!doctype html>")
    assert client.get("/console", follow_redirects=False).status_code == 307
    with client.websocket_connect("/console", subprotocols=[PROTOCOL]) as ws:
        assert ws.accepted_subprotocol == PROTOCOL
        first = ws.receive_bytes()  # the server's opening messages (msgpack)
        assert len(first) > 0


def test_viser_port_refuses_everyone_but_the_relay(guarded) -> None:
    server, secret = guarded
    port = server.get_port()
    # what the issue found open: no secret, a foreign Origin; also no Origin, a wrong secret
    assert direct_websocket(port, {"Origin": "http://evil.com"}) == 403
    assert direct_websocket(port, {}) == 403
    assert direct_websocket(port, {RELAY_HEADER: "guess-" + secret[6:]}) == 403
    # a browser (it always sends Origin) is refused even with the secret
    assert (
        direct_websocket(port, {RELAY_HEADER: secret, "Origin": f"http://127.0.0.1:{port}"}) == 403
    )
    assert direct_websocket(port, {RELAY_HEADER: secret}) is None  # the relay
    with pytest.raises(urllib.error.HTTPError) as refused:  # the client page over HTTP too
        urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10)
    assert refused.value.code == 403
