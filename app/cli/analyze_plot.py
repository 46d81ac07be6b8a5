"""The curves of ``trifuse analyze --plot``: the pixel shift a TOF error causes in each
sensor against the radial distance, a panel per (TOF pixel, error) and image axis.

Drawn with OpenCV into an RGB image (converted to BGR at the PNG encode)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from trifuse.app.cli.analyze_table import error_names
from trifuse.app.workflows.report_format import pixel_cell, sensor_colour

if TYPE_CHECKING:
    from trifuse.fusion.precision import PrecisionAnalysis, SensorShift

Colour = tuple[int, int, int]
BLACK, GREY, LIGHT, RED = (0, 0, 0), (110, 110, 110), (225, 225, 225), (200, 0, 0)
PW, PH = 620, 300  # plot area of one panel, px
ML, MR, MT, MB = 80, 30, 40, 55  # margins of one panel, px
TITLE_H, LEGEND_H = 50, 40  # px
SUB = 4  # fixed-point bits for sub-pixel polylines


class _Canvas:
    """An RGB image (H, W, 3) uint8 with the text and line helpers the plot uses."""

    def __init__(self, height: int, width: int) -> None:
        import cv2

        self.cv2 = cv2
        self.font = cv2.FONT_HERSHEY_SIMPLEX
        self.img = np.full((height, width, 3), 255, np.uint8)

    def text(
        self, s: str, org: tuple[int, int], scale: float = 0.5, colour: Colour = BLACK, th: int = 1
    ) -> None:
        self.cv2.putText(self.img, s, org, self.font, scale, colour, th, self.cv2.LINE_AA)

    def text_w(self, s: str, scale: float = 0.5) -> int:
        """Width of ``s`` in px."""
        return self.cv2.getTextSize(s, self.font, scale, 1)[0][0]

    def dashed(self, y: int, x0: int, x1: int, colour: Colour) -> None:
        """A horizontal dashed line at row ``y`` from column ``x0`` to ``x1``."""
        for xa in range(x0, x1, 12):
            self.cv2.line(self.img, (xa, y), (min(xa + 6, x1), y), colour, 1)

    def dot(self, centre: tuple[int, int], colour: Colour) -> None:
        """A filled dot of radius 5 px."""
        self.cv2.circle(self.img, centre, 5, colour, -1, self.cv2.LINE_AA)


@dataclass(frozen=True)
class _Panel:
    """One panel's plot area: top-left corner (px), the distance axis 0..``hi_m`` (m)
    linear, the shift axis 10**``dec_lo``..10**``dec_hi`` (px) logarithmic."""

    left: int
    top: int
    hi_m: float
    dec_lo: int
    dec_hi: int

    def to_px(self, d: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(..., 2) image points (x, y; px, sub-pixel) of distances ``d`` (m) and shifts
        ``s`` (px; their magnitude, clipped at the axis' bottom)."""
        lo, hi = self.dec_lo, self.dec_hi
        ly = np.log10(np.clip(np.abs(s), 10.0**lo, None))
        return np.stack(
            [self.left + d / self.hi_m * PW, self.top + PH - (ly - lo) / (hi - lo) * PH], axis=-1
        )

    def row(self, value: float) -> int:
        """The image row of the shift ``value`` (px)."""
        return round(float(self.to_px(np.array(0.0), np.array(value))[1]))


def analysis_plot(
    analysis: PrecisionAnalysis, labels: dict[str, str], range_m: tuple[float, float]
) -> bytes:
    """PNG of the shift curves: a row per (TOF pixel, error), columns |dx| and |dy|.

    Log scale in pixels (the shifts span 1e-3 to 1e2 px); the threshold is a dashed red line
    and a dot marks each sensor's threshold distance. ``labels``: TOF pixel key -> what the
    pixel is; ``range_m``: the radial distances analysed (m).
    """
    errors = error_names(analysis)
    keys = list(analysis.distance_error)
    panels = [(key, kind) for key in keys for kind in errors]
    canvas = _Canvas(TITLE_H + LEGEND_H + len(panels) * (MT + PH + MB), 2 * (ML + PW + MR))
    hi_m = range_m[1]
    thr = analysis.threshold_px
    # Decreasing line widths, so that coinciding curves (a left/right pair) both show.
    n = len(analysis.sensors)
    widths = [2 + max(n - 1 - i, 0) for i in range(n)]
    _title_and_legend(canvas, analysis, errors, widths)

    steps = [m * 10.0**k for k in range(-3, 4) for m in (1, 2, 5)]
    step = max([s for s in steps if hi_m / s >= 8], default=steps[0])
    x_ticks = np.arange(0.0, hi_m + 1e-9, step)
    for p, (key, kind) in enumerate(panels):
        per_sensor = analysis.results(kind)[key]
        top = TITLE_H + LEGEND_H + p * (MT + PH + MB) + MT
        u, v = analysis.tof_pixels[keys.index(key)]
        where = f"TOF pixel {pixel_cell(u, v)}" + (f", {labels[key]}" if labels.get(key) else "")
        values = np.abs(np.concatenate([np.r_[r.dx_px, r.dy_px] for r in per_sensor.values()]))
        values = values[np.isfinite(values)]
        y_max = max(float(values.max()) if values.size else 0.0, 2 * thr)
        dec_hi = int(np.ceil(np.log10(y_max)))
        dec_lo = int(np.floor(np.log10(thr))) - 2
        for c, coord in enumerate(("x", "y")):
            panel = _Panel(c * (ML + PW + MR) + ML, top, hi_m, dec_lo, dec_hi)
            _axes(canvas, panel, x_ticks, coord)
            canvas.text(f"{errors[kind]} at {where}", (panel.left + 90, top - 10), 0.5, BLACK)
            canvas.dashed(panel.row(thr), panel.left, panel.left + PW, RED)
            for i, r in enumerate(per_sensor.values()):
                _curve(canvas, panel, r, coord, thr, sensor_colour(i), widths[i])
    ok, buf = canvas.cv2.imencode(".png", canvas.img[..., ::-1])  # RGB -> BGR at the OpenCV call
    if not ok:
        raise RuntimeError("could not encode the plot as PNG")
    return buf.tobytes()


def _title_and_legend(
    canvas: _Canvas, analysis: PrecisionAnalysis, errors: dict[str, str], widths: list[int]
) -> None:
    """The title line, then the legend: a line per sensor, the threshold, the dot."""
    cv2 = canvas.cv2
    thr = analysis.threshold_px
    canvas.text(
        f"Pixel shift in each sensor caused by TOF errors: {errors['distance_error']}, "
        f"{errors['tof_pixel_error']} (threshold {thr:g} px)",
        (ML, 32),
        0.7,
        BLACK,
        2,
    )
    x, y = ML, TITLE_H + 22
    for i, name in enumerate(analysis.sensors):
        colour = sensor_colour(i)
        cv2.line(canvas.img, (x, y - 5), (x + 30, y - 5), colour, widths[i], cv2.LINE_AA)
        canvas.text(name, (x + 38, y))
        x += 38 + canvas.text_w(name) + 30
    canvas.dashed(y - 5, x, x + 30, RED)
    canvas.text(f"threshold {thr:g} px", (x + 38, y))
    x += 38 + canvas.text_w(f"threshold {thr:g} px") + 30
    canvas.dot((x + 5, y - 5), GREY)
    canvas.text("distance where the shift falls to the threshold", (x + 16, y), 0.5, GREY)


def _axes(canvas: _Canvas, panel: _Panel, x_ticks: np.ndarray, coord: str) -> None:
    """A panel's grid, ticks, tick labels, frame and axis titles (``coord``: x or y)."""
    cv2, img = canvas.cv2, canvas.img
    left, top = panel.left, panel.top
    for dec in range(panel.dec_lo, panel.dec_hi + 1):
        yy = panel.row(10.0**dec)
        cv2.line(img, (left, yy), (left + PW, yy), LIGHT, 1)
        cv2.line(img, (left - 6, yy), (left, yy), BLACK, 1)
        label = f"{10.0**dec:g}"
        canvas.text(label, (left - 12 - canvas.text_w(label, 0.45), yy + 5), 0.45)
        for m in range(2, 10) if dec < panel.dec_hi else ():
            minor = panel.row(m * 10.0**dec)
            cv2.line(img, (left - 3, minor), (left, minor), BLACK)
    for t in x_ticks:
        xx = left + round(t / panel.hi_m * PW)
        cv2.line(img, (xx, top), (xx, top + PH), LIGHT, 1)
        cv2.line(img, (xx, top + PH), (xx, top + PH + 5), BLACK, 1)
        canvas.text(f"{t:g}", (xx - canvas.text_w(f"{t:g}", 0.45) // 2, top + PH + 22), 0.45)
    cv2.rectangle(img, (left, top), (left + PW, top + PH), BLACK, 1)
    xl = "radial distance [m]"
    canvas.text(xl, (left + (PW - canvas.text_w(xl)) // 2, top + PH + 44))
    canvas.text(f"|d{coord}| [px]", (left - ML + 4, top - 10))


def _curve(
    canvas: _Canvas,
    panel: _Panel,
    r: SensorShift,
    coord: str,
    thr: float,
    colour: Colour,
    width: int,
) -> None:
    """One sensor's |d``coord``| curve (split where it is not finite) and the dot where it
    falls to the threshold ``thr`` (px), if that is inside the range."""
    cv2 = canvas.cv2
    pts = panel.to_px(r.distance_m, r.dx_px if coord == "x" else r.dy_px)
    good = np.flatnonzero(np.isfinite(pts).all(axis=1))
    for run in np.split(good, np.flatnonzero(np.diff(good) > 1) + 1):
        if run.size > 1:
            poly = np.round(pts[run] * (1 << SUB)).astype(np.int32)
            cv2.polylines(canvas.img, [poly], False, colour, width, cv2.LINE_AA, SUB)
    at = r.x_m if coord == "x" else r.y_m
    if at is not None and at < panel.hi_m:
        mx, my = panel.to_px(np.array(at), np.array(thr))
        centre = (round(float(mx)), round(float(my)))
        canvas.dot(centre, colour)
        cv2.circle(canvas.img, centre, 5, BLACK, 1, cv2.LINE_AA)
