"""Accuracy regions of the TOF image, after the SR4000 data sheet as the method uses them.

Region 1 is the central 11 x 11 pixels (where the maker guarantees +-15 mm); regions 2 and
3 are larger centred rectangles; region 4 is the rest, the border, whose distances are
unreliable and are reported but not trusted.
"""

from __future__ import annotations

import numpy as np

# Half-extents of regions 1-3 as fractions of the image's half width / half height.
REGION_1_PIXELS = 11
REGION_2_FRACTION = 0.5
REGION_3_FRACTION = 0.8


def region_map(width: int, height: int) -> np.ndarray:
    """(height, width) uint8 map of accuracy regions 1-4 (1 = centre, 4 = border)."""
    u = np.abs(np.arange(width) - (width - 1) / 2.0)
    v = np.abs(np.arange(height) - (height - 1) / 2.0)
    uu, vv = np.meshgrid(u, v)
    regions = np.full((height, width), 4, dtype=np.uint8)
    in3 = (uu <= REGION_3_FRACTION * width / 2) & (vv <= REGION_3_FRACTION * height / 2)
    in2 = (uu <= REGION_2_FRACTION * width / 2) & (vv <= REGION_2_FRACTION * height / 2)
    half = REGION_1_PIXELS // 2
    c1 = np.abs(np.arange(width) - (width - 1) // 2) <= half
    r1 = np.abs(np.arange(height) - (height - 1) // 2) <= half
    in1 = r1[:, None] & c1[None, :]
    regions[in3] = 3
    regions[in2] = 2
    regions[in1] = 1
    return regions


def region3_edge_pixel(width: int, height: int) -> tuple[float, float]:
    """The pixel on the image's horizontal centre line at the right edge of region 3."""
    cx = (width - 1) / 2.0
    return (float(np.floor(cx + REGION_3_FRACTION * width / 2)), (height - 1) / 2.0)
