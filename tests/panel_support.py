"""The panels on a real Viser server, for their tests: the Calibration panel over a fresh
session of the simulated head (in-process and in a browser), and the Fusion/Thermal/Feeds
panels (:class:`~app.server.panels.display.Panels`) over a stand-in pipeline."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import viser

from tests.scene_support import pipeline_for
from trifuse.app.server.panels.calibration import CalibrationPanel
from trifuse.app.server.panels.display import Panels
from trifuse.app.server.runtime.context import ConsoleBandwidth, ConsoleContext
from trifuse.app.server.runtime.video_presets import StreamSettings
from trifuse.app.sources.frames import FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.workflows.calib_session import CalibrationSession


@contextlib.contextmanager
def panel_on(
    tmp_path: Path, source: object = None, latest_set: FrameSet | None = None
) -> Iterator[tuple[CalibrationPanel, CalibrationSession, viser.ViserServer]]:
    """A Calibration panel on a real Viser server (loopback, free port) over a fresh
    session of the simulated head (9 x 6 board) in ``tmp_path / "work"``; ``source``
    stands for the console's source. Yields (panel, session, server)."""
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    pipeline = pipeline_for()
    pipeline.rig = default_rig()
    pipeline.latest_set = latest_set
    ctx = ConsoleContext(
        server=server,
        source=source,  # type: ignore[arg-type]
        description="test",
        hub=None,  # type: ignore[arg-type]
        pipeline=pipeline,  # type: ignore[arg-type]
        board=CALIBRATION_BOARD,
        board_watch=SimpleNamespace(  # type: ignore[arg-type]
            latest=None, latest_pose=None, pose_listeners=[], enabled=True, on_sighting=None
        ),
    )
    session = CalibrationSession(tmp_path / "work", default_rig(), CALIBRATION_BOARD)
    try:
        yield CalibrationPanel(ctx, session), session, server
    finally:
        session.close()
        server.stop()


def display_panels(
    server: viser.ViserServer,
    pipeline: object,
    board_watch: object,
    balancer: object = None,
    board: object = None,
    registration: object = None,
) -> Panels:
    """:class:`Panels` on ``server`` over a stand-in ``pipeline`` and ``board_watch`` (and
    thermal ``balancer``, ``board``, registration watch), with no rig saving and no
    next-view outline."""
    ctx = SimpleNamespace(
        server=server,
        pipeline=pipeline,
        board=board,
        board_watch=board_watch,
        balancer=balancer,
        save_rig=None,
        stream_settings=StreamSettings(),
        next_outline={},
        bandwidth=ConsoleBandwidth(),
        registration=registration,
    )
    return Panels(ctx)  # type: ignore[arg-type]
