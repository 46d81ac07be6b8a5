"""The calibration report's plots (:mod:`report_html`) as inline SVG written here, no plotting
library and nothing fetched: one sensor's RMS error per view as bars, its corner residuals as
a scatter, the corners per image region as a heat map and the residual vectors over the
image; the axes' ticks and the colours the captions name.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from trifuse.app.workflows.report_markup import esc, is_finite_number, significant

USED, LEFT_VIEW, LEFT_CORNER, GREY = "#3b6ea5", "#e0a000", "#d62728", "#888"
"""Plot colours, the same for every sensor: a corner or view used, a view left out (an
outlier), a corner left out alone (an outlier corner), the board not found."""


LONGEST_VECTOR = 24.0
"""Longest residual vector drawn (SVG px): an outlier's would cross the image."""


LEGEND_WIDTH = 150.0
"""Room for a line plot's legend (:func:`curves_svg`), SVG px from the plot's right edge."""


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


def hex_colour(c: tuple[int, int, int]) -> str:
    """An (r, g, b) colour, 0-255 each, as ``#rrggbb``."""
    return "#{:02x}{:02x}{:02x}".format(*c)


def _svg(width: float, height: float, body: Sequence[str], label: str) -> str:
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width:g} {height:g}" '
        f'width="{width:g}" height="{height:g}" role="img" aria-label="{esc(label)}" '
        'font-size="10">' + "".join(body) + "</svg>"
    )


def _dots(xy: np.ndarray, colour: str, size: float = 2.6, title: str = "") -> str:
    """Many dots as one path (a zero-length segment per point, round caps): compact."""
    if len(xy) == 0:
        return ""
    d = "".join(f"M{x:.1f} {y:.1f}h0" for x, y in xy)
    t = f"<title>{esc(title)}</title>" if title else ""
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
    values = [r for r in rms if is_finite_number(r)]
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
        if s in ("used", "outlier") and is_finite_number(r):
            fill = LEFT_VIEW if s == "outlier" else USED
            bw = max(1.0, slot * 0.7)
            body.append(
                f'<rect x="{cx - bw / 2:.1f}" y="{y(r):.1f}" width="{bw:.1f}" '
                f'height="{top + ph - y(r):.1f}" fill="{fill}"><title>{esc(v)}: '
                f"{r:.3f} px{' (outlier)' if s == 'outlier' else ''}</title></rect>"
            )
        elif s == "not found":
            body.append(
                f'<text x="{cx:.1f}" y="{top + ph - 2:.1f}" text-anchor="middle" '
                f'fill="{GREY}">×<title>{esc(v)}: board not found</title></text>'
            )
        if i % label_every == 0:
            body.append(
                f'<text transform="translate({cx + 3:.1f} {top + ph + 5:.1f}) rotate(-60)" '
                f'text-anchor="end" font-size="8.5">{esc(v[-10:])}</text>'
            )
    if is_finite_number(sensor_rms):
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
        f'<text x="{12 + bar:.1f}" y="{height + 15.5:.1f}">{significant(bar_px)} px residual '
        f"(drawn ×{significant(gain)})</text>",
    ]
    return _svg(width, round(height + 22, 1), body, "residual vectors over the image"), gain


def curves_svg(
    x: Sequence[float],
    series: Sequence[tuple[str, Sequence[float | None], str, str]],
    x_label: str,
    y_label: str,
) -> str:
    """Lines against a common x (e.g. figures against distance), with a legend.

    Args:
        x: (N,) the abscissae, increasing (from 0 on the axis).
        series: (label, (N,) values (None or NaN: a gap), colour, dash pattern or "") each.
        x_label, y_label: the axes' titles.
    """
    left, right, top, bottom = 50.0, 10.0, 10.0, 40.0
    width, height = 360.0, 220.0
    pw, ph = width - left - right, height - top - bottom
    xs = [float(v) for v in x]
    values = [float(v) for _l, ys, _c, _d in series for v in ys if is_finite_number(v)]
    x_hi = nice_ceil(max(xs, default=1.0))
    y_hi = nice_ceil(max(values, default=1.0) * 1.08)
    px = lambda v: left + pw * v / x_hi  # noqa: E731
    py = lambda v: top + ph * (1 - min(v, y_hi) / y_hi)  # noqa: E731
    body = [f'<rect x="{left}" y="{top}" width="{pw:g}" height="{ph:g}" fill="#fafafa"/>']
    tv, d = ticks(y_hi, 4)
    for t in tv:
        body.append(
            f'<line x1="{left}" x2="{left + pw:g}" y1="{py(t):.1f}" y2="{py(t):.1f}" '
            'stroke="#ddd"/>'
            f'<text x="{left - 4}" y="{py(t) + 3.5:.1f}" text-anchor="end">{t:.{d}f}</text>'
        )
    tx, dx = ticks(x_hi, 5)
    for t in tx:
        body.append(
            f'<text x="{px(t):.1f}" y="{top + ph + 12:.1f}" text-anchor="middle">{t:.{dx}f}</text>'
        )
    for k, (label, ys, colour, dash) in enumerate(series):
        runs, run = [], []
        for xv, yv in zip(xs, ys, strict=False):  # a report read back may lack values
            if is_finite_number(yv):
                run.append(f"{px(xv):.1f} {py(float(yv)):.1f}")  # type: ignore[arg-type]
            elif run:
                runs.append(run)
                run = []
        runs += [run] if run else []
        d_attr = "".join("M" + "L".join(r) for r in runs)
        dashed = f' stroke-dasharray="{dash}"' if dash else ""
        if d_attr:
            body.append(
                f'<path d="{d_attr}" stroke="{colour}" stroke-width="1.6" fill="none"{dashed}>'
                f"<title>{esc(label)}</title></path>"
            )
        ly, lx = top + 10 + 12 * k, left + pw - LEGEND_WIDTH  # top right: the curves
        body.append(  # against distance fall from the left
            f'<line x1="{lx:g}" x2="{lx + 22:g}" y1="{ly:g}" y2="{ly:g}" '
            f'stroke="{colour}" stroke-width="1.6"{dashed}/>'
            f'<text x="{lx + 26:g}" y="{ly + 3.5:g}" font-size="9">{esc(label)}</text>'
        )
    body.append(
        f'<text x="{left + pw / 2:g}" y="{height - 6:g}" text-anchor="middle">'
        f"{esc(x_label)}</text>"
        f'<text transform="translate(11 {top + ph / 2:g}) rotate(-90)" text-anchor="middle">'
        f"{esc(y_label)}</text>"
    )
    return _svg(width, height, body, y_label)
