"""The calibration report's sections on the whole calibration (:mod:`report_html`): summary
and verdict (with the sensors calibrated alone), decisions and any key the report gains
later, the outliers, every view, the comparison with a true rig, how the report was made.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from trifuse.app.workflows.cross_validation import eye_line
from trifuse.app.workflows.report_format import (
    INTRINSICS_HEAD,
    POLARITY_HEAD,
    polarity_caption,
    polarity_rows,
)
from trifuse.app.workflows.report_markup import (
    advice_block,
    and_list,
    esc,
    fixed,
    generic,
    html_id,
    html_table,
    is_finite_number,
    key_label,
    pm,
    significant,
    verdict_box,
    views_list,
)
from trifuse.app.workflows.report_sensors import sigma_of, sigma_vector
from trifuse.app.workflows.report_svg import curves_svg
from trifuse.calib.board import POLARITY_KEYS, board_from_dict

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
        "unreadable_images",
        "cross_validation",
    }
)
"""Top-level report keys with a section of their own; any other is shown generically."""


MAX_CORNER_ROWS = 100
"""Outlier corners listed one by one; the rest are counted (report.json has them all)."""


def summary_section(report: Mapping[str, Any]) -> str:
    """The summary: the verdicts, what was calibrated and what not, the image files that
    could not be read, the advice, a row per sensor, the intrinsics-only sensors and the
    notes."""
    sensors = report.get("sensors") or {}
    excluded = report.get("excluded_sensors") or {}
    parts = ["<section id='summary'><h2>Summary and verdict</h2>"]
    if report.get("verdict") is not None:
        parts.append(verdict_box(report["verdict"]))
    cmp = report.get("comparison")
    if isinstance(cmp, Mapping) and "passed" in cmp:
        parts.append(verdict_box(_comparison_verdict(cmp), "Against the true rig"))
    calibrated = (
        f"{len(sensors)} sensor(s) calibrated ({esc(and_list(list(sensors)))})"
        if sensors
        else "no sensor calibrated"
    )
    if alone := list(report.get("sensors_intrinsics_only") or {}):
        calibrated += f", intrinsics only ({esc(and_list(alone))}: pose unknown)"
    rms = report.get("rms_px")
    line = f"<p>{calibrated}, reference <b>{esc(report.get('reference', '–'))}</b>"
    if is_finite_number(rms):
        line += f", overall RMS reprojection error <b>{rms:.3f} px</b>"
    n_views = len(report.get("detections") or report.get("views") or {})
    line += f", {n_views} view(s)"
    if is_finite_number(report.get("seconds")):
        line += f", solved in {report['seconds']:.1f} s"
    parts.append(line + ".</p>")
    if excluded:
        parts.append(
            "<p class='bad'><b>Not calibrated:</b></p><ul>"
            + "".join(f"<li><b>{esc(s)}</b>: {esc(why)}</li>" for s, why in excluded.items())
            + "</ul>"
        )
    parts.append(_unreadable(report.get("unreadable_images") or []))
    if report.get("advice"):
        parts.append(advice_block(report["advice"]))
    rows = []
    for name, s in sensors.items():
        intr = s.get("intrinsics") or {}
        cov = s.get("coverage") or {}
        size = s.get("image_size") or ["?", "?"]
        rot = float(np.linalg.norm(sigma_vector(s, "rotation_deg")))
        trans = float(np.linalg.norm(sigma_vector(s, "translation_m", 1000.0)))
        reference = name == report.get("reference")
        rows.append(
            [
                f"<a href='#sensor-{html_id(name)}'>{esc(name)}</a>",
                f"{esc(size[0])}&nbsp;×&nbsp;{esc(size[1])}",
                f"{esc(s.get('views_used', '?'))} / {esc(s.get('views_detected', '?'))}",
                fixed(s.get("rms_px"), 3),
                pm(intr.get("fx"), sigma_of(s, "fx")),
                pm(intr.get("fy"), sigma_of(s, "fy")),
                "reference" if reference else fixed(rot, 3),
                "reference" if reference else fixed(trans, 2),
                f"{100 * cov['reached']:.0f}" if is_finite_number(cov.get("reached")) else "–",
            ]
        )
    if rows:
        parts.append(
            html_table(
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
            + "".join(f"<li>{esc(n)}</li>" for n in notes)
            + "</ul>"
        )
    parts.append("</section>")
    return "".join(parts)


def _unreadable(images: Sequence[Any]) -> str:
    """The image files skipped because they could not be read (``unreadable_images``):
    each file and why, or nothing."""
    items = [
        f"<li><b>{esc(u.get('file'))}</b>: {esc(u.get('why'))}"
        + (" (a TOF distance image: not needed to calibrate)" if u.get("distance") else "")
        + "</li>"
        for u in images
        if isinstance(u, Mapping)
    ]
    if not items:
        return ""
    return f"<p class='bad'><b>Unreadable images, skipped:</b></p><ul>{''.join(items)}</ul>"


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
                esc(name),
                f"{esc(size[0])}&nbsp;×&nbsp;{esc(size[1])}",
                f"{esc(s.get('views_used', '?'))} / {esc(s.get('views_detected', '?'))}",
                fixed(s.get("rms_px"), 3),
                *(pm(intr.get(k), sigma_of(s, k)) for k in ("fx", "fy", "cx", "cy")),
            ]
        )
        why.setdefault(str(s.get("pose_unknown") or "pose unknown"), []).append(name)
    table = html_table(
        ["sensor", "image px", "views used / found", "RMS px", "fx px", "fy px", "cx px", "cy px"],
        rows,
        numeric=(1, 2, 3, 4, 5, 6, 7),
        raw=True,
        caption="Sensors calibrated alone, on their own views, ± 1-sigma; not in the rig",
        attrs=" id='intrinsics-only' class='small'",
    )
    reasons = "".join(f"<li><b>{esc(and_list(n))}</b>: {esc(w)}</li>" for w, n in why.items())
    return f"<h3>Intrinsics only: pose unknown</h3>{table}<ul>{reasons}</ul>"


def _comparison_verdict(cmp: Mapping[str, Any]) -> str:
    fails = list(cmp.get("failures") or [])
    n = len(cmp.get("sensors") or {})
    if cmp.get("passed"):
        return f"PASS: every judged figure meets its target ({n} sensors and every pair)."
    shown = ", ".join(fails[:6]) + (f" and {len(fails) - 6} more" if len(fails) > 6 else "")
    return f"FAIL: {len(fails)} figure(s) miss their target: {shown}."


def decisions_section(report: Mapping[str, Any]) -> str:
    """The board polarity and what it decided, then every top-level key without a
    section of its own (:data:`KNOWN_KEYS`); empty when there is none."""
    parts = []
    polarity = report.get("polarity") or {}
    if polarity:
        parts.append(
            html_table(
                POLARITY_HEAD,
                polarity_rows(polarity),
                numeric=(3, 4),
                caption=esc(polarity_caption(polarity)),
            )
        )
        turned = {n: p for n, p in polarity.items() if p.get("turned") or p.get("turned_views")}
        for n, p in turned.items():
            what = "its corners were relabelled by the half turn" if p.get("turned") else ""
            views = p.get("turned_views") or []
            if views:
                what += ("; " if what else "") + f"view(s) {views_list(views)} turned alone"
            parts.append(f"<p>{esc(n)}: {esc(what)}.</p>")
        problems = {n: p["problem"] for n, p in polarity.items() if p.get("problem")}
        for n, why in problems.items():
            parts.append(f"<p class='bad'>{esc(n)} refused: {esc(why)}</p>")
    for key, value in report.items():
        if key not in KNOWN_KEYS and value not in (None, [], {}):
            parts.append(f"<h3>{esc(key_label(key).capitalize())}</h3>" + generic(value))
    if not parts:
        return ""
    return (
        "<section id='decisions'><h2>Decisions and other findings</h2>"
        + "".join(parts)
        + "</section>"
    )


def outliers_section(report: Mapping[str, Any]) -> str:
    """The views and corners left out as outliers, with their error and why."""
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
            html_table(
                ["view", "sensor", "RMS px", "why"],
                [
                    [
                        str(o["view"]),
                        str(o["sensor"]),
                        fixed(o.get("error_px")),
                        str(o.get("reason")),
                    ]
                    for o in views
                ],
                numeric=(2,),
            )
        )
    if corners:
        shown = corners[:MAX_CORNER_ROWS]
        parts.append(
            html_table(
                ["view", "sensor", "corner", "error px", "why"],
                [
                    [
                        str(o["view"]),
                        str(o["sensor"]),
                        str(o["corner"]),
                        fixed(o.get("error_px")),
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


def views_section(report: Mapping[str, Any]) -> str:
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
        row = [esc(v)]
        for s in sensors:
            e = (views.get(v) or {}).get(s)
            d = (detections.get(v) or {}).get(s)
            if e is not None:
                rms = fixed(e.get("rms_px"), 3)
                row.append(f"<span class='bad'>{rms} out</span>" if e.get("outlier") else rms)
            elif d is not None and not d.get("found"):
                n = reasons.setdefault(str(d.get("reason") or "not found"), len(reasons) + 1)
                row.append(f"<span class='muted'>× [{n}]</span>")
            elif d is not None:
                row.append("<span class='muted'>found</span>" if s in excluded else "found")
            else:
                row.append("")
        rows.append(row)
    legend = "".join(f"<li>[{n}] {esc(r)}</li>" for r, n in reasons.items())
    return (
        "<section id='views'><h2>Every view</h2>"
        + html_table(
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


def comparison_section(report: Mapping[str, Any]) -> str:
    """The errors against the true rig (``report["comparison"]``): per sensor, per
    pair and the verdict; empty without a comparison."""
    cmp = report.get("comparison")
    if not isinstance(cmp, Mapping):
        return ""
    parts = [
        "<section id='truth'><h2>Against the true rig</h2>",
        f"<p>Compared with <code>{esc(cmp.get('truth', '?'))}</code> (reference "
        f"{esc(cmp.get('truth_reference', '?'))}); errors are estimate − truth.</p>",
    ]
    for what in ("estimate", "truth"):
        only = cmp.get(f"only_in_{what}") or []
        if only:
            parts.append(f"<p>Only in the {what}, not compared: {esc(', '.join(only))}.</p>")
    rows = []
    for n, e in (cmp.get("sensors") or {}).items():
        fails = [f for f in ("fx", "fy") if e.get(f"{f}_ok") is False]
        rows.append(
            [
                esc(n),
                fixed(e.get("fx_px")),
                fixed(e.get("fy_px")),
                fixed(e.get("fx_percent"), 3),
                fixed(e.get("fy_percent"), 3),
                f"±{significant(e.get('focal_target_percent'))}",
                _pass(fails),
                fixed(e.get("cx_px")),
                fixed(e.get("cy_px")),
                fixed(e.get("distortion_px")),
            ]
        )
    parts.append(
        html_table(
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
                esc(f"{p.get('a')} – {p.get('b')}"),
                fixed(p.get("rotation_deg"), 3),
                significant(p.get("target_deg")),
                fixed(p.get("translation_mm"), 2),
                significant(p.get("target_mm")),
                _pass(fails),
            ]
        )
    if rows:
        parts.append(
            html_table(
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
    parts.append(verdict_box(_comparison_verdict(cmp)) + "</section>")
    return "".join(parts)


def _pass(failed: list[str]) -> str:
    return (
        "<span class='good'>pass</span>"
        if not failed
        else f"<span class='bad'>FAIL ({esc(', '.join(failed))})</span>"
    )


CROSS_VALIDATION_TABLE_M = (0.5, 1.0, 2.0, 3.0, 5.0, 10.0)
"""The distances of the cross-validation's table (the plot has them all), metres."""


def cross_validation_section(report: Mapping[str, Any]) -> str:
    """The cross-validation (``report["cross_validation"]``): how it was made, then per eye
    its line, a plot of the halves' difference against distance beside what their sigmas
    predict, and a table at :data:`CROSS_VALIDATION_TABLE_M`; why it was skipped; empty
    without one."""
    cv = report.get("cross_validation")
    if not isinstance(cv, Mapping):
        return ""
    parts = ["<section id='cross-validation'><h2>Cross-validation</h2>"]
    if cv.get("skipped"):
        parts.append(f"<p>Not run: {esc(cv['skipped'])}.</p></section>")
        return "".join(parts)
    halves = {h: list(v) for h, v in (cv.get("views") or {}).items()}
    which = "; ".join(
        f"{esc(h)}: {len(v)} views ({esc(views_list(v, 6))})" for h, v in halves.items()
    )
    factor = cv.get("factor")
    parts.append(
        f"<p>The views were split into two halves, alternate views in capture order ({which}), "
        "each calibrated alone with the options of the full calibration. Per eye, each half's "
        f"rig fuses the same {esc(cv.get('tof') or 'TOF')} measurements of a wall facing the "
        "colour camera at each distance; the figures are how far apart the two put the same "
        "thermal value, colour pixels, over the pixels that see the wall (median, 95th "
        "percentile, largest). The predicted difference is √(σ<sub>A</sub>² + σ<sub>B</sub>²), "
        "each half's registration 1-sigma from its own covariance (median over the wall); the "
        "halves are consistent when they differ by at most "
        f"{esc(significant(factor))} × that at every distance. Solved in "
        f"{fixed(cv.get('seconds'), 1)} s.</p>"
    )
    for name, e in (cv.get("eyes") or {}).items():
        parts.append(f"<h3>{esc(name)} eye ({esc(e.get('color'))} – {esc(e.get('thermal'))})</h3>")
        tone = "" if e.get("consistent") is None else ("good" if e["consistent"] else "bad")
        box = f"box box-{tone}" if tone else "box"
        parts.append(f"<div class='{box}'><p><b>{esc(eye_line(name, e))}</b></p></div>")
        if e.get("skipped"):
            continue
        d = list(e.get("distance_m") or [])
        plot = curves_svg(
            d,
            [
                ("halves' difference, median", e.get("median_px") or [], "#3b6ea5", ""),
                ("halves' difference, 95 %", e.get("p95_px") or [], "#9bb8d8", ""),
                ("predicted difference", e.get("predicted_difference_px") or [], "#d62728", "5 3"),
                ("full calibration 1-sigma", e.get("predicted_sigma_px") or [], "#888", "2 2"),
            ],
            "distance of the wall, m",
            "colour px",
        )
        parts.append(
            f"<figure>{plot}<figcaption>How far apart the halves' fusions put a thermal value "
            "against the distance of a wall facing the colour camera, and what their "
            "uncertainty predicts.</figcaption></figure>"
        )
        rows = []
        for at in CROSS_VALIDATION_TABLE_M:
            if at not in d:
                continue
            i = d.index(at)
            rows.append(
                [f"{at:g}"]
                + [
                    fixed((e.get(k) or [None] * len(d))[i], 3)
                    for k in ("median_px", "p95_px", "max_px", "predicted_difference_px",
                              "predicted_sigma_px")
                ]
            )  # fmt: skip
        parts.append(
            html_table(
                ["m", "median px", "95 % px", "max px", "predicted px", "full σ px"],
                rows,
                numeric=(0, 1, 2, 3, 4, 5),
                caption="The halves' difference and what their sigmas predict; full σ: the "
                "full calibration's registration 1-sigma",
                attrs=" class='small'",
            )
        )
    parts.append("</section>")
    return "".join(parts)


def run_section(report: Mapping[str, Any], command: str | None, versions: Mapping[str, str]) -> str:
    """How the report was made: the command, capture, board, fewest views, format and
    software versions."""
    board = report.get("board") or {}
    rows = []
    if command:
        rows.append(["command", f"<code>{esc(command)}</code>"])
    if report.get("capture"):
        rows.append(["capture", f"<code>{esc(report['capture'])}</code>"])
    if board:
        rows.append(["board", esc(report_board_text(board))])
    if is_finite_number(report.get("min_views")):
        rows.append(["fewest views per sensor", esc(report["min_views"])])
    rows.append(["report format", esc(report.get("format", "?"))])
    if versions:
        rows.append(["software", esc(", ".join(f"{k} {v}" for k, v in versions.items()))])
    return (
        "<section id='run'><h2>How this was made</h2>"
        + html_table(["", ""], rows, raw=True)
        + "</section>"
    )


def report_board_text(board: Mapping[str, Any]) -> str:
    """:meth:`Board.describe` of the report's board (its polarity keys in brackets); a
    board the report format does not know: its keys as they are."""
    try:
        text, described = board_from_dict(board).describe(), set(board) - set(POLARITY_KEYS)
    except ValueError:
        text, described = "board", set()
    extra = {k: v for k, v in board.items() if k not in described}
    if extra:
        text += " (" + ", ".join(f"{key_label(k)}: {v}" for k, v in extra.items()) + ")"
    return text
