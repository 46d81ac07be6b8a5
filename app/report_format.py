"""How results are shown to people, shared by the CLI and the console's panels."""

from __future__ import annotations

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


def limit_distance_cell(value_m: float | None, range_max_m: float) -> str:
    """A Table 1 cell: the distance (m) at which the shift reaches the threshold."""
    if value_m is None:
        return NEVER
    if value_m >= range_max_m:
        return f"≥{range_max_m:.2f}"
    return f"{value_m:.2f}"
