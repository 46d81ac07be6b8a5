"""The sensors in the console's 3D scene: each sensor's frame and frustum at its pose in
the rig frame (OpenCV axes, metres), and its live image on the image panel below the head
(:mod:`app.server.panels.scene_layout` places the panel), downscaled to at most
:data:`TEXTURE_MAX_W` pixels wide (the 3D scene's low-bandwidth profile asks for less, and
a lower JPEG quality): colour as is, thermal in the pipeline's palette over its span, TOF
amplitude stretched grey."""

from __future__ import annotations

import cv2
import numpy as np
import viser

from trifuse.app.server.panels import scene_layout as layout
from trifuse.app.server.panels.display import draw_outline
from trifuse.app.sources.frames import Frame
from trifuse.app.storage.preview import to_display
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Sensor
from trifuse.calib.transforms import quaternion_from_rotation
from trifuse.fusion.palettes import apply_palette

FRUSTUM_COLORS = {"color": (40, 120, 240), "thermal": (240, 90, 30), "tof": (40, 200, 90)}
FRUSTUM_LINE_PX = 2.0
"""Frustum and image-frame lines are this many screen pixels thick at any distance."""
TEXTURE_MAX_W = 320
"""Live images are downscaled to at most this width (pixels) before JPEG encoding."""
TEXTURE_JPEG_QUALITY = 75


def wxyz_of(T: np.ndarray) -> np.ndarray:
    """Quaternion (4,) ``(w, x, y, z)``, ``w >= 0`` (viser's order), of the rotation of a
    (4, 4) or (3, 3) transform."""
    x, y, z, w = quaternion_from_rotation(np.asarray(T, dtype=np.float64)[:3, :3])
    return np.array([w, x, y, z])


def vertical_fov_rad(sensor: Sensor) -> float:
    """The sensor's vertical field of view in radians (pinhole, from ``fy`` and height)."""
    return float(2.0 * np.arctan2(sensor.height / 2.0, sensor.intrinsics.fy))


def _downscale(image: np.ndarray, max_width: int) -> np.ndarray:
    h, w = image.shape[:2]
    if w <= max_width:
        return image
    size = (max_width, max(1, round(h * max_width / w)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _grey_stretch(image: np.ndarray) -> np.ndarray:
    """(H, W) numbers -> (H, W, 3) uint8 grey, 1st..99th percentile stretched, NaN black."""
    a = image.astype(np.float32, copy=False)
    finite = np.isfinite(a)
    if not finite.any():
        return np.zeros((*a.shape, 3), np.uint8)
    lo, hi = (float(v) for v in np.percentile(a[finite], [1, 99]))
    scale = 255.0 / max(hi - lo, 1e-6)
    grey = np.clip((np.nan_to_num(a, nan=lo) - lo) * scale, 0, 255).astype(np.uint8)
    grey[~finite] = 0
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB)


def sensor_texture(
    image: np.ndarray,
    modality: str,
    max_width: int = TEXTURE_MAX_W,
    span_k: tuple[float, float] | None = None,
    palette: str = "iron",
) -> np.ndarray:
    """A sensor image as a frustum texture: (h, w, 3) uint8 RGB with ``w <= max_width``.

    Args:
        image: colour (H, W, 3) uint8 RGB; thermal (H, W) float kelvin; TOF amplitude
            (H, W) float (any unit).
        modality: ``color``, ``thermal`` or ``tof`` (the logarithm of the amplitude is
            stretched grey, 1st to 99th percentile).
        span_k: thermal only: (low, high) kelvin of ``palette``; None: :func:`to_display`'s
            own percentile stretch.
    Raises:
        ValueError: an image whose shape does not fit its modality.
    """
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 3 and modality == "color":
        return np.ascontiguousarray(_downscale(a, max_width).astype(np.uint8, copy=False))
    if a.ndim != 2:
        raise ValueError(f"{modality} image: expected (H, W), got shape {a.shape}")
    small = _downscale(a.astype(np.float32, copy=False), max_width)
    if modality == "thermal":
        if span_k is not None:
            return apply_palette(small, span_k, palette, nan_color=(0, 0, 0))
        return np.ascontiguousarray(to_display(small))
    # TOF amplitude falls off with the square of the distance (and spans four decades):
    # its logarithm shows the far walls as well as the near objects
    return _grey_stretch(np.log1p(np.maximum(small, 0.0)))


def frustum_scale(depth_m: float, fov_rad: float, aspect: float) -> float:
    """Viser's ``scale`` of a camera frustum whose image plane lies ``depth_m`` metres in
    front of its apex (Viser 1.1.1 normalises the frustum to unit volume before scaling:
    its depth is ``scale / cbrt(tan(fov / 2)^2 * aspect / 3)``)."""
    t = float(np.tan(fov_rad / 2.0))
    return float(depth_m * np.cbrt(t * t * aspect / 3.0))


_PLACEHOLDER = np.zeros((2, 2, 3), np.uint8)


class SensorNodes:
    """One sensor's scene nodes: its frame (pose) with the frustum (wireframe), and on the
    image panel below the head its live image (JPEG of ``jpeg_quality``), a frame in the
    frustum's colour and its name under the image."""

    def __init__(
        self,
        server: viser.ViserServer,
        root: str,
        sensor: Sensor,
        jpeg_quality: int = TEXTURE_JPEG_QUALITY,
    ) -> None:
        self.server = server
        node = f"{root}/{sensor.name}"
        color = FRUSTUM_COLORS.get(sensor.modality, (200, 200, 200))
        self.frame = server.scene.add_frame(node, axes_length=0.015, axes_radius=0.0008)
        self.frustum = server.scene.add_camera_frustum(
            f"{node}/frustum",
            fov=vertical_fov_rad(sensor),
            aspect=sensor.width / sensor.height,
            scale=0.01,
            thickness=FRUSTUM_LINE_PX,
            thickness_units="screen",
            color=color,
        )
        panel = f"/panel/{sensor.name}"  # under the panel's frame (its pose: Scene3D)
        self.cell_node = server.scene.add_frame(panel, show_axes=False)
        self.jpeg_quality = jpeg_quality
        self.picture = self._add_picture(f"{panel}/image", 0.01, 0.01)
        self.outline = server.scene.add_line_segments(
            f"{panel}/outline",
            np.zeros((4, 2, 3)),
            color,
            thickness=FRUSTUM_LINE_PX,
            thickness_units="screen",
        )
        self.label = server.scene.add_label(f"{panel}/label", sensor.name, anchor="top-center")
        self.modality = sensor.modality
        self.depth_m = 0.0
        self.cell: layout.Cell | None = None
        self.shown_frame: object = None  # the Frame whose image the picture shows
        self.shown_outline: np.ndarray | None = None  # the next view's outline drawn on it
        self.shown_radiometry: Radiometry | None = None  # the thermal image read through it

    def _add_picture(self, name: str, width_m: float, height_m: float) -> viser.ImageHandle:
        """The (hidden) live image node ``name``, ``width_m`` x ``height_m`` metres, encoded
        at :attr:`jpeg_quality` (an existing node of that name is replaced)."""
        return self.server.scene.add_image(
            name,
            _PLACEHOLDER,
            render_width=width_m,
            render_height=height_m,
            format="jpeg",
            jpeg_quality=self.jpeg_quality,
            visible=False,
        )

    def set_jpeg_quality(self, quality: int) -> None:
        """Encode the live image at JPEG ``quality`` (0-100) from now on: the image node is
        made again (Viser fixes a node's quality when it is made), hidden until the next
        :meth:`show_frame`."""
        if quality == self.jpeg_quality:
            return
        self.jpeg_quality = quality
        old = self.picture
        self.picture = self._add_picture(old.name, old.render_width, old.render_height)
        self.shown_frame = None

    def set_depth(self, depth_m: float) -> None:
        """Frustum depth ``depth_m`` metres (apex to image plane)."""
        self.depth_m = depth_m
        self.frustum.scale = frustum_scale(depth_m, self.frustum.fov, self.frustum.aspect)

    def set_cell(self, cell: layout.Cell) -> None:
        """Put the live image, its frame and its name at ``cell`` of the image panel."""
        self.cell = cell
        centre = np.asarray(cell.center, dtype=np.float64)
        self.cell_node.position = centre
        self.picture.render_width = cell.width
        self.picture.render_height = cell.height
        self.outline.points = cell.outline().astype(np.float32)
        self.label.position = layout.label_anchor(cell) - centre

    def place(self, sensor: Sensor) -> None:
        """Move to ``sensor.T_rig_sensor`` and take its FOV, aspect and modality."""
        T = sensor.T_rig_sensor
        self.frame.wxyz = wxyz_of(T)
        self.frame.position = np.asarray(T[:3, 3], dtype=np.float64)
        self.frustum.fov = vertical_fov_rad(sensor)
        self.frustum.aspect = sensor.width / sensor.height
        color = FRUSTUM_COLORS.get(sensor.modality, (200, 200, 200))
        self.frustum.color = color
        self.outline.colors = np.tile(np.asarray(color, np.uint8), (4, 2, 1))
        self.modality = sensor.modality
        self.set_depth(self.depth_m)
        self.frame.visible = self.cell_node.visible = True

    def show_image(self, image: np.ndarray | None) -> None:
        """The live image (h, w, 3) uint8 on the panel, or none (the frame stays)."""
        if image is None:
            self.picture.visible = False
        else:
            self.picture.image = image
            self.picture.visible = True

    def show_frame(
        self,
        frame: Frame | None,
        span_k: tuple[float, float] | None,
        palette: str,
        max_width: int = TEXTURE_MAX_W,
        outline: np.ndarray | None = None,
        radiometry: Radiometry | None = None,
    ) -> str | None:
        """The picture shows ``frame``'s image (None: no picture) at most ``max_width``
        pixels wide, made again only for a new frame, outline or radiometry (or after
        :meth:`set_jpeg_quality`, or with ``shown_frame`` set to None); returns why it
        cannot be shown (the picture is then hidden), else None. ``span_k``, ``palette``: a
        thermal image's colours (:func:`sensor_texture`), kelvin; ``radiometry``: the
        imager's raw values -> kelvin, as the fused picture reads them (None: the raw
        values are kelvin). ``outline``: (4, 2) full-image pixels of the next view's board,
        drawn cyan (:func:`~app.server.panels.display.draw_outline`)."""
        if frame is None:
            if self.shown_frame is not None:
                self.show_image(None)
                self.shown_frame = None
            return None
        if (
            frame is self.shown_frame
            and outline is self.shown_outline
            and radiometry == self.shown_radiometry
        ):
            return None
        image = frame.image
        if radiometry is not None and self.modality == "thermal":
            image = radiometry.apply(np.asarray(image, dtype=np.float32))
        try:
            tex = sensor_texture(image, self.modality, max_width, span_k, palette)
        except (ValueError, cv2.error) as exc:
            self.show_image(None)
            self.shown_frame = None
            return str(exc)
        if outline is not None:
            tex = tex.copy()  # the texture may be the frame's own image
            draw_outline(tex, outline, (frame.image.shape[1], frame.image.shape[0]))
        self.show_image(tex)
        self.shown_frame, self.shown_outline = frame, outline
        self.shown_radiometry = radiometry
        return None

    def hide(self) -> None:
        self.frame.visible = self.cell_node.visible = False
