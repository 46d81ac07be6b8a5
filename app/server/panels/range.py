"""The console's Range calibration panel: the TOF's distance error before and after.

"Run range calibration" fits the TOF range correction (:mod:`calib.range_calibration`)
on the session's captured views, with the board poses from the rig in use, in the
session's background job; every 4th view is held out to validate it. The panel shows the
progress, the RMS error per accuracy region before and after on the held-out views (a
table and the bar chart of the method's figure 4), and offers to save the rig with the
correction as a new rig version and to fuse with it.
"""

from __future__ import annotations

import math

from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.workflows.calib_session import CalibrationSession, SessionError
from trifuse.app.workflows.range_run import region_chart
from trifuse.calib.errors import RigError
from trifuse.calib.range_calibration import RegionError


def region_table(holdout: list[RegionError], fit: list[RegionError]) -> str:
    """Markdown table: per region, pixels and RMS error before / after on held-out views
    (and after on the fitted views)."""
    lines = [
        "| region | pixels | before | after | ratio | fitted |",
        "|:--|--:|--:|--:|--:|--:|",
    ]
    for h, f in zip(holdout, fit, strict=True):
        label = "1-3" if h.region == 0 else str(h.region)
        if not h.pixels:
            lines.append(f"| {label} | 0 | – | – | – | – |")
            continue
        after_fit = f"{f.after_rms_mm:.1f}" if math.isfinite(f.after_rms_mm) else "–"
        lines.append(
            f"| {label} | {h.pixels} | {h.before_rms_mm:.1f} | **{h.after_rms_mm:.1f}** "
            f"| {h.ratio:.1f}x | {after_fit} |"
        )
    return "\n".join(lines) + "\n\nRMS error in mm; *fitted*: after, on the views fitted."


class RangePanel(Periodic):
    """Builds the Range calibration folder and follows the session's range job."""

    def __init__(
        self, ctx: ConsoleContext, session: CalibrationSession, rate_hz: float = 2.0
    ) -> None:
        super().__init__("range-panel", 1.0 / rate_hz)
        self.ctx, self.session = ctx, session
        gui = ctx.server.gui
        with gui.add_folder("Range calibration", expand_by_default=False):
            self.intro = gui.add_markdown(
                "Fits the TOF distance correction on the captured views (board poses from "
                "the rig in use); every 4th view is held out to check it."
            )
            self.run = gui.add_button("Run range calibration", color="green")
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.stage = gui.add_markdown("")
            self.table = gui.add_markdown("")
            self.chart = gui.add_image(region_chart([], ""), label="RMS error", visible=False)
            self.save = gui.add_button("Save rig with range correction", disabled=True)
            self.use = gui.add_button("Use the saved rig", disabled=True)
            self.message = gui.add_markdown("")
        self.run.on_click(lambda _e: self._act(self._start))
        self.save.on_click(lambda _e: self._act(self._save))
        self.use.on_click(lambda _e: self._act(self._use))
        self._shown: tuple | None = None

    def _act(self, action) -> None:
        try:
            self.message.content = action() or ""
        except (SessionError, KeyError, RigError, ValueError) as exc:
            self.message.content = f"**Not done:** {md_text(exc.args[0] if exc.args else exc)}"

    def _start(self) -> str:
        self.session.start_range_calibration(self.ctx.pipeline.rig)
        return ""

    def _save(self) -> str:
        v = self.session.save_range()
        return f"Saved **{md_text(v.name)}** ({md_text(v.path)})."

    def _use(self) -> str:
        name = self.session.range_job.saved_as
        if name is None:
            raise SessionError("save the rig first")
        self.ctx.use_rig(self.session.load_version(name))
        return f"The console now fuses with **{md_text(name)}** (TOF distances corrected)."

    def tick(self) -> None:
        job = self.session.range_job
        key = (job.state, job.stage, round(job.progress, 2), job.saved_as, id(job))
        if key == self._shown:
            return
        self._shown = key
        running = job.state == "running"
        self.run.disabled = running
        self.progress.visible = running
        self.progress.value = 100.0 * job.progress
        if job.state == "failed":
            self.stage.content = f"**Range calibration failed:** {md_text(job.error)}"
        elif running:
            self.stage.content = f"Range calibration: {md_text(job.stage)}"
        elif job.state == "done" and job.run is not None:
            run = job.run
            lo, hi = run.model.distance_range_m
            self.stage.content = (
                f"Fitted on {len(run.fit_views)} views, checked on {len(run.holdout_views)} "
                f"held-out views ({lo:.2f}-{hi:.2f} m) in {run.seconds:.1f} s; "
                f"{len(run.skipped)} view(s) not used. RMS distance error, held-out views:"
            )
            self.table.content = region_table(run.holdout, run.fit)
            self.chart.image = region_chart(run.holdout, "RMS distance error, held-out views")
            self.chart.visible = True
        else:
            self.stage.content = ""
        self.save.disabled = job.state != "done" or job.saved_as is not None
        self.use.disabled = job.saved_as is None
