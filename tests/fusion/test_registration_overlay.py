"""The ``registration`` display mode (fusion.registration_overlay, fusion.composer): each
cell's sigma lands on the colour pixels nearest its centre, through a colour map that rises
with sigma over 0-2 px and is clipped above; cells without an estimate, pixels without a
thermal reading and cells whose depth moved since the estimate show the colour image; the
stereo step carries the legend and composes anew when an estimate arrives."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from tests.support import small_rig, synth_frames
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.camera import pixel_grid
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.composer import Composer
from trifuse.fusion.frame_meta import shows_palette
from trifuse.fusion.registration import RegistrationSigma
from trifuse.fusion.registration_overlay import (
    SIGMA_DEPTH_REL,
    SIGMA_SCALE_PX,
    SigmaOverlay,
    sigma_index,
    sigma_lut,
    sigma_lut_hex,
)
from trifuse.fusion.stereo_step import StereoStep

W, H = 64, 48
SCALE, STRIDE = 4, 2  # coarse cells of 4 x 4 pixels, every 2nd estimated: blocks of 8 x 8


def luma(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def estimate(
    sigma_px: np.ndarray, width: int = W, height: int = H, stride: int = STRIDE
) -> RegistrationSigma:
    """A :class:`RegistrationSigma` holding ``sigma_px`` on the strided coarse grid (cells
    of SCALE pixels) of a ``width`` x ``height`` colour image, the other arrays as
    ``registration_sigma`` shapes them."""
    hc, wc = -(-height // SCALE), -(-width // SCALE)
    centres = pixel_grid(wc, hc).astype(np.float64) * SCALE + (SCALE - 1) / 2.0
    centres = centres[::stride, ::stride]
    assert centres.shape[:2] == sigma_px.shape
    cov = np.full((*sigma_px.shape, 2, 2), np.nan)
    return RegistrationSigma(
        "ccd", "thermal", "tof", SCALE * stride, centres, sigma_px, cov, {}, cov, "test"
    )


def grid(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random sigmas 0-3 px on the strided grid (a tenth NaN), and the coarse depth (the
    mapping's full coarse grid) it was made at."""
    rng = np.random.default_rng(seed)
    hc, wc = H // SCALE, W // SCALE
    coarse_z = (1.0 + 4.0 * rng.random((hc, wc))).astype(np.float32)
    sigma = 3.0 * rng.random((-(-hc // STRIDE), -(-wc // STRIDE)))
    sigma[rng.random(sigma.shape) < 0.1] = np.nan
    return sigma, coarse_z


def nearest_cell(n_px: int, n_cells: int) -> np.ndarray:
    """(n_px,) the strided cell whose centre is nearest each pixel (no ties: the centres
    sit at 1.5 + 8 k)."""
    centre = (SCALE - 1) / 2.0 + SCALE * STRIDE * np.arange(n_cells)
    return np.argmin(np.abs(np.arange(n_px)[:, None] - centre[None, :]), axis=1)


def test_each_pixel_shows_its_cells_sigma_and_nan_cells_leave_the_colour_image() -> None:
    sigma, coarse_z = grid(1)
    overlay = SigmaOverlay.of(estimate(sigma), (W, H), coarse_z, STRIDE, False)
    rng = np.random.default_rng(2)
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    thermal = (290.0 + 20.0 * rng.random((H, W))).astype(np.float32)
    thermal[:, :5] = np.nan  # no thermal reading: the colour image, whatever the sigma
    out = Composer(W, H).compose(
        color,
        thermal,
        None,
        DisplaySettings(mode="registration", opacity=1.0),
        (280.0, 320.0),
        registration=overlay,
    )
    cell = sigma[nearest_cell(H, sigma.shape[0])[:, None], nearest_cell(W, sigma.shape[1])[None]]
    drawn = np.isfinite(cell) & np.isfinite(thermal)
    assert drawn.sum() > 0.7 * drawn.size and (~drawn).sum() > 100
    expected = sigma_lut()[sigma_index(cell)]
    np.testing.assert_array_equal(out[drawn], expected[drawn])
    np.testing.assert_array_equal(out[~drawn], color[~drawn])  # NaN cells: unchanged
    # blended like ``blend``: opacity * map + (1 - opacity) * colour (rounded)
    half = Composer(W, H).compose(
        color,
        thermal,
        None,
        DisplaySettings(mode="registration", opacity=0.5),
        None,
        registration=overlay,
    )
    mix = 0.5 * expected.astype(float) + 0.5 * color.astype(float)
    assert np.abs(half[drawn].astype(float) - mix[drawn]).max() <= 1.0
    np.testing.assert_array_equal(half[~drawn], color[~drawn])
    assert overlay.summary["cells"] == int(np.isfinite(sigma).sum())


def test_colour_map_rises_with_sigma_and_is_clipped_at_two_pixels() -> None:
    low, high = SIGMA_SCALE_PX
    assert (low, high) == (0.0, 2.0)
    values = np.round(np.arange(0.0, 2.0001, 0.1), 3)
    sigma = np.full((6, 8), 5.0)  # beyond the scale
    sigma.flat[: values.size] = values
    sigma[5, 7] = 2.5
    coarse_z = np.ones((H // SCALE, W // SCALE), np.float32)
    overlay = SigmaOverlay.of(estimate(sigma), (W, H), coarse_z, STRIDE, True)
    color = np.zeros((H, W, 3), np.uint8)
    thermal = np.full((H, W), 300.0, np.float32)
    out = Composer(W, H).compose(
        color,
        thermal,
        None,
        DisplaySettings(mode="registration", opacity=1.0),
        None,
        registration=overlay,
    )
    at = out[1::8, 1::8]  # one pixel of each cell (the cell's centre's neighbour)
    shown = at.reshape(-1, 3)
    lum = luma(shown[: values.size])
    assert np.all(np.diff(lum) > 0), lum  # brighter with every 0.1 px
    lut = sigma_lut()
    np.testing.assert_array_equal(shown[0], lut[0])  # 0 px: the first entry
    np.testing.assert_array_equal(shown[values.size - 1], lut[255])  # 2 px: the last
    np.testing.assert_array_equal(at[5, 7], lut[255])  # 2.5 px: clipped
    np.testing.assert_array_equal(at[4, 7], lut[255])  # 5 px: clipped
    assert len(sigma_lut_hex()) == 1536 and bytes.fromhex(sigma_lut_hex()) == lut.tobytes()


def test_cells_whose_depth_moved_are_left_out() -> None:
    sigma, coarse_z = grid(3)
    sigma[:] = 1.0  # every cell estimated
    overlay = SigmaOverlay.of(estimate(sigma), (W, H), coarse_z, STRIDE, False)
    now = coarse_z.copy()
    now[0:2, 0:2] *= 1.0 + 2 * SIGMA_DEPTH_REL  # strided cell (0, 0): the depth moved on
    now[4:6, 4:6] *= 1.0 + 0.5 * SIGMA_DEPTH_REL  # strided cell (2, 2): within the tolerance
    mask = overlay.mask_into(now, np.empty((H, W), np.uint8))
    rng = np.random.default_rng(4)
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    thermal = np.full((H, W), 300.0, np.float32)
    out = Composer(W, H).compose(
        color,
        thermal,
        None,
        DisplaySettings(mode="registration", opacity=1.0),
        None,
        registration=overlay,
        registration_mask=mask,
    )
    moved = np.zeros((H, W), bool)
    moved[:6, :6] = True  # the pixels nearest cell (0, 0)'s centre (1.5, 1.5)
    np.testing.assert_array_equal(out[moved], color[moved])
    np.testing.assert_array_equal(out[~moved], np.broadcast_to(sigma_lut()[128], out.shape)[~moved])
    assert mask.sum() == H * W - 36


def test_registration_mode_allocates_no_frame_per_picture() -> None:
    w, h = 1280, 960
    rng = np.random.default_rng(5)
    hc, wc = h // SCALE, w // SCALE
    stride = 5
    sigma = 2.0 * rng.random((-(-hc // stride), -(-wc // stride)))
    est = estimate(sigma, w, h, stride)
    overlay = SigmaOverlay.of(est, (w, h), np.ones((hc, wc), np.float32), stride, False)
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    thermal = (290.0 + 20.0 * rng.random((h, w))).astype(np.float32)
    comp, out = Composer(w, h), np.empty((h, w, 3), np.uint8)
    s = DisplaySettings(mode="registration")
    comp.compose(color, thermal, None, s, None, out=out, registration=overlay)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        for _ in range(3):
            comp.compose(color, thermal, None, s, None, out=out, registration=overlay)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < w * h * 3 / 10, f"peak {peak} bytes"


def test_the_step_carries_the_legend_and_composes_anew_for_a_new_estimate() -> None:
    rig = small_rig()
    step = StereoStep(rig, DisplaySettings(mode="registration"))
    frames = synth_frames(rig, 0.2, seed=6)
    sets = {}
    for f in frames:  # the newest frame of each sensor, as one set
        sets[f.sensor] = f
    fs = FrameSet(frames[-1].stamp_ns, sets)
    step.note(fs)
    step.update_depth(fs.stamp_ns)
    first = step.inputs(fs)
    step.render(first)
    meta = step.meta(first).as_json()
    assert meta["mode"] == "registration" and meta["span_k"] is None  # no temperature scale
    assert not shows_palette(first.settings)
    legend = meta["registration"]
    assert legend["scale_px"] == [0.0, 2.0] and legend["colormap_rgb"] == sigma_lut_hex()
    assert legend["eyes"] == {"left": None, "right": None}  # no estimate yet
    w, h = step.fusion.size
    z, _ = step.fusion.fusion["left"].forward.coarse_depth()
    hc, wc = z.shape
    est = estimate(np.full((hc, wc), 0.25), w, h, stride=1)
    step.fusion.set_registration("left", SigmaOverlay.of(est, (w, h), z, 1, False))
    again = step.inputs(fs)
    assert not again.same_picture(first)  # a new estimate: a new picture
    step.render(again)
    legend = step.meta(again).as_json()["registration"]
    assert legend["eyes"]["right"] is None
    assert legend["eyes"]["left"] == {
        "median_px": 0.25,
        "p95_px": 0.25,
        "cells": hc * wc,
        "calibration_covariance": False,
        "range_source": "test",
    }
    with pytest.raises(ValueError, match="eye"):
        step.fusion.set_registration("middle", None)
    step.settings = DisplaySettings(mode="blend")
    blend = step.inputs(fs)
    step.render(blend)
    assert "registration" not in step.meta(blend).as_json()
