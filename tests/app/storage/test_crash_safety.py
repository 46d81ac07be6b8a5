"""Nothing lost (issue 8): a crash at any moment of a capture, a save or a recording leaves
the previous state readable and the new one complete or absent.

Two levels:

* Deterministic: a forked child runs one write (an atomic file write, a capture view, a rig
  version) and dies (``os._exit``, no clean-up runs) at a chosen step; the parent checks
  what is on disk and what a restart makes of it. A child process writing a recording is
  SIGKILLed; the partial MCAP is recovered, readable up to its last complete chunk.
* The console: ``trifuse serve --scenario calibration`` is SIGKILLed at seeded random
  moments while a client thread captures views, calibrates, saves rig versions and records,
  then restarted on the same work directory: every acknowledged (2xx) capture and rig
  version is listed and byte-identical, everything listed loads, the interrupted recording
  is kept and reported, and the console works on.

No timing is asserted (shared, noisy machine): waits have generous time-outs only.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from tests.browser_support import TEST_BOARD_POSES, wait_for_cache_warmup
from tests.support import ROOT, copy_first_views, wait_for_exit, wait_until
from trifuse.app.devtools.console_process import ConsoleProcess
from trifuse.app.recording import ReplaySource
from trifuse.app.recording.recorder import Recorder
from trifuse.app.recording.recovery import recover_interrupted
from trifuse.app.recording.sealed_file import SEAL
from trifuse.app.recording.writer import RecordingWriter
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.storage import atomic as atomic_mod
from trifuse.app.storage import capture_writer as capture_writer_mod
from trifuse.app.storage.atomic import atomic_write_bytes, remove_temporaries
from trifuse.app.storage.capture import load_capture, load_view
from trifuse.app.storage.capture_writer import write_board, write_rig, write_view
from trifuse.app.storage.rigfile import load_rig
from trifuse.app.workflows.calib_session import CalibrationSession

CRASHED = 86  # exit code of a child that "crashed" where the test wanted
TOKEN = "crash-safety-token-0123456789"


# -- deterministic crashes in a forked child ----------------------------------------------


def _crash_in_child(action: Callable[[], Any], module: Any, name: str, nth: int = 1) -> None:
    """Run ``action`` in a forked child that dies (no clean-up, like a SIGKILL) on the
    ``nth`` call of ``module.name``, before that call does anything."""
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 1
        try:
            original = getattr(module, name)
            calls = [0]

            def crash(*args: Any, **kwargs: Any) -> Any:
                calls[0] += 1
                if calls[0] == nth:
                    os._exit(CRASHED)
                return original(*args, **kwargs)

            setattr(module, name, crash)
            action()
            code = 0  # finished without reaching the crash point
        finally:
            os._exit(code)
    status = wait_for_exit(pid, f"the child writing with a crash at {name} #{nth}", 120)
    assert os.waitstatus_to_exitcode(status) == CRASHED, f"{name} #{nth} was never reached"


def _temporaries(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


@pytest.mark.parametrize(
    ("module", "name", "new_is_there"),
    [
        (os, "fsync", False),  # data written, not yet durable
        (os, "replace", False),  # data durable, not yet renamed
        (atomic_mod, "fsync_dir", True),  # renamed, the directory not yet fsynced
    ],
)
def test_atomic_write_crash_leaves_old_or_new(tmp_path, module, name, new_is_there) -> None:
    path = tmp_path / "rig.yaml"
    path.write_bytes(b"old: 1\n")
    new = b"new: 2\n" * 1000
    _crash_in_child(lambda: atomic_write_bytes(path, new), module, name)
    assert path.read_bytes() == (new if new_is_there else b"old: 1\n")
    # a restart removes the temporary file, and the target is as it was
    removed = remove_temporaries(tmp_path)
    assert _temporaries(tmp_path) == []
    assert len(removed) == (0 if new_is_there else 1)
    assert path.read_bytes() == (new if new_is_there else b"old: 1\n")
    atomic_write_bytes(path, b"after: 3\n")  # writing works on
    assert path.read_bytes() == b"after: 3\n"


@pytest.mark.parametrize(("name", "new_is_there"), [("link", False), ("unlink", True)])
def test_new_file_crash_is_complete_or_absent(tmp_path, name, new_is_there) -> None:
    """``overwrite=False`` (rig versions): hard link into place, then drop the temporary."""
    path = tmp_path / "rig-0002.yaml"
    data = b"x" * 100_000
    _crash_in_child(lambda: atomic_write_bytes(path, data, overwrite=False), os, name)
    assert (path.read_bytes() == data) if new_is_there else not path.exists()
    assert len(_temporaries(tmp_path)) == 1  # the temporary (a second link if complete)
    remove_temporaries(tmp_path)
    assert _temporaries(tmp_path) == []
    assert (path.read_bytes() == data) if new_is_there else not path.exists()


def _flat_frames(rig, stamp_ns: int = 0, seed: int = 0) -> FrameSet:
    """A frame set of every sensor with the rig's sizes (no board: nothing to find)."""
    rng = np.random.default_rng(seed)
    frames = {}
    for name, s in rig.sensors.items():
        w, h = s.image_size
        if s.modality == "color":
            image = np.full((h, w, 3), rng.integers(0, 255), np.uint8)
            frames[name] = Frame(name, stamp_ns, image)
        elif s.modality == "thermal":
            frames[name] = Frame(name, stamp_ns, np.full((h, w), 300.0 + seed, np.float32))
        else:
            amp = np.full((h, w), 100.0 + seed, np.float32)
            frames[name] = Frame(name, stamp_ns, amp, np.full((h, w), 1.5, np.float32))
    return FrameSet(stamp_ns, frames)


def _file_hashes(folder: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.iterdir())
        if p.is_file()
    }


@pytest.mark.parametrize(
    ("module", "name", "nth", "new_is_there"),
    [
        (os, "replace", 3, False),  # two images written into the staging folder, third not
        (os, "rename", 1, False),  # every image written, the folder not renamed into place
        # renamed, the capture directory not fsynced
        (capture_writer_mod, "fsync_dir", 2, True),
    ],
)
def test_capture_crash_leaves_views_whole(tmp_path, module, name, nth, new_is_there) -> None:
    rig = default_rig()
    captures = tmp_path / "captures"
    write_board(captures, CALIBRATION_BOARD)
    write_rig(captures, rig)
    write_view(captures, "0001", _flat_frames(rig, seed=1), rig)
    before = _file_hashes(captures / "0001")
    _crash_in_child(
        lambda: write_view(captures, "0002", _flat_frames(rig, seed=2), rig), module, name, nth
    )
    views = [v.name for v in load_capture(captures, verify=True).views]
    assert views == (["0001", "0002"] if new_is_there else ["0001"])
    assert _file_hashes(captures / "0001") == before
    staging = [p for p in captures.iterdir() if p.name.endswith(".partial")]
    assert len(staging) == (0 if new_is_there else 1)

    # A restart: the interrupted view is not listed but kept (its images are kept, the
    # temporary file of the image being written is removed); capturing works on.
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD, workers=1)
    try:
        assert [v.name for v in session.views()] == views
        assert session.interrupted == staging
        for folder in staging:
            assert _temporaries(folder) == []
            assert len(list(folder.iterdir())) >= (2 if name == "replace" else len(rig.names))
        taken = session.take(_flat_frames(rig, seed=3))
        assert taken.name == "0003"  # the interrupted view's number is not used again
        load_view(captures, taken.name, rig).frames()
    finally:
        session.close()
    assert _file_hashes(captures / "0001") == before


def test_rig_save_crash_keeps_versions_and_numbers_go_on(tmp_path) -> None:
    """The report is written first, the rig file (which makes the version) last: a crash
    between them leaves a report alone, which is not listed and whose number is not used
    again (it used to block every later save: 'could not find a free version name')."""
    rig = default_rig()
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD, workers=1)
    first = session.save_rig(rig, {"rms_px": 0.1})
    rig_bytes, report_bytes = (
        first.path.read_bytes(),
        (tmp_path / "rigs" / "rig-0001.report.json").read_bytes(),
    )
    session.close()
    # the second os.link is the rig file's (the first is the report's)
    _crash_in_child(lambda: session.save_rig(rig, {"rms_px": 0.2}), os, "link", nth=2)
    rigs = tmp_path / "rigs"
    assert (rigs / "rig-0002.report.json").is_file() and not (rigs / "rig-0002.yaml").exists()

    again = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD, workers=1)
    try:
        assert [v.name for v in again.versions()] == ["rig-0001"]
        assert _temporaries(rigs) == []
        saved = again.save_rig(rig, {"rms_px": 0.3})
        assert saved.name == "rig-0003"
        assert [v.name for v in again.versions()] == ["rig-0001", "rig-0003"]
        assert again.versions()[1].rms_px == 0.3
        assert load_rig(saved.path).names == rig.names
    finally:
        again.close()
    assert first.path.read_bytes() == rig_bytes
    assert (rigs / "rig-0001.report.json").read_bytes() == report_bytes


# -- recordings: a writer killed in the middle ----------------------------------------------

_RECORD_CHILD = """
import os, signal, sys
import numpy as np
from trifuse.app.recording.writer import RecordingWriter
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.head import default_rig
rig = default_rig()
w, h = rig["thermal_left"].image_size
rng = np.random.default_rng(5)
writer = RecordingWriter(sys.argv[1], rig, chunk_size=64 * 1024, seal_period_s=3600)
k = 0
def frame():
    image = (290 + 20 * rng.random((h, w))).astype(np.float32)
    return Frame("thermal_left", 1_000_000_000 + k * 50_000_000, image)
while k < 30:
    writer.write(frame())
    k += 1
writer.seal()  # what the writer does every second (seal_period_s)
print(k, flush=True)
for _ in range(5):  # written after the last seal: only in memory when the kill comes
    writer.write(frame())
    k += 1
os.kill(os.getpid(), signal.SIGKILL)
"""


_SIGTERM_CHILD = """
import os, signal, sys, threading, time
import numpy as np
from trifuse.app.cli.record import _sigterm_as_interrupt
from trifuse.app.recording import sealed_file
from trifuse.app.recording.writer import RecordingWriter
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.head import default_rig
signal.signal(signal.SIGTERM, _sigterm_as_interrupt)  # as `trifuse record` does
# Another thread, as `trifuse record` has (the simulator's, OpenCV's): the kernel may give it
# a signal the main thread blocks, and Python then runs the handler on the main thread.
threading.Thread(target=time.sleep, args=(600,), daemon=True).start()
rig = default_rig()
w, h = rig["thermal_left"].image_size
rng = np.random.default_rng(5)
real_write, armed = sealed_file.SealedMcapFile.write, []
def write(self, data):  # the file's write, called by the MCAP writer (Rust)
    if armed == [True]:
        armed.append("sent")
        os.kill(os.getpid(), signal.SIGTERM)  # comes in the middle of the writer's call
    return real_write(self, data)
sealed_file.SealedMcapFile.write = write
k = 0
try:
    with RecordingWriter(sys.argv[1], rig, chunk_size=64 * 1024, seal_period_s=3600) as rec:
        while k < 1000:
            if k == 3:
                armed.append(True)
            image = (290 + 20 * rng.random((h, w))).astype(np.float32)
            rec.write(Frame("thermal_left", 1_000_000_000 + k * 50_000_000, image))
            k += 1
except KeyboardInterrupt:
    print("interrupted after", k, flush=True)
"""


def _run_child(code: str, path: Path) -> subprocess.CompletedProcess:
    """Run ``code`` in a child Python with ``path`` as its argument; its output as text."""
    return subprocess.run(
        [sys.executable, "-c", code, str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_a_sigterm_during_the_writers_call_waits_for_it(tmp_path) -> None:
    """SIGTERM (Ctrl-C alike) coming while the MCAP writer writes a chunk to the file is
    held back until the write returns: the KeyboardInterrupt comes after it, and the
    recording is finished and named. (It used to come inside the writer's call of the
    file's ``write``, and the writer refused to finish: "attempted another write after a
    write method failed"; seen once in a fresh-clone run of the record SIGTERM test.)"""
    path = tmp_path / "term.mcap"
    done = _run_child(_SIGTERM_CHILD, path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["interrupted", "after", "3"]  # in the 4th frame's write
    with ReplaySource(path, realtime=False) as src:  # which went in whole before it
        assert len(list(src.frames())) == 4 and src.damage is None


def _record_and_die(path: Path) -> int:
    """A child process writes thermal frames to ``path`` and is SIGKILLed mid-recording;
    returns how many frames it had sealed (written to disk as a complete MCAP)."""
    done = _run_child(_RECORD_CHILD, path)
    assert done.returncode == -signal.SIGKILL, done.stderr
    return int(done.stdout.split()[0])


def test_killed_recording_is_kept_readable_and_reported(tmp_path) -> None:
    recordings = tmp_path / "recordings"
    written = _record_and_die(recordings / "20260101-120000.mcap")
    (recordings / ".20260101-120000.mcap.reserved").touch()  # as the console reserves it
    leftovers = sorted(p.suffix for p in recordings.iterdir())
    assert leftovers == [".partial", ".reserved"]  # all hidden: .<name>.mcap.<random>.partial
    # What the kill left is a complete MCAP of complete records, as any reader sees it: the
    # standard mcap reader gets every sealed frame (issue 16: it used to stop at a record of
    # length 2**64 - 1).
    (partial,) = recordings.glob("*.partial")
    with partial.open("rb") as f:
        topics = [ch.topic for _, ch, _ in make_reader(f).iter_messages()]
    assert topics.count("/thermal_left/temperature") == written
    assert partial.read_bytes()[-len(SEAL) :] == SEAL

    # Killed after naming a finished recording, before releasing its name: the name is
    # taken anyway. A reservation without any file may be a recorder starting: kept.
    (recordings / "20251231-235959.mcap").write_bytes(b"finished")
    (recordings / ".20251231-235959.mcap.reserved").touch()
    (recordings / ".20251231-000000.mcap.reserved").touch()
    # A writer that is alive is never touched.
    live = RecordingWriter(recordings / "live.mcap", default_rig())
    recorder = Recorder(recordings)  # what the console does when it starts
    kept = recordings / "20260101-120000.partial.mcap"
    assert recorder.interrupted == [kept]
    assert sorted(p.name for p in recordings.iterdir() if p.name.startswith(".")) == sorted(
        [".20251231-000000.mcap.reserved", live.temp_path.name]
    )  # the dead recording's temporary file and reservation are gone, the live one is there
    assert (recordings / "20251231-235959.mcap").read_bytes() == b"finished"
    state = recorder.state()
    assert state.interrupted == [str(kept)] and "20260101-120000.partial.mcap" in state.error
    live.close()
    assert (recordings / "live.mcap").is_file()

    # It reads up to its last complete chunk, then says why it ends.
    with ReplaySource(kept, realtime=False, on_damage="stop") as src:
        frames = list(src.frames())
        assert len(frames) == written
        assert src.damage is not None and "not finished" in str(src.damage)
    with ReplaySource(kept, realtime=False) as src:  # on_damage="raise": a clear error
        with pytest.raises(Exception, match=r"recording damaged.*not finished"):
            for _ in src.frames():
                pass
    stamps = [f.stamp_ns for f in frames]
    assert stamps == [1_000_000_000 + k * 50_000_000 for k in range(len(frames))]

    # Started again: nothing more to recover, the kept file stays.
    assert recover_interrupted(recordings) == []
    assert kept.is_file()


class _Killed(BaseException):
    """The process dies here (raised by a write cut short, as a SIGKILL cuts it)."""


def test_a_seal_cut_short_by_a_kill_leaves_the_previous_one_readable(tmp_path, monkeypatch) -> None:
    """Linux stops a large ``pwrite`` at a page boundary when a fatal signal is pending, so
    a SIGKILL can leave part of a flush on disk. The sealed file writes the new records
    behind the old seal before touching it: a flush cut in the middle of the records
    leaves the file as the previous seal left it, for every reader."""
    rig = default_rig()
    w, h = rig["thermal_left"].image_size
    rng = np.random.default_rng(6)
    writer = RecordingWriter(tmp_path / "cut.mcap", rig, chunk_size=64 * 1024, seal_period_s=3600)
    for k in range(20):
        image = (290 + 20 * rng.random((h, w))).astype(np.float32)
        writer.write(Frame("thermal_left", 1_000_000_000 + k * 50_000_000, image))
        if k == 9:
            writer.seal()
    real_pwrite = os.pwrite

    def torn_pwrite(fd: int, data: bytes, offset: int) -> int:
        if len(data) <= len(SEAL):
            return real_pwrite(fd, data, offset)
        cut.append(real_pwrite(fd, data[: len(data) // 2 // 4096 * 4096], offset))
        raise _Killed  # (the MCAP writer reports it as an I/O error)

    cut: list[int] = []
    monkeypatch.setattr("trifuse.app.recording.sealed_file.os.pwrite", torn_pwrite)
    with pytest.raises((_Killed, RuntimeError)):
        writer.seal()
    monkeypatch.undo()
    assert cut and cut[0] > 100_000  # a large part of the new records reached the disk
    with writer.temp_path.open("rb") as f:
        topics = [ch.topic for _, ch, _ in make_reader(f).iter_messages()]
    assert topics.count("/thermal_left/temperature") == 10  # the first seal's frames
    with ReplaySource(writer.temp_path, realtime=False, on_damage="stop") as src:
        assert len(list(src.frames())) == 10
        assert "not finished" in str(src.damage)


def test_recording_finished_but_not_named_gets_its_name(tmp_path) -> None:
    rig = default_rig()
    done = tmp_path / "done.mcap"
    with RecordingWriter(done, rig) as w:
        w.write(_flat_frames(rig, 1_000).frames["tof"])
    os.link(done, tmp_path / ".done.mcap.abcd1234.partial")  # killed before the unlink
    os.link(done, tmp_path / ".other.mcap.abcd1234.partial")  # killed before the link
    (tmp_path / ".empty.mcap.abcd1234.partial").touch()  # killed before writing anything
    old = time.time() - 3600
    os.utime(tmp_path / ".empty.mcap.abcd1234.partial", (old, old))
    assert recover_interrupted(tmp_path) == [("other.mcap", tmp_path / "other.mcap")]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["done.mcap", "other.mcap"]
    with ReplaySource(tmp_path / "other.mcap", realtime=False) as src:
        assert len(list(src.frames())) == 1 and src.damage is None


# -- the console, killed at random moments ----------------------------------------------------


class Server:
    """One run of ``trifuse serve`` (its output appended to ``log``)."""

    def __init__(self, workdir: Path, log: Path) -> None:
        wait_for_cache_warmup("calibration")
        self.log = log
        args = ["--workdir", str(workdir), "--scenario", "calibration"]
        try:
            self.console = ConsoleProcess(
                [*args, "--board-poses", str(TEST_BOARD_POSES)],
                env={**os.environ, "TRIFUSE_TOKEN": TOKEN},
                log_path=log,
                timeout_s=180,
            )
        except RuntimeError as e:  # what this run printed is in the message
            pytest.fail(str(e))
        self.proc, self.url = self.console.proc, self.console.url

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def this_run(self) -> str:
        """What this run printed."""
        return self.console.output()

    def call(self, method: str, path: str, timeout: float = 300) -> tuple[int, Any]:
        """(status, JSON) of a REST call; OSError when the server is gone."""
        req = urllib.request.Request(
            self.url + path, method=method, data=b"" if method == "POST" else None
        )
        req.add_header("Authorization", f"token {TOKEN}")
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as e:
            return e.code, e.read().decode(errors="replace")

    def get(self, path: str) -> Any:
        status, body = self.call("GET", path)
        assert status == 200, (path, status, body)
        return body

    def kill(self) -> None:
        self.console.kill()  # SIGKILL: no clean-up of any kind

    def stop(self) -> None:
        self.console.close(timeout_s=60)


class Client(threading.Thread):
    """Captures and saves until the server dies; remembers what was acknowledged (2xx) and
    the files as they were at that moment. ``calibrate``: first ``"save"`` (calibrate, wait
    for it, save the rig: the kill may come from then on) or ``"run"`` (start a calibration,
    go on capturing while it runs: the kill will likely come in the middle of it)."""

    def __init__(
        self, server: Server, workdir: Path, rng: random.Random, calibrate: str | None = None
    ):
        super().__init__(name="crash-client", daemon=True)
        self.server, self.workdir, self.rng, self.calibrate = server, workdir, rng, calibrate
        self.views: dict[str, dict[str, str]] = {}
        self.rigs: dict[str, dict[str, str]] = {}
        self.calibrated = False
        self.going = threading.Event()  # set when the kill may come
        self.error: BaseException | None = None

    def _rig_files(self, body: dict) -> dict[str, str]:
        rigs = self.workdir / "rigs"
        return {
            f: hashlib.sha256((rigs / f).read_bytes()).hexdigest()
            for f in (f"{body['name']}.yaml", f"{body['name']}.report.json")
        }

    def run(self) -> None:
        try:
            self._run()
        except OSError:
            pass  # killed: the connection broke
        except BaseException as exc:  # reported by the test
            self.error = exc
        finally:
            self.going.set()

    def _run(self) -> None:
        s = self.server
        if self.calibrate == "run":
            status, body = s.call("POST", "/api/calibrate")
            assert status == 202, body
        elif self.calibrate == "save":
            status, body = s.call("POST", "/api/calibrate")
            assert status == 202, body
            job = wait_until(
                lambda: (j := s.get("/api/calibrate"))["state"] != "running" and j,
                lambda: s.get("/api/calibrate"),
                600,
                poll_s=0.5,
            )
            assert job["state"] == "done", job
            self.calibrated = True
            self.going.set()
            status, body = s.call("POST", "/api/rigs")
            assert status == 201, body
            self.rigs[body["name"]] = self._rig_files(body)
        wait_until(self._capture, "frames to capture", 600, poll_s=0.2)  # the first take a while
        self.going.set()
        while True:
            if self.rng.random() < 0.65:
                self._capture()
            else:
                status, body = s.call("POST", "/api/thermal/save")
                assert status == 201, body
                self.rigs[body["name"]] = self._rig_files(body)

    def _capture(self) -> bool:
        status, body = self.server.call("POST", "/api/captures")
        if status != 201:
            assert status in (409, 422), (status, body)  # no frames (board) yet
            return False
        self.views[body["name"]] = _file_hashes(self.workdir / "captures" / body["name"])
        return True


def _check_after_restart(
    server: Server,
    workdir: Path,
    views: dict[str, dict[str, str]],
    rigs: dict[str, dict[str, str]],
    seen: dict[str, dict[str, str]],
) -> None:
    """Every acknowledged view and rig version is listed, loads and is as it was; every
    listed one loads; nothing half-written is listed or left as a temporary file.

    ``seen``: the file hashes of every view and version checked after an earlier restart
    (a file that is as it was then needs no decoding again)."""
    captures, rigs_dir = workdir / "captures", workdir / "rigs"
    listed = [v["name"] for v in server.get("/api/captures")["views"]]
    missing = sorted(set(views) - set(listed))
    assert not missing, f"acknowledged views lost: {missing}"
    capture = load_capture(captures)  # the views on disk are the views listed
    assert sorted(v.name for v in capture.views) == sorted(listed)
    for view in capture.views:
        hashes = _file_hashes(view.path)
        assert hashes == views.get(view.name, hashes), f"view {view.name} changed"
        assert hashes == seen.get(view.name, hashes), f"view {view.name} changed"
        if view.name not in seen:
            view.frames()  # every image decodes (CaptureError otherwise)
            seen[view.name] = hashes

    versions = server.get("/api/rigs")
    names = [v["name"] for v in versions]
    missing = sorted(set(rigs) - set(names))
    assert not missing, f"acknowledged rig versions lost: {missing}"
    assert sorted(names) == sorted(p.name[:-5] for p in rigs_dir.glob("rig-*.yaml"))
    for v in versions:
        files = [f"{v['name']}.yaml", f"{v['name']}.report.json"]
        hashes = {f: hashlib.sha256((rigs_dir / f).read_bytes()).hexdigest() for f in files}
        assert hashes == rigs.get(v["name"], hashes), f"rig version {v['name']} changed"
        assert hashes == seen.get(v["name"], hashes), f"rig version {v['name']} changed"
        if v["name"] not in seen:
            rig = server.get(f"/api/rigs/{v['name']}")
            assert set(rig["sensors"]) == set(default_rig().names)
            assert set(load_rig(v["path"]).names) == set(default_rig().names)
            json.loads((rigs_dir / files[1]).read_text())
            seen[v["name"]] = hashes
    for folder in (captures, rigs_dir):
        assert _temporaries(folder) == [], "temporary files of interrupted writes remain"


FIRST_VIEWS = 10
"""Views the console starts with: enough for every sensor's intrinsics (the calibration
needs the board in 8 views a sensor)."""

ROUNDS = 6


@pytest.mark.slow  # a console killed and restarted twice, captures and a recording: about 60 s
def test_console_killed_during_captures_saves_and_recording(simulated_capture, tmp_path) -> None:
    workdir = tmp_path / "work"
    # the same files as rendering that many views of `trifuse simulate calibration --seed 1`
    copy_first_views(simulated_capture, workdir / "captures", FIRST_VIEWS)  # a quick calibration
    servers: list[Server] = []
    try:
        _kill_and_restart(workdir, tmp_path / "console.log", servers)
        servers[-1].stop()
    finally:
        for server in servers:  # after a failure: no console left running
            if server.proc.poll() is None:
                server.kill()


def _kill_and_restart(workdir: Path, log: Path, servers: list[Server]) -> None:
    rng = random.Random(20261122)
    views: dict[str, dict[str, str]] = {}
    rigs: dict[str, dict[str, str]] = {}
    interrupted_views: set[str] = set()
    seen: dict[str, dict[str, str]] = {}

    def start() -> Server:
        servers.append(Server(workdir, log))
        return servers[-1]

    server = start()
    for round_ in range(ROUNDS):
        calibrate = {0: "save", 2: "run"}.get(round_)
        client = Client(server, workdir, random.Random(rng.random()), calibrate)
        client.start()
        assert client.going.wait(900), "the client did not get going"
        time.sleep(rng.uniform(0.0, 1.5) if round_ == 0 else rng.uniform(0.3, 3.0))
        server.kill()
        client.join(120)
        assert not client.is_alive()
        if client.error is not None:
            raise client.error
        if round_ == 0:
            assert client.calibrated, "the calibration round did not calibrate"
        views.update(client.views)
        rigs.update(client.rigs)

        server = start()
        _check_after_restart(server, workdir, views, rigs, seen)
        assert server.get("/api/calibrate")["state"] == "idle"  # a killed run is gone
        staging = {p.name for p in (workdir / "captures").glob(".*.partial")}
        for name in staging - interrupted_views:  # a capture was cut: it is reported
            assert name in server.this_run(), server.this_run()
        interrupted_views |= staging
    print(
        f"{ROUNDS} kills: {len(views)} captures and {len(rigs)} rig versions acknowledged, "
        f"{len(interrupted_views)} captures interrupted"
    )
    assert views, "no capture was acknowledged before a kill"

    # Killed while recording: the partial recording is kept, reported and readable.
    status, body = server.call("POST", "/api/recording/start")
    assert status == 200 and body["active"], body
    name = Path(body["path"]).name
    wait_until(  # a chunk (1 MiB) is complete then
        lambda: server.get("/api/recording")["size_bytes"] >= 1_600_000,
        lambda: server.get("/api/recording"),
        300,
        poll_s=0.2,
    )
    client = Client(server, workdir, random.Random(rng.random()))
    client.start()  # captures and saves go on while it records
    time.sleep(rng.uniform(0.0, 1.0))
    server.kill()
    client.join(120)
    if client.error is not None:
        raise client.error
    views.update(client.views)
    rigs.update(client.rigs)

    server = start()
    _check_after_restart(server, workdir, views, rigs, seen)
    recordings = workdir / "recordings"
    kept = recordings / name.replace(".mcap", ".partial.mcap")
    assert sorted(p.name for p in recordings.iterdir()) == [kept.name]  # nothing hidden left
    assert f"{kept}: the console stopped while writing" in server.this_run()
    state = server.get("/api/recording")
    assert not state["active"] and kept.name in state["error"], state
    with ReplaySource(kept, realtime=False, on_damage="stop") as src:
        assert sum(1 for _ in src.frames()) > 0
        assert src.damage is not None and "not finished" in str(src.damage)

    # The console works on: a capture, a save, a recording.
    status, body = wait_until(
        lambda: (reply := server.call("POST", "/api/captures"))[0] == 201 and reply,
        "a capture",
        120,
        poll_s=0.3,
    )
    assert body["name"] in [v["name"] for v in server.get("/api/captures")["views"]]
    assert server.call("POST", "/api/thermal/save")[0] == 201
    assert server.call("POST", "/api/recording/start")[0] == 200
    wait_until(
        lambda: server.get("/api/recording")["frames_written"] > 0,
        "frames written",
        120,
        poll_s=0.2,
    )
    status, state = server.call("POST", "/api/recording/stop", timeout=180)
    assert status == 200 and not state["active"] and state["error"] is None, state
    with ReplaySource(state["files"][0], realtime=False) as src:
        assert sum(1 for _ in src.frames()) > 0 and src.damage is None


def _record_until(out: Path, size_bytes: int = 1_600_000) -> tuple[subprocess.Popen, Path]:
    """``trifuse record --source sim`` into ``out`` until the file it writes into holds
    ``size_bytes`` (a recording's chunks are 1 MiB: one is complete on disk then); returns
    the process and that file."""
    main = "import sys; from trifuse.app.cli import main; sys.exit(main(sys.argv[1:]))"
    argv = ["record", "--source", "sim", "--out", str(out), "--duration", "60"]
    proc = subprocess.Popen(
        [sys.executable, "-c", main, *argv],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    said, temp = "", None
    for line in proc.stdout:  # its first lines: what it records, then where
        said += line
        if line.startswith("Writing into "):
            temp = Path(line.split()[2].rstrip(";"))
            break
    assert temp is not None and temp.name.startswith(f".{out.name}."), said
    wait_until(
        lambda: temp.stat().st_size >= size_bytes,
        lambda: (temp.stat().st_size, proc.poll()),
        300,
        poll_s=0.2,
    )
    return proc, temp


@pytest.mark.slow  # two `trifuse record` processes of the simulated head: about 6 s idle, 15 busy
def test_record_finishes_on_sigterm_and_leaves_a_readable_file_on_sigkill(tmp_path) -> None:
    out = tmp_path / "term.mcap"
    proc, temp = _record_until(out)
    proc.send_signal(signal.SIGTERM)  # like Ctrl-C: the file is finished and named
    rest = proc.communicate(timeout=120)[0]
    assert "interrupted; what was recorded so far is in" in rest
    assert not temp.exists()
    with ReplaySource(out, realtime=False) as src:  # finished: no damage
        assert len(list(src.frames())) > 0 and src.damage is None

    out = tmp_path / "kill.mcap"
    proc, temp = _record_until(out)
    proc.kill()
    proc.wait(30)
    assert not out.exists()
    with temp.open("rb") as f:  # complete records only: the standard reader reads it
        messages = list(make_reader(f).iter_messages())
    assert len(messages) > 0 and temp.read_bytes()[-len(SEAL) :] == SEAL


def test_a_killed_recording_without_frames_goes_after_a_minute(tmp_path) -> None:
    child = (
        "import os, signal, sys\n"
        "from app.recording.writer import RecordingWriter\n"
        "from app.sources.sim.head import default_rig\n"
        "writer = RecordingWriter(sys.argv[1], default_rig())\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    path = tmp_path / "rec" / "empty.mcap"
    done = subprocess.run([sys.executable, "-c", child, str(path)], cwd=ROOT, timeout=120)
    assert done.returncode == -signal.SIGKILL
    (temp,) = path.parent.glob(".empty.mcap.*.partial")
    with temp.open("rb") as f:  # a valid recording of nothing (header, rig, metadata)
        assert list(make_reader(f).iter_messages()) == []
    assert recover_interrupted(path.parent) == [] and temp.exists()  # a writer starting?
    os.utime(temp, (time.time() - 120, time.time() - 120))
    assert recover_interrupted(path.parent) == [] and not temp.exists()
