"""How close a decoded picture is to the one that was encoded: SSIM and PSNR.

Both take two images of the same shape, (H, W) grey or (H, W, 3) colour, uint8 (or any
real dtype on a 0-255 scale); colour is compared channel by channel and averaged.
"""

from __future__ import annotations

import cv2
import numpy as np

_C1 = (0.01 * 255) ** 2
_C2 = (0.03 * 255) ** 2


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a`` and ``b`` as float32, checked for equal shapes (ValueError otherwise)."""
    if a.shape != b.shape:
        raise ValueError(f"images must have equal shapes, got {a.shape} and {b.shape}")
    if a.ndim not in (2, 3) or a.size == 0:
        raise ValueError(f"expected (H, W) or (H, W, C) images, got shape {a.shape}")
    return a.astype(np.float32), b.astype(np.float32)


def ssim(a: np.ndarray, b: np.ndarray, sigma: float = 1.5) -> float:
    """The mean structural similarity of ``a`` and ``b`` (Wang et al. 2004: Gaussian
    window of ``sigma`` pixels, 11x11, K1 = 0.01, K2 = 0.03, 0-255 scale): 1.0 identical,
    ~0 unrelated."""
    x, y = _pair(a, b)

    def blur(img: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(img, (11, 11), sigma, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    mxx, myy, mxy = mx * mx, my * my, mx * my
    vx = blur(x * x) - mxx
    vy = blur(y * y) - myy
    cxy = blur(x * y) - mxy
    num = (2 * mxy + _C1) * (2 * cxy + _C2)
    den = (mxx + myy + _C1) * (vx + vy + _C2)
    return float(np.mean(num / den))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """The peak signal-to-noise ratio of ``b`` against ``a``, dB (peak 255); ``inf`` for
    identical images."""
    x, y = _pair(a, b)
    mse = float(np.mean((x - y) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(255.0**2 / mse))
