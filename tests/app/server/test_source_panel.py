"""The Source panel (Viser) and what it drives: the source tap, the background recorder
(never blocking the pipeline, dropping and counting when the disk is slow, a new file when
replay time goes back) and the per-sensor rate meter."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import viser
from viser import GuiEvent

from tests.support import (
    WAIT_S,
    FakeClock,
    ListSource,
    small_rig,
    synth_frame,
    synth_frames,
    wait_until,
    write_recording,
)
from trifuse.app.errors import ControlError
from trifuse.app.recording import RecordingWriter, ReplaySource
from trifuse.app.recording.recorder import Recorder
from trifuse.app.server.panels import source as source_panel
from trifuse.app.server.panels.source import SourcePanel, human_bytes
from trifuse.app.server.runtime.board_watch import BoardWatch
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.rates import RateWindow
from trifuse.app.server.runtime.source_control import SourceControl, SourceState
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame
from trifuse.calib.board import Board
from trifuse.calib.rig import Rig


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


@pytest.fixture(scope="module")
def recording(tmp_path_factory, rig) -> Path:
    path = tmp_path_factory.mktemp("panel") / "short.mcap"
    return write_recording(path, rig, synth_frames(rig, 3.0, seed=7))


def _server() -> viser.ViserServer:
    with contextlib.redirect_stdout(io.StringIO()):
        return viser.ViserServer(host="127.0.0.1", port=0, verbose=False)


def _ctx(server: viser.ViserServer, pipeline: FusionPipeline, rig: Rig) -> ConsoleContext:
    board = Board(9, 6, 0.04)
    return ConsoleContext(
        server=server,
        source=pipeline.source,
        description="test",
        hub=pipeline.hub,
        pipeline=pipeline,
        board=board,
        board_watch=BoardWatch(lambda: None, rig, board),
    )


def click(button) -> None:
    """What a browser's click does to a button: its callbacks with a client."""
    for cb in button._impl.update_cb:
        cb(GuiEvent(client=SimpleNamespace(), client_id=1, target=button))


def drag(slider, value: float) -> None:
    """What a browser's drag does to a slider: a new value, callbacks with a client."""
    slider._impl.value = float(value)
    for cb in slider._impl.update_cb:
        cb(GuiEvent(client=SimpleNamespace(), client_id=1, target=slider))


@pytest.fixture()
def clock() -> FakeClock:
    """The Source panel's clock (how long a slider the operator moved is left alone)."""
    return FakeClock(100.0)


@pytest.fixture()
def replay_panel(
    recording, rig, tmp_path, clock
) -> Iterator[tuple[SourcePanel, ReplaySource, Path]]:
    replay = ReplaySource(recording, loop=True, realtime=True)
    hub = FrameHub()
    pipeline = FusionPipeline(SourceTap(replay), rig, hub).start()
    control = SourceControl(pipeline, hub, f"replay of {recording.name}", tmp_path / "work")
    server = _server()
    panel = SourcePanel(_ctx(server, pipeline, rig), control, clock=clock)  # ticks by hand
    try:
        yield panel, replay, tmp_path / "work"
    finally:
        control.stop()
        pipeline.stop()
        server.stop()


# -- the panel ------------------------------------------------------------------------------


def test_panel_shows_the_replay_and_its_rates(replay_panel) -> None:
    panel, _, _ = replay_panel
    assert panel.what.content == "**replay**: replay of short.mcap"
    wait_until(lambda: panel.control.rates_hz().get("ccd_left", 0) > 0, "a rate")
    panel.tick()
    text = panel.rates.content
    assert "| ccd_left |" in text and "| tof |" in text and "Fused:" in text
    assert panel.play.label == "Pause" and panel.record.label == "Record"
    assert "Not recording" in panel.recording.content


def test_panel_says_what_a_replay_dropped_to_keep_real_time(replay_panel, monkeypatch) -> None:
    """A replay that keeps real time (``keep_time``) drops what the console has no time for:
    the rates table gets a column with the frames dropped per sensor."""
    panel, _, _ = replay_panel
    assert panel.control.source_state().dropped == {}  # nothing dropped: no column
    panel.tick()
    assert "dropped" not in panel.rates.content
    state = panel.control.source_state

    def dropping() -> SourceState:
        return dataclasses.replace(state(), dropped={"ccd_left": 7, "tof": 2})

    monkeypatch.setattr(panel.control, "source_state", dropping)
    wait_until(lambda: panel.control.rates_hz().get("ccd_left", 0) > 0, "a rate")
    panel.tick()
    text = panel.rates.content
    assert "| sensor | Hz | dropped to keep real time |" in text
    assert re.search(r"\| ccd_left \| [0-9.]+ \| 7 \|", text)
    assert re.search(r"\| tof \| [0-9.]+ \| 2 \|", text)
    assert re.search(r"\| thermal_left \| [0-9.]+ \| 0 \|", text)


def test_play_pause_and_the_position_slider(replay_panel) -> None:
    panel, replay, _ = replay_panel
    wait_until(lambda: replay.position_ns - replay.start_ns > 300_000_000)
    click(panel.play)
    assert replay.paused and panel.play.label == "Play"
    panel.tick()
    held = panel.position.value
    assert held == pytest.approx((replay.position_ns - replay.start_ns) / 1e9, abs=0.01)
    drag(panel.position, 2.5)  # the operator seeks
    assert (replay.position_ns - replay.start_ns) / 1e9 == pytest.approx(2.5)
    panel.tick()
    assert panel.position.value == 2.5
    click(panel.play)
    assert not replay.paused and panel.play.label == "Pause"
    drag(panel.rate, 2.0)
    assert replay.rate == 2.0


def test_the_slider_leaves_the_operators_drag_alone(replay_panel, clock, monkeypatch) -> None:
    panel, replay, _ = replay_panel
    seeks: list[float] = []
    monkeypatch.setattr(panel.control, "seek", seeks.append)  # the replay does not move
    wait_until(lambda: replay.position_ns - replay.start_ns > 100_000_000)
    drag(panel.position, 2.9)
    assert seeks == [2.9]
    panel.tick()
    assert panel.position.value == 2.9  # mid-drag: not pulled back to where the replay is
    clock.advance(source_panel.HOLD_S)  # the hold has passed
    panel.tick()
    assert panel.position.value < 2.9  # follows the replay again


def test_record_and_stop_from_the_panel(replay_panel) -> None:
    panel, _, workdir = replay_panel
    click(panel.record)
    assert panel.record.label == "Stop recording"
    wait_until(lambda: panel.control.recording_state().frames_written > 30, "31 frames")
    panel.tick()
    assert "Recording" in panel.recording.content and "recordings/" in panel.recording.content
    click(panel.record)
    assert panel.record.label == "Record"
    files = sorted((workdir / "recordings").glob("*.mcap"))
    assert files and "Saved" in panel.recording.content
    assert files[0].name in panel.recording.content
    with ReplaySource(files[0], realtime=False) as src:
        assert sum(1 for _ in src.frames()) > 30


def test_panel_of_a_live_source_has_no_replay_controls(rig) -> None:
    hub = FrameHub()
    pipeline = FusionPipeline(SourceTap(ListSource(sensors=["tof"])), rig, hub)
    control = SourceControl(pipeline, hub, "cameras")  # no work directory
    server = _server()
    try:
        panel = SourcePanel(_ctx(server, pipeline, rig), control)
        assert panel.play is None and panel.position is None and panel.rate is None
        assert panel.record.disabled and "unavailable" in panel.recording.content
        with pytest.raises(ControlError, match="not a replay"):
            control.pause()
    finally:
        server.stop()


def test_human_bytes() -> None:
    assert human_bytes(812_000) == "812 kB"
    assert human_bytes(12_340_000) == "12.3 MB"
    assert human_bytes(1_200_000_000) == "1.20 GB"
    assert source_panel.HOLD_S > 0.5


# -- the recorder ---------------------------------------------------------------------------


def test_a_stuck_disk_drops_frames_and_never_blocks(rig, tmp_path, monkeypatch) -> None:
    """The pipeline's offers return while the writer is stuck on the disk: the queue fills
    to ``max_queue`` and every further frame is dropped and counted, none waited for."""
    real_write = RecordingWriter.write
    writing, disk_free = threading.Event(), threading.Event()
    released_in_time: list[bool] = []

    def stuck_write(self, frame):
        writing.set()
        if not released_in_time:  # the first frame waits until every offer has returned
            released_in_time.append(disk_free.wait(WAIT_S))
        return real_write(self, frame)

    monkeypatch.setattr(RecordingWriter, "write", stuck_write)
    recorder = Recorder(tmp_path / "rec", max_queue=4)
    recorder.start(rig)
    rng = np.random.default_rng(1)
    frames = [synth_frame(rig, "tof", 1_000_000_000 + k * 10_000_000, rng) for k in range(100)]
    recorder.offer(frames[0])
    wait_until(writing.is_set, "the writer to take the first frame")
    for f in frames[1:]:  # an offer that waited for the disk would never return here
        recorder.offer(f)
    during = recorder.state()
    disk_free.set()
    state = recorder.stop()
    assert released_in_time == [True]  # the offers returned before the disk moved
    assert during.frames_dropped == state.frames_dropped == len(frames) - 1 - 4
    assert state.frames_written == 1 + 4  # the frame on the disk, then the queue
    (path,) = state.files
    with ReplaySource(path, realtime=False) as src:
        got = [f.stamp_ns for f in src.frames()]
    assert got == [f.stamp_ns for f in frames[:5]]


def test_time_going_back_starts_a_new_file(rig, tmp_path) -> None:
    recorder = Recorder(tmp_path / "rec")
    recorder.start(rig)
    rng = np.random.default_rng(2)
    stamps = [1_000_000_000 + k * 20_000_000 for k in range(10)]
    for s in stamps + stamps[:5]:  # a replay that looped
        recorder.offer(synth_frame(rig, "thermal_left", s, rng))
    state = recorder.stop()
    assert len(state.files) == 2 and state.frames_written == 15 and state.frames_dropped == 0
    counts = []
    for f in state.files:
        with ReplaySource(f, realtime=False) as src:
            counts.append(len(list(src.frames())))
    assert counts == [10, 5]
    assert state.files[0] != state.files[1]  # a new name (-2 within the same second)
    left = sorted(p.name for p in (tmp_path / "rec").iterdir())
    assert left == sorted(Path(f).name for f in state.files)  # no partial or reservation file


def test_frames_outside_the_rig_are_skipped_and_counted(rig, tmp_path) -> None:
    recorder = Recorder(tmp_path / "rec")
    recorder.start(rig)
    img = np.zeros((10, 10), np.float32)
    recorder.offer(Frame("somebody_else", 1, img))
    recorder.offer(Frame("thermal_left", 2, img))  # wrong size
    recorder.offer(synth_frame(rig, "thermal_left", 3, np.random.default_rng(0)))
    state = recorder.stop()
    assert state.frames_rejected == 2 and state.frames_written == 1
    assert "thermal_left" in state.error and "shape" in state.error


def test_nothing_recorded_leaves_no_file(rig, tmp_path) -> None:
    recorder = Recorder(tmp_path / "rec")
    recorder.start(rig)
    state = recorder.stop()
    assert state.files == [] and list((tmp_path / "rec").iterdir()) == []
    with pytest.raises(ControlError, match="not recording"):
        recorder.stop()


def test_rate_meter() -> None:
    meter = RateWindow(window_s=2.0)
    for k in range(90):  # 30 Hz for 3 s
        meter.tick("ccd_left", 100.0 + k / 30)
    for k in range(15):  # 15 Hz for 1 s, then silence
        meter.tick("tof", 100.0 + k / 15)
    rates = meter.rates_hz(["ccd_left", "tof", "thermal_left"], now_s=103.0)
    assert rates["ccd_left"] == pytest.approx(30.0, abs=1.0)
    assert rates["tof"] == 0.0 and rates["thermal_left"] == 0.0


def test_the_head_pose_is_recorded_beside_each_tof_frame(rig, tmp_path) -> None:
    """A source that knows the head's pose (the simulated head, a replay with poses):
    each TOF frame's pose goes to /tf as world -> rig, and the recording gives it back."""
    from trifuse.app.recording.poses import read_poses
    from trifuse.calib.transforms import make_T, rotation_from_euler_deg

    def pose(stamp_ns: int) -> np.ndarray:
        t = stamp_ns * 1e-9
        return make_T(rotation_from_euler_deg(0.0, 10.0 * t, 0.0), (0.1 * t, 0.0, 0.0))

    recorder = Recorder(tmp_path / "rec")
    recorder.head_pose = pose
    recorder.start(rig)
    rng = np.random.default_rng(3)
    stamps = [1_000_000_000 + k * 66_000_000 for k in range(6)]
    for s in stamps:
        recorder.offer(synth_frame(rig, "tof", s, rng))
        recorder.offer(synth_frame(rig, "thermal_left", s + 1000, rng))
    (path,) = recorder.stop().files
    poses = read_poses(path)
    assert poses is not None
    assert list(poses.stamps_ns) == stamps  # one per TOF frame, none for the others
    for s, T in zip(stamps, poses.T_world_rig, strict=True):
        np.testing.assert_allclose(T, pose(s), atol=1e-9)
