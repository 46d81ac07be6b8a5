"""The console's Viser GUI panels: Fusion, Thermal and Feeds.

Fusion and Thermal write the pipeline's display settings and per-imager offsets (taking
effect on the next frame; Fusion also the video stream's default preset,
:mod:`app.server.panels.stream`, and shows each eye's registration sigma,
:mod:`app.server.runtime.registration_watch`, whose colour map its ``registration`` mode
draws); Feeds shows each sensor's newest image (thermal colour-mapped,
TOF amplitude stretched) with the board watch's detected corners drawn on it (or, in a strip
at the bottom, why the board was not found there) and, during a calibration session, the
cyan outline of where to hold the board next (``ctx.next_outline``). The Thermal panel shows
the live left-right temperature difference over points both imagers see (the same TOF point
sampled in each).

While the board watch's newest sighting is recent (:data:`SIGHTING_RECENT_S`), the feeds
show the sighting's own frames, so that the corners sit on the image they were found in.

The feeds follow the console's bandwidth mode (``ctx.bandwidth``, :data:`FEED_PROFILES`):
``full`` 320 px wide, JPEG quality 75, twice a second; ``low`` 160 px, quality 50, once a
second (about 40 % of the bytes per image, half as many images).
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.panels.stream import StreamPresetControl
from trifuse.app.server.runtime.board_sighting import BoardSighting
from trifuse.app.server.runtime.context import BANDWIDTH_MODES, ConsoleBandwidth, ConsoleContext
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.thermal_balance import BalanceStatus
from trifuse.app.server.settings_spec import (
    EDGE_STRENGTH,
    MANUAL_OFFSET_K,
    MAX_GAIN,
    OPACITY,
    PLATEAU,
    SPAN_SMOOTHING_S,
)
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.storage.preview import to_display
from trifuse.app.workflows.calib_session import radiometry_report
from trifuse.calib.detect import Detection
from trifuse.fusion.agc import AGC_MODES
from trifuse.fusion.compose import DIRECTIONS, DISPLAY_MODES
from trifuse.fusion.palettes import PALETTE_NAMES
from trifuse.fusion.span import level_from_span, span_from_level

C_TO_K = 273.15

FEED_WIDTH_PX = 320
"""Width of a feed thumbnail (the height keeps the sensor's aspect ratio)."""
NEXT_RGB = (0, 220, 255)
"""The suggested next board pose's colour (outline in the images, ghost board in the scene)."""


@dataclass(frozen=True)
class FeedProfile:
    """How the Feeds are sent in one bandwidth mode.

    Attributes:
        hz: feed updates per second at most (a feed whose frame is unchanged is not sent).
        width_px: thumbnail width, pixels.
        jpeg_quality: JPEG quality (0-100).
    """

    hz: float
    width_px: int
    jpeg_quality: int


FEED_PROFILES = {
    "full": FeedProfile(2.0, FEED_WIDTH_PX, 75),
    "low": FeedProfile(1.0, FEED_WIDTH_PX // 2, 50),
}
"""The Feeds' profile of each mode of :data:`~app.server.runtime.context.BANDWIDTH_MODES`
(five thumbnails of the simulated head: 26 kB per round in ``full``, 9 kB in ``low``)."""
FEED_SLACK_S = 0.05
"""The feeds are due this much early (the panel's ticks come a little late)."""

SIGHTING_RECENT_S = 30.0
"""A board sighting whose frame set is at most this much older than the newest one is
drawn (on its own frames); an older one is not drawn at all (a paused watch, a replay that
jumped). A detection pass takes about 0.6 s of CPU, but 10-15 s were measured on an
overloaded machine: the feeds then lag by that much, and their labels say so."""

LAG_SHOWN_S = 2.0
"""From this age on, a feed drawn from a sighting says in its label how old it is."""

ROW_COLOURS = (
    (255, 0, 0),
    (255, 128, 0),
    (200, 200, 0),
    (0, 255, 0),
    (0, 200, 200),
    (0, 0, 255),
    (255, 0, 255),
)
"""RGB colour of each row of corners, cyclic (``cv2.drawChessboardCorners``' colours)."""

_SHIFT = 4  # fixed-point bits for sub-pixel drawing


def thumbnail(image: np.ndarray, width: int = FEED_WIDTH_PX) -> np.ndarray:
    """(h, width, 3) uint8 RGB display version of any frame image (:func:`to_display`)."""
    img = to_display(image)
    h, w = img.shape[:2]
    size = (width, max(1, round(width * h / w)))
    interp = cv2.INTER_AREA if width < w else cv2.INTER_LINEAR
    return cv2.resize(img, size, interpolation=interp)


def scale_corners(
    corners_px: np.ndarray, image_size: tuple[int, int], thumb: np.ndarray
) -> np.ndarray:
    """(N, 2) corners in the full image (W, H = ``image_size``) -> thumbnail pixels.

    Pixel centres at integers in both (OpenCV): ``x' = (x + 0.5) * w / W - 0.5``.
    """
    w_full, h_full = image_size
    sx, sy = thumb.shape[1] / w_full, thumb.shape[0] / h_full
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 2)
    return np.stack([(c[:, 0] + 0.5) * sx - 0.5, (c[:, 1] + 0.5) * sy - 0.5], axis=1)


FULL_MARKERS_PX = 10.0
"""Corner spacing (thumbnail pixels) from which corners get circles, crosses and row
lines; closer corners get small dots only, so that the board stays visible under them."""


def draw_corners(thumb: np.ndarray, corners: np.ndarray, cols: int) -> None:
    """Draw corners (N, 2), thumbnail pixels, row-major ``cols`` per row, in place: like
    ``cv2.drawChessboardCorners`` (a circle and an x per corner, a line from the previous
    corner, one colour per row), sized to the corner spacing; dots where the corners are
    closer than :data:`FULL_MARKERS_PX`. NaN rows (corners a partial view did not see)
    are left out."""
    n = len(corners)
    if n == 0:
        return
    cols = cols if cols > 0 and n % cols == 0 else n
    steps = np.linalg.norm(np.diff(corners.reshape(-1, cols, 2), axis=1), axis=2)
    steps = steps[np.isfinite(steps)]
    spacing = float(np.median(steps)) if steps.size else FULL_MARKERS_PX
    one = 1 << _SHIFT
    seen = np.isfinite(corners).all(axis=1)
    pts = np.round(np.where(seen[:, None], corners, 0.0) * one).astype(np.int64)
    aa = cv2.LINE_AA
    full = spacing >= FULL_MARKERS_PX
    rr = round(min(0.3 * spacing, 4.0) * one) if full else round(max(0.2 * spacing, 0.8) * one)
    for i in np.flatnonzero(seen):
        colour = ROW_COLOURS[(i // cols) % len(ROW_COLOURS)]
        x, y = int(pts[i, 0]), int(pts[i, 1])
        if not full:
            cv2.circle(thumb, (x, y), rr, colour, -1, aa, _SHIFT)
            continue
        if i and seen[i - 1]:
            prev = (int(pts[i - 1, 0]), int(pts[i - 1, 1]))
            cv2.line(thumb, prev, (x, y), colour, 1, aa, _SHIFT)
        cv2.line(thumb, (x - rr, y - rr), (x + rr, y + rr), colour, 1, aa, _SHIFT)
        cv2.line(thumb, (x - rr, y + rr), (x + rr, y - rr), colour, 1, aa, _SHIFT)
        cv2.circle(thumb, (x, y), rr + one, colour, 1, aa, _SHIFT)


def short_reason(reason: str | None) -> str:
    """A detector's reason without its parenthesised details, e.g. "board not found"."""
    text = re.sub(r"\s*\([^()]*\)", "", reason or "board not found").strip()
    return text or "board not found"


def draw_note(thumb: np.ndarray, text: str, scale: float = 0.4) -> None:
    """Write ``text`` in white on a darkened strip along the bottom, in place (cut with
    "..." to the width)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    h, w = thumb.shape[:2]
    (tw, th), base = cv2.getTextSize(text, font, scale, 1)
    while tw > w - 8 and len(text) > 4:
        text = text[: len(text) - 5].rstrip() + "..."
        (tw, th), base = cv2.getTextSize(text, font, scale, 1)
    top = max(0, h - th - base - 8)
    thumb[top:] //= 3
    cv2.putText(thumb, text, (4, h - base - 4), font, scale, (255, 255, 255), 1, cv2.LINE_AA)


def feed_image(
    frame: Frame,
    detection: Detection | None,
    cols: int,
    width: int = FEED_WIDTH_PX,
    next_outline: np.ndarray | None = None,
) -> np.ndarray:
    """The feed thumbnail of ``frame`` with the detection drawn: corners when found, else
    the short reason; nothing when ``detection`` is None (no recent search). With
    ``next_outline`` ((4, 2) full-image pixels), the next view's outline too."""
    thumb = np.ascontiguousarray(thumbnail(frame.image, width))
    h, w = frame.image.shape[:2]
    if detection is not None and detection.found:
        draw_corners(thumb, scale_corners(detection.corners, (w, h), thumb), cols)
    elif detection is not None:
        draw_note(thumb, short_reason(detection.reason))
    if next_outline is not None:
        draw_outline(thumb, next_outline, (w, h))
    return thumb


def draw_outline(thumb: np.ndarray, outline_px: np.ndarray, image_size: tuple[int, int]) -> None:
    """The suggested board's outline (4, 2) full-image pixels, drawn in place on ``thumb``:
    a thick cyan quadrilateral with the first corner (the board's origin) marked."""
    pts = scale_corners(outline_px, image_size, thumb)
    if not np.all(np.isfinite(pts)):
        return
    poly = np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(thumb, [poly], True, NEXT_RGB, 2, cv2.LINE_AA, 4)
    x, y = np.round(pts[0]).astype(int)
    cv2.circle(thumb, (int(x), int(y)), 4, NEXT_RGB, -1, cv2.LINE_AA)


def recent_sighting(sighting: BoardSighting | None, newest: FrameSet) -> bool:
    """Whether ``sighting`` searched a frame set within :data:`SIGHTING_RECENT_S` of
    ``newest`` (either way: a looping replay goes back in time)."""
    if sighting is None:
        return False
    return abs(newest.stamp_ns - sighting.frames.stamp_ns) <= SIGHTING_RECENT_S * 1e9


class Panels(Periodic):
    """Builds the panels and refreshes the feeds and the left-right difference.

    Args:
        ctx: the console's shared objects (``ctx.bandwidth``: the feeds' profile).
        feed_hz: ticks per second (the feeds at most this often, or their profile's rate).
        clock: monotonic seconds (tests pass their own).

    Attributes:
        bandwidth: the console's setting (``ctx.bandwidth``).
        bandwidth_mode, profile: the bandwidth mode the feeds are sent in and its
            :class:`FeedProfile`.
    """

    def __init__(
        self,
        ctx: ConsoleContext,
        feed_hz: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__("panels", 1.0 / feed_hz)
        self.ctx = ctx
        self.clock = clock
        self.bandwidth: ConsoleBandwidth = ctx.bandwidth
        self.bandwidth_mode = self.bandwidth.mode
        self.profile = FEED_PROFILES[self.bandwidth_mode]
        self._next_feeds = 0.0
        server, pipeline = ctx.server, ctx.pipeline
        self.server, self.pipeline = server, pipeline
        gui = server.gui
        s = pipeline.settings
        with gui.add_folder("Fusion"):
            self.mode = gui.add_dropdown("Mode", DISPLAY_MODES, initial_value=s.mode)
            self.opacity = gui.add_slider("Opacity", *OPACITY.slider(), s.opacity)
            self.edges = gui.add_slider("Edge strength", *EDGE_STRENGTH.slider(), s.edge_strength)
            self.thr_lo = gui.add_number("Threshold low (°C)", 40.0, step=0.5)
            self.thr_hi = gui.add_number("Threshold high (°C)", 40.0, step=0.5)
            self.thr_dir = gui.add_dropdown(
                "Threshold shows", DIRECTIONS, initial_value=s.threshold_direction
            )
            self.iso_lo = gui.add_number("Isotherm low (°C)", 30.0, step=0.5)
            self.iso_hi = gui.add_number("Isotherm high (°C)", 40.0, step=0.5)
            self.agc = gui.add_dropdown(
                "AGC",
                AGC_MODES,
                initial_value=s.agc,
                hint="How temperatures become colours: linear over the span, plateau "
                "equalization over both eyes (no temperature takes more than the plateau "
                "share of the palette), or dde (equalized base plus amplified local detail)",
            )
            self.plateau = gui.add_slider(
                "Plateau (%)",
                *PLATEAU.slider(),
                round(PLATEAU.gui_scale * s.plateau, 1),
                hint="The largest share of the pixels one 0.1 K bin counts with "
                "(100 %: plain histogram equalization)",
            )
            self.max_gain = gui.add_slider(
                "Max gain (steps/K)",
                *MAX_GAIN.slider(),
                float(min(100, round(s.max_gain))),
                hint="Plateau and dde: the most palette steps one kelvin may take, so that a "
                "flat wall's noise and the imagers' offset are not stretched",
            )
            self.mark = gui.add_checkbox(
                "Mark fallback depth",
                s.mark_fallback,
                hint="Mute the colours where the TOF had no depth (registration approximate)",
            )
            self.stream = StreamPresetControl(gui, ctx.stream_settings)
            self.registration = gui.add_markdown(
                registration_text(ctx.registration.summary_text())
                if ctx.registration is not None
                else ""
            )
        with gui.add_folder("Thermal"):
            self.palette = gui.add_dropdown("Palette", PALETTE_NAMES, initial_value=s.palette)
            self.auto = gui.add_checkbox(
                "Auto span (both eyes)",
                s.span_k is None,
                hint="Percentiles over both imagers, smoothed over time",
            )
            self.level = gui.add_number("Level (°C)", 30.0, step=0.5)
            self.span = gui.add_number("Span (K)", 30.0, min=0.5, step=0.5)
            self.smoothing = gui.add_slider(
                "Span smoothing (s)", *SPAN_SMOOTHING_S.slider(), s.span_smoothing_s
            )
            self.offsets = {
                name: gui.add_number(
                    f"Offset {name} (K)", r.manual_offset_k, **MANUAL_OFFSET_K.number()
                )
                for name, r in pipeline.radiometry.items()
            }
            self._balancer_auto = ctx.balancer is not None and ctx.balancer.auto
            """The balancer's ``auto`` as this panel last saw or set it."""
            self.auto_balance = gui.add_checkbox(
                "Auto-balance",
                self._balancer_auto,
                hint="Estimate the left-right offset from points both imagers see, "
                "filtered over time, and apply it",
            )
            imagers = tuple(pipeline.radiometry)
            self.balance_ref = gui.add_dropdown("Balance onto", (SPLIT, *imagers))
            self.balance_now = gui.add_button("Balance now")
            self.balance_reset = gui.add_button("Reset balance")
            self.balance_md = gui.add_markdown("Balance: not estimated yet")
            self.difference = gui.add_markdown("Left - right: waiting for frames")
            self.save_radiometry = gui.add_button(
                "Save as rig version", hint="The rig in use with this radiometry, as rigs/rig-NNNN"
            )
            self.error = gui.add_markdown("")
        with gui.add_folder("Feeds", expand_by_default=False) as self.feeds_folder:
            blank = np.zeros((90, 120, 3), np.uint8)
            quality = self.profile.jpeg_quality
            self.feeds = {
                name: gui.add_image(blank, label=name, format="jpeg", jpeg_quality=quality)
                for name in pipeline.rig.names
            }
            self.feeds_error = gui.add_markdown("")
        # what each feed shows (:attr:`feeds_shown`), compared by identity
        self._shown: dict[str, tuple[Frame, Detection | None, np.ndarray | None]] = {}
        for handle in (
            self.mode,
            self.palette,
            self.opacity,
            self.edges,
            self.thr_lo,
            self.thr_hi,
            self.thr_dir,
            self.iso_lo,
            self.iso_hi,
            self.agc,
            self.plateau,
            self.max_gain,
            self.mark,
            self.auto,
            self.level,
            self.span,
            self.smoothing,
            *self.offsets.values(),
            self.auto_balance,
            self.balance_ref,
        ):
            # the operator's changes only: the panel's own updates (following the automatic
            # span) must not write its controls over settings made through the REST API
            handle.on_update(lambda event: self.apply() if event.client is not None else None)
        self.balance_now.on_click(lambda _e: self._act(self._balance_now))
        self.balance_reset.on_click(lambda _e: self._act(self._reset_balance))
        self.save_radiometry.on_click(lambda _e: self._act(self._save_radiometry))

    def apply(self) -> None:
        """Settings from the controls; a bad combination is shown, the old one kept."""
        try:
            span = span_from_level(self.level.value + C_TO_K, float(self.span.value))
            settings = dataclasses.replace(
                self.pipeline.settings,
                mode=self.mode.value,
                palette=self.palette.value,
                opacity=float(self.opacity.value),
                edge_strength=float(self.edges.value),
                threshold_k=(self.thr_lo.value + C_TO_K, self.thr_hi.value + C_TO_K),
                threshold_direction=self.thr_dir.value,
                isotherm_k=(self.iso_lo.value + C_TO_K, self.iso_hi.value + C_TO_K),
                mark_fallback=bool(self.mark.value),
                agc=self.agc.value,
                plateau=float(self.plateau.value) / PLATEAU.gui_scale,
                max_gain=float(self.max_gain.value),
                span_k=None if self.auto.value else span,
                span_smoothing_s=float(self.smoothing.value),
            )
            for name, handle in self.offsets.items():
                self.pipeline.set_manual_offset(name, float(handle.value))
        except ValueError as exc:
            self.error.content = f"**Not applied:** {md_text(exc)}"
            return
        self.error.content = ""
        self.pipeline.settings = settings
        balancer = self.ctx.balancer
        if balancer is not None:
            ref = self.balance_ref.value
            balancer.reference = None if ref == SPLIT else ref
            balancer.set_auto(bool(self.auto_balance.value))
            self._balancer_auto = balancer.auto

    def _follow_auto_span(self) -> None:
        """While the span is automatic, Level and Span show it (so that switching to
        manual starts from the colours on screen)."""
        span = self.pipeline.fusion.span_k if self.auto.value else None
        if span is None:
            return
        level, width = level_from_span(*span)
        level_c = round(level - C_TO_K, 1)
        if abs(self.level.value - level_c) > 0.05 or abs(self.span.value - round(width, 1)) > 0.05:
            self.level.value, self.span.value = level_c, round(width, 1)

    def _act(self, action) -> None:
        """Run a button's action; its refusal is shown, never raised into Viser."""
        try:
            self.error.content = action() or ""
        except (KeyError, ValueError, OSError) as exc:
            self.error.content = f"**Not done:** {md_text(exc.args[0] if exc.args else exc)}"

    def _balance_now(self) -> str:
        if self.ctx.balancer is None:
            raise ValueError("no balance estimation in this console")
        state = self.ctx.balancer.apply_filtered()
        return f"Balanced: left - right was {state.offset_k:+.2f} K."

    def _reset_balance(self) -> str:
        if self.ctx.balancer is not None:
            self.ctx.balancer.reset_balance()
        self.auto_balance.value = False
        return "Balance reset."

    def _save_radiometry(self) -> str:
        if self.ctx.save_rig is None:
            raise ValueError("no calibration session to save into")
        rig = self.pipeline.rig_with_radiometry()
        version = self.ctx.save_rig(rig, radiometry_report(rig))
        return f"Saved the radiometry with the rig in use as **{md_text(version.name)}**."

    def follow_bandwidth(self) -> None:
        """Take the console's bandwidth mode (:attr:`bandwidth`) if it changed: the feeds'
        images are made again at the new JPEG quality (Viser fixes it when an image is
        made; same place in the folder) and sent again at the new width."""
        mode = self.bandwidth.mode
        if mode == self.bandwidth_mode or mode not in BANDWIDTH_MODES:
            return
        self.bandwidth_mode, self.profile = mode, FEED_PROFILES[mode]
        gui = self.server.gui
        with self.feeds_folder:
            for name, old in list(self.feeds.items()):
                self.feeds[name] = gui.add_image(
                    old.image,
                    label=old.label,
                    format="jpeg",
                    jpeg_quality=self.profile.jpeg_quality,
                    order=old.order,
                )
                old.remove()
        self._shown.clear()
        self._next_feeds = 0.0

    def tick(self) -> None:
        self.stream.follow()
        self.follow_bandwidth()
        fs = self.pipeline.latest_set
        if fs is None:
            return
        watch = self.ctx.board_watch
        now = self.clock()
        if now >= self._next_feeds - FEED_SLACK_S:
            self._next_feeds = now + 1.0 / self.profile.hz
            try:
                self.update_feeds(fs, watch.latest if watch.enabled else None)
            except Exception as exc:  # shown under the feeds; the panels keep updating
                self.feeds_error.content = f"**Feeds:** {md_text(describe_error(exc))}"
            else:
                if self.feeds_error.content:
                    self.feeds_error.content = ""
        self._follow_auto_span()
        if self.ctx.registration is not None:
            text = registration_text(self.ctx.registration.summary_text())
            if self.registration.content != text:
                self.registration.content = text
        balancer = self.ctx.balancer
        if balancer is not None:
            # set elsewhere (the REST API, Reset balance): shown. Compared with what this
            # panel saw last, not with the checkbox, which holds an operator's click before
            # its callback has applied it (writing it back would undo the click)
            if balancer.auto != self._balancer_auto:
                self._balancer_auto = balancer.auto
                self.auto_balance.value = balancer.auto
            status = balancer.status
            self.difference.content = status.difference_text()
            self.balance_md.content = balance_text(status, balancer.auto, self.pipeline)

    def update_feeds(self, newest: FrameSet, sighting: BoardSighting | None) -> None:
        """Each feed: the sighting's frame with its corners or reason when the sighting is
        recent (its age in the label from :data:`LAG_SHOWN_S`), else the newest frame as
        it is."""
        if not recent_sighting(sighting, newest):
            sighting = None
        lag_s = 0.0 if sighting is None else (newest.stamp_ns - sighting.frames.stamp_ns) / 1e9
        for name, handle in self.feeds.items():
            label = name
            if sighting is not None and name in sighting.frames.frames and lag_s >= LAG_SHOWN_S:
                label = f"{name} (board search: {lag_s:.0f} s ago)"
            if handle.label != label:
                handle.label = label
            if sighting is not None and name in sighting.frames.frames:
                frame = sighting.frames.frames[name]
                detection = sighting.detections.get(name)
            elif name in newest.frames:
                frame, detection = newest.frames[name], None
            else:
                continue
            outline = self.ctx.next_outline.get(name)
            now = (frame, detection, outline)
            shown = self._shown.get(name)
            if shown is not None and all(a is b for a, b in zip(shown, now, strict=True)):
                continue
            handle.image = feed_image(
                frame, detection, self.ctx.board.cols, self.profile.width_px, outline
            )
            self._shown[name] = now

    @property
    def feeds_shown(self) -> Mapping[str, tuple[Frame, Detection | None, np.ndarray | None]]:
        """What each feed shows now, by sensor name: (the frame drawn, its board detection
        drawn on it or None, the next view's outline drawn or None: (N, 2) full-image
        pixels). A feed with no image drawn yet (or since the bandwidth mode changed) is
        absent. A read-only view that follows the feeds."""
        return MappingProxyType(self._shown)


SPLIT = "both (split evenly)"


def registration_text(summary: str) -> str:
    """The Fusion folder's registration sigma (markdown) from
    :meth:`RegistrationWatch.summary_text <app.server.runtime.registration_watch.
    RegistrationWatch.summary_text>`: where a thermal value may land, 1-sigma, colour pixels
    (the ``registration`` mode draws it over the colour image on a 0-2 px scale)."""
    lines = [md_text(line) for line in summary.splitlines()]
    return "  \n".join(["**Registration σ** (colour px; mode registration: 0–2 px)", *lines])


def balance_text(status: BalanceStatus, auto: bool, pipeline: FusionPipeline) -> str:
    """The balance state, markdown: what is applied, what the newest frames say and why a
    refused estimate changed nothing."""
    applied = ", ".join(
        f"{md_text(name)} {r.balance_offset_k:+.2f} K"
        + (f" x{r.balance_gain:.3f}" if r.balance_gain != 1 else "")
        for name, r in pipeline.radiometry.items()
    )
    lines = [f"Balance applied: {applied} ({'automatic' if auto else 'manual'})"]
    e, f = status.estimate, status.filtered
    if status.waiting:
        lines.append(f"Estimate: {md_text(status.waiting)}")
    elif e is not None and not e.ok:
        lines.append(f"Estimate refused, balance unchanged: {md_text(e.reason)}")
    elif f is not None:
        gain = f"gain {f.gain:.3f}" if f.gain_fitted else "offset only"
        lines.append(
            f"Estimate (filtered): left - right {f.offset_k:+.2f} K, {gain}, "
            f"{f.n_inliers} points, scatter {f.mad_k:.2f} K"
        )
    return "  \n".join(lines)
