"""``trifuse bench --soak``: the console's stream under load for minutes (issue 8, "Load").

Ten viewers on the stream plus slow readers; the fast viewers must keep the frame rate and
the server's memory must stay flat. Not a registered benchmark (``app.devtools.bench.REGISTRY``): it
runs for minutes, has its own options and passes or fails (exit code 1).

What runs:

- ``trifuse serve`` on the simulated inspection room, a subprocess with a temporary work
  directory and its own random token (``TRIFUSE_TOKEN``), its output into a log file (a
  pipe nobody reads would stall it once full). The disk cache of rendered head poses is
  filled first (not timed; seconds when it is already full), so that the console loads
  every pose at start instead of rendering them during the soak (its memory would grow
  by 8.4 MB a pose: not a leak, but it would hide one).
- Baseline phase: one viewer (``/stream``, websockets client, ``ack`` at once) for
  ``baseline_s``; its frames per second, median over windows, is the baseline.
- Soak phase, ``soak_s``: ``viewers`` such fast viewers, plus the slow readers:

  - ``ws``: a WebSocket viewer on a raw socket with a small receive buffer
    (``SO_RCVBUF`` ``rcvbuf`` bytes, set before connecting) that acks each frame only
    ``ack_delay_s`` after it arrived, and every ``read_s`` seconds stops reading its
    socket altogether for ``stall_s`` (right after an ack, so a frame is in flight);
    pings are answered only when it reads, so ``stall_s`` stays below the server's
    ping timeout (20 s);
  - ``mjpeg``: an MJPEG reader (``/stream.mjpg``, the fallback of a plain ``<img>``) on a
    socket with the same small receive buffer that reads ``mjpeg_bytes_per_s`` (default
    4 kB/s: one frame of 0.15-0.2 MB in 40-50 s). The harshest case: the server has no ack to
    wait for, only TCP backpressure; it must not buffer the frames it cannot send.

  Every ``window_s`` seconds: each fast viewer's frames per second over the window, the
  median latency from the server publishing a frame (``sent_ns``) to a fast viewer having
  it, the slow readers' progress, of the server process (``/proc/PID``) threads, open file
  descriptors, CPU and child processes, and from ``/api/status`` the frames published
  and the viewers counted. The server's resident memory (``VmRSS``) every second: the
  console's RSS swings by tens of MB from one second to the next (695-728 MB over two
  minutes with two viewers and nothing else), so the slope is fitted over many samples.

Criteria (:data:`CRITERIA`; exit 1 if one fails):

- the median over windows of the fast viewers' median fps is at least 0.9 x the
  baseline, and the slowest fast viewer (its mean over the soak) at least 0.8 x;
- the server's RSS grows by at most 1 MB a minute: least-squares slope over the samples
  after the warm-up (the first ``warmup_s``, default 10 % of the soak, at least two
  windows, at most 60 s: connections, buffers and allocator arenas settle). Why 1 MB/min:
  a leak of one JPEG (0.15-0.2 MB) per frame the slow WebSocket viewer takes shows as
  about 10 MB/min, a leak of 100 bytes per frame sent to 11 viewers at 15 fps as 1
  MB/min; over the 540 samples of a ten-minute run the slope's standard error is about
  0.3 MB/min (RSS noise of about 20 MB), so 1 MB/min is about three of them; 10 MB over
  10 minutes is under 2 % of the console's RSS (about 650 MB, most of it the 31 cached
  poses). Judged only when fitted over at least 2 minutes (:data:`MIN_FIT_S`): the slope
  of a run of seconds is noise; shorter runs report it as "n/a";
- threads and file descriptors: at most 4 and 8 more at the end than after the warm-up
  (the connections do not change during the soak);
- no render process after the warm-up: the console renders poses only while its disk
  cache misses some (another version of the simulator's code), and its RSS then grows by
  8.4 MB a pose: the run says nothing about leaks;
- every viewer stays connected, every fast viewer receives frames in every window and
  each slow reader gets data.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import os
import re
import secrets
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.devtools.processes import stop_process

ROOT = Path(__file__).resolve().parents[2]

MIN_FPS_RATIO = 0.9
"""Median fast-viewer fps over the soak / the 1-viewer baseline, at least."""
MIN_VIEWER_RATIO = 0.8
"""The slowest fast viewer's mean fps over the soak / the baseline, at least."""
MAX_RSS_SLOPE_MB_PER_MIN = 1.0
"""Server RSS growth after the warm-up, MB per minute, at most (see the module docstring)."""
MIN_FIT_S = 120.0
"""The RSS slope is judged only when fitted over this many seconds at least."""
MAX_THREAD_GROWTH = 4
MAX_FD_GROWTH = 8

CRITERIA = (
    f"fast fps >= {MIN_FPS_RATIO} x baseline (median), slowest viewer >= "
    f"{MIN_VIEWER_RATIO} x; RSS slope <= {MAX_RSS_SLOPE_MB_PER_MIN} MB/min (judged from "
    f"{MIN_FIT_S:g} s of samples); threads +{MAX_THREAD_GROWTH}, fds +{MAX_FD_GROWTH} at "
    "most; no pose rendering; everyone connected and served"
)

SLOW_KINDS = ("ws", "mjpeg")


@dataclass(frozen=True)
class SoakConfig:
    """What ``trifuse bench --soak`` runs (defaults: the issue's ten-minute run)."""

    soak_s: float = 600.0
    viewers: int = 10
    baseline_s: float = 20.0
    window_s: float = 5.0
    warmup_s: float | None = None
    """Soak seconds before the RSS figures start; None: 10 % of the soak, 2-12 windows."""
    slow: tuple[str, ...] = SLOW_KINDS
    ack_delay_s: float = 1.0
    read_s: float = 20.0
    stall_s: float = 15.0
    mjpeg_bytes_per_s: int = 4096
    rcvbuf: int = 4096
    prewarm: bool = True
    """Fill the disk cache of rendered poses before the console starts."""
    settle_s: float = 5.0
    """After the first frame, before the baseline: the console loads its poses."""
    start_timeout_s: float = 120.0

    def warmup(self) -> float:
        if self.warmup_s is not None:
            return self.warmup_s
        return min(max(0.1 * self.soak_s, 2 * self.window_s), 12 * self.window_s, 60.0)

    def describe(self) -> str:
        slow = []
        if "ws" in self.slow:
            slow.append(
                f"ws (ack after {self.ack_delay_s:g} s, stops reading for {self.stall_s:g} s "
                f"every {self.read_s + self.stall_s:g} s)"
            )
        if "mjpeg" in self.slow:
            slow.append(f"mjpeg ({self.mjpeg_bytes_per_s / 1e3:g} kB/s)")
        return (
            f"{self.viewers} fast viewers + slow: {', '.join(slow) or 'none'}; receive buffer "
            f"of the slow {self.rcvbuf} B; soak {self.soak_s:g} s after a 1-viewer baseline "
            f"of {self.baseline_s:g} s; windows of {self.window_s:g} s"
        )


# -- pure helpers -------------------------------------------------------------------------


def slope_per_minute(t_s: Sequence[float], values: Sequence[float]) -> float:
    """Least-squares slope of ``values`` over ``t_s`` (seconds), per minute; NaN with
    fewer than two distinct times."""
    if len(t_s) != len(values):
        raise ValueError(f"slope: {len(t_s)} times but {len(values)} values")
    n = len(t_s)
    if n < 2:
        return math.nan
    mt = sum(t_s) / n
    mv = sum(values) / n
    sxx = sum((t - mt) ** 2 for t in t_s)
    if sxx == 0:
        return math.nan
    sxy = sum((t - mt) * (v - mv) for t, v in zip(t_s, values, strict=True))
    return 60.0 * sxy / sxx


def parse_proc_status(text: str) -> tuple[float, int]:
    """(resident memory in MB, threads) from the text of ``/proc/PID/status``."""
    rss = re.search(r"^VmRSS:\s+(\d+)\s+kB", text, re.M)
    threads = re.search(r"^Threads:\s+(\d+)", text, re.M)
    if rss is None or threads is None:
        raise ValueError("/proc status: no VmRSS or Threads line")
    return int(rss.group(1)) / 1024.0, int(threads.group(1))


def parse_proc_cpu_s(stat: str) -> float:
    """User + system CPU seconds from the text of ``/proc/PID/stat``."""
    fields = stat[stat.rindex(")") + 2 :].split()
    # after "pid (comm) ": state is field 3, utime and stime are fields 14 and 15
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class ProcSample:
    rss_mb: float
    threads: int
    fds: int
    cpu_s: float
    children: int = 0


def sample_process(pid: int) -> ProcSample:
    """The process's RSS, threads, open file descriptors, CPU time and child processes
    (Linux ``/proc``)."""
    rss, threads = parse_proc_status(Path(f"/proc/{pid}/status").read_text())
    fds = len(os.listdir(f"/proc/{pid}/fd"))
    cpu = parse_proc_cpu_s(Path(f"/proc/{pid}/stat").read_text())
    children = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            children += len((task / "children").read_text().split())
        except OSError:  # the thread ended meanwhile
            pass
    return ProcSample(rss, threads, fds, cpu, children)


class MjpegParts:
    """Counts the complete JPEG parts of a ``multipart/x-mixed-replace`` body fed in
    chunks (parts as ``/stream.mjpg`` writes them: ``--frame``, headers with
    ``Content-Length``, a blank line, the JPEG, CRLF)."""

    MAX_HEADER = 4096

    def __init__(self) -> None:
        self.parts = 0
        self._head = bytearray()
        self._body_left = 0

    def feed(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            if self._body_left:
                take = min(self._body_left, len(view))
                self._body_left -= take
                view = view[take:]
                if not self._body_left:
                    self.parts += 1
                continue
            self._head += view
            view = memoryview(b"")
            end = self._head.find(b"\r\n\r\n")
            if end < 0:
                if len(self._head) > self.MAX_HEADER:
                    raise ValueError("MJPEG: no end of part headers")
                return
            head, rest = bytes(self._head[:end]), bytes(self._head[end + 4 :])
            self._head.clear()
            m = re.search(rb"content-length:\s*(\d+)", head, re.I)
            if m is None or b"--frame" not in head:
                raise ValueError(f"MJPEG: unexpected part headers {head[:80]!r}")
            self._body_left = int(m.group(1)) + 2  # the CRLF after the JPEG
            view = memoryview(rest)


# -- viewers ------------------------------------------------------------------------------


class FastViewer:
    """A viewer on ``/stream`` that acknowledges each frame as soon as it has it."""

    kind = "fast"

    def __init__(self, url: str, token: str) -> None:
        self.url, self.token = url, token
        self.frames = 0
        self.bytes = 0
        self.latencies_ms: list[float] = []
        self.error: str | None = None
        self.done = False
        self.first_frame = asyncio.Event()

    async def run(self) -> None:
        from websockets.asyncio.client import connect

        headers = {"Authorization": f"token {self.token}"}
        try:
            async with connect(
                self.url,
                additional_headers=headers,
                proxy=None,
                compression=None,
                max_size=None,
                open_timeout=30,
            ) as ws:
                while True:
                    meta = await ws.recv()
                    jpeg = await ws.recv()
                    if not isinstance(meta, str) or not isinstance(jpeg, bytes):
                        raise RuntimeError("expected a JSON text message, then a JPEG")
                    self.latencies_ms.append((time.time_ns() - json.loads(meta)["sent_ns"]) / 1e6)
                    self.frames += 1
                    self.bytes += len(jpeg)
                    self.first_frame.set()
                    await ws.send("ack")
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.done = True


def _small_socket(rcvbuf: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # before connecting: the window scale is agreed in the handshake
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.setblocking(False)
    return sock


class SlowWsViewer:
    """A viewer on ``/stream`` over a raw socket with a small receive buffer: acks each
    frame ``ack_delay_s`` after it arrived and, every ``read_s``, stops reading its socket
    for ``stall_s`` (see the module docstring)."""

    kind = "ws"

    def __init__(self, host: str, port: int, token: str, cfg: SoakConfig) -> None:
        self.host, self.port, self.token, self.cfg = host, port, token, cfg
        self.frames = 0
        self.bytes = 0
        self.stalls = 0
        self.error: str | None = None
        self.done = False
        self.first_frame = asyncio.Event()

    async def run(self) -> None:
        from websockets.client import ClientProtocol
        from websockets.frames import Opcode
        from websockets.http11 import Response
        from websockets.uri import parse_uri

        loop = asyncio.get_running_loop()
        sock = _small_socket(self.cfg.rcvbuf)
        proto = ClientProtocol(parse_uri(f"ws://{self.host}:{self.port}/stream"), max_size=None)

        async def flush() -> None:
            for data in proto.data_to_send():
                if data:
                    await loop.sock_sendall(sock, data)

        try:
            await loop.sock_connect(sock, (self.host, self.port))
            request = proto.connect()
            request.headers["Authorization"] = f"token {self.token}"
            proto.send_request(request)
            await flush()
            stall_at = time.monotonic() + self.cfg.read_s
            parts: list[bytes] = []
            opcode = Opcode.BINARY
            while True:
                data = await loop.sock_recv(sock, 65536)
                if data:
                    proto.receive_data(data)
                else:
                    proto.receive_eof()
                await flush()  # pongs
                for event in proto.events_received():
                    if isinstance(event, Response):
                        if event.status_code != 101:
                            raise RuntimeError(f"upgrade refused: HTTP {event.status_code}")
                        continue
                    if event.opcode in (Opcode.TEXT, Opcode.BINARY):
                        opcode = event.opcode  # of the message (CONT: its continuations)
                    elif event.opcode is not Opcode.CONT:
                        continue
                    parts.append(event.data)
                    if not event.fin:
                        continue
                    message, parts = b"".join(parts), []
                    if opcode is Opcode.TEXT:
                        continue  # the frame's metadata
                    self.frames += 1
                    self.bytes += len(message)
                    self.first_frame.set()
                    await asyncio.sleep(self.cfg.ack_delay_s)
                    proto.send_text(b"ack")
                    await flush()
                    if time.monotonic() >= stall_at:
                        # the next frame is on its way: leave it in the buffers
                        self.stalls += 1
                        await asyncio.sleep(self.cfg.stall_s)
                        stall_at = time.monotonic() + self.cfg.read_s
                if not data:
                    raise RuntimeError(f"the server closed the connection ({proto.close_code})")
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.done = True
            sock.close()


class SlowMjpegReader:
    """``/stream.mjpg`` over a raw socket with a small receive buffer, read at
    ``mjpeg_bytes_per_s``; ``frames``: complete parts received."""

    kind = "mjpeg"
    TICK_S = 0.25

    def __init__(self, host: str, port: int, token: str, cfg: SoakConfig) -> None:
        self.host, self.port, self.token, self.cfg = host, port, token, cfg
        self.parts = MjpegParts()
        self.bytes = 0
        self.stalls = 0
        self.error: str | None = None
        self.done = False
        self.first_frame = asyncio.Event()

    @property
    def frames(self) -> int:
        return self.parts.parts

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        sock = _small_socket(self.cfg.rcvbuf)
        rate = self.cfg.mjpeg_bytes_per_s
        try:
            await loop.sock_connect(sock, (self.host, self.port))
            # HTTP/1.0: the body is the bare multipart stream (no chunked encoding)
            await loop.sock_sendall(
                sock,
                (
                    f"GET /stream.mjpg HTTP/1.0\r\nHost: {self.host}:{self.port}\r\n"
                    f"Authorization: token {self.token}\r\n\r\n"
                ).encode(),
            )
            head = b""
            while b"\r\n\r\n" not in head:
                data = await loop.sock_recv(sock, 1024)
                if not data or len(head) > 16384:
                    raise RuntimeError(f"no HTTP response: {head[:80]!r}")
                head += data
            head, _, body = head.partition(b"\r\n\r\n")
            if not re.match(rb"HTTP/1\.[01] 200 ", head):
                raise RuntimeError(f"HTTP response {head.splitlines()[0]!r}")
            self.parts.feed(body)
            self.bytes = len(body)
            t0 = time.monotonic()
            while True:
                allowed = int(rate * (time.monotonic() - t0)) - self.bytes
                if allowed < max(1, min(1024, int(rate * self.TICK_S))):
                    await asyncio.sleep(self.TICK_S)
                    continue
                data = await loop.sock_recv(sock, min(allowed, 65536))
                if not data:
                    raise RuntimeError("the server closed the connection")
                self.bytes += len(data)
                self.parts.feed(data)
                if self.parts.parts:
                    self.first_frame.set()
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.done = True
            sock.close()


Viewer = FastViewer | SlowWsViewer | SlowMjpegReader


# -- the console --------------------------------------------------------------------------


def prewarm_pose_cache(timeout_s: float = 900.0) -> int:
    """Fill the disk cache of the console's simulated head (every pose rendered once;
    seconds when it is full already). Returns the number of poses."""
    from app.sources.simulated import SimulatedHeadSource

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


_DIRECT = urllib.request.build_opener(urllib.request.ProxyHandler({}))
"""urllib without the environment's proxies (the console is on loopback)."""


class ConsoleProcess:
    """``trifuse serve`` (simulated inspection room) in a subprocess, on a free loopback
    port, with a random token and its output in ``workdir/serve.log``."""

    def __init__(self, workdir: Path, timeout_s: float = 120.0) -> None:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.host = "127.0.0.1"
        self.token = secrets.token_urlsafe(24)
        self.log_path = workdir / "serve.log"
        env = {**os.environ, "TRIFUSE_TOKEN": self.token}
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    "import sys; from app.cli import main; sys.exit(main(sys.argv[1:]))",
                    "serve",
                    "--scenario",
                    "inspection",
                    "--port",
                    str(self.port),
                    "--workdir",
                    str(workdir / "work"),
                ],
                cwd=ROOT,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        self.pid = self.proc.pid
        deadline = time.monotonic() + timeout_s
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"trifuse serve exited ({self.proc.returncode}): {self.log()}")
            try:
                socket.create_connection((self.host, self.port), timeout=0.5).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    self.close()
                    raise RuntimeError(f"trifuse serve does not listen: {self.log()}") from None
                time.sleep(0.1)

    def log(self, tail: int = 2000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-tail:]
        except OSError:
            return ""

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}/stream"

    def status(self) -> dict[str, Any]:
        """``GET /api/status`` (blocking)."""
        req = urllib.request.Request(f"http://{self.host}:{self.port}/api/status")
        req.add_header("Authorization", f"token {self.token}")
        with _DIRECT.open(req, timeout=5) as r:
            return json.loads(r.read())

    def close(self) -> None:
        stop_process(self.proc)


# -- sampling -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Window:
    """One sample: the window ending ``t_s`` seconds into its phase."""

    t_s: float
    fast_fps: tuple[float, ...]
    latency_ms: float
    rss_mb: float
    threads: int
    fds: int
    server_cpu_pct: float
    server_fps: float
    server_viewers: int
    slow_frames: dict[str, int] = field(default_factory=dict)
    slow_bytes: dict[str, int] = field(default_factory=dict)
    children: int = 0
    """The server's child processes: the simulated head's render process runs only while
    poses are missing from the disk cache."""

    @property
    def median_fps(self) -> float:
        return statistics.median(self.fast_fps) if self.fast_fps else math.nan

    @property
    def min_fps(self) -> float:
        return min(self.fast_fps) if self.fast_fps else math.nan

    @property
    def share(self) -> float:
        """The median fast viewer's frames / the frames the server published."""
        return self.median_fps / self.server_fps if self.server_fps > 0 else math.nan


async def _frames_out(console: ConsoleProcess) -> tuple[float, int]:
    """(frames the console has published, viewers it counts) from ``/api/status``; NaN
    and -1 if it does not answer."""
    try:
        status = await asyncio.to_thread(console.status)
        return float(status["frames_out"]), int(status["viewers"])
    except (OSError, ValueError, KeyError):
        return math.nan, -1


@dataclass
class Phase:
    """The samples of one phase: its windows and the server's RSS every ``RSS_EVERY_S``
    (``rss``: pairs of seconds into the phase and MB)."""

    windows: list[Window] = field(default_factory=list)
    rss: list[tuple[float, float]] = field(default_factory=list)


RSS_EVERY_S = 1.0
"""The server's RSS is read this often (more samples: a slope less swayed by the
allocator's ups and downs, which reach tens of MB between seconds)."""


async def sample_phase(
    console: ConsoleProcess,
    fast: Sequence[FastViewer],
    slow: Sequence[SlowWsViewer | SlowMjpegReader],
    duration_s: float,
    window_s: float,
    on_window: Callable[[Window], None] | None = None,
) -> Phase:
    """For ``duration_s``: every ``window_s`` the viewers' progress and the server's
    process and status, every :data:`RSS_EVERY_S` the server's RSS."""
    t0 = time.monotonic()
    t_prev = t0
    frames_prev = [v.frames for v in fast]
    cpu_prev = sample_process(console.pid).cpu_s
    published_prev = await _frames_out(console)
    phase = Phase()
    per_window = math.ceil(window_s / RSS_EVERY_S)
    tick = window_s / per_window  # windows end on ticks
    k = 0
    while True:
        k += 1
        await asyncio.sleep(max(0.0, t0 + min(k * tick, duration_s) - time.monotonic()))
        now = time.monotonic()
        proc = sample_process(console.pid)
        phase.rss.append((now - t0, proc.rss_mb))
        last = now - t0 >= duration_s - 1e-3
        if k % per_window and not last:
            continue
        dt = now - t_prev
        frames = [v.frames for v in fast]
        fps = tuple((f - p) / dt for f, p in zip(frames, frames_prev, strict=True))
        latencies = [x for v in fast for x in v.latencies_ms]
        for v in fast:
            v.latencies_ms.clear()
        published = await _frames_out(console)
        w = Window(
            t_s=now - t0,
            fast_fps=fps,
            latency_ms=statistics.median(latencies) if latencies else math.nan,
            rss_mb=proc.rss_mb,
            threads=proc.threads,
            fds=proc.fds,
            server_cpu_pct=100.0 * (proc.cpu_s - cpu_prev) / dt,
            server_fps=(published[0] - published_prev[0]) / dt,
            server_viewers=published[1],
            slow_frames={v.kind: v.frames for v in slow},
            slow_bytes={v.kind: v.bytes for v in slow},
            children=proc.children,
        )
        phase.windows.append(w)
        if on_window is not None:
            on_window(w)
        t_prev, frames_prev, cpu_prev, published_prev = now, frames, proc.cpu_s, published
        if last:
            return phase


# -- the report ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Criterion:
    """One pass/fail condition. ``judged`` False: the run was too short to tell (the RSS
    slope of a run of seconds is the allocator's noise); it neither passes nor fails."""

    name: str
    value: float
    limit: str
    ok: bool
    judged: bool = True

    @property
    def failed(self) -> bool:
        return self.judged and not self.ok


@dataclass
class SoakReport:
    """What a soak measured: both phases, figures, the viewers' end state, criteria."""

    config: SoakConfig
    baseline: Phase
    soak: Phase
    figures: dict[str, float]
    viewers: list[dict[str, Any]]
    criteria: list[Criterion]

    @property
    def ok(self) -> bool:
        return not any(c.failed for c in self.criteria)

    def format(self) -> str:
        """The soak's table, then the summary and the criteria."""
        rows = [format_row(w, self.figures["baseline_fps"]) for w in self.soak.windows]
        return "\n".join([TABLE_HEAD, *rows, "", format_summary(self)])


TABLE_HEAD = (
    f"{'t_s':>6} {'fast_med':>8} {'fast_min':>8} {'ratio':>5} {'lat_ms':>6} {'srv_fps':>7} "
    f"{'srv_cpu%':>8} {'rss_mb':>7} {'thr':>4} {'fds':>4} {'viewers':>7}  slow: frames/kB"
)


def format_row(w: Window, baseline_fps: float) -> str:
    """One line of the table: the window ``w``; ``ratio`` is its median fast fps over
    ``baseline_fps``."""
    ratio = w.median_fps / baseline_fps if baseline_fps else math.nan
    slow = " ".join(f"{k} {w.slow_frames[k]}/{w.slow_bytes[k] / 1e3:.0f}" for k in w.slow_frames)
    return (
        f"{w.t_s:6.1f} {w.median_fps:8.1f} {w.min_fps:8.1f} {ratio:5.2f} {w.latency_ms:6.0f} "
        f"{w.server_fps:7.1f} {w.server_cpu_pct:8.0f} {w.rss_mb:7.1f} {w.threads:4d} "
        f"{w.fds:4d} {w.server_viewers:7d}  {slow}"
    ).rstrip()


def format_summary(report: SoakReport) -> str:
    """The figures in a few lines, the slow readers, errors, the criteria, PASS/FAIL."""
    f = report.figures
    lines = [
        f"baseline (1 viewer): {f['baseline_fps']:.1f} fps "
        f"(server published {f['baseline_server_fps']:.1f} fps; the viewer got "
        f"{100 * f['baseline_share']:.0f} % of them)",
        f"fast viewers ({f['viewers']:.0f}): median {f['fast_fps_median']:.1f} fps = "
        f"{f['fast_fps_ratio']:.2f} x baseline (server published {f['server_fps_median']:.1f}, "
        f"median viewer got {100 * f['fast_share']:.0f} % of them); "
        f"slowest viewer {f['fast_viewer_min_fps']:.1f} fps mean, worst window "
        f"{f['fast_window_min_fps']:.1f}; latency median {f['latency_ms_median']:.0f} ms",
        f"server RSS: {f['rss_start_mb']:.1f} MB after a {f['warmup_s']:.0f} s warm-up, end "
        f"{f['rss_end_mb']:.1f}, max {f['rss_max_mb']:.1f}, slope "
        f"{f['rss_slope_mb_per_min']:+.2f} MB/min ({f['rss_samples']:.0f} samples)",
        f"server threads {f['threads_start']:.0f} -> {f['threads_end']:.0f}, fds "
        f"{f['fds_start']:.0f} -> {f['fds_end']:.0f}, CPU {f['server_cpu_pct']:.0f} % "
        f"(this process {f['client_cpu_pct']:.0f} %)",
    ]
    for v in report.viewers:
        if v["kind"] != "fast":
            stalls = f"{v['stalls']} stalls, " if v["kind"] == "ws" else ""
            lines.append(
                f"slow {v['kind']}: {v['frames']} frames, {v['bytes'] / 1e3:.0f} kB, {stalls}"
                + (f"ERROR {v['error']}" if v["error"] else "connected to the end")
            )
    for v in report.viewers:
        if v["kind"] == "fast" and v["error"]:
            lines.append(f"fast viewer {v['index']}: ERROR {v['error']}")
    lines.append("criteria:")
    for c in report.criteria:
        mark = "FAIL" if c.failed else "ok  " if c.judged else "n/a "
        lines.append(f"  {mark} {c.name} = {c.value:.3g} ({c.limit})")
    unjudged = [c.name for c in report.criteria if not c.judged]
    verdict = "PASS" if report.ok else "FAIL"
    if unjudged:
        verdict += f" (not judged, the run is too short: {', '.join(unjudged)})"
    lines.append(verdict)
    return "\n".join(lines)


def _median(values: Sequence[float]) -> float:
    values = [v for v in values if v == v]  # NaN: nothing measured
    return statistics.median(values) if values else math.nan


def summarize(
    cfg: SoakConfig,
    baseline: Phase,
    soak: Phase,
    viewers: Sequence[dict[str, Any]],
    client_cpu_pct: float = math.nan,
) -> tuple[dict[str, float], list[Criterion]]:
    """Figures and criteria from both phases and the viewers' end state (dicts with
    ``kind``, ``frames``, ``bytes``, ``error``; ``kind`` ``fast`` or a slow kind)."""
    windows = soak.windows
    base_fps = _median([w.median_fps for w in baseline.windows])
    warmup = cfg.warmup()
    rss = [(t, mb) for t, mb in soak.rss if t >= warmup - 1e-6]
    late = [w for w in windows if w.t_s >= warmup - 1e-6] or windows[-1:]
    n_fast = len(windows[0].fast_fps) if windows else 0
    durations = [b - a for a, b in itertools.pairwise([0.0, *(w.t_s for w in windows)])]
    soak_s = windows[-1].t_s if windows else math.nan
    per_viewer = [
        sum(w.fast_fps[i] * dt for w, dt in zip(windows, durations, strict=True)) / soak_s
        for i in range(n_fast)
    ]
    nan = math.nan
    fig: dict[str, float] = {
        "viewers": float(n_fast),
        "baseline_fps": base_fps,
        "baseline_server_fps": _median([w.server_fps for w in baseline.windows]),
        "baseline_share": _median([w.share for w in baseline.windows]),
        "fast_fps_median": _median([w.median_fps for w in windows]),
        "fast_viewer_min_fps": min(per_viewer, default=nan),
        "fast_window_min_fps": min((w.min_fps for w in windows), default=nan),
        "latency_ms_median": _median([w.latency_ms for w in windows]),
        "server_fps_median": _median([w.server_fps for w in windows]),
        "fast_share": _median([w.share for w in windows]),
        "server_cpu_pct": _median([w.server_cpu_pct for w in windows]),
        "client_cpu_pct": client_cpu_pct,
        "warmup_s": warmup,
        "rss_start_mb": rss[0][1] if rss else nan,
        "rss_end_mb": rss[-1][1] if rss else nan,
        "rss_max_mb": max((mb for _, mb in rss), default=nan),
        "rss_slope_mb_per_min": slope_per_minute([t for t, _ in rss], [mb for _, mb in rss]),
        "rss_samples": float(len(rss)),
        "threads_start": float(late[0].threads) if late else nan,
        "threads_end": float(windows[-1].threads) if windows else nan,
        "fds_start": float(late[0].fds) if late else nan,
        "fds_end": float(windows[-1].fds) if windows else nan,
        "render_processes": float(max((w.children for w in late), default=0)),
    }
    fig["fast_fps_ratio"] = fig["fast_fps_median"] / base_fps if base_fps else nan
    fig["fast_viewer_min_ratio"] = fig["fast_viewer_min_fps"] / base_fps if base_fps else nan
    for v in viewers:
        if v["kind"] != "fast":
            fig[f"slow_{v['kind']}_frames"] = float(v["frames"])
            fig[f"slow_{v['kind']}_kb"] = v["bytes"] / 1e3

    slope = fig["rss_slope_mb_per_min"]
    fit_s = (rss[-1][0] - rss[0][0]) if rss else 0.0
    threads = fig["threads_end"] - fig["threads_start"]
    fds = fig["fds_end"] - fig["fds_start"]
    connected = sum(1 for v in viewers if not v["error"])
    progress = all(v["bytes"] > 0 for v in viewers if v["kind"] != "fast")
    ratio, min_ratio = fig["fast_fps_ratio"], fig["fast_viewer_min_ratio"]
    worst = fig["fast_window_min_fps"]
    renders = fig["render_processes"]
    criteria = [  # comparisons with NaN are False: nothing measured fails
        Criterion("fast_fps_ratio", ratio, f">= {MIN_FPS_RATIO}", ratio >= MIN_FPS_RATIO),
        Criterion(
            "fast_viewer_min_ratio",
            min_ratio,
            f">= {MIN_VIEWER_RATIO}",
            min_ratio >= MIN_VIEWER_RATIO,
        ),
        Criterion(
            "rss_slope_mb_per_min",
            slope,
            f"<= {MAX_RSS_SLOPE_MB_PER_MIN}, fitted over {fit_s:.0f} s after the warm-up",
            slope <= MAX_RSS_SLOPE_MB_PER_MIN,
            judged=fit_s >= MIN_FIT_S,
        ),
        Criterion(
            "thread_growth", threads, f"<= {MAX_THREAD_GROWTH}", threads <= MAX_THREAD_GROWTH
        ),
        Criterion("fd_growth", fds, f"<= {MAX_FD_GROWTH}", fds <= MAX_FD_GROWTH),
        Criterion(
            "fast_window_min_fps", worst, "> 0: every fast viewer served in every window", worst > 0
        ),
        Criterion(
            "render_processes",
            renders,
            "== 0 after the warm-up: the console renders no poses (its RSS would grow by "
            "8.4 MB a pose: the disk cache was not full)",
            renders == 0,
        ),
        Criterion(
            "viewers_connected",
            float(connected),
            f"== {len(viewers)} to the end; each slow reader got data",
            connected == len(viewers) and progress,
        ),
    ]
    return fig, criteria


# -- the run ------------------------------------------------------------------------------


async def _wait_first_frames(viewers: Sequence[Viewer], timeout_s: float) -> None:
    async def one(v: Viewer) -> None:
        while not v.first_frame.is_set() and not v.done:
            try:
                await asyncio.wait_for(v.first_frame.wait(), 0.5)
            except TimeoutError:
                pass
        if not v.first_frame.is_set():
            raise RuntimeError(f"a {v.kind} viewer got no frame: {v.error}")

    await asyncio.wait_for(asyncio.gather(*(one(v) for v in viewers)), timeout_s)


async def _cancel(tasks: Sequence[asyncio.Task[None]]) -> None:
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


def _viewer_state(i: int, v: Viewer) -> dict[str, Any]:
    return {
        "index": i,
        "kind": v.kind,
        "frames": v.frames,
        "bytes": v.bytes,
        "stalls": getattr(v, "stalls", 0),
        "error": v.error,
    }


async def soak(
    console: ConsoleProcess, cfg: SoakConfig, out: Callable[[str], None] = print
) -> SoakReport:
    """Both phases against a running console; prints a row per window to ``out``."""
    base_fps = math.nan

    def show(w: Window) -> None:
        out(format_row(w, base_fps))

    first = FastViewer(console.ws_url, console.token)
    task = asyncio.create_task(first.run())
    try:
        await _wait_first_frames([first], cfg.start_timeout_s)
        await asyncio.sleep(cfg.settle_s)
        out(f"baseline: 1 viewer for {cfg.baseline_s:g} s")
        out(TABLE_HEAD)
        baseline = await sample_phase(console, [first], [], cfg.baseline_s, cfg.window_s, show)
    finally:
        await _cancel([task])
    if first.error:
        raise RuntimeError(f"the baseline viewer failed: {first.error}")
    base_fps = _median([w.median_fps for w in baseline.windows])
    out(f"baseline: {base_fps:.1f} fps")

    fast = [FastViewer(console.ws_url, console.token) for _ in range(cfg.viewers)]
    slow: list[SlowWsViewer | SlowMjpegReader] = []
    if "ws" in cfg.slow:
        slow.append(SlowWsViewer(console.host, console.port, console.token, cfg))
    if "mjpeg" in cfg.slow:
        slow.append(SlowMjpegReader(console.host, console.port, console.token, cfg))
    tasks = [asyncio.create_task(v.run()) for v in [*fast, *slow]]
    try:
        await _wait_first_frames(fast, cfg.start_timeout_s)
        out(f"soak: {cfg.viewers} fast viewers + slow {', '.join(cfg.slow) or 'none'}")
        out(TABLE_HEAD)
        cpu0, t0 = time.process_time(), time.monotonic()
        phase = await sample_phase(console, fast, slow, cfg.soak_s, cfg.window_s, show)
        client_cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - t0)
    finally:
        await _cancel(tasks)
    viewers = [_viewer_state(i, v) for i, v in enumerate([*fast, *slow])]
    figures, criteria = summarize(cfg, baseline, phase, viewers, client_cpu)
    return SoakReport(cfg, baseline, phase, figures, viewers, criteria)


def run_soak(cfg: SoakConfig, out: Callable[[str], None] = print) -> SoakReport:
    """Start a console, run :func:`soak` against it, stop it."""
    if cfg.viewers < 1 or cfg.soak_s <= 0 or cfg.baseline_s <= 0 or cfg.window_s <= 0:
        raise ValueError("soak: viewers, soak_s, baseline_s and window_s must be positive")
    unknown = set(cfg.slow) - set(SLOW_KINDS)
    if unknown:
        raise ValueError(f"soak: unknown slow readers {sorted(unknown)} (known: {SLOW_KINDS})")
    if cfg.prewarm:
        t = time.monotonic()
        poses = prewarm_pose_cache()
        out(f"pose cache: {poses} poses on disk ({time.monotonic() - t:.1f} s)")
    with tempfile.TemporaryDirectory(prefix="trifuse-soak-") as tmp:
        console = ConsoleProcess(Path(tmp), cfg.start_timeout_s)
        try:
            out(f"console: pid {console.pid}, port {console.port}")
            report = asyncio.run(soak(console, cfg, out))
        except BaseException:
            out(f"console log:\n{console.log()}")
            raise
        finally:
            console.close()
    return report


def run_soak_cli(cfg: SoakConfig) -> int:
    """``trifuse bench --soak``: rows as they come, then the table and the verdict; 0 if
    every criterion holds, else 1."""

    def out(line: str) -> None:
        print(line, flush=True)

    out(f"stream soak: {cfg.describe()}")
    out(f"criteria: {CRITERIA}")
    report = run_soak(cfg, out)
    out("")
    out(format_summary(report))
    return 0 if report.ok else 1
