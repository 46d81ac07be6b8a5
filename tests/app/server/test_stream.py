"""The stereo stream: the newest frame to every viewer, never a queue; the stream's rates
(frames published, new pictures) and what each frame's metadata carries for the viewer's
colour scale (palette, span)."""

from __future__ import annotations

import json
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from tests.support import FakeClock, small_rig, synth_frame
from trifuse.app.server.panels.source import stream_text
from trifuse.app.server.routers.stream_routes import make_stream_router
from trifuse.app.server.runtime import stream as stream_mod
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.rates import RatesSnapshot, StreamRates
from trifuse.app.server.runtime.stream import MAX_MESSAGE_CHARS, FrameHub
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.palettes import palette

RIG = small_rig()


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


def test_an_ack_may_be_binary_but_not_huge() -> None:
    """Any small message acknowledges a frame, text or binary; one over
    MAX_MESSAGE_CHARS (16 MiB here) closes the socket with 1009 and its reason."""
    hub = FrameHub()
    app = FastAPI()
    app.include_router(make_stream_router(hub))
    with TestClient(app) as client, client.websocket_connect("/stream") as ws:
        hub.publish(_jpeg(1), {"k": 1})
        assert json.loads(ws.receive_text())["k"] == 1
        ws.receive_bytes()
        ws.send_bytes(b"ack")
        hub.publish(_jpeg(2), {"k": 2})
        assert json.loads(ws.receive_text())["k"] == 2
        ws.receive_bytes()
        ws.send_text("a" * (16 << 20))
        message = ws.receive()
        assert message["type"] == "websocket.close" and message["code"] == 1009
        assert f"at most {MAX_MESSAGE_CHARS}" in message["reason"]
    assert hub.viewers == 0


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


def test_a_picture_is_encoded_for_jpeg_viewers_once_when_first_taken(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A picture published as itself (BGR) is not encoded until a JPEG viewer takes it;
    then once, at the hub's quality, for every JPEG viewer and for the frames that publish
    it again; a JPEG given by the producer goes out as it is."""
    encoded: list[int] = []

    def counting(bgr: np.ndarray, quality: int) -> bytes:
        encoded.append(quality)
        return cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()

    monkeypatch.setattr(stream_mod, "encode_jpeg", counting)
    hub = FrameHub()
    hub.jpeg_quality = 90

    def picture(value: int) -> np.ndarray:
        bgr = np.full((16, 32, 3), value, np.uint8)
        bgr.flags.writeable = False
        return bgr

    def shown(jpeg: bytes) -> int:
        return int(cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[8, 16, 0])

    first = hub.publish(None, {"k": 1}, bgr=picture(40))
    assert encoded == [] and first.made_jpeg == [None]  # nobody asked for a JPEG
    app = FastAPI()
    app.include_router(make_stream_router(hub))
    with TestClient(app) as client:
        with client.websocket_connect("/stream") as a, client.websocket_connect("/stream") as b:
            for ws in (a, b):
                assert json.loads(ws.receive_text())["k"] == 1
                assert abs(shown(ws.receive_bytes()) - 40) <= 2
                ws.send_text("ack")
            again = hub.publish_again({"k": 2})  # the same picture, new metadata
            assert again is not None and again.bgr is first.bgr and again.meta is not first.meta
            for ws in (a, b):
                assert json.loads(ws.receive_text())["k"] == 2
                assert ws.receive_bytes() == first.made_jpeg[0].result()
                ws.send_text("ack")
            assert encoded == [90]  # once, for two viewers and two frames
            hub.publish(_jpeg(3), {"k": 3})
            for ws in (a, b):
                assert json.loads(ws.receive_text())["k"] == 3
                assert ws.receive_bytes() == _jpeg(3)
    assert encoded == [90] and hub.viewers == 0


# -- the stream's rates ----------------------------------------------------------------------


def test_stream_rates_over_a_sliding_window_taken_at_whole_seconds() -> None:
    clock = FakeClock(100.0)
    rates = StreamRates(window_s=3.0, clock=clock, wall_ns=clock.wall_ns)
    assert rates.snapshot().stream_fps == 0.0  # nothing yet
    for k in range(135):  # 30 frames/s for 4.5 s, every 10th a new picture
        clock.now = 100.0 + k / 30
        rates.tick(new=k % 10 == 0)
    clock.now = 104.6
    snap = rates.snapshot()
    # the window (101, 104]: frames k = 31..120, new pictures k = 40, 50, ..., 120
    assert snap.stream_fps == pytest.approx(90 / 3) and snap.new_fps == pytest.approx(9 / 3)
    assert snap.repeat_fps == pytest.approx(27.0)
    assert snap.at_ns == round((1e9 + 104.0) * 1e9)  # the window's end, wall clock
    rates.tick(new=True)  # a frame in the same second: the figures stay those of 104 s
    clock.now = 104.99
    assert rates.snapshot() == snap
    clock.now = 105.0  # the next second
    assert rates.snapshot().at_ns == snap.at_ns + 1_000_000_000
    clock.now = 108.2  # stalled since 104.6: the window (105, 108] is empty
    assert rates.snapshot().stream_fps == 0.0 and rates.snapshot().new_fps == 0.0


def test_stream_rates_right_after_the_first_frame_use_the_time_since() -> None:
    clock = FakeClock(50.0)
    rates = StreamRates(window_s=3.0, clock=clock, wall_ns=clock.wall_ns)
    for k in range(16):  # 10 frames/s from 50.0 s to 51.5 s, all new
        clock.now = 50.0 + k / 10
        rates.tick(new=True)
    snap = rates.snapshot()  # at 51 s: 11 frames over the 1 s since the first, not over 3 s
    assert snap.stream_fps == pytest.approx(11.0) and snap.new_fps == pytest.approx(11.0)


def test_stream_rates_refuse_a_bad_window() -> None:
    for bad in (0, -1.0, float("nan"), "3"):
        with pytest.raises(ValueError, match="window_s: expected a positive number"):
            StreamRates(window_s=bad)  # type: ignore[arg-type]


def test_each_frame_carries_the_rates_readers_see() -> None:
    """The viewer's figures (a frame's metadata) are the ones the panel and status read."""
    clock = FakeClock(100.0)
    hub = FrameHub()
    hub.rates = StreamRates(clock=clock, wall_ns=clock.wall_ns)
    app = FastAPI()
    app.include_router(make_stream_router(hub))
    with TestClient(app) as client, client.websocket_connect("/stream") as ws:
        for k in range(60):  # 20 frames/s for 3 s, one new picture a second
            clock.now = 100.0 + k / 20
            hub.publish(_jpeg(k), {"k": k}, new=k % 20 == 0)
        clock.now = 103.2
        hub.publish(_jpeg(60), {"k": 60}, new=False)
        meta = json.loads(ws.receive_text())
        while meta["k"] != 60:  # the newest frame once acknowledged
            ws.receive_bytes()
            ws.send_text("ack")
            meta = json.loads(ws.receive_text())
        ws.receive_bytes()
    assert meta["rates"] == hub.rates.snapshot().as_dict()
    # the window (100, 103]: frames 1..59, new pictures 20 and 40
    assert meta["rates"]["stream_fps"] == pytest.approx(59 / 3, abs=0.01)
    assert meta["rates"]["new_fps"] == pytest.approx(2 / 3, abs=0.01)
    assert meta["rates"]["window_s"] == 3.0


# -- the colour scale's metadata -------------------------------------------------------------


class _Sets(FrameSource):
    """Frame sets of the small rig at 10 Hz; ``same`` repeats the first set's (read-only)
    images with new time stamps, as the simulated head does for one pose."""

    def __init__(self, n: int, same: bool = False) -> None:
        self.sensors = list(RIG.names)
        rng = np.random.default_rng(3)
        first = {s: synth_frame(RIG, s, 1_000_000_000, rng) for s in RIG.names}
        for f in first.values():
            for a in (f.image, f.distance_m):
                if a is not None:
                    a.flags.writeable = False
        self._frames = []
        for k in range(n):
            t = 1_000_000_000 + k * 100_000_000
            for s in RIG.names:
                f = first[s] if same else synth_frame(RIG, s, t, rng)
                self._frames.append(Frame(s, t, f.image, f.distance_m))

    def frames(self) -> Iterator[Frame]:
        yield from self._frames


def _run(
    source: FrameSource, settings: DisplaySettings, hub: FrameHub | None = None
) -> tuple[FusionPipeline, FrameHub]:
    hub = hub or FrameHub()
    pipeline = FusionPipeline(source, RIG, hub, settings).start()
    pipeline.join(60)
    pipeline.stop()
    assert pipeline.join(0) and pipeline.status.error is None
    assert hub.latest is not None
    json.dumps(hub.latest.meta)  # JSON-able as sent
    return pipeline, hub


def test_metadata_carries_the_palette_and_a_manual_span() -> None:
    settings = DisplaySettings(mode="blend", palette="rainbow", span_k=(290.0, 310.0))
    _, hub = _run(_Sets(4), settings)
    meta = hub.latest.meta
    assert meta["palette"] == "rainbow" and meta["span_k"] == [290.0, 310.0]
    assert meta["span_auto"] is False
    rgb = np.frombuffer(bytes.fromhex(meta["palette_rgb"]), np.uint8).reshape(256, 3)
    assert np.array_equal(rgb, palette("rainbow"))  # cold end first, as the picture uses it


def test_metadata_carries_the_automatic_span_the_picture_was_coloured_with() -> None:
    pipeline, hub = _run(_Sets(4), DisplaySettings(mode="thermal", palette="iron"))
    meta = hub.latest.meta
    assert meta["palette"] == "iron" and meta["span_auto"] is True
    assert meta["span_k"] == list(pipeline.fusion.span_k)
    low, high = meta["span_k"]
    assert 285.0 < low < high < 315.0  # the synthetic scene spans 290-310 K (+ noise, blur)
    assert np.array_equal(
        np.frombuffer(bytes.fromhex(meta["palette_rgb"]), np.uint8).reshape(256, 3),
        palette("iron"),
    )


@pytest.mark.parametrize(
    "settings",
    [
        DisplaySettings(mode="color"),
        DisplaySettings(mode="blend", opacity=0.0),
        DisplaySettings(mode="isotherm", isotherm_color=(0, 255, 0)),
    ],
    ids=["color", "blend-opacity-0", "isotherm-fixed-colour"],
)
def test_no_colour_scale_when_the_picture_shows_no_palette(settings: DisplaySettings) -> None:
    _, hub = _run(_Sets(3), settings)
    meta = hub.latest.meta
    assert meta["palette"] is None and meta["palette_rgb"] is None and meta["span_k"] is None
    assert meta["mode"] == settings.mode


def test_repeated_pictures_are_counted_apart_from_new_ones() -> None:
    """The same read-only images again: published again, not fused again, and the stream's
    rates say so."""
    settings = DisplaySettings(span_k=(290.0, 310.0))  # a fixed span is settled at once
    clock = FakeClock(100.5)  # every frame is published at 100.5 s
    hub = FrameHub()
    hub.rates = StreamRates(clock=clock, wall_ns=clock.wall_ns)
    pipeline, hub = _run(_Sets(12, same=True), settings, hub)
    st = pipeline.status
    assert st.frames_out >= 10 and st.pictures_out == 1
    clock.now = 101.0
    snap = hub.rates.snapshot()  # everything published in the 0.5 s since the first frame
    assert snap.stream_fps == pytest.approx(st.frames_out / 0.5)
    assert snap.new_fps == pytest.approx(1 / 0.5)
    assert hub.latest.meta["palette"] == "iron" and hub.latest.meta["span_k"] == [290.0, 310.0]


def test_the_source_panel_says_what_each_rate_counts() -> None:
    snap = RatesSnapshot(at_ns=0, window_s=3.0, stream_fps=29.7, new_fps=0.7)
    text = stream_text(snap, "simulated", False, frames_out=900, pictures_out=21)
    assert text.startswith("Fused: **0.7 fps** new pictures, stream **29.7 fps** (last 3 s;")
    assert "21 new of 900 frames" in text
    assert "29.0 fps repeat the previous picture: the simulated head holds each" in text
    live = stream_text(snap, "live", False, 900, 21)
    assert "repeat the previous picture: their input did not change" in live
    fresh = RatesSnapshot(at_ns=0, window_s=3.0, stream_fps=30.0, new_fps=30.0)
    assert "repeat" not in stream_text(fresh, "live", False, 900, 900)
    assert stream_text(snap, "replay", True, 900, 21).startswith("Fused: **paused**")
