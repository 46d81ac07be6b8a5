"""Each browser's view of the console's 3D scene (:mod:`app.server.panels.scene3d`).

Viser gives every browser its own camera; the scene moves it to one of the views of
:mod:`app.server.panels.scene_layout` (:func:`apply_camera`) framed in that browser's canvas.
:class:`BrowserViews` keeps what that takes, per browser: the size of its canvas (the
largest its camera has reported, :func:`viewport_of`), its own copy of the image panel
turned to face its view, and whether it still waits for the first cloud to be framed; and,
for every browser, samples of the clouds of the last :data:`FRAME_MEMORY_S` seconds that the
views frame (a panning head sweeps its cloud round).
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

from trifuse.app.server.panels import scene_layout as layout
from trifuse.app.server.panels.scene_sensors import wxyz_of

FALLBACK_VIEWPORT = (1280, 800)
"""Canvas size (CSS px) assumed for a browser that has not reported its own."""
FRAME_MEMORY_S = 45.0
"""The views frame the clouds of this many seconds (a panning head sweeps its cloud)..."""
FRAME_SAMPLE_S = 2.0
"""... sampled this often."""


def apply_camera(camera: object, pose: layout.CameraPose) -> None:
    """Move a browser's camera (a :class:`viser.CameraHandle` or anything with its
    ``fov``, ``near``, ``up_direction``, ``position`` and ``look_at``) to ``pose``. The
    position goes before the look-at point: Viser moves the look-at point along with the
    position."""
    camera.fov = pose.fov_rad  # type: ignore[attr-defined]
    camera.near = pose.near_m  # type: ignore[attr-defined]
    camera.up_direction = pose.up  # type: ignore[attr-defined]
    camera.position = pose.position  # type: ignore[attr-defined]
    camera.look_at = pose.look_at  # type: ignore[attr-defined]


def viewport_of(
    camera: object, fallback: tuple[int, int] | None = FALLBACK_VIEWPORT
) -> tuple[int, int]:
    """(width, height) pixels of a browser's canvas as its camera reports them, or
    ``fallback`` ((0, 0) for None) before it has reported them."""
    missing = fallback or (0, 0)
    try:
        w, h = int(camera.image_width), int(camera.image_height)  # type: ignore[attr-defined]
    except (AssertionError, AttributeError, TypeError, ValueError):
        return missing
    return (w, h) if w > 0 and h > 0 else missing


class BrowserViews:
    """What the 3D scene keeps per browser (by Viser's ``client_id``) to give it its views.

    The canvas sizes have their own lock (a camera reports from Viser's thread at any
    time); the rest is used under the scene's lock.
    """

    def __init__(self) -> None:
        self._recent: deque[tuple[float, np.ndarray]] = deque()  # (time, (M, 3) sample)
        self._unframed: set[int] = set()  # clients framed before the first cloud
        self._canvas: dict[int, tuple[int, int]] = {}  # client -> canvas (px), largest seen
        self._shadows: dict[int, tuple[object, str]] = {}  # client -> (its /panel, view)
        self._canvas_lock = threading.Lock()

    # -- canvases ----------------------------------------------------------------------

    def note_canvas(self, client_id: int, camera: object) -> None:
        """Remember a browser's canvas size: the largest it has reported at its present
        aspect ratio. Viser reports the size of the drawing buffer, which its client
        shrinks (to 0.75 x) while drawing is slow; the largest is the canvas's own."""
        w, h = viewport_of(camera, None)
        if w <= 0:
            return
        with self._canvas_lock:
            old = self._canvas.get(client_id)
            if old is None or w > old[0] or abs(old[0] / old[1] - w / h) > 0.02 * w / h:
                self._canvas[client_id] = (w, h)

    def canvas_of(self, client: object) -> tuple[int, int]:
        """(width, height) of a browser's canvas (:meth:`note_canvas`), else what its
        camera reports now, else :data:`FALLBACK_VIEWPORT`."""
        with self._canvas_lock:
            known = self._canvas.get(getattr(client, "client_id", None))  # type: ignore[arg-type]
        return known or viewport_of(client.camera)  # type: ignore[attr-defined]

    # -- the image panel of each browser ----------------------------------------------

    def turn_panel(self, client: object, view: str, panel: layout.Panel | None) -> None:
        """The image panel faces ``view``'s camera in ``client``'s browser: a client-scoped
        node ``/panel`` shadows the shared one (Viser 1.1.1: same name, this client only)
        and carries its pictures; hidden in the view from the head; none for the
        overview (the shared panel faces it) or without a ``panel``."""
        scene = getattr(client, "scene", None)
        client_id = getattr(client, "client_id", None)
        if scene is None or client_id is None:
            return
        old = self._shadows.pop(client_id, None)
        if old is not None:
            old[0].remove()  # type: ignore[attr-defined]
        if view == "overview" or panel is None:
            return
        T = panel.placed(view).T_rig_panel
        handle = scene.add_frame(
            "/panel",
            show_axes=False,
            wxyz=wxyz_of(T),
            position=T[:3, 3].copy(),
            visible=view != "head",
        )
        self._shadows[client_id] = (handle, view)

    def follow_panel(self, panel: layout.Panel) -> None:
        """The browsers' own panels follow the shared one laid out anew."""
        for handle, view in self._shadows.values():
            T = panel.placed(view).T_rig_panel
            handle.wxyz = wxyz_of(T)  # type: ignore[attr-defined]
            handle.position = T[:3, 3].copy()  # type: ignore[attr-defined]

    # -- framing -----------------------------------------------------------------------

    def wait_for_cloud(self, client_id: int) -> None:
        """``client_id`` connected before the first cloud: frame it again once it comes."""
        self._unframed.add(client_id)

    def take_waiting(self) -> set[int]:
        """The browsers waiting for the first cloud (:meth:`wait_for_cloud`), forgotten."""
        waiting, self._unframed = self._unframed, set()
        return waiting

    def remember(self, points: np.ndarray) -> None:
        """Keep a sample of the cloud (N, 3) every :data:`FRAME_SAMPLE_S` for the views."""
        now = time.monotonic()
        if self._recent and now - self._recent[-1][0] < FRAME_SAMPLE_S:
            return
        box = layout.scene_box(points)
        if box is None:
            return
        self._recent.append((now, box.sample[:-1]))  # without the rig origin
        while self._recent and now - self._recent[0][0] > FRAME_MEMORY_S:
            self._recent.popleft()

    def recent_box(self, head: np.ndarray) -> layout.SceneBox | None:
        """The extent of the clouds of the last :data:`FRAME_MEMORY_S` seconds and the
        head (sensors' positions ``head``, (N, 3)); None before any cloud."""
        if not self._recent:
            return None
        samples = np.vstack([sample for _, sample in self._recent])
        return layout.scene_box(samples, head)

    def forget(self, client_id: int) -> None:
        """A browser has gone."""
        self._unframed.discard(client_id)
        self._shadows.pop(client_id, None)
        with self._canvas_lock:
            self._canvas.pop(client_id, None)
