"""Live checkerboard detection on the console's newest frame set.

:class:`BoardWatch` detects the board in every sensor of the pipeline's newest frame set
about once a second (two threads: OpenCV releases the GIL), and keeps the result as a
:class:`BoardSighting`: the frames it looked at, each sensor's corners (or why not), the
board's pose in the rig frame and whether the board has held still since the previous
sighting. The Feeds panel draws the corners, the 3D scene shows the pose and the
calibration session's auto-capture takes steady, novel sightings.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from app.server.periodic import Periodic
from app.sources.frames import FrameSet
from calib.board import Board
from calib.detect import Detection, detect_board
from calib.rig import Rig

STEADY_PX = 2.0
"""A board is steady when no corner moved more than this many pixels (in any sensor that
saw it both times) since the previous sighting."""

POSE_PREFERENCE = ("color", "thermal", "tof")
"""Modalities in the order their detection is trusted for the board's pose."""


@dataclass(frozen=True, eq=False)
class BoardSighting:
    """One detection pass over a frame set.

    Attributes:
        frames: the frame set that was searched (what a capture of this sighting writes).
        detections: sensor -> :class:`~calib.detect.Detection` (corners (N, 2) px or a reason).
        T_rig_board: (4, 4) board pose in the rig frame, metres (from the most trusted
            sensor that found it, with the rig's intrinsics and pose), or None.
        pose_sensor: the sensor the pose comes from, or None.
        steady: found in at least one sensor, and no sensor that found it in the previous
            sighting too saw a corner move more than :data:`STEADY_PX`.
    """

    frames: FrameSet
    detections: dict[str, Detection]
    T_rig_board: np.ndarray | None
    pose_sensor: str | None
    steady: bool

    @property
    def found(self) -> list[str]:
        """Sensors whose image shows the board."""
        return [s for s, d in self.detections.items() if d.found]


def board_pose(rig: Rig, sensor: str, corners: np.ndarray, board: Board) -> np.ndarray | None:
    """(4, 4) ``T_rig_board`` from one sensor's corners (PnP with the rig's intrinsics)."""
    intr = rig[sensor].intrinsics
    ok, rvec, tvec = cv2.solvePnP(
        board.object_points().astype(np.float64),
        corners.astype(np.float64).reshape(-1, 1, 2),
        intr.K,
        np.asarray(intr.distortion, dtype=np.float64),
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return rig[sensor].T_rig_sensor @ T


def sighting(
    frames: FrameSet,
    rig: Rig,
    board: Board,
    previous: BoardSighting | None = None,
    pool: ThreadPoolExecutor | None = None,
) -> BoardSighting:
    """Detect the board in every frame of ``frames`` (sensors of ``rig`` only); an image
    that is the very object the previous sighting searched (a source repeating a frame)
    keeps its detection."""
    names = [s for s in frames.frames if s in rig]

    def detect(name: str) -> Detection:
        frame = frames.frames[name]
        if previous is not None and name in previous.detections:
            seen = previous.frames.frames.get(name)
            if seen is not None and seen.image is frame.image:  # the very same image again
                return previous.detections[name]
        try:
            return detect_board(frame.image, board, rig[name].modality)
        except ValueError as exc:  # a malformed frame: say so, keep watching
            return Detection(None, f"cannot search this image: {exc}", None)

    found = list(pool.map(detect, names)) if pool is not None else [detect(n) for n in names]
    detections = dict(zip(names, found, strict=True))
    trusted = [
        name
        for modality in POSE_PREFERENCE
        for name, det in detections.items()
        if det.found and rig[name].modality == modality
    ]
    pose_sensor = trusted[0] if trusted else None
    pose = board_pose(rig, pose_sensor, detections[pose_sensor].corners, board) if trusted else None
    moved = [
        float(np.max(np.linalg.norm(det.corners - previous.detections[name].corners, axis=1)))
        for name, det in detections.items()
        if det.found
        and previous is not None
        and name in previous.detections
        and previous.detections[name].found
    ]
    steady = bool(moved) and max(moved) <= STEADY_PX
    return BoardSighting(frames, detections, pose, pose_sensor, steady)


class BoardWatch(Periodic):
    """Detects the board in the newest frame set of ``latest()`` at ``rate_hz``.

    Args:
        latest: returns the newest frame set (or None before the first).
        rig: sensor modalities, intrinsics and poses.
        board: the checkerboard to look for.
        rate_hz: detection passes per second (one pass over five sensors takes about
            0.6 s of CPU on the reference machine).
        on_sighting: called (in the watch's thread) with every new sighting.
        idle_period_s: while the last pass found no board anywhere, passes are this far
            apart instead (a search that fails costs the most: about 1.2 s of CPU for a
            1280 x 960 colour image against 0.1 s when the board is there).

    ``enabled`` may be set False to pause detection (nothing else changes).
    """

    def __init__(
        self,
        latest: Callable[[], FrameSet | None],
        rig: Rig,
        board: Board,
        rate_hz: float = 1.0,
        on_sighting: Callable[[BoardSighting], None] | None = None,
        idle_period_s: float = 3.0,
    ) -> None:
        super().__init__("board-watch", 1.0 / rate_hz)
        self.idle_period_s = idle_period_s
        self._last_pass = -math.inf
        self.latest_frames, self.rig, self.board = latest, rig, board
        self.on_sighting = on_sighting
        self.enabled = True
        self.latest: BoardSighting | None = None
        self.error: str | None = None
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="board-detect")
        self._searched: FrameSet | None = None

    def stop(self, timeout_s: float = 2.0) -> None:
        super().stop(timeout_s)
        self._pool.shutdown(wait=False)

    def tick(self) -> None:
        fs = self.latest_frames()
        if not self.enabled or fs is None or fs is self._searched:
            return
        idle = self.latest is not None and not self.latest.found
        if idle and time.monotonic() - self._last_pass < self.idle_period_s:
            return  # no board lately: search less often (a failed search is the costliest)
        self._last_pass = time.monotonic()
        self._searched = fs
        try:
            s = sighting(fs, self.rig, self.board, self.latest, self._pool)
        except Exception as exc:  # shown in the panel; the watch keeps running
            self.error = f"{type(exc).__name__}: {exc}"
            return
        self.error = None
        self.latest = s
        if self.on_sighting is not None:
            self.on_sighting(s)
