"""``trifuse serve`` refuses at once, in one line, what it cannot do: a port in use, a
work directory another console holds (app/storage/workdir_lock.py, serve.bind_public_socket); and
no socket it listens on lets anyone in without the console's credentials."""

from __future__ import annotations

import os
import socket
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.browser_support import console_running, start_console
from tests.support import direct_websocket
from trifuse.app.cli import main
from trifuse.app.devtools.console_process import free_port, stop_process
from trifuse.app.server.runtime.serve import bind_public_socket
from trifuse.app.storage.workdir_lock import WorkdirInUse, lock_workdir


def test_a_port_in_use_is_one_line(tmp_path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(OSError, match=f"port {port} on 127.0.0.1 is in use"):
            bind_public_socket("127.0.0.1", port)
    with pytest.raises(OSError, match="not an address of this machine"):
        bind_public_socket("no-such-host.invalid", free_port())
    sock = bind_public_socket("127.0.0.1", 0)
    try:
        assert sock.getsockname()[1] > 0
    finally:
        sock.close()


def test_the_work_directory_has_one_console(tmp_path) -> None:
    first = lock_workdir(tmp_path / "w")
    try:
        with pytest.raises(WorkdirInUse, match=r"in use by another console \(process \d+\)"):
            lock_workdir(tmp_path / "w")
    finally:
        first.close()
    lock_workdir(tmp_path / "w").close()  # released with its holder


@pytest.mark.slow
def test_a_second_console_is_refused_at_once(tmp_path, capsys) -> None:
    workdir = tmp_path / "work"
    with console_running(["--workdir", str(workdir)]) as console:
        port = int(console.url.rsplit(":", 1)[1])
        assert main(["serve", "--port", str(port), "--workdir", str(tmp_path / "other")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"port {port} on 127.0.0.1 is in use" in err
        assert not (tmp_path / "other").exists()  # nothing was made
        assert main(["serve", "--port", str(free_port()), "--workdir", str(workdir)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "is in use by another console" in err
        assert console.get("/api/status")["error"] is None  # the first one goes on


def listening_ports(pid: int) -> set[int]:
    """TCP ports the process ``pid`` listens on (Linux: its socket inodes in /proc)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("tcp", "tcp6"):
        lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        for line in lines:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # 0A: LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


@pytest.mark.slow
def test_no_listening_socket_but_the_public_port_lets_anyone_in(tmp_path) -> None:
    """Every socket the console listens on refuses a connection without the console's
    credentials: the public port wants the token, Viser's loopback port the relay's secret
    (tested with what the issue found open: subprotocol viser-v1.1.1, Origin evil.com)."""
    proc, console = start_console(["--workdir", str(tmp_path / "work")])
    try:
        public = int(console.url.rsplit(":", 1)[1])
        ports = listening_ports(proc.pid)
        assert public in ports and len(ports) >= 2, ports  # the public one and Viser's
        for port in ports:
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/api/status", timeout=10)
            assert refused.value.code == (401 if port == public else 403), port
            if port != public:
                assert direct_websocket(port, {"Origin": "http://evil.com"}) == 403
                assert direct_websocket(port, {}) == 403
        # nothing was captured through a side door; the console itself still works
        assert console.get("/api/captures")["views"] == []
        assert console.get("/api/status")["error"] is None
    finally:
        stop_process(proc)
