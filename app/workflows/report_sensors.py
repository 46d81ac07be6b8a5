"""The calibration report's sections on the sensors (:mod:`report_html`): one per calibrated
sensor (verdict, intrinsics and distortion, pose ± 1-sigma, the views left out and why, its
plots from :mod:`report_svg`) and the relative pose of every pair with where its 1-sigma
comes from; the reading of a sensor's pose and sigmas out of ``report.json``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from trifuse.app.workflows.report_format import coverage_sentence, sensor_colour
from trifuse.app.workflows.report_markup import (
    FIGURE_HEAD,
    advice_block,
    esc,
    figure_rows,
    figures_table,
    fixed,
    generic,
    grade_badge,
    html_id,
    html_table,
    is_finite_number,
    is_graded,
    pm,
    sigma_decimals,
    significant,
    verdict_box,
    views_list,
)
from trifuse.app.workflows.report_svg import (
    LEFT_CORNER,
    LEFT_VIEW,
    USED,
    coverage_svg,
    hex_colour,
    scatter_svg,
    vectors_svg,
    view_rms_svg,
)
from trifuse.calib.coverage import PARAM_NAMES
from trifuse.calib.transforms import rotation_angle_deg, rvec_from_rotation

if TYPE_CHECKING:
    from trifuse.calib.rig_result import CornerResiduals


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


DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


def sigma_of(entry: Mapping[str, Any], key: str) -> Any:
    """``entry["sigma"][key]`` of a sensor's report entry; None when it has none."""
    return (entry.get("sigma") or {}).get(key)


def _pose(entry: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vector (deg) and translation (mm) of a sensor's ``T_rig_sensor``."""
    T = np.asarray(entry["T_rig_sensor"], dtype=float)
    return np.degrees(rvec_from_rotation(T[:3, :3])), 1000.0 * T[:3, 3]


def sigma_vector(entry: Mapping[str, Any], key: str, scale: float = 1.0) -> np.ndarray:
    """A sensor's 1-sigma of a 3-vector (``rotation_deg``, ``translation_m``) times
    ``scale``, shape (3,); NaN when the report has no three finite numbers."""
    s = sigma_of(entry, key)
    if not isinstance(s, Sequence) or len(s) != 3 or not all(is_finite_number(v) for v in s):
        return np.full(3, np.nan)
    return scale * np.asarray(s, dtype=float)


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
    """What of the sensor's views was left out, and why (an image that could not be read,
    listed in the report's ``unreadable_images``, as not read rather than without a board)."""
    unread = {
        str(u.get("view"))
        for u in report.get("unreadable_images") or []
        if isinstance(u, Mapping) and u.get("sensor") == name and not u.get("distance")
    }
    by_reason: dict[tuple[str, bool], list[str]] = {}
    for v, per in sorted((report.get("detections") or {}).items()):
        d = per.get(name)
        if d is not None and not d.get("found"):
            by_reason.setdefault((str(d.get("reason") or "not found"), v in unread), []).append(v)
    items = [
        f"<li>{'image not read' if not_read else 'board not found'} in {len(vs)} view(s) "
        f"({esc(views_list(vs))}): {esc(r)}</li>"
        for (r, not_read), vs in by_reason.items()
    ]
    outliers = report.get("outliers") or []
    for o in outliers:
        if o.get("sensor") == name and o.get("corner") is None:
            items.append(
                f"<li>view {esc(o.get('view'))} left out (RMS {fixed(o.get('error_px'))} px when "
                "flagged): "
                f"{esc(o.get('reason'))}</li>"
            )
    corners = [o for o in outliers if o.get("sensor") == name and o.get("corner") is not None]
    if corners:
        views = sorted({str(o.get("view")) for o in corners})
        items.append(
            f"<li>{len(corners)} outlier corner(s) left out, in view(s) {esc(views_list(views))} "
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
    if not is_graded(v):
        return empty
    part = v.get(key)
    return part if isinstance(part, type(empty)) else empty


def sensor_section(
    report: Mapping[str, Any], name: str, index: int, corners: CornerResiduals | None
) -> str:
    """The section of sensor ``name`` (``index``: its place in the report, for its
    colour): verdict and advice, intrinsics and pose ± 1-sigma, what was left out, the
    per-view RMS chart, with ``corners`` the residual scatter and vectors, the coverage
    map, and the sensor's keys this page does not know (:data:`SENSOR_KEYS`)."""
    s = report["sensors"][name]
    colour = hex_colour(sensor_colour(index))
    intr = s.get("intrinsics") or {}
    size = list(s.get("image_size") or [0, 0])
    parts = [
        f"<section class='sensor' id='sensor-{html_id(name)}'>",
        f"<h2><span style='color:{colour}'>■</span> {esc(name)} <span class='sub'>"
        f"({esc(s.get('modality', ''))}, {esc(size[0])} × {esc(size[1])} px)</span></h2>",
    ]
    verdict = s.get("verdict") or _rig_part(report, "sensors").get(name)
    if verdict is not None:
        parts.append(verdict_box(verdict))
    parts.append(
        f"<p>Board found in {esc(s.get('views_detected', '?'))} view(s), "
        f"{esc(s.get('views_used', '?'))} used; RMS reprojection error "
        f"<b>{fixed(s.get('rms_px'), 3)} px</b>; worst view {esc(s.get('worst_view') or '–')}.</p>"
    )
    if s.get("advice"):
        parts.append(advice_block(s["advice"]))
    rows = [[k, pm(intr.get(k), sigma_of(s, k)), "px"] for k in ("fx", "fy", "cx", "cy")]
    dist = list(s.get("distortion") or [])
    dsig = list(sigma_of(s, "distortion") or [])
    for i, v in enumerate(dist):
        sg = dsig[i] if i < len(dsig) else None
        rows.append(
            [
                DIST_NAMES[i] if i < len(DIST_NAMES) else f"d{i}",
                "0 (fixed)" if v == 0 and not (is_finite_number(sg) and sg > 0) else pm(v, sg, 4),
                "",
            ]
        )
    intr_table = html_table(
        ["", "value ± 1-sigma", "unit"],
        rows,
        numeric=(1,),
        caption="Intrinsics and distortion (OpenCV's model)",
    )
    if name == report.get("reference"):
        pose_table = "<p>The reference: its frame is the rig frame.</p>"
    elif "T_rig_sensor" in s:
        rvec, t = _pose(s)
        rs, ts = sigma_vector(s, "rotation_deg"), sigma_vector(s, "translation_m", 1000.0)
        pose_rows = [[f"rotation {a}", pm(rvec[i], rs[i], 3), "°"] for i, a in enumerate("xyz")]
        pose_rows.append(["rotation angle", fixed(float(np.linalg.norm(rvec)), 3), "°"])
        pose_rows += [[f"translation {a}", pm(t[i], ts[i], 2), "mm"] for i, a in enumerate("xyz")]
        pose_table = html_table(
            ["", "value", "unit"],
            pose_rows,
            numeric=(1,),
            caption=f"Pose in the rig frame ({esc(report.get('reference', ''))}'s): "
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
        note = f"; {beyond} beyond ±{significant(lim)} px drawn on the border" if beyond else ""
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
            f"residuals drawn ×{significant(gain)}: {_key(USED, 'used')}, "
            f"{_key(LEFT_VIEW, 'in views left out')}, {_key(LEFT_CORNER, 'outlier corners')} "
            "(vectors cut short). A pattern (all pointing out at the edges, a swirl) is a "
            "model error; directions at random are noise.</figcaption></figure>"
        )
    cov = s.get("coverage") or {}
    if cov.get("corner_counts"):
        counts = np.asarray(cov["corner_counts"], dtype=int)
        bars = ", ".join(
            f"{n} {fixed(cov.get(k.lower()), 2)}"
            for n, k in zip(PARAM_NAMES, ("x", "y", "size", "skew"), strict=True)
        )
        good = "enough" if cov.get("good_enough") else "not yet enough"
        figures.append(
            f"<figure>{coverage_svg(counts, size)}<figcaption>Corners of the views used, per "
            f"region of the image: {esc(coverage_sentence(counts))}. Spread of the views (ROS "
            f"bars, 1 = full): {esc(bars)} ({good}).</figcaption></figure>"
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
    return f"<span style='color:{colour}'>●</span>&nbsp;{esc(text)}"


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
    joint = {tuple(v.get("sensors") or ()): v for v in _rig_part(report, "pairs") if is_graded(v)}
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
                if is_finite_number(rot.get("sigma")) and isinstance(tr.get("axes"), Sequence):
                    s_rot, s_t = float(rot["sigma"]), np.asarray(tr["axes"], dtype=float)
                    s_b = v.get("sigma_baseline_length_mm", s_b)
                    source = "joint"
            rows.append(
                [
                    f"{a} – {b}",
                    pm(angle, s_rot, 3),
                    ", ".join(
                        fixed(x, sigma_decimals(sx, 1)) for x, sx in zip(t_mm, s_t, strict=True)
                    ),
                    ", ".join(fixed(x, sigma_decimals(x, 2)) for x in s_t),
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
        ts = sigma_vector(sensors[n], "translation_m", 1000.0)
        rot.append(float(np.linalg.norm(sigma_vector(sensors[n], "rotation_deg"))))
        trans.append(ts)
        base.append(float(np.sqrt(np.sum((direction * ts) ** 2))))
    if not rot:
        return float("nan"), np.full(3, np.nan), float("nan"), ""
    s_t = np.sqrt(np.sum(np.square(trans), axis=0))
    return math.hypot(*rot), s_t, math.hypot(*base), "own" if len(rot) == 1 else "≈"


def pairs_section(report: Mapping[str, Any]) -> str:
    """The relative pose of every pair of sensors ± 1-sigma, and the pairs' verdicts;
    empty when the report has no pair."""
    rows = pair_rows(report)
    if not rows:
        return ""
    parts = [
        "<section id='pairs'><h2>Relative poses of the sensors</h2>",
        html_table(
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
            f"the reference ({esc(report.get('reference', ''))}); ≈, the two sensors' 1-sigma "
            "relative to the reference combined as if independent.",
            attrs=" class='small'",
        ),
    ]
    rows = []
    for v in _rig_part(report, "pairs"):
        if is_graded(v):
            for k, f in enumerate(figure_rows(v.get("figures"))):
                lead = [esc(v.get("label", "")), grade_badge(v["grade"])] if k == 0 else ["", ""]
                rows.append([*lead, *f])
    if rows:
        parts.append(
            "<p class='caption'>Verdicts of the eye and stereo pairs (calib.verdict): the "
            "1-sigma of their relative pose from the joint covariance, per axis of a's frame "
            "(horizontal, vertical, optical; sideways, vertical, depth)</p>"
            + figures_table(("pair", "grade", *FIGURE_HEAD), rows)
        )
    parts.append("</section>")
    return "".join(parts)
