"""Where to hold the board next, in the console (issue 30, 6).

After each capture (once its images are searched), :class:`NextPoseAdvisor` calibrates the
session's views in the background, as ``Run calibration`` would (the same detections,
:func:`~app.workflows.calibration_run.calibrate_capture`), and asks
:func:`calib.next_pose.suggest_next_pose` for the board pose that would lower the worst
sigma / target ratio of the verdicts most. :class:`NextPoseOverlay` shows it in the
Calibration folder:

- a line: what to do (``move closer (0.9 m), turn the left edge away 30°, lower-right
  corner of ccd_left``; the distance against where the board is now when the board watch
  sees it), which sigma it is for and what it should become;
- the live image of the sensor the words refer to, with the board's outline where it
  should appear (cyan) and where the board is now (yellow: its outer inner corners);
- the same cyan outline in the Feeds panel's image and the 3D scene's live image of every
  sensor that would see the board there (``ctx.next_outline``);
- in the 3D scene, a translucent cyan ghost board at the pose (``/live/next_board``, in
  the rig frame like the live board).

When every sensor's sigma meets its target it says "every sensor meets its target: no
more views needed" and the ghost is hidden.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.panels.display import (
    NEXT_RGB,
    draw_note,
    draw_outline,
    recent_sighting,
    scale_corners,
    thumbnail,
)
from trifuse.app.server.panels.scene_sensors import wxyz_of
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.storage.capture import CaptureError, load_capture
from trifuse.app.workflows.calib_session import CalibrationSession
from trifuse.app.workflows.calibration_run import calibrate_capture
from trifuse.calib.errors import CalibrationError
from trifuse.calib.next_pose import NextPose, outline_points, suggest_next_pose
from trifuse.calib.rig_result import CalibrationResult
from trifuse.calib.verdict import GOOD, ZHANG_MIN_VIEWS

NOW_RGB = (255, 220, 0)
"""The board where it is now (as the 3D scene's live board)."""
IMAGE_WIDTH_PX = 320
IMAGE_PERIOD_S = 1.0
"""The live image with the outline is sent at most this often (when its frame changed)."""
GHOST_OPACITY = 0.35
DONE_TEXT = "every sensor meets its target: no more views needed"


@dataclass(frozen=True)
class Suggestion:
    """The advisor's answer for a set of views.

    Attributes:
        views: the views (searched) it was computed from.
        result: their calibration (None: it failed or there are too few views).
        next: the suggested pose (None: none needed, or none helps).
        error: why there is no calibration.
    """

    views: tuple[str, ...]
    result: CalibrationResult | None
    next: NextPose | None
    error: str | None = None

    @property
    def done(self) -> bool:
        """Every sensor's (and pair's) sigma meets its target."""
        v = None if self.result is None else self.result.verdict
        return self.next is None and v is not None and v.grade == GOOD


def compute_suggestion(session: CalibrationSession, names: list[str]) -> Suggestion:
    """Calibrate the session's views ``names`` (their detections as searched) and suggest
    the next pose."""
    try:
        capture = load_capture(session.captures)
        capture.views = [v for v in capture.views if v.name in names]
        result, _ = calibrate_capture(capture, detections=session.detection_run(names))
        newcomers = {n: session.rig[n] for n in result.excluded_sensors if n in session.rig}
        nxt = suggest_next_pose(result, newcomers=newcomers)
    except (CalibrationError, CaptureError, KeyError, ValueError) as exc:
        return Suggestion(tuple(names), None, None, str(exc))
    return Suggestion(tuple(names), result, nxt)


class NextPoseAdvisor:
    """Computes a :class:`Suggestion` in a background thread whenever the session's
    searched views change (one computation at a time; the newest views win)."""

    def __init__(self, session: CalibrationSession) -> None:
        self.session = session
        self.latest: Suggestion | None = None
        self._thread: threading.Thread | None = None
        self._asked: tuple[str, ...] | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def searched(self) -> tuple[str, ...]:
        """The views whose every image has been searched."""
        return tuple(v.name for v in self.session.views() if v.searched)

    def poll(self) -> None:
        """Start a computation when the searched views differ from the last asked."""
        names = self.searched()
        if names == self._asked or self.running:
            return
        self._asked = names
        if len(names) < ZHANG_MIN_VIEWS:
            self.latest = Suggestion(names, None, None)
            return
        self._thread = threading.Thread(
            target=self._run, args=(list(names),), name="next-pose", daemon=True
        )
        self._thread.start()

    def _run(self, names: list[str]) -> None:
        try:
            self.latest = compute_suggestion(self.session, names)
        except Exception as exc:  # a defect: shown, the console keeps running
            self.latest = Suggestion(tuple(names), None, None, describe_error(exc))


def suggestion_md(s: Suggestion | None, running: bool, words: str | None = None) -> str:
    """The panel's line (markdown) for suggestion ``s`` (``words``: its words against the
    board's present pose, if seen)."""
    if s is None or (s.result is None and s.error is None):
        n = 0 if s is None else len(s.views)
        return (
            f"**Next view:** capture {max(1, ZHANG_MIN_VIEWS - n)} more view(s) of the "
            "board: then the console suggests where to hold it."
        )
    busy = " (updating ...)" if running else ""
    if s.result is None:
        return (
            f"**Next view:** no calibration of {len(s.views)} views yet{busy}: {md_text(s.error)}"
        )
    lines = []
    if s.done:
        lines.append(f"**Next view:** {DONE_TEXT} ({len(s.views)} views){busy}.")
    elif s.next is None:
        worst = max(
            [*s.result.verdict.sensors.values(), *s.result.verdict.pairs],
            key=lambda v: max((f.ratio for f in v.judged), default=0.0),
        )
        lines.append(
            f"**Next view:** no single view helps ({len(s.views)} views){busy}: "
            f"{md_text(worst.label)}: {md_text(worst.advice or worst.line)}"
        )
    else:
        n = s.next
        now, after = n.worst_now, n.worst_after
        lines.append(f"**Next view:** {md_text(words or n.words())}{busy}.")
        lines.append(
            f"For σ of the {md_text(now.what)} ({md_text(' – '.join(n.sensors))}): "
            f"{now.ratio:.1f}× its target now, {after.ratio:.1f}× expected after this view "
            f"({len(s.views)} views so far)."
        )
    for name, why in s.result.excluded_sensors.items():
        shown = s.next is not None and name in s.next.newcomers
        also = " (the next view shows it the board)" if shown else ""
        lines.append(f"- {md_text(name)} not calibrated yet{also}: {md_text(why)}")
    return "  \n".join(lines)


def draw_board_now(thumb: np.ndarray, corners: np.ndarray, cols: int, image_size) -> None:
    """The board where it is now: the quadrilateral of its outer inner corners (N, 2),
    full-image pixels, row-major ``cols`` per row; yellow."""
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if cols <= 0 or len(c) % cols:
        return
    quad = c[[0, cols - 1, len(c) - 1, len(c) - cols]]
    pts = np.round(scale_corners(quad, image_size, thumb) * 16).astype(np.int32)
    cv2.polylines(thumb, [pts.reshape(-1, 1, 2)], True, NOW_RGB, 1, cv2.LINE_AA, 4)


def next_pose_image(
    image: np.ndarray,
    nxt: NextPose | None,
    words: str,
    corners_now: np.ndarray | None,
    cols: int,
    width: int = IMAGE_WIDTH_PX,
) -> np.ndarray:
    """The live image (any frame image, :func:`~app.server.panels.display.thumbnail`)
    ``width`` wide with the suggested outline (cyan), the board now (yellow) and the words
    in a strip at the bottom; (h, width, 3) uint8 RGB."""
    thumb = np.ascontiguousarray(thumbnail(image, width))
    size = (image.shape[1], image.shape[0])
    if words:
        draw_note(thumb, words, 0.35)
    if corners_now is not None:
        draw_board_now(thumb, corners_now, cols, size)
    if nxt is not None and nxt.subject in nxt.outline_px:
        draw_outline(thumb, nxt.outline_px[nxt.subject], size)
    return thumb


class NextPoseOverlay:
    """The suggestion's line and live image (made in the caller's GUI folder) and the 3D
    ghost board; :meth:`tick` (from the Calibration panel's thread) keeps them current."""

    def __init__(self, ctx: ConsoleContext, session: CalibrationSession) -> None:
        self.ctx, self.advisor = ctx, NextPoseAdvisor(session)
        gui, scene = ctx.server.gui, ctx.server.scene
        self.md = gui.add_markdown(suggestion_md(None, False))
        self.image = gui.add_image(
            np.zeros((90, 120, 3), np.uint8),
            label="next view",
            format="jpeg",
            jpeg_quality=75,
            visible=False,
        )
        board = ctx.board
        corners = outline_points(board)
        self.ghost = scene.add_frame("/live/next_board", show_axes=False, visible=False)
        scene.add_mesh_simple(
            "/live/next_board/plate",
            corners.astype(np.float32),
            np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32),
            color=NEXT_RGB,
            opacity=GHOST_OPACITY,
            side="double",
            cast_shadow=False,
            receive_shadow=False,
        )
        scene.add_line_segments(
            "/live/next_board/outline",
            np.stack([corners, np.roll(corners, -1, axis=0)], axis=1),
            NEXT_RGB,
            thickness=3.0,
            thickness_units="screen",
        )
        centre = corners.mean(axis=0)
        scene.add_label("/live/next_board/label", "next view", position=tuple(centre))
        self._shown: Suggestion | None = None
        self._frame: tuple[object, object, str | None] | None = None  # what the image shows
        self._md = ""
        self._next_image = 0.0

    def tick(self) -> None:
        self.advisor.poll()
        s = self.advisor.latest
        nxt = None if s is None else s.next
        if s is not self._shown:
            self._shown = s
            self._show_ghost(nxt)
        watch = self.ctx.board_watch
        sighting = watch.latest if watch.enabled else None
        T_now = None if sighting is None else sighting.T_rig_board
        words = None
        if nxt is not None and s is not None and s.result is not None:
            words = nxt.words(T_now, s.result.sensors)
        md = suggestion_md(s, self.advisor.running, words)
        if md != self._md:
            self._md = self.md.content = md
        self._show_image(nxt, s, words, sighting)

    def _show_ghost(self, nxt: NextPose | None) -> None:
        """The ghost board in the 3D scene, and the outline in the live images."""
        self.ctx.next_outline = {} if nxt is None else dict(nxt.outline_px)
        if nxt is None:
            self.ghost.visible = False
            return
        self.ghost.wxyz = wxyz_of(nxt.T_rig_board)
        self.ghost.position = nxt.T_rig_board[:3, 3].copy()
        self.ghost.visible = True

    def _show_image(self, nxt, s: Suggestion | None, words: str | None, sighting) -> None:
        """The subject's live frame with the outline, about once a second when it changed."""
        now = time.monotonic()
        fs = self.ctx.pipeline.latest_set
        subject = nxt.subject if nxt is not None else None
        if subject is None or fs is None or subject not in fs.frames:
            if self.image.visible:
                self.image.visible = False
            self._frame = None
            return
        frame = fs.frames[subject]
        corners = None
        if recent_sighting(sighting, fs) and subject in sighting.frames.frames:
            det = sighting.detections.get(subject)
            if det is not None and det.found:  # drawn on the frame it was found in
                frame, corners = sighting.frames.frames[subject], det.corners
        key = (frame, s, words)
        same = self._frame is not None and key[0] is self._frame[0] and key[1] is self._frame[1]
        if (same and words == self._frame[2]) or now < self._next_image:
            return
        self._frame, self._next_image = key, now + IMAGE_PERIOD_S
        self.image.image = next_pose_image(
            frame.image, nxt, words or "", corners, self.ctx.board.cols
        )
        self.image.label = f"next view: {subject}"
        self.image.visible = True


def verdict_md(verdict: dict) -> list[str]:
    """The report's ``verdict`` block (calib.verdict ``RigVerdict.as_dict``) as markdown
    lines for the Calibration panel: the overall grade, then one line per sensor and per
    pair with its grade, the sigmas above target and the advice."""
    rows = [
        *verdict["sensors"].values(),
        *verdict.get("sensors_intrinsics_only", {}).values(),
        *verdict["pairs"],
    ]
    return [
        f"**Verdict: {md_text(verdict['grade'])}** (good: every 1-sigma within half its "
        "accuracy target; poor: one beyond twice it)",
        "",
        *(f"- **{md_text(v['label'])}** {md_text(v['line'])}" for v in rows),
    ]
