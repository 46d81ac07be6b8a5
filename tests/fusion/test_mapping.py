"""Thermal onto colour through TOF depth: occlusion, invalid depth, accuracy per band."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.app.sources.sim.render import HeadModel, Renderer
from trifuse.app.sources.sim.scene import Box, Material, Quad, Scene
from trifuse.app.sources.sim.tof_error import RangeErrorModel
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.transforms import make_T
from trifuse.fusion.accuracy import band_errors, depth_edges, exact_mapping, fixed_depth_mapping
from trifuse.fusion.mapping import DepthView, EyeFusion, TofGrid, ViewMapping, mixed_pixels

RIG = default_rig()
NO_RANGE_ERROR = RangeErrorModel(
    bias_m=0.0, wiggle=(), radial_m=0.0, border_m=0.0, pixel_sigma_m=0.0, amplitude_m=0.0
)
SENSORS = ["ccd_left", "thermal_left", "tof"]


@pytest.fixture(scope="module")
def wall_and_box():
    """A 350 K wall at 3 m and a 290 K box 1 m in front of the head, slightly left."""
    wall = Quad(
        "wall",
        Material((0.6, 0.6, 0.6), 350.0, 1.0, 0.6),
        make_T(np.eye(3), (0, 0, 3.0)),
        (-5, 5, -5, 5),
    )
    box = Box(
        "box",
        Material((0.2, 0.3, 0.6), 290.0, 1.0, 0.6),
        make_T(np.eye(3), (-0.1, 0.0, 1.0)),
        (0.12, 0.15, 0.1),
    )
    scene = Scene([wall, box], ambient_k=300.0)
    model = HeadModel(range_error=NO_RANGE_ERROR, thermal_offset_k={})
    frames, truth = Renderer(RIG, model).render(
        scene, np.eye(4), 0, np.random.default_rng(0), SENSORS
    )
    m = ViewMapping(RIG, "ccd_left", "thermal_left")
    m.update(frames["tof"].distance_m)
    fused = m.warp(frames["thermal_left"].image)
    exact = exact_mapping(
        RIG, "ccd_left", "thermal_left", truth["ccd_left"].range_m, truth["thermal_left"].range_m
    )
    return m, fused, truth, exact


def test_object_in_front_of_a_hot_wall_keeps_its_own_temperature(wall_and_box) -> None:
    _m, fused, truth, exact = wall_and_box
    away = ~depth_edges(exact.depth_m, 16)
    on_box = (truth["ccd_left"].solid == 1) & away
    assert on_box.sum() > 5000
    t = fused[on_box]
    assert np.isfinite(t).all()
    # 290 K box, 0.08 K noise: nothing near the wall's 350 K leaks onto it.
    assert np.max(np.abs(t - 290.0)) < 1.0
    on_wall = (truth["ccd_left"].solid == 0) & away & exact.visible
    wall_t = fused[on_wall]
    assert np.isfinite(wall_t).mean() > 0.95  # the rest: beyond the thermal image's border
    assert np.nanmedian(np.abs(wall_t - 350.0)) < 0.2


def test_points_hidden_from_the_thermal_imager_are_not_painted(wall_and_box) -> None:
    _m, fused, truth, exact = wall_and_box
    # Wall pixels the colour camera sees but the thermal imager cannot (behind the box),
    # more than ~2.4 thermal pixels (8 colour pixels) inside that shadow: at its border the
    # thermal optics blur both surfaces into one pixel.
    shadow = (truth["ccd_left"].solid == 0) & ~exact.visible
    inner = cv2.erode(shadow.astype(np.uint8), np.ones((17, 17), np.uint8)).astype(bool)
    hidden = inner & ~depth_edges(exact.depth_m, 16)
    assert hidden.sum() > 500
    t = fused[hidden]
    # Never the occluder's temperature: either left empty or the wall's own.
    assert not np.any(np.abs(t - 290.0) < 5.0)
    assert np.isnan(t).mean() > 0.9


def test_invalid_depth_is_marked_and_never_a_point_at_the_origin() -> None:
    scenario = InspectionScenario(seed=1)
    frames, _ = scenario.render(0.0, SENSORS)
    distance = frames["tof"].distance_m.copy()
    distance[40:80, 60:120] = np.nan  # a patch of invalid TOF pixels
    distance[0:5, 0:5] = 0.0
    m = ViewMapping(RIG, "ccd_left", "thermal_left")
    pts = m.points(distance)
    assert np.isfinite(pts).all() and np.min(np.linalg.norm(pts, axis=1)) > 0.1
    m.update(distance)
    assert m.fallback.any()
    # The patch's centre, seen from the colour camera, is marked as fallback depth.
    centre = RIG["tof"].intrinsics.unproject(np.array([[90.0, 60.0]]))[0] * 4.0
    T = RIG.T("ccd_left", "tof")
    u, v = RIG["ccd_left"].intrinsics.project(T[:3, :3] @ centre + T[:3, 3])
    assert m.fallback[int(v), int(u)]
    full = ViewMapping(RIG, "ccd_left", "thermal_left")
    full.update(frames["tof"].distance_m)
    assert full.fallback.sum() < m.fallback.sum()


def test_z_buffer_ignores_points_beyond_the_fold_and_on_the_image_plane() -> None:
    # k1 = -0.4 folds at a normalised radius of 0.913: a point at radius 1.5 would be drawn
    # at radius 0.15, well inside the image, hiding what is really there.
    cam = Intrinsics(200.0, 200.0, 159.5, 119.5, (-0.4, 0.0, 0.0, 0.0, 0.0))
    rig = Rig(
        sensors={
            "tof": Sensor(
                "tof", "tof", (101, 101), Intrinsics(100.0, 100.0, 50.0, 50.0), np.eye(4)
            ),
            "cam": Sensor("cam", "color", (320, 240), cam, np.eye(4)),
        },
        reference="tof",
    )
    view = DepthView(rig, "cam", "tof", 1)
    points = np.array([[1.5, 0.0, 1.0], [0.3, 1e-17, 1e-17], [0.25, 0.0, 2.0]])
    z = view.render(points)
    # Only the last point, at radius 0.125 (v = 119.5 rounds up to row 120), splatted over
    # 3 x 3 cells (a TOF pixel spans two of the camera's).
    u = round(159.5 + 200.0 * 0.125 * (1 - 0.4 * 0.125**2))
    np.testing.assert_array_equal(
        np.argwhere(np.isfinite(z)), [(v, c) for v in (119, 120, 121) for c in (u - 1, u, u + 1)]
    )
    assert (z[119:122, u - 1 : u + 2] == 2.0).all()


@pytest.mark.parametrize("scale", [1, 2, 4])
def test_z_buffer_keeps_the_nearest_point_over_each_footprint(scale: int) -> None:
    """The splat keeps, in every cell, the nearest of the points whose footprint (the cells
    within ``radius`` of their own) covers it: compared with splatting each point over its
    footprint one cell offset at a time, on points all over and around the image (those
    just outside still cover the border)."""
    view = DepthView(RIG, "ccd_left", "tof", scale)
    assert view.radius >= 1
    rng = np.random.default_rng(7)
    points = rng.uniform((-4.0, -3.0, 0.3), (4.0, 3.0, 8.0), (30_000, 3)).astype(np.float32)
    got = view.render(points).copy()

    T = view.T_sensor_tof
    P = points @ T[:3, :3].T + T[:3, 3]
    uv = RIG["ccd_left"].intrinsics.project(P).astype(np.float32)
    keep = (P[:, 2] > 0.05) & np.isfinite(uv).all(axis=1)
    cu = np.floor((uv[keep, 0] + 0.5) / scale).astype(int)
    cv = np.floor((uv[keep, 1] + 0.5) / scale).astype(int)
    z = P[keep, 2]
    want = np.full(view.shape, np.inf, np.float32)
    hc, wc = view.shape
    r = view.radius
    for dv in range(-r, r + 1):
        for du in range(-r, r + 1):
            u, v = cu + du, cv + dv
            ok = (u >= 0) & (u < wc) & (v >= 0) & (v < hc)
            np.minimum.at(want, (v[ok], u[ok]), z[ok])
    border = np.isfinite(want[0]).sum() + np.isfinite(want[:, 0]).sum()
    assert border > 0 and np.isfinite(want).mean() > 0.3  # the border and many cells covered
    np.testing.assert_array_equal(got, want)


def test_smooth_middle_removes_the_nearest_depths_bias_on_a_slanted_plane() -> None:
    """A plane turned 45 degrees about the vertical, 2 m ahead, seen by the TOF itself (its
    own pixels, scale 1, radius 1): the nearest depth over each 3 x 3 footprint is nearer
    than the plane by about one cell's change of depth; the middle of the footprint's depths
    (``smooth_rel``) is the plane within a tenth of that. Where the footprint meets a step
    of 1 m, both keep the nearest (the foreground wins)."""
    tof = RIG[RIG.by_modality("tof")[0]]
    rig = Rig({"tof": tof}, "tof")
    w, h = tof.image_size
    rays = TofGrid(rig).rays.astype(np.float64)
    normal = np.array([np.sin(np.radians(45)), 0.0, np.cos(np.radians(45))])
    d = 2.0 * np.cos(np.radians(45))  # n . X = d: through (0, 0, 2)
    t = d / (rays @ normal)
    step = np.zeros((h, w), bool)
    step[:, : w // 3] = True  # a wall 1 m nearer on the left third
    t[step] = (1.0 / rays[..., 2])[step]
    points = (rays * t[..., None]).reshape(-1, 3).astype(np.float32)
    plane_z = t * rays[..., 2]
    nearest = DepthView(rig, "tof", "tof", 1).render(points).copy()
    middle = DepthView(rig, "tof", "tof", 1, smooth_rel=0.05).render(points).copy()
    inner = np.zeros((h, w), bool)
    inner[2:-2, w // 3 + 2 : -2] = True  # on the plane, away from the step and the border
    gx = np.abs(np.gradient(plane_z, axis=1))
    bias_nearest = np.median((nearest - plane_z)[inner] / gx[inner])
    bias_middle = np.median((middle - plane_z)[inner] / gx[inner])
    assert -1.2 < bias_nearest < -0.8  # one cell's change of depth
    assert abs(bias_middle) < 0.1
    edge = np.zeros((h, w), bool)
    edge[:, w // 3 - 1 : w // 3 + 1] = True  # footprints that meet both surfaces
    np.testing.assert_array_equal(middle[edge], nearest[edge])
    assert np.all(middle[edge] < 1.05 * plane_z[:, : w // 3].max())


def test_mixed_pixels_are_only_those_between_two_surfaces() -> None:
    d = np.full((5, 7), 3.0, np.float32)
    d[:, :3] = 1.0
    d[2, 3] = 2.0  # a flying pixel between the 1 m and 3 m surfaces
    mixed = mixed_pixels(d, 0.05)
    assert mixed[2, 3] and mixed.sum() == 1


@pytest.mark.parametrize("eye", ["left", "right"])
def test_accuracy_per_band_against_the_exact_mapping(eye: str) -> None:
    """With a range-corrected TOF: within 0.5 thermal px at 0.5-8 m, away from depth
    edges, and at 0.5-2 m at least 5x better than one fixed homography (3 m)."""
    scenario = InspectionScenario(model=HeadModel(range_error=NO_RANGE_ERROR), seed=2)
    color, thermal = RIG.eyes[eye].color, RIG.eyes[eye].thermal
    fusion = EyeFusion(RIG, eye)
    ours, naive = [], []
    for t_s in (0.0, 10.0):
        frames, truth = scenario.render(t_s, [color, thermal, "tof"])
        m = fusion.forward
        m.update(frames["tof"].distance_m)
        exact = exact_mapping(RIG, color, thermal, truth[color].range_m, truth[thermal].range_m)
        mask = ~depth_edges(exact.depth_m, 16) & m.visible & ~m.fallback
        ours.append(band_errors(np.stack([m.map_x, m.map_y], -1), exact, mask))
        naive.append(band_errors(fixed_depth_mapping(RIG, color, thermal, 3.0), exact, mask))
    for k in range(4):
        med = [b[k].median_px for b in ours if b[k].pixels > 1000]
        base = [b[k].median_px for b in naive if b[k].pixels > 1000]
        assert med, f"band {ours[0][k].band_m}: no pixels"
        assert max(med) < 0.5, (ours[0][k].band_m, med)
        if ours[0][k].band_m[1] <= 2.0:
            assert min(base) > 5 * max(med), (ours[0][k].band_m, med, base)
