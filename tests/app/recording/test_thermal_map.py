"""The thermal 3D map against the simulator's truth (issue 20): the scene's exact surfaces
(Scene.nearest_surface), what each TOF point looks like to the other sensors, the map of
the survey, and the pose estimated from the TOF clouds."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.app.sources.sim.inspection import inspection_scene
from trifuse.app.sources.sim.render import HeadModel
from trifuse.app.sources.sim.survey import SURVEY_S, SurveyScenario, survey_pose
from trifuse.app.sources.sim.tof_error import RangeErrorModel
from trifuse.calib.transforms import rotation_angle_deg
from trifuse.fusion.map_builder import MapBuilder
from trifuse.fusion.mapping import TofGrid
from trifuse.fusion.odometry import TofOdometry
from trifuse.fusion.point_attributes import PointAttributes
from trifuse.fusion.voxel_map import MapSettings

EXACT_RANGE = RangeErrorModel(
    bias_m=0.0, wiggle=(), radial_m=0.0, border_m=0.0, pixel_sigma_m=0.0, amplitude_m=0.0
)
"""A TOF without systematic range error (its noise stays: 1.5 mm at the reference
amplitude), as after a perfect range calibration: the map's own accuracy."""
THERMAL_ONLY = ["tof", "thermal_left", "thermal_right"]


def exact_head(**kwargs) -> HeadModel:
    return HeadModel(range_error=EXACT_RANGE, **kwargs)


def test_the_nearest_surface_is_exact_on_and_off_the_surfaces() -> None:
    scene = inspection_scene()
    rng = np.random.default_rng(11)
    dirs = rng.normal(size=(5000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = np.stack([s.intersect(np.zeros(3), dirs) for s in scene.solids], axis=1)
    hit = np.isfinite(t.min(axis=1))
    on = dirs[hit] * t.min(axis=1)[hit, None]
    dist, index, nearest = scene.nearest_surface(on)
    assert dist.max() < 1e-9
    np.testing.assert_array_equal(index, t.argmin(axis=1)[hit])
    np.testing.assert_allclose(nearest, on, atol=1e-9)
    # 3 cm off a wall along its normal (the back wall at z = 8.2, away from other solids)
    p = np.array([[0.0, 0.5, 8.2 - 0.03], [-1.0, -0.2, 8.2 - 0.03]])
    np.testing.assert_allclose(scene.nearest_surface(p)[0], 0.03, atol=1e-9)
    head = scene.solids[[s.name for s in scene.solids].index("person_head")]
    away = np.asarray(head.centre) + np.array([[0.0, 0.0, -0.12 - 0.05]])
    np.testing.assert_allclose(scene.nearest_surface(away)[0], 0.05, atol=1e-9)


def test_each_tof_point_takes_the_temperature_of_what_the_imager_sees_there() -> None:
    """The thermal imagers without their offsets: a point's sample against the surface's
    apparent temperature (what an ideal imager reads), and points hidden from an imager
    (behind the pole, the people) come out unseen rather than with the occluder's value."""
    sc = SurveyScenario(seed=2, live=True, model=exact_head(thermal_offset_k={}))
    rig, scene = sc.rig, sc.scene
    fs, _ = sc.render(0.0, THERMAL_ONLY)
    points = TofGrid(rig, "tof").points(fs.frames["tof"].distance_m, 0.05).astype(np.float64)
    pa = PointAttributes(rig, "tof")
    sampler = pa.samplers["thermal_left"]
    uv = sampler.visible_pixels(points)
    seen = np.isfinite(uv[:, 0])
    # Truth: does the imager's ray to the point hit something else first?
    T_world_thermal = sc.T_world_rig(0.0) @ rig["thermal_left"].T_rig_sensor
    world = points @ sc.T_world_rig(0.0)[:3, :3].T + sc.T_world_rig(0.0)[:3, 3]
    origin = T_world_thermal[:3, 3]
    ray = world - origin
    length = np.linalg.norm(ray, axis=1)
    first = np.min([s.intersect(origin, ray / length[:, None]) for s in scene.solids], axis=0)
    hidden = first < length - 0.05
    T_thermal_world = np.linalg.inv(T_world_thermal)
    px = rig["thermal_left"].intrinsics.project(
        world @ T_thermal_world[:3, :3].T + T_thermal_world[:3, 3]
    )
    w, h = rig["thermal_left"].image_size
    with np.errstate(invalid="ignore"):
        in_view = (px[:, 0] > 1) & (px[:, 0] < w - 2) & (px[:, 1] > 1) & (px[:, 1] < h - 2)
    assert hidden.sum() > 200  # the pole and the people hide part of the room
    assert (seen & hidden).sum() <= 0.01 * seen.sum()
    assert seen[~hidden & in_view].mean() > 0.9
    t = sampler.sample(points, fs.frames["thermal_left"].image)
    _dist, index, nearest = scene.nearest_surface(world)
    truth = scene.apparent_temperature_k(index, nearest)
    flat = seen & ~hidden
    err = t[flat] - truth[flat]
    # NETD 0.08 K, and the blur (0.7 px) and bilinear sampling at edges of hot objects
    assert abs(np.median(err)) < 0.05
    assert np.median(np.abs(err)) < 0.15


VOXEL = 0.037


@pytest.fixture(scope="module")
def survey_map():
    """The survey every 1.5 s (25 TOF frames) with the truth's poses and an exact-range
    TOF, thermal imagers as delivered (±0.75 K offsets: both eyes average them out)."""
    sc = SurveyScenario(seed=3, live=True, model=exact_head())
    # 37 mm: no multiple of it meets the room's walls (at 3.5 m, 1.1 m...), so voxel
    # centres do not sit on them by chance.
    builder = MapBuilder(sc.rig, MapSettings(voxel_m=VOXEL), estimate_pose=False)
    for t in np.arange(0.0, SURVEY_S, 1.5):
        fs, _ = sc.render(float(t), THERMAL_ONLY)
        images = {k: fs.frames[k].image for k in THERMAL_ONLY[1:]}
        builder.add(float(t), fs.frames["tof"].distance_m, images, sc.T_world_rig(float(t)))
    return sc, builder


def test_the_survey_map_lies_on_the_true_surfaces(survey_map) -> None:
    sc, builder = survey_map
    m = builder.map
    occ = m.occupied()
    assert occ.sum() > 50_000 and builder.pose_source == "given"
    dist, index, _nearest = sc.scene.nearest_surface(m["centre"][occ])
    # A voxel's centre is within half its diagonal (32 mm) of a surface through it; a
    # plane through voxels at random offsets gives a median of about a quarter of the edge.
    assert np.median(dist) < 0.35 * VOXEL
    assert np.percentile(dist, 95) < VOXEL * np.sqrt(3) / 2 + 0.005
    names = {sc.scene.solids[k].name for k in np.unique(index)}
    assert {"person_body", "hot_pipe", "rack", "window", "fridge", "wall_back"} <= names


def test_the_survey_map_knows_each_surface_temperature(survey_map) -> None:
    sc, builder = survey_map
    m = builder.map
    occ = m.occupied() & np.isfinite(m["temp_mean"])
    _dist, index, nearest = sc.scene.nearest_surface(m["centre"][occ])
    truth = sc.scene.apparent_temperature_k(index, nearest)
    err = m["temp_mean"][occ] - truth
    assert np.isfinite(m["temp_mean"][m.occupied()]).mean() > 0.8
    assert abs(np.median(err)) < 0.1
    assert np.median(np.abs(err)) < 0.1  # NETD 0.08 K, averaged over points and frames
    pipe = np.array([sc.scene.solids[k].name == "hot_pipe" for k in index])
    assert np.nanmax(m["temp_max"][occ][pipe]) > 345.0  # 85 C, emissivity 0.9: 353 K


def test_the_pose_from_the_tof_clouds_follows_the_first_pan() -> None:
    """KISS-ICP on the first 3 s of the survey at the TOF's 15 Hz (the head pans 60
    degrees): the rotation within 1.5 degrees; the world is the rig frame at the start."""
    sc = SurveyScenario(seed=4, live=True, model=exact_head())
    grid = TofGrid(sc.rig, "tof")
    odo = TofOdometry(sc.rig["tof"].T_rig_sensor)
    worst = 0.0
    for t in np.arange(0.0, 3.0, 1 / 15):
        fs, _ = sc.render(float(t), ["tof"])
        T = odo.update(grid.points(fs.frames["tof"].distance_m, 0.05))
        true = survey_pose(float(t)) @ sc.rig["tof"].T_rig_sensor
        worst = max(worst, rotation_angle_deg(T[:3, :3].T @ true[:3, :3]))
    assert rotation_angle_deg(survey_pose(3.0)[:3, :3]) == pytest.approx(60.0, abs=0.01)
    assert worst < 1.5
    with pytest.raises(ValueError, match="too few"):
        odo.update(np.zeros((10, 3)))
