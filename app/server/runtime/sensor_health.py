"""Per-sensor health: is each sensor of the head delivering usable frames?

One state per sensor, with a human reason and the time since its last good frame:

``ok``
    usable frames arrive.
``silent``
    its last good frame is older than :func:`silence_threshold_s` (``max(1 s, 5 frame
    periods)``, the period being the sensor's own typical interval between frames).
``never``
    no usable frame since the console started.
``failing``
    frames arrive but are unusable: rejected by the push ingest (undecodable, wrong size,
    stamps going back ...) or garbage (:func:`check_frame`: wrong shape or type, no finite
    pixel, implausible values, a frozen constant image).

:func:`check_frame` runs on every frame (``SourceTap`` calls :meth:`HealthMonitor.observe`
in the pipeline thread) and is cheap: it looks at a subsample of about 64 x 48 pixels and
reads the whole frame only to confirm a suspicion, so a legitimate frame is never judged
on its subsample alone (a TOF frame that is mostly NaN, as when it looks at the sky, is
fine as long as one pixel anywhere is finite). Garbage frames are withheld from fusion:
the frame sets report the sensor missing and the others carry on.

:func:`classify` is pure: what is known about one sensor (:class:`SensorFacts`) and the
time now give its :class:`SensorHealth`; times are ``time.monotonic()`` seconds.
"""

from __future__ import annotations

import re
import statistics
import threading
import time
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig

State = Literal["ok", "silent", "never", "failing"]
STATES: tuple[State, ...] = ("ok", "silent", "never", "failing")

MIN_SILENT_S = 1.0
"""A sensor is never called silent before this long without a good frame (seconds)."""
SILENT_PERIODS = 5
"""... nor before this many of its typical frame intervals."""
THERMAL_RANGE_K = (100.0, 2500.0)
"""Plausible temperatures (kelvin): a thermal frame needs at least one pixel inside."""
TOF_RANGE_M = (0.0, 10.0)
"""Plausible TOF distances (metres, low end excluded): a frame needs one pixel inside."""
SUBSAMPLE = (48, 64)
"""Rows x columns (about) looked at first by :func:`check_frame`."""
PERIOD_SAMPLES = 16
"""Intervals between good frames kept per sensor to estimate its period (median)."""


# -- garbage --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Expected:
    """What a sensor's frames must be: its modality and (width, height), where known."""

    modality: str | None = None
    size: tuple[int, int] | None = None


def expected_of(rig: Rig | None, sensors: Iterable[str] = ()) -> dict[str, Expected]:
    """``{sensor: Expected}`` for the rig's sensors (and ``sensors`` not in it: unknown)."""
    out = {s: Expected() for s in sensors}
    if rig is not None:
        for name in rig.names:
            out[name] = Expected(rig[name].modality, tuple(rig[name].image_size))
    return out


def _subsample(a: np.ndarray) -> np.ndarray:
    h, w = a.shape[:2]
    return a[:: max(1, h // SUBSAMPLE[0]), :: max(1, w // SUBSAMPLE[1])]


def _values(
    a: np.ndarray, what: str, unit: str, lo: float, hi: float, constant: bool = True
) -> str | None:
    """Why the (H, W) values ``a`` are garbage: no finite pixel, none within (lo, hi], all
    equal (with ``constant``); None if usable. The subsample decides "usable"; the full
    frame confirms a suspicion."""
    if a.dtype.kind not in "fiu":
        return f"{what} of type {a.dtype} (expected numbers)"
    sub = _subsample(a)
    vals = sub[np.isfinite(sub)] if a.dtype.kind == "f" else sub.ravel()
    if vals.size == 0:
        finite = np.isfinite(a) if a.dtype.kind == "f" else np.ones(a.shape, bool)
        if not finite.any():
            return f"{what} all NaN"
        vals = a[finite]
    in_range = (vals > lo) & (vals <= hi)
    if not in_range.any():
        full = a[np.isfinite(a)] if a.dtype.kind == "f" else a.ravel()
        if not ((full > lo) & (full <= hi)).any():
            return (
                f"{what} implausible: {float(full.min()):.4g}..{float(full.max()):.4g} {unit} "
                f"(expected {lo:g}..{hi:g} {unit})"
            )
        return None
    if constant and vals.size >= 16 and vals.min() == vals.max():
        full = a[np.isfinite(a)] if a.dtype.kind == "f" else a.ravel()
        if full.min() == full.max():
            return f"{what} all {float(full.min()):.6g}{unit and ' ' + unit} (a stuck sensor?)"
    return None


def _shape(a: Any, expected: Expected, channels: int | None, what: str) -> str | None:
    if not isinstance(a, np.ndarray) or a.size == 0:
        return f"{what} is empty" if isinstance(a, np.ndarray) else f"{what} is not an array"
    ndim = 2 if channels is None else 3
    if a.ndim != ndim or (channels is not None and a.shape[2] != channels):
        want = "(H, W)" if channels is None else f"(H, W, {channels})"
        return f"{what} of shape {a.shape} (expected {want})"
    if expected.size is not None and (a.shape[1], a.shape[0]) != tuple(expected.size):
        w, h = expected.size
        return f"{what} of size {a.shape[1]}x{a.shape[0]} (expected {w}x{h})"
    return None


def check_frame(frame: Frame, expected: Expected | None = None) -> str | None:
    """Why ``frame`` is garbage (a short phrase), or None if it is usable.

    Colour: (H, W, 3) uint8 of the rig's size (its pixel values are not judged: a dark or
    saturated picture is a picture). Thermal: (H, W) of the rig's size, a finite pixel
    within :data:`THERMAL_RANGE_K`, not one value everywhere (a stuck imager). TOF: a
    distance (H, W) of the rig's size with a finite pixel within :data:`TOF_RANGE_M` (NaN
    pixels are normal: only a frame without any finite pixel is garbage; a few valid pixels
    may well share one value), an amplitude of the same size. Without a modality it is
    guessed (3 channels: colour; a distance: TOF; else any (H, W) values, judged only for
    having a finite pixel and more than one value).
    """
    expected = expected or Expected()
    image = frame.image
    modality = expected.modality
    if modality is None:
        if frame.distance_m is not None:
            modality = "tof"
        elif isinstance(image, np.ndarray) and image.ndim == 3:
            modality = "color"
    if modality == "color":
        why = _shape(image, expected, 3, "image")
        if why is None and image.dtype != np.uint8:
            why = f"image of type {image.dtype} (expected uint8 RGB)"
        return why
    if modality == "tof":
        if frame.distance_m is None:
            return "no distance"
        why = _shape(frame.distance_m, expected, None, "distance")
        if why is None:
            why = _shape(image, Expected(size=frame.distance_m.shape[::-1]), None, "amplitude")
        return why or _values(frame.distance_m, "distance", "m", *TOF_RANGE_M, constant=False)
    why = _shape(image, expected, None, "image")
    if why is not None:
        return why
    if modality == "thermal":
        return _values(image, "temperatures", "K", *THERMAL_RANGE_K)
    return _values(image, "image", "", -np.inf, np.inf)  # all NaN or constant only


# -- classification -------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorFacts:
    """What is known of one sensor (monotonic seconds).

    Attributes:
        last_good_s: arrival of its last usable frame (None: none yet).
        last_bad_s: arrival of its last unusable frame or rejected message (None: none).
        bad_since_good: unusable frames since the last good one.
        bad_reason: why the last unusable frame was unusable.
        period_s: its typical interval between good frames (None: not known yet).
        device_state, device_reason: a camera reader's state (``running``, ``stopped``,
            ``failed`` ...) and why it stopped, for sources that have readers.
    """

    last_good_s: float | None = None
    last_bad_s: float | None = None
    bad_since_good: int = 0
    bad_reason: str | None = None
    period_s: float | None = None
    device_state: str | None = None
    device_reason: str = ""


@dataclass(frozen=True)
class SensorHealth:
    """One sensor's health.

    Attributes:
        sensor: its name.
        state: ``ok``, ``silent``, ``never`` or ``failing``.
        reason: why, for a person ('' when there is nothing to say).
        last_frame_age_s: seconds since its last good frame (None: none yet).
        rate_hz: frames per second it delivers now (good or not).
        detail: what the reason adds to the state's own words (for :meth:`line`).
    """

    sensor: str
    state: State
    reason: str = ""
    last_frame_age_s: float | None = None
    rate_hz: float = 0.0
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.state == "ok"

    def line(self) -> str:
        """One line for the operator: ``thermal_right: silent for 12 s``, ``tof: failing:
        40 frames rejected (distance all NaN)``, ``tof: no frame yet``."""
        if self.state == "silent":
            head = f"silent for {human_s(self.last_frame_age_s or 0.0)}"
        elif self.state == "never":
            head = "no frame yet"
        else:
            return f"{self.sensor}: {self.state}" + (f": {self.reason}" if self.reason else "")
        return f"{self.sensor}: {head}" + (f" ({self.detail})" if self.detail else "")

    def as_dict(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "reason": self.reason,
            "last_frame_age_s": self.last_frame_age_s,
            "rate_hz": self.rate_hz,
        }


def human_s(seconds: float) -> str:
    """``0.4 s``, ``12 s``, ``4 min``, ``2.5 h``."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def silence_threshold_s(
    period_s: float | None, min_s: float = MIN_SILENT_S, periods: int = SILENT_PERIODS
) -> float:
    """How long without a good frame makes a sensor silent: ``max(min_s, periods *
    period_s)`` (``min_s`` while its period is unknown)."""
    return max(min_s, periods * period_s) if period_s else min_s


def _frames(n: int) -> str:
    return f"{n} frame{'s' if n != 1 else ''}"


def classify(
    sensor: str,
    facts: SensorFacts,
    now_s: float,
    *,
    rate_hz: float = 0.0,
    paused: bool = False,
    min_silent_s: float = MIN_SILENT_S,
    periods: int = SILENT_PERIODS,
) -> SensorHealth:
    """The health of ``sensor`` at ``now_s`` (see the module doc). ``paused``: a replay
    held by the operator (no frame is expected, so none is missed)."""
    f = facts
    limit = silence_threshold_s(f.period_s, min_s=min_silent_s, periods=periods)
    age = None if f.last_good_s is None else max(0.0, now_s - f.last_good_s)
    bad_after_good = f.last_bad_s is not None and (
        f.last_good_s is None or f.last_bad_s >= f.last_good_s
    )
    bad_age = None if f.last_bad_s is None else max(0.0, now_s - f.last_bad_s)

    def health(state: State, reason: str, detail: str = "") -> SensorHealth:
        return SensorHealth(sensor, state, reason, age, rate_hz, detail)

    rejected = f"{_frames(f.bad_since_good)} rejected ({f.bad_reason or 'unusable'})"
    if bad_after_good and bad_age is not None and bad_age <= limit:
        if age is not None:
            rejected += f"; last good frame {human_s(age)} ago"
        return health("failing", rejected)
    device = f.device_reason if f.device_state in ("stopped", "failed") else ""
    if age is None:
        if bad_after_good and f.bad_since_good:
            detail = f"{rejected}, the last {human_s(bad_age or 0.0)} ago"
            return health("never", detail, detail)
        if device:
            return health("never", device, device)
        return health("never", "" if paused else "no frame received yet")
    if paused:
        return health("ok", "replay paused")
    if age > limit:
        details = []
        if bad_after_good and f.bad_since_good:
            details.append(f"then {rejected}, the last {human_s(bad_age or 0.0)} ago")
        if device:
            details.append(device)
        detail = "; ".join(details)
        reason = f"no frame for {human_s(age)}"
        if f.period_s:
            reason += f" (usually every {f.period_s:.2g} s)"
        return health("silent", reason + (f"; {detail}" if detail else ""), detail)
    if f.last_bad_s is not None and bad_age is not None and bad_age <= limit:
        return health("ok", f"some frames rejected (latest: {f.bad_reason or 'unusable'})")
    return health("ok", "")


# -- the monitor ----------------------------------------------------------------------------


@dataclass
class _Track:
    last_good_s: float | None = None
    last_bad_s: float | None = None
    bad_since_good: int = 0
    bad_total: int = 0
    bad_reason: str | None = None
    intervals: deque[float] = field(default_factory=lambda: deque(maxlen=PERIOD_SAMPLES))


@dataclass(frozen=True)
class Rejections:
    """A source's own rejections of one sensor's frames (e.g. push messages that did not
    decode): ``since_accepted`` since its last accepted frame, the ``last_s`` (monotonic)
    and ``last_error`` of the latest."""

    since_accepted: int = 0
    last_s: float | None = None
    last_error: str = ""


_PUSH_PREFIX = re.compile(r"^sensor '[^']*' at stamp_ns \d+(, part \d+)?( \([a-z]+\))?: ")


def short_error(message: str, limit: int = 160) -> str:
    """A rejection message without the sensor/stamp prefix the push ingest puts first."""
    text = _PUSH_PREFIX.sub("", message)
    return text if len(text) <= limit else text[: limit - 1] + "…"


class HealthMonitor:
    """Watches the frames a source delivers (:meth:`observe`, any thread) and reports each
    sensor's health (:meth:`report`).

    Args:
        sensors: the sensors to report (more are added as their frames arrive).
        expected: sensor -> what its frames must be (see :func:`expected_of`).
        min_silent_s, periods: the silence threshold (:func:`silence_threshold_s`).
    """

    def __init__(
        self,
        sensors: Iterable[str] = (),
        expected: Mapping[str, Expected] | None = None,
        *,
        min_silent_s: float = MIN_SILENT_S,
        periods: int = SILENT_PERIODS,
    ) -> None:
        self._lock = threading.Lock()
        self.expected: dict[str, Expected] = dict(expected or {})
        self.min_silent_s, self.periods = float(min_silent_s), int(periods)
        self._tracks: dict[str, _Track] = {}
        for s in [*sensors, *self.expected]:
            self._tracks.setdefault(s, _Track())

    def set_rig(self, rig: Rig) -> None:
        """Judge frames against ``rig`` (modalities, image sizes) from now on."""
        expected = expected_of(rig)
        with self._lock:
            self.expected = {**self.expected, **expected}
            for s in expected:
                self._tracks.setdefault(s, _Track())

    @property
    def sensors(self) -> list[str]:
        with self._lock:
            return list(self._tracks)

    def observe(self, frame: Frame, now_s: float | None = None) -> str | None:
        """Check one arriving frame; None if usable, else why not (counted as bad)."""
        why = check_frame(frame, self.expected.get(frame.sensor))
        now = time.monotonic() if now_s is None else now_s
        with self._lock:
            t = self._tracks.get(frame.sensor)
            if t is None:
                t = self._tracks[frame.sensor] = _Track()
            if why is None:
                if t.last_good_s is not None and now > t.last_good_s:
                    t.intervals.append(now - t.last_good_s)
                t.last_good_s = now
                t.bad_since_good = 0
            else:
                t.last_bad_s = now
                t.bad_since_good += 1
                t.bad_total += 1
                t.bad_reason = why
        return why

    def facts(
        self,
        rejections: Mapping[str, Rejections] | None = None,
        devices: Mapping[str, tuple[str, str]] | None = None,
    ) -> dict[str, SensorFacts]:
        """What is known of each sensor: the frames seen here, merged with the source's
        own ``rejections`` and the ``devices`` ``(state, reason)`` of camera readers."""
        rejections, devices = rejections or {}, devices or {}
        out = {}
        with self._lock:
            names = list(self._tracks) + [
                s for s in (*rejections, *devices) if s not in self._tracks
            ]
            for s in names:
                t = self._tracks.get(s) or _Track()
                last_bad, bad_n, reason = t.last_bad_s, t.bad_since_good, t.bad_reason
                r = rejections.get(s)
                if r is not None and r.last_s is not None and r.since_accepted:
                    rejected_after_good = t.last_good_s is None or r.last_s >= t.last_good_s
                    if rejected_after_good:
                        bad_n += r.since_accepted
                    if last_bad is None or r.last_s >= last_bad:
                        last_bad, reason = r.last_s, short_error(r.last_error)
                period = statistics.median(t.intervals) if t.intervals else None
                state, why = devices.get(s, (None, ""))
                out[s] = SensorFacts(t.last_good_s, last_bad, bad_n, reason, period, state, why)
        return out

    def report(
        self,
        now_s: float | None = None,
        *,
        rates_hz: Mapping[str, float] | None = None,
        paused: bool = False,
        rejections: Mapping[str, Rejections] | None = None,
        devices: Mapping[str, tuple[str, str]] | None = None,
    ) -> dict[str, SensorHealth]:
        """``{sensor: SensorHealth}`` at ``now_s`` (default: now)."""
        now = time.monotonic() if now_s is None else now_s
        rates = rates_hz or {}
        return {
            s: classify(
                s,
                f,
                now,
                rate_hz=float(rates.get(s, 0.0)),
                paused=paused,
                min_silent_s=self.min_silent_s,
                periods=self.periods,
            )
            for s, f in self.facts(rejections, devices).items()
        }


def push_rejections(stats: Mapping[str, Any]) -> dict[str, Rejections]:
    """The per-sensor rejections in ``PushSource.stats()`` (``rejected_by_sensor``)."""
    out = {}
    for s, r in (stats.get("rejected_by_sensor") or {}).items():
        out[s] = Rejections(r["since_accepted"], r["last_rejected_s"], r["last_error"] or "")
    return out
