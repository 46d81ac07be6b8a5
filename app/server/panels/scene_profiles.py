"""What the console's 3D scene (:mod:`app.server.panels.scene3d`) sends in each bandwidth
mode (``full`` or ``low``, :data:`~app.server.runtime.context.BANDWIDTH_MODES`;
console-wide, ``ctx.bandwidth``, also ``/api/console/settings`` and ``trifuse serve
--console-bandwidth``).

Bandwidth (issue 18: the console beside the viewer's video over a 10 Mbit/s radio link):
in ``full`` the cloud carries every valid TOF point (about 23k, float32: 15 bytes each with
its colour) at up to ``rate_hz`` and the live images are 320 px wide at ``texture_hz``:
about 6 Mbit/s, nearly all of it the cloud. ``low`` sends every 2nd pixel of every 2nd row
of the TOF (at most :data:`LOW_CLOUD_MAX_POINTS` points, float16 positions: 9 bytes each)
at 2 Hz, drawn twice as large so that the surface stays closed, and the images 160 px wide
at JPEG quality 50 once a second: about 1 Mbit/s (``trifuse bench``'s console figures;
:mod:`app.devtools.console_bandwidth` measures it per kind). The Feeds follow the same
setting (:mod:`app.server.panels.display`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from trifuse.app.server.panels.scene_sensors import TEXTURE_JPEG_QUALITY, TEXTURE_MAX_W


@dataclass(frozen=True)
class SceneProfile:
    """What the 3D scene sends in one bandwidth mode.

    Attributes:
        cloud_hz: point cloud updates per second, at most (also bounded by the tick rate
            and the TOF's frame rate: an unchanged cloud is not sent again).
        cloud_max_points: decimate the cloud on the TOF grid to at most this many points
            (:func:`~app.server.panels.scene_cloud.grid_stride`); None: every point.
        cloud_precision: the positions on the wire: ``float32`` (4 bytes per coordinate,
            sub-millimetre) or ``float16`` (2 bytes; steps of 2-4 mm at 2-8 m).
        texture_hz: live image updates per second (each sends up to 5 JPEGs).
        texture_max_w: the live images' width at most, pixels.
        texture_jpeg_quality: their JPEG quality (0-100).
    """

    cloud_hz: float
    cloud_max_points: int | None
    cloud_precision: Literal["float16", "float32"]
    texture_hz: float
    texture_max_w: int
    texture_jpeg_quality: int


LOW_CLOUD_MAX_POINTS = 6400
"""The low-bandwidth cloud's points at most: the TOF's 176 x 144 pixels at a stride of 2
(6336 pixels)."""
LOW_PROFILE = SceneProfile(
    cloud_hz=2.0,
    cloud_max_points=LOW_CLOUD_MAX_POINTS,
    cloud_precision="float16",
    texture_hz=1.0,
    texture_max_w=TEXTURE_MAX_W // 2,
    texture_jpeg_quality=50,
)
"""``low``: at most 57 kB per cloud update (6336 points x 9 bytes; 53 kB measured on the
simulated room, whose 5.8k of them are valid) and about 10 kB per round of the five live
images, against 366 kB (23k points x 15 bytes) and 26 kB in ``full``."""


def scene_profiles(rate_hz: float = 4.0, texture_hz: float = 2.0) -> dict[str, SceneProfile]:
    """The profile of each mode of
    :data:`~app.server.runtime.context.BANDWIDTH_MODES`: ``full`` (every point, float32,
    at ``rate_hz``; 320 px images at ``texture_hz``) and :data:`LOW_PROFILE`."""
    full = SceneProfile(rate_hz, None, "float32", texture_hz, TEXTURE_MAX_W, TEXTURE_JPEG_QUALITY)
    return {"full": full, "low": LOW_PROFILE}


SCENE_PROFILES = scene_profiles()
"""The 3D scene's profiles at its default rates."""
