"""One stereo-picture step: a frame set -> the side-by-side picture, for every loop.

The console's pipeline (``app/server/runtime/pipeline.py``), ``trifuse fuse``
(``app/recording/fuse.py``), the recorded fused video (``app/recording/video_track.py``)
and the benchmarks make their pictures with this one :class:`StereoStep`; they differ only
in what they do with a picture (JPEG, H.264, files) and in their :class:`MissingSensors`
policy. Per frame set:

1. :meth:`StereoStep.note` (every set, pictured or not): the newest TOF frame seen, and
   when each eye's colour camera was last in a set (frame time).
2. :meth:`StereoStep.update_depth`: a TOF frame with a new stamp updates both eyes'
   mappings (:meth:`fusion.stereo.StereoFusion.update_depth`, with the rig's range
   correction); a read-only distance array that is the previous one (same object) is not
   mapped again.
3. :meth:`StereoStep.inputs`: what the picture is made of (:class:`PictureInputs`), or why
   the set makes none (:class:`Skip`), by the policy: the colour images (a black
   placeholder for a camera gone for longer than ``color_gone_s``), the thermal images (a
   NaN placeholder for a missing imager), the path (``raw``: the two colour images side by
   side before the first depth; ``color``: no thermal image at all; ``fused``).
4. :meth:`StereoStep.render`: the thermal images through each imager's radiometry into
   preallocated kelvin buffers, then :meth:`~fusion.stereo.StereoFusion.compose`: (H, 2W,
   3) uint8 RGB (a buffer of the step's, overwritten by the next call).

:meth:`StereoStep.picture` does the four in order. The picture's metadata is built once,
from the inputs and the fusion's span (:meth:`StereoStep.meta`: :class:`fusion.frame_meta.
FrameMeta`). Two parts serve loops that make no picture: :class:`DepthFeed` (the thermal
balance over a recording, ``app/workflows/thermal_run.py``) and :class:`ThermalKelvin` (the
3D map's thermal images, ``app/recording/map3d.py``). Pure: no threads (the console hands
in the executors it wants used: :attr:`DepthFeed.submit`), no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np

from trifuse.calib.numbers import is_real
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.frame_meta import ColourScale, FrameMeta
from trifuse.fusion.registration_overlay import registration_meta
from trifuse.fusion.stereo import EYE_ORDER, StereoFusion
from trifuse.fusion.stereo_pair import side_by_side

PicturePath = Literal["raw", "color", "fused"]
"""How a picture is made: ``raw`` the colour images side by side (no depth yet), ``color``
composed in ``color`` mode (no thermal image), ``fused`` composed with the settings."""

COLOR_GONE_S = 0.5
"""The console's default :attr:`MissingSensors.color_gone_s`, seconds."""


class TofFrame(Protocol):
    """What the step reads of a TOF frame (:class:`app.sources.frames.Frame`)."""

    @property
    def stamp_ns(self) -> int: ...
    @property
    def image(self) -> np.ndarray:
        """(H, W) amplitude (for the range correction)."""
        ...

    @property
    def distance_m(self) -> np.ndarray | None:
        """(H, W) radial distances, metres, NaN invalid; None: not a distance frame."""
        ...


class FrameSetLike(Protocol):
    """What the step reads of a frame set (:class:`app.sources.frames.FrameSet`: fusion
    imports nothing of app): its stamp (ns), sensor -> frame (``image``: colour (H, W, 3)
    uint8 RGB, thermal (h, w) float32 kelvin or raw; TOF: :class:`TofFrame`), and the
    missing sensors."""

    @property
    def stamp_ns(self) -> int: ...
    @property
    def frames(self) -> Mapping[str, Any]: ...
    @property
    def missing(self) -> Mapping[str, str]: ...


@dataclass(frozen=True)
class MissingSensors:
    """What a frame set that lacks a sensor makes (a policy; validated, ValueError).

    Attributes:
        color_gone_s: an eye's colour camera missing from a set: the set makes no picture
            while the camera was in a set at most this long before (frame time, seconds: a
            late frame; better wait for the next set than flash black); after that its eye
            is drawn on black. ``math.inf``: a set without both colour images never makes
            a picture. A set without any colour image never makes one.
        thermal: an eye's thermal imager missing: ``"colour"``: its eye shows its colour
            image (a NaN placeholder: no reading), and a set without any thermal image is
            shown in ``color`` mode; ``"skip"``: no picture.
        no_depth: before the first TOF frame: ``"raw"``: the two colour images side by
            side; ``"skip"``: no picture.
    """

    color_gone_s: float = COLOR_GONE_S
    thermal: Literal["colour", "skip"] = "colour"
    no_depth: Literal["raw", "skip"] = "raw"

    def __post_init__(self) -> None:
        s = self.color_gone_s
        if not is_real(s) or math.isnan(s) or s < 0:
            raise ValueError(f"color_gone_s: expected seconds >= 0 (or inf), got {s!r}")
        if self.thermal not in ("colour", "skip"):
            raise ValueError(f"thermal: expected 'colour' or 'skip', got {self.thermal!r}")
        if self.no_depth not in ("raw", "skip"):
            raise ValueError(f"no_depth: expected 'raw' or 'skip', got {self.no_depth!r}")


CONSOLE = MissingSensors()
"""The console's policy (the reference, also the recorded fused video's): a picture from
whatever the set has."""
OFFLINE = MissingSensors(color_gone_s=math.inf, thermal="skip", no_depth="skip")
"""``trifuse fuse``'s policy: only sets with both eyes' colour and thermal images, after the
first depth, make a picture (the others are counted by reason: :attr:`Skip.reason`)."""


@dataclass(frozen=True)
class Skip:
    """A frame set that makes no picture, and why (``"no frame of ccd_right"``, ``"no TOF
    frame yet"``)."""

    reason: str


@dataclass(frozen=True, eq=False)
class PictureInputs:
    """What one picture is made of (:meth:`StereoStep.inputs`).

    Attributes:
        stamp_ns: the frame set's stamp.
        path: see :data:`PicturePath`.
        settings: the display settings the picture is composed with (``color`` mode on the
            ``color`` path).
        colors: eye -> (H, W, 3) uint8 RGB (a black, read-only placeholder for a camera
            gone).
        thermals: eye -> the imager's (h, w) image as the source gave it (before
            radiometry), or a NaN, read-only placeholder.
        radiometry: (imager, its radiometry) pairs, sorted, at the time.
        depth_version: counts the mapping's updates (the depth behind the picture).
        tof_stamp_ns: the stamp of the TOF frame behind the mapping (None: none yet).
        missing: the set's missing sensors, sorted.
        registration_version: the fusion's registration estimates behind the picture
            (:attr:`fusion.stereo.StereoFusion.registration_version`).
    """

    stamp_ns: int
    path: PicturePath
    settings: DisplaySettings
    colors: Mapping[str, np.ndarray]
    thermals: Mapping[str, np.ndarray]
    radiometry: tuple[tuple[str, Radiometry], ...]
    depth_version: int
    tof_stamp_ns: int | None
    missing: tuple[str, ...] = field(default=())
    registration_version: int = 0

    def same_picture(self, other: PictureInputs | None) -> bool:
        """Whether ``other`` makes the same picture: the same path, settings, radiometry,
        depth and registration estimates, and the very same read-only images (a source that
        hands out one read-only array for several frames). An automatic span still gliding
        is not checked here (:attr:`fusion.stereo.StereoFusion.span_settled`)."""
        if other is None:
            return False
        mine = (self.path, self.settings, self.radiometry, self.depth_version)
        if mine != (other.path, other.settings, other.radiometry, other.depth_version):
            return False
        if self.registration_version != other.registration_version:
            return False
        pairs = [(self.colors[e], other.colors[e]) for e in EYE_ORDER]
        pairs += [(self.thermals[e], other.thermals[e]) for e in EYE_ORDER]
        return all(_unchanged(a, b) for a, b in pairs)


def _unchanged(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    """``a`` is ``b`` and cannot have been written to since (read-only), or both None."""
    if a is None or b is None:
        return a is b
    return a is b and not a.flags.writeable


DEPTH_MAX_LAG_S = 0.2
"""Mapping TOF frames aside (:attr:`DepthFeed.submit`), a picture goes on with the depth in
use while a newer one is mapped, unless the depth in use is further than this from the
picture's time (e.g. the first picture after a rest, or a seek): then it waits for it."""

MapAside = Callable[[Callable[[], Callable[[], None]]], "Future[Callable[[], None]]"]
"""``Executor.submit``'s shape, for :attr:`DepthFeed.submit`."""


class DepthFeed:
    """The TOF side of the step: the newest TOF frame noted (:meth:`note`) is mapped
    (:meth:`update`) once per new stamp, with the rig's range correction
    (:meth:`fusion.stereo.StereoFusion.update_depth`); a frame without distances is not.

    Attributes:
        tof_stamp_ns: the stamp of the TOF frame behind the mapping in use (None before
            the first).
        version: counts the mapping's updates (a read-only distance array that is the
            previous one, same object, is not mapped again: the depth is the same).
        submit: None (default): :meth:`update` maps a new TOF frame there and then. The
            console gives an executor's ``submit``: a new TOF frame is mapped aside in its
            worker (:meth:`fusion.stereo.StereoFusion.map_aside`) while the pictures go on
            with the depth in use, which :meth:`update` replaces once the new one is done
            (one TOF frame at a time: the newest noted when the worker is free). Only
            without any depth, or with one more than :data:`DEPTH_MAX_LAG_S` from the
            picture's time, does :meth:`update` wait for it.
    """

    def __init__(self, fusion: StereoFusion) -> None:
        self.fusion = fusion
        self.tof_stamp_ns: int | None = None
        self.version = 0
        self.submit: MapAside | None = None
        self._newest: TofFrame | None = None  # the newest TOF frame noted
        self._last_distance: np.ndarray | None = None
        self._job: tuple[Future[Callable[[], None]], TofFrame] | None = None  # mapped aside

    def note(self, frame: TofFrame | None) -> None:
        """A TOF frame arrived (None: none in this set)."""
        if frame is not None:
            self._newest = frame

    def update(self, stamp_ns: int | None = None) -> bool:
        """Map the newest TOF frame noted if its stamp is new and it has distances (with
        :attr:`submit`: start mapping it aside, and put in use a mapping done aside);
        ``stamp_ns``: the picture's time (see :attr:`submit`). True if a TOF frame was taken
        (mapped, or put in use)."""
        taken = self._finish(stamp_ns)
        tof = self._newest
        if tof is None or tof.stamp_ns == self.tof_stamp_ns or tof.distance_m is None:
            return taken
        if self._job is not None:  # the worker is busy: the newest frame waits
            return taken
        if _unchanged(tof.distance_m, self._last_distance):
            self.tof_stamp_ns = tof.stamp_ns
            return True
        self._last_distance = tof.distance_m
        if self.submit is None:
            self.fusion.update_depth(tof.distance_m, tof.image)
            self.version += 1
            self.tof_stamp_ns = tof.stamp_ns
            return True
        fusion, distance, amplitude = self.fusion, tof.distance_m, tof.image
        self._job = (self.submit(lambda: fusion.map_aside(distance, amplitude)), tof)
        return self._finish(stamp_ns) or taken

    def _finish(self, stamp_ns: int | None) -> bool:
        """Put the mapping done aside in use, waiting for it only without a usable depth;
        True if it was put in use."""
        if self._job is None:
            return False
        job, tof = self._job
        if not job.done() and self.fusion.ready and self.tof_stamp_ns is not None:
            if stamp_ns is None or abs(stamp_ns - self.tof_stamp_ns) <= DEPTH_MAX_LAG_S * 1e9:
                return False  # the depth in use will do meanwhile
        self._job = None
        job.result()()  # a failure of the mapping is raised here, in the caller's thread
        self.version += 1
        self.tof_stamp_ns = tof.stamp_ns
        return True


class ThermalKelvin:
    """Thermal images -> kelvin through each imager's radiometry (calibration, balance,
    trims), each into a preallocated (h, w) float32 buffer of its imager (the image itself
    when its radiometry is the identity: :meth:`calib.radiometry.Radiometry.apply`).

    Args:
        rig: the rig; ``imagers``: the thermal imagers' names.

    Attributes:
        radiometry: imager -> its radiometry (the rig's; identity without one); may be
            replaced whole between images.
    """

    def __init__(self, rig: Rig, imagers: list[str]) -> None:
        self.radiometry: dict[str, Radiometry] = {
            s: rig[s].radiometry or Radiometry() for s in imagers
        }
        self._out = {s: np.empty(rig[s].image_size[::-1], np.float32) for s in imagers}

    def __call__(
        self, sensor: str, image: np.ndarray, radiometry: Radiometry | None = None
    ) -> np.ndarray:
        """``image`` of imager ``sensor`` in kelvin through ``radiometry`` (default: its
        own), in the imager's buffer (overwritten by its next image)."""
        r = self.radiometry[sensor] if radiometry is None else radiometry
        return r.apply(image, out=self._out[sensor])


class StereoStep:
    """Frame sets -> the side-by-side stereo picture (see the module doc).

    Args:
        rig: the rig (two eyes, ``left`` and ``right``, whose colour cameras share a size).
        settings: display mode, palette, span ... (default: the console's); may be replaced
            (:attr:`settings`) between sets.
        policy: what sets missing a sensor make (default: :data:`CONSOLE`).

    Attributes:
        fusion: the :class:`~fusion.stereo.StereoFusion` (mappings, composers, span).
        depth: its :class:`DepthFeed`; ``kelvin``: the :class:`ThermalKelvin` buffers.
        tof: the TOF sensor's name; ``eyes``: eye -> :class:`~calib.rig.Eye`.
        sensors: the sensors a picture is made of: both colour cameras (the left one opens
            the sets), both thermal imagers, the TOF.
    """

    def __init__(
        self,
        rig: Rig,
        settings: DisplaySettings | None = None,
        policy: MissingSensors = CONSOLE,
    ) -> None:
        if not isinstance(policy, MissingSensors):
            raise ValueError(f"policy: expected MissingSensors, got {type(policy).__name__}")
        self.rig = rig
        self.settings = settings or DisplaySettings()
        self.policy = policy
        self.fusion = StereoFusion(rig)
        self.tof = self.fusion.tof
        self.eyes = {e: rig.eyes[e] for e in EYE_ORDER}
        self.depth = DepthFeed(self.fusion)
        self.kelvin = ThermalKelvin(rig, [eye.thermal for eye in self.eyes.values()])
        self._no_thermal = {
            e: np.full(rig[eye.thermal].image_size[::-1], np.nan, np.float32)
            for e, eye in self.eyes.items()
        }
        w, h = self.fusion.size
        self._no_color = {e: np.zeros((h, w, 3), np.uint8) for e in EYE_ORDER}
        for a in (*self._no_thermal.values(), *self._no_color.values()):
            a.flags.writeable = False
        self._raw = np.empty((h, 2 * w, 3), np.uint8)
        self._color_seen: dict[str, int] = {}  # eye -> stamp of the last set with its colour

    @property
    def radiometry(self) -> dict[str, Radiometry]:
        """Thermal imager -> its radiometry (the rig's; identity without one); may be
        replaced whole between sets (the console's balance and trims)."""
        return self.kelvin.radiometry

    @radiometry.setter
    def radiometry(self, value: dict[str, Radiometry]) -> None:
        self.kelvin.radiometry = value

    @property
    def sensors(self) -> list[str]:
        e = self.eyes
        return [e["left"].color, e["right"].color, e["left"].thermal, e["right"].thermal, self.tof]

    # -- the step, part by part ----------------------------------------------------------

    def note(self, fs: FrameSetLike) -> None:
        """What every frame set updates, pictured or not: the newest TOF frame, when each
        eye's colour camera was last in a set."""
        self.depth.note(fs.frames.get(self.tof))
        seen = [e for e, eye in self.eyes.items() if eye.color in fs.frames]
        if seen:
            for e in EYE_ORDER:
                self._color_seen.setdefault(e, fs.stamp_ns)  # not yet: since the first set
            for e in seen:
                self._color_seen[e] = fs.stamp_ns

    def update_depth(self, stamp_ns: int | None = None) -> bool:
        """Map the newest TOF frame noted if its stamp is new (:meth:`DepthFeed.update`;
        ``stamp_ns``: the picture's time); True if it was taken."""
        return self.depth.update(stamp_ns)

    def inputs(self, fs: FrameSetLike) -> PictureInputs | Skip:
        """What the picture of ``fs`` is made of under the policy, or why it makes none.

        Raises ValueError for a colour image of another size than the rig's.
        """
        policy, eyes = self.policy, self.eyes
        frames = fs.frames
        colors = {e: frames[eye.color].image for e, eye in eyes.items() if eye.color in frames}
        w, h = self.fusion.size
        for e, img in colors.items():
            if img.shape[:2] != (h, w):
                raise ValueError(
                    f"frame of {eyes[e].color!r} is {img.shape[1]}x{img.shape[0]}, the "
                    f"rig says {w}x{h}"
                )
        lacking = []  # sensors whose absence skips the set, in eye order
        for e, eye in eyes.items():
            if e not in colors:
                seen = self._color_seen.get(e, fs.stamp_ns)
                if not colors or abs(fs.stamp_ns - seen) <= policy.color_gone_s * 1e9:
                    lacking.append(eye.color)
            if policy.thermal == "skip" and eye.thermal not in frames:
                lacking.append(eye.thermal)
        if lacking:
            return Skip(f"no frame of {', '.join(lacking)}")
        ready = self.fusion.ready
        if not ready and policy.no_depth == "skip":
            return Skip("no TOF frame yet")
        colors = {e: colors.get(e, self._no_color[e]) for e in EYE_ORDER}  # a dead camera
        thermals = {
            e: frames[eye.thermal].image for e, eye in eyes.items() if eye.thermal in frames
        }
        settings = self.settings
        path: PicturePath
        if not ready:
            path = "raw"
        elif not thermals:
            path, settings, thermals = "color", DisplaySettings(mode="color"), self._no_thermal
        else:
            path = "fused"  # an eye without its thermal imager shows its colour image
            thermals = {e: thermals.get(e, self._no_thermal[e]) for e in EYE_ORDER}
        return PictureInputs(
            fs.stamp_ns,
            path,
            settings,
            colors,
            thermals,
            tuple(sorted(self.radiometry.items())),
            self.depth.version,
            self.depth.tof_stamp_ns,
            tuple(sorted(fs.missing)),
            self.fusion.registration_version,
        )

    def render(self, inputs: PictureInputs) -> np.ndarray:
        """The picture (H, 2W, 3) uint8 RGB of ``inputs`` (a buffer of the step's or the
        fusion's, overwritten by the next call). The ``fused`` path moves the automatic
        span and the AGC table on (smoothed over the sets' stamps)."""
        c, t = inputs.colors, inputs.thermals
        if inputs.path == "raw":
            return side_by_side(c["left"], c["right"], out=self._raw)
        if inputs.path == "color":
            return self.fusion.compose(c, t, inputs.settings)
        radiometry = dict(inputs.radiometry)
        kelvin = {}
        for e, eye in self.eyes.items():
            image = t[e]
            if image is self._no_thermal[e]:
                kelvin[e] = image
            else:
                kelvin[e] = self.kelvin(eye.thermal, image, radiometry[eye.thermal])
        return self.fusion.compose(c, kelvin, inputs.settings, inputs.stamp_ns)

    def picture(self, fs: FrameSetLike) -> np.ndarray | Skip:
        """Steps 1-4 for one frame set: its picture (see :meth:`render`), or why none."""
        self.note(fs)
        self.update_depth(fs.stamp_ns)
        inputs = self.inputs(fs)
        return inputs if isinstance(inputs, Skip) else self.render(inputs)

    def meta(
        self,
        inputs: PictureInputs,
        spots: Mapping[str, Any] | None = None,
        health: Mapping[str, str] | None = None,
    ) -> FrameMeta:
        """The metadata of the picture just rendered from ``inputs`` (or repeated: the
        fusion's span and AGC table are still those of the picture shown), with the spot
        meter's ``spots`` and the sensors' ``health`` if given."""
        mode = "color" if inputs.path == "raw" else inputs.settings.mode
        scale = ColourScale.of(
            inputs.settings, self.fusion.span_k if mode != "color" else None, self.fusion.tone
        )
        registration = None
        if mode == "registration":  # the legend of the sigma's colour map
            registration = registration_meta(self.fusion.registration, self.fusion.eyes)
        return FrameMeta(
            inputs.stamp_ns,
            inputs.tof_stamp_ns,
            mode,
            scale,
            inputs.missing,
            spots,
            health,
            registration,
        )
