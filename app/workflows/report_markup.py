"""The calibration report's HTML text (:mod:`report_html`): numbers, a value ± its 1-sigma
to the decimals its sigma calls for, escaping, tables, any JSON value shown generically,
verdicts in coloured boxes with their figures and advice.

Shared by the page's sections (:mod:`report_sections`, :mod:`report_sensors`) and its
plots (:mod:`report_svg`): pure string building, no I/O.
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

from trifuse.calib.numbers import is_int_or_float


def esc(text: Any) -> str:
    """``text`` as HTML text, quotes escaped too (safe in an attribute value)."""
    return html.escape(str(text), quote=True)


def is_finite_number(x: Any) -> bool:
    """Whether ``x`` is an int or float (never a bool) and finite."""
    return is_int_or_float(x) and math.isfinite(x)


def fixed(x: Any, digits: int = 2) -> str:
    """A number with ``digits`` decimals; ``–`` when undefined."""
    return f"{x:.{digits}f}" if is_finite_number(x) else "–"


def significant(x: Any) -> str:
    """A number of unknown scale: 4 significant digits (integers as they are)."""
    if not is_int_or_float(x):
        return esc(x)
    if isinstance(x, int):
        return str(x)
    return f"{x:.4g}" if math.isfinite(x) else "–"


def sigma_decimals(sigma: Any, fallback: int = 2, most: int = 6) -> int:
    """Decimals that show ``sigma`` with two significant digits (``fallback`` when it is
    undefined or zero), at most ``most``."""
    if not is_finite_number(sigma) or sigma <= 0:
        return fallback
    return int(min(most, max(0, 1 - math.floor(math.log10(sigma)))))


def pm(value: Any, sigma: Any, fallback: int = 2) -> str:
    """``value ± sigma``, both to the decimals of sigma's second significant digit."""
    d = sigma_decimals(sigma, fallback)
    if not is_finite_number(sigma):
        return fixed(value, d)
    return f"{fixed(value, d)} ± {fixed(sigma, d)}"


def html_id(name: str) -> str:
    """``name`` as an HTML id or anchor: every character but letters, digits, ``_``
    and ``-`` replaced by ``-``."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", name)


def and_list(names: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``: names as a phrase (at least one name)."""
    names = list(names)
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


def views_list(views: Sequence[str], at_most: int = 12) -> str:
    """View names, comma-separated, the first ``at_most`` of them and how many more."""
    shown = ", ".join(views[:at_most])
    return shown + (f" and {len(views) - at_most} more" if len(views) > at_most else "")


def html_table(
    head: Sequence[str],
    rows: Sequence[Sequence[str]],
    numeric: Sequence[int] = (),
    caption: str = "",
    raw: bool = False,
    attrs: str = "",
) -> str:
    """A table (no header row when ``head`` is all empty); cells are escaped unless
    ``raw`` (then they are HTML already); the columns in ``numeric`` are right-aligned."""
    cell = (lambda c: c) if raw else esc
    cls = [' class="n"' if i in numeric else "" for i in range(len(head))]
    out = [f"<p class='caption'>{caption}</p>"] if caption else []
    out.append(f"<table{attrs}>")
    if any(head):
        heads = "".join(f"<th{c}>{esc(h)}</th>" for h, c in zip(head, cls, strict=True))
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
        return significant(value)
    if isinstance(value, str):
        return esc(value)
    if depth > 4:
        return f"<code>{esc(value)}</code>"
    if isinstance(value, Sequence):
        items = list(value)
        if not items:
            return "–"
        if all(is_int_or_float(v) for v in items):
            return ", ".join(significant(v) for v in items)
        if all(isinstance(v, Mapping) for v in items):
            keys = list(dict.fromkeys(k for v in items for k in v))
            rows = [[generic(v.get(k), depth + 1) for k in keys] for v in items]
            return html_table([key_label(k) for k in keys], rows, raw=True)
        return "<ul>" + "".join(f"<li>{generic(v, depth + 1)}</li>" for v in items) + "</ul>"
    if isinstance(value, Mapping):
        if not value:
            return "–"
        if all(isinstance(v, scalar) for v in value.values()):
            rows = [[esc(key_label(k)), generic(v, depth + 1)] for k, v in value.items()]
            return html_table(["", ""], rows, raw=True)
        inner = list(value.values())
        if all(isinstance(v, Mapping) for v in inner) and all(
            isinstance(x, scalar) for v in inner for x in v.values()
        ):
            keys = list(dict.fromkeys(k for v in inner for k in v))
            rows = [
                [esc(n), *(generic(v.get(k), depth + 1) for k in keys)] for n, v in value.items()
            ]
            return html_table(["", *(key_label(k) for k in keys)], rows, raw=True)
        return (
            "<dl>"
            + "".join(
                f"<dt>{esc(key_label(k))}</dt><dd>{generic(v, depth + 1)}</dd>"
                for k, v in value.items()
            )
            + "</dl>"
        )
    return esc(value)


def key_label(key: Any) -> str:
    """A report key as words: ``views_used`` -> ``views used``."""
    return str(key).replace("_", " ")


def verdict_box(value: Any, title: str = "Verdict") -> str:
    """A verdict in a coloured box: a graded one (calib.verdict's ``grade``, ``line``,
    ``figures``, ``advice``) as its grade, sentence and figures; text as it is; any other
    mapping generically."""
    if isinstance(value, str):
        body = f"<p><b>{esc(value)}</b></p>"
    elif is_graded(value):
        body = _graded_body(value)
    else:
        body = generic(value)
    tone = _tone(value)
    cls = f"box box-{tone}" if tone else "box"
    return f'<div class="{cls}"><p class="small muted">{esc(title)}</p>{body}</div>'


def is_graded(value: Any) -> bool:
    """Whether ``value`` is a graded verdict (calib.verdict: a mapping with a ``grade``
    text)."""
    return isinstance(value, Mapping) and isinstance(value.get("grade"), str)


def grade_badge(grade: Any) -> str:
    """A verdict's grade, upper case and bold, in its tone's colour."""
    return f"<b class='{_tone(str(grade))}'>{esc(str(grade).upper())}</b>"


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
        entries = [e for e in entries if is_graded(e)]
        parts.append(f"<p style='font-size:12pt'>{grade_badge(v['grade'])}</p>")
        rows = [
            [esc(e.get("label", "")), grade_badge(e["grade"]), esc(_sentence(e))] for e in entries
        ]
        if rows:
            parts.append(html_table(["", "grade", "why"], rows, raw=True))
        share, factor = v.get("sigma_share"), v.get("poor_factor")
        if is_finite_number(share) and is_finite_number(factor):
            parts.append(
                "<p class='small muted'>A 1-sigma meets its target when it is at most "
                f"{significant(share)} × the accuracy target; good: every judged 1-sigma meets its "
                f"target, poor: one exceeds it {significant(factor)} times, usable: in between.</p>"
            )
    else:
        parts.append(f"<p>{grade_badge(v['grade'])} {esc(_sentence(v))}</p>")
        figures = figure_rows(v.get("figures"))
        if figures:
            parts.append(figures_table(FIGURE_HEAD, figures))
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


def figures_table(head: Sequence[str], rows: list[list[str]]) -> str:
    """A table of verdict figures (:func:`figure_rows`, maybe after leading cells), without
    the columns empty in every row."""
    keep = [i for i in range(len(head)) if any(r[i] for r in rows)]
    numeric = [k for k, i in enumerate(keep) if head[i] in ("1-sigma", "target", "σ / target")]
    return html_table(
        [head[i] for i in keep], [[r[i] for i in keep] for r in rows], numeric=numeric, raw=True
    )


def figure_rows(figures: Any) -> list[list[str]]:
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
            per_axis = ", ".join(f"{n} {fixed(a, d)}" for n, a in zip(names, axes, strict=False))
        target = f.get("target")
        rows.append(
            [
                esc(f.get("what", "")),
                esc(f"{fixed(f.get('sigma'), d)}{sep}{unit}"),
                esc(f"{significant(target)}{sep}{unit}")
                if is_finite_number(target)
                else "not judged",
                fixed(f.get("ratio"), 2) if is_finite_number(f.get("ratio")) else "",
                esc(per_axis),
                esc(f.get("dominant_axis") or ""),
            ]
        )
    return rows


def advice_block(value: Any) -> str:
    """An "Advice" heading and the advice (a text, or a list of them, as a list)."""
    if isinstance(value, str):
        value = [value]
    return "<h3>Advice</h3>" + generic(value)
