"""The calibration report as one self-contained HTML page, for a colleague to read and print.

``trifuse calibrate ... --report-html report.html``, the Calibration panel's "Download
report" and ``GET /api/calibrate/report.html`` all call :func:`render_report_html`: a pure
function of the ``report.json`` content (docs/FORMATS.md "Calibration report") and,
when the calibration result is at hand, its per-corner residuals
(:class:`calib.rig_result.CornerResiduals`). Without them (a ``report.json`` read back from
disk) the per-corner plots are left out and the page says so.

The page: summary and verdict; per sensor its intrinsics and distortion ± 1-sigma, pose
± 1-sigma, RMS, the views used and left out with the reason, a per-view RMS bar chart, a
per-corner residual scatter, a coverage heat map and the residual vectors over the image;
the relative pose of every pair of sensors; the cross-validation (two halves of the views
calibrated alone: per eye how far apart their fusions put a thermal value against distance,
and what their uncertainty predicts); the board polarity and any other decision the
report holds; the outliers; every view and sensor; the comparison with a true rig (when
the report has one); the command and the software versions.

Self-contained: plots are inline SVG (:mod:`report_svg`, no plotting library), styles
inline, no script, no font, image or link outside the page; a Content-Security-Policy meta tag
forbids any fetch. Laid out for A4 (each sensor starts a page when printed). Keys the
report gains later (a verdict, advice, decisions) are shown as they come: ``verdict`` and
``advice`` in the summary (top level) or at the top of their sensor's section, any other
key under "Decisions and other findings" or the sensor's "Other figures".

The page is put together here, with its entry points; its parts are in
:mod:`report_sections` (summary, cross-validation, decisions, outliers, views, truth, run),
:mod:`report_sensors` (a section per sensor, the pairs), :mod:`report_svg` (the plots) and
:mod:`report_markup` (numbers, tables, verdicts).
"""

from __future__ import annotations

import argparse
import platform
import shlex
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from trifuse.app.storage.atomic import atomic_write_text
from trifuse.app.workflows.report_markup import esc, html_id
from trifuse.app.workflows.report_sections import (
    comparison_section,
    cross_validation_section,
    decisions_section,
    outliers_section,
    report_board_text,
    run_section,
    summary_section,
    views_section,
)
from trifuse.app.workflows.report_sensors import pairs_section, sensor_section

if TYPE_CHECKING:
    from trifuse.app.workflows.calib_session import CalibrationJob
    from trifuse.calib.rig_result import CornerResiduals


CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
"""The page's Content-Security-Policy (a meta tag; the console's route sends it as a
header too): inline styles and data: images only, no script, nothing fetched."""


REPORT_HTML_NAME = "calibration-report.html"
"""The page's file name when the console sends it."""


_STYLE = """
@page { size: A4; margin: 14mm 12mm; }
* { box-sizing: border-box; }
body { font: 10pt/1.4 "DejaVu Sans", "Segoe UI", Helvetica, Arial, sans-serif; color: #222;
  max-width: 190mm; margin: 0 auto; padding: 6mm 4mm; }
h1 { font-size: 17pt; margin: 0 0 2mm; }
h2 { font-size: 13pt; border-bottom: 2px solid #333; margin: 7mm 0 2mm; break-after: avoid; }
h3 { font-size: 11pt; margin: 4mm 0 1.5mm; break-after: avoid; }
p { margin: 1mm 0 2mm; }
.sub { color: #555; }
table { border-collapse: collapse; margin: 1mm 0 3mm; font-variant-numeric: tabular-nums; }
th, td { padding: 1.5px 6px; border-bottom: 1px solid #ddd; text-align: left;
  vertical-align: top; }
th { border-bottom: 1.5px solid #888; font-weight: 600; }
td.n, th.n { text-align: right; } td.n { white-space: nowrap; }
tr { break-inside: avoid; }
.caption { color: #555; font-size: 9pt; margin: 2mm 0 0.5mm; break-after: avoid; }
.small { font-size: 8.5pt; }
.bad { color: #b00; } .good { color: #070; } .muted { color: #888; }
.box { border-left: 5px solid #888; background: #f5f5f5; padding: 2mm 4mm; margin: 2mm 0 3mm; }
.box-good { border-color: #2ca02c; } .box-bad { border-color: #d62728; }
.box-fair { border-color: #e0a030; }
.fair { color: #a06000; }
.box p { margin: 0.5mm 0; color: #222; }
figure { display: inline-block; vertical-align: top; margin: 1mm 3mm 3mm 0; break-inside: avoid; }
figcaption { font-size: 8.5pt; color: #555; max-width: 78mm; }
figure.wide figcaption { max-width: none; }
svg { max-width: 100%; height: auto; font-family: inherit; }
code { font-family: "DejaVu Sans Mono", Consolas, monospace; font-size: 8.5pt;
  overflow-wrap: anywhere; }
ul { margin: 1mm 0 2mm; padding-left: 6mm; }
dl { margin: 1mm 0; } dt { font-weight: 600; } dd { margin: 0 0 1mm 5mm; }
nav ol { columns: 2; margin: 1mm 0; }
a { color: #1f5fa0; text-decoration: none; }
@media print {
  body { padding: 0; max-width: none; }
  section.sensor { break-before: page; }
  nav { display: none; }
}
"""


def render_report_html(
    report: Mapping[str, Any],
    corners: CornerResiduals | None = None,
    command: str | None = None,
    versions: Mapping[str, str] | None = None,
    generated: str | None = None,
) -> str:
    """The calibration report as one self-contained HTML page.

    Args:
        report: ``report.json`` content (docs/FORMATS.md, "Calibration report").
        corners: the calibration's per-corner residuals (``CalibrationResult.corners``);
            None: the page has no per-corner plots and says so.
        command: how the calibration was run, shown as is.
        versions: software name -> version (:func:`software_versions`).
        generated: when, as text (e.g. ``2026-11-24 14:03``).

    Returns:
        The page (UTF-8 text). Nothing in it is fetched: no script, link or image outside it.
    """
    sensors = list(report.get("sensors") or {})
    capture = str(report.get("capture") or "")
    title = "Calibration report" + (f" – {Path(capture).name}" if capture else "")
    sub = [f"capture <code>{esc(capture)}</code>"] if capture else []
    if report.get("board"):
        sub.append(esc(report_board_text(report["board"])))
    if generated:
        sub.append(f"made {esc(generated)}")
    toc = [("summary", "Summary and verdict")]
    toc += [(f"sensor-{html_id(n)}", n) for n in sensors]
    body = [summary_section(report)]
    body += [sensor_section(report, n, i, corners) for i, n in enumerate(sensors)]
    for anchor, label, block in (
        ("pairs", "Relative poses", pairs_section(report)),
        ("cross-validation", "Cross-validation", cross_validation_section(report)),
        ("decisions", "Decisions and other findings", decisions_section(report)),
        ("outliers", "Outliers", outliers_section(report)),
        ("views", "Every view", views_section(report)),
        ("truth", "Against the true rig", comparison_section(report)),
        ("run", "How this was made", run_section(report, command, versions or {})),
    ):
        if block:
            toc.append((anchor, label))
            body.append(block)
    nav = (
        "<nav><ol>"
        + "".join(f"<li><a href='#{a}'>{esc(t)}</a></li>" for a, t in toc)
        + "</ol></nav>"
    )
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<meta http-equiv='Content-Security-Policy' content=\"{CSP}\">"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        "<meta name='generator' content='trifuse'>"
        f"<title>{esc(title)}</title><style>{_STYLE}</style></head><body>"
        f"<header><h1>{esc(title)}</h1><p class='sub'>{' · '.join(sub)}</p></header>"
        + nav
        + "\n".join(body)
        + "</body></html>\n"
    )


def software_versions() -> dict[str, str]:
    """Versions of what the calibration ran on: trifuse, Python, numpy, SciPy, OpenCV."""
    from importlib.metadata import PackageNotFoundError, version

    import cv2
    import scipy

    try:
        trifuse = version("trifuse")
    except PackageNotFoundError:
        trifuse = "(source tree)"
    return {
        "trifuse": trifuse,
        "Python": platform.python_version(),
        "numpy": np.__version__,
        "SciPy": scipy.__version__,
        "OpenCV": cv2.__version__,
    }


def command_line(args: argparse.Namespace, prog: str = "trifuse") -> str:
    """The command as it was run, rebuilt from its parsed arguments: the positional
    ``capture_dir`` then every option that is set (``--flag`` for a true switch)."""
    opts = vars(args)
    words = [prog, str(opts.get("command") or "calibrate")]
    if opts.get("capture_dir") is not None:
        words.append(str(opts["capture_dir"]))
    for key, value in opts.items():
        if key in ("func", "command", "capture_dir") or value is None or value is False:
            continue
        flag = "--" + key.replace("_", "-")
        words += [flag] if value is True else [flag, str(value)]
    return shlex.join(words)


def write_report_html(
    path: str | Path,
    report: Mapping[str, Any],
    corners: CornerResiduals | None = None,
    command: str | None = None,
) -> Path:
    """Render the page (:func:`render_report_html`, with this software's versions and the
    time now) and write it atomically; an existing file is kept (refused)."""
    page = render_report_html(
        report, corners, command, software_versions(), time.strftime("%Y-%m-%d %H:%M")
    )
    return atomic_write_text(path, page, overwrite=False)


def session_report_html(job: CalibrationJob) -> str:
    """The page of the console's finished calibration (the Calibration panel's download
    and ``GET /api/calibrate/report.html`` send the same).

    Raises:
        ValueError: no finished calibration (its state says why).
    """
    if job.state != "done" or job.report is None:
        raise ValueError(f"no finished calibration to report (state: {job.state})")
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime(job.finished or time.time()))
    corners = job.result.corners if job.result is not None else None
    command = f"the console's calibration session ({len(job.views)} views)"
    return render_report_html(job.report, corners, command, software_versions(), when)
