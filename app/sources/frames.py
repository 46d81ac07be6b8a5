"""Frame sets: what every source produces.

Arrays follow docs/CONVENTIONS.md: colour images are (H, W, 3) uint8 RGB; thermal images
are (H, W) float32 temperatures in kelvin; a TOF frame carries (H, W) float32 radial
distance in metres (NaN where invalid) and (H, W) float32 amplitude.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Frame:
    """One sensor's image at one instant.

    Attributes:
        sensor: sensor id in the rig.
        stamp_ns: acquisition time, integer nanoseconds.
        image: colour RGB uint8 (H, W, 3); thermal kelvin float32 (H, W);
            TOF amplitude float32 (H, W).
        distance_m: TOF only: radial distance float32 (H, W), NaN where invalid.
    """

    sensor: str
    stamp_ns: int
    image: np.ndarray
    distance_m: np.ndarray | None = None


@dataclass
class FrameSet:
    """Frames of several sensors grouped around one time stamp (nanoseconds).

    ``missing`` names the expected sensors that have no frame in this set, with the reason
    (never received, too old): a missing or stale sensor is reported, not waited for.
    """

    stamp_ns: int
    frames: dict[str, Frame] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)

    def __getitem__(self, sensor: str) -> Frame:
        try:
            return self.frames[sensor]
        except KeyError:
            raise KeyError(
                f"frame set has no frame of {sensor!r} (has: {sorted(self.frames)})"
            ) from None

    def __contains__(self, sensor: object) -> bool:
        return sensor in self.frames
