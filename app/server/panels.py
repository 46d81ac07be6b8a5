"""The console's Viser GUI panels: Fusion, Thermal and Feeds.

Fusion and Thermal write the pipeline's display settings and per-imager offsets (taking
effect on the next frame); Feeds shows each sensor's newest image (thermal colour-mapped,
TOF amplitude stretched) and the Thermal panel the live left-right temperature difference
over points both imagers see (the same TOF point sampled in each).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import viser

from app.preview import to_display
from app.server.periodic import Periodic
from app.server.pipeline import FusionPipeline
from fusion.palettes import PALETTE_NAMES
from fusion.stereo import sample_image

MODES = ("blend", "edges", "thermal", "threshold", "isotherm", "pip", "color")
C_TO_K = 273.15


class Panels(Periodic):
    """Builds the panels and refreshes the feeds and the left-right difference."""

    def __init__(
        self, server: viser.ViserServer, pipeline: FusionPipeline, feed_hz: float = 2.0
    ) -> None:
        super().__init__("panels", 1.0 / feed_hz)
        self.server, self.pipeline = server, pipeline
        gui = server.gui
        s = pipeline.settings
        with gui.add_folder("Fusion"):
            self.mode = gui.add_dropdown("Mode", MODES, initial_value=s.mode)
            self.palette = gui.add_dropdown("Palette", PALETTE_NAMES, initial_value=s.palette)
            self.opacity = gui.add_slider("Opacity", 0.0, 1.0, 0.05, s.opacity)
            self.edges = gui.add_slider("Edge strength", 0.0, 10.0, 0.5, s.edge_strength)
            self.thr_lo = gui.add_number("Threshold low (°C)", 40.0, step=0.5)
            self.thr_hi = gui.add_number("Threshold high (°C)", 40.0, step=0.5)
            self.thr_dir = gui.add_dropdown(
                "Threshold shows", ("above", "below", "inside"), initial_value=s.threshold_direction
            )
            self.iso_lo = gui.add_number("Isotherm low (°C)", 30.0, step=0.5)
            self.iso_hi = gui.add_number("Isotherm high (°C)", 40.0, step=0.5)
            self.mark = gui.add_checkbox("Mark fallback depth", s.mark_fallback)
        with gui.add_folder("Thermal"):
            self.auto = gui.add_checkbox("Auto span (both eyes)", s.span_k is None)
            self.span_lo = gui.add_number("Span low (°C)", 15.0, step=0.5)
            self.span_hi = gui.add_number("Span high (°C)", 45.0, step=0.5)
            self.offsets = {
                name: gui.add_number(f"Offset {name} (K)", 0.0, step=0.05)
                for name in pipeline.thermal_offset_k
            }
            self.difference = gui.add_markdown("Left - right: waiting for frames")
            self.error = gui.add_markdown("")
        with gui.add_folder("Feeds", expand_by_default=False):
            blank = np.zeros((90, 120, 3), np.uint8)
            self.feeds = {
                name: gui.add_image(blank, label=name, format="jpeg") for name in pipeline.rig.names
            }
        for handle in (
            self.mode,
            self.palette,
            self.opacity,
            self.edges,
            self.thr_lo,
            self.thr_hi,
            self.thr_dir,
            self.iso_lo,
            self.iso_hi,
            self.mark,
            self.auto,
            self.span_lo,
            self.span_hi,
            *self.offsets.values(),
        ):
            handle.on_update(lambda _event: self.apply())

    def apply(self) -> None:
        """Settings from the controls; a bad combination is shown, the old one kept."""
        lo, hi = self.span_lo.value + C_TO_K, self.span_hi.value + C_TO_K
        try:
            settings = dataclasses.replace(
                self.pipeline.settings,
                mode=self.mode.value,
                palette=self.palette.value,
                opacity=float(self.opacity.value),
                edge_strength=float(self.edges.value),
                threshold_k=(self.thr_lo.value + C_TO_K, self.thr_hi.value + C_TO_K),
                threshold_direction=self.thr_dir.value,
                isotherm_k=(self.iso_lo.value + C_TO_K, self.iso_hi.value + C_TO_K),
                mark_fallback=bool(self.mark.value),
                span_k=None if self.auto.value else (lo, hi),
            )
        except ValueError as exc:
            self.error.content = f"**Not applied:** {exc}"
            return
        self.error.content = ""
        self.pipeline.settings = settings
        for name, handle in self.offsets.items():
            self.pipeline.thermal_offset_k[name] = float(handle.value)

    def tick(self) -> None:
        fs = self.pipeline.latest_set
        if fs is None:
            return
        for name, frame in fs.frames.items():
            if name in self.feeds:
                img = to_display(frame.image)
                h, w = img.shape[:2]
                self.feeds[name].image = cv2.resize(
                    img, (240, round(240 * h / w)), interpolation=cv2.INTER_AREA
                )
        self.difference.content = self._difference(fs)

    def _difference(self, fs) -> str:
        """Median left - right temperature over TOF points both thermal imagers see."""
        rig, fusion = self.pipeline.rig, self.pipeline.fusion
        left, right = rig.eyes["left"].thermal, rig.eyes["right"].thermal
        if not fusion.ready or left not in fs.frames or right not in fs.frames:
            return "Left - right: needs both thermal imagers and a TOF frame"
        tof = self.pipeline.tof
        pts = fusion.points
        t_l = sample_image(rig, left, tof, pts, fs.frames[left].image, np.nan)
        t_r = sample_image(rig, right, tof, pts, fs.frames[right].image, np.nan)
        t_l = t_l + self.pipeline.thermal_offset_k.get(left, 0.0)
        t_r = t_r + self.pipeline.thermal_offset_k.get(right, 0.0)
        both = np.isfinite(t_l) & np.isfinite(t_r)
        if both.sum() < 100:
            return f"Left - right: only {int(both.sum())} shared points"
        d = float(np.median(t_l[both] - t_r[both]))
        return f"Left - right: **{d:+.2f} K** over {int(both.sum())} shared points"
