"""Clients of the console's fused stream for the stream soak and the ``idle`` benchmark: a
viewer that keeps up (:class:`FastViewer`), two slow readers that make the server wait
(:class:`SlowWsViewer`, :class:`SlowMjpegReader`; see app/devtools/bench_soak.py), and a
viewer of the video stream that keeps up (:class:`VideoViewer`).

Each runs as an asyncio task (``await client.run()``) until cancelled; it counts what it
received and keeps the error that ended it, if any.
"""

from __future__ import annotations

import asyncio
import json
import re
import socket
import time
from collections.abc import Sequence
from typing import Any

from trifuse.app.errors import describe_error


class MjpegParts:
    """Counts the complete JPEG parts of a ``multipart/x-mixed-replace`` body fed in
    chunks (parts as ``/stream.mjpg`` writes them: ``--frame``, headers with
    ``Content-Length``, a blank line, the JPEG, CRLF)."""

    MAX_HEADER = 4096

    def __init__(self) -> None:
        self.parts = 0
        self._head = bytearray()
        self._body_left = 0

    def feed(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            if self._body_left:
                take = min(self._body_left, len(view))
                self._body_left -= take
                view = view[take:]
                if not self._body_left:
                    self.parts += 1
                continue
            self._head += view
            view = memoryview(b"")
            end = self._head.find(b"\r\n\r\n")
            if end < 0:
                if len(self._head) > self.MAX_HEADER:
                    raise ValueError("MJPEG: no end of part headers")
                return
            head, rest = bytes(self._head[:end]), bytes(self._head[end + 4 :])
            self._head.clear()
            m = re.search(rb"content-length:\s*(\d+)", head, re.I)
            if m is None or b"--frame" not in head:
                raise ValueError(f"MJPEG: unexpected part headers {head[:80]!r}")
            self._body_left = int(m.group(1)) + 2  # the CRLF after the JPEG
            view = memoryview(rest)


def _connect(url: str, token: str | None, open_timeout_s: float) -> Any:
    """A websockets client connection to ``url`` (with the console's ``token``), no proxy,
    no compression, no message size limit: ``async with`` it."""
    from websockets.asyncio.client import connect

    headers = {"Authorization": f"token {token}"} if token else {}
    return connect(
        url,
        additional_headers=headers,
        proxy=None,
        compression=None,
        max_size=None,
        open_timeout=open_timeout_s,
    )


class StreamClient:
    """What every client counts: ``frames`` and ``bytes`` received, ``stalls`` (times it
    stopped reading on purpose), ``error`` (what ended it; None while it runs or when it was
    cancelled), ``done``, and ``first_frame`` (set with the first complete frame)."""

    kind = ""

    def __init__(self) -> None:
        self.frames = 0
        self.bytes = 0
        self.stalls = 0
        self.error: str | None = None
        self.done = False
        self.first_frame = asyncio.Event()

    async def run(self) -> None:
        """Receive until cancelled; an exception ends it and is kept in ``error``."""
        try:
            await self._receive()
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.error = describe_error(exc)
        finally:
            self.done = True

    async def _receive(self) -> None:
        raise NotImplementedError

    def _got_frame(self, size: int) -> None:
        self.frames += 1
        self.bytes += size
        self.first_frame.set()


class FastViewer(StreamClient):
    """A viewer on ``/stream`` (``url``) that acknowledges each frame as soon as it has it;
    ``latencies_ms``: per frame, from the server publishing it (``sent_ns``) to having it."""

    kind = "fast"

    def __init__(self, url: str, token: str | None) -> None:
        super().__init__()
        self.url, self.token = url, token
        self.latencies_ms: list[float] = []

    async def _receive(self) -> None:
        async with _connect(self.url, self.token, open_timeout_s=30) as ws:
            while True:
                meta = await ws.recv()
                jpeg = await ws.recv()
                if not isinstance(meta, str) or not isinstance(jpeg, bytes):
                    raise RuntimeError("expected a JSON text message, then a JPEG")
                self.latencies_ms.append((time.time_ns() - json.loads(meta)["sent_ns"]) / 1e6)
                self._got_frame(len(jpeg))
                await ws.send("ack")


class VideoViewer(StreamClient):
    """A viewer of ``/stream.video`` (``url``, with its ``?preset=``) that acknowledges each
    frame as soon as it has it, saying when it arrived (``recv_ms``), as the browser does
    after drawing; it does not decode. ``latencies_ms``: per frame, from the server
    publishing it (``sent_ns``) to having it; ``level`` and ``bitrate_bps``: of the last
    frame; ``keyframes``: IDRs received."""

    kind = "video"

    def __init__(self, url: str, token: str | None) -> None:
        super().__init__()
        self.url, self.token = url, token
        self.latencies_ms: list[float] = []
        self.level = ""
        self.bitrate_bps = 0
        self.keyframes = 0

    async def _receive(self) -> None:
        async with _connect(self.url, self.token, open_timeout_s=60) as ws:
            while True:
                text = await ws.recv()
                unit = await ws.recv()
                recv_ms = time.monotonic() * 1000
                if not isinstance(text, str) or not isinstance(unit, bytes):
                    raise RuntimeError("expected a JSON text message, then an access unit")
                meta = json.loads(text)
                self.latencies_ms.append((time.time_ns() - meta["sent_ns"]) / 1e6)
                self.level, self.bitrate_bps = meta["level"], meta["bitrate_bps"]
                self.keyframes += bool(meta["key"])
                self._got_frame(len(unit))
                await ws.send(json.dumps({"ack": meta["seq"], "recv_ms": recv_ms}))


def _small_socket(rcvbuf: int) -> socket.socket:
    """A non-blocking TCP socket whose receive buffer is ``rcvbuf`` bytes."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # before connecting: the window scale is agreed in the handshake
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.setblocking(False)
    return sock


class SlowWsViewer(StreamClient):
    """A viewer on ``/stream`` over a raw socket with a small receive buffer (``rcvbuf``
    bytes): acks each frame ``ack_delay_s`` after it arrived and, every ``read_s`` seconds,
    stops reading its socket for ``stall_s`` (right after an ack, so a frame is in flight;
    pings are answered only when it reads, so ``stall_s`` stays below the server's ping
    timeout)."""

    kind = "ws"

    def __init__(
        self,
        host: str,
        port: int,
        token: str | None,
        *,
        rcvbuf: int,
        ack_delay_s: float,
        read_s: float,
        stall_s: float,
    ) -> None:
        super().__init__()
        self.host, self.port, self.token = host, port, token
        self.rcvbuf, self.ack_delay_s = rcvbuf, ack_delay_s
        self.read_s, self.stall_s = read_s, stall_s

    async def _receive(self) -> None:
        from websockets.client import ClientProtocol
        from websockets.frames import Opcode
        from websockets.http11 import Response
        from websockets.uri import parse_uri

        loop = asyncio.get_running_loop()
        proto = ClientProtocol(parse_uri(f"ws://{self.host}:{self.port}/stream"), max_size=None)
        with _small_socket(self.rcvbuf) as sock:

            async def flush() -> None:
                for data in proto.data_to_send():
                    if data:
                        await loop.sock_sendall(sock, data)

            await loop.sock_connect(sock, (self.host, self.port))
            request = proto.connect()
            if self.token:
                request.headers["Authorization"] = f"token {self.token}"
            proto.send_request(request)
            await flush()
            stall_at = time.monotonic() + self.read_s
            parts: list[bytes] = []
            opcode = Opcode.BINARY
            while True:
                data = await loop.sock_recv(sock, 65536)
                if data:
                    proto.receive_data(data)
                else:
                    proto.receive_eof()
                await flush()  # pongs
                for event in proto.events_received():
                    if isinstance(event, Response):
                        if event.status_code != 101:
                            raise RuntimeError(f"upgrade refused: HTTP {event.status_code}")
                        continue
                    if event.opcode in (Opcode.TEXT, Opcode.BINARY):
                        opcode = event.opcode  # of the message (CONT: its continuations)
                    elif event.opcode is not Opcode.CONT:
                        continue
                    parts.append(event.data)
                    if not event.fin:
                        continue
                    message, parts = b"".join(parts), []
                    if opcode is Opcode.TEXT:
                        continue  # the frame's metadata
                    self._got_frame(len(message))
                    await asyncio.sleep(self.ack_delay_s)
                    proto.send_text(b"ack")
                    await flush()
                    if time.monotonic() >= stall_at:
                        # the next frame is on its way: leave it in the buffers
                        self.stalls += 1
                        await asyncio.sleep(self.stall_s)
                        stall_at = time.monotonic() + self.read_s
                if not data:
                    raise RuntimeError(f"the server closed the connection ({proto.close_code})")


class SlowMjpegReader(StreamClient):
    """``/stream.mjpg`` over a raw socket with a small receive buffer (``rcvbuf`` bytes),
    read at ``bytes_per_s``; ``frames``: complete parts received."""

    kind = "mjpeg"
    TICK_S = 0.25

    def __init__(
        self, host: str, port: int, token: str | None, *, rcvbuf: int, bytes_per_s: int
    ) -> None:
        super().__init__()
        self.host, self.port, self.token = host, port, token
        self.rcvbuf, self.bytes_per_s = rcvbuf, bytes_per_s
        self.parts = MjpegParts()

    def _take(self, data: bytes) -> None:
        self.bytes += len(data)
        self.parts.feed(data)
        self.frames = self.parts.parts
        if self.frames:
            self.first_frame.set()

    async def _receive(self) -> None:
        loop = asyncio.get_running_loop()
        rate = self.bytes_per_s
        auth = f"Authorization: token {self.token}\r\n" if self.token else ""
        with _small_socket(self.rcvbuf) as sock:
            await loop.sock_connect(sock, (self.host, self.port))
            # HTTP/1.0: the body is the bare multipart stream (no chunked encoding)
            await loop.sock_sendall(
                sock,
                (
                    f"GET /stream.mjpg HTTP/1.0\r\nHost: {self.host}:{self.port}\r\n{auth}\r\n"
                ).encode(),
            )
            head = b""
            while b"\r\n\r\n" not in head:
                data = await loop.sock_recv(sock, 1024)
                if not data or len(head) > 16384:
                    raise RuntimeError(f"no HTTP response: {head[:80]!r}")
                head += data
            head, _, body = head.partition(b"\r\n\r\n")
            if not re.match(rb"HTTP/1\.[01] 200 ", head):
                raise RuntimeError(f"HTTP response {head.splitlines()[0]!r}")
            self._take(body)
            t0 = time.monotonic()
            while True:
                allowed = int(rate * (time.monotonic() - t0)) - self.bytes
                if allowed < max(1, min(1024, int(rate * self.TICK_S))):
                    await asyncio.sleep(self.TICK_S)
                    continue
                data = await loop.sock_recv(sock, min(allowed, 65536))
                if not data:
                    raise RuntimeError("the server closed the connection")
                self._take(data)


async def wait_first_frames(clients: Sequence[StreamClient], timeout_s: float) -> None:
    """Until every client has its first frame; RuntimeError if one ends without, TimeoutError
    after ``timeout_s``."""

    async def one(v: StreamClient) -> None:
        while not v.first_frame.is_set() and not v.done:
            try:
                await asyncio.wait_for(v.first_frame.wait(), 0.5)
            except TimeoutError:
                pass
        if not v.first_frame.is_set():
            raise RuntimeError(f"a {v.kind} viewer got no frame: {v.error}")

    await asyncio.wait_for(asyncio.gather(*(one(v) for v in clients)), timeout_s)


async def cancel(tasks: Sequence[asyncio.Task[None]]) -> None:
    """Cancel the tasks (the clients' ``run()``) and wait until they have ended."""
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
