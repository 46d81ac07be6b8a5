"""Running ``trifuse serve`` and Debian's chromium for the browser tests.

Browser tests skip, with the reason, where /usr/bin/chromium is not installed; ``.ci/run``
installs it, so CI always runs them. The fixtures ``console`` (the console on the
simulated inspection room, one per test module) and ``browser`` live in conftest.py.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from app.bench import CHROMIUM, CHROMIUM_FLAGS

FLAGS = list(CHROMIUM_FLAGS)
ROOT = Path(__file__).resolve().parents[1]

needs_chromium = pytest.mark.skipif(
    not os.path.exists(CHROMIUM), reason=f"browser tests need Debian's chromium at {CHROMIUM}"
)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_console(args: Sequence[str], port: int | None = None) -> tuple[subprocess.Popen, str]:
    """Start ``trifuse serve ARGS`` on a free loopback port; returns (process, base URL)
    once the port accepts connections."""
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
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    line = proc.stdout.readline()
    if f"http://127.0.0.1:{port}/" not in line:
        proc.kill()
        raise RuntimeError(f"trifuse serve did not start: {line}{proc.stdout.read()}")
    for _ in range(100):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            break
        except OSError:
            time.sleep(0.1)
    return proc, f"http://127.0.0.1:{port}"


@contextlib.contextmanager
def console_running(args: Sequence[str]) -> Iterator[str]:
    """``trifuse serve ARGS`` for the duration of the block; yields its base URL."""
    proc, url = start_console(args)
    try:
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
