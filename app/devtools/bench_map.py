"""Benchmark of the thermal 3D map (issue 20): ``trifuse bench --only map``.

On the simulated survey of the inspection room (:mod:`app.sources.sim.survey`): what a TOF
frame costs the map, how close the map's voxels lie to the scene's true surfaces and how
close their temperatures are to what an ideal imager reads there, how far the pose
estimated from the TOF clouds drifts, and what the console's level of detail costs at a
million voxels.
"""

from __future__ import annotations

from trifuse.app.devtools.benchmark import benchmark, median_ms

MAP_VOXEL_M = 0.03
ACCURACY_HZ = 3.0
"""TOF frames per second of the survey mapped for the accuracy figures (the map converges
long before the TOF's 15)."""
ODOMETRY_HZ = 15.0
"""The TOF's rate: the pose estimate sees every frame, as it would live."""
SURVEY_TURN_ONLY_S = 22.0
"""The survey's head only turns (about the TOF) until then: a position error there is
all the estimate's."""


def _exact_range_model():
    from trifuse.app.sources.sim.render import HeadModel
    from trifuse.app.sources.sim.tof_error import RangeErrorModel

    return HeadModel(
        range_error=RangeErrorModel(
            bias_m=0.0, wiggle=(), radial_m=0.0, border_m=0.0, pixel_sigma_m=0.0, amplitude_m=0.0
        )
    )


WORLD_SHIFT_M = (0.0113, -0.0067, 0.0191)
"""The map's world frame is the room's shifted by this (metres): the room's walls lie at
round coordinates that a voxel grid from the room's origin would meet at voxel centres by
chance; shifted, they meet the grid anywhere, as a real room does."""


def _survey_map(prefix: str, model) -> dict[str, float]:
    """The survey mapped at :data:`ACCURACY_HZ` with the truth's poses (``model``: the
    head's sensor physics, None: the default): the accuracy figures with ``prefix``, and
    for ``exact`` the costs per frame."""
    import time

    import numpy as np

    from trifuse.app.sources.sim.survey import SURVEY_S, SurveyScenario
    from trifuse.calib.transforms import make_T
    from trifuse.fusion.map_builder import MapBuilder
    from trifuse.fusion.stereo import StereoFusion
    from trifuse.fusion.voxel_map import DepthImage, MapSettings

    sensors = ["tof", "thermal_left", "thermal_right", "ccd_left"]
    timed = prefix == "exact"
    sc = SurveyScenario(seed=5, live=True, model=model)
    rig = sc.rig
    shift = make_T(np.eye(3), WORLD_SHIFT_M)
    builder = MapBuilder(rig, MapSettings(voxel_m=MAP_VOXEL_M), estimate_pose=False)
    fusion = StereoFusion(rig)
    cost: dict[str, list[float]] = {"attributes": [], "frame": [], "fusion": []}
    times = np.arange(0.0, SURVEY_S, 1.0 / ACCURACY_HZ)
    for t in times:
        fs, _ = sc.render(float(t), sensors if timed else sensors[:3])
        tof = fs.frames["tof"]
        images = {k: fs.frames[k].image for k in fs.frames if k != "tof"}
        pose = shift @ sc.T_world_rig(float(t))
        t0 = time.perf_counter()
        builder.add(float(t), tof.distance_m, images, pose, tof.image)
        cost["frame"].append(time.perf_counter() - t0)
        if timed:
            t0 = time.perf_counter()
            fusion.update_depth(tof.distance_m, tof.image)
            cost["fusion"].append(time.perf_counter() - t0)
            pts = builder.grid.points(tof.distance_m, builder.edge_rel)
            t0 = time.perf_counter()
            builder.attributes.sample(pts, images)
            cost["attributes"].append(time.perf_counter() - t0)
    m = builder.map
    occ = m.occupied()
    centres = m["centre"][occ].astype(np.float64) - np.asarray(WORLD_SHIFT_M)
    dist, index, nearest = sc.scene.nearest_surface(centres)
    err = m["temp_mean"][occ] - sc.scene.apparent_temperature_k(index, nearest)
    seen = np.isfinite(err)
    figures = {
        f"{prefix}_occupied": float(occ.sum()),
        f"{prefix}_distance_median_mm": float(np.median(dist) * 1e3),
        f"{prefix}_distance_p95_mm": float(np.percentile(dist, 95) * 1e3),
        f"{prefix}_temp_seen_share": float(seen.mean()),
        f"{prefix}_temp_error_median_k": float(np.median(err[seen])),
        f"{prefix}_temp_abs_error_median_k": float(np.median(np.abs(err[seen]))),
        f"{prefix}_temp_abs_error_p95_k": float(np.percentile(np.abs(err[seen]), 95)),
    }
    if timed:
        # the map's own update: the last frame's points integrated again (no new voxels)
        T = shift @ sc.T_world_rig(float(times[-1])) @ rig["tof"].T_rig_sensor
        temps, rgb = builder.attributes.sample(pts, images)
        depth = DepthImage(tof.distance_m, rig["tof"].intrinsics)
        figures.update(
            points_per_frame=float(m.stats.points / len(times)),
            frame_ms=float(np.median(cost["frame"]) * 1e3),
            attributes_ms=float(np.median(cost["attributes"]) * 1e3),
            fusion_tof_update_ms=float(np.median(cost["fusion"]) * 1e3),
            integrate_ms=median_ms(lambda i: m.integrate(T, pts, 100.0 + i, temps, rgb, depth), 30),
            map_voxels=float(len(m)),
            map_memory_mb=float(m.nbytes / 1e6),
        )
    return figures


def _odometry(prefix: str, model) -> dict[str, float]:
    """KISS-ICP (:class:`fusion.odometry.TofOdometry`) on every TOF frame of the survey
    against the truth's poses; ``model``: the head's sensor physics (None: default)."""
    import time

    import numpy as np

    from trifuse.app.sources.sim.survey import SURVEY_S, SurveyScenario, survey_pose
    from trifuse.calib.transforms import rotation_angle_deg
    from trifuse.fusion.mapping import TofGrid
    from trifuse.fusion.odometry import TofOdometry

    sc = SurveyScenario(seed=6, live=True, model=model)
    grid = TofGrid(sc.rig, "tof")
    odo = TofOdometry(sc.rig["tof"].T_rig_sensor)
    prev = None
    path_m = turn_deg = 0.0
    pos_err, rot_err, cost = [], [], []
    for t in np.arange(0.0, SURVEY_S, 1.0 / ODOMETRY_HZ):
        fs, _ = sc.render(float(t), ["tof"])
        pts = grid.points(fs.frames["tof"].distance_m, 0.05)
        t0 = time.perf_counter()
        T = odo.update(pts)
        cost.append(time.perf_counter() - t0)
        true = survey_pose(float(t)) @ sc.rig["tof"].T_rig_sensor
        if prev is not None:
            path_m += float(np.linalg.norm(true[:3, 3] - prev[:3, 3]))
            turn_deg += rotation_angle_deg(prev[:3, :3].T @ true[:3, :3])
        prev = true
        pos_err.append(float(np.linalg.norm(T[:3, 3] - true[:3, 3])))
        rot_err.append(rotation_angle_deg(T[:3, :3].T @ true[:3, :3]))
    turning = round(SURVEY_TURN_ONLY_S * ODOMETRY_HZ) - 1
    return {
        f"{prefix}_path_m": path_m,
        f"{prefix}_turn_deg": turn_deg,
        f"{prefix}_position_error_after_turning_m": pos_err[turning],
        f"{prefix}_final_position_error_m": pos_err[-1],
        f"{prefix}_max_position_error_m": max(pos_err),
        f"{prefix}_final_rotation_error_deg": rot_err[-1],
        f"{prefix}_max_rotation_error_deg": max(rot_err),
        f"{prefix}_drift_per_m": max(pos_err) / path_m,
        f"{prefix}_drift_deg_per_deg": max(rot_err) / turn_deg,
        f"{prefix}_ms": float(np.median(cost) * 1e3),
    }


@benchmark(
    "map",
    "thermal 3D map of the simulated survey: cost per TOF frame (map, attributes, all) "
    "vs the fusion's own TOF update, voxel distance to the true surfaces, temperature error, "
    "odometry drift (KISS-ICP), level of detail at 1 M voxels",
    baselines=(("frame_ms", "fusion_tof_update_ms"),),
    default_repeat=1,
)
def thermal_map(repeat: int) -> dict[str, float]:
    """Figures (``repeat`` is unused: each is a median over many frames):

    - ``integrate_ms``, ``attributes_ms``, ``frame_ms``: per TOF frame (25 k points) of the
      survey at :data:`ACCURACY_HZ`, median: the voxel map's update (hits, temperature,
      colour, free space), the points' temperature and colour from the two thermal imagers
      and the left colour camera with occlusion, and all of :meth:`MapBuilder.add`;
      ``fusion_tof_update_ms``: the stereo fusion's own work per TOF frame
      (``StereoFusion.update_depth``) on the same frames, the baseline;
    - ``exact_*``: the map (voxel :data:`MAP_VOXEL_M`, world frame shifted by
      :data:`WORLD_SHIFT_M`) of the whole survey with the truth's poses and a TOF without
      systematic range error (as after a perfect range calibration): occupied voxels, the
      distance of their centres to the nearest true surface (median, p95, mm), the share
      with a temperature, the error of their temperature against the ideal imager's
      reading at the nearest surface point (median, median and p95 of the absolute, K);
      ``raw_*``: the same with the TOF's range error
      left in (uncalibrated);
    - ``odo_*``: KISS-ICP on every TOF frame of the survey (15 Hz, exact-range TOF):
      path length (m) and turn (degrees) of the truth, the position error when the head
      has only turned (22 s), final and largest position error (m) and rotation error
      (degrees), drift per metre (the largest position error / the path: the error wanders,
      so the final one can be small by chance) and per degree (the largest rotation error
      / the turn), cost per frame (ms, median); ``odo_raw_*``: the same with
      the TOF's range error left in;
    - ``lod_*``: a map of 1 M occupied voxels (a synthetic 1 m-deep shell of a room at
      2 cm): the console's level of detail to 300 k points (ms, level, points).
    """
    import numpy as np

    from trifuse.fusion.map_view import map_cloud
    from trifuse.fusion.voxel_map import MapSettings, VoxelMap

    figures: dict[str, float] = {}
    figures.update(_survey_map("exact", _exact_range_model()))
    figures.update(_survey_map("raw", None))

    figures.update(_odometry("odo", _exact_range_model()))
    figures.update(_odometry("odo_raw", None))

    # Level of detail at a million voxels: the shell of a 24 x 3 x 24 m room at 2 cm.
    rng = np.random.default_rng(0)
    big = VoxelMap(MapSettings(voxel_m=0.02, max_voxels=2_000_000))
    n = 1_000_000
    pts = rng.uniform(-12.0, 12.0, size=(n, 3))
    wall = rng.integers(0, 3, n)
    pts[np.arange(n), wall] = np.where(rng.random(n) < 0.5, -12.0, 12.0) + rng.uniform(-0.5, 0.5, n)
    pts[:, 1] *= 0.125
    for chunk in np.array_split(pts, 10):
        big.integrate(np.eye(4), chunk, 0.0, rng.uniform(290, 320, len(chunk)))
        big.integrate(np.eye(4), chunk, 0.0)  # a second hit: occupied
    figures["lod_occupied"] = float(big.occupied().sum())
    cloud = None

    def lod(_i: int) -> None:
        nonlocal cloud
        cloud = map_cloud(big, "temperature", 300_000)

    figures["lod_ms"] = median_ms(lod, 3)
    assert cloud is not None
    figures["lod_points"] = float(len(cloud.points))
    figures["lod_level"] = float(cloud.level)
    return figures
