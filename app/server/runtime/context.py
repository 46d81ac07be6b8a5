"""What every part of the console is built from: one :class:`ConsoleContext`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, cast, get_args

import numpy as np
import viser

from trifuse.app.server.runtime.board_watch import BoardWatch
from trifuse.app.server.runtime.demand import ConsoleDemand
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.registration_watch import RegistrationWatch
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.runtime.thermal_balance import ThermalBalancer
from trifuse.app.server.runtime.video_presets import StreamSettings
from trifuse.app.sources.base import FrameSource
from trifuse.app.workflows.calib_session import RigVersion
from trifuse.calib.board import Board
from trifuse.calib.rig import Rig

BandwidthMode = Literal["full", "low"]
"""The 3D console's bandwidth modes: ``full`` (every point, images at 2 Hz) and ``low``
(a decimated cloud at 2 Hz, small images at 1 Hz: the panels' profiles say exactly); the
REST model takes it as its type, the GUI's dropdown its values (:data:`BANDWIDTH_MODES`)."""

BANDWIDTH_MODES: tuple[BandwidthMode, ...] = get_args(BandwidthMode)


class ConsoleBandwidth:
    """What ``/console/`` may send: its bandwidth mode, console-wide (``ctx.bandwidth``; the
    "3D scene" folder's Bandwidth dropdown, ``/api/console/settings``, ``trifuse serve
    --console-bandwidth``). Setting a mode not in :data:`BANDWIDTH_MODES` raises
    ValueError. Thread-safe (a plain attribute swap)."""

    def __init__(self, mode: str = "full") -> None:
        self._mode: BandwidthMode = "full"
        self.mode = mode

    @property
    def mode(self) -> BandwidthMode:
        return self._mode

    @mode.setter
    def mode(self, value: str) -> None:
        if value not in BANDWIDTH_MODES:
            raise ValueError(f"console bandwidth {value!r}: expected one of {BANDWIDTH_MODES}")
        self._mode = cast(BandwidthMode, value)


@dataclass
class ConsoleContext:
    """The running console's shared objects.

    Attributes:
        server: the Viser server (3D scene and GUI panels).
        source: the frame source being shown.
        description: one line saying what the source is.
        hub: the fused stereo stream's newest frame.
        pipeline: the live fusion loop; ``pipeline.rig`` is the rig in use.
        board: the calibration checkerboard.
        board_watch: live board detection on the newest frame set.
        ground_truth_rig: the simulated head's exact rig (None for real sources).
        rig_choices: rigs an operator may display, by label (``"in use"``, ``"ground
            truth"``, saved versions ...); the calibration session extends it.
        balancer: the thermal balance estimation (None: not running).
        save_rig: writes a rig (and its report) as the session's next rig version.
        demand: who wants the console's background work now (fused pictures, the board
            search, the GUI's updates): the parts hold or touch it (demand.py).
        bandwidth: what ``/console/`` may send (``full`` or ``low``); the 3D scene and the
            Feeds read it each update.
        registration: each eye's registration sigma estimated in the background (the
            Fusion panel shows it), or None.
        drift: the calibration's drift check on the live frames (the Calibration panel's
            health line, alert and Refine rig), or None.
        next_outline: where the board should appear in the next view: sensor -> (4, 2)
            full-image pixels of its checkered area's corners
            (:class:`calib.next_pose.NextPose` ``outline_px``); empty when nothing is
            suggested. The Calibration panel's next-pose advisor replaces it whole; the
            Feeds and the 3D scene's live images draw it.
    """

    server: viser.ViserServer
    source: FrameSource
    description: str
    hub: FrameHub
    pipeline: FusionPipeline
    board: Board
    board_watch: BoardWatch
    ground_truth_rig: Rig | None = None
    rig_choices: Callable[[], dict[str, Rig]] = field(default=lambda: {})
    balancer: ThermalBalancer | None = None
    save_rig: Callable[[Rig, dict], RigVersion] | None = None
    demand: ConsoleDemand = field(default_factory=ConsoleDemand)
    bandwidth: ConsoleBandwidth = field(default_factory=ConsoleBandwidth)
    next_outline: dict[str, np.ndarray] = field(default_factory=dict)
    registration: RegistrationWatch | None = None
    drift: DriftWatch | None = None

    @property
    def stream_settings(self) -> StreamSettings:
        """The video stream's console-wide settings (``preset``: of new viewers), the
        hub's: ``/api/stream/settings`` and the GUI share them."""
        return self.hub.stream_settings

    def use_rig(self, rig: Rig) -> None:
        """Fuse with, detect with and show ``rig`` from now on (ValueError: wrong sensors)."""
        self.pipeline.set_rig(rig)
        self.board_watch.rig = rig

    def rigs(self) -> dict[str, Rig]:
        """``{"in use": ..., "ground truth": ... (simulated head), **rig_choices()}``."""
        out = {"in use": self.pipeline.rig}
        if self.ground_truth_rig is not None:
            out["ground truth"] = self.ground_truth_rig
        out.update(self.rig_choices())
        return out
