"""The simulated sensor head as a live-like frame source.

:class:`SimulatedHeadSource` turns a simulator scenario (the panning inspection room by
default, :class:`~app.sources.sim.inspection.InspectionScenario`) into a stream of single
frames, each sensor at its own rate (colour 30 Hz, thermal 27 Hz, TOF 15 Hz by default),
time-stamped on a simulated clock, optionally paced in real time.

Rendering is slower than real time. The source therefore renders a *cache* of head poses:
the scenario time is sampled at ``render_hz`` (default 2 Hz) over ``loop_s`` (default one
pan period, 30 s; the stream loops over it), samples that give the same head pose share
one rendering, and the poses are rendered in the background, those the stream is about to
need first. Each frame shows the pose of the sample nearest its time stamp, so the picture
moves in steps of ``1 / render_hz``, and the sensor noise of a pose repeats each time the
pose is shown. The time stamps themselves are exact: sensor ``s`` delivers its ``i``-th
frame at ``start_ns + offset_s[s] + i / rate[s]``.

Live mode (the default scenario's default; ``live``): the poses are rendered in the live
quality (:class:`~app.sources.sim.render.Renderer` ``live=True``: colour and thermal edges
not supersampled; about 0.13 s of CPU per colour image, 0.01 s thermal, 0.013 s TOF, 0.3 s
per pose, where the accurate quality takes about 0.5 s, 0.075 s and 0.013 s, 1.7-2 s per
pose), with the fast noise of :class:`~app.sources.sim.live.LiveDeveloper`. And the picture
moves the same way from the first second: a sample whose pose is not rendered yet shows
the rendered pose nearest in head orientation, turned to its own orientation
(:class:`~app.sources.sim.live.RotationWarp`, about 30 ms for the five images; pixels from
beyond the rendered picture repeat its border, a strip as wide as the turn), until its own
rendering arrives. Without live mode such a sample shows the nearest rendered pose as it
is: the picture stood still for up to half a minute while the cache filled (measured in
``trifuse bench --only sim-first-minute``, BENCHMARKS.md). The calibration scenario keeps
the accurate quality (its captures must be exact) and has no live mode (the board moves,
not the head).

Start-up: the first pose is rendered as soon as the source is made, in two threads; frames
are available once it is done. Measured on the reference machine (2 cores, otherwise
idle): 3.9-4.5 s for the five sensors of the default head in the accurate quality with a
fresh scenario (ray grids included), 1.2-2.5 s when the scenario has rendered before (grids
cached). With screen boxes from each solid's hull (2026-11-24), under a load average of
10: 2.2-3.0 s accurate, 0.5-0.7 s live (a colour camera's rays undistorted on a coarse
grid), both with a fresh scenario. Meanwhile the render process starts, at low priority,
and builds its own ray grids. Every further pose takes about 0.3 s (live) or 1.7-2 s
(accurate) of CPU in the background (see "Render process"); the default cache (60 samples
over a 30 s pan, 31 distinct poses since the pan swings back) holds about 8.4 MB of images
per pose, about 260 MB in all. In the live quality it was complete after 40 s for the
source alone (load average 4) and after 69-126 s beside a console with a viewer on a busy
machine (load average 6-15: rendering takes the CPU left over); in the accurate quality it
took about a minute alone on an idle machine and 3-5 minutes beside a console. Delivered
rates: exactly 30/27/15 frames per simulated second; with ``realtime`` and a consumer that
keeps up, 30.0/27.0/15.3 Hz measured over 3 s.

The cached images are shared by every frame that shows the pose and are read-only
(``flags.writeable`` is False): copy before modifying. A consumer may rely on this: equal
array objects mean equal pictures (the console's fusion pipeline fuses a pose once).

Render process: for the default scenario (or with ``render_process=True``) the poses are
rendered in a separate, lower-priority process
(:class:`~app.sources.sim.render_process.RenderProcess`, whose module says why). The first
pose, which the stream waits for, is still rendered in this process (two threads: no
waiting for a new interpreter); the process starts at the same time when some pose is not
on disk (about 1 s of start-up, then its ray grids, at low priority) and ends with the
source. Like any ``spawn`` child it imports the parent's ``__main__``: a script that makes
a source must guard its top level with ``if __name__ == "__main__":``.

Disk cache: rendered poses are also kept on disk, one ``.npz`` file per pose, so a
restarted console has every pose at once (:mod:`app.sources.sim.pose_cache`: where, how
the files are named and shared; ``TRIFUSE_SIM_CACHE=off`` keeps none).

Sensor drift: a scenario may move one sensor from a scenario time on (``drift``,
:class:`~app.sources.sim.drift.SensorDrift`; ``drift=`` for the default scenario). The
drift follows the stream's scenario time, not the loop: once it began it stays, while the
head's motion loops. Each sample of the cache then has a pose in each drift state (a pose
before the drift only where a time before it can show it), and the states never mix: they
never share a rendering nor a disk file (the drift is part of the cache folder's key, a
drifted pose's file is ``pose-...-drifted.npz``), the live mode turns a picture only from a
rendered pose of the same state, and a frame whose state has no pose rendered yet waits
for its own rather than show the other state. :attr:`SimulatedHeadSource.rig` stays the
rig as calibrated; :meth:`SimulatedHeadSource.truth_at` says the rig a frame was rendered
from. Without a drift nothing of this applies (the same poses, files and speed).
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.drift import SensorDrift
from trifuse.app.sources.sim.live import RotationWarp
from trifuse.app.sources.sim.pose_cache import (
    cache_folder,
    load_pose,
    pose_file,
    sample_poses,
    save_pose,
    scenario_key,
)
from trifuse.app.sources.sim.render import SensorTruth
from trifuse.app.sources.sim.render_process import RenderProcess, render_frames
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import rotation_angle_deg

DEFAULT_RATES_HZ: dict[str, float] = {"color": 30.0, "thermal": 27.0, "tof": 15.0}
"""Frame rate per modality when ``rates_hz`` does not name a sensor."""

_STAMP_MEMORY = 8192  # stamps whose pose is remembered for truth_at()


class Scenario(Protocol):
    """What the source needs of a scenario (InspectionScenario has it all).

    ``render(t_s, sensors)`` returns the frames and per-sensor ground truth at scenario time
    ``t_s``; optionally ``T_world_rig(t_s)`` (the head pose, used to share renderings
    between equal poses and returned by :meth:`SimulatedHeadSource.truth_at`),
    ``scene_key(t_s)`` (a hashable; times with equal keys share one rendering, overriding
    the head pose, for scenes where something other than the head moves),
    ``pan_period_s`` (the default loop length) and ``scenario_time(stamp_ns, start_ns)``
    (the scenario time a frame stamped ``stamp_ns`` of a stream started at ``start_ns``
    shows, for a scenario that paces itself: the calibration board waiting for a capture;
    default ``(stamp_ns - start_ns) / 1e9``) and ``drift`` (a
    :class:`~app.sources.sim.drift.SensorDrift` or None: one sensor moved from scenario
    time ``drift.at_s`` on; such a scenario's ``render`` takes ``drifted=`` (render with
    the drift or without, whatever the time) and it has ``drifted_rig``, the rig with the
    sensor moved; see "Sensor drift" in the module docstring).
    """

    rig: Rig

    def render(
        self, t_s: float, sensors: list[str] | None = None
    ) -> tuple[FrameSet, dict[str, SensorTruth]]: ...


@dataclass(frozen=True)
class SimTruth:
    """Ground truth of the frames delivered at one time stamp.

    Attributes:
        stamp_ns: the frames' time stamp.
        pose_t_s: the scenario time whose head pose the frames show (a multiple of
            ``1 / render_hz`` within the loop), seconds.
        T_world_rig: (4, 4) the head pose at ``pose_t_s`` (world frame of the scenario), or
            None if the scenario does not say.
        sensors: sensor -> exact per-pixel truth (radial range along the pixel-centre ray,
            hit solid) of the image that was delivered.
        rig: the rig the frames were rendered from: the scenario's, or its ``drifted_rig``
            (a sensor moved) while its sensor drift is active.
    """

    stamp_ns: int
    pose_t_s: float
    T_world_rig: np.ndarray | None
    sensors: dict[str, SensorTruth]
    rig: Rig | None = None


@dataclass
class _Pose:
    frames: dict[str, Frame]
    truth: dict[str, SensorTruth] | None


class SimulatedHeadSource(FrameSource):
    """A simulated head delivering each sensor at its own rate (see the module docstring).

    Args:
        scenario: the scenario to render (default: ``InspectionScenario(seed=seed)``).
        sensors: the sensors to deliver (default: every sensor of the scenario's rig).
        rates_hz: frame rate per sensor name or per modality (``color``, ``thermal``,
            ``tof``); unnamed ones take :data:`DEFAULT_RATES_HZ`.
        offsets_s: time of each sensor's first frame after ``start_ns`` (default 0: all
            sensors start together), seconds, in ``[0, 1 / rate)``.
        realtime: release frames at wall-clock times (``speed`` simulated seconds per
            second); a consumer that is late gets each sensor's newest due frame and the
            older ones are dropped (counted in :meth:`stats`). Without it, frames come as
            fast as they are asked for.
        speed: simulated seconds per wall-clock second when ``realtime``.
        render_hz: how often per simulated second the head pose is sampled for the cache.
        loop_s: length of the simulated time covered by the cache; the stream loops over
            it (default: the scenario's ``pan_period_s``, else one sample: a still head).
        start_ns: time stamp of scenario time 0; None: the host clock (``time.time_ns()``)
            when a stream starts (after the first pose is rendered), so that realtime
            stamps follow the host clock.
        duration_s: end the stream after this much simulated time (default: never).
        wait_for_render: each frame waits until the pose nearest its time stamp is
            rendered instead of showing the nearest one rendered so far: reproducible
            pictures, but far slower than real time until the cache is full.
        keep_truth: keep each pose's per-pixel ground truth in the cache (about 16 MB more
            per pose for the default head); otherwise :meth:`truth_at` renders it again.
        seed: seed of the default scenario.
        drift: a sensor of the default scenario that moves during the run
            (``InspectionScenario(drift=drift)``; see "Sensor drift" in the module
            docstring); a scenario of your own takes its drift itself.
        cache_dir: directory of the disk cache of rendered poses (see "Disk cache" in
            the module docstring); None: the default directory
            (:func:`~app.sources.sim.pose_cache.default_cache_dir`) for a scenario that
            can be cached (the default one, or one with ``cache_key()``) without
            ``keep_truth``; False: no disk cache.
        render_process: render in a separate, lower-priority process instead of a
            thread of this one; None: for the default scenario without ``keep_truth``.
            True with a scenario of your own pickles it to the process.
        live: the live (demo) mode (see "Live mode" in the module docstring): the
            default scenario renders in the live quality, and a frame whose pose is not
            rendered yet shows the nearest rendered pose turned to its head pose. None:
            for the default scenario without ``keep_truth`` or ``wait_for_render``. With
            a scenario of your own only the turning applies (its quality is its own), and
            it needs a scenario where only the head turns (``T_world_rig``, no
            ``scene_key``).
        clock, sleep: the wall clock that paces ``realtime`` (seconds) and how to wait on
            it; None: ``time.monotonic`` and a wait that :meth:`close` cuts short (tests
            pass a simulated clock).

    Attributes:
        rig: the scenario's ground-truth rig.
        sensors: the delivered sensors, in rig order.
        rates_hz: the rate of each delivered sensor.
        first_pose_s: wall-clock seconds the first pose took to render (None until done).
    """

    source_kind = "simulated"

    def __init__(
        self,
        scenario: Scenario | None = None,
        *,
        sensors: Sequence[str] | None = None,
        rates_hz: Mapping[str, float] | None = None,
        offsets_s: Mapping[str, float] | None = None,
        realtime: bool = False,
        speed: float = 1.0,
        render_hz: float = 2.0,
        loop_s: float | None = None,
        start_ns: int | None = 0,
        duration_s: float | None = None,
        wait_for_render: bool = False,
        keep_truth: bool = False,
        seed: int = 0,
        cache_dir: str | os.PathLike[str] | bool | None = None,
        render_process: bool | None = None,
        live: bool | None = None,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], object] | None = None,
        drift: SensorDrift | None = None,
    ) -> None:
        default_seed = seed if scenario is None else None
        if drift is not None and scenario is not None:
            raise ValueError("drift: for the default scenario; give it to your scenario instead")
        if live is None:
            live = scenario is None and not keep_truth and not wait_for_render
        if live and scenario is not None:
            if not hasattr(scenario, "T_world_rig") or hasattr(scenario, "scene_key"):
                raise ValueError(
                    "live: needs a scenario where only the head turns (T_world_rig and no "
                    "scene_key)"
                )
        if scenario is None:
            from trifuse.app.sources.sim.inspection import InspectionScenario

            scenario = InspectionScenario(seed=seed, live=live, drift=drift)
        self.scenario = scenario
        self._scenario_clock: Callable[[int, int], float] | None = getattr(
            scenario, "scenario_time", None
        )
        self.rig: Rig = scenario.rig
        names = list(self.rig.names)
        if sensors is None:
            self.sensors = names
        else:
            unknown = [s for s in sensors if s not in names]
            if unknown or not sensors:
                raise ValueError(
                    f"sensors: expected a non-empty subset of the rig's sensors {names}, "
                    f"got {list(sensors)}"
                )
            self.sensors = [s for s in names if s in sensors]
        self.rates_hz = self._resolve_rates(rates_hz or {})
        self._offsets_ns = self._resolve_offsets(offsets_s or {})
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed: expected a positive number, got {speed}")
        if not (math.isfinite(render_hz) and render_hz > 0):
            raise ValueError(f"render_hz: expected a positive number, got {render_hz}")
        if loop_s is None:
            loop_s = getattr(scenario, "pan_period_s", None) or 1.0 / render_hz
        if not (math.isfinite(loop_s) and loop_s > 0):
            raise ValueError(f"loop_s: expected a positive number of seconds, got {loop_s}")
        if duration_s is not None and not duration_s > 0:
            raise ValueError(f"duration_s: expected a positive number or None, got {duration_s}")
        self.realtime = realtime
        self.speed = float(speed)
        self.render_hz = float(render_hz)
        self._clock_at_stream_start = start_ns is None
        self.start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self.duration_s = duration_s
        self.wait_for_render = wait_for_render
        self.keep_truth = keep_truth
        self.live = bool(live)
        self._clock = clock or time.monotonic
        self._sleep = sleep or (lambda s: self._stop.wait(s))

        # The cache: K samples of scenario time; samples with equal head poses share a pose.
        k = max(1, round(loop_s * render_hz))
        self.loop_s = k / render_hz
        self._samples = sample_poses(scenario, k, render_hz)
        self._sample_t = self._samples.sample_t
        self._pose_t = self._samples.pose_t  # representative scenario time of each pose
        self._pose_T = self._samples.pose_T
        self._pose_drifted = self._samples.pose_drifted
        self._drift: SensorDrift | None = getattr(scenario, "drift", None)

        self._poses: dict[int, _Pose] = {}
        # Live mode: pictures of poses not rendered yet, turned from a rendered one:
        # pose -> (the rendered pose it was turned from, the picture).
        self._provisional: dict[int, tuple[int, _Pose]] = {}
        self._warps: dict[str, RotationWarp] = {}
        self.provisional_made = 0
        """Live mode: provisional pictures made so far (poses turned from another)."""
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._wanted: int | None = None  # a pose a waiting consumer needs now
        self._now_s = 0.0  # scenario time of the latest delivered frame
        self._last_render_s = 1.0
        self._stamp_pose: OrderedDict[int, int] = OrderedDict()  # stamp -> the pose shown
        self._truth_cache: OrderedDict[int, dict[str, SensorTruth]] = OrderedDict()
        self._delivered = dict.fromkeys(self.sensors, 0)
        self._dropped = dict.fromkeys(self.sensors, 0)
        self.first_pose_s: float | None = None

        # Where poses come from: the disk cache, a render process or a render thread.
        self.cache_dir: Path | None = cache_folder(
            cache_dir, scenario_key(scenario, default_seed), self.sensors, keep_truth
        )
        """This scenario's directory in the disk cache (None: no disk cache)."""
        if render_process is None:
            render_process = default_seed is not None and not keep_truth
        elif render_process and keep_truth:
            raise ValueError("render_process: not with keep_truth (truth stays in-process)")
        self._process_args = (None if default_seed is not None else scenario, seed, self.live)
        self._process_drift = drift if default_seed is not None else None
        self.render_process = bool(render_process)
        self._process: RenderProcess | None = None
        self._thread = threading.Thread(target=self._run, name="simulated-head-render", daemon=True)
        self._thread.start()

    # -- configuration ------------------------------------------------------------------

    def _resolve_rates(self, rates: Mapping[str, float]) -> dict[str, float]:
        known = set(self.rig.names) | set(DEFAULT_RATES_HZ)
        unknown = sorted(set(rates) - known)
        if unknown:
            raise ValueError(
                f"rates_hz: {unknown} are neither sensors of the rig {self.rig.names} nor "
                f"modalities {sorted(DEFAULT_RATES_HZ)}"
            )
        out = {}
        for s in self.sensors:
            modality = self.rig[s].modality
            hz = rates.get(s, rates.get(modality, DEFAULT_RATES_HZ[modality]))
            if not (isinstance(hz, int | float) and math.isfinite(hz) and hz > 0):
                raise ValueError(f"rates_hz[{s!r}]: expected a positive number of Hz, got {hz}")
            out[s] = float(hz)
        return out

    def _resolve_offsets(self, offsets: Mapping[str, float]) -> dict[str, int]:
        unknown = sorted(set(offsets) - set(self.sensors))
        if unknown:
            raise ValueError(f"offsets_s: {unknown} are not delivered sensors {self.sensors}")
        out = {}
        for s in self.sensors:
            off = offsets.get(s, 0.0)
            if not (math.isfinite(off) and 0 <= off < 1.0 / self.rates_hz[s]):
                raise ValueError(
                    f"offsets_s[{s!r}]: expected seconds in [0, {1.0 / self.rates_hz[s]:.4f}) "
                    f"(one frame period), got {off}"
                )
            out[s] = round(off * 1e9)
        return out

    # -- the clock ----------------------------------------------------------------------

    def stamp_ns(self, sensor: str, index: int) -> int:
        """Time stamp of ``sensor``'s ``index``-th frame (0 = the first), nanoseconds."""
        return self.start_ns + self._offsets_ns[sensor] + round(index * 1e9 / self.rates_hz[sensor])

    def _latest_index(self, sensor: str, stamp_ns: int) -> int:
        """The largest frame index of ``sensor`` whose stamp is <= ``stamp_ns`` (may be -1)."""
        rel = stamp_ns - self.start_ns - self._offsets_ns[sensor]
        i = math.floor(rel * self.rates_hz[sensor] / 1e9)
        while self.stamp_ns(sensor, i + 1) <= stamp_ns:
            i += 1
        while i >= 0 and self.stamp_ns(sensor, i) > stamp_ns:
            i -= 1
        return max(i, -1)

    # -- rendering ----------------------------------------------------------------------

    @property
    def pose_count(self) -> int:
        """Distinct head poses in the cache (rendered or not)."""
        return len(self._pose_t)

    @property
    def rendered_count(self) -> int:
        """Poses rendered so far."""
        with self._cond:
            return len(self._poses)

    @property
    def render_thread_alive(self) -> bool:
        """Whether the background render thread is still running."""
        return self._thread.is_alive()

    def _run(self) -> None:
        try:
            t0 = time.perf_counter()
            if self.render_process and not self._all_on_disk():
                # Start the render process now, at low priority: its start-up (a new
                # interpreter, the ray grids) overlaps the first pose.
                self._process = RenderProcess(
                    *self._process_args, self.sensors, warm_up=True, drift=self._process_drift
                )
            # The first pose in this process: no waiting for the render process to start.
            self._obtain(self._pose_of(0, self._drifted_at(0.0)), workers=2, in_process=True)
            self.first_pose_s = time.perf_counter() - t0
            while not self._stop.is_set():
                pose = self._next_pose()
                if pose is None:
                    return
                t0 = time.perf_counter()
                if self._obtain(pose, workers=1):
                    self._last_render_s = time.perf_counter() - t0
        except BaseException as exc:
            with self._cond:
                self._error = exc
                self._cond.notify_all()
        finally:
            if self._process is not None:
                self._process.close()

    def _all_on_disk(self) -> bool:
        paths = [self._pose_path(p) for p in range(len(self._pose_t))]
        return all(p is not None and p.exists() for p in paths)

    def _next_pose(self) -> int | None:
        """The pose to render next: one a consumer waits for, else the first unrendered one
        at or after where the stream will be when the rendering is done."""
        with self._cond:
            if len(self._poses) == len(self._pose_t):
                return None
            if self._wanted is not None and self._wanted not in self._poses:
                return self._wanted
            lead = self._last_render_s * self.speed if self.realtime else 0.0
            k = len(self._sample_t)
            ahead_s = self._now_s + lead
            j = round((ahead_s % self.loop_s) * self.render_hz)
            for step in range(k):
                drifted = self._drifted_at(ahead_s + step / self.render_hz)
                pose = self._pose_of((j + step) % k, drifted)
                if pose not in self._poses:
                    return pose
            # With a sensor drift: the poses of the state the next loop does not show
            # (the stream before the drift, shown again by a new stream).
            return next((p for p in range(len(self._pose_t)) if p not in self._poses), None)

    # -- sensor drift ---------------------------------------------------------------------

    def _drifted_at(self, t_s: float) -> bool:
        """Whether the scenario's sensor drift is active at scenario time ``t_s`` (seconds,
        of the stream: not wrapped into the loop)."""
        return self._drift is not None and self._drift.active(t_s)

    def _pose_of(self, sample: int, drifted: bool) -> int:
        """The pose cache sample ``sample`` shows with the drift active or not."""
        return self._samples.pose_of(sample, drifted)

    def _rig_of(self, pose: int) -> Rig:
        """The rig ``pose`` is rendered from: the scenario's ``drifted_rig`` for a drifted
        pose, else :attr:`rig`."""
        if self._pose_drifted[pose]:
            return self.scenario.drifted_rig  # type: ignore[attr-defined]
        return self.rig

    def _drifted_arg(self, pose: int) -> bool | None:
        """``drifted=`` for the scenario's ``render`` of ``pose`` (None: no drift)."""
        return None if self._drift is None else self._pose_drifted[pose]

    def _pose_path(self, pose: int) -> Path | None:
        if self.cache_dir is None:
            return None
        return pose_file(self.cache_dir, self._pose_t[pose], self._pose_drifted[pose])

    def _obtain(self, pose: int, workers: int, in_process: bool = False) -> bool:
        """Put ``pose`` in the cache: from the disk cache if it is there (False), else
        rendered (True; written to the disk cache too), in the render process unless
        ``in_process`` or there is none."""
        path = self._pose_path(pose)
        if path is not None:
            frames = load_pose(path, self.rig, self.sensors)
            if frames is not None:
                self._store(pose, frames, None)
                return False
        t_s = self._pose_t[pose]
        drifted = self._drifted_arg(pose)
        if in_process or not self.render_process:
            out = render_frames(
                self.scenario, self.rig, self.sensors, t_s, workers, self._stop, drifted
            )
            if self._stop.is_set() or len(out) != len(self.sensors):
                return True
            frames = {name: f for name, (f, _) in out.items()}
            if path is not None:
                try:
                    save_pose(path, frames)
                except OSError:
                    pass
            truth = {name: tr for name, (_, tr) in out.items()} if self.keep_truth else None
            self._store(pose, frames, truth)
            return True
        if self._process is None:
            self._process = RenderProcess(
                *self._process_args, self.sensors, drift=self._process_drift
            )
        with self._cond:
            low = bool(self._poses)
        rendered = self._process.render(
            pose, t_s, workers, path, low, self._stop, self.rig, drifted
        )
        if rendered is None:  # closed
            return True
        self._store(pose, rendered, None)
        return True

    def _store(
        self, pose: int, frames: dict[str, Frame], truth: dict[str, SensorTruth] | None
    ) -> None:
        for f in frames.values():
            f.image.flags.writeable = False
            if f.distance_m is not None:
                f.distance_m.flags.writeable = False
        with self._cond:
            self._poses[pose] = _Pose(frames, truth)
            self._provisional.pop(pose, None)
            self._cond.notify_all()

    def _wait_first_pose(self) -> bool:
        with self._cond:
            while not self._poses and self._error is None and not self._stop.is_set():
                self._cond.wait(0.1)
            if self._error is not None and not self._poses:
                raise RuntimeError(
                    f"simulated head: rendering the first pose failed: {self._error!r}"
                ) from self._error
            return bool(self._poses)

    def wait_ready(self, timeout_s: float | None = None) -> bool:
        """Block until the first pose is rendered (frames can flow); False on timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._poses and self._error is None and not self._stop.is_set():
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(0.1 if left is None else min(left, 0.1))
            return bool(self._poses)

    # -- which pose a stamp shows -------------------------------------------------------

    def _scenario_t(self, stamp_ns: int) -> float:
        if self._scenario_clock is not None:  # a scenario that paces itself
            return self._scenario_clock(stamp_ns, self.start_ns)
        return (stamp_ns - self.start_ns) / 1e9

    def _pose_for(self, stamp_ns: int) -> int:
        """The cache pose a time stamp shows; remembered so that every frame of that
        stamp, and :meth:`truth_at`, agree. Call with the lock held.

        The sample nearest the stamp's scenario time within the loop, in the drift state
        of that (unwrapped) time. It is shown rendered; meanwhile (live mode) turned from
        the nearest rendered pose of the same drift state, else the nearest rendered
        sample's pose of that state. A frame never shows the other drift state's picture:
        with no pose of its state rendered yet (or ``wait_for_render``) it waits for its own.
        """
        pose = self._stamp_pose.get(stamp_ns)
        if pose is not None:
            return pose
        n = len(self._sample_t)
        t_s = self._scenario_t(stamp_ns)
        drifted = self._drifted_at(t_s)
        j = round((t_s % self.loop_s) * self.render_hz) % n
        pose = self._pose_of(j, drifted)
        if self.wait_for_render or (self._drift is not None and not self._state_rendered(drifted)):
            while pose not in self._poses and not self._stop.is_set():
                if self._error is not None:
                    raise RuntimeError(f"simulated head: rendering failed: {self._error!r}")
                self._wanted = pose
                self._cond.wait(0.1)
        elif not self.live:
            for step in range(n // 2 + 1):
                near = [self._pose_of((j + d) % n, drifted) for d in (step, -step)]
                found = [p for p in near if p in self._poses and self._pose_drifted[p] == drifted]
                if found:
                    pose = found[0]
                    break
        # live: shown rendered, or turned from the nearest rendered pose meanwhile
        self._stamp_pose[stamp_ns] = pose
        if len(self._stamp_pose) > _STAMP_MEMORY:
            self._stamp_pose.popitem(last=False)
        return pose

    def _state_rendered(self, drifted: bool) -> bool:
        """Whether some pose of that drift state is rendered. Call with the lock held."""
        return any(self._pose_drifted[p] == drifted for p in self._poses)

    def _provisional_pose(self, pose: int) -> _Pose | None:
        """Live mode: the picture of an unrendered ``pose``, turned from the rendered pose
        whose head orientation is nearest (made again when a nearer one is rendered).
        Call with the lock held. Only a pose of the same drift state is turned (the drifted
        sensor's picture must not come from the other state)."""
        state = self._pose_drifted[pose]
        same = [p for p in self._poses if self._pose_drifted[p] == state]
        if not same or self._pose_T[pose] is None:
            return None

        def angle(p: int) -> float:
            R = self._pose_T[p][:3, :3].T @ self._pose_T[pose][:3, :3]  # type: ignore[index]
            return rotation_angle_deg(R)

        src = min(same, key=lambda p: (angle(p), p))
        made = self._provisional.get(pose)
        if made is not None and made[0] == src:
            return made[1]
        picture = _Pose(self._turn(self._poses[src].frames, src, pose), None)
        self._provisional[pose] = (src, picture)
        self.provisional_made += 1
        return picture

    def _turn(self, frames: dict[str, Frame], src: int, dst: int) -> dict[str, Frame]:
        """``frames`` of pose ``src`` turned to the head orientation of pose ``dst``
        (:class:`~app.sources.sim.live.RotationWarp`; pixels from beyond the picture
        repeat its border). Read-only arrays."""
        T_src, T_dst = self._pose_T[src], self._pose_T[dst]
        assert T_src is not None and T_dst is not None
        rig = self._rig_of(dst)  # that of src too: poses of one drift state
        out = {}
        for name, f in frames.items():
            warp = self._warps.get(name)
            if warp is None:
                warp = self._warps[name] = RotationWarp(self.rig[name])
            R_rs = rig[name].T_rig_sensor[:3, :3]
            R_src_dst = (T_src[:3, :3] @ R_rs).T @ (T_dst[:3, :3] @ R_rs)
            m = warp.update(R_src_dst, 0)
            nearest = self.rig[name].modality == "tof"
            interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
            image = cv2.remap(f.image, m, None, interp, borderMode=cv2.BORDER_REPLICATE)
            dist = None
            if f.distance_m is not None:
                dist = cv2.remap(
                    f.distance_m, m, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE
                )
                dist.flags.writeable = False
            image.flags.writeable = False
            out[name] = Frame(name, 0, image, dist)
        return out

    def _frame(self, sensor: str, stamp_ns: int) -> Frame | None:
        with self._cond:
            self._now_s = self._scenario_t(stamp_ns)
            pose_id = self._pose_for(stamp_ns)
            pose = self._poses.get(pose_id)
            if pose is None and self.live and not self._stop.is_set():
                pose = self._provisional_pose(pose_id)
        if pose is None:  # closed while waiting
            return None
        f = pose.frames[sensor]
        self._delivered[sensor] += 1
        return Frame(sensor, stamp_ns, f.image, f.distance_m)

    # -- the stream ---------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        """Frames of every sensor in time order, from ``start_ns``.

        Blocks until the first pose is rendered. Without ``realtime``, every frame in
        stamp order (ties in rig order). With it, each frame when its time comes; a late
        consumer gets, one at a time, the newest due frame of each sensor (the oldest of
        those first; equal stamps go to the sensor served least recently, so every sensor
        gets its share), and the frames it was too slow for are dropped. Each call starts a
        new stream at ``start_ns``; the pose cache is shared. Ends at ``duration_s`` or on
        :meth:`close`.
        """
        if not self._wait_first_pose():
            return
        if self._clock_at_stream_start:
            self.start_ns = time.time_ns()
        order = {s: i for i, s in enumerate(self.sensors)}
        end_ns = None if self.duration_s is None else self.start_ns + round(self.duration_s * 1e9)
        next_idx = dict.fromkeys(self.sensors, 0)
        served = dict.fromkeys(self.sensors, -1)  # when each sensor was last delivered
        n = 0
        wall0 = self._clock()
        while not self._stop.is_set():
            if self.realtime:
                now_ns = self.start_ns + round((self._clock() - wall0) * self.speed * 1e9)
                due = []
                for s in self.sensors:
                    i = self._latest_index(s, now_ns)
                    if i >= next_idx[s]:
                        due.append((self.stamp_ns(s, i), served[s], order[s], s, i))
                if not due:
                    nxt = min(self.stamp_ns(s, next_idx[s]) for s in self.sensors)
                    self._sleep(max((nxt - now_ns) / 1e9 / self.speed, 0.0))
                    continue
                # One frame, then look again: a slow consumer never gets a stale frame.
                stamp, _, _, s, i = min(due)
            else:
                s = min(self.sensors, key=lambda s: (self.stamp_ns(s, next_idx[s]), order[s]))
                i = next_idx[s]
                stamp = self.stamp_ns(s, i)
            if end_ns is not None and stamp >= end_ns:
                return
            self._dropped[s] += i - next_idx[s]
            next_idx[s] = i + 1
            served[s] = n
            n += 1
            frame = self._frame(s, stamp)
            if frame is None:
                return
            yield frame

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per sensor: ``rate_hz``, frames ``delivered`` and ``dropped`` (realtime, late
        consumer) so far, over every stream of this source."""
        return {
            s: {
                "rate_hz": self.rates_hz[s],
                "delivered": self._delivered[s],
                "dropped": self._dropped[s],
            }
            for s in self.sensors
        }

    # -- ground truth -------------------------------------------------------------------

    def head_pose(self, stamp_ns: int) -> np.ndarray | None:
        """(4, 4) ``T_world_rig`` of the frames delivered at ``stamp_ns`` (the scenario's
        world frame; :meth:`truth_at` without its per-pixel part), or None if the
        scenario does not say or nothing is rendered yet."""
        try:
            T = self.truth_at(stamp_ns, sensors=[]).T_world_rig
        except RuntimeError:
            return None
        return None if T is None else np.array(T, dtype=np.float64)

    def truth_at(self, stamp_ns: int, sensors: Sequence[str] | None = None) -> SimTruth:
        """Ground truth of the frames delivered at ``stamp_ns``.

        For a stamp this source delivered (the latest 8192 stamps are remembered) it is the
        truth of the pose those frames show; for any other stamp, of the pose a frame at
        that stamp would show now. Per-pixel truth comes from the cache with
        ``keep_truth=True``, else the pose is rendered again (about 1.7 s for the default
        head; the latest two are cached) — the truth does not depend on the noise.
        """
        names = self.sensors if sensors is None else list(sensors)
        unknown = [s for s in names if s not in self.sensors]
        if unknown:
            raise KeyError(f"truth_at: {unknown} are not delivered sensors {self.sensors}")
        with self._cond:
            if not self._poses:
                raise RuntimeError("truth_at: no pose rendered yet (wait_ready() first)")
            pose_id = self._pose_for(int(stamp_ns))
            pose = self._poses.get(pose_id)
            cached = self._truth_cache.get(pose_id, {})
        t_s = self._pose_t[pose_id]
        if pose is not None and pose.truth is not None:
            truth = {s: pose.truth[s] for s in names}
        else:
            todo = [s for s in names if s not in cached]
            truth = dict(cached)
            if todo:
                drifted = self._drifted_arg(pose_id)
                extra = {} if drifted is None else {"drifted": drifted}
                _, rendered = self.scenario.render(t_s, todo, **extra)  # type: ignore[call-arg]
                truth.update(rendered)
            with self._cond:
                self._truth_cache[pose_id] = truth
                self._truth_cache.move_to_end(pose_id)
                while len(self._truth_cache) > 2:
                    self._truth_cache.popitem(last=False)
            truth = {s: truth[s] for s in names}
        T = self._pose_T[pose_id]
        rig = self._rig_of(pose_id)
        return SimTruth(int(stamp_ns), t_s, None if T is None else T.copy(), truth, rig)

    # -- lifetime -----------------------------------------------------------------------

    def close(self) -> None:
        """Stop the render thread (it finishes the image in progress, at most about a
        second) and end every stream. Idempotent."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=30.0)
