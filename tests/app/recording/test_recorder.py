"""One recorder for the console and ``trifuse record`` (app/recording/recorder.py), and the
one rate window every rate the console shows is counted with (app/server/runtime/rates.py).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from tests.support import run_cli, small_rig, synth_frame, synth_frames, write_recording
from trifuse.app.recording import RecordingError, ReplaySource
from trifuse.app.recording.recorder import Recorder
from trifuse.app.recording.recording import Recording
from trifuse.app.server.runtime.rates import RateWindow
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


def messages(path: Path) -> list[tuple[str, int, str]]:
    """(topic, log time ns, SHA-1 of the payload) of every message, in the file's order."""
    with path.open("rb") as f:
        return [
            (channel.topic, msg.log_time, hashlib.sha1(msg.data).hexdigest())
            for _schema, channel, msg in make_reader(f).iter_messages(log_time_order=False)
        ]


def test_the_console_and_record_write_the_same_recording(rig, tmp_path, capsys) -> None:
    """The same frames through the console's recorder (its queue and writing thread) and
    through ``trifuse record --source replay:`` make the same messages, byte for byte."""
    source = write_recording(tmp_path / "in.mcap", rig, synth_frames(rig, 0.4, seed=4))
    out = tmp_path / "cli.mcap"
    code, _out, err = run_cli(["record", "--source", f"replay:{source}", "--out", str(out)], capsys)
    assert code == 0, err
    recorder = Recorder(tmp_path / "console", max_queue=10_000)
    recorder.start(rig)
    with ReplaySource(source, realtime=False) as src:
        for frame in src.frames():
            recorder.offer(frame)
    state = recorder.stop()
    assert state.frames_dropped == 0 and state.error is None
    (console,) = state.files
    assert messages(Path(console)) == messages(out) != []


def test_a_recording_to_a_path_keeps_one_file_when_time_goes_back(rig, tmp_path) -> None:
    """``trifuse record`` writes exactly --out (also when a sensor's time goes back, and
    without frames); the console's recordings begin a new file then, and keep none empty."""
    rng = np.random.default_rng(1)
    back = [synth_frame(rig, "tof", s, rng) for s in (3_000_000_000, 4_000_000_000, 1_000_000_000)]
    with Recording(rig, path=tmp_path / "one.mcap") as rec:
        for f in back:
            rec.write(f)
    assert rec.files == [tmp_path / "one.mcap"] and rec.frames_written == 3
    with Recording(rig, directory=tmp_path / "dir") as rec:
        for f in back:
            rec.write(f)
    assert len(rec.files) == 2 and rec.frames_written == 3
    with Recording(rig, path=tmp_path / "empty.mcap"):
        pass
    assert (tmp_path / "empty.mcap").is_file()
    with Recording(rig, directory=tmp_path / "none") as rec:
        pass
    assert rec.files == [] and list((tmp_path / "none").iterdir()) == []
    with Recording(rig, path=tmp_path / "bad.mcap") as rec, pytest.raises(RecordingError):
        rec.write(Frame("nope", 1, np.zeros((4, 4), np.float32)))  # not in the rig


def test_rate_window_counts_per_key_over_the_window() -> None:
    clock = [100.0]
    w = RateWindow(2.0, clock=lambda: clock[0])
    ramp = RateWindow(2.0, from_first=False)
    for k in range(10):  # 10 Hz for 1 s
        w.tick("a", 100.0 + k / 10)
        ramp.tick("a", 100.0 + k / 10)
    clock[0] = 100.9
    assert w.rate("a") == pytest.approx(10 / 0.9)  # young: over the time since the first
    assert ramp.rate("a", 100.9) == pytest.approx(10 / 2.0)  # always over the window
    w.tick("b", 100.5)
    assert w.rate("b", 100.9, since="a") == pytest.approx(1 / 0.9)
    assert w.rates_hz(["c"], now_s=103.5) == {"c": 0.0, "a": 0.0, "b": 0.0}  # all gone
    with pytest.raises(ValueError, match="window_s"):
        RateWindow(0.0)
