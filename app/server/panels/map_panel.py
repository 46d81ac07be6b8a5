"""The console's "Thermal map" folder and the map in the 3D scene (issue 20).

The map is drawn in the head's frame, like the rest of the scene (the TOF cloud, the
frustums): its node ``/map`` carries ``T_rig_world`` of the newest pose mapped, so the
frustums stand where the head is and the map and the head's path (``/map/path``) turn
around them as it moves (a display frame fixed to the rig, as in Foxglove). The points are
the occupied voxels, merged into coarser cells when there are more than the bandwidth mode
allows (:func:`fusion.map_view.map_cloud`: 300 k in ``full``, 60 k in ``low``), so a map of a
million voxels stays interactive; they are sent again only when the map changed, at most
every ``redraw_s`` seconds. Temperatures take the Fusion panel's palette and AGC (``dde``
shows as ``plateau``: a voxel has no neighbourhood detail to add).
"""

from __future__ import annotations

import threading
import time

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.panels.scene_sensors import wxyz_of
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.map_worker import MapWorker
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.calib.transforms import invert
from trifuse.fusion.map_view import MAP_COLORINGS, map_cloud, path_segments

C_TO_K = 273.15
MAX_POINTS = {"full": 300_000, "low": 60_000}
"""Points sent per map update in each bandwidth mode."""
PATH_RGB = (40, 220, 255)


class MapPanel(Periodic):
    """The Thermal map folder, the map's scene nodes and their updates.

    Args:
        ctx: the console's shared objects (server, bandwidth).
        worker: the map worker.
        rate_hz: ticks per second (the map's pose in the scene, the status).
        redraw_s: the least time between two sends of the map's points.
    """

    def __init__(
        self, ctx: ConsoleContext, worker: MapWorker, rate_hz: float = 4.0, redraw_s: float = 1.0
    ) -> None:
        super().__init__("map-panel", 1.0 / rate_hz)
        self.ctx, self.worker = ctx, worker
        self.redraw_s = redraw_s
        self._lock = threading.Lock()
        self._drawn: tuple | None = None
        self._next_draw = 0.0
        self.shown_points = self.shown_level = self.above = 0
        self.above_c: float | None = None
        """The threshold (°C) ``above`` was counted at, None: not counted (no highlight)."""
        self.span_k: tuple[float, float] | None = None
        gui, scene = ctx.server.gui, ctx.server.scene
        with gui.add_folder("Thermal map", expand_by_default=False):
            self.build = gui.add_checkbox(
                "Build map",
                worker.enabled,
                hint="Accumulate every TOF frame into a voxel map of what the head has seen",
            )
            self.pause = gui.add_button("Pause", disabled=not worker.enabled)
            self.reset_button = gui.add_button("Reset map")
            self.coloring = gui.add_dropdown(
                "Map colour", MAP_COLORINGS, initial_value="temperature"
            )
            self.highlight = gui.add_checkbox("Highlight hot spots", False)
            self.threshold_c = gui.add_number("Above (°C)", 50.0, min=-40.0, max=500.0, step=1.0)
            self.show_path = gui.add_checkbox("Head's path", True)
            self.save_button = gui.add_button("Save map")
            self.saved = gui.add_dropdown("Saved maps", tuple(worker.saved()) or ("(none)",))
            self.load_button = gui.add_button("Load map")
            self.status_md = gui.add_markdown("Map: off")
            self.message = gui.add_markdown("")
        self.node = scene.add_frame("/map", show_axes=False, visible=False)
        self.points = scene.add_point_cloud(
            "/map/voxels",
            points=np.zeros((1, 3), np.float32),
            colors=np.zeros((1, 3), np.uint8),
            point_size=worker.map.settings.voxel_m,
            precision="float32",
            visible=False,
        )
        self.path = scene.add_line_segments(
            "/map/path",
            points=np.zeros((1, 2, 3), np.float32),
            colors=PATH_RGB,
            thickness=3.0,
            thickness_units="screen",
            visible=False,
        )
        self.build.on_update(lambda _e: self._act(self._on_build))
        self.pause.on_click(lambda _e: self._act(self._on_pause))
        self.reset_button.on_click(lambda _e: self._act(self._on_reset))
        self.save_button.on_click(lambda _e: self._act(self._on_save))
        self.load_button.on_click(lambda _e: self._act(self._on_load))
        for control in (self.coloring, self.highlight, self.threshold_c, self.show_path):
            control.on_update(lambda _e: self._act(self._redraw_now))

    def _act(self, action) -> None:
        try:
            self.message.content = action() or ""
        except (OSError, ValueError) as exc:
            self.message.content = f"**Not done:** {md_text(describe_error(exc))}"

    def _on_build(self) -> str:
        self.worker.set_enabled(self.build.value)
        self.pause.disabled = not self.build.value
        self._redraw_now()
        return ""

    def _on_pause(self) -> str:
        paused = not self.worker.builder.paused
        self.worker.set_paused(paused)
        self.pause.label = "Resume" if paused else "Pause"
        return "Paused: the map is kept and shown." if paused else ""

    def _on_reset(self) -> str:
        self.worker.reset()
        self._redraw_now()
        return "The map is empty again."

    def _on_save(self) -> str:
        path, ply = self.worker.save()
        self.saved.options = tuple(self.worker.saved()) or ("(none)",)
        return f"Saved {md_text(path.name)} and {md_text(ply.name)} in {md_text(path.parent)}"

    def _on_load(self) -> str:
        name = self.saved.value
        if name == "(none)":
            raise ValueError("no saved map chosen")
        self.worker.load(name)
        self.pause.label = "Resume"
        self._redraw_now()
        return f"Showing {md_text(name)} (paused: Resume adds what the head sees now)."

    def _redraw_now(self) -> None:
        self._drawn = None
        self._next_draw = 0.0

    def tick(self) -> None:
        status = self.worker.status()
        on = status["enabled"] or status["occupied"] > 0
        self.node.visible = on
        T = self.worker.T_world_rig
        if T is not None:
            T_rig_world = invert(T)
            self.node.wxyz = wxyz_of(T_rig_world)
            self.node.position = tuple(float(v) for v in T_rig_world[:3, 3])
        now = time.monotonic()
        mode = self.ctx.bandwidth.mode
        key = (
            self.worker.map.revision,
            id(self.worker.map),
            self.coloring.value,
            self.highlight.value,
            self.threshold_c.value,
            self.show_path.value,
            mode,
            self.ctx.pipeline.settings.palette,
            self.ctx.pipeline.settings.agc,
        )
        if key != self._drawn and now >= self._next_draw:
            self._drawn, self._next_draw = key, now + self.redraw_s
            self.draw(mode)
        self.status_md.content = self._status_text(status)

    def draw(self, mode: str = "full") -> None:
        """Send the map's points and path (the scene nodes) as they are now."""
        threshold_c = self.threshold_c.value if self.highlight.value else None
        threshold = None if threshold_c is None else threshold_c + C_TO_K
        display = self.ctx.pipeline.settings  # the map's colours follow the Fusion panel's
        with self.worker.lock:
            cloud = map_cloud(
                self.worker.map,
                self.coloring.value,
                MAX_POINTS.get(mode, MAX_POINTS["full"]),
                palette_name=display.palette,
                threshold_k=threshold,
                agc="linear" if display.agc == "linear" else "plateau",
            )
            segments = path_segments(self.worker.map)
        with self._lock:
            if len(cloud.points):
                self.points.points = cloud.points
                self.points.colors = cloud.colors
                self.points.point_size = float(cloud.cell_m)
                self.points.precision = "float16" if mode == "low" else "float32"
            self.points.visible = bool(len(cloud.points))
            if len(segments):
                self.path.points = segments
            self.path.visible = bool(len(segments)) and self.show_path.value
            self.shown_points, self.shown_level = len(cloud.points), cloud.level
            self.span_k, self.above = cloud.span_k, cloud.above
            self.above_c = threshold_c

    def _status_text(self, s: dict) -> str:
        if not s["enabled"] and s["occupied"] == 0:
            return "Map: off"
        state = "paused" if s["paused"] else ("building" if s["enabled"] else "stopped")
        cost = "–" if s["ms_per_frame"] is None else f"{s['ms_per_frame']:.1f} ms"
        lod = (
            f", shown as {self.shown_points:,} cells of {2**self.shown_level} voxels"
            if self.shown_level
            else ""
        )
        lines = [
            f"Map ({state}): **{s['occupied']:,}** occupied voxels of {s['voxel_m'] * 100:.0f} "
            f"cm{lod}; {s['frames']} TOF frames ({s['skipped']} skipped), {cost} a frame, "
            f"{s['memory_mb']} MB; pose: {md_text(s['pose_source'] or '–')}",
        ]
        if self.highlight.value:
            t = self.threshold_c.value
            counted = f"{self.above:,}" if self.above_c == t else "Counting the"
            lines.append(f"{counted} points at or above {t:.0f} °C")
        if s["last_error"]:
            lines.append(f"**Last error:** {md_text(s['last_error'])}")
        return "\n\n".join(lines)
