"""Helpers shared by test modules (plain functions and classes; fixtures are in
``conftest.py``, the console launcher and the browser's settings in ``browser_support.py``).

- The checkout: :data:`ROOT`, :data:`DATA_DIR` (the real test images, with their licences),
  :data:`OPENCV_LEFT_9X6`; tests build paths from these, never from their own file's place.
- Waiting: :func:`wait_until` polls a condition another thread makes true (failing the
  test after a time-out; :func:`poll_until` returns instead); :func:`wait_for_exit` waits
  for a forked child. Tests write no deadline loops of their own.
- Web apps: :func:`serve` runs one with uvicorn on a free loopback port.
- The command line: :func:`run_cli` runs ``trifuse`` in this process.
- Time: :class:`FakeClock`, a clock and a sleep that a test moves, for code that paces
  itself on the wall clock (``clock``/``sleep`` parameters): what such code decides is
  checked exactly, whatever else the machine is doing. How fast things are is measured
  by ``trifuse bench``, not asserted by tests.
- Sources: :class:`ListSource`, given frames as fast as they are taken.
- Recordings: a small five-sensor head, seeded synthetic frames at the sensors' rates,
  writing a recording and comparing replayed frames with what was written.
- Capture directories: a small three-sensor rig, its board and a view of known values.
- Calibration: the accuracy targets, a rig with sensors mounted upside down.
- Viser: opening its port directly, as a browser or an attacker would.
- Memory: :func:`measure_in_child`, one call's peak memory and time in a fresh interpreter.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest

from trifuse.app.devtools.image_quality import psnr
from trifuse.app.recording import RecordingWriter
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Eye, Rig, Sensor
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.calib.units import encode_amplitude, encode_distance, encode_thermal

V = TypeVar("V")

# -- the checkout ---------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parent.parent
"""The checkout's root (``pyproject.toml``, ``app/``, ``tests/``)."""
DATA_DIR = ROOT / "tests" / "data"
"""The real images and files the tests read, each with its licence and README: everything
the tests read lies inside the checkout, so a fresh clone runs them as they are."""
OPENCV_LEFT_9X6 = DATA_DIR / "opencv-left-9x6"
"""OpenCV's 9 x 6 chessboard samples (left camera)."""

# -- waiting --------------------------------------------------------------------------------

WAIT_S = 120.0
"""How long a test waits at most for something another thread or process does. Generous:
on a busy machine that thread may get little CPU; a test that passes returns as soon as the
condition holds, so only a failing test waits this long."""


def poll_until(
    condition: Callable[[], V],
    timeout_s: float,
    *,
    poll_s: float = 0.02,
    pause: Callable[[float], object] = time.sleep,
) -> V:
    """Call ``condition`` at once, then every ``poll_s`` seconds (waiting with ``pause``),
    until it returns something true or ``timeout_s`` has passed; its last value (false when
    the time ran out: the caller decides what that means)."""
    end = time.monotonic() + timeout_s
    while not (value := condition()) and time.monotonic() <= end:
        pause(poll_s)
    return value


def wait_until(
    condition: Callable[[], V],
    what: str | Callable[[], object] = "the condition",
    timeout_s: float = WAIT_S,
    *,
    poll_s: float = 0.02,
    pause: Callable[[float], object] = time.sleep,
) -> V:
    """Poll ``condition`` until it returns something true, and return that; fail saying
    ``what`` (or what ``what()`` says then: the state it waits on) after ``timeout_s``.

    Args:
        condition: called at once, then every ``poll_s`` seconds.
        pause: how to wait ``poll_s`` seconds between calls (a browser page's own wait lets
            the page run meanwhile: :func:`tests.browser_support.wait_on_page`).
    """
    value = poll_until(condition, timeout_s, poll_s=poll_s, pause=pause)
    if not value:
        said = what if isinstance(what, str) else what()
        pytest.fail(f"timed out after {timeout_s} s waiting for {said}")
    return value


def wait_searched(session) -> None:
    """Until every view of a :class:`~app.workflows.calib_session.CalibrationSession` has
    been searched for the board (in its background thread)."""
    wait_until(lambda: all(v.searched for v in session.views()), "every view searched")


def wait_for_exit(pid: int, what: str, timeout_s: float = WAIT_S) -> int:
    """Wait for the child process ``pid`` (``os.fork``) to end; its wait status. After
    ``timeout_s`` it is killed and the test fails saying it waited for ``what``."""
    status: list[int] = []

    def ended() -> bool:
        done, code = os.waitpid(pid, os.WNOHANG)
        status.append(code)
        return done != 0

    try:
        wait_until(ended, what, timeout_s)
    except pytest.fail.Exception:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        raise
    return status[-1]


# -- a web app on a port --------------------------------------------------------------------


@contextlib.contextmanager
def serve(app: object, ws_max_size: int = 4 << 20, port: int | None = None) -> Iterator[int]:
    """Run the ASGI ``app`` (FastAPI) with uvicorn on 127.0.0.1 (a free port unless given),
    in a thread; yields the port once it serves."""
    import uvicorn

    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port or 0))
    port = sock.getsockname()[1]
    config = uvicorn.Config(app, log_level="warning", ws_max_size=ws_max_size, lifespan="off")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    wait_until(lambda: server.started, "uvicorn to start", 10, poll_s=0.01)
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()


# -- the command line -----------------------------------------------------------------------


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``trifuse argv`` in this process: its exit status, stdout and stderr (never a
    traceback: the CLI turns errors into one line)."""
    from trifuse.app.cli import main

    code = main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err, out + err
    return code, out, err


# -- time -----------------------------------------------------------------------------------


class FakeClock:
    """A monotonic clock (seconds) that only moves when told: :meth:`sleep` (what paced
    code calls to wait; it returns at once) or :meth:`advance` (a consumer that is busy).

    Attributes:
        now: the clock's reading, seconds.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self.now = float(start_s)

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> bool:
        """Move the clock on by ``seconds``; False, like an ``Event.wait`` nobody set."""
        assert seconds >= 0, seconds
        self.now += seconds
        return False

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def wall_ns(self) -> int:
        """A wall clock that goes with it: 1e9 s (2001) + :attr:`now`, nanoseconds."""
        return round((1e9 + self.now) * 1e9)


# -- sources --------------------------------------------------------------------------------


class ListSource(FrameSource):
    """The given frames, as fast as they are taken (not ``realtime``); none: a source that
    never delivers.

    Args:
        frames: the frames, in time order.
        sensors: the source's sensors (default: those of ``frames``, sorted by name).
        rig: the rig the source reports (default None: it knows none).
    """

    realtime = False

    def __init__(
        self,
        frames: Iterable[Frame] = (),
        sensors: Iterable[str] | None = None,
        rig: Rig | None = None,
    ) -> None:
        self._frames = list(frames)
        own = sorted({f.sensor for f in self._frames})
        self.sensors = own if sensors is None else list(sensors)
        self.rig = rig

    @classmethod
    def of_sets(cls, sets: Iterable[FrameSet], **kw) -> ListSource:
        """The frames of ``sets``, one set after the other."""
        return cls([f for fs in sets for f in fs.frames.values()], **kw)

    def frames(self) -> Iterator[Frame]:
        yield from self._frames


# -- recordings -----------------------------------------------------------------------------

RATES_HZ = {"color": 30, "thermal": 27, "tof": 15}
"""Frame rates of :func:`synth_frames` per modality (the real head's)."""


def small_rig() -> Rig:
    """A five-sensor head at a tenth of the real resolutions (fast to encode and render)."""
    spec = {  # name: modality, size, (fx, fy, cx, cy), translation m, (roll, pitch, yaw) deg
        "tof": ("tof", (44, 36), (41.4, 41.4, 21.5, 17.5), (0, 0, 0), (0, 0, 0)),
        "ccd_left": (
            "color", (128, 96), (133.3, 133.1, 63.6, 47.4), (-0.06, -0.03, 0.002), (0.6, -1.1, 0.3)
        ),
        "ccd_right": (
            "color", (128, 96), (133.6, 133.5, 63.8, 48.2), (0.06, -0.03, 0.002), (-0.4, 1.3, -0.5)
        ),
        "thermal_left": (
            "thermal", (96, 72), (100.5, 100.4, 47.9, 35.7), (-0.055, 0.001, -0.01), (1.2, 1.6, 0)
        ),
        "thermal_right": (
            "thermal", (96, 72), (99.9, 100.0, 47.4, 36.3), (0.055, -0.001, -0.01), (0, -1.8, 0.8)
        ),
    }  # fmt: skip
    sensors = {}
    for name, (modality, size, (fx, fy, cx, cy), t, rpy) in spec.items():
        dist = (-0.1, 0.02, 0.0003, -0.0002, 0.0) if modality != "tof" else (0.0,) * 5
        if name == "thermal_right":
            dist = (-0.1, 0.02, 0.0003, -0.0002, 0.001, 0.01, -0.002, 0.0005)  # rational
        T = make_T(rotation_from_euler_deg(*rpy), t)
        sensors[name] = Sensor(name, modality, size, Intrinsics(fx, fy, cx, cy, dist), T)  # type: ignore[arg-type]
    eyes = {"left": Eye("ccd_left", "thermal_left"), "right": Eye("ccd_right", "thermal_right")}
    return Rig(sensors=sensors, reference="tof", eyes=eyes)


def synth_frame(rig: Rig, sensor: str, stamp_ns: int, rng: np.random.Generator) -> Frame:
    """A seeded frame with smooth content and noise, NaN where a sensor has no reading."""
    s = rig[sensor]
    w, h = s.image_size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    phase = stamp_ns / 1e9
    if s.modality == "color":
        img = np.empty((h, w, 3), np.uint8)
        for k in range(3):
            base = 128 + 80 * np.sin(xx / (9 + 4 * k) + phase) * np.cos(yy / 13 - k)
            img[..., k] = np.clip(base + rng.normal(0, 2, (h, w)), 0, 255)
        return Frame(sensor, stamp_ns, img)
    if s.modality == "thermal":
        t = 290 + 15 * xx / w + 5 * np.sin(yy / 7 + phase) + rng.normal(0, 0.05, (h, w))
        t = t.astype(np.float32)
        t[0, :5] = np.nan
        return Frame(sensor, stamp_ns, t)
    dist = (0.5 + 7.5 * (xx + yy) / (w + h) + rng.normal(0, 0.01, (h, w))).astype(np.float32)
    dist[rng.random((h, w)) < 0.05] = np.nan
    amp = (rng.random((h, w)) * 20000).astype(np.float32)
    return Frame(sensor, stamp_ns, amp, dist)


def synth_frames(
    rig: Rig,
    duration_s: float,
    seed: int = 0,
    start_ns: int = 1_000_000_000,
    skip: Iterable[str] = (),
) -> list[Frame]:
    """Frames of every sensor at its own rate over ``duration_s``, in time order."""
    rng = np.random.default_rng(seed)
    skip = set(skip)
    frames = []
    for name, s in rig.sensors.items():
        if name in skip:
            continue
        rate = RATES_HZ[s.modality]
        k = 0
        while (t := k * 1_000_000_000 // rate) < duration_s * 1e9:
            frames.append(synth_frame(rig, name, start_ns + t, rng))
            k += 1
    order = {n: i for i, n in enumerate(rig.names)}
    return sorted(frames, key=lambda f: (f.stamp_ns, order[f.sensor]))


def write_recording(path: Path, rig: Rig, frames: Iterable[Frame], **kw) -> Path:
    """``frames`` written to the MCAP file ``path`` (``kw``: RecordingWriter's options)."""
    with RecordingWriter(path, rig, **kw) as w:
        for f in frames:
            w.write(f)
    return path


def assert_same_frame(got: Frame, want: Frame, min_psnr_db: float = 35.0) -> None:
    """``got`` is ``want`` as a recording keeps it: colour through JPEG (PSNR above
    ``min_psnr_db``), thermal to its 0.01 K and TOF distance to its 0.5 mm quantisation,
    NaN where NaN."""
    assert (got.sensor, got.stamp_ns) == (want.sensor, want.stamp_ns)
    if want.image.ndim == 3:
        assert got.image.dtype == np.uint8 and got.image.shape == want.image.shape
        assert psnr(got.image, want.image) > min_psnr_db
    elif want.distance_m is None:  # thermal: equal to the 0.01 K quantisation
        assert got.image.dtype == np.float32
        np.testing.assert_array_equal(encode_thermal(got.image), encode_thermal(want.image))
        np.testing.assert_array_equal(np.isnan(got.image), np.isnan(want.image))
    else:
        assert got.image.dtype == np.float32 and got.distance_m.dtype == np.float32
        np.testing.assert_array_equal(encode_amplitude(got.image), encode_amplitude(want.image))
        np.testing.assert_array_equal(
            encode_distance(got.distance_m), encode_distance(want.distance_m)
        )
        np.testing.assert_array_equal(np.isnan(got.distance_m), np.isnan(want.distance_m))
        assert np.nanmax(np.abs(got.distance_m - want.distance_m)) <= 0.0005 + 1e-6


# -- capture directories --------------------------------------------------------------------

CAPTURE_BOARD = Board(9, 6, 0.025)
"""The board of :func:`small_capture_rig`'s capture directories."""
CAPTURE_SIZES = {"tof": (22, 18), "ccd_left": (64, 48), "thermal_left": (38, 29)}
"""Image sizes (width, height) of :func:`small_capture_rig`'s sensors."""


def small_capture_rig() -> Rig:
    """A three-sensor rig with tiny images, so that tests write and read quickly."""
    modality = {"tof": "tof", "ccd_left": "color", "thermal_left": "thermal"}
    sensors = {}
    for i, (name, (w, h)) in enumerate(CAPTURE_SIZES.items()):
        T = (
            np.eye(4)
            if name == "tof"
            else make_T(rotation_from_euler_deg(1, 2, 3), (0.05 * i, -0.01, 0.0))
        )
        sensors[name] = Sensor(
            name,
            modality[name],
            (w, h),  # type: ignore[arg-type]
            Intrinsics(50.0, 50.0, (w - 1) / 2, (h - 1) / 2),
            T,
        )
    return Rig(sensors, "tof", {"left": Eye("ccd_left", "thermal_left")})


def capture_frames(seed: int = 0) -> FrameSet:
    """A view of :func:`small_capture_rig`: known values for every sensor, including the
    edge cases of each encoding (NaN, out of range)."""
    rng = np.random.default_rng(seed)
    w, h = CAPTURE_SIZES["ccd_left"]
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    w, h = CAPTURE_SIZES["thermal_left"]
    thermal = (280.0 + 60.0 * rng.random((h, w))).astype(np.float32)
    thermal[0, 0] = np.nan
    w, h = CAPTURE_SIZES["tof"]
    amplitude = (20000.0 * rng.random((h, w))).astype(np.float32)
    amplitude[0, 0], amplitude[0, 1] = -5.0, 70000.0
    distance = (0.1 + 9.9 * rng.random((h, w))).astype(np.float32)
    distance[1, :4] = [np.nan, 0.0, -1.0, 70.0]  # all invalid
    return FrameSet(
        123,
        {
            "tof": Frame("tof", 1, amplitude, distance),
            "ccd_left": Frame("ccd_left", 1, color),
            "thermal_left": Frame("thermal_left", 1, thermal),
        },
    )


# -- calibration ----------------------------------------------------------------------------

# Targets of the issue: focal length (relative) and pose (deg, m) per modality.
FOCAL = {"color": 0.003, "thermal": 0.003, "tof": 0.01}
POSE = {"color": (0.1, 0.001), "thermal": (0.1, 0.001), "tof": (0.2, 0.003)}


def upside_down(rig: Rig, names: tuple[str, ...]) -> Rig:
    """``rig`` with the sensors ``names`` mounted upside down: turned 180 degrees about
    their optical axis (``T_rig_sensor @ Rz(180)``)."""
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    sensors = {
        n: dataclasses.replace(s, T_rig_sensor=s.T_rig_sensor @ flip) if n in names else s
        for n, s in rig.sensors.items()
    }
    return Rig(sensors=sensors, reference=rig.reference, eyes=dict(rig.eyes))


# -- Viser ----------------------------------------------------------------------------------


def direct_websocket(port: int, headers: dict[str, str]) -> int | None:
    """Open Viser's port directly; the HTTP status it refused with, None if accepted."""
    import viser
    import websockets.exceptions
    import websockets.sync.client

    try:
        with websockets.sync.client.connect(
            f"ws://127.0.0.1:{port}/",
            subprotocols=[f"viser-v{viser.__version__}"],
            additional_headers=headers,
            open_timeout=10,
        ):
            return None
    except websockets.exceptions.InvalidStatus as e:
        return e.response.status_code


def record_survey_archive(directory: Path, seeds: Iterable[int], duration_s: float) -> list[Path]:
    """Recordings ``mission<seed>.mcap`` of the simulated survey (the head pans, its poses
    recorded) at a tenth of the real resolutions (:func:`small_rig`), made by ``trifuse
    record``: the archive an offline job (fuse, map) runs over."""
    from trifuse.app.cli import main
    from trifuse.app.storage.rigfile import save_rig

    rig_path = save_rig(directory / "rig.yaml", small_rig())
    out = []
    for seed in seeds:
        path = directory / f"mission{seed}.mcap"
        argv = ["record", "--source", "sim", "--scenario", "survey", "--duration", str(duration_s)]
        assert main([*argv, "--rig", str(rig_path), "--seed", str(seed), "--out", str(path)]) == 0
        out.append(path)
    return out


def directory_bytes(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` (hidden ones too) by relative path, with its bytes."""
    return {
        str(p.relative_to(directory)): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


_MEASURE = """
import json, resource, sys, time
exec(sys.argv[1])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
try:
    outcome = str(eval(sys.argv[2]))
except {error} as exc:
    outcome = str(exc)
took = time.perf_counter() - start
grew = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base
print(json.dumps({{"outcome": outcome, "grew_mib": grew / 1024, "took_s": took}}))
"""


def measure_in_child(setup: str, call: str, error: str, timeout_s: float = 120.0) -> dict:
    """Run ``setup`` (statements: imports, reading input) and then evaluate ``call`` (an
    expression) in a fresh interpreter at the repository's root; ``{"outcome": str(its
    value) or the message of the ``error`` it raised (an exception name ``setup`` made
    available), "grew_mib": the peak resident memory added by the call (ru_maxrss), MiB,
    "took_s": its wall time}``. Any other exception fails the test with the child's
    traceback."""
    child = subprocess.run(
        [sys.executable, "-c", _MEASURE.format(error=error), setup, call],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    if child.returncode != 0:
        pytest.fail(f"the child failed:\n{child.stderr}")
    return json.loads(child.stdout)


def copy_first_views(capture: Path, folder: Path, n: int, files: tuple[str, ...] = ()) -> None:
    """Into a new ``folder``: the first ``n`` view folders of the capture directory
    ``capture`` (``0001`` ...) and its ``files`` (e.g. ``board.yaml``, ``rig.yaml``)."""
    folder.mkdir(parents=True)
    for name in files:
        shutil.copy(capture / name, folder / name)
    for i in range(1, n + 1):
        shutil.copytree(capture / f"{i:04d}", folder / f"{i:04d}")


LOOPBACK_DDS = (
    '<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
    "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto"
    "</ParticipantIndex><MaxAutoParticipantIndex>50</MaxAutoParticipantIndex><Peers>"
    '<Peer address="127.0.0.1"/></Peers></Discovery><Internal>'
    '<SocketReceiveBufferSize min="default" max="64MB"/></Internal></Domain></CycloneDDS>'
)
"""A Cyclone DDS configuration (``CYCLONEDDS_URI``) for the ROS 2 tests: loopback only,
unicast discovery (no multicast, which a machine's network may not have), the large socket
buffers of app/recording/ros2_live.py."""
