"""The head's pose from its TOF clouds alone, for a source that gives none: KISS-ICP
(point-to-point ICP against a local voxel map, with a constant-velocity prediction and an
adaptive correspondence threshold; PRBonn's ``kiss-icp`` package, C++ core).

Chosen by measurement (docs/FINDINGS.md, "Registration for the thermal map"; BENCHMARKS.md,
"Thermal 3D map"): on the simulated survey (543 degrees of pan and tilt, 3 m of driving,
every frame at 15 Hz) it keeps the rotation within about a degree with a range-calibrated
TOF (6 degrees at worst with the uncalibrated one), where OpenCV 5's frame-to-frame depth
odometry (``cv2.Odometry``) drifts by 14-24 degrees; Open3D 0.20 was not taken (a 105 MB
wheel that does not import without plotly and dash). The position is its weak side: it
wanders by up to about 1 m over the survey, already while the head only turns (a narrow
view of flat walls is not a LiDAR sweep). Where the robot reports its pose, that is used.

Frames: the world frame is the TOF frame of the first cloud, carried by ``T_world_tof0``
(e.g. the rig's ``T_rig_tof``, so that the world is the rig frame at the start).
"""

from __future__ import annotations

import numpy as np


class OdometryUnavailable(RuntimeError):
    """The registration library is not installed."""


class TofOdometry:
    """Incremental pose of the TOF from its point clouds.

    Args:
        T_world_tof0: (4, 4) the TOF's pose at the first cloud (default identity).
        voxel_m: KISS-ICP's map voxel (metres); clouds are thinned to half of it.
        max_range_m, min_range_m: the points used, metres from the TOF.
        max_points_per_voxel: KISS-ICP's local map density (5: three times faster than its
            default of 20 here, and as accurate).
    """

    def __init__(
        self,
        T_world_tof0: np.ndarray | None = None,
        voxel_m: float = 0.1,
        max_range_m: float = 10.0,
        min_range_m: float = 0.1,
        max_points_per_voxel: int = 5,
    ) -> None:
        try:
            from kiss_icp.config import KISSConfig
            from kiss_icp.kiss_icp import KissICP
        except ImportError as e:  # pragma: no cover - kiss-icp is a dependency
            raise OdometryUnavailable(
                "pose estimation needs the kiss-icp package (pip install kiss-icp)"
            ) from e
        config = KISSConfig()
        config.data.max_range = float(max_range_m)
        config.data.min_range = float(min_range_m)
        config.data.deskew = False  # a TOF frame is one exposure, not a sweep
        config.mapping.voxel_size = float(voxel_m)
        config.mapping.max_points_per_voxel = int(max_points_per_voxel)
        config.adaptive_threshold.initial_threshold = 0.5  # metres: a room, not a road
        config.adaptive_threshold.min_motion_th = 0.01
        config.registration.max_num_iterations = 100
        config.registration.max_num_threads = 1
        self._icp = KissICP(config)
        self.T_world_tof0 = np.eye(4) if T_world_tof0 is None else np.asarray(T_world_tof0, float)
        self.frames = 0

    def update(self, points_tof: np.ndarray) -> np.ndarray:
        """Register a cloud (N, 3) (TOF frame, metres, no NaN); returns ``T_world_tof``
        (4, 4) of this cloud."""
        pts = np.ascontiguousarray(points_tof, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) < 100:
            raise ValueError(f"odometry: {len(pts)} valid points, too few to register")
        self._icp.register_frame(pts, np.zeros(len(pts)))
        self.frames += 1
        return self.T_world_tof0 @ self._icp.last_pose
