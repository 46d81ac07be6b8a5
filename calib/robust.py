"""Robust statistics shared by the fits."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

MAD_TO_SIGMA = 1.4826
"""Median absolute deviation of a normal distribution -> its standard deviation."""


def mad_sigma(r: npt.ArrayLike) -> float:
    """Robust standard deviation of residuals ``r`` (any shape, units of ``r``):
    1.4826 x the median absolute deviation from their median."""
    r = np.asarray(r, dtype=np.float64)
    return MAD_TO_SIGMA * float(np.median(np.abs(r - np.median(r))))
