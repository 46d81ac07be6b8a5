"""Connection limits of the console's public port, in front of uvicorn's HTTP protocol.

Uvicorn never times out a request whose headers do not finish, and caps no connections: two
clients holding 10 000 half-sent requests each exhausted the file descriptors, the console
stopped answering and its log grew by the accept loop's tracebacks. :class:`GuardedH11Protocol`
(uvicorn's ``http=`` protocol class) adds

* a header-read timeout: a connection that has not sent a complete request head within
  ``HEADER_TIMEOUT_S`` seconds of connecting, or of its previous response, is closed (a
  request whose head is in, e.g. an upload or a WebSocket, is not limited by it);
* a cap per client address (``MAX_PER_CLIENT``) and in all (``MAX_TOTAL``), WebSockets
  included: a connection over a cap is closed at once, before anything is read;

and :func:`quiet_repeated_logs` keeps a message that repeats (``socket.accept() out of
system resource``) to one line per ``period_s`` with a count of the ones left out. The cap
in all stays below the process's limit of open files (:func:`total_cap`), so the caps, not
the operating system, decide.

``TRIFUSE_HEADER_TIMEOUT_S``, ``TRIFUSE_MAX_CONNECTIONS_PER_CLIENT`` and
``TRIFUSE_MAX_CONNECTIONS`` override the defaults (tests use short ones).
"""

from __future__ import annotations

import asyncio
import logging
import os
import resource
import time
from collections.abc import Callable

from uvicorn.protocols.http.h11_impl import H11Protocol

HEADER_TIMEOUT_S = float(os.environ.get("TRIFUSE_HEADER_TIMEOUT_S", "10"))
MAX_PER_CLIENT = int(os.environ.get("TRIFUSE_MAX_CONNECTIONS_PER_CLIENT", "64"))
MAX_TOTAL = int(os.environ.get("TRIFUSE_MAX_CONNECTIONS", "512"))

log = logging.getLogger("trifuse.connections")


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a header-read timeout and connection caps."""

    _header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        host = self.client[0] if self.client else None
        same = sum(
            1 for c in self.connections if getattr(c, "client", None) and c.client[0] == host
        )
        total = total_cap()
        if len(self.connections) > total or (host is not None and same > MAX_PER_CLIENT):
            log.warning(
                "refused connections over the caps (%d per client, %d in all)",
                MAX_PER_CLIENT,
                total,
            )
            self.connections.discard(self)  # now: its connection_lost comes later
            transport.abort()
            return
        self._arm()

    def data_received(self, data: bytes) -> None:
        if self._header_timer is None and self._between_requests():
            self._arm()  # the next request of a kept-alive connection
        super().data_received(data)
        if not self._between_requests():
            self._disarm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _between_requests(self) -> bool:
        return self.cycle is None or self.cycle.response_complete

    def _arm(self) -> None:
        self._disarm()
        self._header_timer = self.loop.call_later(HEADER_TIMEOUT_S, self._headers_too_slow)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if self.transport.get_protocol() is self and self._between_requests():
            self.transport.close()  # upgraded connections belong to another protocol


class _RepeatFilter(logging.Filter):
    """Lets a message through once per ``period_s`` (by its text, with its traceback only
    the first time), and says how many it left out. ``clock``: monotonic seconds (tests pass
    their own)."""

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.period_s = period_s
        self._clock = clock
        self._last: dict[str, float] = {}
        self._dropped: dict[str, int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = str(record.msg).split("\n", 1)[0][:200]
        now = self._clock()
        if key in self._last:
            if now - self._last[key] < self.period_s:
                self._dropped[key] = self._dropped.get(key, 0) + 1
                return False
            record.exc_info = None  # the traceback was logged the first time
            dropped = self._dropped.pop(key, 0)
            if dropped:
                record.msg = f"{record.msg} (and {dropped} more like it)"
        self._last[key] = now
        return True


def quiet_repeated_logs(period_s: float = 10.0) -> None:
    """Rate-limit repeated messages of asyncio's accept loop, uvicorn and the caps."""
    for name in ("asyncio", "trifuse.connections", "uvicorn.error"):
        logging.getLogger(name).addFilter(_RepeatFilter(period_s))


def total_cap() -> int:
    """``MAX_TOTAL``, or fewer when the process may open fewer files (128 kept for the
    console's own files, pipes and its Viser port)."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return MAX_TOTAL
    return max(16, min(MAX_TOTAL, soft - 128))
