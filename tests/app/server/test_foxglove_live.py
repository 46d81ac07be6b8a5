"""Foxglove live (issue 21, app/server/runtime/foxglove_live.py): the console's frames on
foxglove-sdk's WebSocket server with a recording's topics and schemas, read by a client
speaking the Foxglove protocol (subprotocol ``foxglove.sdk.v1``: JSON ``serverInfo`` and
``advertise``, ``subscribe``; binary message data: opcode 1, subscription id, log time,
payload); no work without a subscriber; the port on 127.0.0.1 only, a port in use refused
in one line."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import socket
import socketserver
import struct
import subprocess
import sys
import threading
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

from tests.support import ROOT, run_cli, synth_frame, wait_until
from trifuse.app.procfs import parse_proc_status
from trifuse.app.recording import RecordingWriter
from trifuse.app.recording.layout import FUSED_VIDEO_SCHEMA, FUSED_VIDEO_TOPIC, topic_of
from trifuse.app.recording.video_track import FusedVideoEncoder, nal_types
from trifuse.app.server.runtime.demand import ConsoleDemand
from trifuse.app.server.runtime.foxglove_gate import (
    LOOPBACK,
    MAX_CLIENT_MESSAGE_BYTES,
    MAX_CLIENTS,
    MAX_WAITING,
    FoxgloveGate,
)
from trifuse.app.server.runtime.foxglove_live import (
    HEALTH_SCHEMA_NAME,
    HEALTH_TOPIC,
    MESSAGE_BACKLOG,
    SUBPROTOCOL,
    FoxgloveLive,
    check_foxglove_port,
    points_topic,
    start_foxglove_server,
)
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.app.sources.sim.render import HeadModel
from trifuse.app.sources.simulated import SimulatedHeadSource

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
        topic, log_time, payload = await self.raw_message()
        return topic, log_time, self.decode(topic, payload)

    async def raw_message(self) -> tuple[str, int, bytes]:
        """The next message data: (topic, log time ns, payload)."""
        while True:
            data = await asyncio.wait_for(self.ws.recv(), RECV_S)
            if isinstance(data, str):
                continue  # status and the like
            opcode, sid, log_time = struct.unpack_from("<BIQ", data)
            if opcode == 1 and sid in self.subscriptions:
                return self.subscriptions[sid], log_time, bytes(data[13:])

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
    wait_until(lambda: not live.busy, "the set being published when the client left")
    counts = (live.encoded, live.taken)
    for _ in range(2):  # the second: the pipeline's listeners have had the first one
        seen = console.pipeline.status.last_stamp_ns
        wait_until(lambda s=seen: console.pipeline.status.last_stamp_ns != s, "more frame sets")
    wait_until(lambda: not live.busy, "the publisher's thread idle")
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
    # the SDK's own server, behind the port's relay: an address of 127.0.0.0/8 only
    (inner,) = listening_addresses(console.live.server.port)
    assert inner.endswith("7F") and len(inner) == 8, inner  # /proc writes 127.a.b.c as c b a 7F
    for refuse in (check_foxglove_port, lambda p: start_foxglove_server(p, _context())):
        with pytest.raises(OSError, match=f"--foxglove-port {port} on 127.0.0.1 is in use") as e:
            refuse(port)
        assert "\n" not in str(e.value)


def _context():
    import foxglove

    return foxglove.Context()


def test_serve_refuses_a_foxglove_port_in_use_before_anything_starts(tmp_path, capsys) -> None:
    from trifuse.app.devtools.console_process import free_port

    with socket.socket() as taken:
        taken.bind((LOOPBACK, 0))
        taken.listen()
        port = taken.getsockname()[1]
        argv = ["serve", "--port", str(free_port()), "--workdir", str(tmp_path / "w")]
        code, _out, err = run_cli([*argv, "--foxglove-port", str(port)], capsys)
    assert code == 2 and err.count("\n") == 1
    assert f"--foxglove-port {port} on 127.0.0.1 is in use" in err
    assert not (tmp_path / "w").exists()  # refused before the work directory was made


# -- the limits (issue 29) ------------------------------------------------------------------

CAPS_CHILD = [sys.executable, "-c", "from tests.foxglove_caps_support import main; main()"]
"""The Foxglove port on a synthetic full-size head in a process of its own (its memory)."""
ROUND_S = 4.0
"""How long the stalled clients hold their places in each round."""


@contextlib.contextmanager
def _port_in_a_process() -> Iterator[tuple[int, str]]:
    """(pid, url) of :data:`CAPS_CHILD`'s Foxglove port."""
    proc = subprocess.Popen(
        CAPS_CHILD, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        yield proc.pid, f"ws://{LOOPBACK}:{int(proc.stdout.readline())}"
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _rss_mb(pid: int) -> float:
    return parse_proc_status(Path(f"/proc/{pid}/status").read_text())[0]


async def _stalled_client(url: str) -> FoxgloveClient:
    """A client that subscribes to every channel and then takes nothing (its library
    stops reading the socket once it holds one message)."""
    ws = await websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None, max_queue=1)
    client = FoxgloveClient(ws)
    await client.read_advertise()
    await client.subscribe(list(client.channels))
    return client


@pytest.mark.slow
def test_clients_that_never_read_cannot_fill_the_consoles_memory() -> None:
    """Issue 29: 16 clients that subscribed to everything and never read took the console
    from 0.6 to 2.15 GiB. Now, on a full-size head: beside one reading client, MAX_CLIENTS
    - 1 stalled clients get in and the next one is refused at once (503); while they hold
    their places the console's memory grows by at most twice their queues (MESSAGE_BACKLOG
    of the largest message each, plus the relay's buffers), and the reader goes on
    receiving new messages; after they leave it does not grow, and a second round of them
    costs no more than the first."""
    thermal = topic_of("thermal_left", "thermal")

    async def read_for(reader: FoxgloveClient, pid: int, seconds: float) -> SimpleNamespace:
        """Read for ``seconds``: messages per topic, the largest payload, the newest log
        time of the thermal images, and the peak resident memory (MB) meanwhile."""
        got = SimpleNamespace(counts=dict.fromkeys(reader.channels, 0), largest=0, stamps=[])
        got.peak_mb = _rss_mb(pid)
        end = time.monotonic() + seconds
        next_sample = 0.0
        while (now := time.monotonic()) < end:
            topic, log_time, payload = await reader.raw_message()
            got.counts[topic] += 1
            got.largest = max(got.largest, 13 + len(payload))
            if topic == thermal:
                got.stamps.append(log_time)
            if now >= next_sample:
                next_sample = now + 0.2
                got.peak_mb = max(got.peak_mb, _rss_mb(pid))
        return got

    async def scenario(pid: int, url: str) -> None:
        async with await _connect(url) as ws:
            reader = FoxgloveClient(ws)
            await reader.read_advertise()
            await reader.subscribe(list(reader.channels))
            warm = await read_for(reader, pid, 4.0)  # every encoder has started
            assert all(warm.counts.values()), warm.counts
            base_mb = _rss_mb(pid)
            peaks = []
            for _round in range(2):
                stalled = [await _stalled_client(url) for _ in range(MAX_CLIENTS - 1)]
                started = time.monotonic()
                with pytest.raises(websockets.InvalidStatus) as refused:
                    await _connect(url)
                assert refused.value.response.status_code == 503
                assert f"{MAX_CLIENTS} clients at most".encode() in refused.value.response.body
                assert time.monotonic() - started < 5.0  # at once, not after a time-out

                held = await read_for(reader, pid, ROUND_S)
                # the reader got fresh thermal images all along (stamps move on)
                assert len(held.stamps) >= ROUND_S, held.counts
                assert held.stamps[-1] > held.stamps[0]
                largest = max(warm.largest, held.largest)
                queues_mb = (MAX_CLIENTS - 1) * (MESSAGE_BACKLOG * largest + 2**20) / 2**20
                growth_mb = held.peak_mb - base_mb
                assert growth_mb < 2 * queues_mb, (growth_mb, queues_mb, largest)
                peaks.append(held.peak_mb)

                for client in stalled:
                    client.ws.transport.abort()
                after = await read_for(reader, pid, 2.0)
                assert after.counts[thermal] > 0
                assert after.peak_mb < held.peak_mb + 16, (after.peak_mb, held.peak_mb)
            assert peaks[1] < peaks[0] + 16, peaks  # no leak from round to round

    with _port_in_a_process() as (pid, url):
        asyncio.run(scenario(pid, url))


@pytest.mark.slow
def test_a_client_cannot_make_the_server_gather_a_long_message() -> None:
    """foxglove-sdk gathers a client's message up to 64 MiB (8 clients sending 56 MiB
    each took the console up by about 0.5 GB). Now MAX_CLIENTS - 1 clients that each send an
    unfinished message in 1 MiB frames are cut off at MAX_CLIENT_MESSAGE_BYTES, the
    console's memory does not grow by their 32 MiB each, and their places are free again."""
    frame = _client_frame(1, bytes(MAX_CLIENT_MESSAGE_BYTES), fin=False)
    more = _client_frame(0, bytes(MAX_CLIENT_MESSAGE_BYTES), fin=False)

    async def scenario(pid: int, url: str) -> None:
        base_mb = _rss_mb(pid)
        senders = []
        for _ in range(MAX_CLIENTS - 1):
            ws = await websockets.connect(url, subprotocols=[SUBPROTOCOL], max_queue=1)
            ws.transport.write(frame + more * 31)  # 32 MiB, never finished
            senders.append(ws)
        for ws in senders:
            await asyncio.wait_for(ws.wait_closed(), RECV_S)
        grown_mb = _rss_mb(pid) - base_mb
        assert grown_mb < 16, grown_mb
        async with await _connect(url) as ws:  # the places are free again
            assert HEALTH_TOPIC in await FoxgloveClient(ws).read_advertise()

    with _port_in_a_process() as (pid, url):
        asyncio.run(scenario(pid, url))


class _EndlessServer(socketserver.ThreadingTCPServer):
    """Stands for the SDK's server behind the gate: to each connection it sends ``HEAD:``,
    the request head it got, then 64 KiB blocks without end (there is always data for the
    client), and reads what comes after the head; it closes a connection at its end of
    file. ``live``: its connections not yet closed; ``received``: the bytes read after the
    heads, in all."""

    daemon_threads = True
    BLOCK = bytes(range(256)) * 256

    def __init__(self) -> None:
        super().__init__((LOOPBACK, 0), self._Handler)
        self.live = self.received = 0
        self.lock = threading.Lock()  # the counts, kept by the connections' threads

    class _Handler(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            server, sock = self.server, self.request
            assert isinstance(server, _EndlessServer)
            with server.lock:
                server.live += 1
            try:
                head = b""
                while not head.endswith(b"\r\n\r\n"):
                    head += sock.recv(1)
                sock.sendall(b"HEAD:" + head)
                threading.Thread(target=self._read, daemon=True).start()
                while True:
                    sock.sendall(_EndlessServer.BLOCK)
            except OSError:
                pass
            finally:
                with server.lock:
                    server.live -= 1

        def _read(self) -> None:
            server = self.server
            assert isinstance(server, _EndlessServer)
            with contextlib.suppress(OSError):
                while data := self.request.recv(1 << 16):
                    with server.lock:
                        server.received += len(data)
                self.request.shutdown(socket.SHUT_RDWR)  # the end of file: as the SDK does


def _client_frame(opcode: int, payload: bytes, fin: bool = True) -> bytes:
    """A client's WebSocket frame (RFC 6455), masked with zeros (the payload as it is)."""
    n = len(payload)
    if n < 126:
        size = bytes([0x80 | n])
    elif n < 1 << 16:
        size = bytes([0x80 | 126]) + n.to_bytes(2, "big")
    else:
        size = bytes([0x80 | 127]) + n.to_bytes(8, "big")
    return bytes([(0x80 if fin else 0) | opcode]) + size + bytes(4) + payload


def _gate_client(port: int, head: bool = True) -> socket.socket:
    sock = socket.create_connection((LOOPBACK, port), timeout=10)
    if head:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: foxglove\r\n\r\n")
    return sock


def _closed(sock: socket.socket) -> bool:
    """Whether the other side closed ``sock`` within 64 MiB of data (far more than the
    gate's buffers hold)."""
    left = 64 << 20
    try:
        while data := sock.recv(1 << 20):
            left -= len(data)
            if left < 0:
                return False
    except ConnectionResetError:
        pass
    return True


def test_the_gate_caps_clients_and_waiting_connections_and_drops_stalled_ones() -> None:
    """The relay in front of the SDK's server, with 2 places, a 3 s head time-out and a
    3 s stall: two clients that never read get in, a third gets 503; MAX_WAITING
    connections that send no head wait, one more is closed at once (while they still
    wait), they after the time-out; the stalled clients are disconnected and their
    connections to the server closed, which frees their places; a client that reads gets
    the server's bytes as sent, and the server its messages; a client message over
    MAX_CLIENT_MESSAGE_BYTES ends the connection before the server gets more of it."""
    upstream = _EndlessServer()
    threading.Thread(target=upstream.serve_forever, daemon=True).start()
    gate = FoxgloveGate(0, upstream.server_address[:2], max_clients=2, handshake_s=3.0, stall_s=3.0)
    gate.start()
    sockets: list[socket.socket] = []
    try:
        sockets += [_gate_client(gate.port), _gate_client(gate.port)]
        wait_until(lambda: gate.clients == 2 and upstream.live == 2, "two relayed clients")
        third = _gate_client(gate.port)
        assert third.recv(1024).startswith(b"HTTP/1.1 503 Service Unavailable\r\n")
        assert _closed(third) and gate.refused == 1

        waiting = [_gate_client(gate.port, head=False) for _ in range(MAX_WAITING)]
        sockets += waiting
        wait_until(lambda: gate.waiting == MAX_WAITING, "the connections without a head")
        assert _closed(_gate_client(gate.port, head=False)) and gate.refused == 2
        assert gate.waiting == MAX_WAITING  # closed at once: the others still wait
        assert all(_closed(sock) for sock in waiting)  # after the head time-out
        assert gate.waiting == 0

        # the stalled clients' places and their connections to the server are freed
        wait_until(lambda: gate.clients == 0 and upstream.live == 0, "the stalled clients out")
        assert all(_closed(sock) for sock in sockets[:2])

        reader = _gate_client(gate.port)
        sockets.append(reader)
        want = b"HEAD:GET / HTTP/1.1\r\nHost: foxglove\r\n\r\n" + _EndlessServer.BLOCK * 8
        got = b""
        while len(got) < len(want):
            got += reader.recv(len(want) - len(got))
        assert got == want and gate.clients == 1

        # messages up to MAX_CLIENT_MESSAGE_BYTES go through as they are, a longer one ends
        # the connection before the server gets more than the limit of it
        part = _client_frame(1, b"x" * (MAX_CLIENT_MESSAGE_BYTES // 2), fin=False)
        ok = part + _client_frame(0, b"y" * (MAX_CLIENT_MESSAGE_BYTES // 2)) + _client_frame(9, b"")
        before = upstream.received
        reader.sendall(ok * 3)
        wait_until(lambda: upstream.received - before == 3 * len(ok), "the messages upstream")
        big = _gate_client(gate.port)
        sockets.append(big)
        wait_until(lambda: gate.clients == 2, "the second client in")
        before = upstream.received
        with contextlib.suppress(OSError):  # the gate may close it while it sends
            big.sendall(part + part + part)
        assert _closed(big)
        wait_until(lambda: gate.clients == 1, "the long message's connection closed")
        # the server got the first two frames (the limit), nothing of the third
        wait_until(lambda: upstream.received - before == 2 * len(part), "the first two frames")
    finally:
        gate.stop()
        upstream.shutdown()
        upstream.server_close()
        for sock in sockets:
            sock.close()
