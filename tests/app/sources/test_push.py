"""Push ingest: the protocol, the WebSocket endpoint (uvicorn on 127.0.0.1), the clients and
the example driver."""

from __future__ import annotations

import asyncio
import json
import re
import socket
import struct
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np
import pytest
from fastapi import FastAPI
from websockets.exceptions import ConnectionClosedError, InvalidStatus
from websockets.sync.client import connect

from tests.support import serve, wait_until
from trifuse.app.drivers import push_sim
from trifuse.app.server.middleware.auth import AuthConfig, AuthMiddleware
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.clients import AsyncPushClient, PushClient, PushRejected
from trifuse.app.sources.push.encode import encode_frame, encode_part
from trifuse.app.sources.push.protocol import MAGIC, Part, PushError, encode_message
from trifuse.app.sources.push.router import make_push_router, uvicorn_ws_max_size
from trifuse.app.sources.push.source import PushSource
from trifuse.app.sources.sim.head import default_rig

RIG = default_rig()
LIMIT = 1 << 20  # 1 MiB message limit in these tests


@contextmanager
def console(source: PushSource, **router_kwargs) -> Iterator[str]:
    app = FastAPI()
    app.include_router(make_push_router(source, **router_kwargs))
    with serve(app, ws_max_size=uvicorn_ws_max_size(source)) as port:
        yield f"ws://127.0.0.1:{port}/ingest"


@pytest.fixture
def source() -> Iterator[PushSource]:
    src = PushSource(RIG, max_message_bytes=LIMIT)
    yield src
    src.close()


def smooth_rgb(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth colour image (JPEG-friendly) with some texture."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 32, w // 32, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def counts_to_values(counts: np.ndarray, scale: float, zero_invalid: bool) -> np.ndarray:
    values = (counts.astype(np.float64) * scale).astype(np.float32)
    if zero_invalid:
        values[counts == 0] = np.nan
    return values


# -- round trips ----------------------------------------------------------------------------


def test_frames_arrive_exact_16bit_and_jpeg_close(source):
    rng = np.random.default_rng(7)
    thermal_counts = rng.integers(0, 65536, (288, 382), dtype=np.uint16)
    thermal_counts[0, :3] = 0
    amp_counts = rng.integers(0, 65536, (144, 176), dtype=np.uint16)
    dist_counts = rng.integers(0, 10001, (144, 176), dtype=np.uint16)
    colour = smooth_rgb(960, 1280)
    kelvin = rng.uniform(250, 400, (288, 382)).astype(np.float32)
    kelvin[5, 5] = np.nan
    with console(source) as url, PushClient(url, RIG) as client:
        # 16-bit PNG and raw 16-bit counts: bit-exact counts, scaled on arrival.
        for encoding, stamp in (("png16", 1000), ("raw16", 2000)):
            client.send(Frame("thermal_left", stamp, thermal_counts), ack=True)
            f = source.take(2.0)
            assert (f.sensor, f.stamp_ns) == ("thermal_left", stamp)
            np.testing.assert_array_equal(f.image, counts_to_values(thermal_counts, 0.01, True))
            msg = encode_message(
                "tof",
                stamp,
                [
                    encode_part("image", amp_counts, encoding),
                    encode_part("distance", dist_counts, encoding),
                ],
                ack=True,
            )
            assert client.send_bytes(msg, ack=True)["ok"]
            f = source.take(2.0)
            assert f.stamp_ns == stamp
            np.testing.assert_array_equal(f.image, amp_counts.astype(np.float32))
            np.testing.assert_array_equal(f.distance_m, counts_to_values(dist_counts, 0.001, True))
        # Float32: exact, NaN included.
        client.send_bytes(
            encode_frame(
                Frame("thermal_right", 3000, kelvin), "thermal", value_encoding="raw32f", ack=True
            ),
            ack=True,
        )
        f = source.take(2.0)
        np.testing.assert_array_equal(f.image, kelvin)
        # Kelvin through the default png16 (centi-kelvin): within 0.005 K.
        client.send(Frame("thermal_right", 3001, kelvin), ack=True)
        f = source.take(2.0)
        ok = np.isfinite(kelvin)
        assert np.abs(f.image[ok] - kelvin[ok]).max() <= 0.0051
        assert np.isnan(f.image[5, 5])
        # Colour: JPEG close, PNG and raw8 exact.
        client.send(Frame("ccd_left", 4000, colour), ack=True)
        f = source.take(2.0)
        assert f.image.shape == (960, 1280, 3) and f.image.dtype == np.uint8
        assert np.abs(f.image.astype(int) - colour).mean() < 2.0
        assert f.image[..., 0].mean() == pytest.approx(colour[..., 0].mean(), abs=1.0)
        # A lossless colour frame (PNG, 1.8 MB) is over this console's 1 MiB limit: refused.
        msg = encode_frame(Frame("ccd_right", 5000, colour), color_encoding="png")
        assert len(msg) > LIMIT
        with pytest.raises(PushRejected, match="exceeds the limit"):
            client.send_bytes(msg, ack=True)
    # Within a larger limit, PNG and raw8 colour arrive exactly.
    src = PushSource(sensors={"cam": "color"}, image_sizes={"cam": (1280, 960)})
    for encoding in ("png", "raw8"):
        _, frame, _ = src.accept(encode_frame(Frame("cam", 9, colour), color_encoding=encoding))
        np.testing.assert_array_equal(frame.image, colour)


def test_scale_and_offset_of_raw_counts():
    src = PushSource(sensors={"lwir": "thermal"}, image_sizes={"lwir": (4, 2)})
    counts = np.arange(8, dtype=np.uint16).reshape(2, 4) + 1000
    part = encode_part("image", counts, "raw16", scale=0.04, offset=100.0)
    _, frame, _ = src.accept(encode_message("lwir", 5, [part]))
    np.testing.assert_array_equal(
        frame.image, (counts.astype(np.float64) * 0.04 + 100.0).astype(np.float32)
    )


# -- bad messages ---------------------------------------------------------------------------


def _message(header: dict, payload: bytes = b"") -> bytes:
    head = json.dumps(header).encode()
    return MAGIC + struct.pack("<I", len(head)) + head + payload


def _bad_messages() -> list[tuple[bytes, str]]:
    rgb = smooth_rgb(96, 128)
    thermal = np.full((288, 382), 29315, np.uint16)
    jpeg = encode_part("image", rgb, "jpeg")
    good_thermal = encode_part("image", thermal, "png16")
    return [
        (encode_frame(Frame("lidar", 1, rgb), "color"), "unknown sensor 'lidar'"),
        (
            encode_frame(Frame("thermal_left", 1, np.zeros((240, 320), np.uint16)), "thermal"),
            "bad size: expected 382x288 .* got 320x240",
        ),
        (encode_message("thermal_left", 1, [jpeg]), "encoding must be one of"),
        (encode_message("ccd_left", 1, [jpeg]), "expected 1280x960"),
        (b"XXXX" + b"\0" * 20, "magic"),
        (b"TFP1", "shorter than the 8-byte prefix"),
        (MAGIC + struct.pack("<I", 5) + b"{nope", "not UTF-8 JSON"),
        (_message({"sensor": "tof", "stamp_ns": -1, "parts": []}), "stamp_ns"),
        (_message({"sensor": "tof", "stamp_ns": 1, "parts": [], "x": 1}), "unknown keys"),
        (
            _message(
                {
                    "sensor": "thermal_left",
                    "stamp_ns": 1,
                    "parts": [{**good_thermal.header(), "length": 10}],
                },
                good_thermal.data,
            ),
            "lengths add up to 10 bytes",
        ),
        (
            encode_message(
                "thermal_left", 1, [Part("image", "png16", 382, 288, good_thermal.data[:100])]
            ),
            "corrupt png16",
        ),
        (
            encode_message(
                "thermal_left",
                1,
                [Part("image", "png16", 382, 288, good_thermal.data, scale=0.0)],
            ),
            "scale must not be 0",
        ),
        (
            encode_message("tof", 1, [Part("image", "raw16", 176, 144, b"\0" * 10)]),
            "needs 50688 bytes, got 10",
        ),
        (
            encode_message(
                "thermal_left",
                1,
                [Part("image", "png16", 382, 288, _imencode_png8(thermal))],
            ),
            "16-bit grey PNG",
        ),
        (
            encode_message(
                "tof",
                1,
                [Part("distance", "raw16", 176, 144, b"\0" * (176 * 144 * 2))],
            ),
            "no 'image' part",
        ),
    ]


def _imencode_png8(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", (image >> 8).astype(np.uint8))[1].tobytes()


def test_bad_messages_get_error_replies_and_connection_survives(source):
    bad = _bad_messages()
    good = np.full((288, 382), 29315, np.uint16)
    with console(source) as url, connect(url, compression=None, proxy=None) as ws:
        for seq, (message, pattern) in enumerate(bad, start=1):
            ws.send(message)
            reply = json.loads(ws.recv(timeout=5))
            assert reply["seq"] == seq and reply["ok"] is False
            assert re.search(pattern, reply["error"]), reply
        ws.send("hello")  # text is not part of the protocol
        reply = json.loads(ws.recv(timeout=5))
        assert reply["ok"] is False and "binary" in reply["error"]
        # The same connection still delivers frames.
        ws.send(encode_frame(Frame("thermal_left", 42, good), "thermal", ack=True))
        reply = json.loads(ws.recv(timeout=5))
        assert reply == {
            "seq": len(bad) + 2,
            "ok": True,
            "sensor": "thermal_left",
            "stamp_ns": 42,
            "replaced": False,
        }
        # A stamp that goes back in time on this connection is refused.
        ws.send(encode_frame(Frame("thermal_left", 41, good), "thermal"))
        reply = json.loads(ws.recv(timeout=5))
        assert "not after the previous frame's 42" in reply["error"]
        assert reply["sensor"] == "thermal_left" and reply["stamp_ns"] == 41
    assert source.take(1.0).stamp_ns == 42
    stats = source.stats()
    assert stats["rejected"] == len(bad) + 1  # the text message is not counted as decoded
    assert stats["sensors"]["thermal_left"]["received"] == 1


def test_oversize_message_rejected_connection_kept(source):
    good = np.full((288, 382), 29315, np.uint16)
    with console(source) as url, PushClient(url, RIG) as client:
        huge = MAGIC + struct.pack("<I", 2) + b"{}" + b"\0" * LIMIT
        with pytest.raises(PushRejected, match=f"exceeds the limit of {LIMIT} bytes"):
            client.send_bytes(huge, ack=True)
        assert client.send(Frame("thermal_left", 1, good), ack=True)["ok"]
        # Beyond the WebSocket server's own ws_max_size, the server closes the connection.
        too_big = b"\0" * (uvicorn_ws_max_size(source) + 1)
        with pytest.raises(ConnectionClosedError) as closed:
            client.send_bytes(too_big, ack=True)
        # 1009 "message too big", when the close frame arrives before the socket drops
        # (under load the client may only see the drop).
        assert closed.value.rcvd is None or closed.value.rcvd.code == 1009
        # The server is fine: a new connection is accepted and its frames arrive.
        with PushClient(url, RIG) as again:
            assert again.send(Frame("thermal_left", 2, good), ack=True)["ok"]
    assert source.take(1.0).sensor == "thermal_left"


def test_errors_without_ack_are_collected_by_the_client(source):
    with console(source) as url, PushClient(url, RIG) as client:
        client.send_bytes(b"junk-message")
        wait_until(lambda: client.poll() or client.errors, "the error reply", 5)
        assert client.errors[0]["seq"] == 1 and "magic" in client.errors[0]["error"]


def test_newest_frame_wins_for_a_slow_consumer(source):
    good = np.zeros((288, 382), np.uint16)
    with console(source) as url, PushClient(url, RIG) as client:
        for stamp in range(1, 11):
            good[0, 0] = stamp
            reply = client.send(Frame("thermal_left", stamp, good), ack=True)
            assert reply["replaced"] is (stamp > 1)
        client.send(Frame("tof", 5, np.ones((144, 176), np.float32), None), ack=True)
    first, second = source.take(1.0), source.take(1.0)
    assert (first.sensor, first.stamp_ns) == ("tof", 5)  # oldest stamp first
    assert (second.sensor, second.stamp_ns) == ("thermal_left", 10)  # only the newest
    assert second.image[0, 0] == pytest.approx(0.1)
    assert source.take(0) is None  # no backlog (every message was acknowledged: all arrived)
    stats = source.stats()["sensors"]["thermal_left"]
    assert stats["received"] == 10 and stats["dropped"] == 9 and stats["delivered"] == 1


def test_frames_iterator_and_close(source):
    got: list[Frame] = []
    reader = threading.Thread(target=lambda: got.extend(source.frames()), daemon=True)
    reader.start()
    with console(source) as url, PushClient(url, RIG) as client:
        client.send(Frame("tof", 1, np.ones((144, 176), np.float32), None), ack=True)
        wait_until(lambda: got, "the frame read", 5, poll_s=0.01)
        source.close()
        reader.join(5)
        assert not reader.is_alive()
        assert [f.stamp_ns for f in got] == [1]
        with pytest.raises(PushError, match="closed"):
            source.accept(b"")


def test_console_token_guards_the_ingest(source):
    app = FastAPI()
    app.add_middleware(AuthMiddleware, config=AuthConfig("s3cret-0123456789abcdef", 1))
    app.include_router(make_push_router(source))
    with serve(app, ws_max_size=uvicorn_ws_max_size(source)) as port:
        url = f"ws://127.0.0.1:{port}/ingest"
        for token in (None, "wrong-0123456789abcdef"):
            with pytest.raises(InvalidStatus) as refused:
                PushClient(url, RIG, token=token)
            assert refused.value.response.status_code == 403
        with PushClient(url, RIG, token="s3cret-0123456789abcdef") as client:
            frame = Frame("tof", 1, np.ones((144, 176), np.float32), None)
            assert client.send(frame, ack=True)["ok"]


def test_async_client(source):
    async def run(url: str) -> dict:
        async with AsyncPushClient(url, RIG) as client:
            frame = Frame("ccd_left", 77, smooth_rgb(960, 1280, seed=2))
            reply = await client.send(frame, ack=True)
            with pytest.raises(PushRejected, match="unknown sensor"):
                await client.send_bytes(
                    encode_frame(Frame("x", 1, smooth_rgb(32, 32)), ack=True), ack=True
                )
            return reply

    with console(source) as url:
        reply = asyncio.run(run(url))
    assert reply["ok"] and reply["stamp_ns"] == 77
    assert source.take(1.0).stamp_ns == 77


def test_encode_frame_needs_modality_for_single_channel():
    with pytest.raises(PushError, match="pass modality"):
        encode_frame(Frame("t", 1, np.zeros((4, 4), np.float32)))
    with pytest.raises(PushError, match="value_encoding"):
        encode_frame(Frame("t", 1, np.zeros((4, 4), np.float32)), "thermal", value_encoding="jpeg")


# -- the example driver ---------------------------------------------------------------------


def test_driver_help_and_arguments(capsys):
    with pytest.raises(SystemExit) as exit_:
        push_sim.main(["--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "--url" in out and "--rate" in out
    args = push_sim.build_parser().parse_args(["--url", "ws://robot:1/ingest", "--rate", "0.5"])
    assert args.url == "ws://robot:1/ingest" and args.rate == 0.5
    with pytest.raises(SystemExit):
        push_sim.build_parser().parse_args(["--rate", "-1"])


def test_driver_pushes_and_reconnects(source, capsys):
    # Start the driver before the console exists: it retries until the console is up.
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    url = f"ws://127.0.0.1:{port}/ingest"
    result: list[int] = []
    driver = threading.Thread(
        target=lambda: result.append(
            push_sim.main(
                ["--url", url, "--sensors", "tof,thermal_left", "--frames", "20", "--retry", "0.2"]
            )
        ),
        daemon=True,
    )
    said = {"out": "", "err": ""}

    def printed() -> dict[str, str]:
        out, err = capsys.readouterr()
        said["out"] += out
        said["err"] += err
        return said

    driver.start()
    wait_until(lambda: "retrying" in printed()["err"], "the driver to retry", 60)
    app = FastAPI()
    app.include_router(make_push_router(source))
    got: list[Frame] = []

    def finished() -> bool:
        if (f := source.take(0.2)) is not None:
            got.append(f)
        return not driver.is_alive()

    with serve(app, port=port):
        wait_until(finished, "the driver to finish", 60, poll_s=0)
        driver.join(5)
    assert result == [0]
    captured = printed()
    assert "retrying" in captured["err"]
    assert "sent tof" in captured["out"] and "sent 20 frames; done" in captured["out"]
    assert {f.sensor for f in got} <= {"tof", "thermal_left"}
    assert source.stats()["sensors"]["tof"]["received"] >= 5
    assert source.stats()["rejected"] == 0


def test_scale_that_overflows_float32_is_rejected(source):
    counts = encode_part("image", np.full((288, 382), 30000, np.uint16), "raw16").data
    for bad in (1e308, -1e31):
        part = Part("image", "raw16", 382, 288, counts, scale=bad)
        with pytest.raises(PushError, match="magnitude at most 1e"):
            source.accept(encode_message("thermal_left", 1, [part]))
    ok = Part("image", "raw16", 382, 288, counts, scale=0.01)
    assert source.accept(encode_message("thermal_left", 1, [ok]))
