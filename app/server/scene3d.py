"""The Viser 3D scene: the rig's frames, every sensor's frustum at its pose, and the TOF
point cloud, updated from the fusion pipeline a few times a second."""

from __future__ import annotations

import numpy as np
import viser

from app.server.periodic import Periodic
from app.server.pipeline import FusionPipeline
from calib.rig import Rig
from calib.transforms import rvec_from_rotation

FRUSTUM_COLORS = {"color": (40, 120, 240), "thermal": (240, 90, 30), "tof": (40, 200, 90)}


def _wxyz(R: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation matrix."""
    r = rvec_from_rotation(R)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return (1.0, 0.0, 0.0, 0.0)
    axis = r / angle
    s = np.sin(angle / 2)
    return (float(np.cos(angle / 2)), *(float(a * s) for a in axis))


def add_rig(server: viser.ViserServer, rig: Rig, name: str = "/rig") -> None:
    """Each sensor's frame and frustum at ``T_rig_sensor`` (vertical FOV, aspect W/H).

    The scene uses the rig's frames (OpenCV: +y down, +z forward), so "up" is -y; every
    viewer starts behind and above the head, looking forward.
    """
    server.scene.set_up_direction("-y")

    @server.on_client_connect
    def _start_view(client: viser.ClientHandle) -> None:
        client.camera.up_direction = (0.0, -1.0, 0.0)
        client.camera.position = (0.0, -0.6, -1.5)
        client.camera.look_at = (0.0, 0.0, 2.5)

    server.scene.add_frame(name, axes_length=0.05, axes_radius=0.002)
    for s in rig.sensors.values():
        T = s.T_rig_sensor
        node = f"{name}/{s.name}"
        server.scene.add_frame(
            node,
            wxyz=_wxyz(T[:3, :3]),
            position=tuple(T[:3, 3]),
            axes_length=0.03,
            axes_radius=0.0015,
        )
        fov = 2 * np.arctan2(s.height / 2.0, s.intrinsics.fy)
        server.scene.add_camera_frustum(
            f"{node}/frustum",
            fov=float(fov),
            aspect=s.width / s.height,
            scale=0.08,
            color=FRUSTUM_COLORS[s.modality],
        )
        server.scene.add_label(f"{node}/label", s.name)


class SceneUpdater(Periodic):
    """Pushes the pipeline's TOF point cloud (coloured by the colour camera) to Viser."""

    def __init__(
        self, server: viser.ViserServer, pipeline: FusionPipeline, rate_hz: float = 5.0
    ) -> None:
        super().__init__("scene3d", 1.0 / rate_hz)
        self.server, self.pipeline = server, pipeline

    def tick(self) -> None:
        fusion = self.pipeline.fusion
        fs = self.pipeline.latest_set
        if fs is None or not fusion.ready:
            return
        eyes = self.pipeline.rig.eyes
        if not all(eyes[e].color in fs.frames for e in ("left", "right")):
            return
        colors = {e: fs.frames[eyes[e].color].image for e in ("left", "right")}
        try:
            points, rgb = fusion.point_cloud(colors, {}, "color")
        except (KeyError, ValueError, RuntimeError):
            return
        with self.server.atomic():
            self.server.scene.add_point_cloud(
                "/rig/tof_points",
                points=points,
                colors=rgb,
                point_size=0.01,
                precision="float32",
            )
