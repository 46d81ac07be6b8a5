"""Grey thermal images as a vendor tool saves them (tests/calib/test_palette_thermal.py,
tests/calib/test_detect_parity.py): a palette, a colour bar at the right edge, white text in three
corners (:func:`render`), on 640 x 480 images (:data:`SIZE`)."""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.fusion.palettes import palette

SIZE = (640, 480)
"""(width, height) of the images :func:`render` takes, px."""


def vendor_palette() -> np.ndarray:
    """A palette the code does not know: five evenly spaced control points, linear in RGB
    (navy, purple, crimson, orange, pale yellow), luma rising; (256, 3) uint8 RGB."""
    points = np.array(
        [(0, 0, 64), (128, 0, 160), (224, 32, 96), (255, 144, 0), (255, 240, 160)], float
    )
    x = np.linspace(0.0, 4.0, 256)
    return np.stack([np.interp(x, np.arange(5), points[:, k]) for k in range(3)], axis=1).round()


def opencv_map(code: int) -> np.ndarray:
    """OpenCV's colour map ``code`` (``cv2.COLORMAP_*``) as a palette, (256, 3) uint8 RGB."""
    ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
    return cv2.applyColorMap(ramp, code).reshape(256, 3)[:, ::-1].copy()


PALETTES = {
    "iron": palette("iron"),
    "rainbow": palette("rainbow"),
    "jet": opencv_map(cv2.COLORMAP_JET),
    "vendor": vendor_palette().astype(np.uint8),
}
"""Test palettes, (256, 3) uint8 RGB, cold end first."""


def text_mask() -> np.ndarray:
    """(480, 640) bool: where the overlay's white text lies."""
    mask = np.zeros(SIZE[::-1], np.uint8)
    draw_text(mask, 255)
    return mask > 0


def draw_text(image: np.ndarray, colour: int | tuple[int, int, int]) -> None:
    """Draw the overlay's text (two temperatures, a time) on ``image`` (480, 640[, 3]) in place."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(image, "34.2 C", (530, 28), font, 0.7, colour, 2, cv2.LINE_AA)
    cv2.putText(image, "11.8 C", (530, 470), font, 0.7, colour, 2, cv2.LINE_AA)
    cv2.putText(image, "LWIR 12:03:41", (8, 470), font, 0.55, colour, 1, cv2.LINE_AA)


def render(grey: np.ndarray, name: str | None) -> np.ndarray:
    """A grey image as a vendor tool saves it: a colour bar (the palette, hot at the top)
    at the right edge, white text in three corners; (H, W, 3) uint8 RGB, or with ``name``
    None the grey reference with the same overlay, (H, W) uint8."""
    index = grey.copy()
    index[40:440, 612:628] = np.linspace(255, 0, 400).round().astype(np.uint8)[:, None]
    if name is None:
        draw_text(index, 255)
        return index
    rgb = PALETTES[name][index]
    draw_text(rgb, (255, 255, 255))
    return rgb
