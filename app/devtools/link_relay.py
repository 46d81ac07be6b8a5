"""The emulated link's packets, carried in user space: two TUN devices and a process that
moves IP packets between them with a rate, a delay and random loss (what ``tc netem``
does, for kernels built without it; :mod:`app.devtools.netem`).

Run as ``python -m trifuse.app.devtools.link_relay HOST_IF NS_IF``: it creates the two TUN devices
(IP packets, no header), prints ``ready`` and relays until its standard input ends (its
parent is gone) or it is killed; the devices vanish with it. Each line on standard input is
a shape for both directions, JSON ``{"rate_mbit": R, "delay_ms": D, "loss_pct": L,
"limit": N}`` (the first before ``ready``).

Per direction, a packet read from one device is lost with probability ``loss_pct`` / 100,
dropped when ``limit`` packets already wait (tail drop), else it is serialised at
``rate_mbit`` after the packets before it (its length in bits over the rate: the link is
busy until then) and written to the other device ``delay_ms`` after that.
"""

from __future__ import annotations

import collections
import fcntl
import json
import os
import random
import selectors
import struct
import sys
import time
from dataclasses import dataclass

TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
MTU = 1500


def open_tun(name: str) -> int:
    """A new TUN device ``name`` (IP packets, no packet information), non-blocking; its
    file descriptor (the device lives while it is open)."""
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
    fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI))
    return fd


@dataclass
class Direction:
    """One direction of the link: packets from ``src`` to ``dst`` (file descriptors).

    Attributes:
        busy_until: ``time.monotonic()`` when the link finishes sending what it holds.
        queue: (delivery time, packet), in delivery order.
        lost, dropped, delivered: packets lost at random, dropped at a full queue, written.
    """

    src: int
    dst: int
    busy_until: float = 0.0
    lost: int = 0
    dropped: int = 0
    delivered: int = 0

    def __post_init__(self) -> None:
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()

    def take(self, packet: bytes, shape: dict[str, float], now: float, rng: random.Random) -> None:
        """Accept a packet read now: lose, drop or schedule it."""
        if rng.random() * 100 < shape["loss_pct"]:
            self.lost += 1
            return
        if len(self.queue) >= shape["limit"]:
            self.dropped += 1
            return
        self.busy_until = max(now, self.busy_until) + len(packet) * 8 / (shape["rate_mbit"] * 1e6)
        self.queue.append((self.busy_until + shape["delay_ms"] / 1e3, packet))

    def deliver(self, now: float) -> None:
        """Write the packets due by ``now``."""
        while self.queue and self.queue[0][0] <= now:
            _, packet = self.queue.popleft()
            try:
                os.write(self.dst, packet)
                self.delivered += 1
            except (BlockingIOError, OSError):  # the receiving device is down or full
                self.dropped += 1


def _read_shape(line: str) -> dict[str, float]:
    shape = json.loads(line)
    return {k: float(shape[k]) for k in ("rate_mbit", "delay_ms", "loss_pct", "limit")}


def relay(host_if: str, ns_if: str) -> None:
    """Create the devices and relay (see the module docstring) until stdin ends."""
    shape = _read_shape(sys.stdin.readline())
    host_fd, ns_fd = open_tun(host_if), open_tun(ns_if)
    downlink, uplink = Direction(host_fd, ns_fd), Direction(ns_fd, host_fd)
    rng = random.Random()
    sel = selectors.DefaultSelector()
    sel.register(host_fd, selectors.EVENT_READ, downlink)
    sel.register(ns_fd, selectors.EVENT_READ, uplink)
    stdin = sys.stdin.fileno()
    sel.register(stdin, selectors.EVENT_READ, None)
    print("ready", flush=True)
    pending = b""
    while True:
        due = [d.queue[0][0] for d in (downlink, uplink) if d.queue]
        timeout = max(0.0, min(due) - time.monotonic()) if due else None
        for key, _ in sel.select(timeout):
            if key.data is None:
                chunk = os.read(stdin, 4096)
                if not chunk:
                    return
                pending += chunk
                while b"\n" in pending:
                    line, pending = pending.split(b"\n", 1)
                    shape = _read_shape(line.decode())
                continue
            direction: Direction = key.data
            now = time.monotonic()
            for _ in range(64):  # what the device holds, a bounded batch
                try:
                    packet = os.read(direction.src, MTU + 64)
                except (BlockingIOError, OSError):
                    break
                direction.take(packet, shape, now, rng)
        now = time.monotonic()
        downlink.deliver(now)
        uplink.deliver(now)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m trifuse.app.devtools.link_relay HOST_IF NS_IF")
    relay(sys.argv[1], sys.argv[2])
