"""Recording the simulated head (``trifuse record --source sim``) without a real-time source.

Time stamps follow each sensor group's own rate (colour 30 Hz, thermal 27 Hz, TOF 15 Hz,
all starting at t = 0; :func:`sim_schedule`), each distinct instant once with only the
sensors due then, so the recording's stamps, not the wall clock, carry the rates. What is
rendered depends on the mode:

* default (live): the scenario (:data:`SIM_SCENARIOS`: the inspection room, or the survey
  of :mod:`app.sources.sim.survey`) in the live quality
  (:class:`~app.sources.sim.render.Renderer` ``live=True``: no edge supersampling) at
  :data:`POSE_HZ` head poses per second, each sensor's picture rendered once per pose with
  a margin; every frame is that picture turned to the head's orientation at the frame's
  own time stamp, with fresh sensor noise (:class:`~app.sources.sim.live.LiveDeveloper`).
  The head moves smoothly at every sensor's rate; 3 s take about 10 s of CPU.
* ``exact``: every instant rendered at its own time in the accurate quality (edge
  supersampling, the accurate sensor model), about 130x slower than real time.

A sensor drift (``drift``, :class:`~app.sources.sim.drift.SensorDrift`) moves one sensor
from its ``at_s`` on: every frame from that instant on is rendered from the moved pose (in
the live mode a render is reused only within one drift state: the instant that crosses
``at_s`` renders its pose again with the sensor moved). The recording's rig (``rig.yaml``,
the sensors' ``/tf``) stays the rig as calibrated; the metadata record
``trifuse.simulation`` (:func:`simulation_metadata`) names the scenario and the drift and
gives the moved sensor's true pose, so that a drift checker can check itself.

Every instant also gets the head's pose, ``T_world_rig`` on ``/tf``
(:meth:`~app.recording.writer.RecordingWriter.write_pose`): the pose the instant's frames
show (:func:`shown_pose`). In the exact mode that is the scenario's pose at the instant; in
the live mode a picture is turned, not moved, so it shows the instant's orientation from
the position of the rendered pose (the same for the inspection room, whose head only
turns; up to 4 cm apart at 5 Hz while the survey's robot drives).

:func:`plan_simulation` says beforehand what will be rendered and estimates the time from
costs measured on the reference machine; :func:`record_simulation` reports progress with
an estimate of the time left, refined from the time the work done so far took.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from trifuse.app.recording.recording import Recording
from trifuse.calib.rig import Rig

if TYPE_CHECKING:
    from trifuse.app.sources.frames import Frame
    from trifuse.app.sources.sim.drift import SensorDrift
    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.app.sources.sim.live import CleanImage

SIM_SCENARIOS = ("inspection", "survey")
"""The scenarios :func:`record_simulation` renders: the panning inspection room, or its
survey (:class:`~app.sources.sim.survey.SurveyScenario`: pan and tilt, then a drive)."""
SIM_RATES_HZ = {"color": 30, "thermal": 27, "tof": 15}
"""Frame rates of the simulated head per modality."""
POSE_HZ = 5.0
"""Head poses rendered per simulated second in the default (live) mode."""

# Costs on the reference machine (2 cores, otherwise quiet), seconds of CPU per megapixel of
# the sensor's image: a live render (with its clean picture), one frame from it (turn,
# noise, encoding, writing), an accurate render with its frame, and a sensor's ray grid
# (its first render: a live one undistorts a colour camera's rays on a coarse grid).
# Measured with `trifuse record --source sim` and app/devtools/bench_sim.py's `render`.
_LIVE_RENDER_S_PER_MPX = {"color": 0.13, "thermal": 0.12, "tof": 0.5}
_LIVE_FRAME_S_PER_MPX = {"color": 0.022, "thermal": 0.03, "tof": 0.12}
_EXACT_S_PER_MPX = {"color": 0.6, "thermal": 1.2, "tof": 0.8}
_SETUP_S_PER_MPX = {"live": {"color": 0.12, "thermal": 0.3, "tof": 0.3}}
_SETUP_S_PER_MPX["exact"] = {"color": 1.0, "thermal": 0.3, "tof": 0.3}
_START_S = 1.5  # imports, the scenario, the writer


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

    from trifuse.app.sources.sim.render import HeadModel

    tofs = rig.by_modality("tof")
    model = HeadModel()
    if not tofs:
        return None
    w, h = rig[tofs[0]].image_size
    if (model.range_error.width, model.range_error.height) == (w, h):
        return None
    return replace(model, range_error=replace(model.range_error, width=w, height=h))


def sim_scenario(
    name: str, rig: Rig, seed: int = 0, live: bool = True, drift: SensorDrift | None = None
) -> InspectionScenario:
    """The scenario ``name`` (one of :data:`SIM_SCENARIOS`) with ``rig``'s sensors
    (:func:`head_model_for`), noise seeded by ``seed``, in the live quality or not, with
    one sensor moving during the run (``drift``) or none. ValueError for an unknown name
    or a drift of a sensor the rig does not have."""
    from trifuse.app.sources.sim.inspection import InspectionScenario
    from trifuse.app.sources.sim.survey import SurveyScenario

    kinds = {"inspection": InspectionScenario, "survey": SurveyScenario}
    if name not in kinds:
        raise ValueError(f"scenario: expected one of {', '.join(SIM_SCENARIOS)}, got {name!r}")
    return kinds[name](rig=rig, model=head_model_for(rig), seed=seed, live=live, drift=drift)


def shown_pose(scenario: InspectionScenario, stamp_ns: int, pose_hz: float | None) -> np.ndarray:
    """(4, 4) ``T_world_rig`` that the frames of the instant ``stamp_ns`` show.

    Args:
        scenario: the scenario rendered.
        stamp_ns: the instant, nanoseconds of scenario time.
        pose_hz: the live mode's rate of rendered poses, or None (exact mode: every instant
            rendered at its own pose).

    Returns:
        Exact mode: the scenario's pose at the instant. Live mode: its rotation at the
        instant with the translation of the rendered pose (:func:`pose_index`) the frames
        are turned from (turning a picture cannot move it).
    """
    T = np.array(scenario.T_world_rig(stamp_ns / 1e9), dtype=np.float64)
    if pose_hz is not None:
        T[:3, 3] = scenario.T_world_rig(pose_index(stamp_ns, pose_hz) / pose_hz)[:3, 3]
    return T


def pose_index(stamp_ns: int, pose_hz: float) -> int:
    """The head pose (``k``: time ``k / pose_hz``) whose render a frame at ``stamp_ns``
    reuses in the live mode: the nearest one."""
    return round(stamp_ns * pose_hz / 1e9)


def render_key(
    stamp_ns: int, pose_hz: float, sensor: str, drift: SensorDrift | None = None
) -> tuple[int, bool]:
    """Which live render ``sensor``'s frame at ``stamp_ns`` reuses: the head pose
    (:func:`pose_index`) and whether it is the drifted sensor with the drift active at the
    frame's own time (a render is never reused across the drift's start)."""
    moved = drift is not None and drift.sensor == sensor and drift.active(stamp_ns / 1e9)
    return pose_index(stamp_ns, pose_hz), moved


@dataclass(frozen=True)
class SimRecordPlan:
    """What a simulated recording renders, and how long it should take.

    Attributes:
        schedule: (stamp_ns, sensors due) per instant (:func:`sim_schedule`).
        exact: every instant rendered accurately (else live, poses at ``pose_hz``).
        pose_hz: head poses rendered per simulated second (live), None when exact.
        renders: images rendered in all (every sensor's, every pose or instant).
        costs_s: estimated seconds of each instant on the reference machine (its renders,
            a sensor's first render with its ray grid, and its frames).
        drift: the sensor that moves during the recording, or None.
    """

    schedule: list[tuple[int, list[str]]]
    exact: bool
    pose_hz: float | None
    renders: int
    costs_s: list[float]
    drift: SensorDrift | None = None

    @property
    def frames(self) -> int:
        """Frames the recording will hold."""
        return sum(len(sensors) for _, sensors in self.schedule)

    @property
    def poses(self) -> int:
        """Distinct head poses rendered (live; the drifted sensor's pose at the drift's start
        counts again) or instants (exact)."""
        if self.pose_hz is None:
            return len(self.schedule)
        sensor = "" if self.drift is None else self.drift.sensor
        return len(
            {render_key(stamp, self.pose_hz, sensor, self.drift) for stamp, _ in self.schedule}
        )

    @property
    def estimate_s(self) -> float:
        """Estimated seconds for the whole recording on the reference machine."""
        return float(sum(self.costs_s))


def plan_simulation(
    rig: Rig,
    duration_s: float,
    *,
    exact: bool = False,
    pose_hz: float = POSE_HZ,
    drift: SensorDrift | None = None,
) -> SimRecordPlan:
    """The plan of :func:`record_simulation` with the same arguments."""
    if not exact and not (math.isfinite(pose_hz) and pose_hz > 0):
        raise ValueError(f"pose rate: expected a positive number of Hz, got {pose_hz}")
    schedule = sim_schedule(rig, duration_s)
    mpx = {n: rig[n].image_size[0] * rig[n].image_size[1] / 1e6 for n in rig.names}
    modality = {n: rig[n].modality for n in rig.names}
    rendered: dict[str, object] = {}
    costs: list[float] = []
    renders = 0
    for stamp, sensors in schedule:
        cost = 0.0 if costs else _START_S
        for name in sensors:
            mod, size = modality[name], mpx[name]
            if name not in rendered:
                cost += _SETUP_S_PER_MPX["exact" if exact else "live"][mod] * size
            if exact:
                cost += _EXACT_S_PER_MPX[mod] * size
                renders += 1
                rendered[name] = stamp
                continue
            k = render_key(stamp, pose_hz, name, drift)
            if rendered.get(name) != k:
                cost += _LIVE_RENDER_S_PER_MPX[mod] * size
                renders += 1
                rendered[name] = k
            cost += _LIVE_FRAME_S_PER_MPX[mod] * size
        costs.append(cost)
    rate = None if exact else float(pose_hz)
    return SimRecordPlan(schedule, exact, rate, renders, costs, drift)


@dataclass(frozen=True)
class SimProgress:
    """Progress of :func:`record_simulation` after one instant.

    Attributes:
        index: instants done (1-based), of ``total``.
        stamp_ns: the instant's time stamp; ``sensors``: the sensors recorded at it.
        seconds: wall seconds the instant took; ``elapsed_s``: since the recording began.
        eta_s: estimated seconds left: the plan's costs of the instants left, scaled by
            how long the instants done took against their planned costs.
    """

    index: int
    total: int
    stamp_ns: int
    sensors: list[str]
    seconds: float
    elapsed_s: float
    eta_s: float


def _margin_px(rig: Rig, name: str, turn_rad: float) -> int:
    """Pixels a picture needs beyond the image to be turned by up to ``turn_rad``: the
    shift at the image centre, 30 % more for the edges (perspective, distortion), plus 2."""
    intr = rig[name].intrinsics
    return min(64, math.ceil(1.3 * max(intr.fx, intr.fy) * math.tan(turn_rad)) + 2)


def record_simulation(
    out: str | Path,
    rig: Rig,
    duration_s: float,
    *,
    seed: int = 0,
    jpeg_quality: int = 90,
    exact: bool = False,
    pose_hz: float = POSE_HZ,
    progress: Callable[[SimProgress], None] | None = None,
    plan: SimRecordPlan | None = None,
    opened: Callable[[Recording], None] | None = None,
    scenario: str = "inspection",
    drift: SensorDrift | None = None,
) -> Recording:
    """Render the ``scenario`` (:data:`SIM_SCENARIOS`) per :func:`plan_simulation` and
    record it at ``out``, with the head's pose per instant (:func:`shown_pose`).

    Live (default): each sensor's picture of the head pose nearest each instant
    (:func:`pose_index`) is rendered once, with a margin, and every frame is that picture
    turned to the instant's head orientation with fresh noise (seeded by ``seed`` and the
    instant). ``exact``: every instant rendered accurately. ``drift``: one sensor moves
    from ``drift.at_s`` on (module docstring). ``plan``: the plan made beforehand (made
    here otherwise; with the same ``drift``). ``opened(writer)`` is called once the file is open
    (its ``temp_path`` is where the frames go until it is finished), ``progress(SimProgress)``
    after each instant. Returns the finished recording (its counters say what was written). A
    KeyboardInterrupt keeps what was recorded so far (the file is finished and named) and
    propagates.
    """
    plan = plan or plan_simulation(rig, duration_s, exact=exact, pose_hz=pose_hz, drift=drift)
    if plan.drift != drift:
        raise ValueError(f"plan: made for the drift {plan.drift}, not {drift}")
    live = not plan.exact
    sim = sim_scenario(scenario, rig, seed, live, drift)
    metadata = {SIMULATION_METADATA: simulation_metadata(scenario, seed, plan, rig)}
    margins: dict[str, int] = {}
    if live:
        assert plan.pose_hz is not None
        turn = sim.max_turn_rad(0.5 / plan.pose_hz)
        margins = {name: _margin_px(rig, name, turn) for name in rig.names}
    cleans: dict[str, tuple[tuple[int, bool], CleanImage]] = {}
    total_cost = plan.estimate_s
    done_cost = 0.0
    t_start = time.perf_counter()
    with Recording(rig, path=Path(out), jpeg_quality=jpeg_quality, metadata=metadata) as writer:
        if opened is not None:
            opened(writer)
        for i, ((stamp, sensors), cost) in enumerate(
            zip(plan.schedule, plan.costs_s, strict=True), start=1
        ):
            t0 = time.perf_counter()
            if live:
                frames = _live_frames(sim, rig, stamp, sensors, plan, margins, cleans, seed)
            else:
                frames = sim.render(stamp / 1e9, sensors)[0].frames
            writer.write_pose(stamp, shown_pose(sim, stamp, plan.pose_hz))
            for name in sensors:
                frame = frames[name]
                if frame.stamp_ns != stamp:
                    raise RuntimeError(
                        f"simulator stamped {name} {frame.stamp_ns} ns, expected {stamp} ns"
                    )
                writer.write(frame)
            done_cost += cost
            if progress is not None:
                now = time.perf_counter()
                elapsed = now - t_start
                eta = (total_cost - done_cost) * (elapsed / done_cost) if done_cost > 0 else 0.0
                progress(
                    SimProgress(i, len(plan.schedule), stamp, list(sensors), now - t0, elapsed, eta)
                )
    return writer


def _live_frames(
    scenario: InspectionScenario,
    rig: Rig,
    stamp: int,
    sensors: list[str],
    plan: SimRecordPlan,
    margins: dict[str, int],
    cleans: dict[str, tuple[tuple[int, bool], CleanImage]],
    seed: int,
) -> dict[str, Frame]:
    """The frames of one instant in the live mode (see :func:`record_simulation`);
    ``cleans`` holds each sensor's latest picture (:func:`render_key`, picture). A sensor
    is rendered and turned in the drift state of the instant (its pose in
    ``scenario.rig_at``), whatever the state at the rendered pose's time."""
    assert plan.pose_hz is not None and scenario.developer is not None
    t_s = stamp / 1e9
    T_world_rig = scenario.T_world_rig(t_s)
    rig_now = scenario.rig_at(t_s)
    drifted = scenario.drift_active(t_s)
    rng = np.random.default_rng([seed, 3, stamp])
    frames = {}
    for name in sensors:
        key = render_key(stamp, plan.pose_hz, name, plan.drift)
        have = cleans.get(name)
        if have is None or have[0] != key:
            k = key[0]
            clean = scenario.render_clean(k / plan.pose_hz, [name], margins, drifted=drifted)
            cleans[name] = have = (key, clean[name])
        T_world_sensor = T_world_rig @ rig_now[name].T_rig_sensor
        frames[name] = scenario.developer.frame(have[1], stamp, rng, T_world_sensor)
    return frames


SIMULATION_METADATA = "trifuse.simulation"
"""Name of the metadata record of a simulated recording (:func:`simulation_metadata`)."""


def simulation_metadata(scenario: str, seed: int, plan: SimRecordPlan, rig: Rig) -> dict[str, str]:
    """The ``trifuse.simulation`` metadata of a simulated recording (docs/FORMATS.md):
    ``scenario``, ``seed``, ``mode`` (``live`` or ``exact``), ``pose_hz`` (live); with a
    drift also ``drift`` (its command-line spelling, :func:`~app.sources.sim.drift.parse_drift`
    reads it) and ``drift_T_rig_sensor``: the moved sensor's true pose ``T_rig_sensor``
    from the drift's start on, 16 comma-separated numbers in row order (metres)."""
    meta = {"scenario": scenario, "seed": str(seed), "mode": "exact" if plan.exact else "live"}
    if plan.pose_hz is not None:
        meta["pose_hz"] = repr(plan.pose_hz)
    if plan.drift is not None:
        from trifuse.app.sources.sim.drift import moved_rig

        T = moved_rig(rig, plan.drift)[plan.drift.sensor].T_rig_sensor
        meta["drift"] = str(plan.drift)
        meta["drift_T_rig_sensor"] = ",".join(repr(float(x)) for x in np.ravel(T))
    return meta
