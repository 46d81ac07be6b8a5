"""Feeds a :class:`~fusion.voxel_map.VoxelMap` from the head's frames: one call per TOF
frame with the latest images of the other sensors and, where the source has it, the head's
pose (the simulator's truth, a recording's ``world -> rig`` transform); without a pose,
the pose comes from the TOF clouds (:class:`~fusion.odometry.TofOdometry`).

The TOF frame goes the fusion's way (:class:`fusion.stereo.StereoFusion`): the rig's range
correction, then points without flying pixels (:meth:`fusion.mapping.TofGrid.points`);
each point takes its temperature and colour from the sensors that see it
(:class:`fusion.point_attributes.PointAttributes`).

Frames: ``T_world_rig`` (4, 4) the rig's pose in the world frame; the map's world frame is
that of the poses given, or the rig frame at the first TOF frame when estimated.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from trifuse.calib.rig import Rig
from trifuse.fusion.geometry import tof_sensor_name
from trifuse.fusion.mapping import MappingOptions, TofGrid
from trifuse.fusion.odometry import TofOdometry
from trifuse.fusion.point_attributes import PointAttributes
from trifuse.fusion.voxel_map import DepthImage, IntegrateStats, MapSettings, VoxelMap


class MapBuilder:
    """A rig's frames into a voxel map (see the module docstring).

    Args:
        rig: the rig (intrinsics, poses, the TOF's range correction).
        settings: the map's settings.
        estimate_pose: estimate the pose from the TOF clouds when :meth:`add` gets none
            (False: such frames are skipped and counted in :attr:`skipped_no_pose`).
        edge_rel: flying-pixel threshold (:func:`fusion.mapping.mixed_pixels`).

    Attributes:
        map: the map.
        paused: while True, :meth:`add` does nothing (the console's Pause).
        pose_source: ``"given"``, ``"estimated"`` or None (nothing added yet): where the
            last pose came from.
    """

    def __init__(
        self,
        rig: Rig,
        settings: MapSettings | None = None,
        *,
        estimate_pose: bool = True,
        edge_rel: float = MappingOptions.edge_rel,
    ) -> None:
        self.rig = rig
        self.tof = tof_sensor_name(rig)
        self.grid = TofGrid(rig, self.tof)
        self.attributes = PointAttributes(rig, self.tof)
        self.map = VoxelMap(settings or MapSettings())
        self.estimate_pose = estimate_pose
        self.edge_rel = edge_rel
        self.paused = False
        self.pose_source: str | None = None
        self.skipped_no_pose = 0
        self._odometry: TofOdometry | None = None

    @property
    def T_rig_tof(self) -> np.ndarray:
        return self.rig[self.tof].T_rig_sensor

    def reset(self) -> None:
        """An empty map; the pose estimate starts again."""
        self.map.reset()
        self._odometry = None
        self.pose_source = None
        self.skipped_no_pose = 0

    def add(
        self,
        stamp_s: float,
        distance_m: np.ndarray,
        images: Mapping[str, np.ndarray],
        T_world_rig: np.ndarray | None = None,
        amplitude: np.ndarray | None = None,
    ) -> IntegrateStats | None:
        """Add one TOF frame.

        Args:
            stamp_s: its time, seconds.
            distance_m: (H, W) the TOF's radial distances, metres, NaN invalid.
            images: sensor -> the latest image of each other sensor: thermal (H, W) in
                kelvin, colour (H, W, 3) uint8 RGB; missing sensors are skipped.
            T_world_rig: (4, 4) the rig's pose, or None (estimated, or skipped).
            amplitude: (H, W) the TOF's amplitude, for the range correction.

        Returns:
            What the frame did, or None when paused or skipped for want of a pose.
        """
        if self.paused:
            return None
        d = np.asarray(distance_m, dtype=np.float32)
        correction = self.rig[self.tof].range_correction
        if correction is not None:
            d = correction.apply(d, amplitude)
        points = self.grid.points(d, self.edge_rel)
        if T_world_rig is not None:
            T_world_tof = np.asarray(T_world_rig, dtype=np.float64) @ self.T_rig_tof
            self.pose_source = "given"
        elif self.estimate_pose:
            if self._odometry is None:
                self._odometry = TofOdometry(self.T_rig_tof)
            T_world_tof = self._odometry.update(points)
            self.pose_source = "estimated"
        else:
            self.skipped_no_pose += 1
            return None
        temperature, colour = self.attributes.sample(points, images)
        depth = DepthImage(d, self.rig[self.tof].intrinsics)
        return self.map.integrate(T_world_tof, points, stamp_s, temperature, colour, depth)
