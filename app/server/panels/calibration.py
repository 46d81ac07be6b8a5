"""The console's Calibration panel (Viser GUI) over a :class:`CalibrationSession`.

At its top, the calibration's health: whether each camera still sits where the rig in use
says, checked on the live pictures without a board, with an alert and Refine rig while one
has turned (:mod:`app.server.panels.drift_health`).

Capture (the newest frames, written at once) and auto-capture (steady, novel board
sightings, as ROS ``camera_calibration`` does), with the reason a pose is not taken shown
live under the checkbox (moving and how much in frame time, captured already and how near,
seen by which sensors, waiting for frames or for the views' searches:
:meth:`CalibrationSession.assess`); on the simulated head, auto-capture asks the board to
wait at each pose until it is captured (the scenario's ``capture_hold``, reached through the
source without importing it: a slow machine still gets every pose); coverage bars per
sensor; the views with
the board found or not per sensor; delete a view; run the calibration with progress; then
per-sensor RMS, the per-view error chart with "drop this view and calibrate again", the
1-sigma table, the verdicts, the cross-validation (two halves of the views calibrated
alone: per eye how far apart their fusions put a thermal value, against the prediction),
the board polarity found per sensor (which squares read dark/cold or
bright/hot, and how decisively) with any sensor left out and why (and, on the simulated
head, the errors against the ground truth); Save as a new rig version and use a saved
version.
"""

from __future__ import annotations

import html
from typing import Any

import numpy as np
import viser.uplot as uplot

from trifuse.app.server.markdown_text import md_cells, md_text
from trifuse.app.server.panels.drift_health import DriftHealth
from trifuse.app.server.panels.next_pose_overlay import NextPoseOverlay, verdict_md
from trifuse.app.server.runtime.board_sighting import BoardSighting
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.demand import Hold
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.workflows.calib_session import (
    CalibrationSession,
    CaptureVerdict,
    SessionError,
    ViewInfo,
)
from trifuse.app.workflows.cross_validation import cross_validation_lines
from trifuse.app.workflows.report_format import (
    POLARITY_PANEL_HEAD,
    TRUTH_HEAD,
    markdown_table,
    polarity_panel_note,
    polarity_panel_rows,
    sensor_colour,
    truth_rows,
    verdict_line,
)
from trifuse.app.workflows.report_html import REPORT_HTML_NAME, session_report_html
from trifuse.calib.coverage import PARAM_NAMES
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig
from trifuse.calib.rig_compare import compare_rigs
from trifuse.calib.rig_result import CalibrationResult

NONE = "(none)"


def coverage_html(bars: dict[str, tuple[float, float, float, float]], views: dict[str, int]) -> str:
    """A table of ROS-style bars: one row per sensor, X / Y / size / skew in [0, 1]."""
    head = "".join(f"<th style='font-weight:normal'>{n}</th>" for n in PARAM_NAMES)
    rows = []
    for sensor, values in bars.items():
        cells = []
        for v in values:
            pct = round(100 * min(1.0, max(0.0, v)))
            color = "#2ca02c" if v >= 1.0 else "#e0a030"
            cells.append(
                "<td><div style='background:#ddd;height:8px;width:48px'>"
                f"<div style='background:{color};height:8px;width:{pct}%'></div></div></td>"
            )
        rows.append(
            f"<tr><td>{html.escape(sensor)} ({views.get(sensor, 0)})</td>{''.join(cells)}</tr>"
        )
    return (
        "<table style='font-size:0.8em;border-spacing:4px 1px'>"
        f"<tr><th></th>{head}</tr>{''.join(rows)}</table>"
    )


def views_html(views: list[ViewInfo], sensors: list[str]) -> str:
    """The views as a compact table: per sensor ✓ board found, ✗ not, … still searching."""
    if not views:
        return (
            "<p style='font-size:0.85em'>No views yet: show the board, then Capture or "
            "Auto-capture.</p>"
        )
    head = "".join(
        f"<th style='font-weight:normal'>{html.escape(s).replace('_', '<br>')}</th>"
        for s in sensors
    )
    rows = []
    for v in views:
        marks = []
        for s in sensors:
            found = v.found(s) if s in v.sensors else False
            title = html.escape(v.detections[s].reason or "") if s in v.detections else ""
            mark = "…" if found is None else ("✓" if found else "✗")
            color = "#2ca02c" if found else ("#888" if found is None else "#d62728")
            marks.append(f"<td title='{title}' style='color:{color}'>{mark}</td>")
        rows.append(f"<tr><td>{html.escape(v.name)}</td>{''.join(marks)}</tr>")
    paletted = {s: fit.what for v in views for s, fit in v.palettes.items()}  # false colour
    return (
        f"<p style='font-size:0.85em;margin:0'>{len(views)} views</p>"
        "<div style='max-height:220px;overflow-y:auto'>"
        "<table style='font-size:0.75em;text-align:center;border-spacing:6px 0'>"
        f"<tr><th></th>{head}</tr>{''.join(rows)}</table></div>"
        + "".join(
            f"<p style='font-size:0.75em;margin:0'>{html.escape(s)}: false-colour images "
            f"({html.escape(what)}), read back for geometry; values not radiometric</p>"
            for s, what in paletted.items()
        )
    )


STALE_SEARCH_S = 1.0
"""The reason line says how old the searched frames were when they are older than this
(seconds of frame time behind the newest frame set: the board search lags)."""


def rms_chart(
    result: CalibrationResult, sensors: list[str]
) -> tuple[tuple[np.ndarray, ...], tuple[float, float]]:
    """The "RMS error per view" chart of ``result``: its data and its y range.

    Returns:
        (data, (y_min, y_max)): data is the views' numbers (x; a view named otherwise
        counts by its place) and, per sensor of ``sensors`` in that order, its RMS
        reprojection error in each view, pixels (NaN where the sensor has none in that
        view: not seen, left out, or not calibrated at all). The y range runs from 0 to a
        little above the largest error: uPlot cannot range an axis itself over a series
        with no number in it (the whole chart stays empty), so the range is given.
    """
    views = sorted(result.views)
    x = np.array([int(v) if v.isdigit() else i for i, v in enumerate(views, 1)], float)
    ys = tuple(
        np.array(
            [result.views[v][s].rms_px if s in result.views[v] else np.nan for v in views],
            dtype=np.float64,
        )
        for s in sensors
    )
    finite = [float(np.nanmax(y)) for y in ys if np.isfinite(y).any()]
    top = max(finite, default=0.0)
    return (x, *ys), (0.0, 1.1 * top if top > 0 else 1.0)


class CalibrationPanel(Periodic):
    """Builds the Calibration folder and keeps it current (refreshed at ``rate_hz``)."""

    def __init__(
        self, ctx: ConsoleContext, session: CalibrationSession, rate_hz: float = 2.0
    ) -> None:
        super().__init__("calibration-panel", 1.0 / rate_hz)
        self.ctx, self.session = ctx, session
        self.sensors = list(ctx.pipeline.rig.names)
        gui = ctx.server.gui
        with gui.add_folder("Calibration"):
            self.health = DriftHealth(ctx, session)  # drift: line, alert, Refine rig
            self.seen = gui.add_markdown("Board: not searched yet")
            self.capture = gui.add_button("Capture", hint="Write the newest frames as a view")
            self.auto = gui.add_checkbox(
                "Auto-capture",
                False,
                hint="Take the board whenever it is steady and at a new pose",
            )
            self.why = gui.add_markdown("")  # auto-capture: why the pose is not taken
            self.message = gui.add_markdown("")
            self.next_pose = NextPoseOverlay(ctx, session)  # where to hold the board next
            self.coverage = gui.add_html(coverage_html({s: (0, 0, 0, 0) for s in self.sensors}, {}))
            self.views_html = gui.add_html(views_html([], self.sensors))
            self.view_pick = gui.add_dropdown("View", (NONE,))
            self.delete = gui.add_button("Delete view", color="red")
            self.run = gui.add_button("Run calibration", color="green")
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.stage = gui.add_markdown("")
            self.results = gui.add_markdown("")
            self.chart = gui.add_uplot(
                (np.zeros(1), *(np.full(1, np.nan) for _ in self.sensors)),
                self._series(),
                title="RMS error per view (px)",
                scales={"x": uplot.Scale(time=False), "y": uplot.Scale(auto=True)},
                aspect=1.6,
                visible=False,
            )
            self.drop = gui.add_button("Drop view and calibrate again", visible=False)
            self.download = gui.add_button(
                "Download report",
                hint="The calibration report as one HTML page to read, print or send",
                visible=False,
            )
            self.save = gui.add_button("Save rig", disabled=True)
            self.version_pick = gui.add_dropdown("Saved rig", (NONE,))
            self.use = gui.add_button("Use this rig")
        self._auto_hold: Hold | None = None  # the board search while auto-capture is on
        # the simulated calibration board's wait for captures (None: another source)
        self.capture_hold = getattr(getattr(ctx.source, "scenario", None), "capture_hold", None)
        self.auto.on_update(lambda _e: self._want_board(bool(self.auto.value)))
        self.capture.on_click(lambda _e: self._act(self._capture))
        self.delete.on_click(lambda _e: self._act(self._delete))
        self.run.on_click(lambda _e: self._act(self._calibrate))
        self.drop.on_click(lambda _e: self._act(self._drop))
        self.download.on_click(lambda e: self.send_report(e.client))
        self.save.on_click(lambda _e: self._act(self._save))
        self.use.on_click(lambda _e: self._act(self._use))
        self._dirty = True
        self._shown_job: object = None
        session.on_change.append(self._mark_dirty)
        ctx.board_watch.on_sighting = self._on_sighting
        self._saved_rigs: dict[str, Rig] = {}
        ctx.rig_choices = self._rig_choices

    # -- actions --------------------------------------------------------------------------

    def send_report(self, client) -> None:
        """What Download report does: send the finished calibration's report page to the
        browser ``client``; what happened, or why not, shown in :attr:`message`."""
        self._act(lambda: self._download(client))

    def _act(self, action) -> None:
        """Run a button's action; its refusal is shown, never raised into Viser."""
        try:
            self.message.content = action() or ""
        except (SessionError, KeyError, RigError, ValueError) as exc:
            self.message.content = f"**Not done:** {md_text(exc.args[0] if exc.args else exc)}"
        self._dirty = True

    def _capture(self) -> str:
        fs = self.ctx.pipeline.latest_set
        if fs is None:
            raise SessionError("no frames yet")
        name = self.session.take(fs).name
        self._release(fs.stamp_ns)
        return f"Captured view {md_text(name)}."

    def _release(self, stamp_ns: int) -> None:
        """The simulated board need not wait at the pose of ``stamp_ns`` any more."""
        if self.capture_hold is not None:
            self.capture_hold.release(stamp_ns)

    def _delete(self) -> str:
        name = self.view_pick.value
        if name == NONE:
            raise SessionError("choose a view first")
        moved = self.session.delete(name)
        return f"Deleted view {md_text(name)} (kept in {md_text(moved)})."

    def _calibrate(self) -> str:
        self.session.start_calibration()
        return ""

    def _drop(self) -> str:
        name = self.view_pick.value
        if name == NONE:
            raise SessionError("choose a view first")
        self.session.delete(name)
        self.session.start_calibration()
        return f"Dropped view {md_text(name)}; calibrating again."

    def _download(self, client) -> str:
        """Send the finished calibration's report page (as GET /api/calibrate/report.html)."""
        page = session_report_html(self.session.job).encode("utf-8")
        client.send_file_download(REPORT_HTML_NAME, page, save_immediately=True)
        return f"Report sent: {REPORT_HTML_NAME} ({len(page) // 1024} kB)."

    def _save(self) -> str:
        v = self.session.save()
        return f"Saved **{md_text(v.name)}** ({md_text(v.path)})."

    def _use(self) -> str:
        name = self.version_pick.value.split(" ")[0]
        if name == NONE:
            raise SessionError("choose a saved rig first")
        self.ctx.use_rig(self.session.load_version(name))
        return f"The console now fuses with **{md_text(name)}**."

    def _want_board(self, on: bool) -> None:
        """Auto-capture needs the board search whether or not a browser is connected, and
        asks the simulated board to wait at each pose until it is captured."""
        if self.capture_hold is not None:
            self.capture_hold.waiting = on
        if on and self._auto_hold is None:
            self._auto_hold = self.ctx.demand.board.hold()
            self.why.content = self._waiting_text()
        elif not on and self._auto_hold is not None:
            self._auto_hold, hold = None, self._auto_hold
            hold.release()
            self.why.content = ""

    def _on_sighting(self, s: BoardSighting) -> None:
        """Auto-capture (in the board watch's thread): take the sighting or say why not."""
        self._sighting_text(s)
        if not self.auto.value:
            return
        verdict = self.session.assess(s.detections, s.steady, self._motion_text(s), s.T_rig_board)
        if not verdict.take:
            if verdict.kind in ("captured", "not seen"):  # nothing to wait for there
                self._release(s.frames.stamp_ns)
            self.why.content = self._why_text(s, verdict)
            return
        try:
            view = self.session.take(s.frames)
        except SessionError as exc:
            self.message.content = f"**Auto-capture failed:** {md_text(exc)}"
            return
        self._release(s.frames.stamp_ns)
        self.why.content = f"Auto-capture took view {md_text(view.name)}."
        self.message.content = (
            f"Auto-captured view {md_text(view.name)} ({md_text(verdict.reason)})."
        )

    @staticmethod
    def _motion_text(s: BoardSighting) -> str:
        """How the board moved, in words (the reason when it is not steady)."""
        if s.motion is None:
            return "waiting for frames: a second look at the board tells whether it is still"
        return s.motion.describe()

    def _why_text(self, s: BoardSighting, verdict: CaptureVerdict) -> str:
        """The reason line: why the sighting is not taken, which sensors see the board,
        how old the searched frames are when the search lags, the simulated board's
        wait."""
        parts = [verdict.reason]
        rig = [n for n in self.sensors if n in s.frames.frames]
        found = [n for n in rig if s.detections.get(n) is not None and s.detections[n].found]
        if found and len(found) < len(rig):
            missing = ", ".join(n for n in rig if n not in found)
            parts.append(f"seen by {len(found)} of {len(rig)} sensors (missing {missing})")
        newest = self.ctx.pipeline.latest_set
        if newest is not None:
            lag_s = (newest.stamp_ns - s.frames.stamp_ns) / 1e9
            if lag_s > STALE_SEARCH_S:
                parts.append(f"searched frames {lag_s:.1f} s old")
        status = self.capture_hold.status() if self.capture_hold is not None else None
        if status:
            parts.append(status)
        return "**Not taken:** " + md_text("; ".join(parts))

    def _waiting_text(self) -> str:
        """The reason line before the first sighting while auto-capture is on."""
        if self.ctx.pipeline.latest_set is None:
            why = "waiting for frames: none has arrived yet"
        else:
            why = "waiting for frames: the board search has not finished a look yet"
        return "**Not taken:** " + md_text(why)

    def _rig_choices(self) -> dict[str, Rig]:
        """Saved versions by label; each file is read once (versions are never rewritten)."""
        out = {}
        for v in self.session.versions():
            if v.name not in self._saved_rigs:
                try:
                    self._saved_rigs[v.name] = self.session.load_version(v.name)
                except RigError:
                    continue
            out[v.label] = self._saved_rigs[v.name]
        return out

    def _mark_dirty(self) -> None:
        self._dirty = True

    # -- refresh --------------------------------------------------------------------------

    def _sighting_text(self, s: BoardSighting) -> None:
        found = s.found
        if not found:
            self.seen.content = "Board: not seen"
            return
        if s.steady:
            state = "steady"
        elif s.motion is None or not s.motion.decided:
            state = "waiting for frames"
        else:
            state = "moving"
        self.seen.content = f"Board ({state}): seen by {md_text(', '.join(found))}"

    def tick(self) -> None:
        self.health.tick()
        self.next_pose.tick()
        if self.auto.value and self._auto_hold is not None:
            latest = self.ctx.board_watch.latest
            if latest is None:
                self.why.content = self._waiting_text()
        if not self._dirty:
            return
        self._dirty = False
        views = self.session.views()
        cov = self.session.coverage()
        self.coverage.content = coverage_html(
            {s: c.progress for s, c in cov.items()}, {s: c.n_views for s, c in cov.items()}
        )
        self.views_html.content = views_html(views, self.sensors)
        names = tuple(v.name for v in views) or (NONE,)
        if tuple(self.view_pick.options) != names:
            keep = self.view_pick.value
            self.view_pick.options = names
            if keep in names:
                self.view_pick.value = keep
        versions = tuple(v.label for v in self.session.versions()) or (NONE,)
        if tuple(self.version_pick.options) != versions:
            self.version_pick.options = versions
            self.version_pick.value = versions[-1]
        # nothing to act on: no view to delete or calibrate, no saved rig to use
        self.delete.disabled = not views
        self.use.disabled = versions == (NONE,)
        self._show_job(len(views))

    def _series(self, labels: list[str] | None = None) -> tuple[uplot.Series, ...]:
        """The chart's series: the view number, then one per sensor (``labels``: their
        legend, default the sensors' names)."""
        return (
            uplot.Series(label="view"),
            *(
                uplot.Series(
                    label=label,
                    stroke="rgb({}, {}, {})".format(*sensor_colour(i)),
                    width=1.5,
                    points={"show": True, "size": 5},
                )
                for i, label in enumerate(labels or self.sensors)
            ),
        )

    def _show_job(self, n_views: int) -> None:
        """The calibration job's state; ``n_views``: the session's views now."""
        job = self.session.job
        running = job.state == "running"
        self.run.disabled = running or n_views == 0
        self.progress.visible = running
        self.progress.value = 100.0 * job.progress
        self.save.disabled = job.state != "done" or job.saved_as is not None
        done = job.state == "done" and job.result is not None
        # the results go out before the line that says they are there (a browser that
        # reads "Calibrated" finds them)
        if not done:
            self.results.content = ""
        elif self._shown_job is not job:
            self._shown_job = job
            self.results.content = self._results_md(job.result, job.report)
            self._chart(job.result)
        self.chart.visible = self.drop.visible = self.download.visible = done
        if job.state == "idle":
            self.stage.content = ""
        elif running:
            self.stage.content = f"Calibrating {len(job.views)} views: {md_text(job.stage)}"
        elif job.state == "failed":
            self.stage.content = f"**Calibration failed:** {md_text(job.error)}"
        else:
            took = (job.finished or 0) - (job.started or 0)
            saved = f", saved as **{md_text(job.saved_as)}**" if job.saved_as else ""
            self.stage.content = f"Calibrated {len(job.views)} views in {took:.0f} s{saved}."

    def _results_md(self, result, report: dict[str, Any] | None = None) -> str:
        """Per-sensor RMS and 1-sigma, the verdicts, the cross-validation's line per eye
        (from ``report``, the job's report); on the simulated head a second table of errors
        against the ground truth."""
        truth = self.ctx.ground_truth_rig
        lines = [
            f"Overall RMS **{result.rms_px:.3f} px**, reference {md_text(result.reference)}.",
            "",
            "| sensor | views | RMS px | σ fx px | σ rot ° | σ trans mm |",
            "|---|---|---|---|---|---|",
        ]
        for name, s in result.sensors.items():
            sig = s.sigma
            rot = float(np.linalg.norm(sig.get("rotation_deg", [0, 0, 0])))
            trans = 1000 * float(np.linalg.norm(sig.get("translation_m", [0, 0, 0])))
            lines.append(
                f"| {md_text(name)} | {s.views_used}/{s.views_detected} | {s.rms_px:.3f} | "
                f"{sig.get('fx', 0.0):.2f} | {rot:.3f} | {trans:.2f} |"
            )
        for name, s in result.intrinsics_only.items():  # calibrated alone: no pose
            lines.append(
                f"| {md_text(name)} | {s.views_used}/{s.views_detected} | {s.rms_px:.3f} | "
                f"{s.sigma.get('fx', 0.0):.2f} | pose unknown | |"
            )
        if result.verdict is not None:
            lines += ["", *verdict_md(result.verdict.as_dict())]
        if cv := cross_validation_lines((report or {}).get("cross_validation")):
            lines += ["", *(f"- {md_text(line)}" for line in cv)]
        if result.polarity:
            pol = {n: p.as_dict() for n, p in result.polarity.items()}
            lines += [
                "",
                f"**Board polarity per sensor** ({md_text(polarity_panel_note(pol))}):",
                "",
                *markdown_table(POLARITY_PANEL_HEAD, md_cells(polarity_panel_rows(pol))),
            ]
        if result.intrinsics_only:
            lines.append("")
            lines += [
                f"- **{md_text(n)}: intrinsics only:** {md_text(s.pose_unknown)}"
                for n, s in result.intrinsics_only.items()
            ]
        if result.excluded_sensors:
            lines.append("")
            lines += [
                f"- **{md_text(s)} not calibrated:** {md_text(why)}"
                for s, why in result.excluded_sensors.items()
            ]
        if result.notes:
            lines.append("")
            lines += [f"- Note: {md_text(note)}" for note in result.notes]
        if truth is not None:
            lines += ["", *self._truth_md(result.rig(), truth)]
        return "\n".join(lines)

    @staticmethod
    def _truth_md(rig: Rig, truth: Rig) -> list[str]:
        """The errors against the ground truth (calib.rig_compare): per sensor its pose
        relative to the truth's reference sensor and its focal lengths, pass/fail against
        the calibration targets, and the verdict over every pair of sensors."""
        try:
            cmp = compare_rigs(rig, truth)
        except ValueError as exc:
            return [f"Not compared with the ground truth: {md_text(exc)}"]
        reference = truth.reference if truth.reference in cmp.intrinsics else rig.reference
        return [
            "Error against the simulated head's ground truth (poses relative to "
            f"{md_text(reference)}):",
            "",
            *markdown_table(TRUTH_HEAD, md_cells(truth_rows(cmp, reference))),
            "",
            md_text(verdict_line(cmp)),
        ]

    def _chart(self, result: CalibrationResult) -> None:
        """Per-view RMS of every sensor against the view number (:func:`rms_chart`; a
        sensor without any is labelled so); the worst view is preselected for "Drop
        view"."""
        data, y_range = rms_chart(result, self.sensors)
        labels = [
            s if np.isfinite(y).any() else f"{s} (none)"
            for s, y in zip(self.sensors, data[1:], strict=True)
        ]
        # new series and scales make the browser build the chart anew, with this data
        self.chart.series = self._series(labels)
        self.chart.scales = {
            "x": uplot.Scale(time=False),
            "y": uplot.Scale(auto=False, range=y_range),
        }
        self.chart.data = data
        views = sorted(result.views)
        if views:
            self.view_pick.value = max(
                views, key=lambda v: max((e.rms_px for e in result.views[v].values()), default=0)
            )
