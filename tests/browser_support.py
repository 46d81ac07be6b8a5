"""Running ``trifuse serve`` and Debian's chromium for the browser tests.

Browser tests skip, with the reason, where /usr/bin/chromium is not installed; ``.ci/run``
installs it, so CI always runs them. The fixtures ``console`` (the console on the
simulated inspection room, one per test module) and ``browser`` live in conftest.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from app.bench import CHROMIUM, CHROMIUM_FLAGS, stop_process

FLAGS = list(CHROMIUM_FLAGS)
ROOT = Path(__file__).resolve().parents[1]

needs_chromium = pytest.mark.skipif(
    not os.path.exists(CHROMIUM), reason=f"browser tests need Debian's chromium at {CHROMIUM}"
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@dataclass(frozen=True)
class Console:
    """A running console: its base URL and the token it printed."""

    url: str
    token: str

    def signin(self, path: str = "/") -> str:
        """What an operator opens: ``path`` with the token (the browser exchanges it for a
        session cookie and is sent on to ``path``)."""
        return f"{self.url}{path}?token={self.token}"

    def request(self, path: str, method: str = "GET", body: Any = None) -> tuple[int, Any]:
        """A REST call as a script makes it (``Authorization: token``): (status, JSON)."""
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method)
        req.add_header("Authorization", f"token {self.token}")
        if data is not None:
            req.add_header("Content-Type", "application/json")
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read())

    def get(self, path: str) -> Any:
        return self.request(path)[1]

    def post(self, path: str, body: Any = None) -> tuple[int, Any]:
        return self.request(path, "POST", body)


def start_console(
    args: Sequence[str], port: int | None = None, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, Console]:
    """Start ``trifuse serve ARGS`` on a free loopback port (with its own random token
    unless ``env`` gives one); returns the process and the console (its URL as printed:
    ``https`` under TLS) once the port accepts connections."""
    port = port or free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from app.cli import main; sys.exit(main(sys.argv[1:]))",
            "serve",
            "--port",
            str(port),
            *args,
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    said = ""  # warnings (e.g. about an interrupted capture) may come before the URL
    for _ in range(50):
        line = proc.stdout.readline()
        said += line
        m = re.search(rf"(https?://127\.0\.0\.1:{port})/\?token=(\S+)", line)
        if m is not None or not line:
            break
    if m is None:
        proc.kill()
        raise RuntimeError(f"trifuse serve did not start: {said}{proc.stdout.read()}")
    for _ in range(100):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            break
        except OSError:
            time.sleep(0.1)
    return proc, Console(m.group(1), m.group(2))


@contextlib.contextmanager
def console_running(args: Sequence[str]) -> Iterator[Console]:
    """``trifuse serve ARGS`` for the duration of the block; yields the console."""
    proc, console = start_console(args)
    try:
        yield console
    finally:
        stop_process(proc)
