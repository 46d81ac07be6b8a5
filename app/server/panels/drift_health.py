"""The calibration's health at the top of the Calibration panel (issue 34 item 3).

One line, "Calibration health: thermal_left DRIFTED 0.31° (σ 0.01°); others ok" (or "ok:
every sensor within 0.15°", "checking… (3 instants)", why nothing is measured), from the
console's drift check (:class:`~app.server.runtime.drift_watch.DriftWatch`); while a camera
is drifted an alert box under it ("⚠ thermal_left has turned 0.31° against the rig: refine
or recalibrate": Viser has notifications per browser only, which die on reconnect, so the
panel carries it) and the Refine rig button, which turns the drifted cameras back, saves
the rig as the session's next version, puts it in use and starts the check again
(:meth:`DriftWatch.refine`; ``POST /api/drift/refine`` does the same). A refusal (a turn
beyond 2 degrees: recalibrate) is shown under the button and changes nothing.
"""

from __future__ import annotations

import html

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.drift_watch import (
    DriftWatch,
    alerts,
    health_summary,
    refine_text,
)
from trifuse.app.workflows.calib_session import CalibrationSession

ALERT_STYLE = (
    "background:#fff4e5;border-left:4px solid #d9480f;color:#862e00;padding:4px 8px;"
    "font-weight:600;font-size:0.9em;margin:2px 0"
)
"""The alert box: amber, a red-orange bar at its left."""


def health_md(summary: str) -> str:
    """The panel's health line (markdown) from :func:`health_summary`'s text."""
    return f"**Calibration health:** {md_text(summary)}"


def alert_html(lines: list[str]) -> str:
    """The alert box (HTML) of :func:`alerts`' lines; empty without any."""
    if not lines:
        return ""
    body = "<br>".join(html.escape(line) for line in lines)
    return f"<div role='alert' style='{ALERT_STYLE}'>{body}</div>"


class DriftHealth:
    """The health line, the alert and Refine rig, built in the folder open when it is made
    (the Calibration panel's, at its top); :meth:`tick` keeps them current. Without a
    drift check (``ctx.drift`` None) it builds nothing."""

    def __init__(self, ctx: ConsoleContext, session: CalibrationSession) -> None:
        self.ctx, self.session = ctx, session
        self.watch: DriftWatch | None = ctx.drift
        if self.watch is None:
            return
        gui = ctx.server.gui
        self.line = gui.add_markdown(health_md(health_summary(None)))
        self.alert = gui.add_html("", visible=False)
        self.refine = gui.add_button(
            "Refine rig",
            disabled=True,
            hint="Turn the drifted cameras back by the rotation measured; saved as the next "
            "rig version and put in use (at most 2°: beyond, recalibrate)",
        )
        self.message = gui.add_markdown("")
        self.refine.on_click(lambda _e: self.press())

    def press(self) -> None:
        """What Refine rig does: refine (:meth:`DriftWatch.refine`); what happened, or why
        not, shown under the button."""
        if self.watch is None:
            return
        try:
            result = self.watch.refine(self.session.save_rig, self.ctx.use_rig)
        except ValueError as exc:  # RefineRefused (beyond 2°), nothing drifted, not checked
            self.message.content = f"**Not refined:** {md_text(exc)}"
        except OSError as exc:  # the rig version could not be written
            self.message.content = f"**Not refined:** {md_text(describe_error(exc))}"
        else:
            text = refine_text(result)
            self.message.content = md_text(text[0].upper() + text[1:] + ".")
        self.tick()

    def tick(self) -> None:
        """The line, the alert and the button from the check's newest report."""
        if self.watch is None:
            return
        state = self.watch.state()
        text = health_md(health_summary(state, self.watch.waiting))
        if self.watch.error:
            text += f"  \nLast measure failed: {md_text(self.watch.error)}"
        if self.line.content != text:
            self.line.content = text
        box = alert_html(alerts(state))
        if self.alert.content != box:
            self.alert.content = box
        self.alert.visible = bool(box)
        self.refine.disabled = state is None or not state.report.drifted
