"""The text of ``trifuse analyze``: the method's Table 1, the radial distance below which a
TOF error shifts a sensor's pixels by more than the threshold."""

from __future__ import annotations

from typing import TYPE_CHECKING

from trifuse.app.workflows.report_format import NEVER, limit_distance_cell, pixel_cell

if TYPE_CHECKING:
    from trifuse.fusion.precision import PrecisionAnalysis


def error_names(analysis: PrecisionAnalysis) -> dict[str, str]:
    """Each error kind of the analysis (``distance_error``, ``tof_pixel_error``) -> its
    label with its size (mm, TOF px)."""
    return {
        "distance_error": f"distance error {analysis.distance_error_m * 1000:g} mm",
        "tof_pixel_error": f"TOF pixel error {analysis.tof_pixel_error_px:g} px",
    }


def analysis_table(
    analysis: PrecisionAnalysis, labels: dict[str, str], range_m: tuple[float, float]
) -> str:
    """The method's Table 1: radial distance (m) at which the shift reaches the threshold.

    ``labels``: TOF pixel key -> what that pixel is (e.g. "principal point"); ``range_m``:
    the radial distances analysed (m)."""
    lo, hi = range_m
    errors = error_names(analysis)
    head = ["TOF pixel", "error", "coord", *analysis.sensors]
    rows: list[list[str]] = []
    for (u, v), key in zip(analysis.tof_pixels, analysis.distance_error, strict=True):
        first_column = iter([pixel_cell(u, v), labels.get(key, "")])
        for kind, name in errors.items():
            per_sensor = analysis.results(kind)[key]
            for coord in ("x", "y"):
                cells = [
                    limit_distance_cell(getattr(r, f"{coord}_m"), hi) for r in per_sensor.values()
                ]
                rows.append([next(first_column, ""), name if coord == "x" else "", coord, *cells])
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]

    def line(cells: list[str]) -> str:
        left = [c.ljust(w) for c, w in zip(cells[:3], widths[:3], strict=True)]
        right = [c.rjust(max(w, 6)) for c, w in zip(cells[3:], widths[3:], strict=True)]
        return "  ".join(left + right).rstrip()

    out = [
        f"Radial distance [m] below which the shift in each sensor exceeds "
        f"{analysis.threshold_px:g} px (TOF: {analysis.tof}, range {lo:g}-{hi:g} m)",
        f"{NEVER} = never in the range; ≥{hi:.2f} = over the whole range",
        "",
        line(head),
    ]
    for i, row in enumerate(rows):
        if i and i % 4 == 0:
            out.append("")
        out.append(line(row))
    return "\n".join(out)
