"""The console's Foxglove port (issue 29): a relay in front of foxglove-sdk's server that
bounds what clients can make the console hold.

foxglove-sdk's server takes any number of clients, queues up to 1024 messages for each and
gathers a client's message up to 64 MiB; 16 clients that never read took the console from
0.6 to 2.15 GiB, not given back. :mod:`app.server.runtime.foxglove_live` therefore starts the
SDK's server on a random address of 127.0.0.0/8 and an ephemeral port with a short queue
(``MESSAGE_BACKLOG``), and the console's port is :class:`FoxgloveGate` (a thread and event
loop of its own):

- at most :data:`MAX_CLIENTS` clients at once: one more gets ``503 Service Unavailable``
  once its request head is in; beyond :data:`MAX_WAITING` connections still sending their
  head, a connection is closed at once; a head must come within :data:`HANDSHAKE_S`;
- towards a client the relay passes the server's bytes only as fast as the client takes
  them (about :data:`RELAY_BUFFER_BYTES` waiting at most), so a slow client's backlog stays
  in the SDK's queue; when that is full the SDK drops the oldest message waiting for the
  new one: a slow client loses the oldest messages (the fused video may show artefacts
  until its next key frame, a second at most);
- a client that takes nothing for :data:`STALL_S` while data waits for it is disconnected
  (its place and its queue are freed);
- from a client the relay reads the WebSocket frames' headers as it passes them on; a
  message longer than :data:`MAX_CLIENT_MESSAGE_BYTES` (a client sends only subscriptions
  and the like) ends the connection before the server has more of it.

A client therefore holds at most about the SDK's queue times the largest message (with the
default head a thermal image or a colour JPEG, about 215 KB: about 7 MB) plus 1 MiB of
buffers, and all clients at most :data:`MAX_CLIENTS` times that.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import socket
import threading
import time

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
MAX_CLIENTS = 8
"""Foxglove clients at once (one more gets 503)."""
MAX_WAITING = 8
"""Connections still sending their request head at most, beyond the clients (more: closed
at once)."""
HANDSHAKE_S = 10.0
"""A connection's request head must be in within this (else it is closed)."""
STALL_S = 30.0
"""A client that takes nothing for this long while data waits for it is disconnected."""
RELAY_BUFFER_BYTES = 256 * 1024
"""The relay's write buffer in each direction of a connection (it reads no more while a
side holds this much)."""
RELAY_CHUNK_BYTES = 64 * 1024
"""The relay reads at most this much at once (its read buffer holds twice as much)."""
MAX_CLIENT_MESSAGE_BYTES = 1024 * 1024
"""A client's WebSocket message (all its frames) at most; a larger one ends the connection
(the SDK would gather up to 64 MiB; a client only sends subscriptions and the like)."""
LOG_PERIOD_S = 10.0
"""The port's warnings (refused connections, clients closed) come once per this at most."""


def in_use_message(port: int) -> str:
    """What to say when ``--foxglove-port`` is taken."""
    return (
        f"--foxglove-port {port} on {LOOPBACK} is in use (another console or Foxglove "
        "server?); choose another --foxglove-port"
    )


class ClientMessageError(ValueError):
    """A Foxglove client sent a WebSocket message or frame over the relay's limits."""


def _full_response(max_clients: int) -> bytes:
    """The answer to a client over the limit: 503 and why."""
    body = (
        f"the console's Foxglove port serves {max_clients} clients at most; close one and "
        "connect again\n"
    ).encode()
    return (
        b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\n"
        + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
        + body
    )


class FoxgloveGate:
    """The console's Foxglove port: accepts on 127.0.0.1:``port`` and relays each
    WebSocket connection, byte for byte, to the SDK's server at ``upstream`` (host, port),
    with the limits of the module doc (``max_clients``, ``handshake_s`` and ``stall_s``:
    :data:`MAX_CLIENTS`, :data:`HANDSHAKE_S`, :data:`STALL_S`). Its own thread and event
    loop; binds in the constructor (OSError in one line if the port is taken), serves from
    :meth:`start`.

    Attributes:
        clients: connections relayed now; ``waiting``: connections whose request head is
            not in yet; ``refused``: connections refused over the limits so far.
    """

    def __init__(
        self,
        port: int,
        upstream: tuple[str, int],
        max_clients: int = MAX_CLIENTS,
        handshake_s: float = HANDSHAKE_S,
        stall_s: float = STALL_S,
    ) -> None:
        self.upstream = upstream
        self.max_clients, self.handshake_s, self.stall_s = max_clients, handshake_s, stall_s
        self.clients = self.waiting = self.refused = 0
        self._next_log = 0.0
        self._writers: set[asyncio.StreamWriter] = set()  # both sides of every connection
        self._handlers: set[asyncio.Task] = set()
        self._stopping = asyncio.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((LOOPBACK, port))
            self._sock.listen(64)
        except OSError as e:
            self._sock.close()
            if e.errno == errno.EADDRINUSE:
                raise OSError(in_use_message(port)) from None
            raise OSError(f"cannot serve Foxglove on {LOOPBACK}:{port}: {e.strerror}") from None
        self.port: int = self._sock.getsockname()[1]
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name="foxglove-gate", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Close the port and every connection. Idempotent."""
        if self._thread.ident is None:  # never started
            self._sock.close()
            if not self._loop.is_closed():
                self._loop.close()
            return
        with contextlib.suppress(RuntimeError):  # the loop has ended already
            self._loop.call_soon_threadsafe(self._stopping.set)
        self._thread.join(timeout_s)

    def _run(self) -> None:
        with asyncio.Runner(loop_factory=lambda: self._loop) as runner:  # cancels the rest
            runner.run(self._serve())

    async def _serve(self) -> None:
        server = await asyncio.start_server(self._accept, sock=self._sock, limit=RELAY_CHUNK_BYTES)
        await self._stopping.wait()
        server.close()
        for writer in list(self._writers):
            writer.transport.abort()
        if self._handlers:  # they end by themselves now (cancelling them would log errors)
            await asyncio.wait(list(self._handlers), timeout=self.handshake_s)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.clients + self.waiting >= self.max_clients + MAX_WAITING:
            self._refused()
            writer.transport.abort()
            return
        self._writers.add(writer)
        self._handlers.add(asyncio.current_task())  # type: ignore[arg-type]
        self.waiting += 1
        try:
            try:
                async with asyncio.timeout(self.handshake_s):
                    head = await reader.readuntil(b"\r\n\r\n")
            finally:
                self.waiting -= 1
            if self.clients >= self.max_clients:
                self._refused()
                writer.write(_full_response(self.max_clients))
                async with asyncio.timeout(self.handshake_s):
                    await writer.drain()
                return
            self.clients += 1
            try:
                await self._relay(head, reader, writer)
            finally:
                self.clients -= 1
        except (TimeoutError, OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass  # the client left, was too slow or sent garbage: nothing to keep
        finally:
            self._writers.discard(writer)
            self._handlers.discard(asyncio.current_task())  # type: ignore[arg-type]
            writer.transport.abort()

    async def _relay(
        self, head: bytes, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Both directions until one side ends or stalls; then the SDK's server is told the
        client left (end of file) and what it still sends is read and dropped."""
        async with asyncio.timeout(self.handshake_s):
            up_reader, up_writer = await asyncio.open_connection(
                *self.upstream, limit=RELAY_CHUNK_BYTES
            )
        self._writers.add(up_writer)
        try:
            for w in (writer, up_writer):
                w.transport.set_write_buffer_limits(high=RELAY_BUFFER_BYTES)
            up_writer.write(head)
            pipes = [
                asyncio.create_task(_pipe_frames(reader, up_writer, self.stall_s)),
                asyncio.create_task(_pipe(up_reader, writer, self.stall_s)),
            ]
            try:
                await asyncio.wait(pipes, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for pipe in pipes:
                    pipe.cancel()
                ends = await asyncio.gather(*pipes, return_exceptions=True)
            if isinstance(ends[0], ClientMessageError):
                self._warn(f"closed a client's connection: {ends[0]}")
            writer.transport.abort()
            with contextlib.suppress(OSError):
                up_writer.write_eof()
            with contextlib.suppress(OSError, TimeoutError):
                async with asyncio.timeout(self.handshake_s):
                    await _discard(up_reader)
        finally:
            self._writers.discard(up_writer)
            up_writer.transport.abort()

    def _refused(self) -> None:
        self.refused += 1
        self._warn(
            f"refused a connection ({self.max_clients} clients at most, {self.refused} "
            "refused so far)"
        )

    def _warn(self, message: str) -> None:
        """Logged once per :data:`LOG_PERIOD_S` at most (the others are left out)."""
        now = time.monotonic()
        if now >= self._next_log:
            self._next_log = now + LOG_PERIOD_S
            log.warning("Foxglove port: %s", message)


async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter, stall_s: float) -> None:
    """``src`` to ``dst`` as fast as ``dst`` takes it; TimeoutError if it takes nothing
    for ``stall_s`` while data waits."""
    while data := await src.read(RELAY_CHUNK_BYTES):
        dst.write(data)
        async with asyncio.timeout(stall_s):
            await dst.drain()


async def _pipe_frames(
    src: asyncio.StreamReader, dst: asyncio.StreamWriter, stall_s: float
) -> None:
    """A client's WebSocket frames (RFC 6455, section 5.2) to the server as they come, as
    :func:`_pipe` does, until the client's end of file; ClientMessageError for a message
    larger than :data:`MAX_CLIENT_MESSAGE_BYTES` or a control frame over 125 bytes."""
    message = 0  # bytes of the message so far (its frames before the last)
    while head := await src.read(2):
        if len(head) == 1:
            head += await src.readexactly(1)
        fin, opcode, size = head[0] & 0x80, head[0] & 0x0F, head[1] & 0x7F
        extra = await src.readexactly({126: 2, 127: 8}.get(size, 0))
        if extra:
            size = int.from_bytes(extra, "big")
        mask = await src.readexactly(4 if head[1] & 0x80 else 0)
        if opcode >= 8:  # ping, pong, close: on their own, at most 125 bytes
            if size > 125:
                raise ClientMessageError(
                    f"expected control frames of 125 bytes at most, got {size} bytes"
                )
        else:
            message += size
            if message > MAX_CLIENT_MESSAGE_BYTES:
                raise ClientMessageError(
                    f"expected messages of {MAX_CLIENT_MESSAGE_BYTES} bytes at most, got "
                    f"one of {message} bytes or more"
                )
            if fin:
                message = 0
        dst.write(head + extra + mask)
        while size:
            data = await src.read(min(size, RELAY_CHUNK_BYTES))
            if not data:
                raise asyncio.IncompleteReadError(b"", size)
            dst.write(data)
            size -= len(data)
            async with asyncio.timeout(stall_s):
                await dst.drain()


async def _discard(src: asyncio.StreamReader) -> None:
    """Read ``src`` to its end, keeping nothing."""
    while await src.read(RELAY_CHUNK_BYTES):
        pass
