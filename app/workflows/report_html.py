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
the relative pose of every pair of sensors; the board polarity and any other decision the
report holds; the outliers; every view and sensor; the comparison with a true rig (when
the report has one); the command and the software versions.

Self-contained: plots are inline SVG written here (no plotting library), styles inline,
no script, no font, image or link outside the page; a Content-Security-Policy meta tag
forbids any fetch. Laid out for A4 (each sensor starts a page when printed). Keys the
report gains later (a verdict, advice, decisions) are shown as they come: ``verdict`` and
``advice`` in the summary (top level) or at the top of their sensor's section, any other
key under "Decisions and other findings" or the sensor's "Other figures".
"""

from __future__ import annotations

import argparse
import html
import math
import platform
import re
import shlex
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from trifuse.app.storage.atomic import atomic_write_text
from trifuse.app.workflows.report_format import (
    INTRINSICS_HEAD,
    POLARITY_HEAD,
    coverage_sentence,
    polarity_caption,
    polarity_rows,
    sensor_colour,
)
from trifuse.calib.board import POLARITY_KEYS, board_from_dict
from trifuse.calib.coverage import PARAM_NAMES
from trifuse.calib.numbers import is_int_or_float
from trifuse.calib.transforms import rotation_angle_deg, rvec_from_rotation

if TYPE_CHECKING:
    from trifuse.app.workflows.calib_session import CalibrationJob
    from trifuse.calib.rig_result import CornerResiduals

CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
"""The page's Content-Security-Policy (a meta tag; the console's route sends it as a
header too): inline styles and data: images only, no script, nothing fetched."""

KNOWN_KEYS = frozenset(
    {
        "format",
        "reference",
        "board",
        "rms_px",
        "seconds",
        "sensors",
        "sensors_intrinsics_only",
        "excluded_sensors",
        "polarity",
        "notes",
        "views",
        "outliers",
        "board_poses",
        "capture",
        "detections",
        "comparison",
        "verdict",
        "advice",
        "min_views",
    }
)
"""Top-level report keys with a section of their own; any other is shown generically."""

SENSOR_KEYS = frozenset(
    {
        "modality",
        "image_size",
        "views_detected",
        "views_used",
        "rms_px",
        "worst_view",
        "intrinsics",
        "distortion",
        "T_rig_sensor",
        "sigma",
        "coverage",
        "verdict",
        "advice",
    }
)
"""Per-sensor keys with a place of their own; any other goes under "Other figures"."""

REPORT_HTML_NAME = "calibration-report.html"
"""The page's file name when the console sends it."""

MAX_CORNER_ROWS = 100
"""Outlier corners listed one by one; the rest are counted (report.json has them all)."""

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
USED, LEFT_VIEW, LEFT_CORNER, GREY = "#3b6ea5", "#e0a000", "#d62728", "#888"
"""Plot colours, the same for every sensor: a corner or view used, a view left out (an
outlier), a corner left out alone (an outlier corner), the board not found."""
LONGEST_VECTOR = 24.0
"""Longest residual vector drawn (SVG px): an outlier's would cross the image."""

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


# -- numbers and text -----------------------------------------------------------------------


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _finite(x: Any) -> bool:
    return is_int_or_float(x) and math.isfinite(x)


def _f(x: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals; ``–`` when undefined."""
    return f"{x:.{digits}f}" if _finite(x) else "–"


def _g(x: Any) -> str:
    """A number of unknown scale: 4 significant digits (integers as they are)."""
    if not is_int_or_float(x):
        return _e(x)
    if isinstance(x, int):
        return str(x)
    return f"{x:.4g}" if math.isfinite(x) else "–"


def sigma_decimals(sigma: Any, fallback: int = 2, most: int = 6) -> int:
    """Decimals that show ``sigma`` with two significant digits (``fallback`` when it is
    undefined or zero), at most ``most``."""
    if not _finite(sigma) or sigma <= 0:
        return fallback
    return int(min(most, max(0, 1 - math.floor(math.log10(sigma)))))


def pm(value: Any, sigma: Any, fallback: int = 2) -> str:
    """``value ± sigma``, both to the decimals of sigma's second significant digit."""
    d = sigma_decimals(sigma, fallback)
    if not _finite(sigma):
        return _f(value, d)
    return f"{_f(value, d)} ± {_f(sigma, d)}"


def _id(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "-", name)


def _and(names: Sequence[str]) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def _views_list(views: Sequence[str], at_most: int = 12) -> str:
    shown = ", ".join(views[:at_most])
    return shown + (f" and {len(views) - at_most} more" if len(views) > at_most else "")


def _table(
    head: Sequence[str],
    rows: Sequence[Sequence[str]],
    numeric: Sequence[int] = (),
    caption: str = "",
    raw: bool = False,
    attrs: str = "",
) -> str:
    """A table (no header row when ``head`` is all empty); cells are escaped unless
    ``raw`` (then they are HTML already); the columns in ``numeric`` are right-aligned."""
    cell = (lambda c: c) if raw else _e
    cls = [' class="n"' if i in numeric else "" for i in range(len(head))]
    out = [f"<p class='caption'>{caption}</p>"] if caption else []
    out.append(f"<table{attrs}>")
    if any(head):
        heads = "".join(f"<th{c}>{_e(h)}</th>" for h, c in zip(head, cls, strict=True))
        out.append(f"<thead><tr>{heads}</tr></thead>")
    out.append("<tbody>")
    for r in rows:
        out.append(
            "<tr>"
            + "".join(f"<td{c}>{cell(v)}</td>" for v, c in zip(r, cls, strict=True))
            + "</tr>"
        )
    out.append("</tbody></table>")
    return "".join(out)


_GOOD = ("pass", "good", "excellent", "ok")
_BAD = ("fail", "poor", "bad", "refused", "unusable", "not calibrated")
_FAIR = ("fair", "marginal", "usable", "warning", "weak", "uncertain")


def _tone(value: Any) -> str:
    """``good``, ``bad``, ``fair`` or ``""``: a verdict's colour, from its first words (or
    a mapping's ``passed``, ``grade`` or ``status``)."""
    if isinstance(value, Mapping):
        if isinstance(value.get("passed"), bool):
            return "good" if value["passed"] else "bad"
        return _tone(value.get("grade", value.get("status")))
    if not isinstance(value, str):
        return ""
    head = value.lower()[:40]
    for tone, words in (("bad", _BAD), ("fair", _FAIR), ("good", _GOOD)):
        if any(re.search(rf"\b{w}\b", head) for w in words):
            return tone
    return ""


def generic(value: Any, depth: int = 0) -> str:
    """Any JSON value as HTML: text as a paragraph, a list of texts as a list, a list of
    mappings as a table, a mapping of scalars as a two-column table, a mapping of mappings
    as a table with a row per key, deeper nesting as definition lists."""
    scalar = (str, int, float, bool, type(None))
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | float):
        return _g(value)
    if isinstance(value, str):
        return _e(value)
    if depth > 4:
        return f"<code>{_e(value)}</code>"
    if isinstance(value, Sequence):
        items = list(value)
        if not items:
            return "–"
        if all(is_int_or_float(v) for v in items):
            return ", ".join(_g(v) for v in items)
        if all(isinstance(v, Mapping) for v in items):
            keys = list(dict.fromkeys(k for v in items for k in v))
            rows = [[generic(v.get(k), depth + 1) for k in keys] for v in items]
            return _table([_label(k) for k in keys], rows, raw=True)
        return "<ul>" + "".join(f"<li>{generic(v, depth + 1)}</li>" for v in items) + "</ul>"
    if isinstance(value, Mapping):
        if not value:
            return "–"
        if all(isinstance(v, scalar) for v in value.values()):
            rows = [[_e(_label(k)), generic(v, depth + 1)] for k, v in value.items()]
            return _table(["", ""], rows, raw=True)
        inner = list(value.values())
        if all(isinstance(v, Mapping) for v in inner) and all(
            isinstance(x, scalar) for v in inner for x in v.values()
        ):
            keys = list(dict.fromkeys(k for v in inner for k in v))
            rows = [
                [_e(n), *(generic(v.get(k), depth + 1) for k in keys)] for n, v in value.items()
            ]
            return _table(["", *(_label(k) for k in keys)], rows, raw=True)
        return (
            "<dl>"
            + "".join(
                f"<dt>{_e(_label(k))}</dt><dd>{generic(v, depth + 1)}</dd>"
                for k, v in value.items()
            )
            + "</dl>"
        )
    return _e(value)


def _label(key: Any) -> str:
    return str(key).replace("_", " ")


def _verdict_box(value: Any, title: str = "Verdict") -> str:
    """A verdict in a coloured box: a graded one (calib.verdict's ``grade``, ``line``,
    ``figures``, ``advice``) as its grade, sentence and figures; text as it is; any other
    mapping generically."""
    if isinstance(value, str):
        body = f"<p><b>{_e(value)}</b></p>"
    elif _graded(value):
        body = _graded_body(value)
    else:
        body = generic(value)
    tone = _tone(value)
    cls = f"box box-{tone}" if tone else "box"
    return f'<div class="{cls}"><p class="small muted">{_e(title)}</p>{body}</div>'


def _graded(value: Any) -> bool:
    return isinstance(value, Mapping) and isinstance(value.get("grade"), str)


def _grade(grade: Any) -> str:
    return f"<b class='{_tone(str(grade))}'>{_e(str(grade).upper())}</b>"


def _sentence(entry: Mapping[str, Any]) -> str:
    """A graded verdict's ``line`` without its leading ``grade:``."""
    line = str(entry.get("line") or "")
    prefix = f"{entry.get('grade')}:"
    return line[len(prefix) :].strip() if line.startswith(prefix) else line


def _graded_body(v: Mapping[str, Any]) -> str:
    """A rig's verdict (a ``grade`` over ``sensors`` and ``pairs`` verdicts) as its grade and
    a table of theirs; one sensor's or pair's as its grade, sentence and figures."""
    parts = []
    sensors, pairs = v.get("sensors"), v.get("pairs")
    if isinstance(sensors, Mapping) or isinstance(pairs, list):
        alone = v.get("sensors_intrinsics_only") or {}
        entries = [*(sensors or {}).values(), *(pairs or []), *alone.values()]
        entries = [e for e in entries if _graded(e)]
        parts.append(f"<p style='font-size:12pt'>{_grade(v['grade'])}</p>")
        rows = [[_e(e.get("label", "")), _grade(e["grade"]), _e(_sentence(e))] for e in entries]
        if rows:
            parts.append(_table(["", "grade", "why"], rows, raw=True))
        share, factor = v.get("sigma_share"), v.get("poor_factor")
        if _finite(share) and _finite(factor):
            parts.append(
                "<p class='small muted'>A 1-sigma meets its target when it is at most "
                f"{_g(share)} × the accuracy target; good: every judged 1-sigma meets its "
                f"target, poor: one exceeds it {_g(factor)} times, usable: in between.</p>"
            )
    else:
        parts.append(f"<p>{_grade(v['grade'])} {_e(_sentence(v))}</p>")
        figures = _figure_rows(v.get("figures"))
        if figures:
            parts.append(_figures_table(FIGURE_HEAD, figures))
    rest = {k: x for k, x in v.items() if k not in _GRADED_SHOWN and x not in (None, [], {})}
    if rest:  # what its sentence says already, in figures (folded: open it to see)
        parts.append(f"<details class='small'><summary>more</summary>{generic(rest)}</details>")
    return "".join(parts)


_GRADED_SHOWN = frozenset(
    {
        "grade",
        "line",
        "label",
        "sensors",
        "pairs",
        "sensors_intrinsics_only",
        "figures",
        "sigma_share",
        "poor_factor",
        "advice",
        "advice_kinds",
        "predicted_ratio",
        "baseline_mm",
        "sigma_baseline_length_mm",
        "more_views",
    }
)
"""Keys of a graded verdict shown by :func:`_graded_body` (its sentence holds the advice,
the views to add and the baseline); any other is shown generically, folded."""


FIGURE_HEAD = ("figure", "1-sigma", "target", "σ / target", "per axis", "mostly")


def _figures_table(head: Sequence[str], rows: list[list[str]]) -> str:
    """A table of verdict figures (:func:`_figure_rows`, maybe after leading cells), without
    the columns empty in every row."""
    keep = [i for i in range(len(head)) if any(r[i] for r in rows)]
    numeric = [k for k, i in enumerate(keep) if head[i] in ("1-sigma", "target", "σ / target")]
    return _table(
        [head[i] for i in keep], [[r[i] for i in keep] for r in rows], numeric=numeric, raw=True
    )


def _figure_rows(figures: Any) -> list[list[str]]:
    """Rows of a verdict's figures: what, 1-sigma with its unit, target, ratio, per axis."""
    rows = []
    for f in figures or []:
        if not isinstance(f, Mapping):
            continue
        unit = str(f.get("unit") or "")
        sep = "" if unit in ("%", "°") else " "
        d = sigma_decimals(f.get("sigma"), 2, 4)
        axes, names = f.get("axes"), f.get("axis_names")
        per_axis = ""
        if isinstance(axes, Sequence) and isinstance(names, Sequence):
            per_axis = ", ".join(f"{n} {_f(a, d)}" for n, a in zip(names, axes, strict=False))
        target = f.get("target")
        rows.append(
            [
                _e(f.get("what", "")),
                _e(f"{_f(f.get('sigma'), d)}{sep}{unit}"),
                _e(f"{_g(target)}{sep}{unit}") if _finite(target) else "not judged",
                _f(f.get("ratio"), 2) if _finite(f.get("ratio")) else "",
                _e(per_axis),
                _e(f.get("dominant_axis") or ""),
            ]
        )
    return rows


def _advice(value: Any) -> str:
    if isinstance(value, str):
        value = [value]
    return "<h3>Advice</h3>" + generic(value)


# -- plots (inline SVG) -----------------------------------------------------------------------


def nice_ceil(x: float) -> float:
    """The smallest of 1, 2, 2.5, 5 times a power of ten that is >= ``x`` (> 0)."""
    if not math.isfinite(x) or x <= 0:
        return 1.0
    mag = 10.0 ** math.floor(math.log10(x))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * mag >= x * (1 - 1e-9):
            return m * mag
    return 10.0 * mag


def ticks(hi: float, n: int = 5) -> tuple[list[float], int]:
    """Tick values from 0 to ``hi`` about ``n`` apart, and the decimals to print them."""
    step = nice_ceil(hi / n)
    k = math.floor(math.log10(step) + 1e-9)
    d = max(0, -k + (1 if abs(step / 10.0**k - 2.5) < 1e-6 else 0))  # 0.25: 2, 25: 0
    values = [k * step for k in range(math.floor(hi / step + 1e-9) + 1)]
    return values, d


def _rgb(c: tuple[int, int, int]) -> str:
    return "#{:02x}{:02x}{:02x}".format(*c)


def _svg(width: float, height: float, body: Sequence[str], label: str) -> str:
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:g} {height:g}" '
        f'width="{width:g}" height="{height:g}" role="img" aria-label="{_e(label)}" '
        'font-size="10">' + "".join(body) + "</svg>"
    )


def _dots(xy: np.ndarray, colour: str, size: float = 2.6, title: str = "") -> str:
    """Many dots as one path (a zero-length segment per point, round caps): compact."""
    if len(xy) == 0:
        return ""
    d = "".join(f"M{x:.1f} {y:.1f}h0" for x, y in xy)
    t = f"<title>{_e(title)}</title>" if title else ""
    return (
        f'<path d="{d}" stroke="{colour}" stroke-width="{size:g}" stroke-linecap="round" '
        f'fill="none">{t}</path>'
    )


def _segments(a: np.ndarray, b: np.ndarray, colour: str, width: float = 1.0) -> str:
    if len(a) == 0:
        return ""
    d = "".join(
        f"M{x0:.1f} {y0:.1f}L{x1:.1f} {y1:.1f}" for (x0, y0), (x1, y1) in zip(a, b, strict=True)
    )
    return f'<path d="{d}" stroke="{colour}" stroke-width="{width:g}" fill="none"/>'


def view_rms_svg(
    views: Sequence[str],
    rms: Sequence[float | None],
    state: Sequence[str],
    sensor_rms: float | None,
) -> str:
    """Bar chart of one sensor's RMS error per view (px).

    ``state`` per view: ``used``, ``outlier`` (an amber bar: left out), ``not found`` (a
    grey x on the axis) or ``no image`` (nothing). A dashed line marks the sensor's RMS."""
    n = max(1, len(views))
    left, right, top, bottom = 50.0, 8.0, 12.0, 46.0
    width = 680.0
    height = 210.0
    pw, ph = width - left - right, height - top - bottom
    values = [r for r in rms if _finite(r)]
    hi = nice_ceil(max(values, default=1.0) * 1.08)
    tv, d = ticks(hi, 4)
    y = lambda v: top + ph * (1 - min(v, hi) / hi)  # noqa: E731
    slot = pw / n
    body = [f'<rect x="{left}" y="{top}" width="{pw:g}" height="{ph:g}" fill="#fafafa"/>']
    for t in tv:
        body.append(
            f'<line x1="{left}" x2="{left + pw:g}" y1="{y(t):.1f}" y2="{y(t):.1f}" '
            'stroke="#ddd"/>'
            f'<text x="{left - 4}" y="{y(t) + 3.5:.1f}" text-anchor="end">{t:.{d}f}</text>'
        )
    label_every = max(1, math.ceil(n / 48))
    for i, (v, r, s) in enumerate(zip(views, rms, state, strict=True)):
        cx = left + slot * (i + 0.5)
        if s in ("used", "outlier") and _finite(r):
            fill = LEFT_VIEW if s == "outlier" else USED
            bw = max(1.0, slot * 0.7)
            body.append(
                f'<rect x="{cx - bw / 2:.1f}" y="{y(r):.1f}" width="{bw:.1f}" '
                f'height="{top + ph - y(r):.1f}" fill="{fill}"><title>{_e(v)}: '
                f"{r:.3f} px{' (outlier)' if s == 'outlier' else ''}</title></rect>"
            )
        elif s == "not found":
            body.append(
                f'<text x="{cx:.1f}" y="{top + ph - 2:.1f}" text-anchor="middle" '
                f'fill="{GREY}">×<title>{_e(v)}: board not found</title></text>'
            )
        if i % label_every == 0:
            body.append(
                f'<text transform="translate({cx + 3:.1f} {top + ph + 5:.1f}) rotate(-60)" '
                f'text-anchor="end" font-size="8.5">{_e(v[-10:])}</text>'
            )
    if _finite(sensor_rms):
        body.append(
            f'<line x1="{left}" x2="{left + pw:g}" y1="{y(sensor_rms):.1f}" '
            f'y2="{y(sensor_rms):.1f}" stroke="#333" stroke-dasharray="4 3"/>'
            f'<text x="{left + pw - 2:g}" y="{y(sensor_rms) - 3:.1f}" text-anchor="end">'
            f"RMS {sensor_rms:.3f} px</text>"
        )
    body.append(
        f'<text transform="translate(10 {top + ph / 2:.1f}) rotate(-90)" '
        'text-anchor="middle">RMS error, px</text>'
    )
    return _svg(width, height, body, "RMS error per view")


def scatter_svg(
    residual: np.ndarray, used: np.ndarray, in_outlier_view: np.ndarray
) -> tuple[str, float, int]:
    """Scatter of one sensor's corner residuals (du, dv), px.

    Args:
        residual: (M, 2) detected minus reprojected, px.
        used: (M,) the corner was in the final solution.
        in_outlier_view: (M,) the corner's view was left out (amber); other corners not
            used are outlier corners (red).

    Returns:
        The SVG, the half-width of the plotted square (px) and how many points lay beyond
        it (drawn on its border).
    """
    left, top, inner = 48.0, 8.0, 230.0
    ref = np.abs(residual[used]) if used.any() else np.abs(residual)
    lim = nice_ceil(float(np.percentile(ref, 99.5)) * 1.15 if ref.size else 1.0)
    beyond = int(np.count_nonzero(np.any(np.abs(residual) > lim, axis=1)))
    pts = (np.clip(residual, -lim, lim) + lim) / (2 * lim) * inner + (left, top)
    cx, cy = left + inner / 2, top + inner / 2
    body = [
        f'<rect x="{left:g}" y="{top:g}" width="{inner:g}" height="{inner:g}" fill="#fafafa" '
        'stroke="#999"/>',
        f'<line x1="{left:g}" x2="{left + inner:g}" y1="{cy:g}" y2="{cy:g}" stroke="#ccc"/>',
        f'<line y1="{top:g}" y2="{top + inner:g}" x1="{cx:g}" x2="{cx:g}" stroke="#ccc"/>',
    ]
    tv, d = ticks(lim, 2)
    for t in sorted({-t for t in tv} | set(tv)):
        f = (t + lim) / (2 * lim) * inner
        label = f"{t + 0.0:.{d}f}"  # + 0.0: no "-0.00"
        body.append(
            f'<text x="{left + f:.1f}" y="{top + inner + 12:.1f}" text-anchor="middle">'
            f"{label}</text>"
            f'<text x="{left - 4:g}" y="{top + f + 3.5:.1f}" text-anchor="end">{label}</text>'
        )
    if used.any():
        rms = float(np.sqrt(np.mean(np.sum(residual[used] ** 2, axis=1))))
        body.append(
            f'<circle cx="{cx:g}" cy="{cy:g}" r="{rms / (2 * lim) * inner:.1f}" fill="none" '
            f'stroke="#333" stroke-dasharray="3 2"><title>RMS {rms:.3f} px</title></circle>'
        )
    outlier_corner = ~used & ~in_outlier_view
    body.append(_dots(pts[used], USED, 2.2, "used"))
    body.append(_dots(pts[in_outlier_view], LEFT_VIEW, 2.6, "in a view left out"))
    body.append(_dots(pts[outlier_corner], LEFT_CORNER, 3.0, "outlier corner"))
    width, height = left + inner + 16, top + inner + 32
    body.append(
        f'<text x="{cx:g}" y="{height - 4:g}" text-anchor="middle">du, px (right)</text>'
        f'<text transform="translate(11 {cy:g}) rotate(-90)" text-anchor="middle">'
        "dv, px (down)</text>"
    )
    return _svg(width, height, body, "corner residuals"), lim, beyond


def _heat(fraction: float) -> str:
    """White to dark blue."""
    f = min(1.0, max(0.0, fraction))
    r, g, b = (round(255 + (t - 255) * f) for t in (31, 80, 150))
    return f"#{r:02x}{g:02x}{b:02x}"


def coverage_svg(counts: np.ndarray, image_size: Sequence[int]) -> str:
    """Heat map of the corners counted per cell of the image (the report's
    ``coverage.corner_counts``): darker = more corners, pink = none; counts in the cells."""
    w_px, h_px = image_size
    width = 320.0
    height = width * h_px / w_px
    rows, cols = counts.shape
    cw, ch = width / cols, height / rows
    top = float(counts.max()) if counts.size else 0.0
    body = []
    for r in range(rows):
        for c in range(cols):
            n = int(counts[r, c])
            fill = "#f6d5d5" if n == 0 else _heat(0.15 + 0.85 * math.sqrt(n / top))
            ink = "#fff" if n and math.sqrt(n / top) > 0.55 else "#333"
            body.append(
                f'<rect x="{c * cw:.1f}" y="{r * ch:.1f}" width="{cw:.1f}" height="{ch:.1f}" '
                f'fill="{fill}" stroke="#fff"/>'
                f'<text x="{(c + 0.5) * cw:.1f}" y="{(r + 0.5) * ch + 3.5:.1f}" '
                f'text-anchor="middle" fill="{ink}" font-size="9">{n}</text>'
            )
    body.append(f'<rect width="{width:g}" height="{height:.1f}" fill="none" stroke="#666"/>')
    return _svg(width, round(height, 1), body, "corners per image region")


def vectors_svg(
    uv: np.ndarray,
    residual: np.ndarray,
    used: np.ndarray,
    in_outlier_view: np.ndarray,
    image_size: Sequence[int],
) -> tuple[str, float]:
    """The corners where they fell in the image, each used one with its residual drawn
    magnified; corners of views left out as amber dots, outlier corners as red dots with
    their residual cut to at most :data:`LONGEST_VECTOR`.

    Args:
        uv: (M, 2) detected corners, px (pixel centres at integers).
        residual: (M, 2) detected minus reprojected, px.
        used: (M,) in the final solution.
        in_outlier_view: (M,) in a view left out.
        image_size: (width, height) px.

    Returns:
        The SVG and the magnification of the vectors.
    """
    w_px, h_px = image_size
    width = 340.0
    s = width / w_px
    height = h_px * s
    length = np.linalg.norm(residual, axis=1)
    ref = length[used] if used.any() else length
    p95 = float(np.percentile(ref, 95)) if ref.size else 0.0
    gain = nice_ceil(0.03 * w_px / p95) if p95 > 0 else 1.0
    a = (uv + 0.5) * s
    drawn = gain * residual * s
    lone = ~used & ~in_outlier_view
    longest = np.maximum(np.linalg.norm(drawn, axis=1, keepdims=True), 1e-9)
    drawn[lone] *= np.minimum(1.0, LONGEST_VECTOR / longest[lone])
    b = a + drawn
    bar_px = nice_ceil(0.06 * w_px / gain)  # a residual of this size draws about 6 % wide
    bar = bar_px * gain * s
    body = [
        f'<rect width="{width:g}" height="{height:.1f}" fill="#fafafa" stroke="#666"/>',
        _dots(a[used], "#bbb", 1.6),
        _segments(a[used], b[used], USED, 0.9),
        _dots(a[in_outlier_view], LEFT_VIEW, 2.2, "in a view left out"),
        _segments(a[lone], b[lone], LEFT_CORNER, 1.2),
        _dots(a[lone], LEFT_CORNER, 3.0, "outlier corner"),
        f'<line x1="8" x2="{8 + bar:.1f}" y1="{height + 12:.1f}" y2="{height + 12:.1f}" '
        f'stroke="{USED}" stroke-width="2"/>'
        f'<text x="{12 + bar:.1f}" y="{height + 15.5:.1f}">{_g(bar_px)} px residual '
        f"(drawn ×{_g(gain)})</text>",
    ]
    return _svg(width, round(height + 22, 1), body, "residual vectors over the image"), gain


# -- sections ------------------------------------------------------------------------------


def _sigma(entry: Mapping[str, Any], key: str) -> Any:
    return (entry.get("sigma") or {}).get(key)


def _pose(entry: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vector (deg) and translation (mm) of a sensor's ``T_rig_sensor``."""
    T = np.asarray(entry["T_rig_sensor"], dtype=float)
    return np.degrees(rvec_from_rotation(T[:3, :3])), 1000.0 * T[:3, 3]


def _vec_sigma(entry: Mapping[str, Any], key: str, scale: float = 1.0) -> np.ndarray:
    s = _sigma(entry, key)
    if not isinstance(s, Sequence) or len(s) != 3 or not all(_finite(v) for v in s):
        return np.full(3, np.nan)
    return scale * np.asarray(s, dtype=float)


def _summary(report: Mapping[str, Any]) -> str:
    sensors = report.get("sensors") or {}
    excluded = report.get("excluded_sensors") or {}
    parts = ["<section id='summary'><h2>Summary and verdict</h2>"]
    if report.get("verdict") is not None:
        parts.append(_verdict_box(report["verdict"]))
    cmp = report.get("comparison")
    if isinstance(cmp, Mapping) and "passed" in cmp:
        parts.append(_verdict_box(_comparison_verdict(cmp), "Against the true rig"))
    calibrated = (
        f"{len(sensors)} sensor(s) calibrated ({_e(_and(list(sensors)))})"
        if sensors
        else "no sensor calibrated"
    )
    if alone := list(report.get("sensors_intrinsics_only") or {}):
        calibrated += f", intrinsics only ({_e(_and(alone))}: pose unknown)"
    rms = report.get("rms_px")
    line = f"<p>{calibrated}, reference <b>{_e(report.get('reference', '–'))}</b>"
    if _finite(rms):
        line += f", overall RMS reprojection error <b>{rms:.3f} px</b>"
    n_views = len(report.get("detections") or report.get("views") or {})
    line += f", {n_views} view(s)"
    if _finite(report.get("seconds")):
        line += f", solved in {report['seconds']:.1f} s"
    parts.append(line + ".</p>")
    if excluded:
        parts.append(
            "<p class='bad'><b>Not calibrated:</b></p><ul>"
            + "".join(f"<li><b>{_e(s)}</b>: {_e(why)}</li>" for s, why in excluded.items())
            + "</ul>"
        )
    if report.get("advice"):
        parts.append(_advice(report["advice"]))
    rows = []
    for name, s in sensors.items():
        intr = s.get("intrinsics") or {}
        cov = s.get("coverage") or {}
        size = s.get("image_size") or ["?", "?"]
        rot = float(np.linalg.norm(_vec_sigma(s, "rotation_deg")))
        trans = float(np.linalg.norm(_vec_sigma(s, "translation_m", 1000.0)))
        reference = name == report.get("reference")
        rows.append(
            [
                f"<a href='#sensor-{_id(name)}'>{_e(name)}</a>",
                f"{_e(size[0])}&nbsp;×&nbsp;{_e(size[1])}",
                f"{_e(s.get('views_used', '?'))} / {_e(s.get('views_detected', '?'))}",
                _f(s.get("rms_px"), 3),
                pm(intr.get("fx"), _sigma(s, "fx")),
                pm(intr.get("fy"), _sigma(s, "fy")),
                "reference" if reference else _f(rot, 3),
                "reference" if reference else _f(trans, 2),
                f"{100 * cov['reached']:.0f}" if _finite(cov.get("reached")) else "–",
            ]
        )
    if rows:
        parts.append(
            _table(
                [
                    "sensor",
                    "image px",
                    "views used / found",
                    "RMS px",
                    "fx px",
                    "fy px",
                    "σ rot °",
                    "σ trans mm",
                    "coverage %",
                ],
                rows,
                numeric=(1, 2, 3, 4, 5, 6, 7, 8),
                raw=True,
                caption="Per sensor, ± 1-sigma. σ rot, σ trans: norms of the 1-sigma of its "
                "pose relative to the reference (rotation vector, translation); coverage: "
                "share of the image's cells (6 × 8) that a corner reached",
                attrs=" id='overview' class='small'",
            )
        )
    parts.append(_intrinsics_only(report.get("sensors_intrinsics_only") or {}))
    notes = report.get("notes") or []
    if notes:
        parts.append(
            "<h3>Decided on its own</h3><ul>"
            + "".join(f"<li>{_e(n)}</li>" for n in notes)
            + "</ul>"
        )
    parts.append("</section>")
    return "".join(parts)


def _intrinsics_only(alone: Mapping[str, Any]) -> str:
    """The sensors calibrated alone (``sensors_intrinsics_only``): their intrinsics ± 1-sigma,
    then why their pose is unknown (the sensors with the same reason together)."""
    if not alone:
        return ""
    rows, why = [], {}
    for name, s in alone.items():
        intr = s.get("intrinsics") or {}
        size = s.get("image_size") or ["?", "?"]
        rows.append(
            [
                _e(name),
                f"{_e(size[0])}&nbsp;×&nbsp;{_e(size[1])}",
                f"{_e(s.get('views_used', '?'))} / {_e(s.get('views_detected', '?'))}",
                _f(s.get("rms_px"), 3),
                *(pm(intr.get(k), _sigma(s, k)) for k in ("fx", "fy", "cx", "cy")),
            ]
        )
        why.setdefault(str(s.get("pose_unknown") or "pose unknown"), []).append(name)
    table = _table(
        ["sensor", "image px", "views used / found", "RMS px", "fx px", "fy px", "cx px", "cy px"],
        rows,
        numeric=(1, 2, 3, 4, 5, 6, 7),
        raw=True,
        caption="Sensors calibrated alone, on their own views, ± 1-sigma; not in the rig",
        attrs=" id='intrinsics-only' class='small'",
    )
    reasons = "".join(f"<li><b>{_e(_and(n))}</b>: {_e(w)}</li>" for w, n in why.items())
    return f"<h3>Intrinsics only: pose unknown</h3>{table}<ul>{reasons}</ul>"


def _comparison_verdict(cmp: Mapping[str, Any]) -> str:
    fails = list(cmp.get("failures") or [])
    n = len(cmp.get("sensors") or {})
    if cmp.get("passed"):
        return f"PASS: every judged figure meets its target ({n} sensors and every pair)."
    shown = ", ".join(fails[:6]) + (f" and {len(fails) - 6} more" if len(fails) > 6 else "")
    return f"FAIL: {len(fails)} figure(s) miss their target: {shown}."


def _sensor_views(
    report: Mapping[str, Any], name: str
) -> tuple[list[str], list[float | None], list[str]]:
    """Views showing ``name`` (every view of the report), its RMS and state per view."""
    detections = report.get("detections") or {}
    views = report.get("views") or {}
    names = sorted(set(detections) | set(views))
    rms: list[float | None] = []
    state: list[str] = []
    for v in names:
        e = (views.get(v) or {}).get(name)
        d = (detections.get(v) or {}).get(name)
        if e is not None:
            rms.append(e.get("rms_px"))
            state.append("outlier" if e.get("outlier") else "used")
        else:
            rms.append(None)
            state.append("not found" if d is not None and not d.get("found") else "no image")
    return names, rms, state


def _left_out(report: Mapping[str, Any], name: str) -> str:
    """What of the sensor's views was left out, and why."""
    by_reason: dict[str, list[str]] = {}
    for v, per in sorted((report.get("detections") or {}).items()):
        d = per.get(name)
        if d is not None and not d.get("found"):
            by_reason.setdefault(str(d.get("reason") or "not found"), []).append(v)
    items = [
        f"<li>board not found in {len(vs)} view(s) ({_e(_views_list(vs))}): {_e(r)}</li>"
        for r, vs in by_reason.items()
    ]
    outliers = report.get("outliers") or []
    for o in outliers:
        if o.get("sensor") == name and o.get("corner") is None:
            items.append(
                f"<li>view {_e(o.get('view'))} left out (RMS {_f(o.get('error_px'))} px when "
                "flagged): "
                f"{_e(o.get('reason'))}</li>"
            )
    corners = [o for o in outliers if o.get("sensor") == name and o.get("corner") is not None]
    if corners:
        views = sorted({str(o.get("view")) for o in corners})
        items.append(
            f"<li>{len(corners)} outlier corner(s) left out, in view(s) {_e(_views_list(views))} "
            "(<a href='#outliers'>Outliers</a>)</li>"
        )
    if not items:
        return "<p>Nothing left out: every view that showed the board was used.</p>"
    return "<ul>" + "".join(items) + "</ul>"


def _rig_part(report: Mapping[str, Any], key: str) -> Any:
    """``report["verdict"][key]`` (``sensors``: by name, ``pairs``: a list) when the
    verdict is a graded rig verdict (calib.verdict), else empty."""
    v = report.get("verdict")
    empty: Any = {} if key == "sensors" else []
    if not _graded(v):
        return empty
    part = v.get(key)
    return part if isinstance(part, type(empty)) else empty


def _sensor_section(
    report: Mapping[str, Any], name: str, index: int, corners: CornerResiduals | None
) -> str:
    s = report["sensors"][name]
    colour = _rgb(sensor_colour(index))
    intr = s.get("intrinsics") or {}
    size = list(s.get("image_size") or [0, 0])
    parts = [
        f"<section class='sensor' id='sensor-{_id(name)}'>",
        f"<h2><span style='color:{colour}'>■</span> {_e(name)} <span class='sub'>"
        f"({_e(s.get('modality', ''))}, {_e(size[0])} × {_e(size[1])} px)</span></h2>",
    ]
    verdict = s.get("verdict") or _rig_part(report, "sensors").get(name)
    if verdict is not None:
        parts.append(_verdict_box(verdict))
    parts.append(
        f"<p>Board found in {_e(s.get('views_detected', '?'))} view(s), "
        f"{_e(s.get('views_used', '?'))} used; RMS reprojection error "
        f"<b>{_f(s.get('rms_px'), 3)} px</b>; worst view {_e(s.get('worst_view') or '–')}.</p>"
    )
    if s.get("advice"):
        parts.append(_advice(s["advice"]))
    rows = [[k, pm(intr.get(k), _sigma(s, k)), "px"] for k in ("fx", "fy", "cx", "cy")]
    dist = list(s.get("distortion") or [])
    dsig = list(_sigma(s, "distortion") or [])
    for i, v in enumerate(dist):
        sg = dsig[i] if i < len(dsig) else None
        rows.append(
            [
                DIST_NAMES[i] if i < len(DIST_NAMES) else f"d{i}",
                "0 (fixed)" if v == 0 and not (_finite(sg) and sg > 0) else pm(v, sg, 4),
                "",
            ]
        )
    intr_table = _table(
        ["", "value ± 1-sigma", "unit"],
        rows,
        numeric=(1,),
        caption="Intrinsics and distortion (OpenCV's model)",
    )
    if name == report.get("reference"):
        pose_table = "<p>The reference: its frame is the rig frame.</p>"
    elif "T_rig_sensor" in s:
        rvec, t = _pose(s)
        rs, ts = _vec_sigma(s, "rotation_deg"), _vec_sigma(s, "translation_m", 1000.0)
        pose_rows = [[f"rotation {a}", pm(rvec[i], rs[i], 3), "°"] for i, a in enumerate("xyz")]
        pose_rows.append(["rotation angle", _f(float(np.linalg.norm(rvec)), 3), "°"])
        pose_rows += [[f"translation {a}", pm(t[i], ts[i], 2), "mm"] for i, a in enumerate("xyz")]
        pose_table = _table(
            ["", "value", "unit"],
            pose_rows,
            numeric=(1,),
            caption=f"Pose in the rig frame ({_e(report.get('reference', ''))}'s): "
            "T_rig_sensor, rotation vector and translation ± 1-sigma",
        )
    else:
        pose_table = ""
    parts.append(f"<div>{_inline(intr_table)}{_inline(pose_table)}</div>")
    parts.append("<h3>Views left out, and why</h3>" + _left_out(report, name))

    views, rms, state = _sensor_views(report, name)
    parts.append(
        "<figure class='wide'>"
        + view_rms_svg(views, rms, state, s.get("rms_px"))
        + "<figcaption>RMS reprojection error per view (all its corners at the final "
        f"solution): {_key(USED, 'used')}, {_key(LEFT_VIEW, 'left out as an outlier')}; "
        "×: board not found; dashed: the sensor's RMS (used corners).</figcaption></figure>"
    )
    figures = []
    outlier_views = {v for v, st in zip(views, state, strict=True) if st == "outlier"}
    sel = _corners_of(corners, name, outlier_views)
    if sel is not None:
        uv, res, used, in_bad_view = sel
        svg, lim, beyond = scatter_svg(res, used, in_bad_view)
        note = f"; {beyond} beyond ±{_g(lim)} px drawn on the border" if beyond else ""
        figures.append(
            f"<figure>{svg}<figcaption>Residual of every corner, detected minus reprojected "
            f"(du, dv) px: {_key(USED, f'{int(used.sum())} used')}, "
            f"{_key(LEFT_VIEW, f'{int(in_bad_view.sum())} in views left out')}, "
            f"{_key(LEFT_CORNER, f'{int((~used & ~in_bad_view).sum())} outlier corners')}; "
            f"dashed circle: RMS{note}.</figcaption></figure>"
        )
        svg, gain = vectors_svg(uv, res, used, in_bad_view, size)
        figures.append(
            f"<figure>{svg}<figcaption>Where the corners fell in the image and their "
            f"residuals drawn ×{_g(gain)}: {_key(USED, 'used')}, "
            f"{_key(LEFT_VIEW, 'in views left out')}, {_key(LEFT_CORNER, 'outlier corners')} "
            "(vectors cut short). A pattern (all pointing out at the edges, a swirl) is a "
            "model error; directions at random are noise.</figcaption></figure>"
        )
    cov = s.get("coverage") or {}
    if cov.get("corner_counts"):
        counts = np.asarray(cov["corner_counts"], dtype=int)
        bars = ", ".join(
            f"{n} {_f(cov.get(k.lower()), 2)}"
            for n, k in zip(PARAM_NAMES, ("x", "y", "size", "skew"), strict=True)
        )
        good = "enough" if cov.get("good_enough") else "not yet enough"
        figures.append(
            f"<figure>{coverage_svg(counts, size)}<figcaption>Corners of the views used, per "
            f"region of the image: {_e(coverage_sentence(counts))}. Spread of the views (ROS "
            f"bars, 1 = full): {_e(bars)} ({good}).</figcaption></figure>"
        )
    if sel is None:
        figures.append(
            "<p class='muted small'>Per-corner residuals are not in report.json: the "
            "scatter and the residual vectors need the calibration itself (trifuse "
            "calibrate --report-html, or the console).</p>"
        )
    parts.append("<div>" + "".join(figures) + "</div>")
    extra = {k: v for k, v in s.items() if k not in SENSOR_KEYS}
    if extra:
        parts.append("<h3>Other figures</h3>" + generic(extra))
    parts.append("</section>")
    return "".join(parts)


def _key(colour: str, text: str) -> str:
    """A legend entry: a dot of ``colour`` and the text."""
    return f"<span style='color:{colour}'>●</span>&nbsp;{_e(text)}"


def _inline(block: str) -> str:
    return (
        f"<div style='display:inline-block;vertical-align:top;margin-right:8mm'>{block}</div>"
        if block
        else ""
    )


def _corners_of(
    corners: CornerResiduals | None, name: str, outlier_views: set[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """One sensor's corners: (M, 2) uv px, (M, 2) residual px, (M,) used, (M,) in one of
    ``outlier_views``; None without residuals or corners of that sensor."""
    if corners is None or name not in corners.sensors:
        return None
    sel = np.asarray(corners.s_idx) == corners.sensors.index(name)
    if not sel.any():
        return None
    bad = [i for i, v in enumerate(corners.views) if v in outlier_views]
    return (
        np.asarray(corners.uv_px, dtype=float)[sel],
        np.asarray(corners.residual_px, dtype=float)[sel],
        np.asarray(corners.inlier, dtype=bool)[sel],
        np.isin(np.asarray(corners.v_idx)[sel], bad),
    )


def pair_rows(report: Mapping[str, Any]) -> list[list[str]]:
    """Every pair of calibrated sensors: ``T_a_b = inv(T_rig_a) @ T_rig_b`` as its rotation
    angle (deg), translation (mm, in a's frame) and baseline (mm), each ± 1-sigma, and
    where the sigmas come from (the last cell).

    ``joint``: the pair's verdict (calib.verdict, from the joint covariance) gives them
    (rotation: the norm of its per-axis sigma; translation per axis; the baseline's
    length). ``own``: a pair with the reference, its partner's sigmas relative to it.
    ``≈``: other pairs, the two sensors' sigmas relative to the reference combined as if
    independent. Without a joint figure the rotation sigma is the norm of the rotation
    vector's sigma and the baseline's the translation sigma along the baseline."""
    sensors = report.get("sensors") or {}
    reference = report.get("reference")
    joint = {tuple(v.get("sensors") or ()): v for v in _rig_part(report, "pairs") if _graded(v)}
    names = [n for n in sensors if "T_rig_sensor" in sensors[n]]
    rows = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            Ta = np.asarray(sensors[a]["T_rig_sensor"], dtype=float)
            Tb = np.asarray(sensors[b]["T_rig_sensor"], dtype=float)
            T_ab = np.linalg.inv(Ta) @ Tb
            angle = rotation_angle_deg(T_ab[:3, :3])
            t_mm = 1000.0 * T_ab[:3, 3]
            s_rot, s_t, s_b, source = _pair_sigma(sensors, reference, a, b)
            v = joint.get((a, b))
            if v is not None:
                figures = {
                    f.get("unit"): f for f in v.get("figures") or [] if isinstance(f, Mapping)
                }
                rot, tr = figures.get("°") or {}, figures.get("mm") or {}
                if _finite(rot.get("sigma")) and isinstance(tr.get("axes"), Sequence):
                    s_rot, s_t = float(rot["sigma"]), np.asarray(tr["axes"], dtype=float)
                    s_b = v.get("sigma_baseline_length_mm", s_b)
                    source = "joint"
            rows.append(
                [
                    f"{a} – {b}",
                    pm(angle, s_rot, 3),
                    ", ".join(
                        _f(x, sigma_decimals(sx, 1)) for x, sx in zip(t_mm, s_t, strict=True)
                    ),
                    ", ".join(_f(x, sigma_decimals(x, 2)) for x in s_t),
                    pm(float(np.linalg.norm(t_mm)), s_b, 2),
                    source,
                ]
            )
    return rows


def _pair_sigma(
    sensors: Mapping[str, Any], reference: Any, a: str, b: str
) -> tuple[float, np.ndarray, float, str]:
    """Rotation (deg), translation (3, mm) and baseline (mm) sigma of the pair from the
    sensors' own sigmas relative to the reference, and ``own`` or ``≈`` (see
    :func:`pair_rows`)."""
    Ta = np.asarray(sensors[a]["T_rig_sensor"], dtype=float)
    Tb = np.asarray(sensors[b]["T_rig_sensor"], dtype=float)
    d = Tb[:3, 3] - Ta[:3, 3]
    direction = d / max(float(np.linalg.norm(d)), 1e-12)
    rot, trans, base = [], [], []
    for n in (a, b):
        if n == reference:
            continue
        ts = _vec_sigma(sensors[n], "translation_m", 1000.0)
        rot.append(float(np.linalg.norm(_vec_sigma(sensors[n], "rotation_deg"))))
        trans.append(ts)
        base.append(float(np.sqrt(np.sum((direction * ts) ** 2))))
    if not rot:
        return float("nan"), np.full(3, np.nan), float("nan"), ""
    s_t = np.sqrt(np.sum(np.square(trans), axis=0))
    return math.hypot(*rot), s_t, math.hypot(*base), "own" if len(rot) == 1 else "≈"


def _pairs(report: Mapping[str, Any]) -> str:
    rows = pair_rows(report)
    if not rows:
        return ""
    parts = [
        "<section id='pairs'><h2>Relative poses of the sensors</h2>",
        _table(
            [
                "pair a – b",
                "rotation °",
                "translation x, y, z mm",
                "σ x, y, z mm",
                "baseline mm",
                "σ from",
            ],
            rows,
            numeric=(1, 2, 3, 4),
            caption="T_a_b = inv(T_rig_a) @ T_rig_b: the angle of its rotation, its "
            "translation in a's frame (x right, y down, z forward) and its length, ± 1-sigma. "
            "σ from: joint, the pair's own verdict (the joint covariance); own, a pair with "
            f"the reference ({_e(report.get('reference', ''))}); ≈, the two sensors' 1-sigma "
            "relative to the reference combined as if independent.",
            attrs=" class='small'",
        ),
    ]
    rows = []
    for v in _rig_part(report, "pairs"):
        if _graded(v):
            for k, f in enumerate(_figure_rows(v.get("figures"))):
                lead = [_e(v.get("label", "")), _grade(v["grade"])] if k == 0 else ["", ""]
                rows.append([*lead, *f])
    if rows:
        parts.append(
            "<p class='caption'>Verdicts of the eye and stereo pairs (calib.verdict): the "
            "1-sigma of their relative pose from the joint covariance, per axis of a's frame "
            "(horizontal, vertical, optical; sideways, vertical, depth)</p>"
            + _figures_table(("pair", "grade", *FIGURE_HEAD), rows)
        )
    parts.append("</section>")
    return "".join(parts)


def _decisions(report: Mapping[str, Any]) -> str:
    parts = []
    polarity = report.get("polarity") or {}
    if polarity:
        parts.append(
            _table(
                POLARITY_HEAD,
                polarity_rows(polarity),
                numeric=(3, 4),
                caption=_e(polarity_caption(polarity)),
            )
        )
        turned = {n: p for n, p in polarity.items() if p.get("turned") or p.get("turned_views")}
        for n, p in turned.items():
            what = "its corners were relabelled by the half turn" if p.get("turned") else ""
            views = p.get("turned_views") or []
            if views:
                what += ("; " if what else "") + f"view(s) {_views_list(views)} turned alone"
            parts.append(f"<p>{_e(n)}: {_e(what)}.</p>")
        problems = {n: p["problem"] for n, p in polarity.items() if p.get("problem")}
        for n, why in problems.items():
            parts.append(f"<p class='bad'>{_e(n)} refused: {_e(why)}</p>")
    for key, value in report.items():
        if key not in KNOWN_KEYS and value not in (None, [], {}):
            parts.append(f"<h3>{_e(_label(key).capitalize())}</h3>" + generic(value))
    if not parts:
        return ""
    return (
        "<section id='decisions'><h2>Decisions and other findings</h2>"
        + "".join(parts)
        + "</section>"
    )


def _outliers(report: Mapping[str, Any]) -> str:
    outliers = report.get("outliers") or []
    views = [o for o in outliers if o.get("corner") is None]
    corners = [o for o in outliers if o.get("corner") is not None]
    parts = [
        "<section id='outliers'><h2>Outliers</h2>",
        f"<p>{len(views)} view(s) and {len(corners)} corner(s) were left out of the final "
        "solution, with the error that had them flagged.</p>",
    ]
    if views:
        parts.append(
            _table(
                ["view", "sensor", "RMS px", "why"],
                [
                    [str(o["view"]), str(o["sensor"]), _f(o.get("error_px")), str(o.get("reason"))]
                    for o in views
                ],
                numeric=(2,),
            )
        )
    if corners:
        shown = corners[:MAX_CORNER_ROWS]
        parts.append(
            _table(
                ["view", "sensor", "corner", "error px", "why"],
                [
                    [
                        str(o["view"]),
                        str(o["sensor"]),
                        str(o["corner"]),
                        _f(o.get("error_px")),
                        str(o.get("reason")),
                    ]
                    for o in shown
                ],
                numeric=(2, 3),
            )
        )
        if len(corners) > len(shown):
            parts.append(f"<p>… and {len(corners) - len(shown)} more corners (report.json).</p>")
    parts.append("</section>")
    return "".join(parts)


def _views_table(report: Mapping[str, Any]) -> str:
    """Every view and sensor: RMS px when used, the outlier's RMS in red, × [n] when the
    board was not found (n: the reason, listed below)."""
    detections = report.get("detections") or {}
    views = report.get("views") or {}
    names = sorted(set(detections) | set(views))
    if not names:
        return ""
    sensors = list(
        dict.fromkeys(
            [*(report.get("sensors") or {}), *(s for per in detections.values() for s in per)]
        )
    )
    reasons: dict[str, int] = {}
    excluded = report.get("excluded_sensors") or {}
    rows = []
    for v in names:
        row = [_e(v)]
        for s in sensors:
            e = (views.get(v) or {}).get(s)
            d = (detections.get(v) or {}).get(s)
            if e is not None:
                rms = _f(e.get("rms_px"), 3)
                row.append(f"<span class='bad'>{rms} out</span>" if e.get("outlier") else rms)
            elif d is not None and not d.get("found"):
                n = reasons.setdefault(str(d.get("reason") or "not found"), len(reasons) + 1)
                row.append(f"<span class='muted'>× [{n}]</span>")
            elif d is not None:
                row.append("<span class='muted'>found</span>" if s in excluded else "found")
            else:
                row.append("")
        rows.append(row)
    legend = "".join(f"<li>[{n}] {_e(r)}</li>" for r, n in reasons.items())
    return (
        "<section id='views'><h2>Every view</h2>"
        + _table(
            ["view", *sensors],
            rows,
            numeric=tuple(range(1, len(sensors) + 1)),
            raw=True,
            caption="RMS reprojection error per view and sensor, px; red “out”: left out as an "
            "outlier; ×: no usable board, for the reason numbered below; “found”: found in a "
            "sensor that was not calibrated",
            attrs=" class='small'",
        )
        + (
            f"<ol class='small' style='list-style:none;padding-left:0'>{legend}</ol>"
            if legend
            else ""
        )
        + "</section>"
    )


def _comparison(report: Mapping[str, Any]) -> str:
    cmp = report.get("comparison")
    if not isinstance(cmp, Mapping):
        return ""
    parts = [
        "<section id='truth'><h2>Against the true rig</h2>",
        f"<p>Compared with <code>{_e(cmp.get('truth', '?'))}</code> (reference "
        f"{_e(cmp.get('truth_reference', '?'))}); errors are estimate − truth.</p>",
    ]
    for what in ("estimate", "truth"):
        only = cmp.get(f"only_in_{what}") or []
        if only:
            parts.append(f"<p>Only in the {what}, not compared: {_e(', '.join(only))}.</p>")
    rows = []
    for n, e in (cmp.get("sensors") or {}).items():
        fails = [f for f in ("fx", "fy") if e.get(f"{f}_ok") is False]
        rows.append(
            [
                _e(n),
                _f(e.get("fx_px")),
                _f(e.get("fy_px")),
                _f(e.get("fx_percent"), 3),
                _f(e.get("fy_percent"), 3),
                f"±{_g(e.get('focal_target_percent'))}",
                _pass(fails),
                _f(e.get("cx_px")),
                _f(e.get("cy_px")),
                _f(e.get("distortion_px")),
            ]
        )
    parts.append(
        _table(
            INTRINSICS_HEAD,
            rows,
            numeric=(1, 2, 3, 4, 5, 7, 8, 9),
            raw=True,
            caption="Intrinsics; distortion px: how far apart the two distortion models put a "
            "pixel, at most over the image (not judged)",
        )
    )
    rows = []
    for p in cmp.get("pairs") or []:
        fails = [
            f for f, k in (("rot", "rotation_ok"), ("trans", "translation_ok")) if p.get(k) is False
        ]
        rows.append(
            [
                _e(f"{p.get('a')} – {p.get('b')}"),
                _f(p.get("rotation_deg"), 3),
                _g(p.get("target_deg")),
                _f(p.get("translation_mm"), 2),
                _g(p.get("target_mm")),
                _pass(fails),
            ]
        )
    if rows:
        parts.append(
            _table(
                [
                    "pair",
                    "rotation error °",
                    "target °",
                    "translation error mm",
                    "target mm",
                    "pose",
                ],
                rows,
                numeric=(1, 2, 3, 4),
                raw=True,
                caption="Relative pose of every pair, inv(T_rig_a) @ T_rig_b, estimate against "
                "truth",
            )
        )
    parts.append(_verdict_box(_comparison_verdict(cmp)) + "</section>")
    return "".join(parts)


def _pass(failed: list[str]) -> str:
    return (
        "<span class='good'>pass</span>"
        if not failed
        else f"<span class='bad'>FAIL ({_e(', '.join(failed))})</span>"
    )


def _run(report: Mapping[str, Any], command: str | None, versions: Mapping[str, str]) -> str:
    board = report.get("board") or {}
    rows = []
    if command:
        rows.append(["command", f"<code>{_e(command)}</code>"])
    if report.get("capture"):
        rows.append(["capture", f"<code>{_e(report['capture'])}</code>"])
    if board:
        rows.append(["board", _e(_board_text(board))])
    if _finite(report.get("min_views")):
        rows.append(["fewest views per sensor", _e(report["min_views"])])
    rows.append(["report format", _e(report.get("format", "?"))])
    if versions:
        rows.append(["software", _e(", ".join(f"{k} {v}" for k, v in versions.items()))])
    return (
        "<section id='run'><h2>How this was made</h2>"
        + _table(["", ""], rows, raw=True)
        + "</section>"
    )


def _board_text(board: Mapping[str, Any]) -> str:
    """:meth:`Board.describe` of the report's board (its polarity keys in brackets); a
    board the report format does not know: its keys as they are."""
    try:
        text, described = board_from_dict(board).describe(), set(board) - set(POLARITY_KEYS)
    except ValueError:
        text, described = "board", set()
    extra = {k: v for k, v in board.items() if k not in described}
    if extra:
        text += " (" + ", ".join(f"{_label(k)}: {v}" for k, v in extra.items()) + ")"
    return text


# -- the page ---------------------------------------------------------------------------


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
    sub = [f"capture <code>{_e(capture)}</code>"] if capture else []
    if report.get("board"):
        sub.append(_e(_board_text(report["board"])))
    if generated:
        sub.append(f"made {_e(generated)}")
    toc = [("summary", "Summary and verdict")]
    toc += [(f"sensor-{_id(n)}", n) for n in sensors]
    body = [_summary(report)]
    body += [_sensor_section(report, n, i, corners) for i, n in enumerate(sensors)]
    for anchor, label, block in (
        ("pairs", "Relative poses", _pairs(report)),
        ("decisions", "Decisions and other findings", _decisions(report)),
        ("outliers", "Outliers", _outliers(report)),
        ("views", "Every view", _views_table(report)),
        ("truth", "Against the true rig", _comparison(report)),
        ("run", "How this was made", _run(report, command, versions or {})),
    ):
        if block:
            toc.append((anchor, label))
            body.append(block)
    nav = (
        "<nav><ol>"
        + "".join(f"<li><a href='#{a}'>{_e(t)}</a></li>" for a, t in toc)
        + "</ol></nav>"
    )
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<meta http-equiv='Content-Security-Policy' content=\"{CSP}\">"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        "<meta name='generator' content='trifuse'>"
        f"<title>{_e(title)}</title><style>{_STYLE}</style></head><body>"
        f"<header><h1>{_e(title)}</h1><p class='sub'>{' · '.join(sub)}</p></header>"
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
