"""How results are shown to people, shared by the CLI and the console's panels."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from trifuse.app.workflows.report_markup import and_list
from trifuse.calib.coverage import COARSE_NAMES, coarse_reached, reached_fraction

if TYPE_CHECKING:
    from trifuse.calib.rig_compare import RigComparison

SENSOR_COLOURS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
)
"""One colour per sensor in plots (RGB; matplotlib's tab10): ``sensor_colour(i)``."""

NEVER = "–"
"""Table 1's "never reaches the threshold in the range"."""


def sensor_colour(i: int) -> tuple[int, int, int]:
    """The plot colour of the ``i``-th sensor (RGB 0-255), cycling."""
    return SENSOR_COLOURS[i % len(SENSOR_COLOURS)]


def pixel_cell(u: float, v: float) -> str:
    """A TOF pixel ``(u, v)`` for people: one decimal, e.g. ``(88.0, 71.2)``."""
    return f"({u:.1f}, {v:.1f})"


def limit_distance_cell(value_m: float | None, range_max_m: float) -> str:
    """A Table 1 cell: the distance (m) at which the shift reaches the threshold."""
    if value_m is None:
        return NEVER
    if value_m >= range_max_m:
        return f"≥{range_max_m:.2f}"
    return f"{value_m:.2f}"


def coverage_sentence(corner_counts: np.ndarray, sparse_at_most: float = 0.5) -> str:
    """How much of a sensor's image the board's corners reached, in one short sentence.

    ``corner_counts`` is the (rows, cols) grid of ``calib.coverage.Coverage``; the share of
    its cells holding a corner is given in whole percent (rounded down, so that 100 % means
    every cell), then the coarse regions of ``COARSE_NAMES`` that no corner reached
    ("none in ...") and those where at most ``sparse_at_most`` of the cells were reached
    ("few in ..."): where to hold the board next.
    """
    reached = reached_fraction(corner_counts)
    if reached == 0.0:
        return "no corner anywhere in the image"
    if reached == 1.0:
        return "corners cover the whole image"
    fractions = coarse_reached(corner_counts)
    none, few = [], []
    for r in range(3):
        for c in range(3):
            f = fractions[r, c]
            if f == 0.0:
                none.append(COARSE_NAMES[r][c])
            elif f <= sparse_at_most:
                few.append(COARSE_NAMES[r][c])
    text = f"corners cover {math.floor(100 * reached + 1e-9)} % of the image"  # 0.29 * 100
    if none:
        text += f"; none in the {and_list(none)}"
    if few:
        text += f"; few in the {and_list(few)}"
    return text


# -- a calibrated rig against the truth (calib.rig_compare) ---------------------------------

PASS, FAIL = "pass", "FAIL"


def result_cell(failed: list[str]) -> str:
    """``pass``, or ``FAIL`` naming the figures that miss their target."""
    return PASS if not failed else f"{FAIL} ({', '.join(failed)})"


def verdict_line(cmp: RigComparison) -> str:
    """One line: do all judged figures meet their targets, and if not, which miss."""
    n = cmp.n_figures
    if cmp.passed:
        return (
            f"Verdict: PASS, all {n} judged figures meet their targets "
            f"({len(cmp.intrinsics)} sensors' focal lengths, {len(cmp.pairs)} pairs' poses)."
        )
    fails = cmp.failures
    shown = ", ".join(fails[:6]) + (f" and {len(fails) - 6} more" if len(fails) > 6 else "")
    return f"Verdict: FAIL, {len(fails)} of {n} judged figures miss their target: {shown}."


INTRINSICS_HEAD = [
    "sensor",
    "fx px",
    "fy px",
    "fx %",
    "fy %",
    "target %",
    "focal",
    "cx px",
    "cy px",
    "distortion px",
]
PAIRS_HEAD = ["pair", "rot °", "target °", "trans mm", "target mm", "pose"]


def intrinsics_rows(cmp: RigComparison) -> list[list[str]]:
    """Rows under ``INTRINSICS_HEAD``: errors estimate - truth, the focal target (±%) and
    pass/fail, the largest pixel displacement between the distortion models."""
    rows = []
    for name, e in cmp.intrinsics.items():
        failed = [f for f, ok in (("fx", e.fx_ok), ("fy", e.fy_ok)) if not ok]
        dist = f"{e.distortion_px:.2f}" if math.isfinite(e.distortion_px) else "?"
        rows.append(
            [
                name,
                f"{e.fx_px:+.2f}",
                f"{e.fy_px:+.2f}",
                f"{100 * e.fx_rel:+.3f}",
                f"{100 * e.fy_rel:+.3f}",
                f"±{100 * e.focal_target_rel:g}",
                result_cell(failed),
                f"{e.cx_px:+.2f}",
                f"{e.cy_px:+.2f}",
                dist,
            ]
        )
    return rows


def pair_rows(cmp: RigComparison) -> list[list[str]]:
    """Rows under ``PAIRS_HEAD``: rotation (deg) and translation (mm) errors of each
    pair's relative pose, the targets and pass/fail."""
    rows = []
    for p in cmp.pairs:
        failed = [f for f, ok in (("rot", p.rotation_ok), ("trans", p.translation_ok)) if not ok]
        rows.append(
            [
                f"{p.a} – {p.b}",
                f"{p.rotation_deg:.3f}",
                f"{p.target_deg:g}",
                f"{1000 * p.translation_m:.2f}",
                f"{1000 * p.target_m:g}",
                result_cell(failed),
            ]
        )
    return rows


TRUTH_HEAD = ["sensor", "rot °", "trans mm", "fx %", "fy %", "targets"]


def truth_rows(cmp: RigComparison, reference: str) -> list[list[str]]:
    """Rows under ``TRUTH_HEAD``, one per sensor (the console's compact table): the error
    of its pose relative to ``reference`` (rotation deg, translation mm; ``–`` for the
    reference itself), its focal-length errors in %, and pass/fail of those four figures."""
    rows = []
    for name, e in cmp.intrinsics.items():
        failed = [f for f, ok in (("fx", e.fx_ok), ("fy", e.fy_ok)) if not ok]
        rot = trans = NEVER
        if name != reference and reference in cmp.intrinsics:
            p = cmp.pair(reference, name)
            rot, trans = f"{p.rotation_deg:.3f}", f"{1000 * p.translation_m:.2f}"
            pose = (("rot", p.rotation_ok), ("trans", p.translation_ok))
            failed += [f for f, ok in pose if not ok]
        rows.append(
            [
                name,
                rot,
                trans,
                f"{100 * e.fx_rel:+.3f}",
                f"{100 * e.fy_rel:+.3f}",
                result_cell(failed),
            ]
        )
    return rows


def text_table(head: list[str], rows: list[list[str]], gap: str = "  ") -> list[str]:
    """Lines of a plain-text table: the first column left-aligned, the others right-aligned,
    except the last, left-aligned (a pass/fail or free-text column)."""
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]

    def line(cells: list[str]) -> str:
        out = []
        for i, (c, w) in enumerate(zip(cells, widths, strict=True)):
            out.append(c.ljust(w) if i in (0, len(cells) - 1) else c.rjust(w))
        return gap.join(out).rstrip()

    return [line(head), *(line(r) for r in rows)]


def markdown_table(head: list[str], rows: list[list[str]]) -> list[str]:
    """Lines of a Markdown table (the console's panels)."""
    return [
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
        *("| " + " | ".join(r) + " |" for r in rows),
    ]


def comparison_text(cmp: RigComparison, estimate: str, truth: str) -> str:
    """The comparison for a terminal: what was compared, the intrinsics table, the pairs
    table, sensors in one rig only, and the verdict line. ``estimate`` and ``truth`` name
    the two rigs (file names)."""
    lines = [
        f"Comparing {estimate} (reference {cmp.estimate_reference}) with {truth} "
        f"(reference {cmp.truth_reference}): {len(cmp.intrinsics)} sensors in common",
    ]
    for what, names in (("estimate", cmp.only_in_estimate), ("truth", cmp.only_in_truth)):
        if names:
            lines.append(f"only in the {what}, not compared: {', '.join(names)}")
    lines += ["", "Intrinsics, estimate - truth:"]
    lines += text_table(INTRINSICS_HEAD, intrinsics_rows(cmp))
    lines.append(
        "(distortion px: how far apart the two distortion models put a pixel, at most, "
        "over the image)"
    )
    if cmp.pairs:
        lines += [
            "",
            "Relative pose of every pair, inv(T_rig_a) @ T_rig_b, estimate against truth:",
            *text_table(PAIRS_HEAD, pair_rows(cmp)),
        ]
    lines += ["", verdict_line(cmp)]
    return "\n".join(lines)


# -- board polarity per sensor (calib.polarity, the report's ``polarity``) ----------------

POLARITY_HEAD = ["sensor", "squares", "found by", "spread as detected °", "half-turned °", "ratio"]
POLARITY_PANEL_HEAD = ["sensor", "black squares", "found by", "spread °"]

_FOUND_BY = {
    "colour": "printed colours",
    "data": "poses vs {anchor}",
    "board.yaml": "board.yaml",
    "assumed": "assumed (no colour camera)",
    "undecided": "not decided",
}


def _degrees(value: float | None) -> str:
    return NEVER if value is None else f"{value:.2f}"


def polarity_rows(polarity: dict[str, dict]) -> list[list[str]]:
    """Rows under ``POLARITY_HEAD`` from a report's ``polarity`` block: per sensor which
    squares read dark/cold or bright/hot, how that was found, the spread (degrees) of its
    per-view poses against the anchor's for its corners as detected and half-turned, and
    their ratio (how decisive); ``turned`` when the corners were relabelled, ``REFUSED``
    when the sensor was left out (its reason is listed with the sensors not calibrated)."""
    rows = []
    for name, p in polarity.items():
        how = _FOUND_BY.get(p["decided_by"], p["decided_by"]).format(anchor=p.get("anchor"))
        if p["decided_by"] == "board.yaml" and p.get("anchor"):
            how += f", checked vs {p['anchor']}"
        spread = p.get("spread_deg") or {}
        ratio = p.get("ratio")
        cell = NEVER if not spread else ("∞" if ratio is None else f"×{ratio:.0f}")
        if p.get("problem"):
            cell += " REFUSED"
        elif p.get("turned"):
            cell += " turned"
        if p.get("turned_views"):
            cell += f" ({len(p['turned_views'])} view(s) turned alone)"
        rows.append(
            [
                name,
                p["polarity"],
                how,
                _degrees(spread.get("as_detected")),
                _degrees(spread.get("half_turned")),
                cell,
            ]
        )
    return rows


_SHORT_FOUND_BY = {"colour": "colours", "data": "poses", "undecided": "–"}


def polarity_panel_rows(polarity: dict[str, dict]) -> list[list[str]]:
    """Rows under ``POLARITY_PANEL_HEAD``: :func:`polarity_rows` narrowed for the console's
    side panel (about 280 px): the polarity in a word (``hot``, ``cold``, ``dark``,
    ``bright``; ``turned`` or ``REFUSED`` added), how it was found in a word, and the two
    spreads as ``as detected / half-turned`` degrees."""
    rows = []
    for name, p in polarity.items():
        word = p["polarity"].removeprefix("black squares ")
        if p.get("problem"):
            word += ", REFUSED"
        elif p.get("turned"):
            word += ", turned"
        spread = p.get("spread_deg") or {}
        cell = (
            f"{_degrees(spread.get('as_detected'))} / {_degrees(spread.get('half_turned'))}"
            if spread
            else NEVER
        )
        rows.append([name, word, _SHORT_FOUND_BY.get(p["decided_by"], p["decided_by"]), cell])
    return rows


def _with_anchors(polarity: dict[str, dict]) -> str:
    anchors = sorted({p["anchor"] for p in polarity.values() if p.get("anchor")})
    return f" with {', '.join(anchors)}" if anchors else ""


def polarity_panel_note(polarity: dict[str, dict]) -> str:
    """What :func:`polarity_panel_rows` shows, in a few words."""
    return (
        "found by the printed colours, or by how the per-view poses agree"
        f"{_with_anchors(polarity)}; "
        "spread: as detected / half-turned, the smaller wins"
    )


def polarity_note(polarity: dict[str, dict]) -> str:
    """What the polarity table's figures are, in a few words."""
    return (
        "thermal and TOF decided by how their per-view poses agree"
        f"{_with_anchors(polarity)}: spread in degrees "
        "of their corners as detected and half-turned; the smaller wins"
    )


def polarity_caption(polarity: dict[str, dict]) -> str:
    """One sentence over the polarity table: what the figures are."""
    return (
        "Board polarity per sensor, which squares read dark/cold or bright/hot ("
        + polarity_note(polarity)
        + ")"
    )


# -- verdicts from the calibration's own uncertainty (calib.verdict, the report's ``verdict``)


def verdict_lines(verdict: dict) -> list[str]:
    """The report's ``verdict`` block for a terminal: the overall grade, then one line per
    sensor and per pair (eyes, stereo) with its grade, the sigmas above target and the
    advice (``label  usable: σ of ...; capture about 3 more views: ...``); then each
    sensor calibrated alone (its intrinsics judged, its pose not linked)."""
    alone = verdict.get("sensors_intrinsics_only") or {}
    rows = [*verdict["sensors"].values(), *verdict["pairs"], *alone.values()]
    width = max((len(v["label"]) for v in rows), default=0)
    head = (
        f"Verdict: {verdict['grade']} (good: every 1-sigma within half its accuracy target; "
        "poor: one beyond twice its accuracy target)"
    )
    return [head, *(f"  {v['label']:<{width}}  {v['line']}" for v in rows)]
