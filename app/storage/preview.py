"""Contact sheets: every view of a capture in every sensor, in one viewable 8-bit image.

Thermal and TOF images are contrast-stretched per thumbnail (1st-99th percentile), thermal
in an iron-like palette, so a person can see at a glance that the board is in every sensor.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.atomic import atomic_write_bytes

THUMB_W, THUMB_H = 192, 144
LABEL_H = 18


def to_display(image: np.ndarray) -> np.ndarray:
    """Any frame image as (H, W, 3) uint8 RGB: colour as is, others stretched.

    Single-channel images (thermal kelvin, TOF amplitude) are stretched between their
    1st and 99th percentiles; thermal-looking data (all values 150-500) gets the INFERNO
    palette, the rest grey. NaN becomes black.
    """
    if image.ndim == 3:
        return image
    a = image.astype(np.float32)
    finite = np.isfinite(a)
    if not finite.any():
        return np.zeros((*a.shape, 3), np.uint8)
    lo, hi = np.percentile(a[finite], [1, 99])
    grey = np.clip((np.nan_to_num(a, nan=lo) - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255)
    grey = grey.astype(np.uint8)
    if 150 < lo and hi < 500:
        rgb = cv2.applyColorMap(grey, cv2.COLORMAP_INFERNO)[..., ::-1]
    else:
        rgb = np.repeat(grey[..., None], 3, axis=2)
    rgb = np.ascontiguousarray(rgb)
    rgb[~finite] = 0
    return rgb


class ContactSheet:
    """Collects one row of thumbnails per view, one column per sensor."""

    def __init__(self, sensors: list[str]) -> None:
        self.sensors = list(sensors)
        self.rows: list[np.ndarray] = []

    def add(self, view_name: str, frames: FrameSet) -> None:
        """Add a view's row; sensors missing from the frame set stay grey."""
        row = np.full((THUMB_H + LABEL_H, THUMB_W * len(self.sensors), 3), 40, np.uint8)
        for i, sensor in enumerate(self.sensors):
            x = i * THUMB_W
            if sensor in frames:
                thumb = cv2.resize(
                    to_display(frames[sensor].image),
                    (THUMB_W, THUMB_H),
                    interpolation=cv2.INTER_AREA,
                )
                row[LABEL_H:, x : x + THUMB_W] = thumb
            cv2.putText(
                row,
                f"{view_name} {sensor}",
                (x + 4, 13),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.4,
                (230, 230, 230),
                1,
                cv2.LINE_AA,
            )
        self.rows.append(row)

    def image(self) -> np.ndarray:
        """The sheet as (H, W, 3) uint8 RGB."""
        if not self.rows:
            return np.zeros((LABEL_H, THUMB_W * len(self.sensors), 3), np.uint8)
        return np.vstack(self.rows)

    def write(self, path: str | Path) -> Path:
        ok, buf = cv2.imencode(".png", self.image()[..., ::-1])
        if not ok:
            raise ValueError(f"{path}: OpenCV could not encode the contact sheet")
        return atomic_write_bytes(path, buf.tobytes())
