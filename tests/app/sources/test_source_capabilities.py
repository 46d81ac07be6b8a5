"""What sources declare they can do (app/sources/capabilities.py), and that the console
treats a source lacking a capability as before: no replay controls, no head pose, no
device states, no notes."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import viser

from tests.support import ListSource, small_rig, synth_frames, write_recording
from trifuse.app.recording import ReplaySource
from trifuse.app.server.panels.source import SourcePanel
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.camera import DeviceStatus
from trifuse.app.sources.capabilities import (
    DeviceStatusSource,
    NotedSource,
    PosedSource,
    ReplayControls,
    device_states,
    head_pose_of,
    kind_of,
    notes_of,
    replay_controls,
)
from trifuse.app.sources.push.source import PushSource
from trifuse.app.sources.simulated import SimulatedHeadSource
from trifuse.calib.board import Board


def test_a_plain_source_has_no_capabilities() -> None:
    src = ListSource(sensors=["tof"])
    assert kind_of(src) == "live"
    assert head_pose_of(src) is None and replay_controls(src) is None
    assert device_states(src) == {} and notes_of(src) == []
    for protocol in (PosedSource, ReplayControls, DeviceStatusSource, NotedSource):
        assert not isinstance(src, protocol)


def test_sources_declare_their_kind() -> None:
    assert kind_of(PushSource(small_rig())) == "push"
    assert SimulatedHeadSource.source_kind == "simulated"
    assert issubclass(SimulatedHeadSource, PosedSource)  # its ground truth


def test_a_replay_is_posed_controllable_and_noted(tmp_path: Path) -> None:
    rig = small_rig()
    path = write_recording(tmp_path / "r.mcap", rig, synth_frames(rig, 0.5, seed=1))
    with ReplaySource(path, realtime=False) as src:
        assert kind_of(src) == "replay" and replay_controls(src) is src
        assert isinstance(src, ReplayControls) and isinstance(src, NotedSource)
        pose = head_pose_of(src)
        assert pose is not None and pose(src.start_ns) is None  # no world -> rig recorded
        assert notes_of(src) == []


class _Cameras(ListSource):
    """A live source reading devices; ``broken``: asking for their state fails."""

    broken = False

    def status(self) -> dict[str, DeviceStatus]:
        if self.broken:
            raise RuntimeError("a device thread is failing")
        return {"tof": DeviceStatus("tof", 0, "failed", "no such device")}


def test_device_states_of_cameras_and_of_a_failing_status() -> None:
    cams = _Cameras(sensors=["tof"])
    assert isinstance(cams, DeviceStatusSource)
    assert device_states(cams) == {"tof": ("failed", "no such device")}
    cams.broken = True
    assert device_states(cams) == {}


def _rates_text(source, rig) -> str:
    """The Source panel's rates text after one tick, over ``source``."""
    hub = FrameHub()
    pipeline = FusionPipeline(SourceTap(source), rig, hub)
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        ctx = ConsoleContext(
            server=server,
            source=pipeline.source,
            description="test",
            hub=hub,
            pipeline=pipeline,
            board=Board(9, 6, 0.04),
            board_watch=None,
        )
        panel = SourcePanel(ctx, SourceControl(pipeline, hub, "test"))
        panel.tick()
        return panel.rates.content
    finally:
        server.stop()


def test_the_source_panel_shows_notes_only_of_a_noted_source(tmp_path: Path) -> None:
    rig = small_rig()
    assert "Notes:" not in _rates_text(ListSource(sensors=rig.names), rig)
    path = write_recording(tmp_path / "r.mcap", rig, synth_frames(rig, 0.5, seed=2))
    replay = ReplaySource(path, realtime=False)
    replay.notes.append("a damaged summary <b>")
    text = _rates_text(replay, rig)
    replay.close()
    assert "Notes: a damaged summary" in text and "<b>" not in text  # escaped


def test_a_head_pose_is_a_bound_method_of_the_source() -> None:
    class Posed(ListSource):
        def head_pose(self, stamp_ns: int) -> np.ndarray | None:
            return np.eye(4) if stamp_ns else None

    src = Posed(sensors=["tof"])
    pose = head_pose_of(src)
    assert pose is not None and pose(0) is None and (pose(1) == np.eye(4)).all()
