"""Push clients for drivers: :class:`PushClient` (blocking, ``websockets.sync``) and its
asyncio twin :class:`AsyncPushClient` (``websockets.asyncio``). Both take the same
arguments, encode frames with :func:`~app.sources.push.encode.encode_frame` and handle the
console's replies the same way (:class:`_ClientState`): error replies to messages sent
without ``ack`` are collected as they arrive, and an acknowledged message waits for its
own reply.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Mapping
from typing import Any

from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.encode import encode_frame
from trifuse.calib.rig import Rig

TOKEN_ENV = "TRIFUSE_TOKEN"
"""Environment variable holding the console's token, read by ``trifuse serve`` and by the
drivers (safer than ``--token``: not shown by ``ps``)."""
MAX_REPLY_BYTES = 1 << 20
"""Largest reply a client accepts (replies are short JSON objects)."""


class PushRejected(RuntimeError):
    """The console rejected a message the client sent (its error reply)."""

    def __init__(self, reply: Mapping[str, Any]) -> None:
        super().__init__(str(reply.get("error", reply)))
        self.reply = dict(reply)


def _modality_lookup(modalities: Mapping[str, str] | Rig | None) -> Mapping[str, str]:
    if modalities is None:
        return {}
    if isinstance(modalities, Rig):
        return {s: modalities[s].modality for s in modalities.names}
    return dict(modalities)


def _parse_reply(text: str | bytes) -> dict[str, Any]:
    try:
        reply = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {"ok": False, "error": f"unreadable reply {text!r:.200}"}
    return reply if isinstance(reply, dict) else {"ok": False, "error": f"reply {reply!r}"}


def _with_token(headers: Mapping[str, str] | None, token: str | None) -> dict[str, str]:
    """``headers`` plus the console's ``Authorization`` header when there is a token."""
    out = dict(headers or {})
    if token:
        out["Authorization"] = f"token {token}"
    return out


class _ClientState:
    """What both clients keep and how they read replies.

    Args:
        url: the console's ingest URL, e.g. ``ws://console:8000/ingest``.
        modalities: sensor -> modality, or the rig (tells thermal from TOF amplitude).
        encode_options: passed to :func:`encode_frame` (``color_encoding``,
            ``jpeg_quality``, ``value_encoding``).
        open_timeout_s: connection timeout, seconds.
        additional_headers: more HTTP headers for the connection.
        on_error: called with each error reply collected (None: nothing is called).
        token: the console's token (sent as ``Authorization: token ...``).

    Attributes:
        errors: the error replies collected so far (JSON objects, see the protocol).
        sent, sent_bytes: messages and bytes sent; ``sent`` is the last message's ``seq``.
    """

    def __init__(
        self,
        url: str,
        modalities: Mapping[str, str] | Rig | None = None,
        *,
        encode_options: Mapping[str, Any] | None = None,
        open_timeout_s: float = 10.0,
        additional_headers: Mapping[str, str] | None = None,
        on_error: Callable[[dict[str, Any]], Any] | None = None,
        token: str | None = None,
    ) -> None:
        self.url = url
        self.modalities = _modality_lookup(modalities)
        self.encode_options = dict(encode_options or {})
        self.open_timeout_s = open_timeout_s
        self.additional_headers = _with_token(additional_headers, token)
        self.errors: list[dict[str, Any]] = []
        self.on_error = on_error
        self.sent = 0
        self.sent_bytes = 0
        self._ws: Any = None
        self._opened()

    def _opened(self) -> None:
        """The end of ``__init__`` (the blocking client connects there)."""

    def _connect_options(self) -> dict[str, Any]:
        """Keyword arguments of ``websockets``' ``connect`` (sync and asyncio alike)."""
        return {
            "open_timeout": self.open_timeout_s,
            "compression": None,  # JPEG/PNG payloads do not compress
            "proxy": None,
            "max_size": MAX_REPLY_BYTES,
            "additional_headers": self.additional_headers,
        }

    def _encode(self, frame: Frame, ack: bool) -> bytes:
        return encode_frame(
            frame, self.modalities.get(frame.sensor), ack=ack, **self.encode_options
        )

    def _count(self, message: bytes) -> int:
        """Count a message just sent; returns its ``seq``."""
        self.sent += 1
        self.sent_bytes += len(message)
        return self.sent

    def _note(self, text: str | bytes) -> None:
        """A reply to no message being waited for: kept if it is an error."""
        self._keep(_parse_reply(text))

    def _keep(self, reply: dict[str, Any]) -> None:
        if not reply.get("ok", False):
            self.errors.append(reply)
            if self.on_error is not None:
                self.on_error(reply)

    def _reply_to(self, seq: int, text: str | bytes) -> dict[str, Any] | None:
        """The reply to message ``seq`` if ``text`` is it (raises PushRejected if it is an
        error); else None, the reply noted as by :meth:`_note`."""
        reply = _parse_reply(text)
        if reply.get("seq") == seq:
            if not reply.get("ok", False):
                raise PushRejected(reply)
            return reply
        self._keep(reply)
        return None


class PushClient(_ClientState):
    """A blocking push client (``websockets.sync``): connects when made, sends frames,
    reads replies. Arguments: see :class:`_ClientState`.

    Error replies to messages sent without ``ack`` arrive later; they are collected in
    :attr:`errors` (checked on every send, never blocking) and handed to ``on_error``.
    """

    def _opened(self) -> None:
        from websockets.sync.client import connect

        self._ws = connect(self.url, **self._connect_options())

    def poll(self) -> None:
        """Read the replies that have arrived (errors go to :attr:`errors`), never blocking."""
        while True:
            try:
                text = self._ws.recv(timeout=0)
            except TimeoutError:
                return
            self._note(text)

    def send_bytes(
        self, message: bytes, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Send one encoded message. With ``ack`` (the header must ask for it, or an error
        reply is awaited) wait for its reply: return it, or raise PushRejected."""
        self.poll()
        self._ws.send(message)
        seq = self._count(message)
        if not ack:
            return None
        while True:
            reply = self._reply_to(seq, self._ws.recv(timeout=timeout_s))
            if reply is not None:
                return reply

    def send(
        self, frame: Frame, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Encode and send one frame (see :meth:`send_bytes`)."""
        return self.send_bytes(self._encode(frame, ack), ack=ack, timeout_s=timeout_s)

    def close(self) -> None:
        self._ws.close()

    def __enter__(self) -> PushClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncPushClient(_ClientState):
    """The asyncio twin of :class:`PushClient` (``websockets.asyncio``; the same
    arguments), connected by :meth:`connect` or ``async with``::

    async with AsyncPushClient(url, rig) as client:
        await client.send(frame)

    Unlike :class:`PushClient` it does not read the replies that have arrived before each
    send (:meth:`poll` does).
    """

    async def connect(self) -> AsyncPushClient:
        from websockets.asyncio.client import connect

        self._ws = await connect(self.url, **self._connect_options())
        return self

    async def __aenter__(self) -> AsyncPushClient:
        return await self.connect()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def poll(self) -> None:
        """Collect the replies that have arrived, never blocking."""
        while True:
            try:
                text = await asyncio.wait_for(self._ws.recv(), timeout=0.0001)
            except TimeoutError:
                return
            self._note(text)

    async def send_bytes(
        self, message: bytes, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Send one encoded message; with ``ack`` wait for its reply (PushRejected on error)."""
        await self._ws.send(message)
        seq = self._count(message)
        if not ack:
            return None
        while True:
            reply = self._reply_to(seq, await asyncio.wait_for(self._ws.recv(), timeout_s))
            if reply is not None:
                return reply

    async def send(
        self, frame: Frame, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Encode and send one frame."""
        return await self.send_bytes(self._encode(frame, ack), ack=ack, timeout_s=timeout_s)

    async def close(self) -> None:
        if self._ws is not None:
            await self._ws.close()
