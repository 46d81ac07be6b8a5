"""The live fusion loop: frames from a source, grouped, fused, encoded, published.

Two background threads. The fusion thread: a :class:`FrameSource` ->
:class:`FrameSetAssembler` (the left colour camera opens each set) -> :class:`StereoFusion`
(depth mapping updated on each new TOF frame) -> a BGR copy of the picture. The encoder
thread: JPEG -> :class:`FrameHub`. OpenCV releases the GIL while it encodes, so the fusion
of frame N+1 overlaps the encoding of frame N; two BGR buffers pass between the threads,
and the fusion thread waits when both are taken (the source drops what a late consumer
cannot take). A frame set that misses a sensor still produces a picture from what it has:
an eye whose thermal imager is missing shows its colour image; an eye whose colour camera
is gone (:data:`COLOR_GONE_S`) shows the thermal picture on black; the last depth while
the TOF is missing.
When the left colour camera (which opens the frame sets) stops, the right one opens them
(:class:`FrameSetAssembler` ``fallback``). Each frame's metadata carries ``missing`` and,
when :attr:`FusionPipeline.sensor_notes` is set, ``health``: a line per sensor that is not
ok (``{"thermal_right": "silent for 12 s"}``, :mod:`app.server.runtime.sensor_health`). For the
viewer's colour scale it carries the palette and the span the picture was coloured with
(:func:`scale_meta`: ``palette``, ``palette_rgb``, ``span_k``, ``span_auto``, the AGC mode
``agc`` and ``palette_ticks_k``, the temperature at evenly spaced palette positions; null
when the picture shows no palette colour). For the viewer's spot meter it carries each eye's hot
and cold spot (``spots``: :meth:`fusion.spot.SpotFrame.extremes`); :attr:`FusionPipeline.spots`
keeps the last picture's temperatures and depths for ``/api/spot`` and ``/api/area``.

Repeated inputs are not fused again. A source may hand out the very same read-only array
for several frames (the simulated head shows each rendered pose for many frames). When
both colour images, both thermal images, the depth behind the mapping, the display
settings and the imagers' radiometry are all what the previous picture was made of (and
an automatic span has settled), its JPEG is published again with the new frame's metadata
(time stamp, missing sensors): the stream's time stamps advance at the source's rate while
no pixel is computed twice. The stream counts the two apart (frames published and new
pictures per second, :class:`app.server.runtime.rates.StreamRates`). Only arrays with
``flags.writeable`` False count as unchanged, so a source that refills its buffers in place
is fused every frame. Likewise, a TOF frame whose distance array is the previous one (same
read-only object) does not recompute the mapping.

Work on demand (:mod:`app.server.runtime.demand`): given a ``demand``, the pipeline fuses,
maps depth and encodes only while it is wanted (a stream viewer, a Viser client, a REST
client of the status). Otherwise it still drains the source and groups its frames into
sets (``latest_set``, the missing sensors and the sensors' health stay current; the
source never backs up), but makes no picture; the stream forgets its last picture (it
would be stale). While a video viewer is connected (:attr:`FrameHub.wants_bgr
<app.server.runtime.stream.FrameHub.wants_bgr>`), each frame also carries the BGR picture
(``StreamFrame.bgr``: the encoder thread's buffer, handed over read-only and replaced by a
new one in the pool; a repeat carries the previous picture), and the JPEG is encoded only
while a JPEG viewer listens too (:attr:`FrameHub.wants_jpeg
<app.server.runtime.stream.FrameHub.wants_jpeg>`; a repeat encodes it for a JPEG viewer
that came meanwhile). When the demand turns wanted,
the newest frame set is fused at once (a new viewer waits at most one frame period; a
paused replay shows its picture again), the depth from the newest TOF frame seen.
Without a ``demand`` every frame set is fused.
"""

from __future__ import annotations

import dataclasses
import functools
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.base import FrameSetAssembler, FrameSource
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.agc import ToneMap
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.palettes import palette
from trifuse.fusion.spot import SpotFrame, SpotMeter
from trifuse.fusion.stereo import StereoFusion

EYES = ("left", "right")
COLOR_GONE_S = 0.5
"""A colour camera missing from a frame set for less than this (seconds of frame time since
it was last in one) skips the picture; for longer, its eye is drawn on black."""


@dataclass
class PipelineStatus:
    """What the status route and the viewer's overlay report."""

    frames_out: int = 0
    """Frames published to the stream since the start (new pictures and repeats)."""
    pictures_out: int = 0
    """Of these, new pictures (fused, not a repeat of the previous one)."""
    last_stamp_ns: int = 0
    missing: dict[str, str] = field(default_factory=dict)
    error: str | None = None


def shows_palette(settings: DisplaySettings) -> bool:
    """Whether a picture made with ``settings`` shows palette colours (so the viewer shows
    a colour scale): not in ``color`` mode, not in ``blend`` at opacity 0, not in
    ``isotherm`` with a fixed highlight colour."""
    if settings.mode == "color" or (settings.mode == "blend" and settings.opacity == 0.0):
        return False
    return not (settings.mode == "isotherm" and settings.isotherm_color is not None)


@functools.cache
def palette_hex(name: str) -> str:
    """Palette ``name``'s 256 RGB entries, cold end first, as one string of 1536 hex digits
    (``"000000..."``: two per channel), for the viewer's colour scale."""
    return palette(name).tobytes().hex()


PALETTE_TICKS = 9
"""The colour scale's ticks: palette positions 0, 1/8, ..., 1 (first entry to last)."""


def scale_meta(
    settings: DisplaySettings, span_k: tuple[float, float] | None, tone: ToneMap | None = None
) -> dict[str, Any]:
    """What the viewer's colour scale needs (JSON-able): ``palette`` (name), ``palette_rgb``
    (:func:`palette_hex`), ``span_k`` ([low, high] kelvin: the palette's first entry is
    ``low``, its last ``high``), ``span_auto`` (the span follows the picture, or is the
    operator's), ``agc`` (the AGC mode of ``tone``, the picture's mapping; "linear" without
    one), ``palette_ticks_k`` (the temperatures, kelvin, at :data:`PALETTE_TICKS` evenly
    spaced palette positions from the first entry to the last: non-linear under
    equalization) and ``mark_fallback`` (the legend of the marking). All None when the
    picture shows no palette colour or there is no span."""
    if span_k is None or not shows_palette(settings):
        keys = ("palette", "palette_rgb", "span_k", "span_auto", "agc", "palette_ticks_k")
        return {**dict.fromkeys(keys), "mark_fallback": None}
    tone = tone or ToneMap.linear(span_k)
    return {
        "palette": settings.palette,
        "palette_rgb": palette_hex(settings.palette),
        "span_k": [float(span_k[0]), float(span_k[1])],
        "span_auto": settings.span_k is None,
        "agc": tone.mode,
        "palette_ticks_k": [round(t, 3) for t in tone.ticks_k(PALETTE_TICKS)],
        "mark_fallback": settings.mark_fallback,
    }


def _encode_jpeg(bgr: np.ndarray, quality: int) -> bytes:
    """``bgr`` ((H, W, 3) uint8) as JPEG of ``quality`` (RuntimeError if OpenCV fails)."""
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("OpenCV could not encode the fused picture as JPEG")
    return buf.tobytes()


def _unchanged(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """``a`` is ``b`` and cannot have been written to since (read-only), or both None."""
    if a is None or b is None:
        return a is b
    return a is b and not a.flags.writeable


@dataclass
class _Job:
    """One frame for the encoder: a BGR picture to encode, or None to publish the
    previous JPEG again, with the frame's metadata; or, with ``forget``, the stream
    forgets its picture (the pipeline rests)."""

    meta: dict[str, Any]
    bgr: np.ndarray | None = None
    quality: int = 80
    forget: bool = False


class _StreamEncoder:
    """JPEG encoding and publishing in a thread of its own.

    The fusion thread takes a free BGR buffer (:meth:`buffer`, blocks while both are being
    encoded or waiting), fills it and :meth:`submit` s it; frames are published in the order
    submitted. ``stop`` (any thread) ends the waits.
    """

    BUFFERS = 2

    def __init__(self, hub: FrameHub, status: PipelineStatus, stop: threading.Event) -> None:
        self.hub, self.status, self._stop = hub, status, stop
        self._jobs: queue.Queue[_Job | None] = queue.Queue(maxsize=1)
        self._free: queue.Queue[np.ndarray | None] = queue.Queue()
        for _ in range(self.BUFFERS):
            self._free.put(None)  # allocated on first use, at the picture's shape
        self._jpeg: bytes | None = None
        self.kept_bgr: np.ndarray | None = None
        """The last picture published with its BGR (read-only; repeats carry it too)."""
        self._thread = threading.Thread(target=self._run, name="stream-encoder", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _wait(self, op: Any) -> Any:
        """``op(timeout)`` of a queue until it succeeds; None once stopping."""
        while not self._stop.is_set():
            if not self._thread.is_alive():
                raise RuntimeError("the stream encoder thread has stopped")
            try:
                return op(0.5)
            except (queue.Empty, queue.Full):
                continue
        return None

    def buffer(self, shape: tuple[int, ...]) -> np.ndarray | None:
        """A free (H, W, 3) uint8 buffer of ``shape`` to fill; None once stopping."""
        buf = self._wait(lambda t: self._free.get(timeout=t))
        if buf is None and self._stop.is_set():
            return None
        if buf is None or buf.shape != shape:
            buf = np.empty(shape, np.uint8)
        return buf

    def submit(self, job: _Job) -> bool:
        """Queue ``job`` (blocks while the encoder is one frame behind); False once stopping."""
        ok = self._wait(lambda t: self._jobs.put(job, timeout=t) or True)
        if not ok and job.bgr is not None:
            self._free.put(job.bgr)
        return bool(ok)

    def close(self, timeout_s: float = 2.0) -> None:
        """Finish the queued frames, then end the thread."""
        if not self._thread.is_alive():
            return
        try:
            self._jobs.put(None, timeout=timeout_s)
        except queue.Full:
            pass
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                if job.forget:
                    self._jpeg = self.kept_bgr = None
                    self.hub.forget()
                    continue
                new = job.bgr is not None
                if job.bgr is not None:
                    want = self.hub.wants_jpeg
                    self._jpeg = _encode_jpeg(job.bgr, job.quality) if want else None
                    self.kept_bgr = self._keep(job)
                elif self._jpeg is None and self.kept_bgr is not None and self.hub.wants_jpeg:
                    self._jpeg = _encode_jpeg(self.kept_bgr, job.quality)  # a JPEG viewer came
                if self._jpeg is not None or self.kept_bgr is not None:
                    self.hub.publish(self._jpeg, job.meta, new=new, bgr=self.kept_bgr)
                    self.status.frames_out += 1
                    self.status.pictures_out += new
            except Exception as exc:  # shown in the status; the next frame is tried
                self.status.error = describe_error(exc)
            finally:
                if job.bgr is not None:
                    self._free.put(job.bgr)

    def _keep(self, job: _Job) -> np.ndarray | None:
        """While video viewers want the picture itself (:attr:`FrameHub.wants_bgr`), the
        job's buffer goes out with the frame, read-only, and is never reused (a new one
        takes its place in the pool: ``job.bgr`` becomes None); otherwise None."""
        if job.bgr is None or not self.hub.wants_bgr:
            return None
        kept, job.bgr = job.bgr, None
        kept.flags.writeable = False
        self._free.put(None)  # allocated afresh by the next buffer()
        return kept


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
        self.settings = settings or DisplaySettings()
        self.jpeg_quality = jpeg_quality
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
        self._pending_rig: Rig | None = None
        self.radiometry: dict[str, Radiometry] = {}
        self._init_rig(rig)
        self._stop = threading.Event()
        self._encoder = _StreamEncoder(hub, self.status, self._stop)
        self._thread = threading.Thread(target=self._run, name="fusion", daemon=True)
        self._fuse_lock = threading.Lock()  # one frame set at a time (fusion, catch-up)
        self._fused_set: FrameSet | None = None  # the last set handed to _publish
        self._resting = False  # frame sets arrived unwanted: the stream was told to forget
        if demand is not None:
            demand.on_wanted.append(self._catch_up)

    def _init_rig(self, rig: Rig) -> None:
        """Everything that depends on the rig: the fusion, the frame-set assembly, the
        per-imager buffers; forgets the previous depth and picture."""
        self.rig = rig
        self.fusion = StereoFusion(rig)
        self.spot_meter = SpotMeter(self.fusion)
        self.spots: SpotFrame | None = None
        """The spot meter's view of the last fused picture (``/api/spot``, the metadata's
        ``spots``); None before the first, after a rig change and while resting."""
        left, right = rig.eyes["left"], rig.eyes["right"]
        self.tof = self.fusion.tof
        sensors = [left.color, right.color, left.thermal, right.thermal, self.tof]
        self.assembler = FrameSetAssembler(
            sensors, reference=left.color, tolerance_s=self.tolerance_s, fallback=right.color
        )
        thermals = (left.thermal, right.thermal)
        self._offset_buf = {s: np.empty(rig[s].image_size[::-1], np.float32) for s in thermals}
        # A rig's own radiometry replaces the imager's current one; without it, the live
        # balance and trims stay (e.g. a new geometric calibration keeps the balance).
        self.radiometry = {
            s: rig[s].radiometry or self.radiometry.get(s, Radiometry()) for s in thermals
        }
        self._no_thermal = {
            e: np.full(rig[rig.eyes[e].thermal].image_size[::-1], np.nan, np.float32) for e in EYES
        }
        self._no_color = {
            e: np.zeros((*rig[rig.eyes[e].color].image_size[::-1], 3), np.uint8) for e in EYES
        }
        for a in (*self._no_thermal.values(), *self._no_color.values()):
            a.flags.writeable = False
        self._last_tof_ns: int | None = None
        self._newest_tof: Frame | None = None  # the newest TOF frame seen, fused or not
        self._last_distance: np.ndarray | None = None
        self._depth_version = 0  # counts mapping updates: part of what a picture is made of
        self._color_seen: dict[str, int] = {}  # eye -> stamp of the last set with its colour
        self._made_of: tuple | None = None  # what the previous picture was made of

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
        self._encoder.start()
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self.source.close()
        self._thread.join(timeout_s)
        self._encoder.close(timeout_s)

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
        finally:
            self._encoder.close()

    def _arrived(self, fs: FrameSet) -> None:
        """A new frame set: noted always, fused while wanted."""
        with self._fuse_lock:
            rig, self._pending_rig = self._pending_rig, None
            if rig is not None:
                self._init_rig(rig)
            self._note(fs)
            if self.wanted:
                self._publish(fs)
            elif not self._resting:  # the last picture would soon be stale: forget it
                self._resting, self._made_of, self.spots = True, None, None
                self._encoder.submit(_Job({}, forget=True))

    def _catch_up(self) -> None:
        """The demand turned wanted: fuse the newest frame set now, in a thread of its own
        (the fusion thread may be waiting for the source: a paused replay)."""
        if self._thread.is_alive() and not self._stop.is_set():
            threading.Thread(target=self._fuse_newest, name="fusion-catch-up", daemon=True).start()

    def _fuse_newest(self) -> None:
        with self._fuse_lock:
            fs = self.latest_set
            if fs is not None and fs is not self._fused_set and self.wanted:
                try:
                    self._publish(fs)
                except Exception as exc:  # shown in the status, like the fusion thread's
                    self.status.error = describe_error(exc)

    def _note(self, fs: FrameSet) -> None:
        """What every frame set updates, fused or not: the newest set, the status, the
        newest TOF frame, when each eye's colour camera was last in a set."""
        self.latest_set = fs
        for listener in list(self.set_listeners):
            try:
                listener(fs)
            except Exception:  # a listener's failure is its own: the fusion goes on
                pass
        self.status.missing = dict(fs.missing)
        self.status.last_stamp_ns = fs.stamp_ns
        tof = fs.frames.get(self.tof)
        if tof is not None:
            self._newest_tof = tof
        eyes = self.rig.eyes
        seen = [e for e in EYES if eyes[e].color in fs.frames]
        if seen:
            for e in EYES:
                self._color_seen.setdefault(e, fs.stamp_ns)  # not yet: since the first set
            for e in seen:
                self._color_seen[e] = fs.stamp_ns

    def _publish(self, fs: FrameSet) -> bool:
        """Fuse one frame set (noted) and hand it to the encoder; False if it makes no
        picture."""
        self._fused_set, self._resting = fs, False
        tof = self._newest_tof
        if tof is not None and tof.stamp_ns != self._last_tof_ns and tof.distance_m is not None:
            if not _unchanged(tof.distance_m, self._last_distance):
                self.fusion.update_depth(tof.distance_m, tof.image)
                self._depth_version += 1
            self._last_tof_ns = tof.stamp_ns
            self._last_distance = tof.distance_m
        eyes = self.rig.eyes
        colors = {e: fs.frames[eyes[e].color].image for e in EYES if eyes[e].color in fs.frames}
        if not colors:
            return False
        for e in EYES:
            seen = self._color_seen.get(e, fs.stamp_ns)
            if e not in colors and abs(fs.stamp_ns - seen) <= COLOR_GONE_S * 1e9:
                return False  # a late frame: wait for the next set rather than flash black
        colors = {e: colors.get(e, self._no_color[e]) for e in EYES}  # a dead camera: black
        thermals = {
            e: fs.frames[eyes[e].thermal].image for e in EYES if eyes[e].thermal in fs.frames
        }
        settings = self.settings
        if not self.fusion.ready:
            path = "raw"
        elif not thermals:
            path, settings, thermals = "color", DisplaySettings(mode="color"), self._no_thermal
        else:
            path = "fused"  # an eye without its thermal imager shows its colour image
            thermals = {e: thermals.get(e, self._no_thermal[e]) for e in EYES}
        radiometry = tuple(sorted(self.radiometry.items()))
        made_of = (
            path,
            settings,
            radiometry,
            self._depth_version,
            *(colors[e] for e in EYES),
            *(thermals[e] for e in EYES),
        )
        previous = self._made_of
        if (
            previous is not None
            and (self._encoder.kept_bgr is not None or not self.hub.wants_bgr)
            and previous[:4] == made_of[:4]
            and self.fusion.span_settled
            and all(_unchanged(a, b) for a, b in zip(made_of[4:], previous[4:], strict=True))
        ):
            return self._encoder.submit(_Job(self._meta(fs, path, settings), None))
        self._made_of = None  # until the new picture is submitted
        if path == "raw":
            rgb = np.hstack([colors["left"], colors["right"]])
        elif path == "color":
            rgb = self.fusion.compose(colors, thermals, settings)
        else:
            kelvin = {
                e: thermals[e]
                if thermals[e] is self._no_thermal[e]
                else self.kelvin(eyes[e].thermal, thermals[e])
                for e in EYES
            }
            rgb = self.fusion.compose(colors, kelvin, settings, fs.stamp_ns)
        if path != "raw":  # the spot meter's copy of this picture's temperatures and depths
            self.spots = self.spot_meter.capture(fs.stamp_ns)
        bgr = self._encoder.buffer(rgb.shape)
        if bgr is None:
            return False
        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR, dst=bgr)
        job = _Job(self._meta(fs, path, settings), bgr, self.jpeg_quality)
        if not self._encoder.submit(job):
            return False
        self._made_of = made_of
        return True

    def _meta(self, fs: FrameSet, path: str, settings: DisplaySettings) -> dict[str, Any]:
        """What the viewer overlays with the frame (JSON-able)."""
        mode = "color" if path == "raw" else settings.mode
        meta = {
            "stamp_ns": fs.stamp_ns,
            "mode": mode,
            **scale_meta(
                settings, self.fusion.span_k if mode != "color" else None, self.fusion.tone
            ),
            "missing": sorted(fs.missing),
        }
        if self.spots is not None and path != "raw":  # hot and cold spot per eye
            meta["spots"] = self.spots.extremes()
        notes = self.sensor_notes
        if notes is not None:
            try:
                meta["health"] = dict(notes())
            except Exception as exc:  # the picture goes out whatever the report does
                meta["health"] = {"console": f"health unavailable: {describe_error(exc)}"}
        return meta

    def kelvin(self, sensor: str, image: np.ndarray) -> np.ndarray:
        """The imager's readings through its radiometry (calibration, balance, trim), in a
        preallocated buffer (the image itself when the radiometry is the identity)."""
        r = self.radiometry.get(sensor)
        if r is None or r.identity:
            return image
        return r.apply(image, out=self._offset_buf[sensor])

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
