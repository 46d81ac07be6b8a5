"""The emulated radio link (app/devtools/netem.py): set up and torn down, shaped as asked
(round trip, throughput and loss across it), and Chromium inside its namespace.

Needs root and iproute2; skipped, saying why, elsewhere."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.support import poll_until
from trifuse.app.devtools.netem import (
    IP,
    EmulatedLink,
    LinkShape,
    emulated_link,
    netns_available,
    remove_stale,
)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(netns_available() is not None, reason=str(netns_available())),
]

PORT = 45831

ECHO_SERVER = """
import socket, sys
srv = socket.socket(); srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
srv.bind((sys.argv[1], int(sys.argv[2]))); srv.listen(16)
print("ready", flush=True)
while True:
    c, _ = srv.accept()
    c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    while (d := c.recv(65536)):
        c.sendall(d)
    c.close()
"""

UDP_ECHO = """
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind((sys.argv[1], int(sys.argv[2])))
print("ready", flush=True)
while True:
    d, a = s.recvfrom(64)
    s.sendto(d, a)
"""

SINK = """
import json, socket, sys, time
srv = socket.socket(); srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
srv.bind((sys.argv[1], int(sys.argv[2]))); srv.listen(1)
print("ready", flush=True)
c, _ = srv.accept()
n, t0, t1 = 0, None, None
while (d := c.recv(1 << 20)):
    now = time.monotonic()
    t0 = now if t0 is None else t0
    n, t1 = n + len(d), now
print(json.dumps({"bytes": n, "seconds": t1 - t0}), flush=True)
"""


def _in_namespace(link: EmulatedLink, code: str) -> subprocess.Popen:
    """Python ``code`` inside the link's namespace, listening on its address; returns once
    it printed ``ready``."""
    proc = link.popen(
        [sys.executable, "-c", code, link.ns_ip, str(PORT)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.strip() == "ready", proc.stderr.read() if proc.stderr else line
    return proc


def _exists(link: EmulatedLink) -> tuple[bool, bool]:
    """(the namespace is listed, the host's end of the link exists)."""
    names = subprocess.run([IP, "netns", "list"], capture_output=True, text=True).stdout
    listed = any(line.split()[0] == link.namespace for line in names.splitlines() if line)
    return listed, Path(f"/sys/class/net/{link.host_if}").exists()


def test_round_trip_is_twice_the_delay() -> None:
    delay_ms = 40.0
    with emulated_link(100, delay_ms, 0, name="rtt") as link:
        server = _in_namespace(link, ECHO_SERVER)
        try:
            connects, echoes = [], []
            for _ in range(8):
                t0 = time.perf_counter()
                with socket.create_connection((link.ns_ip, PORT), timeout=10) as sock:
                    connects.append((time.perf_counter() - t0) * 1e3)
                    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    for _ in range(3):
                        t0 = time.perf_counter()
                        sock.sendall(b"x" * 64)
                        assert sock.recv(64) == b"x" * 64
                        echoes.append((time.perf_counter() - t0) * 1e3)
        finally:
            server.kill()
            server.wait()
    # a SYN/SYN-ACK and a request/answer each cross the link both ways: 2 x delay, and
    # never less (netem holds every packet delay_ms); the slack above is the machine's
    for rtt in (statistics.median(connects), statistics.median(echoes)):
        assert 2 * delay_ms * 0.98 <= rtt <= 2 * delay_ms + 40, (connects, echoes)


def test_throughput_is_the_rate() -> None:
    rate_mbit = 8.0
    with emulated_link(rate_mbit, 10, 0, name="rate") as link:
        sink = _in_namespace(link, SINK)
        try:
            with socket.create_connection((link.ns_ip, PORT), timeout=10) as sock:
                chunk = b"\0" * 65536
                t_end = time.monotonic() + 2.5
                while time.monotonic() < t_end:
                    sock.sendall(chunk)
            out, err = sink.communicate(timeout=60)
        finally:
            sink.kill()
            sink.wait()
        received = link.received_bytes()
    got = json.loads(out)
    assert got["seconds"] > 1.5, (got, err)
    mbit = got["bytes"] * 8 / got["seconds"] / 1e6
    # TCP payload: at most the link's rate; at 0 % loss it fills most of it
    assert 0.7 * rate_mbit <= mbit <= 1.02 * rate_mbit, got
    assert received >= got["bytes"]  # the namespace's counter: all of it, with the headers


def test_loss_drops_packets() -> None:
    sent = 400
    with emulated_link(100, 0, 20, name="loss") as link:
        echo = _in_namespace(link, UDP_ECHO)
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
                sock.settimeout(1.0)
                for i in range(sent):
                    sock.sendto(str(i).encode(), (link.ns_ip, PORT))
                    time.sleep(0.001)
                back = set()
                with contextlib.suppress(TimeoutError):
                    while True:
                        back.add(sock.recv(64))
        finally:
            echo.kill()
            echo.wait()
    lost_pct = 100 * (sent - len(back)) / sent
    # each datagram and its echo cross a 20 % link: 36 % lost on average (sd 2.4 % here)
    assert 26 <= lost_pct <= 46, lost_pct


def test_torn_down_after_an_error_and_stale_links_removed() -> None:
    with pytest.raises(RuntimeError, match="boom"):
        with emulated_link(10, 5, 0, name="err") as link:
            assert _exists(link) == (True, True)
            raise RuntimeError("boom")
    poll_until(lambda: _exists(link) == (False, False), 10, poll_s=0.1)
    assert _exists(link) == (False, False)
    # a killed run's namespace: its pid is gone
    dead = next(p for p in range(4_100_000, 4_190_000) if not os.path.exists(f"/proc/{p}"))
    stale = f"trifuse-link-{dead}-0"
    subprocess.run([IP, "netns", "add", stale], check=True)
    try:
        assert stale in remove_stale()
    finally:
        subprocess.run([IP, "netns", "del", stale], capture_output=True)


def test_bad_shapes_are_refused() -> None:
    for bad in ((0, 10, 0), (10, -1, 0), (10, 10, 100)):
        with pytest.raises(ValueError):
            LinkShape(*bad)
    with pytest.raises(ValueError, match="name"):
        with emulated_link(10, 10, 0, name="no spaces"):
            pass


@pytest.mark.skipif(not os.path.exists("/usr/bin/chromium"), reason="needs /usr/bin/chromium")
def test_chromium_runs_inside_the_namespace() -> None:
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    from trifuse.app.devtools.browser_console import CHROMIUM, CHROMIUM_FLAGS

    seen: list[str] = []

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            seen.append(self.client_address[0])
            body = b"<title>across the link</title>"
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    from playwright.sync_api import sync_playwright

    with emulated_link(50, 5, 0, name="chromium") as link:
        server = ThreadingHTTPServer((link.host_ip, 0), Handler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(
                    executable_path=link.wrapper(CHROMIUM), args=list(CHROMIUM_FLAGS)
                )
                try:
                    page = browser.new_page()
                    page.goto(f"http://{link.host_ip}:{server.server_port}/")
                    assert page.title() == "across the link"
                finally:
                    browser.close()
        finally:
            server.shutdown()
            server.server_close()
    assert seen and set(seen) == {link.ns_ip}  # the page came from inside the namespace
