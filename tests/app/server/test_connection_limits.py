"""The public port against connection exhaustion (app/server/middleware/connections.py): half-sent
requests are closed after the header timeout, a client cannot hold more than its share of
connections, the total stays below the file limit, and a message that repeats is logged once
per period."""

from __future__ import annotations

import http.client
import logging
import os
import resource
import socket
import time

import pytest

from tests.browser_support import start_console
from tests.support import FakeClock, wait_until
from trifuse.app.devtools.console_process import stop_process
from trifuse.app.server.middleware.connections import _RepeatFilter

HEADER_TIMEOUT_S = 3.0
PER_CLIENT = 40
TOTAL = 100
HALF_REQUEST = b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "


def is_open(sock: socket.socket) -> bool:
    """True while the console keeps ``sock`` open (nothing to read and no close or reset)."""
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) != b""
    except BlockingIOError:
        return True
    except OSError:
        return False


def half_sent(source: str, port: int, count: int) -> list[socket.socket]:
    """``count`` connections from the loopback address ``source``, each with a request head
    that never ends."""
    socks = []
    for _ in range(count):
        sock = socket.socket()
        sock.bind((source, 0))
        try:
            sock.connect(("127.0.0.1", port))
            sock.sendall(HALF_REQUEST)
        except OSError:
            pass  # refused or reset at once: counts as closed below
        socks.append(sock)
    return socks


def settle_at(socks: list[socket.socket], count: int, what: str) -> None:
    """Until exactly ``count`` of ``socks`` are open: the console has dealt with them (it
    may take long on a busy machine)."""
    wait_until(lambda: sum(is_open(s) for s in socks) == count, what)


@pytest.mark.slow
def test_half_sent_requests_neither_starve_the_console_nor_flood_its_log() -> None:
    env = {
        **os.environ,
        "TRIFUSE_HEADER_TIMEOUT_S": str(HEADER_TIMEOUT_S),
        "TRIFUSE_MAX_CONNECTIONS_PER_CLIENT": str(PER_CLIENT),
        "TRIFUSE_MAX_CONNECTIONS": str(TOTAL),
    }
    proc, console = start_console([], env=env)
    port = int(console.url.rsplit(":", 1)[1])
    socks: list[socket.socket] = []
    try:
        # a file limit the attack would reach without the caps (the caps stay below it)
        _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        resource.prlimit(proc.pid, resource.RLIMIT_NOFILE, (400, hard))
        first = half_sent("127.0.0.2", port, 3 * PER_CLIENT)
        second = half_sent("127.0.0.3", port, 3 * PER_CLIENT)
        socks += first + second
        settle_at(first, PER_CLIENT, "one client's share")
        settle_at(second, PER_CLIENT, "another client's share")
        assert console.get("/api/status")["error"] is None  # the operator is still served

        third = half_sent("127.0.0.4", port, 3 * PER_CLIENT)
        socks += third
        settle_at(third, TOTAL - 2 * PER_CLIENT, "the cap in all")

        settle_at(socks, 0, "the header timeout to close every half-sent request")
        assert console.get("/api/status")["error"] is None
        # a complete request on a kept-alive connection is not cut by the timeout
        keep = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        keep.connect()
        first = keep.sock
        try:
            for _ in range(2):
                auth = {"Authorization": f"token {console.token}"}
                keep.request("GET", "/api/status", headers=auth)
                reply = keep.getresponse()
                assert reply.status == 200
                reply.read()
                time.sleep(HEADER_TIMEOUT_S / 2)
            assert keep.sock is first  # the same connection throughout
        finally:
            keep.close()
    finally:
        for sock in socks:
            sock.close()
        stop_process(proc)
    log = proc.stdout.read()
    assert log.count("refused connections over the caps") == 1, log[-3000:]
    assert len(log) < 5000, log[-3000:]


def test_a_repeating_message_is_logged_once_per_period() -> None:
    logger = logging.getLogger("trifuse.test_repeats")
    logger.propagate = False
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logger.addHandler(handler)
    clock = FakeClock()
    limiter = _RepeatFilter(period_s=0.2, clock=clock)
    logger.addFilter(limiter)
    try:
        for _ in range(1000):
            try:
                raise OSError(24, "Too many open files")
            except OSError:
                logger.exception("socket.accept() out of system resource\nsocket: fd=7")
        logger.warning("another message")
        clock.advance(0.25)
        logger.exception("socket.accept() out of system resource\nsocket: fd=9")
    finally:
        logger.removeFilter(limiter)
        logger.removeHandler(handler)
    texts = [r.getMessage() for r in records]
    assert len(records) == 3, texts
    assert records[0].exc_info is not None  # the first one with its traceback
    assert texts[1] == "another message"
    assert texts[2].endswith("(and 999 more like it)") and records[2].exc_info is None
