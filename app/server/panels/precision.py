"""The console's Precision panel: the method's Table 1 and its curves for the rig in use.

How far a TOF error moves a fused pixel, as a function of the radial distance (the method's
section 4.1, :mod:`fusion.precision`): for the TOF's two significant pixels (principal
point, edge of accuracy region 3), the radial distance below which a TOF distance error
(before and after range calibration) or a TOF pixel error shifts each sensor's pixel by
more than the threshold, and the shift curves |dx|, |dy| against distance (uPlot, log
scale). The numbers are :func:`fusion.precision.analyze_precision`'s, the cells formatted
as ``trifuse analyze`` prints them. Below the table, the registration sigma
(:func:`fusion.registration.sigma_vs_distance`): how far a thermal value can land from the
colour pixel that sees its point, 1-sigma in colour pixels, per eye at a few distances, from
the rig's own calibration covariance and TOF range error (a wall facing the colour camera),
and its curves (plot choice "registration σ": total, calibration and range shares).

The analysis runs in the panel's own thread (about 0.5 s for the default head, longer for
fine steps), again whenever ``pipeline.rig`` is replaced by another object or the
operator changes an error or the threshold; meanwhile the panel says "computing...". An
error (a rig without a TOF, a bad value) is shown in the panel; the console keeps running.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import viser
import viser.uplot

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.workflows.report_format import limit_distance_cell, pixel_cell, sensor_colour
from trifuse.calib.rig import Rig
from trifuse.fusion.precision import (
    DEFAULT_DISTANCE_ERROR_M,
    DEFAULT_THRESHOLD_PX,
    DEFAULT_TOF_PIXEL_ERROR_PX,
    PrecisionAnalysis,
    analyze_precision,
    tof_pixel_label,
)
from trifuse.fusion.registration import SigmaCurve, range_error, sigma_vs_distance

AFTER_RANGE_CAL_M = 0.015
"""The method's TOF distance error after range calibration (Table 1: 15 mm)."""

REGISTRATION = "registration σ"
ERROR_KINDS = ("distance error", "TOF pixel error", REGISTRATION)
COORDS = ("x", "y")
REGISTRATION_DISTANCES_M = np.arange(0.5, 10.01, 0.5)
"""Where the registration curves are computed (a wall facing each colour camera), metres."""
REGISTRATION_TABLE_M = (1.0, 2.0, 3.0, 5.0, 10.0)
REGISTRATION_CELL_PX = 64
"""One registration value per 64 x 64 colour pixels: 300 a picture, medians to 1 %."""
PLOT_HEIGHT_PX = 260


@dataclass(frozen=True, eq=False)
class PrecisionResult:
    """What the panel shows.

    Attributes:
        rig: the rig analysed (the object ``pipeline.rig`` was).
        before, after: the analyses with the distance error before and after range
            calibration (same TOF pixels, TOF pixel error and threshold; the TOF pixel error
            rows come from ``before``).
        labels: pixel key -> "principal point", "region 3 edge" or "".
        registration: eye -> where its thermal values land, 1-sigma against distance
            (:func:`fusion.registration.sigma_vs_distance`, the rig's own covariance and
            range error); empty for a rig without eyes.
        registration_note: what the registration curves are made of, in words.
    """

    rig: Rig
    before: PrecisionAnalysis
    after: PrecisionAnalysis
    labels: dict[str, str]
    registration: dict[str, SigmaCurve]
    registration_note: str

    @property
    def range_m(self) -> tuple[float, float]:
        any_shift = next(iter(next(iter(self.before.distance_error.values())).values()))
        return float(any_shift.distance_m[0]), float(any_shift.distance_m[-1])


def compute(
    rig: Rig,
    before_m: float = DEFAULT_DISTANCE_ERROR_M,
    after_m: float = AFTER_RANGE_CAL_M,
    tof_pixel_error_px: float = DEFAULT_TOF_PIXEL_ERROR_PX,
    threshold_px: float = DEFAULT_THRESHOLD_PX,
) -> PrecisionResult:
    """Both analyses of ``rig`` (default TOF pixels and distances, as ``trifuse analyze``)."""
    before = analyze_precision(
        rig,
        distance_error_m=before_m,
        tof_pixel_error_px=tof_pixel_error_px,
        threshold_px=threshold_px,
    )
    after = analyze_precision(
        rig,
        distance_error_m=after_m,
        tof_pixel_error_px=tof_pixel_error_px,
        threshold_px=threshold_px,
    )
    labels = {
        key: tof_pixel_label(rig, pixel, before.tof)
        for key, pixel in zip(before.distance_error, before.tof_pixels, strict=True)
    }
    err = range_error(rig, before.tof)
    curves = {
        name: sigma_vs_distance(
            rig,
            e.color,
            e.thermal,
            before.tof,
            REGISTRATION_DISTANCES_M,
            err,
            REGISTRATION_CELL_PX,
        )
        for name, e in rig.eyes.items()
    }
    covariance = (
        "the calibration's covariance"
        if rig.covariance is not None
        else "no calibration covariance in the rig (range share only)"
    )
    note = f"{covariance}; TOF range error: {err.source}"
    return PrecisionResult(rig, before, after, labels, curves, note)


MODALITY_SHORT = {"color": "col", "thermal": "th", "tof": "tof"}


def short_names(rig: Rig, sensors: tuple[str, ...]) -> dict[str, str]:
    """Column headers narrow enough for the side panel: ``"col L"``, ``"th R"`` ... for
    the sensors of an eye (modality and the eye's initial, as the method's "CCDl", "TH. r"),
    the sensor's own name otherwise or where two would read the same."""
    out = {}
    for name in sensors:
        eye = next((e for e, v in rig.eyes.items() if name in (v.color, v.thermal)), None)
        modality = MODALITY_SHORT.get(rig[name].modality, rig[name].modality)
        out[name] = f"{modality} {eye[:1].upper()}" if eye else name
    if len(set(out.values())) != len(out):
        return {name: name for name in sensors}
    return out


def table_markdown(result: PrecisionResult) -> str:
    """Table 1 as markdown: one table per TOF pixel, a row per (error, coordinate), a column
    per sensor; cells in metres as ``trifuse analyze`` prints them."""
    before, after = result.before, result.after
    lo, hi = result.range_m
    short = short_names(result.rig, before.sensors)
    nbsp = "\u00a0"
    out = [
        f"Radial distance [m] below which the shift exceeds **{before.threshold_px:g} px** "
        f"(TOF {md_text(before.tof)}, {lo:g}–{hi:g} m; – never, ≥{hi:.2f} everywhere)."
    ]
    head = (
        "| error | | "
        + " | ".join(md_text(short[n]).replace(" ", nbsp) for n in before.sensors)
        + " |"
    )
    rule = "|:--|:-:|" + "--:|" * len(before.sensors)
    rows_of = (
        (f"{before.distance_error_m * 1000:g}{nbsp}mm", before.distance_error),
        (f"{after.distance_error_m * 1000:g}{nbsp}mm", after.distance_error),
        (f"{before.tof_pixel_error_px:g}{nbsp}px", before.tof_pixel_error),
    )
    for (u, v), key in zip(before.tof_pixels, before.distance_error, strict=True):
        label = result.labels.get(key, "")
        out.append(f"**TOF pixel {pixel_cell(u, v)}**" + (f", {label}" if label else ""))
        lines = [head, rule]
        for name, results in rows_of:
            for coord in COORDS:
                cells = [
                    limit_distance_cell(getattr(r, f"{coord}_m"), hi) for r in results[key].values()
                ]
                first = name if coord == "x" else ""
                lines.append(f"| {first} | {coord} | " + " | ".join(cells) + " |")
        out.append("\n".join(lines))
    legend = ", ".join(
        f"{md_text(short[n])} = {md_text(n)}" for n in before.sensors if short[n] != n
    )
    out.append(
        f"Rows: TOF distance error before range calibration ({before.distance_error_m * 1000:g}"
        f" mm), after it ({after.distance_error_m * 1000:g} mm), TOF pixel error along x "
        f"({before.tof_pixel_error_px:g} px)." + (f" Columns: {legend}." if legend else "")
    )
    if result.registration:
        out.append(registration_markdown(result))
    return "\n\n".join(out)


def registration_markdown(result: PrecisionResult) -> str:
    """Where thermal values land, 1-sigma in colour pixels (median over the picture), per
    eye at a few distances: a wall facing the colour camera."""
    cols = REGISTRATION_TABLE_M
    lines = [
        "| eye | " + " | ".join(f"{d:g}\u00a0m" for d in cols) + " |",
        "|:--|" + "--:|" * len(cols),
    ]
    for eye, c in result.registration.items():
        at = [float(np.interp(d, c.distance_m, c.median_px["total"])) for d in cols]
        lines.append(f"| {md_text(eye)} | " + " | ".join(f"{v:.2f}" for v in at) + " |")
    return (
        "**Registration σ** [colour px]: where a thermal value lands, 1-sigma, median over "
        "the picture, a wall facing the colour camera at that distance "
        f"({md_text(result.registration_note)}).\n\n" + "\n".join(lines)
    )


def _colour(i: int, alpha: float = 1.0) -> str:
    r, g, b = sensor_colour(i)
    return f"rgba({r}, {g}, {b}, {alpha:g})"


def plot_data(
    result: PrecisionResult, key: str, kind: str, coord: str
) -> tuple[tuple[np.ndarray, ...], tuple[viser.uplot.Series, ...], tuple[float, float]]:
    """uPlot data, series and y range for one plot: |d<coord>| against the radial distance
    for every sensor (distance error: before solid, after dashed), and the threshold; for
    :data:`REGISTRATION`, :func:`registration_plot_data` (one plot, ``coord`` unused).
    Colours and decreasing line widths per sensor as in ``trifuse analyze --plot``.

    Shifts are clipped to the bottom of the log axis (two decades below the threshold);
    NaN (the point does not project into the sensor) is drawn there too.
    """
    if kind not in ERROR_KINDS:
        raise ValueError(f"kind: expected one of {ERROR_KINDS}, got {kind!r}")
    if kind == REGISTRATION:
        return registration_plot_data(result)
    before, after = result.before, result.after
    thr = before.threshold_px
    floor = 10.0 ** (int(np.floor(np.log10(thr))) - 2)
    curves: list[tuple[str, np.ndarray, int, bool]] = []  # label, |shift|, colour, dashed
    if kind == "distance error":
        groups = [(before.distance_error, False), (after.distance_error, True)]
        errors = [before.distance_error_m, after.distance_error_m]
    else:
        groups, errors = [(before.tof_pixel_error, False)], []
    short = short_names(result.rig, before.sensors)
    for g, (results, dashed) in enumerate(groups):
        for i, (name, r) in enumerate(results[key].items()):
            label = short[name] + (f" {errors[g] * 1000:g} mm" if errors else "")
            shift = r.dx_px if coord == "x" else r.dy_px
            curves.append((label, np.abs(shift), i, dashed))
    distance = next(iter(before.distance_error[key].values())).distance_m
    ys = [np.clip(np.nan_to_num(c[1], nan=floor), floor, None) for c in curves]
    top = max(float(max(y.max() for y in ys)), 2.0 * thr)
    y_range = (floor, 10.0 ** int(np.ceil(np.log10(top))))
    series = [viser.uplot.Series(label="distance [m]")]
    n = len(before.sensors)
    for label, _, colour, dashed in curves:
        # decreasing widths, so that coinciding curves (a left/right pair) both show
        width = 1.0 + 0.75 * (n - 1 - colour)
        s = viser.uplot.Series(label=label, stroke=_colour(colour), width=width)
        if dashed:
            s["dash"] = (6.0, 4.0)
        series.append(s)
    series.append(
        viser.uplot.Series(
            label=f"threshold {thr:g} px", stroke="rgba(0, 0, 0, 1)", width=1, dash=(3.0, 3.0)
        )
    )
    data = (distance, *ys, np.full(distance.shape, thr))
    return tuple(np.asarray(a, np.float64) for a in data), tuple(series), y_range


SHARE_DASH = {"total": None, "calibration": (6.0, 4.0), "range": (2.0, 3.0)}


def registration_plot_data(
    result: PrecisionResult,
) -> tuple[tuple[np.ndarray, ...], tuple[viser.uplot.Series, ...], tuple[float, float]]:
    """uPlot data, series and y range of the registration curves: per eye its total sigma
    (solid), the calibration's share (dashed) and the range error's (dotted), colour pixels
    against distance; clipped to the log axis's bottom, 0.001 px."""
    floor = 1e-3
    first = next(iter(result.registration.values()), None)
    if first is None:
        raise ValueError("registration: the rig has no eyes (a colour camera and a thermal imager)")
    series = [viser.uplot.Series(label="distance [m]")]
    ys = []
    for i, (eye, c) in enumerate(result.registration.items()):
        for share, dash in SHARE_DASH.items():
            ys.append(np.clip(np.nan_to_num(c.median_px[share], nan=floor), floor, None))
            s = viser.uplot.Series(
                label=f"{eye} {share}", stroke=_colour(2 * i), width=2.0 - 0.5 * i
            )
            if dash:
                s["dash"] = dash
            series.append(s)
    top = max(float(max(y.max() for y in ys)), 1.0)
    y_range = (floor, 10.0 ** int(np.ceil(np.log10(top))))
    data = (first.distance_m, *ys)
    return tuple(np.asarray(a, np.float64) for a in data), tuple(series), y_range


def plot_axes(
    y_range: tuple[float, float], coord: str, range_m: tuple[float, float]
) -> tuple[dict[str, viser.uplot.Scale], tuple[viser.uplot.Axis, ...]]:
    """Scales and axes: distance in metres (ticks every 2 m), |shift| log10 in pixels (a
    tick and grid line per decade only: the side panel is narrow)."""
    lo, hi = range_m
    step = 2.0 if hi - lo > 4.0 else 0.5
    x_splits = tuple(float(x) for x in np.arange(0.0, hi + 1e-9, step) if x >= lo)
    decades = range(round(np.log10(y_range[0])), round(np.log10(y_range[1])) + 1)
    y_splits = tuple(10.0**k for k in decades)
    scales = {
        "x": viser.uplot.Scale(time=False, range=(lo, hi)),
        "y": viser.uplot.Scale(distr=3, log=10, range=y_range),
    }
    axes = (
        viser.uplot.Axis(
            label="wall distance [m]" if coord == "σ" else "radial distance [m]",
            splits=x_splits,
            values=tuple(f"{x:g}" for x in x_splits),
        ),
        viser.uplot.Axis(
            label="σ [colour px]" if coord == "σ" else f"|d{coord}| [px]",
            splits=y_splits,
            values=tuple(f"{y:g}" for y in y_splits),
        ),
    )
    return scales, axes


class PrecisionPanel(Periodic):
    """The "Precision" folder; recomputes when ``ctx.pipeline.rig`` changes (polled)."""

    def __init__(self, ctx: ConsoleContext, poll_s: float = 0.5) -> None:
        super().__init__("precision-panel", poll_s)
        self.ctx, self.server = ctx, ctx.server
        gui = self.server.gui
        self.result: PrecisionResult | None = None
        self.error: str | None = None
        self.analysed: Rig | None = None  # the rig the panel's content is about, once shown
        self.updates = 0  # analyses shown (result or error)
        self._rig: Rig | None = None
        self._dirty = True
        self._plots: list[viser.GuiUplotHandle] = []
        self.folder = gui.add_folder("Precision", expand_by_default=False)
        with self.folder:
            gui.add_markdown(
                "How far a TOF error moves a fused pixel, by radial distance "
                "(the method's Table 1; `trifuse analyze`), and how far a thermal value "
                "can land from its colour pixel (registration σ, the rig's own uncertainty)."
            )
            self.before_mm = gui.add_number(
                "Distance error before (mm)", DEFAULT_DISTANCE_ERROR_M * 1000, min=0.0, step=1.0
            )
            self.after_mm = gui.add_number(
                "Distance error after (mm)", AFTER_RANGE_CAL_M * 1000, min=0.0, step=1.0
            )
            self.pixel_px = gui.add_number(
                "TOF pixel error (px)", DEFAULT_TOF_PIXEL_ERROR_PX, min=0.0, step=0.1
            )
            self.threshold = gui.add_number(
                "Threshold (px)", DEFAULT_THRESHOLD_PX, min=0.01, step=0.1
            )
            self.status = gui.add_markdown("computing...")
            self.table = gui.add_markdown("")
            self.pixel_choice = gui.add_dropdown("Plot TOF pixel", ("principal point",))
            self.kind_choice = gui.add_dropdown(
                "Plot error", ERROR_KINDS, initial_value=ERROR_KINDS[0]
            )
        for handle in (self.before_mm, self.after_mm, self.pixel_px, self.threshold):
            handle.on_update(lambda _event: self._invalidate())
        for handle in (self.pixel_choice, self.kind_choice):
            handle.on_update(lambda _event: self._replot())
        self._lock = threading.Lock()

    def _invalidate(self) -> None:
        self._dirty = True

    def start(self) -> PrecisionPanel:
        super().start()
        return self

    def _run(self) -> None:
        self.tick_once()  # the first result without waiting a period
        super()._run()

    def tick(self) -> None:
        rig = self.ctx.pipeline.rig
        if rig is self._rig and not self._dirty:
            return
        self._rig, self._dirty = rig, False
        self.status.content = "computing..."
        try:
            self._update(rig)
        except Exception as exc:  # shown in the panel; the console keeps running
            self.error = describe_error(exc)
            self.result = None
            self.status.content = f"**Cannot analyse this rig:** {md_text(self.error)}"
            self.table.content = ""
            self._remove_plots()
        self.analysed = rig
        self.updates += 1

    def _update(self, rig: Rig) -> None:
        result = compute(
            rig,
            before_m=float(self.before_mm.value) / 1000.0,
            after_m=float(self.after_mm.value) / 1000.0,
            tof_pixel_error_px=float(self.pixel_px.value),
            threshold_px=float(self.threshold.value),
        )
        self.table.content = table_markdown(result)
        self.error, self.result = None, result
        choices = tuple(self._pixel_choices(result))
        if tuple(self.pixel_choice.options) != choices:
            self.pixel_choice.options = choices
        self._show_plots()
        self.status.content = ""

    @staticmethod
    def _pixel_choices(result: PrecisionResult) -> list[str]:
        return [
            result.labels.get(key) or f"({u:.10g}, {v:.10g})"
            for (u, v), key in zip(
                result.before.tof_pixels, result.before.distance_error, strict=True
            )
        ]

    def _replot(self) -> None:
        try:
            self._show_plots()
        except Exception as exc:  # shown in the panel
            self.status.content = f"**Cannot plot:** {md_text(describe_error(exc))}"

    @property
    def plots(self) -> tuple[viser.GuiUplotHandle, ...]:
        """The plots shown: |dx| and |dy| against radial distance (none before a result)."""
        return tuple(self._plots)

    def _remove_plots(self) -> None:
        for plot in self._plots:
            plot.remove()
        self._plots = []

    def _show_plots(self) -> None:
        """(Re)build the |dx| and |dy| plots for the chosen TOF pixel and error."""
        result = self.result
        if result is None:
            return
        with self._lock:
            choices = self._pixel_choices(result)
            index = (
                choices.index(self.pixel_choice.value) if self.pixel_choice.value in choices else 0
            )
            key = list(result.before.distance_error)[index]
            kind = self.kind_choice.value
            plots = []
            with self.folder:
                for coord in ("σ",) if kind == REGISTRATION else COORDS:
                    data, series, y_range = plot_data(result, key, kind, coord)
                    scales, axes = plot_axes(y_range, coord, result.range_m)
                    title = (
                        "where thermal values land, 1-sigma"
                        if kind == REGISTRATION
                        else f"|d{coord}| from the {kind}"
                    )
                    plots.append(
                        self.server.gui.add_uplot(
                            data,
                            series,
                            title=title,
                            scales=scales,
                            axes=axes,
                            legend=viser.uplot.Legend(show=True, live=False),
                            height=PLOT_HEIGHT_PX,
                            padding=(12, 16, 0, 0),
                        )
                    )
            self._remove_plots()
            self._plots = plots
