"""Foxglove live (issue 21, app/server/runtime/foxglove_live.py): the console's frames on
foxglove-sdk's WebSocket server with a recording's topics and schemas, read by a client
speaking the Foxglove protocol (subprotocol ``foxglove.sdk.v1``: JSON ``serverInfo`` and
``advertise``, ``subscribe``; binary message data: opcode 1, subscription id, log time,
payload); no work without a subscriber; the port on 127.0.0.1 only, a port in use refused
in one line."""

from __future__ import annotations

import asyncio
import base64
import json
import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import websockets
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from app.recording import RecordingWriter
from app.recording.layout import FUSED_VIDEO_SCHEMA, FUSED_VIDEO_TOPIC, topic_of
from app.recording.video_track import FusedVideoEncoder, nal_types
from app.server.runtime.demand import ConsoleDemand
from app.server.runtime.foxglove_live import (
    HEALTH_SCHEMA_NAME,
    HEALTH_TOPIC,
    LOOPBACK,
    SUBPROTOCOL,
    FoxgloveLive,
    check_foxglove_port,
    points_topic,
    start_foxglove_server,
)
from app.server.runtime.pipeline import FusionPipeline
from app.server.runtime.source_control import SourceControl, SourceTap
from app.server.runtime.stream import FrameHub
from app.sources.sim.render import HeadModel
from app.sources.sim.scenarios import InspectionScenario
from app.sources.simulated import SimulatedHeadSource
from tests.support import run_cli, synth_frame, wait_until

RECV_S = 60.0
"""Longest wait for one message (the first pose renders in a few seconds)."""


@pytest.fixture(scope="module")
def console() -> Iterator[SimpleNamespace]:
    """The console's parts in this process, as serve.py wires them: the simulated head (one
    pose, edges not supersampled: rendered in a few seconds), the tap, the pipeline with
    its fusion demand, the source control and the Foxglove publisher on a free port."""
    model = HeadModel(supersample={"color": 1, "thermal": 1, "tof": 1})
    scenario = InspectionScenario(model=model, seed=3)
    source = SimulatedHeadSource(scenario, realtime=True, start_ns=None, render_hz=0.5, loop_s=2.0)
    demand = ConsoleDemand()
    hub = FrameHub(demand.fusion)
    pipeline = FusionPipeline(SourceTap(source), source.rig, hub, demand=demand.fusion).start()
    control = SourceControl(pipeline, hub, "the simulated head")
    live = FoxgloveLive(control, 0).start()
    try:
        yield SimpleNamespace(
            live=live, pipeline=pipeline, hub=hub, demand=demand, rig=source.rig, source=source
        )
    finally:
        live.stop()
        pipeline.stop()


# -- a client of the Foxglove WebSocket protocol -------------------------------------------


class FoxgloveClient:
    """What Foxglove does on the wire: connect with the SDK's subprotocol, read the
    server's channels, subscribe, receive message data and decode it with the schema the
    channel advertised."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}  # topic -> advertised channel
        self.subscriptions: dict[int, str] = {}  # subscription id -> topic
        self._decoders: dict[str, Any] = {}

    async def read_advertise(self) -> dict[str, dict[str, Any]]:
        """serverInfo, then the advertise message: the server's channels by topic."""
        while True:
            text = await asyncio.wait_for(self.ws.recv(), RECV_S)
            assert isinstance(text, str), "expected JSON before any subscription"
            msg = json.loads(text)
            if msg["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in msg["channels"]})
                return self.channels

    async def subscribe(self, topics: list[str]) -> None:
        subs = []
        for topic in topics:
            sid = len(self.subscriptions) + 1
            self.subscriptions[sid] = topic
            subs.append({"id": sid, "channelId": self.channels[topic]["id"]})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def unsubscribe_all(self) -> None:
        ids = list(self.subscriptions)
        await self.ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": ids}))
        self.subscriptions.clear()

    async def message(self) -> tuple[str, int, Any]:
        """The next message data: (topic, log time ns, decoded message)."""
        while True:
            data = await asyncio.wait_for(self.ws.recv(), RECV_S)
            if isinstance(data, str):
                continue  # status and the like
            opcode, sid, log_time = struct.unpack_from("<BIQ", data)
            if opcode != 1 or sid not in self.subscriptions:
                continue
            topic = self.subscriptions[sid]
            return topic, log_time, self.decode(topic, bytes(data[13:]))

    def decode(self, topic: str, payload: bytes) -> Any:
        ch = self.channels[topic]
        if ch["encoding"] == "json":
            return json.loads(payload)
        decoder = self._decoders.get(topic)
        if decoder is None:
            assert ch["schemaEncoding"] == "protobuf", ch
            schema = Schema(
                id=ch["id"],
                name=ch["schemaName"],
                encoding="protobuf",
                data=base64.b64decode(ch["schema"]),
            )
            decoder = self._decoders[topic] = DecoderFactory().decoder_for("protobuf", schema)
        return decoder(payload)


async def _connect(url: str) -> Any:
    ws = await websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None)
    assert ws.subprotocol == SUBPROTOCOL
    return ws


def _recording_channels(path: Path, rig) -> dict[str, tuple[str, str, str]]:
    """topic -> (schema name, schema encoding, message encoding) of a short recording of
    ``rig``'s sensors with its fused video (one frame each, one picture)."""
    rng = np.random.default_rng(1)
    with RecordingWriter(path, rig, fused_video=True) as w:
        for k, name in enumerate(rig.names):
            w.write(synth_frame(rig, name, 1_000_000_000 + k, rng))
        encoder = FusedVideoEncoder()
        unit = encoder.encode(np.zeros((32, 64, 3), np.uint8), 1_000_000_000)
        encoder.close()
        assert w.write_video(unit.data, unit.key, unit.stamp_ns)
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = {}
    for ch in summary.channels.values():
        schema = summary.schemas[ch.schema_id]
        out[ch.topic] = (schema.name, schema.encoding, ch.message_encoding)
    return out


# -- the tests ------------------------------------------------------------------------------


def test_the_topics_and_schemas_are_a_recordings(console, tmp_path) -> None:
    """The same sensors give the same topics, schema names and encodings as a recording
    (its fused video too); the live server adds the TOF cloud and the health."""

    async def advertised() -> dict[str, dict[str, Any]]:
        async with await _connect(console.live.url) as ws:
            return await FoxgloveClient(ws).read_advertise()

    channels = asyncio.run(advertised())
    live = {t: (c["schemaName"], c["schemaEncoding"], c["encoding"]) for t, c in channels.items()}
    recorded = _recording_channels(tmp_path / "short.mcap", console.rig)
    assert recorded[FUSED_VIDEO_TOPIC][0] == FUSED_VIDEO_SCHEMA
    assert recorded[topic_of("thermal_left", "thermal")][0] == "foxglove.RawImage"
    assert {t: live[t] for t in recorded if t in live} == recorded
    assert set(live) - set(recorded) == {points_topic("tof"), HEALTH_TOPIC}
    assert live[points_topic("tof")] == ("foxglove.PointCloud", "protobuf", "protobuf")
    assert live[HEALTH_TOPIC] == (HEALTH_SCHEMA_NAME, "jsonschema", "json")


def test_subscribers_get_decodable_messages_and_nobody_costs_nothing(console) -> None:
    """No encoding while a client is connected but subscribes to nothing; a thermal image,
    /tf (the rig's transforms and the head's pose), the TOF cloud, a calibration, the
    health and the fused video decode with their advertised schemas; after the client
    unsubscribes the work stops again (and the fused video's hold on the fusion)."""
    live, rig = console.live, console.rig
    thermal = rig["thermal_left"]
    tof = rig["tof"]
    wanted = [
        topic_of("thermal_left", "thermal"),
        "/tf",
        points_topic("tof"),
        topic_of("tof", "calibration"),
        HEALTH_TOPIC,
        FUSED_VIDEO_TOPIC,
    ]

    async def session() -> dict[str, list[tuple[int, Any]]]:
        async with await _connect(live.url) as ws:
            client = FoxgloveClient(ws)
            await client.read_advertise()
            # connected, subscribed to nothing: frame sets flow, nothing is taken or encoded
            await asyncio.to_thread(
                wait_until, lambda: console.pipeline.latest_set is not None, "a frame set"
            )
            seen = console.pipeline.status.last_stamp_ns
            await asyncio.to_thread(
                wait_until,
                lambda: console.pipeline.status.last_stamp_ns != seen,
                "more frame sets",
            )
            assert (live.encoded, live.taken, live.dropped) == (0, 0, 0)
            assert not console.hub.takers and console.demand.fusion.holds == 0

            await client.subscribe(wanted)
            got: dict[str, list[tuple[int, Any]]] = {t: [] for t in wanted}
            pairs: set[tuple[str, str]] = set()
            want_pairs = {("rig", n) for n in rig.names} | {("world", "rig")}
            end = time.monotonic() + RECV_S
            while time.monotonic() < end and (
                any(not v for v in got.values()) or not want_pairs <= pairs
            ):
                topic, log_time, msg = await client.message()
                got[topic].append((log_time, msg))
                if topic == "/tf":
                    pairs.add((msg.parent_frame_id, msg.child_frame_id))
            assert want_pairs <= pairs, pairs
            await client.unsubscribe_all()
            await asyncio.to_thread(
                wait_until, lambda: not live.subscribed, "the server to see the unsubscribe"
            )
            return got

    got = asyncio.run(session())
    assert all(got.values()), {t: len(v) for t, v in got.items()}

    log_time, img = got[topic_of("thermal_left", "thermal")][0]
    w, h = thermal.image_size
    assert (img.width, img.height, img.encoding, img.step) == (w, h, "16UC1", 2 * w)
    assert img.frame_id == "thermal_left" and len(img.data) == 2 * w * h
    assert img.timestamp.seconds * 10**9 + img.timestamp.nanos == log_time > 0
    centi_k = np.frombuffer(img.data, "<u2")
    valid = centi_k[centi_k > 0] / 100.0
    assert valid.size > 0.5 * w * h and 200.0 < np.median(valid) < 400.0  # kelvin

    _, cloud = got[points_topic("tof")][0]
    assert cloud.frame_id == "tof" and cloud.point_stride == 16
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "amplitude"]
    pts = np.frombuffer(cloud.data, "<f4").reshape(-1, 4)
    assert len(pts) > 100 and np.isfinite(pts).all()
    assert np.median(pts[:, 2]) > 0.1  # in front of the TOF (its frame)
    assert len(pts) <= tof.image_size[0] * tof.image_size[1] / 4  # decimated

    _, cal = got[topic_of("tof", "calibration")][0]
    assert (cal.width, cal.height) == tof.image_size and cal.frame_id == "tof"
    assert cal.K[0] == pytest.approx(tof.intrinsics.fx)

    _, health = got[HEALTH_TOPIC][0]
    assert set(health["sensors"]) == set(rig.names)
    assert {h["state"] for h in health["sensors"].values()} <= {"ok", "silent", "never", "failing"}

    _, video = got[FUSED_VIDEO_TOPIC][0]
    assert video.format == "h264" and video.frame_id == rig.eyes["left"].color
    assert 7 in nal_types(video.data) and 5 in nal_types(video.data)  # a key frame first

    # after the unsubscribe: the video's tap let go of the fusion, nothing more is encoded
    wait_until(
        lambda: not console.hub.takers and console.demand.fusion.holds == 0,
        "the fused video to stop",
    )
    time.sleep(0.3)  # a frame set being published when the client left
    counts = (live.encoded, live.taken)
    seen = console.pipeline.status.last_stamp_ns
    wait_until(lambda: console.pipeline.status.last_stamp_ns != seen, "more frame sets")
    time.sleep(0.5)
    assert (live.encoded, live.taken) == counts
    assert live.failed == 0, live.last_error


def listening_addresses(port: int) -> set[str]:
    """The local addresses (hex, as /proc/net/tcp{,6} writes them) listening on ``port``."""
    found = set()
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/self/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            address, hex_port = fields[1].rsplit(":", 1)
            if fields[3] == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                found.add(address)
    return found


def test_the_server_listens_on_loopback_only_and_a_port_in_use_is_one_line(console) -> None:
    port = console.live.port
    assert listening_addresses(port) == {"0100007F"}  # 127.0.0.1, nothing else
    for refuse in (check_foxglove_port, lambda p: start_foxglove_server(p, _context())):
        with pytest.raises(OSError, match=f"--foxglove-port {port} on 127.0.0.1 is in use") as e:
            refuse(port)
        assert "\n" not in str(e.value)


def _context():
    import foxglove

    return foxglove.Context()


def test_serve_refuses_a_foxglove_port_in_use_before_anything_starts(tmp_path, capsys) -> None:
    from app.devtools.console_process import free_port

    with socket.socket() as taken:
        taken.bind((LOOPBACK, 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = ["serve", "--port", str(free_port()), "--workdir", str(tmp_path / "w")]
        code, _out, err = run_cli([*argv, "--foxglove-port", str(port)], capsys)
    assert code == 2 and err.count("\n") == 1
    assert f"--foxglove-port {port} on 127.0.0.1 is in use" in err
    assert not (tmp_path / "w").exists()  # refused before the work directory was made
