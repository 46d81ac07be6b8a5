"""The console's 3D scene without a console: a small fake of the FusionPipeline (the
simulated head's rig, a real StereoFusion, one synthetic frame set) and the console context
around a Viser server (tests/app/server/test_scene3d.py,
tests/app/server/browser/test_browser_scene.py)."""

from __future__ import annotations

import contextlib
import io
from types import SimpleNamespace

import numpy as np
import viser

from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.board import Board
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.stereo import StereoFusion

RED = (200, 30, 30)
GREEN = (30, 200, 30)
LEFT_K, RIGHT_K = 305.0, 299.0
SPAN_K = (295.0, 315.0)


def synthetic_set(rig: Rig, distance_m: np.ndarray) -> FrameSet:
    """Uniform red left and green right colour images, uniform 305 K / 299 K thermal
    images, the given TOF distance (H, W) metres with a ramp amplitude."""

    def size(name: str) -> tuple[int, int]:
        w, h = rig[name].image_size
        return h, w

    frames = {
        "ccd_left": Frame("ccd_left", 1, np.full((*size("ccd_left"), 3), RED, np.uint8)),
        "ccd_right": Frame("ccd_right", 1, np.full((*size("ccd_right"), 3), GREEN, np.uint8)),
        "thermal_left": Frame("thermal_left", 1, np.full(size("thermal_left"), LEFT_K, np.float32)),
        "thermal_right": Frame(
            "thermal_right", 1, np.full(size("thermal_right"), RIGHT_K, np.float32)
        ),
        "tof": Frame(
            "tof",
            1,
            np.tile(np.linspace(100, 3000, size("tof")[1], dtype=np.float32), (size("tof")[0], 1)),
            distance_m,
        ),
    }
    return FrameSet(1, frames)


def ramp_distance(rig: Rig) -> np.ndarray:
    """TOF radial distance (H, W) float32 metres: 1.5 m at the top row to 3.5 m at the
    bottom, a NaN hole in the middle."""
    w, h = rig["tof"].image_size
    d = np.repeat(np.linspace(1.5, 3.5, h, dtype=np.float32)[:, None], w, axis=1)
    d[60:70, 80:90] = np.nan
    return d


def pipeline_for(fusion: StereoFusion | None = None) -> SimpleNamespace:
    """What the 3D scene reads of the console's FusionPipeline: the simulated head's rig,
    a real StereoFusion with the :func:`ramp_distance` depth (or ``fusion``) and the
    :func:`synthetic_set` frames."""
    if fusion is None:
        fusion = StereoFusion(default_rig())
        fusion.update_depth(ramp_distance(fusion.rig))
    rig = fusion.rig
    fusion.span_k = None
    return SimpleNamespace(
        rig=rig,
        fusion=fusion,
        tof="tof",
        latest_set=synthetic_set(rig, ramp_distance(rig)),
        settings=DisplaySettings(span_k=SPAN_K, palette="iron"),
        radiometry={"thermal_left": Radiometry(), "thermal_right": Radiometry()},
    )


def scene_context(pipeline: SimpleNamespace, **kwargs: object) -> ConsoleContext:
    """A Viser server on a free loopback port and the console context of ``pipeline``
    around it (no source, no stream, a 9 x 6 board never seen); ``kwargs`` add to it."""
    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    return ConsoleContext(
        server=server,
        source=None,  # type: ignore[arg-type]
        description="test",
        hub=None,  # type: ignore[arg-type]
        pipeline=pipeline,  # type: ignore[arg-type]
        board=Board(9, 6, 0.04),
        board_watch=SimpleNamespace(  # type: ignore[arg-type]
            latest=None, latest_pose=None, pose_listeners=[], enabled=True
        ),
        **kwargs,  # type: ignore[arg-type]
    )
