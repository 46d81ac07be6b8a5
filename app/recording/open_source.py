"""Opening the source of frames a command names: a recording (``--replay``), OpenCV cameras
(``--live``), frames pushed to ``/ingest`` (``--push``), or else the simulated head.

``trifuse serve``, ``record``, ``fuse`` and ``balance-thermal`` all open their source here,
so a source refuses the same way whichever command opens it. It lives beside the replay
(``app.recording`` builds on ``app.sources``, not the other way round).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.sources.base import FrameSource
from trifuse.calib.rig import Rig

if TYPE_CHECKING:
    from trifuse.app.sources.sim.drift import SensorDrift
    from trifuse.app.sources.simulated import SimulatedHeadSource
    from trifuse.calib.board import Board

SCENARIOS = ("inspection", "calibration", "survey")
"""What the simulated head can show (:func:`simulated_source`)."""


@dataclass
class OpenedSource:
    """A source, the rig to fuse with, and what to tell the operator."""

    source: FrameSource
    rig: Rig
    description: str
    ground_truth_rig: Rig | None = None


class NeedsRig(ValueError):
    """Live cameras opened without a rig: they do not know their calibration."""


def simulated_source(
    scenario: str,
    board_poses: int = 40,
    hold_s: float = 3.0,
    board: Board | None = None,
    drift: SensorDrift | None = None,
) -> tuple[SimulatedHeadSource, str]:
    """The simulated head as the console shows it: ``(source, description)``.

    Args:
        scenario: ``inspection`` (the panning room, live quality), ``calibration`` (the
            heated board held at ``board_poses`` poses for ``hold_s`` seconds each, looping;
            accurate quality; ``board``: the board it holds, default the simulated
            head's checkerboard) or ``survey`` (the room surveyed for the 3D map: pan and
            tilt, then a 3 m drive, looping every 36 s; live quality, head poses sampled
            at 2 Hz and shown as rendered: the head moves, so a picture cannot stand in
            for another by turning; ``truth_at(stamp).T_world_rig`` is the pose shown).
        drift: one sensor moves during the run (:mod:`app.sources.sim.drift`; inspection
            and survey only: ValueError for the calibration scenario); the source's
            ``rig`` stays the rig as calibrated.
    """
    from trifuse.app.sources.simulated import SimulatedHeadSource

    moving = ""
    if drift is not None:
        if scenario == "calibration":
            raise ValueError("drift: for the inspection and survey scenarios, not calibration")
        turn = ", ".join(f"{x:g}" for x in drift.rotation_deg)
        moving = f"; {drift.sensor} turned by ({turn}) deg from {drift.at_s:g} s on"
    if scenario == "calibration":
        from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, CalibrationScenario

        cal = CalibrationScenario(
            n_poses=board_poses, hold_s=hold_s, board=board or CALIBRATION_BOARD
        )
        src = SimulatedHeadSource(
            cal, realtime=True, render_hz=1.0 / cal.hold_s, loop_s=cal.loop_s, start_ns=None
        )
        return src, (
            f"the simulated head (calibration: {cal.n_poses} board poses, "
            f"{cal.hold_s:g} s each, looping)"
        )
    if scenario == "survey":
        from trifuse.app.sources.sim.survey import SurveyScenario

        survey = SurveyScenario(live=True, drift=drift)
        src = SimulatedHeadSource(survey, realtime=True, start_ns=None, live=False)
        return src, (
            f"the simulated head (survey of the inspection room, {survey.pan_period_s:g} s, "
            f"looping{moving})"
        )
    if scenario == "inspection":
        return SimulatedHeadSource(realtime=True, start_ns=None, drift=drift), (
            f"the simulated head (inspection room{moving})"
        )
    raise ValueError(f"scenario: expected one of {', '.join(SCENARIOS)}, got {scenario!r}")


def open_source(
    replay: str | Path | None = None,
    live: str | Path | None = None,
    push: bool = False,
    rig: Rig | None = None,
    *,
    realtime: bool = True,
    loop: bool = False,
    keep_time: bool = False,
    scenario: str = "inspection",
    board_poses: int = 40,
    hold_s: float = 3.0,
    board: Board | None = None,
    live_flag: str = "--live",
    drift: SensorDrift | None = None,
    ros2: str | Path | None = None,
    ros2_domain: int | None = None,
    ros2_reliable: bool = False,
    ros2_max_bytes: int | None = None,
) -> OpenedSource:
    """The source named by ``--replay FILE``, ``--live CONFIG`` or ``--push`` (the first
    given), else the simulated head's ``scenario``; with the rig to use (``rig`` if given,
    else the recording's or the simulated head's).

    Args:
        replay: a recording (.mcap), replayed at its own pace (``realtime``) or as fast as
            it is read, from the start again at its end when ``loop``; with ``keep_time``
            (the console) dropping the frames its consumer has no time for rather than
            slowing down (:mod:`app.recording.player`).
        live: a live camera configuration (docs/FORMATS.md); needs ``rig``.
        push: frames pushed by an on-robot driver at ``/ingest`` (rig default: the
            simulated head's).
        rig: the rig given on the command line, or None.
        scenario, board_poses, hold_s, board, drift: the simulated head's, see
            :func:`simulated_source` (``drift`` with another source: ValueError).
        live_flag: how the command names ``live`` in the error when ``rig`` is missing.
        ros2: a topic map: the robot's live ROS 2 topics over DDS (app/recording/ros2_live.py;
            needs ``rig``), in domain ``ros2_domain`` (None: ``ROS_DOMAIN_ID``, else 0),
            reliable QoS with ``ros2_reliable``, messages over ``ros2_max_bytes`` refused
            (None: the source's default).

    Raises:
        ValueError: the recording holds no rig and none is given (the replay is closed
            again); :class:`NeedsRig` for ``live`` without ``rig``; the sources' own errors
            (a missing or damaged file, a camera that does not open).
    """
    if drift is not None and (replay or live or push or ros2):
        raise ValueError("drift: for the simulated head only")
    if replay:
        from trifuse.app.recording.reader import ReplaySource

        src = ReplaySource(Path(replay), loop=loop, realtime=realtime, keep_time=keep_time)
        rig = rig or src.rig
        if rig is None:
            src.close()
            raise ValueError(f"{replay}: the recording holds no rig; give one with --rig")
        src.expect(rig)  # frames of another size are skipped (counted), never delivered
        return OpenedSource(src, rig, f"replay of {replay}" + (" (looping)" if loop else ""))
    if live:
        from trifuse.app.sources.camera import CameraSource

        if rig is None:
            raise NeedsRig(
                f"{live_flag} needs --rig RIG.yaml (cameras do not know their calibration)"
            )
        return OpenedSource(CameraSource(Path(live), rig=rig), rig, f"live cameras of {live}")
    if ros2:
        from trifuse.app.recording.ros2_live import Ros2LiveSource
        from trifuse.app.recording.topicmap import load_topic_map

        if rig is None:
            raise NeedsRig("--ros2 needs --rig RIG.yaml (topics do not carry the calibration)")
        tmap = load_topic_map(ros2)
        domain = ros2_domain if ros2_domain is not None else int(os.environ.get("ROS_DOMAIN_ID", 0))
        limit = {} if ros2_max_bytes is None else {"max_message_bytes": ros2_max_bytes}
        src = Ros2LiveSource(tmap, rig, domain_id=domain, reliable=ros2_reliable, **limit)
        return OpenedSource(src, rig, f"ROS 2 topics of {ros2} (DDS domain {domain})")
    if push:
        from trifuse.app.sources.push.source import PushSource
        from trifuse.app.sources.sim.head import default_rig

        rig = rig or default_rig()
        return OpenedSource(PushSource(rig), rig, "frames pushed to /ingest")
    src, what = simulated_source(scenario, board_poses, hold_s, board, drift)
    return OpenedSource(src, rig or src.rig, what, ground_truth_rig=src.rig)
