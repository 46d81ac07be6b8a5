"""Benchmarks of the simulated head: ``render`` (frame sets of the accurate renderer) and
``sim-live`` (the live quality the console and ``trifuse record --source sim`` use)."""

from __future__ import annotations

import time
from pathlib import Path

from trifuse.app.devtools.benchmark import benchmark, median_ms


@benchmark(
    "render",
    "simulator: five-sensor frame sets (calibration view, inspection frame, per sensor) (ms)",
    default_repeat=5,
)
def render(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` renders of the simulated head.

    ``calibration_view_ms``: one view in a stream of ``calibration_views`` (what
    ``trifuse simulate calibration`` pays per view, without writing the PNGs);
    ``inspection_frame_ms``: one five-sensor frame set of the inspection room;
    ``<sensor>_ms``: one sensor of that room alone; ``setup_ms``: a new renderer's first
    frame set (ray grids of all sensors, with undistortion, are built then).
    """
    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.app.sources.sim.scenarios import calibration_views

    stream = calibration_views(repeat + 1, seed=1000)
    figures = {"calibration_view_ms": median_ms(lambda _i: next(stream), repeat)}
    scenario = InspectionScenario(seed=0)
    figures["inspection_frame_ms"] = median_ms(lambda i: scenario.render(0.1 * i), repeat)
    for name in scenario.rig.names:
        figures[f"{name}_ms"] = median_ms(lambda i, n=name: scenario.render(0.1 * i, [n]), repeat)
    figures["setup_ms"] = median_ms(lambda i: InspectionScenario(seed=0).render(0.0), repeat)
    return figures


_LIVE_SENSORS = ("ccd_left", "thermal_left", "tof")
"""The sensors ``sim-live`` times one by one: a colour camera, a thermal imager, the TOF."""


@benchmark(
    "sim-live",
    "simulated head: the live quality against the accurate one per image and per pose, one "
    "frame from a live render, and a 3 s `trifuse record --source sim` against 3 s of real "
    "time",
    baselines=(
        *((f"live_{what}_ms", f"accurate_{what}_ms") for what in (*_LIVE_SENSORS, "pose")),
        ("record_s", "recorded_s"),
    ),
    default_repeat=5,
)
def sim_live(repeat: int) -> dict[str, float]:
    """Medians over ``repeat`` renders of the inspection room at distinct moments (warm:
    ray grids built), the accurate quality (``InspectionScenario``) against the live one
    (``live=True``), frames with noise included: ``<sensor>_ms`` one sensor,
    ``pose_ms`` all five. ``frame_<sensor>_ms``: one frame from a live render with a margin,
    turned by 0.2 degrees, with fresh noise (what the recording pays per frame besides
    encoding). ``record_s``: one ``record_simulation`` of ``recorded_s`` = 3 s in the
    default (live) mode, wall time, new scenario included; the ratio is "x real time".
    """
    import tempfile

    import numpy as np

    from trifuse.app.recording.simrecord import record_simulation
    from trifuse.app.sources.sim.inspection import InspectionScenario

    sensors = _LIVE_SENSORS
    figures: dict[str, float] = {}
    for label, live in (("accurate", False), ("live", True)):
        scenario = InspectionScenario(seed=0, live=live)
        scenario.render(0.0)
        for name in sensors:
            figures[f"{label}_{name}_ms"] = median_ms(
                lambda i, n=name, s=scenario: s.render(1.0 + 0.37 * i, [n]), repeat
            )
        figures[f"{label}_pose_ms"] = median_ms(
            lambda i, s=scenario: s.render(2.0 + 0.41 * i), repeat
        )
    assert scenario.developer is not None
    dev = scenario.developer
    rng = np.random.default_rng(0)
    margins = dict.fromkeys(sensors, 15)
    clean = scenario.render_clean(5.0, list(sensors), margins)
    T = scenario.T_world_rig(5.07)  # 0.2 degrees on
    for name in sensors:
        T_sensor = T @ scenario.rig[name].T_rig_sensor
        figures[f"frame_{name}_ms"] = median_ms(
            lambda _i, n=name, Ts=T_sensor: dev.frame(clean[n], 0, rng, Ts), max(repeat, 20)
        )
    from trifuse.app.sources.sim.head import default_rig

    with tempfile.TemporaryDirectory(prefix="trifuse-bench-simrec-") as tmp:
        t0 = time.perf_counter()
        record_simulation(Path(tmp) / "sim.mcap", default_rig(), 3.0)
        figures["record_s"] = time.perf_counter() - t0
    figures["recorded_s"] = 3.0
    return figures
