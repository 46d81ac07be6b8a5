"""Viser's console served and relayed by FastAPI under /console/ (no browser needed), and
Viser's own loopback port closed to everyone but the relay (viser_bridge.py)."""

from __future__ import annotations

import contextlib
import socket
import threading
import urllib.error
import urllib.request

import msgspec
import pytest
import uvicorn
import viser
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect
from viser._messages import FileTransferPart, FileTransferStartUpload

from tests.browser_support import needs_chromium
from tests.support import direct_websocket, wait_until
from trifuse.app.server.panels import rig_files
from trifuse.app.server.routers.viser_bridge import (
    MAX_UPLOAD_BYTES,
    RELAY_HEADER,
    UploadGate,
    UploadRefused,
    make_viser_router,
    start_guarded_viser,
)

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


@pytest.mark.slow  # starts a console: about 6 s
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


# -- uploads (issue 29): refused in the relay before Viser buffers them ---------------------


BUTTON = "button"
CHUNK = 512 * 1024  # Viser's client's part size


def start(uuid: str, size: int, parts: int, name: str = "rig.yaml", button: str = BUTTON) -> bytes:
    """A FileTransferStartUpload as Viser's client sends it (msgpack)."""
    return msgspec.msgpack.encode(
        {
            "type": "FileTransferStartUpload",
            "source_component_uuid": button,
            "transfer_uuid": uuid,
            "filename": name,
            "mime_type": "",
            "part_count": parts,
            "size_bytes": size,
        }
    )


def part(uuid: str, index: int, content: bytes, button: str = BUTTON) -> bytes:
    return msgspec.msgpack.encode(
        {
            "type": "FileTransferPart",
            "source_component_uuid": button,
            "transfer_uuid": uuid,
            "part_index": index,
            "content": content,
        }
    )


CAMERA = msgspec.msgpack.encode(
    {
        "type": "ViewerCameraMessage",
        "wxyz": [1.0, 0.0, 0.0, 0.0],
        "position": [0.0, 0.0, -3.0],
        "fov": 1.0,
        "near": 0.01,
        "far": 100.0,
        "image_height": 480,
        "image_width": 640,
        "look_at": [0.0, 0.0, 0.0],
        "up_direction": [0.0, -1.0, 0.0],
    }
)
"""The first message of Viser's client: Viser counts a client as connected from then on
(and delivers uploads only to connected clients)."""


def refusal(gate: UploadGate, owner: object, data: bytes) -> tuple[int, str] | None:
    try:
        gate.check(owner, data)
    except UploadRefused as exc:
        return exc.code, str(exc)
    return None


def test_the_upload_gate_passes_uploads_within_the_caps_and_nothing_else() -> None:
    gate, a, b = UploadGate(), object(), object()
    body = bytes(range(256)) * 4096  # 1 MiB
    assert refusal(gate, a, start("t1", len(body), 2)) is None
    assert gate.in_flight_bytes == len(body)
    assert refusal(gate, b, part("t1", 0, body[:CHUNK]))[0] == 1008  # not b's upload
    assert refusal(gate, a, part("t1", 0, body[:CHUNK])) is None
    assert refusal(gate, a, part("t1", 0, body[:CHUNK]))[0] == 1008  # the same part again
    assert refusal(gate, a, part("t1", 2, b"x"))[0] == 1008  # no such part
    assert refusal(gate, a, part("t1", 1, body[CHUNK:])) is None
    assert gate.in_flight_bytes == 0  # complete: forgotten
    # declared sizes and counts
    assert refusal(gate, a, start("t2", MAX_UPLOAD_BYTES + 1, 9)) == (
        1009,
        f"upload of {MAX_UPLOAD_BYTES + 1} bytes refused: at most {MAX_UPLOAD_BYTES}",
    )
    assert refusal(gate, a, start("t2", 100, 10**9))[0] == 1008  # a billion empty parts
    assert refusal(gate, a, start("t2", -1, 1))[0] == 1008
    assert refusal(gate, a, start("t2", 10, 1, name="x" * 5000))[0] == 1008
    assert refusal(gate, a, start("t0", 0, 0)) is None  # an empty file: Viser finishes it
    # more bytes than declared
    assert refusal(gate, a, start("t3", 10, 2)) is None
    assert refusal(gate, a, part("t3", 0, bytes(8))) is None
    assert refusal(gate, a, part("t3", 1, bytes(8)))[0] == 1009
    # the budget over all connections, released when a connection closes
    gate.forget(a)
    for i in range(4):
        assert refusal(gate, b, start(f"u{i}", MAX_UPLOAD_BYTES, 8)) is None
    assert refusal(gate, a, start("u4", 1, 1))[0] == 1013
    gate.forget(b)
    assert gate.in_flight_bytes == 0 and refusal(gate, a, start("u4", 1, 1)) is None
    # other messages pass without being decoded
    assert refusal(gate, a, b"\xc1 not msgpack") is None
    assert refusal(gate, a, msgspec.msgpack.encode({"type": "GuiUpdateMessage"})) is None


def test_rig_files_fit_under_the_relays_upload_cap() -> None:
    assert rig_files.MAX_UPLOAD_BYTES <= MAX_UPLOAD_BYTES


def test_the_relay_refuses_an_oversized_upload_before_viser_buffers_it(guarded) -> None:
    """Through the relay: a 600 kB file in two parts arrives whole; a start declaring
    5 MiB closes the connection (1009, with the reason) and Viser never sees it; parts
    beyond the declared size close it too, with Viser holding no more than declared."""
    server, secret = guarded
    button = server.gui.add_upload_button("Import")
    uuid = button._impl.uuid
    received: list[bytes] = []
    button.on_upload(lambda e: received.append(e.target.value.content))
    starts: list[int] = []  # what Viser itself receives
    parts: list[tuple[str, int, int]] = []
    server._websock_server.register_handler(
        FileTransferStartUpload, lambda _client, m: starts.append(m.size_bytes)
    )
    server._websock_server.register_handler(
        FileTransferPart,
        lambda _client, m: parts.append((m.transfer_uuid, m.part_index, len(m.content))),
    )
    buffered = server.gui._current_file_upload_states
    app = FastAPI()
    app.include_router(make_viser_router(server.get_port(), secret))
    client = TestClient(app)

    def connected(ws) -> None:
        ws.send_bytes(CAMERA)
        wait_until(server.get_clients, "Viser to count the client as connected")

    def closed_with(ws) -> tuple[int, str]:
        """The code and reason the relay closed ``ws`` with (once Viser lost the relay's
        side of it)."""
        wait_until(lambda: not server.get_clients(), "the relay to close the connection")
        with pytest.raises(WebSocketDisconnect) as closed:
            while True:
                ws.receive_bytes()
        return closed.value.code, closed.value.reason

    body = bytes(range(256)) * 2400  # 614,400 bytes
    with client.websocket_connect("/console", subprotocols=[PROTOCOL]) as ws:
        connected(ws)
        ws.send_bytes(start("ok", len(body), 2, button=uuid))
        ws.send_bytes(part("ok", 0, body[:CHUNK], button=uuid))
        ws.send_bytes(part("ok", 1, body[CHUNK:], button=uuid))
        wait_until(lambda: received, "the upload")
    assert received == [body] and starts == [len(body)]
    wait_until(lambda: not server.get_clients(), "the first connection to close")

    with client.websocket_connect("/console", subprotocols=[PROTOCOL]) as ws:
        connected(ws)
        ws.send_bytes(start("big", 5 << 20, 10, button=uuid))
        for i in range(10):
            with contextlib.suppress(WebSocketDisconnect):
                ws.send_bytes(part("big", i, bytes(CHUNK), button=uuid))
        assert closed_with(ws) == (1009, "upload of 5242880 bytes refused: at most 4194304")
    assert starts == [len(body)] and len(parts) == 2 and not buffered  # Viser saw none of it

    with client.websocket_connect("/console", subprotocols=[PROTOCOL]) as ws:
        connected(ws)
        ws.send_bytes(start("liar", CHUNK, 4, button=uuid))
        ws.send_bytes(part("liar", 0, bytes(CHUNK), button=uuid))
        ws.send_bytes(part("liar", 1, bytes(CHUNK), button=uuid))  # beyond the declared size
        assert closed_with(ws) == (1009, "upload: more than the 524288 bytes declared")
    assert starts == [len(body), CHUNK] and parts[2:] == [("liar", 0, CHUNK)]
    assert not buffered and received == [body]  # dropped with the connection


@needs_chromium
@pytest.mark.slow
def test_viser_client_uploads_pass_the_relay_and_oversized_ones_do_not(guarded, browser) -> None:
    """Viser's own client in Chromium, through the relay served by uvicorn: a 600 kB file
    arrives whole (the gate reads the client's real messages right); a 5 MiB file is
    refused at its start, and Viser never sees it."""
    server, secret = guarded
    button = server.gui.add_upload_button("Import")
    received: list[tuple[str, int]] = []
    button.on_upload(lambda e: received.append((e.target.value.name, len(e.target.value.content))))
    starts: list[int] = []
    server._websock_server.register_handler(
        FileTransferStartUpload, lambda _client, m: starts.append(m.size_bytes)
    )
    app = FastAPI()
    app.include_router(make_viser_router(server.get_port(), secret))
    sock = socket.create_server(("127.0.0.1", 0))
    web = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=web.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{sock.getsockname()[1]}/console/")
        page.get_by_text("Import").wait_for()
        first = set(wait_until(server.get_clients, "the browser to connect"))
        page.set_input_files("input[type=file]", files=[
            {"name": "rig.yaml", "mimeType": "text/plain", "buffer": bytes(614_400)}
        ])  # fmt: skip
        wait_until(lambda: received, "the upload")
        assert received == [("rig.yaml", 614_400)] and starts == [614_400]
        page.set_input_files("input[type=file]", files=[
            {"name": "big.yaml", "mimeType": "text/plain", "buffer": bytes(5 << 20)}
        ])  # fmt: skip
        # the relay closes the page's connection; Viser's client connects again
        wait_until(lambda: not first & set(server.get_clients()), "the relay to close it")
        wait_until(server.get_clients, "the browser to connect again")
        page.close()
    finally:
        web.should_exit = True
        thread.join(timeout=30)
    assert starts == [614_400] and received == [("rig.yaml", 614_400)]
