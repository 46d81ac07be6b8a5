"""The console's Source panel (Viser GUI): what is playing, replay controls, recording.

Shows the source's description, each sensor's delivered frame rate, one line per sensor
that is not ok (silent, no frame yet, failing: :mod:`app.server.runtime.sensor_health`), the
stream's rates (:func:`stream_text`: new pictures and frames published per second, the same
figures as the viewer's, and why pictures repeat), missing sensors and errors. Every rate is
counted over the last few seconds (:data:`app.server.runtime.rates.RATE_WINDOW_S`). For a replay:
a play/pause button, a position slider that follows the replay (and leaves the operator's
hand alone while it drags) and a speed slider (0.25x-4x). For every source: Record / Stop
recording, which records the frames the console receives to
``<workdir>/recordings/<time>.mcap`` (see :mod:`app.recording.recorder`), with the
file's size and duration while it grows; "Record fused video" (off by default: encoding
costs about 9 ms of CPU per 2560 x 960 picture, a quarter of a core at 30 pictures/s, and
the console keeps fusing while it records, about 23 ms a picture when nobody watches) makes
the next recordings also keep the fused stereo picture as H.264 (``/fused/video``, which
Foxglove plays).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import viser

from trifuse.app.errors import ControlError
from trifuse.app.recording.recorder import RecordingState
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.server.runtime.rates import RatesSnapshot
from trifuse.app.server.runtime.sensor_health import SensorHealth
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.settings_spec import REPLAY_RATE
from trifuse.app.sources.capabilities import notes_of

HOLD_S = 1.5
"""After the operator moves a slider, the panel leaves it alone for this long (seconds)."""


def human_bytes(n: int) -> str:
    """``n`` bytes as ``"812 kB"`` / ``"12.3 MB"`` / ``"1.20 GB"`` (powers of 1000)."""
    if n < 1_000_000:
        return f"{n / 1000:.0f} kB"
    if n < 1_000_000_000:
        return f"{n / 1e6:.1f} MB"
    return f"{n / 1e9:.2f} GB"


def _short(path: str | None) -> str:
    """``recordings/NAME.mcap`` of a recording's path."""
    if not path:
        return ""
    p = Path(path)
    return f"{p.parent.name}/{p.name}"


def recording_text(r: RecordingState) -> str:
    """The recording's line(s) in the panel (markdown)."""
    if not r.available:
        return f"Recording unavailable: {md_text(r.error)}"
    if r.active:
        head = "Finishing" if r.stopping else "**● Recording**"
        text = (
            f"{head} {md_text(_short(r.path))}  \n{human_bytes(r.size_bytes)}, "
            f"{r.duration_s:.1f} s, {r.frames_written} frames"
        )
        if r.frames_dropped:
            text += f", **{r.frames_dropped} dropped** (the writer fell behind)"
        text += video_text(r)
    elif r.files:
        names = ", ".join(md_text(_short(f)) for f in r.files)
        text = (
            f"Saved {names}  \n{human_bytes(r.size_bytes)}, {r.duration_s:.1f} s, "
            f"{r.frames_written} frames"
        )
        if r.frames_dropped:
            text += f", {r.frames_dropped} dropped"
        text += video_text(r)
    else:
        text = "Not recording. Record saves what the console receives to `recordings/`."
    if r.frames_rejected:
        text += f"  \n{r.frames_rejected} frames not in the rig were skipped"
    if r.error:
        text += f"  \n**Error:** {md_text(r.error)}"
    return text


def video_text(r: RecordingState) -> str:
    """The fused video's part of the recording's line ('' without it)."""
    if not r.fused_video:
        return ""
    text = f"; fused video: {r.video_frames_written} pictures"
    if r.video_frames_skipped:
        text += f" ({r.video_frames_skipped} skipped)"
    if r.video_error:
        text += " (**stopped**)"
    return text


REPEAT_WHY = {
    "simulated": "the simulated head holds each rendered pose for several frames, fused once",
}
"""Why a source's pictures repeat, by source kind (other kinds: "their input did not
change")."""


def stream_text(
    rates: RatesSnapshot, kind: str, paused: bool, frames_out: int, pictures_out: int
) -> str:
    """The stream's line(s) in the panel (markdown): new pictures and published frames per
    second over the rates' window, the totals, and why pictures repeat when they do."""
    if paused:
        return f"Fused: **paused**, {frames_out} frames published ({pictures_out} new pictures)"
    text = (
        f"Fused: **{rates.new_fps:.1f} fps** new pictures, stream **{rates.stream_fps:.1f} fps** "
        f"(last {rates.window_s:g} s; {pictures_out} new of {frames_out} frames)"
    )
    repeat = rates.repeat_fps
    if repeat >= 0.05:
        why = REPEAT_WHY.get(kind, "their input did not change")
        text += f"  \n{repeat:.1f} fps repeat the previous picture: {why}"
    return text


def health_text(health: dict[str, SensorHealth]) -> str:
    """One markdown line per sensor that is not ok (e.g. ``thermal_right: silent for
    12 s``); '' when all are."""
    return "  \n".join(f"⚠ {md_text(h.line())}" for h in health.values() if not h.ok)


class SourcePanel(Periodic):
    """Builds the Source folder and refreshes it ``refresh_hz`` times a second.

    Args:
        ctx: the console (its Viser server; build this panel before the others so that it
            comes first).
        control: the source's state and controls (shared with the REST API).
        refresh_hz: display updates per second.
        clock: monotonic seconds, for how long a slider the operator moved is left alone
            (tests pass their own).
    """

    def __init__(
        self,
        ctx: ConsoleContext,
        control: SourceControl,
        refresh_hz: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__("source-panel", 1.0 / refresh_hz)
        server = ctx.server
        self.server, self.control = server, control
        self._clock = clock
        self._hold_until = {"position": 0.0, "rate": 0.0}
        gui = server.gui
        state = control.source_state()
        with gui.add_folder("Source"):
            self.what = gui.add_markdown(
                f"**{md_text(state.kind)}**: {md_text(control.description)}"
            )
            self.play = self.position = self.rate = None
            if control.is_replay:
                duration = state.duration_s or 0.0
                self._slider_max_s = math.floor(duration * 100) / 100  # never past the end
                step = 0.1 if duration >= 5.0 else 0.01
                self.play = gui.add_button(
                    "Pause", icon=viser.Icon.PLAYER_PAUSE, hint="Pause or continue the replay"
                )
                self.position = gui.add_slider(
                    "Position (s)",
                    0.0,
                    self._slider_max_s,
                    step,
                    0.0,
                    hint="Where the replay is, seconds from the recording's start; drag to seek",
                )
                self.rate = gui.add_slider(
                    "Speed (x)",
                    *REPLAY_RATE.slider(),
                    float(state.rate or 1.0),
                    marks=((0.25, "¼"), (1.0, "1"), (2.0, "2"), (4.0, "4")),
                    hint="Replay speed, times real time",
                )
                self.play.on_click(lambda _e: self._toggle_play())
                self.position.on_update(self._on_position)
                self.rate.on_update(self._on_rate)
            self.rates = gui.add_markdown("Waiting for frames")
            self.record = gui.add_button(
                "Record",
                icon=viser.Icon.PLAYER_RECORD,
                color="red",
                hint="Record what the console receives to the work directory's recordings/",
                disabled=control.recorder is None,
            )
            self.record.on_click(lambda _e: self._toggle_record())
            self.record_video = gui.add_checkbox(
                "Record fused video",
                initial_value=control.fused_video,
                hint="Recordings started from now on also keep the fused stereo picture as "
                "H.264 video (/fused/video, 10 Mbit/s, a key frame every second; Foxglove "
                "plays it). Encoding costs about 9 ms of CPU per picture (a quarter of a "
                "core at 30 pictures/s), and the console keeps fusing while it records.",
                disabled=control.recorder is None,
            )
            self.record_video.on_update(self._on_record_video)
            self.recording = gui.add_markdown(recording_text(control.recording_state()))
            self.message = gui.add_markdown("")
        self.tick()

    # -- operator actions ---------------------------------------------------------------

    def _toggle_play(self) -> None:
        try:
            st = self.control.source_state()
            st = self.control.resume() if st.paused else self.control.pause()
        except ControlError as exc:
            self.message.content = f"**Not done:** {md_text(exc)}"
            return
        self._show_paused(bool(st.paused))

    def _on_position(self, event: viser.GuiEvent) -> None:
        if event.client is None or self.position is None:
            return  # the panel's own update
        self._hold_until["position"] = self._clock() + HOLD_S
        try:
            duration = self.control.source_state().duration_s or 0.0
            self.control.seek(min(max(float(self.position.value), 0.0), duration))
        except (ControlError, ValueError) as exc:
            self.message.content = f"**Not done:** {md_text(exc)}"

    def _on_rate(self, event: viser.GuiEvent) -> None:
        if event.client is None or self.rate is None:
            return
        self._hold_until["rate"] = self._clock() + HOLD_S
        try:
            self.control.set_rate(float(self.rate.value))
        except (ControlError, ValueError) as exc:
            self.message.content = f"**Not done:** {md_text(exc)}"

    def _on_record_video(self, _event: viser.GuiEvent) -> None:
        self.control.fused_video = bool(self.record_video.value)

    def _toggle_record(self) -> None:
        self.record.disabled = True
        try:
            if self.control.recording_state().active:
                state = self.control.stop_recording()
            else:
                state = self.control.start_recording()
            self.message.content = ""
        except (ControlError, OSError, ValueError) as exc:
            self.message.content = f"**Not done:** {md_text(exc)}"
            state = self.control.recording_state()
        finally:
            self.record.disabled = self.control.recorder is None
        self._show_recording(state)

    # -- display ------------------------------------------------------------------------

    def _show_paused(self, paused: bool) -> None:
        if self.play is None:
            return
        label = "Play" if paused else "Pause"
        if self.play.label != label:
            self.play.label = label
            self.play.icon = viser.Icon.PLAYER_PLAY if paused else viser.Icon.PLAYER_PAUSE

    def _show_recording(self, r: RecordingState) -> None:
        label = "Stop recording" if r.active else "Record"
        if self.record.label != label:
            self.record.label = label
            self.record.icon = viser.Icon.PLAYER_STOP if r.active else viser.Icon.PLAYER_RECORD
        locked = r.active or self.control.recorder is None  # applies to the next recording
        if self.record_video.disabled != locked:
            self.record_video.disabled = locked
        text = recording_text(r)
        if self.recording.content != text:
            self.recording.content = text

    def _rates_text(self) -> str:
        c = self.control
        status = c.pipeline.status
        rates = c.rates_hz()
        dropped = c.source_state().dropped  # a replay keeping real time
        extra = " dropped to keep real time |" if dropped else ""
        lines = ["| sensor | Hz |" + extra, "| :--- | ---: |" + (" ---: |" if dropped else "")]
        lines += [
            f"| {md_text(name)} | {hz:.1f} |" + (f" {dropped.get(name, 0)} |" if dropped else "")
            for name, hz in rates.items()
        ]
        text = "\n".join(lines) if rates else "No per-sensor rates (the source is not tapped)"
        sick = health_text(c.sensor_health())
        if sick:
            text += "\n\n" + sick
        text += "\n\n" + stream_text(
            c.stream_rates(), c.kind, c.paused, status.frames_out, status.pictures_out
        )
        if status.missing:
            text += "\n\nMissing: " + "; ".join(
                f"{md_text(name)} ({md_text(why)})" for name, why in sorted(status.missing.items())
            )
        if status.error:
            text += f"\n\n**Error:** {md_text(status.error)}"
        notes = notes_of(c.source)
        if notes:
            text += "\n\nNotes: " + "; ".join(md_text(n) for n in notes)
        return text

    def tick(self) -> None:
        c = self.control
        st = c.source_state()
        now = self._clock()
        if st.kind == "replay" and self.position is not None and self.rate is not None:
            self._show_paused(bool(st.paused))
            if now >= self._hold_until["position"]:
                pos = min(max(st.position_s or 0.0, 0.0), self._slider_max_s)
                self.position.value = round(pos, 2)
            if now >= self._hold_until["rate"] and st.rate is not None:
                self.rate.value = st.rate
        text = self._rates_text()
        if self.rates.content != text:
            self.rates.content = text
        self._show_recording(c.recording_state())
