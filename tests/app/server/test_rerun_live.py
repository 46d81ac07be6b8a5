"""``trifuse serve --rerun`` (app/server/runtime/rerun_live.py) on a real pipeline fusing the
small rig's synthetic frames, with a real rerun process as the viewer (``rerun --save``: it
receives what an SDK sends and writes it to a file): nothing is logged (nor kept) while no
viewer answers; once one listens the console connects and logs the rig (each sensor's pose
and pinhole), the images, the TOF's cloud, the fused pair and the thermal map being built
(the head's path, the rig at its pose); a viewer started again gets a new connection and
the rig again. A wrong address: one line."""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.support import ListSource, small_rig, synth_frame, wait_until
from trifuse.app.server.runtime import rerun_live
from trifuse.app.server.runtime.map_worker import MapWorker
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.rerun_live import RerunLive, viewer_endpoint
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T

pytest.importorskip("rerun", reason="the [rerun] extra (in the test extra)")
import rerun_cli
from rerun.chunk import RrdReader

# The rerun-sdk's viewer itself: its ``rerun`` command is a Python wrapper that runs this
# binary as a child, and a signal sent to the wrapper alone can leave the child listening.
RERUN = Path(rerun_cli.__file__).with_name("rerun")


class PacedSource(ListSource):
    """The rig's synthetic frame sets, one every 50 ms until :attr:`done` is set."""

    def __init__(self, rig: Rig) -> None:
        super().__init__([], sensors=rig.names)
        self.sim_rig, self.done = rig, threading.Event()

    def frames(self) -> Iterator[Frame]:
        rng = np.random.default_rng(0)
        k = 0
        while not self.done.is_set():
            stamp = 1_000_000_000 + k * 50_000_000
            for name in self.sim_rig.names:
                yield synth_frame(self.sim_rig, name, stamp, rng)
            k += 1
            time.sleep(0.05)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _viewer(port: int, path: Path) -> subprocess.Popen:
    """A rerun process listening on 127.0.0.1:``port`` that saves what it receives."""
    proc = subprocess.Popen(
        [str(RERUN), "--bind", "127.0.0.1", "--port", str(port), "--save", str(path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    wait_until(lambda: _answers(port), "the rerun viewer listening")
    return proc


def _answers(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return True
    except OSError:
        return False


def _entities(path: Path) -> dict[str, list[str]]:
    """Entity path -> the components logged to it (the file a viewer saved)."""
    out: dict[str, list[str]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        out[chunk.entity_path] += chunk.to_record_batch().schema.names
    return out


def _stop(proc: subprocess.Popen) -> None:
    # SIGTERM, not SIGINT: a process started in the background inherits SIGINT ignored
    # (a busy round launched with ``&`` left every viewer running; the test then waited)
    proc.terminate()  # it finishes its file
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.mark.filterwarnings("ignore::UserWarning")  # rerun: a file without its footer
def test_logs_only_to_a_viewer_that_answers_and_again_when_it_comes_back(
    tmp_path, monkeypatch
) -> None:
    monkeypatch.setattr(rerun_live, "PROBE_S", 0.2)
    monkeypatch.setattr(rerun_live, "MAP_S", 0.2)
    rig = small_rig()
    source = PacedSource(rig)
    hub = FrameHub()
    pipeline = FusionPipeline(source, rig, hub)
    port = _free_port()

    def walking(stamp_ns: int) -> np.ndarray:  # the head's pose: 0.1 m/s along x
        return make_T(np.eye(3), (0.1 * (stamp_ns * 1e-9 - 1.0), 0.0, 0.0))

    mapper = MapWorker(pipeline, walking, tmp_path / "maps", enabled=True).start()
    live = RerunLive(
        pipeline, hub, f"rerun+http://127.0.0.1:{port}/proxy", rate_hz=20.0, mapper=mapper
    )
    viewers: list[subprocess.Popen] = []
    try:
        with hub.watching():
            pipeline.start()
            live.start()
            wait_until(lambda: pipeline.status.pictures_out > 5, "pictures fused")
            time.sleep(1.0)  # five probes: nobody answers
            assert (live.connected, live.connections, live.logged) == (False, 0, 0)
            first = tmp_path / "first.rrd"
            viewers.append(_viewer(port, first))
            wait_until(lambda: live.logged >= 10, lambda: f"sets logged: {live.status()}")
            assert live.connections == 1 and live.error is None
            _stop(viewers.pop())
            wait_until(lambda: not live.connected, "the viewer gone")
            logged = live.logged
            time.sleep(0.5)
            assert live.logged == logged  # nothing logged (kept) without a viewer
            second = tmp_path / "second.rrd"
            viewers.append(_viewer(port, second))
            wait_until(lambda: live.logged >= logged + 5, lambda: f"again: {live.status()}")
            assert live.connections == 2
    finally:
        live.stop()
        mapper.stop()
        source.done.set()
        pipeline.stop()
        for proc in viewers:
            _stop(proc)
    for path in (first, second):
        entities = _entities(path)
        for name, s in rig.sensors.items():
            assert "Transform3D:translation" in entities[f"/rig/{name}"], (path, name)
            assert "Pinhole:image_from_camera" in entities[f"/rig/{name}/image"], (path, name)
            image = "EncodedImage:blob" if s.modality != "tof" else "Image:buffer"
            assert image in entities[f"/rig/{name}/image"], (path, name)
        assert "Points3D:positions" in entities["/rig/tof/cloud"]
        assert "EncodedImage:blob" in entities["/fused"]
        # the thermal map in the world, the head's path, the rig at its pose
        assert "Points3D:positions" in entities["/map"] and "Points3D:colors" in entities["/map"]
        assert "LineStrips3D:strips" in entities["/map/path"]
        assert "Transform3D:translation" in entities["/rig"]


@pytest.mark.parametrize(
    ("address", "says"),
    [
        ("http://127.0.0.1:9876", "expected a rerun viewer's address"),
        ("rerun+http://127.0.0.1:port/proxy", "is not a number"),
    ],
)
def test_a_wrong_address_is_one_line(address: str, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        viewer_endpoint(address)
    assert viewer_endpoint("rerun+http://viewer.local/proxy") == ("viewer.local", 9876)


def test_serve_refuses_a_wrong_address_in_one_line(tmp_path, capsys) -> None:
    from tests.support import run_cli

    workdir = tmp_path / "work"
    argv = ["serve", "--port", "0", "--rerun", "http://x:1", "--workdir", str(workdir)]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert "--rerun: expected a rerun viewer's address" in err
    assert not workdir.exists()  # refused before anything started
