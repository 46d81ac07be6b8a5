"""The head in rerun (issue 36, item 2): the rig as pinhole cameras at their poses, each
sensor's images, the TOF's points coloured by temperature and the fused pair, logged with the
``rerun-sdk`` (the optional ``[rerun]`` extra) to a file (``trifuse fuse --rerun OUT.rrd``) or
to a viewer (``trifuse serve --rerun [ADDRESS]``).

Entities (rerun paths); the rig frame is the TOF's, OpenCV's axes (x right, y down, z
forward: rerun's ``RDF``):

- ``rig``: its view coordinates, RDF (static).
- ``rig/<sensor>``: a ``Transform3D``, the sensor's pose ``T_rig_sensor`` (parent from
  child; static, logged again with a new rig).
- ``rig/<sensor>/image``: a ``Pinhole`` (K and the image size; static) and the sensor's
  images: a colour camera's RGB and a thermal imager's kelvin in the palette over the span
  of both imagers (as the fused picture colours them), JPEG; the TOF's amplitude, 8 bits
  over its 1st-99th percentile.
- ``rig/<tof>/cloud``: ``Points3D``, the TOF frame's points (metres, TOF frame, after the
  rig's range correction, flying pixels left out) coloured by the temperature the left
  eye's thermal imager sees there (grey where it sees none).
- ``fused``: the side-by-side stereo picture (JPEG).
- ``map`` (the console's thermal map, while it builds one): ``Points3D`` in the world frame
  as the 3D console shows it, ``map/path`` the head's path, and ``rig`` then placed at the
  head's pose (a ``Transform3D``): the root is the world.

Time: the timeline ``sensor_time``, each frame's own stamp (nanoseconds as the stamps are).

rerun's ``Pinhole`` has no lens distortion: an image of a sensor with distortion is
undistorted onto its own K before it is logged (a remap with maps made once per rig), so
that it lines up with the 3D view (the frustum, the cloud); the cloud is metric and needs
none. docs/FINDINGS.md "rerun" says what else rerun cannot show.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import ModuleType
from typing import Any

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.map_view import map_cloud
from trifuse.fusion.mapping import MappingOptions, TofGrid
from trifuse.fusion.palettes import PaletteName, palette_colors
from trifuse.fusion.span import auto_span
from trifuse.fusion.stereo import sample_image
from trifuse.fusion.voxel_map import VoxelMap

TIMELINE = "sensor_time"
"""The rerun timeline of the frames' stamps."""
JPEG_QUALITY = 85
"""JPEG quality of the images logged."""


def require_rerun() -> ModuleType:
    """The ``rerun`` module; RuntimeError in one line naming the extra when it is missing."""
    try:
        import rerun
    except ImportError:
        raise RuntimeError(
            "rerun: the rerun-sdk is not installed; install the extra: pip install -e '.[rerun]'"
        ) from None
    return rerun


class RerunHead:
    """Logs a rig and its frames to one rerun recording stream (see the module doc).

    Args:
        stream: a ``rerun.RecordingStream`` with its sink (a file, a viewer).
        rig: the rig (logged at once; :meth:`set_rig` for another).
        palette: the thermal images' and the cloud's palette.

    Not thread-safe: one thread logs.
    """

    def __init__(self, stream: Any, rig: Rig, palette: PaletteName = "iron") -> None:
        self.rr = require_rerun()
        self.stream, self.palette = stream, palette
        self.set_rig(rig)

    def set_rig(self, rig: Rig) -> None:
        """Log ``rig`` (static: its poses and pinholes) and make the undistortion maps."""
        rr, log = self.rr, self.stream.log
        self.rig = rig
        self.tof = next(n for n in rig.names if rig[n].modality == "tof")
        self.thermal = rig.eyes["left"].thermal if "left" in rig.eyes else None
        self.grid = TofGrid(rig, self.tof)
        self.edge_rel = MappingOptions().edge_rel
        self.maps: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
        log("rig", rr.ViewCoordinates.RDF, static=True)
        for name, s in rig.sensors.items():
            T = s.T_rig_sensor
            log(f"rig/{name}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            K = s.intrinsics.K
            log(
                f"rig/{name}/image",
                rr.Pinhole(image_from_camera=K, resolution=list(s.image_size),
                           camera_xyz=rr.ViewCoordinates.RDF),
                static=True,
            )  # fmt: skip
            dist = s.intrinsics.dist
            self.maps[name] = (
                cv2.initUndistortRectifyMap(K, dist, None, K, s.image_size, cv2.CV_16SC2)
                if np.any(dist)
                else None
            )

    def _undistorted(self, name: str, image: np.ndarray) -> np.ndarray:
        maps = self.maps.get(name)
        if maps is None:
            return image
        return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def _time(self, stamp_ns: int) -> None:
        self.stream.set_time(TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))

    def log_frames(
        self,
        frames: Mapping[str, Frame],
        radiometry: Mapping[str, Radiometry] | None = None,
    ) -> None:
        """Each frame's image at its own stamp, and the TOF frame's cloud: colour RGB,
        thermal kelvin (through ``radiometry``, default the rig's) in the palette over both
        imagers' span, the TOF's amplitude. Sensors the rig lacks are not logged."""
        rr, log, rig = self.rr, self.stream.log, self.rig
        kelvin: dict[str, np.ndarray] = {}
        for name, f in frames.items():
            if name in rig.sensors and rig[name].modality == "thermal":
                r = (radiometry or {}).get(name) or rig[name].radiometry or Radiometry()
                kelvin[name] = r.apply(np.asarray(f.image))
        span = auto_span(list(kelvin.values()), default=(273.15, 313.15)) if kelvin else None
        for name, f in frames.items():
            if name not in rig.sensors:
                continue
            self._time(f.stamp_ns)
            modality = rig[name].modality
            if modality == "color":
                rgb = self._undistorted(name, np.asarray(f.image))
                log(f"rig/{name}/image", rr.Image(rgb).compress(jpeg_quality=JPEG_QUALITY))
            elif modality == "thermal":
                assert span is not None
                rgb = palette_colors(self._undistorted(name, kelvin[name]), span, self.palette)
                log(f"rig/{name}/image", rr.Image(rgb).compress(jpeg_quality=JPEG_QUALITY))
            else:
                log(f"rig/{name}/image", rr.Image(self._amplitude(name, f)))
                if f.distance_m is not None:
                    thermal = kelvin.get(self.thermal) if self.thermal else None
                    points, colours = self.cloud(f, thermal, span)
                    log(f"rig/{name}/cloud", rr.Points3D(points, colors=colours))

    def _amplitude(self, name: str, f: Frame) -> np.ndarray:
        """The TOF's amplitude image, undistorted, 8 bits over its 1st-99th percentile."""
        a = self._undistorted(name, np.asarray(f.image, dtype=np.float32))
        finite = a[np.isfinite(a)]
        if finite.size == 0:
            return np.zeros(a.shape, np.uint8)
        lo, hi = np.percentile(finite, (1.0, 99.0))
        scaled = (np.nan_to_num(a, nan=lo) - lo) * (255.0 / max(hi - lo, 1e-6))
        return np.clip(scaled, 0, 255).astype(np.uint8)

    def cloud(
        self,
        tof: Frame,
        kelvin: np.ndarray | None,
        span: tuple[float, float] | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The TOF frame's points (N, 3) float32 (TOF frame, metres; the rig's range
        correction applied, flying pixels left out) and their colours (N, 3) uint8 RGB: the
        temperature ``kelvin`` (the left thermal imager's image) shows there in the palette
        over ``span``; grey without one."""
        s = self.rig[self.tof]
        d = np.asarray(tof.distance_m, dtype=np.float32)
        if s.range_correction is not None:
            d = s.range_correction.apply(d, np.asarray(tof.image, dtype=np.float32))
        points = self.grid.points(d, self.edge_rel)
        if kelvin is None or span is None or self.thermal is None:
            return points, np.full(points.shape, 128, np.uint8)
        t = sample_image(self.rig, self.thermal, self.tof, points, kelvin, np.nan)
        return points, palette_colors(t, span, self.palette)

    def log_map(
        self, stamp_ns: int, voxel_map: VoxelMap, T_world_rig: np.ndarray, max_points: int
    ) -> int:
        """The thermal map (world frame): its points as the 3D console shows them (at most
        ``max_points``), the head's path, and the rig placed at ``T_world_rig`` (the root
        then is the world); returns the points logged. The caller holds the map still."""
        rr, log = self.rr, self.stream.log
        cloud = map_cloud(voxel_map, max_points=max_points)
        path = np.array([T[:3, 3] for _, T in voxel_map.path], dtype=np.float32)
        self._time(stamp_ns)
        T = np.asarray(T_world_rig, dtype=np.float64)
        log("rig", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        log("map", rr.Points3D(cloud.points, colors=cloud.colors, radii=cloud.cell_m / 2))
        if len(path) > 1:
            log("map/path", rr.LineStrips3D([path]))
        return len(cloud.points)

    def log_fused(self, stamp_ns: int, picture: np.ndarray | bytes) -> None:
        """The fused side-by-side picture: (H, 2W, 3) uint8 RGB, or its JPEG bytes."""
        rr = self.rr
        self._time(stamp_ns)
        if isinstance(picture, bytes | bytearray):
            image = rr.EncodedImage(contents=bytes(picture), media_type="image/jpeg")
        else:
            image = rr.Image(picture).compress(jpeg_quality=JPEG_QUALITY)
        self.stream.log("fused", image)
