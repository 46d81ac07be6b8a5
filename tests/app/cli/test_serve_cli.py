"""``trifuse serve --port``: 1-65535, or 0 for a free port the system chooses; the URL it
prints names the port actually bound. Out-of-range ports are refused in one line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from tests.support import run_cli

ANY = "expected a port number from 1 to 65535, or 0 for any free port"
REFUSED = [
    (["--port", "-1"], f"--port: {ANY}, got -1"),
    (["--port", "65536"], f"--port: {ANY}, got 65536"),
    (["--port", "80000"], f"--port: {ANY}, got 80000"),
    (["--port", "abc"], f"--port: {ANY}, got 'abc'"),
    (["--foxglove-port", "0"], "--foxglove-port: expected a port number from 1 to 65535, got 0"),
    (["--foxglove-port", "65536"], "--foxglove-port: expected a port number from 1 to 65535"),
]


@pytest.mark.parametrize(("argv", "says"), REFUSED, ids=[" ".join(a) for a, _ in REFUSED])
def test_a_port_out_of_range_is_refused(
    argv: list[str], says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    workdir = tmp_path / "work"
    code, out, err = run_cli(["serve", *argv, "--workdir", str(workdir)], capsys)
    assert code == 2 and out == ""
    assert err.startswith("trifuse serve: argument ") and says in err, err
    assert err.rstrip().endswith("(see 'trifuse serve --help')")
    assert len(err.strip().splitlines()) == 1
    assert not workdir.exists()  # refused before anything started


def test_port_0_serves_on_a_free_port_and_says_which(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The console's runtime is replaced by one that prints the URL as it does, from what
    it is given: the bound socket and the authentication (whose port names the cookie and
    the console's own origin)."""
    from trifuse.app.recording import open_source
    from trifuse.app.server.runtime import serve as runtime

    given: dict[str, Any] = {}

    def serve(opened: Any, board: Any, workdir: Any, auth: Any, host: str, tls: Any, sock: Any,
              *_args: Any, **_kw: Any) -> None:  # fmt: skip
        given.update(auth=auth, bound=sock.getsockname()[1])
        print(f"trifuse console on {opened}: {runtime.console_url(host, auth.port, auth)}")

    monkeypatch.setattr(runtime, "serve", serve)
    monkeypatch.setattr(open_source, "open_source", lambda *a, **k: "the simulated head")
    argv = ["serve", "--port", "0", "--workdir", str(tmp_path / "work")]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    port = given["bound"]
    assert port > 0 and given["auth"].port == port
    assert f"http://127.0.0.1:{port}/?token=" in out
    assert given["auth"].cookie_name == f"trifuse-session-{port}"
