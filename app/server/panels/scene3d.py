"""The console's Viser 3D scene, built from the :class:`~app.server.runtime.context.ConsoleContext`.

What it shows, all in the rig frame (OpenCV axes: +x right, +y down, +z forward, metres;
the scene's "up" is therefore -y):

- every sensor of the displayed rig: its frame at ``T_rig_sensor`` and its frustum (vertical
  FOV from ``fy``, aspect W/H) as a wireframe in the modality's colour;
- the sensors' live images on a panel just below the head, laid out as the sensors sit on
  the head, each framed in its frustum's colour and named underneath, at ``texture_hz``
  (frames, frustums and images: :mod:`app.server.panels.scene_sensors`);
- the TOF point cloud of the newest depth frame, coloured by the colour camera, by
  temperature (the thermal imager, in the pipeline's palette over its span) or by radial
  distance, at ``rate_hz`` (:mod:`app.server.panels.scene_cloud`);
- the checkerboard at its live estimated pose ``T_rig_board`` (hidden while not seen;
  :mod:`app.server.panels.scene_board`);
- in the "3D scene" GUI folder: the view buttons (overview, from the head, from above,
  from the side: each moves the camera of the browser that pressed it), which rig to
  display ("in use", "ground truth", saved versions; the list is re-read every
  ``choices_period_s``), the cloud's colouring, the point size, the frustums' depth
  ("Frustum size") and whether the live images are shown, the console's "Bandwidth"
  (``full`` or ``low``: :mod:`app.server.panels.scene_profiles`; console-wide,
  ``ctx.bandwidth``, also ``/api/console/settings`` and ``trifuse serve
  --console-bandwidth``), and per sensor the displayed rig's pose difference to the rig in
  use (rotation deg, translation mm).

First sight (the layout and the views are :mod:`app.server.panels.scene_layout`'s pure functions;
its docstring says why): the head is about 15 cm wide and the scene 0.5-8 m away, and the
five sensors sit within a few centimetres of each other looking the same way. Frustums at
the head's scale are invisible in a view of the scene; at the scene's scale, their live
images would cover each other (and the cloud) and their names collide. So the frustums
stay at their true poses as wireframes, whose depth the first TOF cloud sets (a quarter of
its median distance, 2.5 head widths to 0.5 m) unless the operator has moved the "Frustum
size" slider (then their value stays); the live images are spread out on a panel below the
head, each a fifth of the scene's width wide, and each name hangs under its image, so no
two names overlap. Each browser starts with the overview: from behind and above the head,
steep enough that everything the TOF camera sees lies above the head on the screen and the
image panel below it covers none of it, framed in the part of the canvas that Viser's
control panel leaves free; the first cloud re-frames browsers that connected before it.
The view from the head clips what lies nearer than the frustums' ends (their lines would
cross the view), never beyond 0.55 m. The views frame the clouds of the last 45 seconds (a
panning head sweeps its cloud round). What each browser needs: :mod:`app.server.panels.scene_views`.

The point cloud and the board are measured with the rig in use; they hang under the node
``/live``, placed so that the TOF camera of the displayed rig carries them (for two rigs
whose reference is the TOF camera, ``/live`` is the identity). The board is the board
watch's newest pose (:attr:`~app.server.runtime.board_watch.BoardWatch.latest_pose`, published as
soon as the most trusted sensor has found it in a new picture), moved the moment the watch
publishes it; the folder says when the picture it was found in is older than the cloud's.

One thread (:class:`Periodic`) does all the pushing, in the console only while a Viser
client is connected (its ``demand``); GUI callbacks (Viser's thread) and the tick share a
lock. Every step of a tick is guarded: a missing sensor, NaN depth or a
bad rig shows nothing for that part and the error in the folder, and the thread goes on.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np
import viser

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.panels import scene_layout as layout
from trifuse.app.server.panels.scene_board import BoardMarker
from trifuse.app.server.panels.scene_cloud import (
    coloured_cloud,
    decimate_cloud,
    grid_stride,
    temperature_span,
    thermal_k,
)
from trifuse.app.server.panels.scene_profiles import scene_profiles
from trifuse.app.server.panels.scene_sensors import SensorNodes, vertical_fov_rad, wxyz_of
from trifuse.app.server.panels.scene_views import BrowserViews, apply_camera
from trifuse.app.server.runtime.context import BANDWIDTH_MODES, ConsoleContext
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.workflows.report_format import markdown_table
from trifuse.calib.rig import Rig, Sensor
from trifuse.calib.transforms import invert, pose_error
from trifuse.fusion.cloud_colors import CLOUD_COLORINGS

FRUSTUM_SIZE_RANGE_M = (0.05, 2.0)
"""The "Frustum size" slider: the frustums' depth, metres."""
RIG_AXES_PER_DEPTH = 0.3
"""The rig frame's axes are this fraction of the frustum depth long (visible at the
scene's scale; the sensors' own frames keep 15 mm axes)."""
IN_USE = "in use"
VIEW_BUTTONS = {
    "Overview": "overview",
    "View from head": "head",
    "View from above": "above",
    "View from side": "side",
}
"""The "3D scene" folder's view buttons: label -> :data:`scene_layout.VIEWS` name."""
TICK_SLACK_S = 0.05
"""A part updated every ``period`` seconds is due again this much before (ticks come a
little late: a part at half the tick rate would otherwise skip two ticks of three)."""


def rig_difference_markdown(shown_label: str, shown: Rig, in_use: Rig) -> str:
    """Markdown: per sensor of ``shown``, rotation (deg), translation (mm) and focal length
    (px) of ``shown`` minus ``in_use`` (sensors absent from either rig are listed as such)."""
    if shown_label == IN_USE:
        return "Showing the rig in use."
    rows = []
    for name, s in shown.sensors.items():
        if name not in in_use.sensors:
            rows.append([md_text(name), "not in use", "", ""])
            continue
        u = in_use.sensors[name]
        rot_deg, trans_m = pose_error(s.T_rig_sensor, u.T_rig_sensor)
        dfx = s.intrinsics.fx - u.intrinsics.fx
        rows.append([md_text(name), f"{rot_deg:.3f}", f"{trans_m * 1000:.1f}", f"{dfx:+.1f}"])
    rows += [
        [md_text(n), "not in this rig", "", ""] for n in in_use.sensors if n not in shown.sensors
    ]
    head = ["sensor", "rot (deg)", "trans (mm)", "Δfx (px)"]
    return "\n".join(
        [f"**{md_text(shown_label)}** vs **{IN_USE}**", "", *markdown_table(head, rows)]
    )


class Scene3D(Periodic):
    """The 3D scene and its "3D scene" GUI folder; :meth:`start` runs the updates.

    Args:
        ctx: the console's shared objects (server, pipeline, board, board watch, rigs;
            ``ctx.bandwidth``: the mode, followed each tick).
        rate_hz: ticks per second: board pose at most this often, the point cloud too in
            ``full`` (:func:`scene_profiles`).
        texture_hz: live image updates per second in ``full`` (each pushes ~5 small JPEGs).
        choices_period_s: how often ``ctx.rigs()`` is re-read for the rig dropdown.
        clock: monotonic seconds (tests pass their own).

    Attributes:
        box: the scene's extent from the first TOF cloud (None before it): what the views
            frame and the default frustum depth come from.
        user_sized: whether an operator has moved the "Frustum size" slider (then the
            first cloud leaves the frustum depth alone).
        profiles: :class:`~app.server.panels.scene_profiles.SceneProfile` of each bandwidth mode.
        bandwidth_mode, profile: the bandwidth mode applied now and its profile.
        cloud_stride: the cloud keeps every this-many-th TOF pixel in each direction.
    """

    def __init__(
        self,
        ctx: ConsoleContext,
        rate_hz: float = 4.0,
        texture_hz: float = 2.0,
        choices_period_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__("scene3d", 1.0 / rate_hz)
        self.ctx = ctx
        self.server = server = ctx.server
        self.choices_period_s = choices_period_s
        self.clock = clock
        self._lock = threading.RLock()
        self._next_cloud = self._next_texture = 0.0  # when they are due (clock)
        self._next_choices = 0.0
        self.profiles = scene_profiles(rate_hz, texture_hz)
        self.bandwidth_mode = ctx.bandwidth.mode
        self.profile = self.profiles[self.bandwidth_mode]
        self.cloud_stride = 1
        self.errors: dict[str, str] = {}
        self.cloud_span: tuple[float, float] | None = None
        self._cloud_key: tuple | None = None
        self.box: layout.SceneBox | None = None
        self.user_sized = False
        self._sizing = False  # the scene itself is setting the slider
        self.views = BrowserViews()  # each browser's canvas, panel and framing

        server.scene.set_up_direction("-y")

        try:
            self._rigs: dict[str, Rig] = self._read_rigs()
        except Exception as exc:  # a bad saved rig must not stop the console
            self._rigs = {}
            self.errors["rigs"] = describe_error(exc)
        self._rigs = self._rigs or {IN_USE: ctx.pipeline.rig}
        self.shown_label = IN_USE if IN_USE in self._rigs else next(iter(self._rigs))
        self.shown_rig: Rig = self._rigs[self.shown_label]
        first_depth = layout.default_frustum_depth(
            layout.DEFAULT_BOX, layout.head_width(self._positions(self.shown_rig))
        )

        gui = server.gui
        with gui.add_folder("3D scene"):
            self.view_buttons = {label: gui.add_button(label) for label in VIEW_BUTTONS}
            self.rig_choice = gui.add_dropdown(
                "Rig shown", tuple(self._rigs), initial_value=self.shown_label
            )
            self.cloud_mode = gui.add_dropdown(
                "Cloud colour", CLOUD_COLORINGS, initial_value="color"
            )
            self.point_size = gui.add_slider("Point size (mm)", 1.0, 30.0, 1.0, 8.0)
            self.textures_on = gui.add_checkbox("Live images", True)
            self.bandwidth_choice = gui.add_dropdown(
                "Bandwidth",
                BANDWIDTH_MODES,
                initial_value=self.bandwidth_mode,
                hint="What this console sends to every browser. low, for a radio link: "
                "the cloud of every 2nd TOF pixel at 2 Hz, live images and feeds 160 px "
                "wide once a second (about 1 Mbit/s against 6)",
            )
            self.frustum_size = gui.add_slider(
                "Frustum size (m)", *FRUSTUM_SIZE_RANGE_M, 0.01, first_depth
            )
            self.cloud_md = gui.add_markdown("Cloud: waiting for a TOF frame")
            self.board_md = gui.add_markdown("Board: not detected")
            self.rig_md = gui.add_markdown("")
            self.error_md = gui.add_markdown("")

        self.rig_axes = server.scene.add_frame("/rig", axes_length=0.05, axes_radius=0.002)
        self.panel_node = server.scene.add_frame("/panel", show_axes=False)
        self.panel: layout.Panel | None = None
        self.nodes: dict[str, SensorNodes] = {}
        self.live = server.scene.add_frame("/live", show_axes=False)
        self.cloud = server.scene.add_point_cloud(
            "/live/tof_points",
            points=np.zeros((1, 3), np.float32),
            colors=np.zeros((1, 3), np.uint8),
            point_size=self.point_size.value / 1000.0,
            precision="float32",
            visible=False,
        )
        self.board_marker = BoardMarker(server.scene, ctx.board, self.board_md)
        self.board_node = self.board_marker.node
        self._show_rig(self.shown_label)

        for label, view in VIEW_BUTTONS.items():
            self.view_buttons[label].on_click(
                lambda e, v=view: self._guard("view", lambda: self.set_view(e.client, v))
            )
        self.rig_choice.on_update(lambda _e: self._guard("rig", self._on_rig_choice))
        self.cloud_mode.on_update(lambda _e: self._guard("cloud", self.update_cloud))
        self.point_size.on_update(lambda _e: self._guard("cloud", self._on_point_size))
        self.textures_on.on_update(lambda _e: self._guard("textures", self._on_textures))
        self.frustum_size.on_update(lambda _e: self._guard("rig", self._on_frustum_size))
        self.bandwidth_choice.on_update(lambda _e: self._guard("bandwidth", self._on_bandwidth))
        self._apply_bandwidth(self.bandwidth_mode)

        # the board moves the moment its pose is known
        ctx.board_watch.pose_listeners.append(lambda _s: self._guard("board", self.update_board))

        @server.on_client_connect
        def _start_view(client: viser.ClientHandle) -> None:
            self._note_canvas(client.client_id, client.camera)
            client.camera.on_update(lambda camera: self._note_canvas(client.client_id, camera))
            with self._lock:
                if self.box is None:
                    self.views.wait_for_cloud(client.client_id)
            self._guard("view", lambda: self.set_view(client, "overview"))

        @server.on_client_disconnect
        def _gone(client: viser.ClientHandle) -> None:
            with self._lock:
                self.views.forget(client.client_id)

    # -- building ----------------------------------------------------------------------

    def _nodes_for(self, sensor: Sensor) -> SensorNodes:
        nodes = self.nodes.get(sensor.name)
        if nodes is None:
            quality = self.profile.texture_jpeg_quality
            nodes = self.nodes[sensor.name] = SensorNodes(self.server, "/rig", sensor, quality)
        return nodes

    # -- helpers -----------------------------------------------------------------------

    def _guard(self, part: str, fn: Callable[[], None]) -> None:
        """Run one part of an update under the lock; an exception is shown, not raised."""
        with self._lock:
            try:
                fn()
            except Exception as exc:  # the scene must outlive any bad frame
                self.errors[part] = describe_error(exc)
            else:
                self.errors.pop(part, None)
            text = "\n\n".join(
                f"**{md_text(k)}:** {md_text(v)}" for k, v in sorted(self.errors.items())
            )
            if self.error_md.content != text:
                self.error_md.content = text

    def _due(self, part: str, period_s: float, now: float) -> bool:
        """Whether ``part`` (``cloud``, ``texture``: its ``_next_<part>`` time) is due at
        ``now``, :data:`TICK_SLACK_S` early being in time; if so it is next due
        ``period_s`` seconds later."""
        attr = f"_next_{part}"
        if now < getattr(self, attr) - TICK_SLACK_S:
            return False
        setattr(self, attr, now + period_s)
        return True

    def _read_rigs(self) -> dict[str, Rig]:
        return dict(self.ctx.rigs())

    @property
    def in_use(self) -> Rig:
        return self._rigs.get(IN_USE, self.ctx.pipeline.rig)

    def _tof_name(self) -> str:
        return self.ctx.pipeline.tof or self.in_use.reference

    @staticmethod
    def _positions(rig: Rig) -> np.ndarray:
        """(N, 3) the sensors' positions in the rig frame, metres."""
        return np.stack([np.asarray(s.T_rig_sensor[:3, 3], float) for s in rig.sensors.values()])

    # -- views -------------------------------------------------------------------------

    def view_pose(self, view: str, viewport: tuple[int, int]) -> layout.CameraPose:
        """The camera of ``view`` (:data:`scene_layout.VIEWS`) for a canvas of ``viewport``
        (width, height) CSS px: framing the clouds of the last
        :data:`~app.server.panels.scene_views.FRAME_MEMORY_S` seconds (or
        :data:`scene_layout.DEFAULT_BOX` before any), the head and the image panel."""
        box = self.views.recent_box(self._positions(self.shown_rig))
        box = box or self.box or layout.DEFAULT_BOX
        extra = None if self.panel is None else self.panel.placed(view).corners()
        fov = max(vertical_fov_rad(s) for s in self.shown_rig.sensors.values())
        depth = float(self.frustum_size.value)
        return layout.view_pose(view, box, viewport, extra, fov, frustum_depth_m=depth)

    def _note_canvas(self, client_id: int, camera: object) -> None:
        """Remember a browser's canvas size (:meth:`BrowserViews.note_canvas
        <app.server.panels.scene_views.BrowserViews.note_canvas>`)."""
        self.views.note_canvas(client_id, camera)

    def canvas_of(self, client: object) -> tuple[int, int]:
        """(width, height) of a browser's canvas (:meth:`BrowserViews.canvas_of
        <app.server.panels.scene_views.BrowserViews.canvas_of>`)."""
        return self.views.canvas_of(client)

    def set_view(self, client: viser.ClientHandle | None, view: str) -> None:
        """Move ``client``'s camera to ``view`` (nothing without a client) and turn the
        image panel to face it, for this browser only."""
        if client is None:
            return
        apply_camera(client.camera, self.view_pose(view, self.canvas_of(client)))
        self.views.turn_panel(client, view, self.panel)

    def _frame_waiting_clients(self) -> None:
        """Re-frame the browsers that connected before the first cloud (once)."""
        waiting = self.views.take_waiting()
        if not waiting:
            return
        for client_id, client in self.server.get_clients().items():
            if client_id in waiting:
                self.set_view(client, "overview")

    # -- rig ---------------------------------------------------------------------------

    def _on_frustum_size(self) -> None:
        if not self._sizing:
            self.user_sized = True
        self._apply_depth(float(self.frustum_size.value))

    def _apply_depth(self, depth_m: float) -> None:
        """Frustums ``depth_m`` deep and the rig's axes to match."""
        for nodes in self.nodes.values():
            nodes.set_depth(depth_m)
        self.rig_axes.axes_length = RIG_AXES_PER_DEPTH * depth_m
        self.rig_axes.axes_radius = 0.02 * RIG_AXES_PER_DEPTH * depth_m

    def _layout_panel(self) -> None:
        """Lay the image panel out for the displayed rig, its pictures sized from the
        first cloud's extent (or :data:`scene_layout.DEFAULT_BOX` before it)."""
        rig = self.shown_rig
        shown = {n: self.nodes[n] for n in rig.sensors if n in self.nodes}
        if not shown:
            return
        self.panel = layout.image_panel(
            {n: rig[n].T_rig_sensor[:3, 3] for n in shown},
            {n: rig[n].width / rig[n].height for n in shown},
            layout.panel_image_width(self.box or layout.DEFAULT_BOX),
        )
        self.panel_node.wxyz = wxyz_of(self.panel.T_rig_panel)
        self.panel_node.position = self.panel.T_rig_panel[:3, 3].copy()
        for name, cell in self.panel.cells.items():
            shown[name].set_cell(cell)
        self.views.follow_panel(self.panel)  # the browsers' own views follow

    def _set_first_sight(self, points: np.ndarray) -> None:
        """The first cloud: the scene's extent; the image panel sized from it, the
        frustum depth too (unless an operator has set one); browsers that connected
        before it re-framed."""
        head = self._positions(self.shown_rig)
        box = layout.scene_box(points, head)
        if box is None:
            return
        self.box = box
        self._layout_panel()
        if not self.user_sized:
            depth = layout.default_frustum_depth(box, layout.head_width(head))
            depth = float(np.clip(depth, *FRUSTUM_SIZE_RANGE_M))
            self._sizing = True
            try:
                self.frustum_size.value = depth  # runs _on_frustum_size
            finally:
                self._sizing = False
            self._apply_depth(depth)
        self._frame_waiting_clients()

    def _on_rig_choice(self) -> None:
        self._show_rig(self.rig_choice.value)

    def _show_rig(self, label: str) -> None:
        """Move frames and frustums to the rig ``label``; the live nodes follow its TOF."""
        rig = self._rigs.get(label)
        if rig is None:
            return
        self.shown_label, self.shown_rig = label, rig
        for sensor in rig.sensors.values():
            self._nodes_for(sensor).place(sensor)
        for name, nodes in self.nodes.items():
            if name not in rig.sensors:
                nodes.hide()
        self._apply_depth(float(self.frustum_size.value))
        self._layout_panel()
        tof = self._tof_name()
        T_shown_use = np.eye(4)
        if tof in rig and tof in self.in_use:
            T_shown_use = rig[tof].T_rig_sensor @ invert(self.in_use[tof].T_rig_sensor)
        self.live.wxyz = wxyz_of(T_shown_use)
        self.live.position = T_shown_use[:3, 3].copy()
        self.rig_md.content = rig_difference_markdown(label, rig, self.in_use)

    def refresh_rigs(self) -> None:
        """Re-read ``ctx.rigs()``: new labels join the dropdown, a vanished selection falls
        back to "in use", a changed displayed rig (or rig in use) is redrawn."""
        rigs = self._read_rigs()
        if not rigs:
            return
        old = self._rigs
        self._rigs = rigs
        labels = tuple(rigs)
        if tuple(self.rig_choice.options) != labels:
            self.rig_choice.options = labels  # may reset the value (-> _show_rig)
        label = self.rig_choice.value
        if label not in rigs:
            label = IN_USE if IN_USE in rigs else labels[0]
        changed = old.get(label) != rigs[label] or old.get(IN_USE) != rigs.get(IN_USE)
        if changed or label != self.shown_label:
            self._show_rig(label)

    # -- cloud -------------------------------------------------------------------------

    def _on_point_size(self) -> None:
        """The points' size: the slider's (mm) times the cloud's stride (a decimated cloud
        is drawn with larger points, so that its surface stays as closed)."""
        self.cloud.point_size = float(self.point_size.value) / 1000.0 * self.cloud_stride

    # -- bandwidth ---------------------------------------------------------------------

    def _on_bandwidth(self) -> None:
        """The dropdown's mode becomes the console's and is applied."""
        mode = str(self.bandwidth_choice.value)
        self.ctx.bandwidth.mode = mode
        self._apply_bandwidth(mode)

    def follow_bandwidth(self) -> None:
        """Apply the console's mode if it changed elsewhere (``/api/console/settings``) and
        show it in the dropdown. A dropdown that merely differs is left alone: Viser sets its
        value before the choice's callback runs, and writing the old mode back in between
        would lose the operator's choice."""
        mode = self.ctx.bandwidth.mode
        if mode != self.bandwidth_mode:
            self._apply_bandwidth(mode)
            self.bandwidth_choice.value = mode

    def _apply_bandwidth(self, mode: str) -> None:
        """Take ``mode``'s profile: the cloud's stride and point size, the live images'
        JPEG quality; cloud and images are sent again at the next tick."""
        self.bandwidth_mode, self.profile = mode, self.profiles[mode]
        limit = self.profile.cloud_max_points
        tof = self.in_use[self._tof_name()] if self._tof_name() in self.in_use else None
        self.cloud_stride = grid_stride(tof.image_size, limit) if limit and tof else 1
        self._on_point_size()
        for nodes in self.nodes.values():
            nodes.set_jpeg_quality(self.profile.texture_jpeg_quality)
            nodes.shown_frame = None  # made again at the new size
        self._cloud_key = None
        self._next_cloud = self._next_texture = 0.0

    def update_cloud(self) -> None:
        """Push the newest TOF points (in the in-use rig's TOF frame, metres) coloured by
        the chosen mode; hidden while there is no depth. Skips unchanged inputs."""
        p = self.ctx.pipeline
        fusion, fs = p.fusion, p.latest_set
        if fs is None or not fusion.ready:
            self.cloud.visible = False
            self.cloud_md.content = "Cloud: waiting for a TOF frame"
            return
        mode = self.cloud_mode.value
        points = fusion.points
        key = (fs, points, mode, p.settings)
        if self._cloud_key is not None and all(
            a is b for a, b in zip(key, self._cloud_key, strict=True)
        ):
            return
        pts, rgb, legend, self.cloud_span = coloured_cloud(p, fs, mode)
        pts = np.asarray(pts, dtype=np.float32)
        finite = np.isfinite(pts).all(axis=1)
        if not finite.all():
            pts, rgb = pts[finite], rgb[finite]
        if len(pts) == 0:
            self.cloud.visible = False
            self.cloud_md.content = "Cloud: no valid depth in the last TOF frame"
            self._cloud_key = key
            return
        full_count = len(pts)
        if self.cloud_stride > 1:
            tof = p.fusion.rig[p.fusion.tof]
            pts, rgb = decimate_cloud(pts, rgb, tof, self.cloud_stride)
        with self.server.atomic():
            self.cloud.precision = self.profile.cloud_precision
            self.cloud.points = pts
            self.cloud.colors = np.ascontiguousarray(rgb, dtype=np.uint8)
            self.cloud.visible = True
        text = f"Cloud: {len(pts):,} points, {md_text(mode)}: {md_text(legend)}"
        if self.cloud_stride > 1:
            s = self.cloud_stride
            text += f" (low bandwidth: one TOF pixel in {s} x {s}, of {full_count:,} points)"
        self.cloud_md.content = text
        self._cloud_key = key
        if self.box is None:
            self._set_first_sight(pts)
        self.views.remember(pts)

    # -- textures ----------------------------------------------------------------------

    def _on_textures(self) -> None:
        if not self.textures_on.value:
            for nodes in self.nodes.values():
                nodes.show_image(None)
                nodes.shown_frame = None
        else:
            self.update_textures()

    def update_textures(self) -> None:
        """Each displayed sensor's picture on the image panel shows its newest image
        (:func:`~app.server.panels.scene_sensors.sensor_texture`) with the next view's
        outline when one is suggested (``ctx.next_outline``); a sensor without a frame in
        the newest set shows none (its frame and name stay)."""
        if not self.textures_on.value:
            return
        max_width = self.profile.texture_max_w
        p = self.ctx.pipeline
        fs = p.latest_set
        frames = fs.frames if fs is not None else {}
        radiometry = p.radiometry  # the thermal images as the fused picture reads them
        span = None
        try:
            thermals = [
                thermal_k(p, fs, n)
                for n in frames
                if n in self.shown_rig and self.shown_rig[n].modality == "thermal"
            ]
            span = temperature_span(p, thermals)
        except (ValueError, KeyError, AttributeError):
            span = None
        palette = p.settings.palette
        outlines = self.ctx.next_outline
        for name, nodes in self.nodes.items():
            shown = frames.get(name) if name in self.shown_rig else None
            why = nodes.show_frame(
                shown, span, palette, max_width, outlines.get(name), radiometry.get(name)
            )
            if why is None:
                self.errors.pop(f"texture {name}", None)
            else:
                self.errors[f"texture {name}"] = why

    # -- board -------------------------------------------------------------------------

    def update_board(self) -> None:
        """The board at the board watch's newest pose ``T_rig_board`` (rig in use; its
        ``latest_pose``, which may come before the other sensors' search ends), hidden
        when that sighting has no pose (:meth:`BoardMarker.show
        <app.server.panels.scene_board.BoardMarker.show>`)."""
        watch = self.ctx.board_watch
        latest = watch.latest_pose or watch.latest
        self.board_marker.show(latest, self.ctx.pipeline.latest_set)

    # -- the loop ----------------------------------------------------------------------

    def tick(self) -> None:
        now = self.clock()
        self._guard("bandwidth", self.follow_bandwidth)
        if now >= self._next_choices:
            self._next_choices = now + self.choices_period_s
            self._guard("rigs", self.refresh_rigs)
        self._guard("board", self.update_board)
        profile = self.profile
        every_tick = profile.cloud_hz * self.period_s >= 1.0  # full: the tick is the limit
        if every_tick or self._due("cloud", 1.0 / profile.cloud_hz, now):
            self._guard("cloud", self.update_cloud)
        if self._due("texture", 1.0 / profile.texture_hz, now):
            self._guard("textures", self.update_textures)
