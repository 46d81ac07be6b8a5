"""Benchmark ``registration``: what the registration uncertainty (fusion.registration)
costs, against the depth mapping it follows: ``trifuse bench --only registration``."""

from __future__ import annotations

import statistics
import time
from typing import Any

from trifuse.app.devtools.benchmark import benchmark

CONSOLE_CELLS = 3000
"""Cells the console evaluates per eye and update (its stride is chosen for at most this)."""


def _covariance(rig: Any) -> Any:
    """A full joint covariance over every sensor's pose (but the reference's) and
    intrinsics with 5 distortion coefficients, as ``trifuse calibrate`` writes (seeded; the
    cost depends on the parameters' count, not their values)."""
    import numpy as np

    from trifuse.calib.parameter_covariance import (
        DISTORTION_PARAMETERS,
        INTRINSIC_PARAMETERS,
        POSE_PARAMETERS,
        ParameterCovariance,
    )

    names = [f"{s}.{p}" for s in rig.names if s != rig.reference for p in POSE_PARAMETERS]
    names += [
        f"{s}.{p}" for s in rig.names for p in INTRINSIC_PARAMETERS + DISTORTION_PARAMETERS[:5]
    ]
    A = np.random.default_rng(0).standard_normal((len(names), len(names)))
    scale = np.array([1e-3 if n.split(".")[1] in POSE_PARAMETERS else 1e-2 for n in names])
    return ParameterCovariance.from_matrix(names, (A @ A.T) * np.outer(scale, scale) / len(names))


@benchmark(
    "registration",
    "registration sigma of one eye (console: about 3000 cells; full coarse grid) and the "
    "Precision panel's curves, against one eye's depth mapping update (ms)",
    baselines=(("console_ms", "mapping_ms"), ("full_ms", "mapping_ms")),
    default_repeat=9,
)
def registration(repeat: int) -> dict[str, float]:
    """Median times on the inspection scene's TOF frame, the simulated head's rig with a
    full covariance (:func:`_covariance`), left eye.

    ``mapping_ms``: :meth:`fusion.mapping.ViewMapping.update` (the work of every TOF frame,
    the baseline); ``console_ms``: :func:`fusion.registration.registration_sigma` with the
    stride the console uses (at most :data:`CONSOLE_CELLS` cells); ``full_ms``: every coarse
    cell; ``panel_ms``: :func:`fusion.registration.sigma_vs_distance` for both eyes as the
    Precision panel computes it. ``cells``: the console's cells.
    """
    import numpy as np

    from trifuse.app.server.panels.precision import (
        REGISTRATION_CELL_PX,
        REGISTRATION_DISTANCES_M,
    )
    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.fusion.mapping import ViewMapping
    from trifuse.fusion.registration import range_error, registration_sigma, sigma_vs_distance

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    cov = _covariance(rig)
    eye = rig.eyes["left"]
    tof = rig.by_modality("tof")[0]
    err = range_error(rig, tof)
    distance = frames[tof].distance_m
    mapping = ViewMapping(rig, eye.color, eye.thermal)
    mapping.update(distance)
    z, ok, _ = mapping.coarse_cells()
    scale = mapping.options.scale
    stride = max(1, int(np.ceil(np.sqrt(ok.sum() / CONSOLE_CELLS))))

    def timed(fn: Any) -> float:
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return 1000.0 * statistics.median(times)

    def sigma(s: int) -> Any:
        return registration_sigma(rig, cov, eye.color, eye.thermal, tof, z, ok, scale, err, s)

    with_cov = rig.__class__(rig.sensors, rig.reference, rig.eyes, cov)
    out = {
        "mapping_ms": timed(lambda: mapping.update(distance)),
        "console_ms": timed(lambda: sigma(stride)),
        "full_ms": timed(lambda: sigma(1)),
        "panel_ms": timed(
            lambda: [
                sigma_vs_distance(
                    with_cov,
                    e.color,
                    e.thermal,
                    tof,
                    REGISTRATION_DISTANCES_M,
                    err,
                    REGISTRATION_CELL_PX,
                )
                for e in rig.eyes.values()
            ]
        ),
        "cells": float(sigma(stride).summary()["cells"]),
    }
    return out
