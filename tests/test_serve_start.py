"""``trifuse serve`` refuses at once, in one line, what it cannot do: a port in use, a
work directory another console holds (app/workdir_lock.py, serve.bind_public_socket)."""

from __future__ import annotations

import socket

import pytest

from app.cli import main
from app.server.serve import bind_public_socket
from app.workdir_lock import WorkdirInUse, lock_workdir
from tests.browser_support import console_running, free_port


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
