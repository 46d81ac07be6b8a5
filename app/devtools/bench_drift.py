"""Benchmark ``drift``: issue 34's targets for drift found without a board
(:mod:`fusion.drift`), on the simulator's inspection and survey scenarios:
``trifuse bench --only drift``.

The console measures an instant at most every :data:`PERIOD_S` and within
:data:`CPU_SHARE` of a core (``app.server.runtime.drift_watch``): after a measure of ``c``
seconds the next waits ``c / CPU_SHARE``. The benchmark times the measure here (median CPU
seconds, the fusion's own BLAS/OpenCV threads as the console has them), takes the period the
console would then keep, ``max(PERIOD_S, c / CPU_SHARE)``, and feeds the check the
scenario's frames at that period (every sensor rendered at the same instant: the console's
synchronous sets):

* ``<scenario>_<axis>_flagged_s``: with thermal_left turned 0.3 degrees about its x, y or
  z axis, the first time (seconds of data) it is ``drifted``; inf if never within 60 s
  (target: within 60 s);
* ``<scenario>_<axis>_refined_err_deg``: the angle between the refined rig's thermal_left
  and the truth after 60 s, in its rotation to the TOF (target: within 0.1 degrees);
* ``<scenario>_tof_<axis>_flagged_s`` and ``<scenario>_tof_<axis>_refined_err_deg``: the
  same with the TOF turned (its rotation to ccd_left);
* ``<scenario>_false_drifted``: verdicts ``drifted`` of any sensor over ten minutes with the
  true rig (target: 0);
* ``measure_cpu_ms`` (median) and ``cpu_share``: the measure's CPU over the period it keeps
  (target: at most 0.10 while the console fuses; the watch's own rule).
"""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

from trifuse.app.devtools.benchmark import benchmark

PERIOD_S = 2.0
CPU_SHARE = 0.10
TURN_DEG = 0.3
FLAG_WITHIN_S = 60.0
QUIET_S = 600.0
MOVED = (("thermal_left", "tof", ""), ("tof", "ccd_left", "tof_"))
"""The sensors turned: (name, the sensor its refined rotation is compared to, key prefix);
the TOF is the rig's reference, which a refined rig keeps at the origin."""


def _measure_cpu_s(check: Any, frames: dict, t_s: float) -> float:
    """CPU seconds of one measure (the check's own instant ``t_s``)."""
    c0 = time.process_time()
    check.measure(t_s, frames)
    return time.process_time() - c0


@benchmark(
    "drift",
    "drift without a board: a thermal imager or the TOF turned 0.3 deg flagged (s) and "
    "refined (deg) on the inspection and survey scenarios; false verdicts over 10 min; the "
    "check's CPU",
    default_repeat=1,
)
def drift(repeat: int) -> dict[str, float]:
    """See the module docstring; ``repeat`` is not used (one pass is minutes of rendering)."""
    from trifuse.app.sources.sim.drift import SensorDrift, moved_rig
    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.app.sources.sim.survey import SurveyScenario
    from trifuse.calib.transforms import rotation_angle_deg
    from trifuse.fusion.drift import DriftCheck, refined_rig

    del repeat
    out: dict[str, float] = {}
    cpu: list[float] = []
    scenarios = {"inspection": InspectionScenario, "survey": SurveyScenario}
    period = PERIOD_S
    for name, cls in scenarios.items():
        true_scenario = cls(live=True, seed=11)
        rig = true_scenario.rig
        for sensor, anchor, prefix in MOVED:
            for axis, k in (("x", 0), ("y", 1), ("z", 2)):
                turn = tuple(TURN_DEG if i == k else 0.0 for i in range(3))
                moved = SensorDrift(sensor, turn)  # type: ignore[arg-type]
                truth = moved_rig(rig, moved)
                scenario = cls(live=True, seed=11, drift=moved)
                check = DriftCheck(rig)
                flagged = math.inf
                t = 0.25
                while t <= FLAG_WITHIN_S:
                    fs, _ = scenario.render(t)
                    cost = _measure_cpu_s(check, fs.frames, t)
                    cpu.append(cost)
                    period = max(PERIOD_S, statistics.median(cpu) / CPU_SHARE)
                    if math.isinf(flagged) and sensor in check.report().drifted:
                        flagged = t
                    t += period
                report = check.report()
                key = f"{name}_{prefix}{axis}"
                out[f"{key}_flagged_s"] = flagged
                try:
                    refined = refined_rig(rig, report)
                    R = refined.T(anchor, sensor)[:3, :3]
                    R_true = truth.T(anchor, sensor)[:3, :3]
                    out[f"{key}_refined_err_deg"] = rotation_angle_deg(R.T @ R_true)
                except ValueError:
                    out[f"{key}_refined_err_deg"] = math.nan
        check = DriftCheck(rig)
        false = 0
        t = 0.25
        while t <= QUIET_S:
            fs, _ = true_scenario.render(t)
            cpu.append(_measure_cpu_s(check, fs.frames, t))
            false += len(check.report().drifted)
            t += period
        out[f"{name}_false_drifted"] = float(false)
    median = statistics.median(cpu)
    out["measure_cpu_ms"] = 1000.0 * median
    out["period_s"] = period
    out["cpu_share"] = median / max(PERIOD_S, median / CPU_SHARE)
    out["measures"] = float(len(cpu))
    return out
