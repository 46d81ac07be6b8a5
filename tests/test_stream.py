"""The stereo stream: the newest frame to every viewer, never a queue."""

from __future__ import annotations

import json

import cv2
import numpy as np
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.server.stream import FrameHub, make_stream_router


def _jpeg(k: int) -> bytes:
    img = np.full((16, 32, 3), k % 256, np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def test_slow_viewer_gets_the_newest_frame_not_a_backlog() -> None:
    """A viewer that has not acknowledged its frame gets nothing; once it does, it gets
    the newest frame published meanwhile, not the next in line."""
    hub = FrameHub()
    app = FastAPI()
    app.include_router(make_stream_router(hub))
    with TestClient(app) as client, client.websocket_connect("/stream") as ws:
        hub.publish(_jpeg(1), {"k": 1})
        assert json.loads(ws.receive_text())["k"] == 1
        jpeg = ws.receive_bytes()
        assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) is not None
        for k in range(2, 21):  # the viewer is busy: 19 frames go by
            hub.publish(_jpeg(k), {"k": k})
        ws.send_text("ack")
        assert json.loads(ws.receive_text())["k"] == 20
        ws.receive_bytes()
        assert hub.viewers == 1


def test_mjpeg_fallback_streams_jpeg_parts() -> None:
    hub = FrameHub()
    hub.publish(_jpeg(1), {})
    app = FastAPI()
    app.include_router(make_stream_router(hub))
    with TestClient(app) as client, client.stream("GET", "/stream.mjpg") as resp:
        assert resp.headers["content-type"].startswith("multipart/x-mixed-replace")
        chunk = b""
        for part in resp.iter_bytes():
            chunk += part
            if b"\xff\xd9" in chunk:
                break
        assert b"Content-Type: image/jpeg" in chunk and b"\xff\xd8" in chunk
