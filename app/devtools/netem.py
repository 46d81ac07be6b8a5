"""An emulated radio link on this machine: a network namespace (the viewer's browser)
joined to the host (the console) by a shaped point-to-point link, for measuring the
console's stream as a viewer on a slow, lossy link sees it.

::

    host (the console, 10.231.x.1)  ==link==  namespace (the viewer's browser, 10.231.x.2)
      downlink: rate, delay, loss  -->
                                   <--  uplink: rate, delay, loss

Both directions get the same :class:`LinkShape` (:meth:`EmulatedLink.shape`): the downlink,
server -> viewer, carries the video and is limited to ``rate_mbit``, delayed by
``delay_ms`` and loses ``loss_pct`` % of its packets; the uplink (acks, requests) the same,
so the round trip takes ``2 * delay_ms`` plus the serialisation at ``rate_mbit``. The queue
holds ``limit`` packets per direction (netem's default, 1000: about 1.2 s at 10 Mbit/s).

What ``tc netem`` on a veth pair would do, done in user space: this machine's kernel is
built without ``sch_netem`` (``CONFIG_NET_SCH_NETEM`` is not set, no modules), so the link
is two TUN devices, one on the host and one moved into the namespace, and a relay process
(:mod:`app.devtools.link_relay`) that moves the IP packets between them with the rate,
delay and loss, packet by packet (at most the MTU, 1500 bytes, each), as netem would.

Names are unique per run and link (namespace ``trifuse-NAME-PID-K``, devices ``tfPIDxKh``
on the host and ``tfPIDxKn`` in the namespace; the /30 in 10.231.0.0/16 is derived from PID
and K), so two runs do not collide; a namespace left by a run that was killed (its PID is
gone) is removed when the next link is set up, and its relay ends (with its devices) when
its parent's pipe closes. Everything is removed on leaving :func:`emulated_link`, also after
an error.

Needs root and iproute2 (``ip``); :class:`LinkError` otherwise.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import stat
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from trifuse.app.devtools.console_process import ROOT, stop_process

IP = "/usr/sbin/ip"
NEEDS = "the link benchmark needs root and iproute2 (ip)"
TUN = "/dev/net/tun"
_STALE_NS = re.compile(r"^trifuse-[A-Za-z0-9_]+-(\d+)-\d+$")
_counter = itertools.count()


class LinkError(RuntimeError):
    """The link could not be set up (not root, no iproute2, a command failed)."""


@dataclass(frozen=True)
class LinkShape:
    """What netem does on each direction of the link.

    Attributes:
        rate_mbit: the rate, Mbit/s (10^6 bit/s).
        delay_ms: one-way delay, milliseconds.
        loss_pct: packets lost at random, percent.
        limit: packets the queue holds (netem's ``limit``).
    """

    rate_mbit: float
    delay_ms: float
    loss_pct: float = 0.0
    limit: int = 1000

    def __post_init__(self) -> None:
        if not self.rate_mbit > 0:
            raise ValueError(f"rate_mbit: expected > 0, got {self.rate_mbit}")
        if not 0 <= self.delay_ms <= 10_000:
            raise ValueError(f"delay_ms: expected 0-10000, got {self.delay_ms}")
        if not 0 <= self.loss_pct < 100:
            raise ValueError(f"loss_pct: expected 0-100 (exclusive), got {self.loss_pct}")
        if self.limit < 1:
            raise ValueError(f"limit: expected >= 1, got {self.limit}")

    def as_json(self) -> str:
        """The line the relay reads (:mod:`app.devtools.link_relay`)."""
        return json.dumps(
            {
                "rate_mbit": self.rate_mbit,
                "delay_ms": self.delay_ms,
                "loss_pct": self.loss_pct,
                "limit": self.limit,
            }
        )

    def describe(self) -> str:
        """``10 Mbit/s, 30 ms, 1 % loss``."""
        return f"{self.rate_mbit:g} Mbit/s, {self.delay_ms:g} ms, {self.loss_pct:g} % loss"


def _run(args: Sequence[str], check: bool = True) -> subprocess.CompletedProcess[str]:
    """Run an iproute2 command; LinkError with its output when it fails and ``check``."""
    proc = subprocess.run(list(args), capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if check and proc.returncode != 0:
        out = (proc.stderr or proc.stdout).strip()
        raise LinkError(f"{' '.join(args)}: {out} ({NEEDS})")
    return proc


def require_netns() -> None:
    """LinkError unless this process may create network namespaces (root, iproute2)."""
    if not os.path.exists(IP):
        raise LinkError(f"{NEEDS}: {IP} is missing")
    if not os.path.exists(TUN):
        raise LinkError(f"{NEEDS} and TUN devices: {TUN} is missing")
    if os.geteuid() != 0:
        raise LinkError(f"{NEEDS}: this process is not root")


def netns_available() -> str | None:
    """None where :func:`emulated_link` can work here, else why not (for a test's skip)."""
    try:
        require_netns()
    except LinkError as exc:
        return str(exc)
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale() -> list[str]:
    """Remove the namespaces of links whose process is gone (a run that was killed; its
    relay and devices ended with it); returns their names."""
    removed = []
    for line in _run([IP, "netns", "list"], check=False).stdout.splitlines():
        name = line.split()[0] if line.strip() else ""
        m = _STALE_NS.match(name)
        if m and not _pid_alive(int(m.group(1))):
            _run([IP, "netns", "del", name], check=False)
            removed.append(name)
    return removed


def _subnet(pid: int, k: int) -> tuple[str, str]:
    """(host address, namespace address) of a /30 in 10.231.0.0/16 for run ``pid``, link
    ``k``."""
    index = (pid * 8 + k) % 16384
    third, fourth = index >> 6, (index & 63) * 4
    return f"10.231.{third}.{fourth + 1}", f"10.231.{third}.{fourth + 2}"


class EmulatedLink:
    """A namespace and a veth pair set up by :func:`emulated_link`.

    Attributes:
        namespace: the network namespace's name (``ip netns exec NAMESPACE ...``).
        host_if, ns_if: the veth ends on the host and in the namespace.
        host_ip, ns_ip: their IPv4 addresses (a /30): the console listens on ``host_ip``,
            the viewer reaches it there.
        shape_now: the current :class:`LinkShape`.
    """

    def __init__(self, name: str, shape: LinkShape) -> None:
        if not re.fullmatch(r"[A-Za-z0-9_]{1,20}", name):
            raise ValueError(f"name: letters, digits and _ only (1-20), got {name!r}")
        pid, k = os.getpid(), next(_counter)
        self.namespace = f"trifuse-{name}-{pid}-{k}"
        self.host_if, self.ns_if = f"tf{pid}x{k}h", f"tf{pid}x{k}n"
        self.host_ip, self.ns_ip = _subnet(pid, k)
        self.shape_now = shape
        self._relay: subprocess.Popen[str] | None = None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None

    # -- setting up and tearing down -----------------------------------------------------

    def _up(self) -> None:
        ns, h, n = self.namespace, self.host_if, self.ns_if
        _run([IP, "netns", "add", ns])
        self._relay = subprocess.Popen(
            [sys.executable, "-m", "trifuse.app.devtools.link_relay", h, n],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self._relay.stdin is not None and self._relay.stdout is not None
        self._relay.stdin.write(self.shape_now.as_json() + "\n")
        self._relay.stdin.flush()
        if self._relay.stdout.readline().strip() != "ready":
            self._relay.wait(10)
            err = self._relay.stderr.read() if self._relay.stderr else ""
            raise LinkError(f"the link relay did not start: {err.strip()} ({NEEDS})")
        _run([IP, "link", "set", n, "netns", ns])
        _run([IP, "addr", "add", self.host_ip, "peer", f"{self.ns_ip}/32", "dev", h])
        _run([IP, "link", "set", h, "up"])
        self.exec([IP, "link", "set", "lo", "up"])
        self.exec([IP, "addr", "add", self.ns_ip, "peer", f"{self.host_ip}/32", "dev", n])
        self.exec([IP, "link", "set", n, "up"])

    def close(self) -> None:
        """End the relay (its devices go with it), remove the namespace and the Chromium
        wrapper; never raises."""
        if self._relay is not None:
            with contextlib.suppress(OSError):
                self._relay.stdin.close()  # type: ignore[union-attr]
            stop_process(self._relay, 5.0)
            for pipe in (self._relay.stdout, self._relay.stderr):
                if pipe is not None:
                    pipe.close()
            self._relay = None
        _run([IP, "netns", "del", self.namespace], check=False)
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    # -- using it --------------------------------------------------------------------------

    def shape(self, shape: LinkShape) -> None:
        """Apply ``shape`` to both directions from now on (packets on the way keep theirs)."""
        if self._relay is None or self._relay.stdin is None or self._relay.poll() is not None:
            raise LinkError("the link relay is not running")
        self._relay.stdin.write(shape.as_json() + "\n")
        self._relay.stdin.flush()
        self.shape_now = shape

    def command(self, args: Sequence[str]) -> list[str]:
        """``args`` as a command that runs inside the namespace."""
        return [IP, "netns", "exec", self.namespace, *args]

    def exec(self, args: Sequence[str], check: bool = True) -> subprocess.CompletedProcess[str]:
        """Run ``args`` inside the namespace and wait; LinkError when it fails and
        ``check``."""
        return _run(self.command(args), check=check)

    def popen(self, args: Sequence[str], **kwargs: object) -> subprocess.Popen:
        """Start ``args`` inside the namespace (``subprocess.Popen`` keyword arguments)."""
        return subprocess.Popen(self.command(args), **kwargs)  # type: ignore[call-overload]

    def wrapper(self, program: str) -> str:
        """The path of an executable script that runs ``program`` inside the namespace with
        the script's arguments (``exec ip netns exec NAMESPACE PROGRAM "$@"``: the same
        process, its file descriptors kept). Playwright, which talks to Chromium over a
        pipe, launches the browser in the namespace with ``executable_path=`` this."""
        if self._tmp is None:
            self._tmp = tempfile.TemporaryDirectory(prefix=f"{self.namespace}-")
        path = Path(self._tmp.name) / Path(program).name
        path.write_text(f'#!/bin/sh\nexec {IP} netns exec {self.namespace} {program} "$@"\n')
        path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
        return str(path)

    def received_bytes(self) -> int:
        """Bytes the namespace has received over the link (its device's counter): what
        the link delivered downstream, IP headers included."""
        out = self.exec([IP, "-j", "-s", "link", "show", "dev", self.ns_if]).stdout
        return int(json.loads(out)[0]["stats64"]["rx"]["bytes"])


@contextlib.contextmanager
def emulated_link(
    rate_mbit: float,
    delay_ms: float,
    loss_pct: float = 0.0,
    name: str = "link",
    limit: int = 1000,
) -> Iterator[EmulatedLink]:
    """A network namespace behind a veth pair shaped by netem (see the module docstring)
    for the duration of the block; removed afterwards, also after an error. Stale links of
    killed runs are removed first. LinkError when this machine cannot (not root, no
    iproute2); ValueError for a bad shape or name."""
    shape = LinkShape(rate_mbit, delay_ms, loss_pct, limit)
    require_netns()
    remove_stale()
    link = EmulatedLink(name, shape)
    try:
        link._up()
        yield link
    finally:
        link.close()
