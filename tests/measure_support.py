"""The simulated measurement scene (app/sources/sim/measurement_scene.py) as the tests of
issue 35 render it: imagers without offset (radiometrically calibrated), and a box well
inside each panel (tests/fusion/test_measure.py, tests/app/server/test_measure_api.py,
tests/app/cli/test_measure_cli.py)."""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.app.sources.frames import FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.measurement_scene import PANELS, measurement_scene
from trifuse.app.sources.sim.render import HeadModel, Renderer, SensorTruth
from trifuse.app.sources.sim.scene import Scene

Box = tuple[tuple[float, float], tuple[float, float]]
TARGETS = PANELS[:4]
"""The panels read (the backdrop is not one)."""


def render(
    scene: Scene | None = None, stamp_ns: int = 0, seed: int = 0
) -> tuple[FrameSet, dict[str, SensorTruth]]:
    """One frame set of ``scene`` (default: the measurement scene) seen by the default head
    at the world's origin, imagers without offset, live quality."""
    renderer = Renderer(default_rig(), HeadModel(thermal_offset_k={}), live=True)
    return renderer.render(
        scene or measurement_scene(), np.eye(4), stamp_ns, np.random.default_rng(seed)
    )


def panel_boxes(truth: dict[str, SensorTruth], erode_px: int = 51) -> dict[str, Box]:
    """Per panel, the box ((x0, y0), (x1, y1)) of the left eye's pixels that see it, away
    from its outline by ``erode_px // 2`` (the blur and the mapping's edges stay outside)."""
    names = [s.name for s in measurement_scene().solids]
    boxes = {}
    for p in TARGETS:
        m = (truth["ccd_left"].solid == names.index(p.name)).astype(np.uint8)
        ys, xs = np.nonzero(cv2.erode(m, np.ones((erode_px, erode_px), np.uint8)))
        boxes[p.name] = ((float(xs.min()), float(ys.min())), (float(xs.max()), float(ys.max())))
    return boxes
