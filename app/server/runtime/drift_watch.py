"""Calibration drift of the live head, checked in the background (issue 34 item 3).

Whether each sensor still sits where the rig in use says (:mod:`fusion.drift`: each pair of
cameras compared through the TOF depth, the TOF's depth edges against the colour cameras, a
verdict per sensor over the last 60 s) is checked on the live frame sets by
:class:`DriftWatch`, at most every :data:`PERIOD_S` and within :data:`CPU_SHARE` of a core,
while the fusion is wanted (:mod:`app.server.runtime.demand`):

1. in the fusion thread (a set listener of :class:`~app.server.runtime.pipeline.
   FusionPipeline`), a frame set is taken when a check is due (and none is under way: a
   measure may take longer than the period) and the set is usable: a
   frame of every camera (colour and thermal) and the TOF with its depth, their stamps
   within 12 ms of each other (:func:`fusion.drift.synchronous`: frames taken apart while
   the head turns would read as drift), not the set measured last (a paused replay). Its
   frames are handed on (a writeable array is copied: a source may refill it);
2. in the worker thread ``drift-check`` (a :class:`~app.latest_worker.LatestWorker`
   keeping the newest job), :meth:`fusion.drift.DriftCheck.measure` on them (about
   0.15-0.35 s of a core on the simulated head, 0.5-1.4 s on a busy 2-core machine) at the
   watch's clock, then :meth:`~fusion.drift.DriftCheck.report`. A measure that took ``t``
   seconds holds the next one back ``t / CPU_SHARE``.

The newest report is kept (:meth:`DriftWatch.status`, ``GET /api/status`` ``drift``; the
Calibration panel's and the viewer's health line and alert: :func:`health_summary`,
:func:`alerts`). A rig put in use (``pipeline.set_rig``) gets a new
:class:`~fusion.drift.DriftCheck`: the old rig's report is dropped, and a measure under way
for it is discarded. :meth:`DriftWatch.refine` corrects the drifted sensors
(:func:`fusion.drift.refined_rig`), saves the result as the session's next rig version,
puts it in use and starts the check again. A failure is worded
(:func:`app.errors.describe_error`) in :attr:`DriftWatch.error` and counted; the next
measure is tried as usual.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.set_watch import SetWatch
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.workflows.calib_session import RigVersion
from trifuse.calib.rig import Rig
from trifuse.fusion.drift import (
    DRIFT_DEG,
    MAX_SPREAD_S,
    REFUSE_DEG,
    DriftCheck,
    DriftReport,
    SensorCheck,
    refined_rig,
    synchronous,
)
from trifuse.fusion.geometry import tof_sensor_name

PERIOD_S = 2.0
"""Shortest time between two measures, seconds."""
CPU_SHARE = 0.10
"""The share of one core the measures may take: after a measure that took ``t`` seconds
the next one waits at least ``t / CPU_SHARE`` (0.15-0.35 s on the simulated head: one
measure every 2-4 s; 0.5-1.4 s beside a busy machine's other work: every 5-14 s)."""
SHARE_WINDOW_S = 60.0
"""The measured share of a core (``cpu_share`` in the status) is over the measures that
started in the last this many seconds."""
PROBLEMS_SHOWN = 3
"""The newest problems of the check the status lists."""


def _kept(frame: Frame) -> Frame:
    """``frame`` safe to hand to another thread: its writeable arrays copied (a source may
    refill them in place), read-only ones shared."""

    def own(a: np.ndarray | None) -> np.ndarray | None:
        return a if a is None or not a.flags.writeable else a.copy()

    return Frame(frame.sensor, frame.stamp_ns, own(frame.image), own(frame.distance_m))  # type: ignore[arg-type]


def checked_sensors(rig: Rig) -> tuple[list[str], str | None]:
    """The sensors a frame set must hold for a measure: every camera (colour and thermal)
    and the TOF, rig order; and the TOF's name (None: the rig has none, or several)."""
    try:
        tof: str | None = tof_sensor_name(rig)
    except (KeyError, ValueError):
        tof = None
    cameras = [n for n in rig.names if rig[n].modality in ("color", "thermal")]
    return cameras + ([tof] if tof is not None else []), tof


def unusable(rig: Rig, fs: FrameSet) -> str | None:
    """Why the frame set ``fs`` cannot be measured against ``rig`` (a sentence), or None
    when it can: a frame of every camera and the TOF, the TOF's depth, stamps within
    :data:`fusion.drift.MAX_SPREAD_S`."""
    needed, tof = checked_sensors(rig)
    if tof is None:
        return "the rig has no single TOF: the cameras are compared through its depth"
    missing = [n for n in needed if fs.frames.get(n) is None]
    if missing:
        return (
            f"waiting for a frame set with every camera and the TOF (missing: {', '.join(missing)})"
        )
    if fs.frames[tof].distance_m is None:
        return f"waiting for a frame set with the TOF's depth ({tof} brought none)"
    frames = {n: fs.frames[n] for n in needed}
    if not synchronous(frames):
        stamps = [f.stamp_ns for f in frames.values()]
        spread_ms = (max(stamps) - min(stamps)) / 1e6
        return (
            f"waiting for synchronous frames (the last set's spread {spread_ms:.0f} ms, at most "
            f"{MAX_SPREAD_S * 1e3:.0f} ms)"
        )
    return None


@dataclass(frozen=True, eq=False)
class _Job:
    """One measure to make: the rig it is for, the frame set's stamp (ns), the frames of
    :func:`checked_sensors` and the watch's generation when it was taken."""

    rig: Rig
    stamp_ns: int
    frames: dict[str, Frame]
    generation: int


@dataclass(frozen=True, eq=False)
class DriftState:
    """The newest report of the check of one rig.

    Attributes:
        report: the check's report after the newest measure.
        rig: the rig it checks (a new rig in use makes this one stale).
        computed_at_s: when the measure ended (the watch's clock, seconds).
        compute_s: how long the measure and report took, seconds.
    """

    report: DriftReport
    rig: Rig
    computed_at_s: float
    compute_s: float


@dataclass(frozen=True, eq=False)
class RefineResult:
    """What :meth:`DriftWatch.refine` did: the version saved, the refined rig now in use,
    and the checks of the sensors it corrected (their ``rotation_deg`` is the correction)."""

    version: RigVersion
    rig: Rig
    corrected: dict[str, SensorCheck]


def sensors_of(rig: Rig, report: DriftReport) -> dict[str, SensorCheck]:
    """The report's checks of the rig's sensors the check judges: the cameras (colour and
    thermal) and the TOF."""
    return {
        n: s
        for n, s in report.sensors.items()
        if n in rig.sensors and rig[n].modality in ("color", "thermal", "tof")
    }


def _sigma(s: SensorCheck) -> str:
    return "" if s.sigma_deg is None else f" (σ {max(s.sigma_deg):.2f}°)"


def health_summary(state: DriftState | None, waiting: str | None = None) -> str:
    """The calibration health in one line (without the ``calibration health:`` label the
    panel and the viewer put before it), e.g. ``thermal_left DRIFTED 0.31° (σ 0.01°);
    others ok``, ``ok: every sensor within 0.15° (24 instants)``, ``checking… (3 instants;
    ok: ccd_left)``, or why nothing is measured (``waiting``, when nothing is yet)."""
    if state is None:
        return f"not checked yet: {waiting}" if waiting else "checking… (0 instants)"
    report = state.report
    checked = sensors_of(state.rig, report)
    n = report.instants
    instants = f"{n} instant{'s' if n != 1 else ''}"
    by: dict[str, list[str]] = {}
    for name, s in checked.items():
        by.setdefault(s.verdict, []).append(name)
    drifted = by.get("drifted", [])
    if drifted:
        head = ", ".join(
            f"{name} DRIFTED {checked[name].angle_deg or 0.0:.2f}°{_sigma(checked[name])}"
            for name in drifted
        )
        others = [name for name in checked if name not in drifted]
        if not others:
            return head
        if all(checked[name].verdict == "ok" for name in others):
            return f"{head}; others ok"
        rest = "; ".join(f"{v}: {', '.join(by[v])}" for v in ("ok", "undecided") if v in by)
        return f"{head}; {rest}"
    if checked and len(by.get("ok", [])) == len(checked):
        return f"ok: every sensor within {DRIFT_DEG}° ({instants})"
    ok = by.get("ok", [])
    return f"checking… ({instants}{'; ok: ' + ', '.join(ok) if ok else ''})"


def alerts(state: DriftState | None) -> list[str]:
    """One alert per drifted sensor, e.g. ``⚠ thermal_left has turned 0.31° against the
    rig: refine or recalibrate`` (a turn beyond :data:`fusion.drift.REFUSE_DEG` is not
    refined: ``recalibrate with the board``)."""
    if state is None:
        return []
    out = []
    for name, s in sensors_of(state.rig, state.report).items():
        if s.verdict != "drifted":
            continue
        angle = s.angle_deg or 0.0
        what = (
            "refine or recalibrate"
            if angle <= REFUSE_DEG
            else f"recalibrate with the board (more than {REFUSE_DEG:g}° is not refined)"
        )
        out.append(f"⚠ {name} has turned {angle:.2f}° against the rig: {what}")
    return out


def sensor_status(s: SensorCheck) -> dict[str, Any]:
    """One sensor's block of the status: ``verdict``, ``rotation_deg`` [x, y, z] (its own
    axes), ``sigma_deg`` [x, y, z], ``angle_deg``, ``sigma_max_deg`` (degrees; null when not
    estimated), ``reason``, ``pairs`` (the sensors it was compared with)."""
    d = s.as_dict()
    return {
        k: d[k]
        for k in ("verdict", "rotation_deg", "sigma_deg", "angle_deg", "sigma_max_deg", "reason")
    } | {"pairs": d["pairs"]}


class DriftWatch(SetWatch[_Job]):
    """Checks the live head for calibration drift in the background (see the module doc).

    Args:
        pipeline: the console's fusion pipeline (its set listener is added here).
        period_s: shortest time between two measures, seconds.
        cpu_share: the share of one core the measures may take.
        clock: monotonic seconds (tests pass their own); also the check's time line.

    Attributes:
        error: the newest measure's failure (``"<type>: <message>"``), or None when it
            succeeded.
        error_count: failures so far.
        measures: measures made so far (every rig).
        waiting: why the newest frame set looked at when a measure was due was not taken
            (:func:`unusable`), or None.
        last_refine: what the newest :meth:`refine` did (``saved_as``, ``sensors``: name
            -> angle corrected, degrees; ``at_s``: the watch's clock), or None.
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        period_s: float = PERIOD_S,
        cpu_share: float = CPU_SHARE,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 0 < cpu_share <= 1:
            raise ValueError(f"cpu_share: expected a share of a core in (0, 1], got {cpu_share}")
        super().__init__(pipeline, "drift-check", self._compute)
        self.period_s, self.cpu_share, self.clock = period_s, cpu_share, clock
        self.measures = 0
        self.waiting: str | None = None
        self.last_refine: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self._refining = threading.Lock()
        self._state: DriftState | None = None
        self._generation = 0  # reset() starts a new one: older measures are dropped
        self._due_s = -float("inf")
        self._last_stamp_ns: int | None = None
        self._spent: deque[tuple[float, float]] = deque()  # (start, seconds) of the measures
        self._check: DriftCheck | None = None  # the worker thread's
        self._check_generation = -1
        self._listen()

    # -- the fusion thread -------------------------------------------------------------------

    def _on_set(self, fs: FrameSet) -> None:
        """A frame set arrived (fusion thread): hand it to the worker when a measure is due
        and the set is usable (:func:`unusable`), else note why not."""
        p = self.pipeline
        if not p.wanted:
            return
        now = self.clock()
        if now < self._due_s or self._worker.busy:
            return  # a measure under way sets the next due time when it ends
        rig = p.rig
        why = unusable(rig, fs)
        if why is None and fs.stamp_ns == self._last_stamp_ns:
            why = "waiting for a new frame set (the source delivers the measured one again)"
        self.waiting = why
        if why is not None:
            return
        self._due_s = now + self.period_s
        self._last_stamp_ns = fs.stamp_ns
        needed, _ = checked_sensors(rig)
        frames = {n: _kept(fs.frames[n]) for n in needed}
        self._worker.submit(_Job(rig, fs.stamp_ns, frames, self._generation))

    # -- the worker thread -------------------------------------------------------------------

    def _compute(self, job: _Job) -> None:
        if job.generation != self._generation or job.rig is not self.pipeline.rig:
            return  # a new rig came, or the check was reset, meanwhile: it is not measured
        started = self.clock()
        try:
            check = self._check
            fresh = self._check_generation == job.generation
            if check is None or check.rig is not job.rig or not fresh:
                check = self._check = DriftCheck(job.rig)
                self._check_generation = job.generation
            check.measure(started, job.frames)
            report = check.report(started)
        except Exception as exc:  # reported in the status; the next measure goes on
            self.error = describe_error(exc)
            self.error_count += 1
            return
        finally:
            ended = self.clock()
            spent = ended - started
            self._due_s = max(self._due_s, ended + spent / self.cpu_share)
            self._spent.append((started, spent))
            while self._spent and self._spent[0][0] < ended - SHARE_WINDOW_S:
                self._spent.popleft()
        self.error = None
        self.measures += 1
        with self._lock:
            if job.generation == self._generation:
                self._state = DriftState(report, job.rig, ended, spent)

    # -- any thread --------------------------------------------------------------------------

    def state(self) -> DriftState | None:
        """The newest report of the check of the rig in use, or None (none yet)."""
        rig = self.pipeline.rig
        with self._lock:
            if self._state is not None and self._state.rig is not rig:
                self._state = None  # a new rig is in use: dropped
            return self._state

    def reset(self) -> None:
        """Forget every measure and start the check again (e.g. after a refined rig was put
        in use); a measure under way is discarded."""
        with self._lock:
            self._generation += 1
            self._state = None

    def measured_share(self) -> float | None:
        """The share of one core the measures took over the last :data:`SHARE_WINDOW_S`:
        their time (all but the newest) over the time from the first's start to the newest's
        (the clock's seconds); None before two measures."""
        spent = list(self._spent)
        if len(spent) < 2:
            return None
        span = spent[-1][0] - spent[0][0]
        return None if span <= 0 else sum(s for _, s in spent[:-1]) / span

    def status(self) -> dict[str, Any]:
        """The ``drift`` block of ``GET /api/status``: ``sensors`` (name ->
        :func:`sensor_status`, rig order; empty before the first measure of the rig in
        use), ``instants`` (measured in the window), ``age_s`` (seconds since the newest
        measure, null before), ``drifted`` (names), ``summary`` (:func:`health_summary`),
        ``alerts`` (:func:`alerts`), ``error``, ``waiting``, ``problems`` (the newest few
        of the check), ``measures``, ``cpu_share`` (:meth:`measured_share`) and
        ``last_refine`` (:attr:`last_refine` with its ``age_s``)."""
        now = self.clock()
        state = self.state()
        report = state.report if state is not None else None
        refine = None
        if self.last_refine is not None:
            refine = {k: v for k, v in self.last_refine.items() if k != "at_s"}
            refine["age_s"] = round(max(0.0, now - self.last_refine["at_s"]), 3)
        share = self.measured_share()
        sensors = {} if report is None else report.sensors
        return {
            "sensors": {n: sensor_status(s) for n, s in sensors.items()},
            "instants": 0 if report is None else report.instants,
            "age_s": None if state is None else round(max(0.0, now - state.computed_at_s), 3),
            "drifted": [] if report is None else report.drifted,
            "summary": health_summary(state, self.waiting),
            "alerts": alerts(state),
            "error": self.error,
            "waiting": self.waiting,
            "problems": [] if report is None else list(report.problems[-PROBLEMS_SHOWN:]),
            "measures": self.measures,
            "cpu_share": None if share is None else round(share, 4),
            "last_refine": refine,
        }

    def refine(
        self, save_rig: Callable[[Rig, dict], RigVersion], use_rig: Callable[[Rig], None]
    ) -> RefineResult:
        """Correct the drifted sensors of the rig in use (:func:`fusion.drift.refined_rig`),
        save the result with ``save_rig`` (the session's next rig version; its report: the
        check's), put it in use with ``use_rig`` and start the check again.

        Raises:
            fusion.drift.RefineRefused: a correction beyond
                :data:`fusion.drift.REFUSE_DEG` (nothing saved, nothing changed).
            ValueError: no check of the rig in use yet, or no sensor drifted.
        """
        with self._refining:
            rig = self.pipeline.rig
            state = self.state()
            if state is None:
                raise ValueError(
                    "refine: the rig in use has not been checked yet; wait for the "
                    "calibration health's verdicts"
                )
            refined = refined_rig(rig, state.report)  # RefineRefused, ValueError: unchanged
            drifted = state.report.drifted
            corrected = {n: state.report.sensors[n] for n in drifted}
            report = {
                "drift_refine": {
                    "corrected": {n: sensor_status(s) for n, s in corrected.items()},
                    "check": state.report.as_dict(),
                }
            }
            version = save_rig(refined, report)
            use_rig(refined)
            self.reset()
            self.last_refine = {
                "saved_as": version.name,
                "sensors": {n: round(s.angle_deg or 0.0, 4) for n, s in corrected.items()},
                "at_s": self.clock(),
            }
            return RefineResult(version, refined, corrected)


def refine_text(result: RefineResult) -> str:
    """What a refine did, in words (plain text): ``refined thermal_left (0.31°): saved as
    rig-0002, now in use; checking again``."""
    turned = ", ".join(f"{n} ({s.angle_deg or 0.0:.2f}°)" for n, s in result.corrected.items())
    return f"refined {turned}: saved as {result.version.name}, now in use; checking again"
