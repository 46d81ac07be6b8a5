"""Recording the simulated head (``trifuse record --source sim``) without a real-time source.

The inspection scenario is rendered at each sensor group's own rate (colour 30 Hz,
thermal 27 Hz, TOF 15 Hz, all starting at t = 0), each distinct instant once, with only
the sensors due then: rendering is far slower than real time (seconds per colour frame on
two cores), so the recording's time stamps, not the wall clock, carry the rates.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from app.recording.writer import RecordingWriter
from calib.rig import Rig

SIM_RATES_HZ = {"color": 30, "thermal": 27, "tof": 15}
"""Frame rates of the simulated head per modality."""


def sim_schedule(rig: Rig, duration_s: float) -> list[tuple[int, list[str]]]:
    """(stamp_ns, sensors due) for every distinct instant in [0, duration_s), in time order.

    Stamps are integer nanoseconds ``k * 10**9 // rate`` so that instants shared by two
    rates (colour and TOF every 1/15 s, colour and thermal every 1/3 s) coincide exactly.
    """
    if not duration_s > 0:
        raise ValueError(f"duration: expected a positive number of seconds, got {duration_s}")
    end_ns = round(duration_s * 1e9)
    due: dict[int, list[str]] = {}
    for name, sensor in rig.sensors.items():
        rate = SIM_RATES_HZ[sensor.modality]
        k = 0
        while (stamp := k * 1_000_000_000 // rate) < end_ns:
            due.setdefault(stamp, []).append(name)
            k += 1
    return sorted(due.items())


def head_model_for(rig: Rig):  # -> HeadModel | None
    """The simulator's default sensor physics, with the TOF range-error model sized to the
    rig's TOF camera (the default model is made for 176 x 144 pixels); None if it is."""
    from dataclasses import replace

    from app.sources.sim.render import HeadModel

    tofs = rig.by_modality("tof")
    model = HeadModel()
    if not tofs:
        return None
    w, h = rig[tofs[0]].image_size
    if (model.range_error.width, model.range_error.height) == (w, h):
        return None
    return replace(model, range_error=replace(model.range_error, width=w, height=h))


def record_simulation(
    out: str | Path,
    rig: Rig,
    duration_s: float,
    *,
    seed: int = 0,
    jpeg_quality: int = 90,
    progress: Callable[[int, int, int, list[str], float], None] | None = None,
) -> RecordingWriter:
    """Render the inspection scenario per :func:`sim_schedule` and record it at ``out``.

    ``progress(i, n, stamp_ns, sensors, seconds)`` is called after each rendered instant.
    Returns the closed writer (its counters say what was written). A KeyboardInterrupt
    keeps what was recorded so far (the file is finished and named) and propagates.
    """
    from app.sources.sim.scenarios import InspectionScenario

    schedule = sim_schedule(rig, duration_s)
    scenario = InspectionScenario(rig=rig, model=head_model_for(rig), seed=seed)
    with RecordingWriter(out, rig, jpeg_quality=jpeg_quality) as writer:
        for i, (stamp, sensors) in enumerate(schedule, start=1):
            t0 = time.perf_counter()
            frames, _truth = scenario.render(stamp / 1e9, sensors)
            for name in sensors:
                frame = frames[name]
                if frame.stamp_ns != stamp:
                    raise RuntimeError(
                        f"simulator stamped {name} {frame.stamp_ns} ns, expected {stamp} ns"
                    )
                writer.write(frame)
            if progress is not None:
                progress(i, len(schedule), stamp, sensors, time.perf_counter() - t0)
    return writer
