"""The live fusion loop: frames from a source, grouped, fused, published.

One background thread, the fusion thread: a :class:`FrameSource` ->
:class:`FrameSetAssembler` (the left colour camera opens each set) -> the stereo-picture
step (:class:`fusion.stereo_step.StereoStep`) -> a BGR copy of the picture, read-only,
published to the :class:`FrameHub` (the JPEG for the JPEG viewers is made there when the
first of them takes it, in a worker thread; the H.264 for the video viewers in theirs), and
on to the next frame set: nothing the viewers do holds the fusion up (the source drops what
a late consumer cannot take).

The step uses two workers of the pipeline's, so that it runs on both cores: each new TOF
frame is mapped aside in ``fusion-depth`` while the pictures go on with the depth in use,
which the new mapping replaces once done (:attr:`fusion.stereo_step.DepthFeed.submit`; a
source that is not ``realtime`` gets every picture with its own depth instead); the
right eye's warp and composition run in ``fusion-eye`` while the fusion thread does the
left eye's (:attr:`fusion.stereo.StereoFusion.map_eyes`).

A frame set that misses a sensor still produces a picture from what it has (the step's
:data:`~fusion.stereo_step.CONSOLE` policy): an eye whose thermal imager is missing shows
its colour image; an eye whose colour camera is gone
(:data:`~fusion.stereo_step.COLOR_GONE_S`) shows the thermal picture on black; the last
depth while the TOF is missing.
When the left colour camera (which opens the frame sets) stops, the right one opens them
(:class:`FrameSetAssembler` ``fallback``). Each frame's metadata
(:class:`fusion.frame_meta.FrameMeta`, built once a picture) carries ``missing`` and, when
:attr:`FusionPipeline.sensor_notes` is set, ``health``: a line per sensor that is not ok
(``{"thermal_right": "silent for 12 s"}``, :mod:`app.server.runtime.sensor_health`). For
the viewer's colour scale it carries the palette and the span the picture was coloured
with (``palette``, ``palette_rgb``, ``span_k``, ``span_auto``, the AGC mode ``agc`` and
``palette_ticks_k``, the temperature at evenly spaced palette positions; null when the
picture shows no palette colour). For the viewer's spot meter it carries each eye's hot
and cold spot (``spots``: :meth:`fusion.spot.SpotFrame.extremes`);
:attr:`FusionPipeline.spots` keeps the last picture's temperatures and depths for
``/api/spot`` and ``/api/area``. When :attr:`FusionPipeline.balance_note` is set and the
picture shows palette colour, it carries ``balance``: which thermal balance it shows.

Repeated inputs are not fused again. A source may hand out the very same read-only array
for several frames (the simulated head shows each rendered pose for many frames). When
both colour images, both thermal images, the depth behind the mapping, the display
settings and the imagers' radiometry are all what the previous picture was made of (and
an automatic span has settled), its picture is published again with the new frame's metadata
(time stamp, missing sensors): the stream's time stamps advance at the source's rate while
no pixel is computed twice. The stream counts the two apart (frames published and new
pictures per second, :class:`app.server.runtime.rates.StreamRates`). Only arrays with
``flags.writeable`` False count as unchanged, so a source that refills its buffers in place
is fused every frame. Likewise, a TOF frame whose distance array is the previous one (same
read-only object) does not recompute the mapping.

Work on demand (:mod:`app.server.runtime.demand`): given a ``demand``, the pipeline fuses and
maps depth only while it is wanted (a stream viewer, a Viser client, a REST client of the
status). Otherwise it still drains the source and groups its frames into
sets (``latest_set``, the missing sensors and the sensors' health stay current; the
source never backs up), but makes no picture; the stream forgets its last picture (it
would be stale). When the demand turns wanted,
the newest frame set is fused at once (a new viewer waits at most one frame period; a
paused replay shows its picture again), the depth from the newest TOF frame seen.
Without a ``demand`` every frame set is fused.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2

from trifuse.app.errors import describe_error
from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.measurements import Measurements
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.base import FrameSetAssembler, FrameSource
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.spot import SpotFrame, SpotMeter
from trifuse.fusion.stereo_step import CONSOLE, PictureInputs, Skip, StereoStep

HELD_S = 0.3
"""No frame set for this long (seconds): the source holds still (a paused replay), and a
change of the display settings fuses the newest set again."""


@dataclass
class PipelineStatus:
    """What the status route and the viewer's overlay report."""

    frames_out: int = 0
    """Frames published to the stream since the start (new pictures and repeats)."""
    pictures_out: int = 0
    """Of these, new pictures (fused, not a repeat of the previous one)."""
    depth_updates: int = 0
    """TOF frames mapped and put in use for the pictures since the start."""
    last_stamp_ns: int = 0
    missing: dict[str, str] = field(default_factory=dict)
    error: str | None = None


class FusionPipeline:
    """Fuses a source's frames into the stereo stream, in background threads.

    Args:
        demand: fuse only while it is wanted (see the module doc); None: always.
    """

    def __init__(
        self,
        source: FrameSource,
        rig: Rig,
        hub: FrameHub,
        settings: DisplaySettings | None = None,
        jpeg_quality: int = 80,
        tolerance_s: float = 0.05,
        demand: Demand | None = None,
    ) -> None:
        self.source, self.hub = source, hub
        self.demand = demand
        self._settings = settings or DisplaySettings()
        self._noted_at = -math.inf  # monotonic time of the newest frame set noted
        self.tolerance_s = tolerance_s
        self.status = PipelineStatus()
        self.latest_set: FrameSet | None = None
        self.set_listeners: list[Callable[[FrameSet], None]] = []
        """Called (in the fusion thread) with every frame set as it arrives, fused or not
        (e.g. the thermal map's worker): they must return quickly; a failure is theirs."""
        self.sensor_notes: Callable[[], dict[str, str]] | None = None
        """Sensor -> a line for each sensor that is not ok, put in each frame's metadata
        (``health``); set by the console (``SourceControl``). Called in the fusion thread:
        it must be quick (cached)."""
        self.balance_note: Callable[[], dict[str, Any]] | None = None
        """The thermal balance the pictures show, put in each frame's metadata (``balance``;
        :meth:`ThermalBalancer.describe <app.server.runtime.thermal_balance.ThermalBalancer.
        describe>`); set by the console. Called in the fusion thread: it must be quick."""
        self._pending_rig: Rig | None = None
        self.measurements = Measurements()
        """Object parameters, regions and alarms, read on the pictures (issue 35)."""
        self._eye_worker = ThreadPoolExecutor(1, thread_name_prefix="fusion-eye")
        self._depth_worker = ThreadPoolExecutor(1, thread_name_prefix="fusion-depth")
        self._init_rig(rig, {})
        hub.jpeg_quality = jpeg_quality
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fusion", daemon=True)
        self._fuse_lock = threading.Lock()  # one frame set at a time (fusion, catch-up)
        self._fused_set: FrameSet | None = None  # the last set handed to _publish
        self._resting = False  # frame sets arrived unwanted: the stream was told to forget
        if demand is not None:
            demand.on_wanted.append(self._catch_up)

    def _init_rig(self, rig: Rig, radiometry: Mapping[str, Radiometry]) -> None:
        """Everything that depends on the rig: the stereo-picture step (fusion, buffers),
        the frame-set assembly; forgets the previous depth and picture. ``radiometry``: the
        imagers' radiometry in use, kept for an imager the rig gives none."""
        self.rig = rig
        self.step = StereoStep(rig, self.settings, CONSOLE)
        self.fusion = self.step.fusion
        self.fusion.map_eyes = self._both_cores
        if self.source.realtime:  # else every picture waits for its depth, as fuse's do
            self.step.depth.submit = self._depth_worker.submit
        self.spot_meter = SpotMeter(self.fusion)
        self.spots: SpotFrame | None = None
        """The spot meter's view of the last fused picture (``/api/spot``, the metadata's
        ``spots``); None before the first, after a rig change and while resting."""
        self.tof = self.fusion.tof
        self.assembler = FrameSetAssembler.stereo(self.step.sensors, self.tolerance_s)
        # A rig's own radiometry replaces the imager's current one; without it, the live
        # balance and trims stay (e.g. a new geometric calibration keeps the balance).
        self.step.radiometry = {
            s: rig[s].radiometry or radiometry.get(s, Radiometry()) for s in self.step.radiometry
        }
        self._made_of: PictureInputs | None = None  # what the previous picture was made of

    def _both_cores(self, fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
        """``map(fn, items)`` with the items after the first in :attr:`_eye_worker` while
        this thread does the first (NumPy and OpenCV release the GIL)."""
        first, *rest = list(items)
        futures = [self._eye_worker.submit(fn, item) for item in rest]
        return [fn(first), *(f.result() for f in futures)]

    @property
    def radiometry(self) -> dict[str, Radiometry]:
        """Thermal imager -> the radiometry its readings go through (calibration, balance,
        trims): the step's; replaced whole, never changed in place."""
        return self.step.radiometry

    @radiometry.setter
    def radiometry(self, value: dict[str, Radiometry]) -> None:
        self.step.radiometry = value

    def set_rig(self, rig: Rig) -> None:
        """Fuse with ``rig`` from the next frame set on (e.g. a new calibration).

        Raises ValueError (and keeps the current rig) unless ``rig`` has the same sensors
        (names, modalities, image sizes) and eyes as the current one.
        """
        mine = {n: (s.modality, s.image_size) for n, s in self.rig.sensors.items()}
        theirs = {n: (s.modality, s.image_size) for n, s in rig.sensors.items()}
        if mine != theirs or rig.eyes != self.rig.eyes:
            raise ValueError(
                f"the rig's sensors {theirs} and eyes {sorted(rig.eyes)} must match the "
                f"console's {mine} and {sorted(self.rig.eyes)}"
            )
        self._pending_rig = rig  # swapped in by the fusion thread, which owns that state

    def start(self) -> FusionPipeline:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self.source.close()
        self._thread.join(timeout_s)
        self._eye_worker.shutdown(wait=False)
        self._depth_worker.shutdown(wait=False, cancel_futures=True)
        self.measurements.close()

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait (at most ``timeout_s``) for the fusion thread to end by itself (its source ran
        out, or :meth:`stop`); whether it has. Every frame it fused is published by then."""
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    @property
    def wanted(self) -> bool:
        """Whether pictures are wanted now (always without a demand)."""
        return self.demand is None or self.demand.wanted

    def touch_demand(self) -> None:
        """A request-response client wants pictures for the next few seconds
        (:meth:`Demand.touch <app.server.runtime.demand.Demand.touch>`; REST routes)."""
        if self.demand is not None:
            self.demand.touch()

    def _run(self) -> None:
        try:
            for frame in self.source.frames():
                if self._stop.is_set():
                    return
                for fs in self.assembler.push(frame):
                    self._arrived(fs)
        except Exception as exc:  # shown in the status, the server keeps running
            self.status.error = describe_error(exc)

    def _arrived(self, fs: FrameSet) -> None:
        """A new frame set: noted always, fused while wanted."""
        with self._fuse_lock:
            rig, self._pending_rig = self._pending_rig, None
            if rig is not None:
                self._init_rig(rig, self.radiometry)
            self._note(fs)
            if self.wanted:
                self._publish(fs)
            elif not self._resting:  # the last picture would soon be stale: forget it
                self._resting, self._made_of, self.spots = True, None, None
                self.hub.forget()

    @property
    def settings(self) -> DisplaySettings:
        """The display settings the next picture is composed with."""
        return self._settings

    @settings.setter
    def settings(self, value: DisplaySettings) -> None:
        """New display settings; while the source holds still (a paused replay: no frame
        set for :data:`HELD_S`) the newest set is fused again with them, so the picture
        shows the change (a new span, a mode) rather than the old settings."""
        self._settings = value
        if time.monotonic() - self._noted_at > HELD_S and self._thread.is_alive():
            threading.Thread(
                target=self._fuse_newest, args=(True,), name="fusion-refresh", daemon=True
            ).start()

    def _catch_up(self) -> None:
        """The demand turned wanted: fuse the newest frame set now, in a thread of its own
        (the fusion thread may be waiting for the source: a paused replay)."""
        if self._thread.is_alive() and not self._stop.is_set():
            threading.Thread(target=self._fuse_newest, name="fusion-catch-up", daemon=True).start()

    def _fuse_newest(self, again: bool = False) -> None:
        """Fuse the newest frame set unless it is the last one fused (``again``: also then)."""
        with self._fuse_lock:
            fs = self.latest_set
            if fs is not None and (again or fs is not self._fused_set) and self.wanted:
                try:
                    self._publish(fs)
                except Exception as exc:  # shown in the status, like the fusion thread's
                    self.status.error = describe_error(exc)

    def _note(self, fs: FrameSet) -> None:
        """What every frame set updates, fused or not: the newest set, the status, and the
        step's note (the newest TOF frame, when each eye's colour camera was last seen)."""
        self.latest_set, self._noted_at = fs, time.monotonic()
        for listener in list(self.set_listeners):
            try:
                listener(fs)
            except Exception:  # a listener's failure is its own: the fusion goes on
                pass
        self.status.missing = dict(fs.missing)
        self.status.last_stamp_ns = fs.stamp_ns
        self.step.note(fs)

    def _publish(self, fs: FrameSet) -> bool:
        """Fuse one frame set (noted) and publish its picture; False if it makes none."""
        self._fused_set, self._resting = fs, False
        step = self.step
        version = step.depth.version
        step.update_depth(fs.stamp_ns)
        self.status.depth_updates += step.depth.version - version
        step.settings = self.settings
        inputs = step.inputs(fs)
        if isinstance(inputs, Skip):
            return False
        if inputs.same_picture(self._made_of) and self.fusion.span_settled:
            if self.hub.publish_again(self._meta(inputs)) is not None:
                self._count(new=False)
                return True
        self._made_of = None  # until the new picture is published
        rgb = step.render(inputs)
        if inputs.path != "raw":  # the spot meter's copy of this picture's temperatures and depths
            self.spots = self.spot_meter.capture(fs.stamp_ns)
            self.measurements.submit(self.spots)  # the regions and alarms, aside
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)  # a new buffer: the last one went out
        bgr.flags.writeable = False
        self.hub.publish(None, self._meta(inputs), bgr=bgr)
        self._count(new=True)
        self._made_of = inputs
        return True

    def _count(self, new: bool) -> None:
        self.status.frames_out += 1
        self.status.pictures_out += new

    def _meta(self, inputs: PictureInputs) -> dict[str, Any]:
        """What the viewer overlays with the frame (JSON-able: :meth:`fusion.frame_meta.
        FrameMeta.as_json`), with the spot meter's hot and cold spots and the sensors'
        health."""
        spots = None
        if self.spots is not None and inputs.path != "raw":  # hot and cold spot per eye
            spots = self.spots.extremes()
        health = None
        notes = self.sensor_notes
        if notes is not None:
            try:
                health = dict(notes())
            except Exception as exc:  # the picture goes out whatever the report does
                health = {"console": f"health unavailable: {describe_error(exc)}"}
        meta = self.step.meta(inputs, spots, health).as_json()
        if self.balance_note is not None and meta["span_k"] is not None:  # palette colour shown
            meta["balance"] = self.balance_note()
        return meta

    def set_manual_offset(self, sensor: str, offset_k: float) -> None:
        """The operator's trim of one imager, kelvin (from the next frame on)."""
        self._check_imager(sensor)
        self.radiometry = {**self.radiometry, sensor: self.radiometry[sensor].with_manual(offset_k)}

    def set_balance(self, terms: dict[str, tuple[float, float]]) -> None:
        """The automatic balance: imager -> (balance_gain, balance_offset_k)."""
        for sensor in terms:
            self._check_imager(sensor)
        new = dict(self.radiometry)
        for sensor, (gain, offset) in terms.items():
            new[sensor] = new[sensor].with_balance(gain, offset)
        self.radiometry = new

    def _check_imager(self, sensor: str) -> None:
        if sensor not in self.radiometry:
            raise KeyError(
                f"{sensor!r} is not a thermal imager of an eye (imagers: {sorted(self.radiometry)})"
            )

    def rig_with_radiometry(self) -> Rig:
        """A copy of the rig in use whose thermal imagers carry their current radiometry."""
        rig = self.rig
        for name, r in self.radiometry.items():
            rig = rig.with_sensor(dataclasses.replace(rig[name], radiometry=r))
        return rig
