"""Viser's console served and relayed by FastAPI under /console/ (no browser needed)."""

from __future__ import annotations

import viser
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.server.viser_bridge import make_viser_router


def test_console_page_and_websocket_relay() -> None:
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        server.scene.add_box("box", color=(255, 0, 0), dimensions=(1.0, 1.0, 1.0))
        app = FastAPI()
        app.include_router(make_viser_router(server.get_port()))
        client = TestClient(app)
        page = client.get("/console/")
        assert page.status_code == 200 and page.content.startswith(b"<!doctype html>")
        assert client.get("/console", follow_redirects=False).status_code == 307
        protocol = f"viser-v{viser.__version__}"
        with client.websocket_connect("/console", subprotocols=[protocol]) as ws:
            assert ws.accepted_subprotocol == protocol
            first = ws.receive_bytes()  # the server's opening messages (msgpack)
            assert len(first) > 0
    finally:
        server.stop()
