"""The ``registration`` display mode's picture: each colour pixel's registration sigma
(:mod:`fusion.registration`) as a colour map over the colour image.

:class:`SigmaOverlay` is made once per sigma estimate (the console makes one every few
seconds, off the fusion thread) and drawn by :class:`fusion.composer.Composer` on every
picture: the estimate's coarse grid brought to the colour image's pixels (each pixel takes
the cell whose centre is nearest: one value per ``cell_px`` x ``cell_px`` block, no blending
across cells; one ``cv2.warpAffine``), then through :data:`SIGMA_SCALE_PX`'s fixed scale into
the colour map (:func:`sigma_lut`: OpenCV's viridis, dark violet at 0 px to yellow at 2 px,
clipped above). Pixels without an estimate (no TOF depth, not seen by the thermal imager, on
a depth edge) are left out (:attr:`SigmaOverlay.mask`): the picture shows the colour image
there.

An estimate holds for the depth it was made at. While the head or the scene moves, the
pictures go on with newer depth: a cell whose depth now differs from the estimate's by more
than :data:`SIGMA_DEPTH_REL` is left out too (:meth:`SigmaOverlay.mask_into`, once per depth
update), so that a sigma is never drawn on another surface than the one it was made for.

Pure: arrays in, arrays out.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from trifuse.fusion.registration import RegistrationSigma

SIGMA_SCALE_PX = (0.0, 2.0)
"""The colour map's fixed scale, colour pixels: 0 gets its first entry, 2 (and above,
clipped) its last."""
SIGMA_DEPTH_REL = 0.05
"""A cell's sigma is drawn while its depth is within this fraction of the depth it was
estimated at (the fusion's own depth-edge threshold, ``MappingOptions.edge_rel``)."""
SIGMA_COLORMAP = "viridis"
"""The colour map's name (OpenCV's ``COLORMAP_VIRIDIS``): unlike the thermal palettes, so
that the picture is not read as temperatures; brighter is larger."""


@functools.cache
def sigma_lut() -> np.ndarray:
    """(256, 3) uint8 RGB, read-only: the colour map, entry 0 for 0 px, 255 for 2 px."""
    bgr = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)
    lut = np.ascontiguousarray(bgr[:, 0, ::-1])
    lut.flags.writeable = False
    return lut


@functools.cache
def sigma_lut_hex() -> str:
    """:func:`sigma_lut` as 1536 hex digits (two per channel, RGB, entry 0 first), the
    layout of the thermal scale's ``palette_rgb``."""
    return sigma_lut().tobytes().hex()


def sigma_index(sigma_px: np.ndarray) -> np.ndarray:
    """Colour-map entries (same shape, uint8) of sigmas in colour pixels:
    ``round(255 * sigma / 2)`` clipped to [0, 255]; NaN gets 0 (mask it)."""
    low, high = SIGMA_SCALE_PX
    s = np.nan_to_num(np.asarray(sigma_px, dtype=np.float64), nan=low)
    return np.rint(np.clip((s - low) / (high - low), 0.0, 1.0) * 255.0).astype(np.uint8)


def cells_to_pixels(
    cells: np.ndarray,
    size: tuple[int, int],
    first_centre_px: tuple[float, float],
    cell_px: int,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """A coarse grid (h, w) or (h, w, 3) uint8 at the pixels of a (width, height) image:
    each pixel takes the cell whose centre is nearest (cell (i, j) centred on pixel
    ``first_centre_px + (j, i) * cell_px``; beyond the grid, its border cell). One
    ``cv2.warpAffine`` (nearest) into ``out`` if given."""
    u0, v0 = first_centre_px
    inverse = np.array([[1.0 / cell_px, 0.0, -u0 / cell_px], [0.0, 1.0 / cell_px, -v0 / cell_px]])
    return cv2.warpAffine(
        cells,
        inverse,
        size,
        dst=out,
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


@dataclass(frozen=True, eq=False)
class SigmaOverlay:
    """One eye's registration sigma at the colour image's pixels, ready to draw.

    Attributes:
        rgb: (H, W, 3) uint8 RGB, read-only: each pixel's sigma through the colour map.
        mask: (H, W) uint8, read-only: 1 where the pixel has an estimate, 0 elsewhere.
        depth_m: (h, w) float32, read-only: the depth each cell's estimate was made at
            (metres along the colour camera's axis; NaN where there is no estimate).
        stride: the estimate's cells are every ``stride``-th cell of the mapping's coarse
            grid (:meth:`fusion.mapping.ViewMapping.coarse_depth`).
        first_centre_px: (u, v) colour pixel of the first cell's centre.
        summary: ``{"median_px", "p95_px", "cells"}`` over the cells with an estimate
            (:meth:`fusion.registration.RegistrationSigma.summary`).
        calibration_covariance: whether the calibration's share is in (the rig carries the
            covariance of this eye's sensors); else only the range and footprint shares.
        range_source: where the TOF range error came from, in words.
        cell_px: colour pixels per cell side of the grid the sigma was computed on.
    """

    rgb: np.ndarray
    mask: np.ndarray
    depth_m: np.ndarray
    stride: int
    first_centre_px: tuple[float, float]
    summary: Mapping[str, float | int | None]
    calibration_covariance: bool
    range_source: str
    cell_px: int

    @classmethod
    def of(
        cls,
        sigma: RegistrationSigma,
        size: tuple[int, int],
        coarse_z: np.ndarray,
        stride: int,
        calibration_covariance: bool,
    ) -> SigmaOverlay:
        """The overlay of ``sigma`` on a colour image of ``size`` (width, height) pixels:
        each pixel takes the value of the cell whose centre (``sigma.centres``) is nearest.

        Args:
            sigma: the estimate, made with ``stride`` over the coarse depth ``coarse_z``
                ((hc, wc) float32 metres: :meth:`fusion.mapping.ViewMapping.coarse_cells`).
            calibration_covariance: whether the estimate has the calibration's share.
        """
        coarse = sigma.sigma_px
        if coarse.size == 0:
            raise ValueError("sigma: expected at least one cell, got an empty grid")
        z = np.asarray(coarse_z, dtype=np.float32)[::stride, ::stride]
        if z.shape != coarse.shape:
            raise ValueError(
                f"coarse_z: expected {coarse.shape} cells at stride {stride}, got {z.shape}"
            )
        first = (float(sigma.centres[0, 0, 0]), float(sigma.centres[0, 0, 1]))
        found = np.isfinite(coarse)
        mask = cells_to_pixels(found.view(np.uint8), size, first, sigma.cell_px)
        lut = sigma_lut()[sigma_index(coarse)]  # (h, w, 3): one look-up per cell
        rgb = cells_to_pixels(lut, size, first, sigma.cell_px)
        depth = np.where(found, z, np.float32(np.nan))
        for a in (rgb, mask, depth):
            a.flags.writeable = False
        return cls(
            rgb,
            mask,
            depth,
            int(stride),
            first,
            dict(sigma.summary()),
            bool(calibration_covariance),
            sigma.range_source,
            int(sigma.cell_px),
        )

    def mask_into(
        self, coarse_z: np.ndarray, out: np.ndarray, rel: float = SIGMA_DEPTH_REL
    ) -> np.ndarray:
        """``out`` (H, W) uint8: 1 where the pixel's cell has an estimate and its depth now,
        ``coarse_z`` ((hc, wc) float32 metres: the mapping in use,
        :meth:`fusion.mapping.ViewMapping.coarse_depth`), is within ``rel`` of the depth
        the estimate was made at; 0 elsewhere."""
        z = coarse_z[:: self.stride, :: self.stride]
        if z.shape != self.depth_m.shape:
            raise ValueError(
                f"coarse_z: expected {self.depth_m.shape} cells at stride {self.stride}, "
                f"got {z.shape}"
            )
        with np.errstate(invalid="ignore"):  # NaN (no estimate) compares false
            held = np.abs(z - self.depth_m) <= rel * self.depth_m
        h, w = self.mask.shape
        return cells_to_pixels(held.view(np.uint8), (w, h), self.first_centre_px, self.cell_px, out)

    def as_json(self) -> dict[str, Any]:
        """``median_px``, ``p95_px`` (rounded to 0.001 px; null without an estimate),
        ``cells``, ``calibration_covariance`` and ``range_source``."""
        s = self.summary

        def px(v: float | int | None) -> float | None:
            return None if v is None else round(float(v), 3)

        return {
            "median_px": px(s.get("median_px")),
            "p95_px": px(s.get("p95_px")),
            "cells": int(s.get("cells") or 0),
            "calibration_covariance": self.calibration_covariance,
            "range_source": self.range_source,
        }


def registration_meta(overlays: Mapping[str, SigmaOverlay | None], eyes: tuple[str, ...]) -> dict:
    """What the viewer's legend of the ``registration`` mode needs: ``scale_px`` ([0, 2]
    colour pixels), ``colormap`` (its name), ``colormap_rgb`` (:func:`sigma_lut_hex`) and
    ``eyes``: eye -> :meth:`SigmaOverlay.as_json`, or None before the eye's first estimate."""
    return {
        "scale_px": list(SIGMA_SCALE_PX),
        "colormap": SIGMA_COLORMAP,
        "colormap_rgb": sigma_lut_hex(),
        "eyes": {
            e: (None if overlays.get(e) is None else overlays[e].as_json())  # type: ignore[union-attr]
            for e in eyes
        },
    }
