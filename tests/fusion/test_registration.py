"""Registration uncertainty per pixel (fusion.registration) against the fusion itself: a
Monte Carlo of the calibration and range errors re-fused, and the footprint share against
the fusion's own error on slanted planes of exactly known depth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from trifuse.calib.camera import pixel_grid
from trifuse.calib.range_correction import RangeCorrection, offset_grid_shape
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.tof import region_map
from trifuse.fusion.mapping import MappingOptions, TofGrid, ViewMapping
from trifuse.fusion.registration import (
    UNCORRECTED_RANGE_SIGMA_M,
    RangeError,
    major_sigma,
    range_error,
    registration_sigma,
)

SCALE = 8  # coarse cells of 8 x 8 colour pixels: 160 x 120 cells, cheap to re-fuse
NO_RANGE = RangeError(dict.fromkeys((1, 2, 3, 4), 0.0), "none")


def _plane(rig: Rig, tof: str, tilt_deg: float, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A TOF distance image (H, W) of a plane ``distance_m`` from the TOF, turned by
    ``tilt_deg`` about the TOF's y axis, and its unit normal (TOF frame)."""
    n = np.array([np.sin(np.radians(tilt_deg)), 0.1, np.cos(np.radians(tilt_deg))])
    n /= np.linalg.norm(n)
    return distance_m / (TofGrid(rig, tof).rays.astype(np.float64) @ n), n


def _eye(rig: Rig, eye: str = "left") -> tuple[str, str, str]:
    e = rig.eyes[eye]
    return e.color, e.thermal, rig.by_modality("tof")[0]


@pytest.mark.slow  # 200 fusions: 15-30 s
def test_propagated_sigma_matches_a_monte_carlo_of_the_fusion(simulated: dict) -> None:
    """Draw the calibration within its covariance (the rig file's) and the TOF's distances
    within their per-region error, re-fuse each draw, and compare the spread of where the
    thermal values land (colour pixels) with the propagated sigma, cell by cell."""
    rig = simulated["rig"]
    color, thermal, tof = _eye(rig)
    dist, _ = _plane(rig, tof, 20.0, 3.0)
    s = rig[tof]
    box = np.zeros(dist.shape, bool)  # a box 1.2 m nearer in the middle: depth edges
    box[50:90, 70:110] = True
    dist[box] -= 1.2
    rerr = RangeError({1: 0.01, 2: 0.02, 3: 0.03, 4: 0.05}, "test")
    opts = MappingOptions(scale=SCALE)
    base = ViewMapping(rig, color, thermal, options=opts)
    base.update(dist)
    z, ok, F0 = base.coarse_cells()
    pred = registration_sigma(rig, rig.covariance, color, thermal, tof, z, ok, SCALE, rerr)

    sub = rig.covariance.restricted((color, thermal, tof))
    rng = np.random.default_rng(7)
    K = 200
    deltas = sub.sample(rng, K)
    regions = region_map(s.width, s.height)
    sig_d = rerr.per_pixel(s.width, s.height)
    moved = np.empty((K, *F0.shape))
    seen = ok.copy()
    for k in range(K):
        m = ViewMapping(rig.perturbed(sub, deltas[k]), color, thermal, options=opts)
        m.update(dist + rng.standard_normal(5)[regions] * sig_d)  # one error per region
        _, ok_k, F_k = m.coarse_cells()
        moved[k] = F_k - F0
        seen &= ok_k
    land = np.einsum("hwij,khwj->khwi", pred.thermal_to_color, moved)  # colour px
    land -= land.mean(axis=0)
    emp = major_sigma(np.einsum("khwi,khwj->hwij", land, land) / (K - 1))
    predicted = major_sigma(pred.parts["calibration"] + pred.parts["range"])
    cells = seen & np.isfinite(predicted)
    assert cells.sum() > 0.6 * ok.size
    ratio = emp[cells] / predicted[cells]
    # 200 draws: a sigma is known to 1/sqrt(2 K) = 5 %; the draws are shared by every cell
    # (their ratios err together), and the z-buffer's choice among TOF points shifts with
    # each draw (+3 % measured), which the linear propagation of these two shares omits.
    assert 0.88 < np.median(ratio) < 1.15, np.median(ratio)
    lo, hi = np.percentile(ratio, [5, 95])
    assert lo > 0.8 and hi < 1.3, (lo, hi)
    # every part is there: the calibration's share is not negligible here
    assert np.nanmedian(major_sigma(pred.parts["calibration"])) > 0.1 * np.nanmedian(predicted)

    # the box's outline has no estimate (a depth edge), its inside and the wall have
    row = pred.centres[:, 0, 1]
    col = pred.centres[0, :, 0]
    finite = np.isfinite(pred.sigma_px)
    assert finite.mean() > 0.6
    assert not finite[np.ix_(np.abs(row - 480) < 300, np.abs(col - 640) < 400)].all()


@pytest.mark.parametrize("tilt_deg", [10.0, 50.0])
@pytest.mark.parametrize("scale", [4, 8])
def test_footprint_share_is_the_fusions_own_error_on_a_slanted_plane(
    simulated: dict, tilt_deg: float, scale: int
) -> None:
    """With the true rig and exact distances the only error left is the depth the fusion
    holds over each cell; its predicted RMS is the measured one (exact plane geometry)."""
    rig = simulated["truth"]
    color, thermal, tof = _eye(rig)
    dist, n_tof = _plane(rig, tof, tilt_deg, 3.0)
    m = ViewMapping(rig, color, thermal, options=MappingOptions(scale=scale))
    m.update(dist)
    z, ok, F = m.coarse_cells()
    hc, wc = z.shape
    q = pixel_grid(wc, hc) * scale + (scale - 1) / 2
    rays = np.concatenate([rig[color].intrinsics.normalized(q), np.ones((hc, wc, 1))], -1)
    T_tof_c, T_t_c = rig.T(tof, color), rig.T(thermal, color)
    depth = (3.0 - n_tof @ T_tof_c[:3, 3]) / (rays @ (T_tof_c[:3, :3].T @ n_tof))
    exact = rig[thermal].intrinsics.project(
        (depth[..., None] * rays) @ T_t_c[:3, :3].T + T_t_c[:3, 3]
    )
    pred = registration_sigma(rig, None, color, thermal, tof, z, ok, scale, NO_RANGE)
    err = np.einsum("hwij,hwj->hwi", pred.thermal_to_color, F - exact)
    cells = np.isfinite(pred.sigma_px) & ok
    actual = np.sqrt(np.mean(np.sum(err[cells] ** 2, axis=-1)))
    share = np.sqrt(np.mean(np.trace(pred.parts["footprint"][cells], axis1=1, axis2=2)))
    assert actual > 0.005  # there is an error to predict (0.008-0.05 px here)
    assert 0.85 < share / actual < 1.15, (share, actual)
    assert np.all(pred.parts["calibration"][cells] == 0)  # no covariance given
    assert np.all(pred.parts["range"][cells] == 0)


def test_range_error_comes_from_the_rigs_range_correction(simulated: dict) -> None:
    rig = simulated["rig"]
    tof = rig.by_modality("tof")[0]
    assert rig[tof].range_correction is None
    plain = range_error(rig, tof)
    assert set(plain.sigma_m.values()) == {UNCORRECTED_RANGE_SIGMA_M}
    assert "no range correction" in plain.source
    w, h = rig[tof].image_size
    fit = {"holdout_rms_mm": {"before": 40.0, "after": 9.0}}
    overall = range_error(rig.with_sensor(_with_range(rig[tof], fit)), tof)
    assert set(overall.sigma_m.values()) == {0.009}
    regions = {"1": 5.0, "2": 6.0, "3": 8.0, "4": 20.0}
    with_regions = {**fit, "holdout_region_rms_mm": regions}
    per_region = range_error(rig.with_sensor(_with_range(rig[tof], with_regions)), tof)
    assert per_region.sigma_m == {1: 0.005, 2: 0.006, 3: 0.008, 4: 0.02}
    px = per_region.per_pixel(w, h)
    assert px[h // 2, w // 2] == 0.005 and px[0, 0] == 0.02


def _with_range(sensor: Sensor, fit: dict) -> Sensor:
    """``sensor`` with a range correction that corrects nothing, fitted as ``fit`` says."""
    w, h = sensor.image_size
    rc = RangeCorrection((w, h), 0.9, 0.5, np.zeros(4), 8, np.zeros(offset_grid_shape(w, h, 8)))
    return replace(sensor, range_correction=replace(rc, fit=fit))


def test_cells_without_depth_have_no_estimate(simulated: dict) -> None:
    rig = simulated["rig"]
    color, thermal, tof = _eye(rig)
    z = np.full((120, 160), np.nan, np.float32)
    r = registration_sigma(
        rig, rig.covariance, color, thermal, tof, z, np.zeros(z.shape, bool), SCALE, NO_RANGE
    )
    assert np.isnan(r.sigma_px).all()
    assert r.summary() == {"median_px": None, "p95_px": None, "cells": 0}


def test_range_share_against_distance_is_the_parallax_of_the_depth_error() -> None:
    """A wall facing the colour camera: a TOF distance error dd moves the depth by about
    dd cos(angle off the TOF's axis), and the thermal value by the parallax between the two
    cameras, f B dd / z^2 (B their baseline across the view): the inverse-square law, with
    the median over the picture of that cosine (near 1) as the factor."""
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.fusion.registration import sigma_vs_distance

    rig = default_rig()
    d = np.array([1.0, 2.0, 3.0, 5.0, 10.0])
    err = RangeError(dict.fromkeys((1, 2, 3, 4), 0.01), "test")
    curve = sigma_vs_distance(rig, "ccd_left", "thermal_left", "tof", d, err, 64)
    baseline = np.hypot(*rig.T("thermal_left", "ccd_left")[:2, 3])
    factor = curve.median_px["range"] * d**2 / (rig["ccd_left"].intrinsics.fx * baseline * 0.01)
    assert np.all((factor > 0.85) & (factor <= 1.0)), factor
    assert np.ptp(factor) < 0.01 * factor.mean()  # 1 / z^2, at every distance
    assert rig.covariance is None and np.all(curve.median_px["calibration"] == 0)
    assert np.all(curve.median_px["footprint"] == 0)  # a flat wall: no depth change
    assert np.allclose(curve.median_px["total"], curve.median_px["range"])
    assert np.all(curve.p95_px["total"] >= curve.median_px["total"])


def test_mapping_difference_of_a_turned_thermal_imager_is_its_angle_in_colour_pixels() -> None:
    """0.3° of a thermal imager's rotation about its vertical axis moves every thermal
    value by about f_colour * 0.3° (7 colour pixels, the issue's example; a little more off
    the axis) at any distance; a rig against itself differs by nothing."""
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.calib.parameter_covariance import ParameterCovariance
    from trifuse.fusion.registration import mapping_difference

    rig = default_rig()
    turn = ParameterCovariance.from_matrix(["thermal_left.ry"], np.eye(1))
    turned = rig.perturbed(turn, np.array([np.radians(0.3)]))
    d = np.array([0.5, 1.0, 3.0, 10.0])
    same = mapping_difference(rig, rig, "ccd_left", "thermal_left", "tof", d)
    assert np.all(same.max_px == 0)
    moved = mapping_difference(rig, turned, "ccd_left", "thermal_left", "tof", d, cell_px=32)
    # a turn by t about y moves a pinhole's pixel at normalised (x, y) by f t (1 + x^2, x y)
    c = rig["ccd_left"].intrinsics
    xy = c.normalized(pixel_grid(40, 30).reshape(-1, 2) * 32 + 15.5)
    x, y = xy[:, 0], xy[:, 1]
    expected = c.fx * np.radians(0.3) * np.median(np.hypot(1 + x * x, x * y))  # 7.2 px
    assert np.allclose(moved.median_px, expected, rtol=0.03), (moved.median_px, expected)
    assert np.all(moved.p95_px >= moved.median_px) and np.all(moved.max_px >= moved.p95_px)
    assert moved.worst()[0] == np.max(moved.median_px)
    other_eye = mapping_difference(rig, turned, "ccd_right", "thermal_right", "tof", d)
    assert np.all(other_eye.max_px == 0)
