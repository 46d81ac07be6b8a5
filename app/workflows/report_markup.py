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
