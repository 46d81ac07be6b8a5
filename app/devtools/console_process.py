"""``trifuse serve`` in a subprocess, as the benchmarks, the stream soak and the tests drive
it: started on a free loopback port, awaited until it answers, asked over REST, stopped.

One launcher for all of them (:class:`ConsoleProcess`); :func:`stop_process` also ends the
other subprocesses of these tools.
"""

from __future__ import annotations

import json
import re
import socket
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
"""The checkout: the console's working directory."""
HOST = "127.0.0.1"
SERVE_CODE = "import sys; from trifuse.app.cli import main; sys.exit(main(sys.argv[1:]))"
"""What the subprocess runs: the installed ``trifuse`` (an editable install: this checkout)."""


def _direct_opener() -> urllib.request.OpenerDirector:
    """urllib without the environment's proxies (the console is on loopback) and without
    certificate checks (a test console's certificate is self-signed)."""
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    return urllib.request.build_opener(
        urllib.request.ProxyHandler({}), urllib.request.HTTPSHandler(context=context)
    )


_DIRECT = _direct_opener()


def free_port() -> int:
    """A TCP port on the loopback interface that nothing listens on now."""
    with socket.socket() as sock:
        sock.bind((HOST, 0))
        return sock.getsockname()[1]


def stop_process(proc: Any, timeout_s: float = 15.0) -> None:
    """End a subprocess (a ``subprocess.Popen``): SIGTERM (a console finishes recordings and
    closes cleanly), then SIGKILL if it has not ended within ``timeout_s``."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


def prewarm_pose_cache(timeout_s: float = 900.0) -> int:
    """Fill the disk cache of the console's simulated head (every pose of the inspection room
    rendered once; seconds when it is full already). Returns the number of poses."""
    from trifuse.app.sources.simulated import SimulatedHeadSource

    src = SimulatedHeadSource()
    try:
        deadline = time.monotonic() + timeout_s
        while src.rendered_count < src.pose_count and src.render_thread_alive:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the pose cache was not full after {timeout_s:g} s")
            time.sleep(0.2)
        return src.pose_count
    finally:
        src.close()


class ConsoleProcess:
    """``trifuse serve --port PORT ARGS`` in a subprocess (on the simulated inspection room
    unless ``ARGS`` say otherwise), on a free loopback port unless ``port`` is given.

    Its output goes to ``log_path`` (appended; :meth:`output` reads what this run wrote) or,
    without one, to the text pipe ``proc.stdout``, which the caller may read on (a console
    that writes much more than the pipe holds would stall: prefer a log file).

    The constructor returns once the console printed its URL (``https`` under TLS, with
    ``?token=`` unless it runs without one; ``host``: the address to listen on, passed as
    ``--host`` unless loopback) and answers an HTTP request; after
    ``timeout_s`` without that, or if the process ends, it stops the process and raises
    RuntimeError with what the console printed.

    Attributes:
        proc: the ``subprocess.Popen``; ``pid`` its process id.
        host, port: where it listens.
        url: its base URL as printed (``http://127.0.0.1:PORT``).
        token: the token in its URL, None without one.
        t_start: ``time.monotonic()`` when the process was started.
        log_path: the log file, or None (the pipe).
    """

    def __init__(
        self,
        args: Sequence[str] = (),
        *,
        env: Mapping[str, str] | None = None,
        log_path: Path | None = None,
        port: int | None = None,
        timeout_s: float = 120.0,
        host: str = HOST,
    ) -> None:
        self.host = host
        self.port = port or free_port()
        self.log_path = log_path
        self._said = ""
        self._log_start = 0
        command = [sys.executable, "-c", SERVE_CODE, "serve", "--port", str(self.port), *args]
        if host != HOST:
            command += ["--host", host]
        common: dict[str, Any] = {
            "cwd": ROOT,
            "env": None if env is None else dict(env),
            "stdin": subprocess.DEVNULL,
            "stderr": subprocess.STDOUT,
        }
        self.t_start = time.monotonic()
        if log_path is None:
            self.proc = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, **common)
        else:
            self._log_start = log_path.stat().st_size if log_path.exists() else 0
            with log_path.open("ab") as log:
                self.proc = subprocess.Popen(command, stdout=log, **common)
        self.pid = self.proc.pid
        deadline = self.t_start + timeout_s
        try:
            self.url, self.token = self._await_url(deadline)
            self._await_answer(deadline)
        except BaseException:
            self.close()
            raise

    # -- starting ------------------------------------------------------------------------

    def _read_more(self) -> bool:
        """Take in more of the console's output (a line from the pipe, blocking; or the log
        file so far); False at the pipe's end."""
        if self.log_path is None:
            line = self.proc.stdout.readline() if self.proc.stdout else ""
            self._said += line
            return bool(line)
        self._said = self.output()
        return True

    def _await_url(self, deadline: float) -> tuple[str, str | None]:
        """(base URL, token) from the line the console prints once it is set up (warnings,
        e.g. about an interrupted capture, may come before it)."""
        at = re.escape(f"{self.host}:{self.port}")
        printed = re.compile(rf"(https?://{at})/(?:\?token=(\S+))?(?=\s)")
        while True:
            more = self._read_more()
            m = printed.search(self._said)
            if m is not None:
                return m.group(1), m.group(2)
            if not more or self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"trifuse serve did not start: {self.output()}")
            if self.log_path is not None:
                time.sleep(0.1)

    def _await_answer(self, deadline: float) -> None:
        """Until ``GET /api/status`` gets an HTTP answer (its socket listens from the start,
        the server answers once it runs)."""
        while True:
            try:
                self.request("/api/status", timeout=5.0)
                return
            except urllib.error.HTTPError:
                return
            except OSError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(
                    f"trifuse serve does not answer on port {self.port}: {self.output()}"
                )
            time.sleep(0.1)

    # -- using it --------------------------------------------------------------------------

    def output(self) -> str:
        """What this run of the console printed: the log file from where this run began, or
        (with the pipe) what was read of it while starting."""
        if self.log_path is None:
            return self._said
        try:
            with self.log_path.open("rb") as f:
                f.seek(self._log_start)
                return f.read().decode(errors="replace")
        except OSError:
            return ""

    def signin(self, path: str = "/") -> str:
        """What an operator opens: ``path`` with the token (the browser exchanges it for a
        session cookie and is sent on to ``path``)."""
        return f"{self.url}{path}" + (f"?token={self.token}" if self.token else "")

    @property
    def ws_url(self) -> str:
        """The fused stream's WebSocket (``/stream``)."""
        return f"{self.url.replace('http', 'ws', 1)}/stream"

    def request(
        self, path: str, method: str = "GET", body: Any = None, timeout: float = 10.0
    ) -> tuple[int, Any]:
        """A REST call as a script makes it (``Authorization: token``): (status, JSON);
        ``urllib.error.HTTPError`` for an error status, OSError when nothing answers."""
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url + path, data=data, method=method)
        if self.token:
            req.add_header("Authorization", f"token {self.token}")
        if data is not None:
            req.add_header("Content-Type", "application/json")
        with _DIRECT.open(req, timeout=timeout) as r:
            return r.status, json.loads(r.read())

    def get(self, path: str) -> Any:
        """The JSON of ``GET path``."""
        return self.request(path)[1]

    def post(self, path: str, body: Any = None) -> tuple[int, Any]:
        """(status, JSON) of ``POST path`` with ``body`` as JSON."""
        return self.request(path, "POST", body)

    def status(self) -> dict[str, Any]:
        """``GET /api/status`` (blocking, at most 5 s)."""
        return self.request("/api/status", timeout=5.0)[1]

    # -- ending it ---------------------------------------------------------------------------

    def close(self, timeout_s: float = 15.0) -> None:
        """Stop the console (:func:`stop_process`: SIGTERM, SIGKILL after ``timeout_s``)."""
        stop_process(self.proc, timeout_s)

    def kill(self) -> None:
        """SIGKILL: no clean-up of any kind."""
        self.proc.kill()
        self.proc.wait(60)

    def __enter__(self) -> ConsoleProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
