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

from app.devtools.bench import CHROMIUM, CHROMIUM_FLAGS
from app.devtools.processes import stop_process

FLAGS = list(CHROMIUM_FLAGS)
WAIT_MS = 300_000
"""Bound of a browser test's wait for the console (ms): generous, because a 2-core machine
busy with other work runs the console several times slower; the awaited event ends the wait
as soon as it comes. Also every page's default timeout (conftest.py's ``browser``)."""
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


# -- the simulator's disk cache, warmed once per run ----------------------------------------

TEST_BOARD_POSES = 20
"""Board poses of the calibration scenario the tests' consoles show (``--board-poses``):
half the default, so half the rendering; 16 of them give a calibration well within the
calibration issue's targets (test_browser_calibration.py)."""
WARM_SCENARIOS = {"inspection": {}, "calibration": {"board_poses": TEST_BOARD_POSES}}
_warmups: dict[str, subprocess.Popen] = {}


def start_cache_warmup() -> None:
    """Render every pose the tests' consoles show into the simulator's disk cache, one
    background process per scenario, while the first tests run (conftest.py starts them
    when the run has console tests). Consoles then load their pictures instead of rendering
    beside the tests (and beside each other)."""
    cache = os.environ.get("TRIFUSE_SIM_CACHE", "")
    if _warmups or cache.lower() in ("off", "0", "no", "false"):
        return
    for name, kwargs in WARM_SCENARIOS.items():
        code = (
            "from app.server.runtime import serve as s; "
            f"s.warm_simulator_cache({{{name!r}: {kwargs!r}}})"
        )
        _warmups[name] = subprocess.Popen(
            [sys.executable, "-c", code],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )


def wait_for_cache_warmup(scenario: str, timeout_s: float = 1200.0) -> None:
    """Block until the warm-up of ``scenario`` (if one was started) has finished; fail if
    it failed."""
    proc = _warmups.get(scenario)
    if proc is None:
        return
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the simulator's {scenario} poses were not rendered after {timeout_s} s")
    if proc.returncode != 0:
        pytest.fail(f"rendering the simulator's {scenario} poses failed: {proc.stderr.read()}")


def stop_cache_warmup() -> None:
    for proc in _warmups.values():
        stop_process(proc)


def scenario_of(args: Sequence[str]) -> str:
    """The simulated scenario ``trifuse serve ARGS`` shows (``inspection`` by default)."""
    args = list(args)
    return args[args.index("--scenario") + 1] if "--scenario" in args else "inspection"


def start_console(
    args: Sequence[str], port: int | None = None, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, Console]:
    """Start ``trifuse serve ARGS`` on a free loopback port (with its own random token
    unless ``env`` gives one; the calibration scenario once its poses are rendered);
    returns the process and the console (its URL as printed: ``https`` under TLS) once the
    port accepts connections."""
    if scenario_of(args) == "calibration":  # the inspection room's live mode needs none
        wait_for_cache_warmup("calibration")
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
    deadline = time.monotonic() + 120  # the port opens once the console is up
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            break
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                stop_process(proc)
                raise RuntimeError(f"trifuse serve did not open port {port}: {said}") from None
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
