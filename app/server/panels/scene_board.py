"""The calibration board in the console's 3D scene: a frame node at the board watch's
newest pose ``T_rig_board`` (board frame: origin at the first detectable point, +z away
from the cameras, metres) carrying the board's pattern (checkerboard, ChArUco, circle
grid) as an image and the outline of the patterned area, and the line that says where it
is."""

from __future__ import annotations

import numpy as np
import viser

from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.panels.scene_sensors import wxyz_of
from trifuse.app.server.runtime.board_sighting import BoardSighting
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.board import Board, aruco_dictionary

BOARD_PX_PER_SQUARE = 16
BOARD_PX_PER_CELL = 4
"""A ChArUco marker's cells (bits) are drawn at least this many pixels wide."""
BOARD_PLATE_BEHIND_M = 0.003
"""The board's checker plate is drawn this far behind the board plane (+z of the board
frame, away from the cameras) so the cloud's points on the board stay visible."""
BOARD_OUTLINE_RGB = (255, 220, 0)
BOARD_LAG_SHOWN_S = 0.5
"""The board's line in the folder says how much older its frames are than the cloud's
from this lag on."""


def board_checker_image(board: Board, px_per_square: int = BOARD_PX_PER_SQUARE) -> np.ndarray:
    """The board's patterned area (:meth:`Board.extent_m`) as an (H, W, 3) uint8 RGB image
    of ``px_per_square`` pixels a square (circle grids: a spacing; ChArUco: more where a
    marker's cells need :data:`BOARD_PX_PER_CELL`); pixel row 0 is the area's -y edge,
    column 0 its -x edge, and the dark pixels are where :meth:`Board.is_black` says
    (black squares, markers, circles)."""
    x0, y0, x1, y1 = board.extent_m()
    px_per_m = px_per_square / board.square_size_m
    if board.pattern == "charuco":
        cells = int(aruco_dictionary(board.dictionary).markerSize) + 2  # type: ignore[arg-type]
        px_per_m = max(px_per_m, BOARD_PX_PER_CELL * cells / board.marker_size_m)  # type: ignore[operator]
    w, h = round((x1 - x0) * px_per_m), round((y1 - y0) * px_per_m)
    x = x0 + (np.arange(w) + 0.5) * (x1 - x0) / w
    y = y0 + (np.arange(h) + 0.5) * (y1 - y0) / h
    black = board.is_black(x[None, :], y[:, None])
    grey = np.where(black, 20, 235).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def board_outline(board: Board) -> np.ndarray:
    """The patterned area's edges as line segments (4, 2, 3) in the board frame, metres."""
    x0, y0, x1, y1 = board.extent_m()
    c = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    return np.stack([c, np.roll(c, -1, axis=0)], axis=1)


def board_lag_s(sighting: BoardSighting | None, newest: object) -> float:
    """How much older (seconds) the frames a board sighting was found in are than the
    ``newest`` frame set: 0 when the newest set shows the very image the pose came from
    (a simulated head holding a pose, a paused replay: the board drawn is current), or
    without a sighting or a frame set (``newest`` is whatever the pipeline holds: the
    board is drawn even if that is broken)."""
    if sighting is None or not isinstance(newest, FrameSet):
        return 0.0
    sensor = sighting.pose_sensor
    if sensor is not None:
        seen, current = sighting.frames.frames.get(sensor), newest.frames.get(sensor)
        if seen is not None and current is not None and seen.image is current.image:
            return 0.0
    return (newest.stamp_ns - sighting.frames.stamp_ns) / 1e9


class BoardMarker:
    """The board's node in the scene (under ``/live``: the rig in use) and its line in the
    "3D scene" folder (``md``)."""

    def __init__(self, scene: viser.SceneApi, board: Board, md: viser.GuiMarkdownHandle) -> None:
        node = scene.add_frame("/live/board", axes_length=0.05, axes_radius=0.002, visible=False)
        x0, y0, x1, y1 = board.extent_m()
        scene.add_image(
            "/live/board/plate",
            board_checker_image(board),
            render_width=x1 - x0,
            render_height=y1 - y0,
            format="png",
            position=((x0 + x1) / 2.0, (y0 + y1) / 2.0, BOARD_PLATE_BEHIND_M),
        )
        scene.add_line_segments(
            "/live/board/outline",
            board_outline(board),
            BOARD_OUTLINE_RGB,
            thickness=3.0,
            thickness_units="screen",
        )
        self.node, self.md = node, md
        self._sighting: BoardSighting | None = None

    def show(self, sighting: BoardSighting | None, newest: object) -> None:
        """The board at ``sighting``'s pose ``T_rig_board`` (a
        :class:`~app.server.runtime.board_sighting.BoardSighting`, or None), hidden when it
        has none; the line says how far away, from which sensor, who saw it and, from
        :data:`BOARD_LAG_SHOWN_S` on, how much older its frames are than the ``newest``
        frame set. Nothing changes for the sighting shown already."""
        lag_s = board_lag_s(sighting, newest)
        if sighting is self._sighting:
            return
        self._sighting = sighting
        T = None if sighting is None else sighting.T_rig_board
        if sighting is None or T is None or np.shape(T) != (4, 4) or not np.isfinite(T).all():
            self.node.visible = False
            self.md.content = "Board: not detected"
            return
        T = np.asarray(T, dtype=np.float64)
        self.node.wxyz = wxyz_of(T)
        self.node.position = T[:3, 3].copy()
        self.node.visible = True
        dist = float(np.linalg.norm(T[:3, 3]))
        pose_sensor = md_text(sighting.pose_sensor)
        text = f"Board: {dist:.2f} m away, pose from {pose_sensor}"
        seen = ", ".join(sighting.found)
        if not sighting.complete:
            text += "; searching the other sensors"
        elif seen:
            text += f"; seen by {md_text(seen)}"
        if lag_s >= BOARD_LAG_SHOWN_S:  # detection is slower than the board may move
            text += f" (in frames {lag_s:.1f} s older than the cloud)"
        self.md.content = text
