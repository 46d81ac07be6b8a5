"""The pictures a benchmark compares with what a viewer shows: the hub keeps the last N
with ``TRIFUSE_BENCH_KEEP_FRAMES`` and ``/api/stream/frame/{seq}.png`` returns them; and the
link benchmark's figures of the frames a page drew (app/devtools/bench_link.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from trifuse.app.devtools.bench_link import draw_figures
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime.kept_frames import ENV, KeptFrames
from trifuse.app.server.runtime.stream import FrameHub


def _picture(value: int) -> np.ndarray:
    bgr = np.full((6, 8, 3), value, np.uint8)
    bgr[0, 0] = (1, 2, 3)  # B, G, R: the PNG keeps the channel order
    bgr.flags.writeable = False
    return bgr


def test_off_without_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV, raising=False)
    hub = FrameHub()
    assert hub.kept is None
    hub.publish(b"jpeg", {}, bgr=_picture(5))
    client = TestClient(create_app(hub))
    r = client.get("/api/stream/frame/1.png")
    assert r.status_code == 404 and ENV in r.json()["detail"]


def test_the_last_pictures_by_seq(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV, "3")
    hub = FrameHub()
    assert hub.kept is not None
    for value in range(10, 15):  # seq 1..5
        hub.publish(b"jpeg", {}, bgr=_picture(value))
    hub.publish(b"jpeg", {}, new=False)  # seq 6: no picture, nothing kept
    client = TestClient(create_app(hub))
    for seq in (1, 2, 6, 99):
        assert client.get(f"/api/stream/frame/{seq}.png").status_code == 404
    for seq, value in ((3, 12), (5, 14)):
        r = client.get(f"/api/stream/frame/{seq}.png")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        got = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(got, _picture(value))


@pytest.mark.parametrize("value", ["0", "lots", "5000"])
def test_bad_values_are_refused(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv(ENV, value)
    with pytest.raises(ValueError, match=ENV):
        KeptFrames.from_env()


def test_draw_figures() -> None:
    # 25 fps for 2 s, then nothing for 1.5 s, then 10 fps; latencies 100 ms, one of 400
    draws = [[1000 + 40 * i, 100.0, 50.0, i] for i in range(50)]
    draws += [[4500 + 100 * i, 100.0, 50.0, 100 + i] for i in range(15)]
    draws[10][1] = 400.0
    f = draw_figures(draws, 1000, 6000)
    assert f["fps"] == 10  # per second: 25, 25, 0, 5, 10 (one window in the gap)
    assert f["latency_ms"] == 100 and f["latency_p95_ms"] == 100 and f["send_latency_ms"] == 50
    assert f["longest_stall_ms"] == pytest.approx(4500 - 2960)
    assert f["stall_ms"] == pytest.approx(4500 - 2960)
    empty = draw_figures([], 0, 3000)
    assert empty["fps"] == 0 and empty["longest_stall_ms"] == 3000
    assert math.isnan(empty["latency_ms"])
