"""The console's measurements (issue 35): object parameters, measurement regions and alarms,
and what the regions read on the fused pictures.

One :class:`Measurements` per console, kept across rig changes (regions are colour pixels
of an eye: a rig of another picture size reports the regions outside it). The fusion thread
hands it each picture's spot-meter capture (:meth:`Measurements.submit`: never waits); a
thread of its own (``measurements``) reads the regions on the newest one
(:meth:`Measurements.update`), never when there is no region, and at most every
:attr:`Measurements.interval_s` of frame time (10 a second by default: alarms and tables need
no more) or less often when the regions are large: a reading costs about 0.2 us of CPU a
pixel on a slow host (a whole eye, 1.2 million pixels, 250 ms), and the readings take at
most :data:`MAX_SHARE` of a core, but come at least every :data:`MAX_WAIT_S`. The REST
routes (``app/server/routers/measure_api.py``) change the settings from the server's
threads: everything is behind one lock, readings are immutable once made.

Alarm events (raised, cleared) are numbered and the last :data:`KEEP_EVENTS` kept:
``/api/status`` shows the active alarms and the newest events.
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from trifuse.app.latest_worker import LatestWorker
from trifuse.app.recording.layout import ALARM_NOTE, SETTINGS_NOTE
from trifuse.app.recording.writer import Note
from trifuse.fusion.alarms import AlarmEvent, AlarmRule, AlarmTracker
from trifuse.fusion.measure import Measurement, measure_regions
from trifuse.fusion.regions import Region
from trifuse.fusion.spot import SpotFrame
from trifuse.fusion.thermography import ObjectParameters

MAX_SHARE = 0.2
"""The largest share of a core the readings take: after a reading that cost c seconds of CPU
the next one waits at least c / MAX_SHARE of frame time."""
MAX_WAIT_S = 2.0
"""The longest frame time between two readings, seconds (alarms must still come)."""
KEEP_EVENTS = 200
"""Alarm events kept (the newest)."""
STATUS_EVENTS = 20
"""Alarm events ``/api/status`` shows (the newest)."""


@dataclass(frozen=True)
class Readings:
    """What the regions read on one picture.

    Attributes:
        stamp_ns: the picture's stamp.
        regions: name -> :class:`fusion.measure.Measurement`, the regions that could be read.
        errors: name -> one line, the regions that could not (outside the picture).
        params: the object parameters they were read with.
    """

    stamp_ns: int
    regions: dict[str, Measurement]
    errors: dict[str, str]
    params: ObjectParameters


class Measurements:
    """Object parameters, regions, alarm rules; the last readings and the alarm events."""

    def __init__(self, interval_s: float = 0.1) -> None:
        self.interval_s = interval_s
        self.wait_s = interval_s
        """Frame time between two readings now: :attr:`interval_s`, or longer after a
        costly reading (:data:`MAX_SHARE`)."""
        self._worker: LatestWorker[SpotFrame] | None = None
        self.on_note: Callable[[Note], None] | None = None
        """Given each alarm event and each change of the settings (the console's recorder:
        kept in a recording running then, docs/FORMATS.md "Measurement notes")."""
        self._stamp_ns = 0  # the newest picture handed over: a note's time
        self._frame: SpotFrame | None = None  # read again after a change (a paused replay)
        self._lock = threading.Lock()
        self._params = ObjectParameters()
        self._regions: tuple[Region, ...] = ()
        self._tracker = AlarmTracker([])
        self._readings: Readings | None = None
        self._last_s: float | None = None
        self._events: deque[tuple[int, AlarmEvent]] = deque(maxlen=KEEP_EVENTS)
        self._seq = itertools.count(1)

    # -- settings (any thread) ------------------------------------------------------------

    @property
    def params(self) -> ObjectParameters:
        return self._params

    def set_params(self, params: ObjectParameters) -> None:
        with self._lock:
            self._params = params
            self._last_s = None  # read again at the next picture
        self._changed()

    @property
    def regions(self) -> tuple[Region, ...]:
        return self._regions

    def set_regions(self, regions: Sequence[Region], size: tuple[int, int]) -> None:
        """Replace the regions. ValueError (nothing changed) for two of one name, a region
        outside the (width, height) picture, or an alarm left on a region no more there."""
        names = [r.name for r in regions]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"regions: names must be unique, {', '.join(twice)} more than once")
        for r in regions:
            r.mask(*size)  # ValueError naming it when it covers none of the picture
        with self._lock:
            orphans = sorted({a.region for a in self._tracker.rules} - set(names))
            if orphans:
                raise ValueError(
                    f"regions: alarms watch {', '.join(orphans)}: remove those alarms first"
                )
            self._regions = tuple(regions)
            self._last_s = None
        self._changed()

    def edit_region(self, name: str, region: Region, size: tuple[int, int]) -> None:
        """Put ``region`` in the place of the region called ``name`` (its name may be new:
        the alarms watching it follow it, raised ones staying raised). KeyError when there
        is none of that name; ValueError (nothing changed) for a name another region has or
        a region outside the (width, height) picture."""
        region.mask(*size)
        with self._lock:
            names = [r.name for r in self._regions]
            if name not in names:
                raise KeyError(name)
            if region.name != name and region.name in names:
                raise ValueError(f"name: another region is called {region.name!r}")
            self._regions = tuple(region if r.name == name else r for r in self._regions)
            if region.name != name:
                rules = [
                    dataclasses.replace(a, region=region.name) if a.region == name else a
                    for a in self._tracker.rules
                ]
                self._tracker = self._tracker.with_rules(rules, {name: region.name})
            self._last_s = None
        self._changed()

    @property
    def rules(self) -> tuple[AlarmRule, ...]:
        return tuple(self._tracker.rules)

    def set_rules(self, rules: Sequence[AlarmRule]) -> None:
        """Replace the alarm rules (an alarm raised and still among them stays raised: no
        second event; the others start anew). ValueError (nothing changed)
        for a rule on a region that does not exist, or a rule given twice."""
        with self._lock:
            names = {r.name for r in self._regions}
            unknown = sorted({a.region for a in rules} - names)
            if unknown:
                raise ValueError(f"alarms: no region named {', '.join(unknown)}")
            keys = [a.key for a in rules]
            if len(set(keys)) != len(keys):
                raise ValueError("alarms: the same rule is given twice")
            self._tracker = self._tracker.with_rules(list(rules))
            self._last_s = None
        self._changed()

    def _changed(self) -> None:
        """After a change of the settings: note them, and read the newest picture again (a
        paused replay makes no new one; its alarms must still be judged)."""
        self.note_settings()
        if self._frame is not None:
            self.submit(self._frame)

    def settings(self) -> dict[str, object]:
        """The object parameters, regions and alarm rules in force (JSON-able)."""
        with self._lock:
            return {
                "parameters": dataclasses.asdict(self._params),
                "regions": [dataclasses.asdict(r) for r in self._regions],
                "alarms": [dataclasses.asdict(a) for a in self._tracker.rules],
            }

    def note_settings(self) -> None:
        """Give :attr:`on_note` the settings in force (at the newest picture's time)."""
        if self.on_note is not None:
            self.on_note(Note(self._stamp_ns, SETTINGS_NOTE, "info", self.settings()))

    # -- readings -------------------------------------------------------------------------

    def submit(self, frame: SpotFrame) -> None:
        """Hand over a picture's capture (the fusion thread; never waits): read in the
        ``measurements`` thread when it is due."""
        self._stamp_ns, self._frame = frame.stamp_ns, frame
        if not self._regions and self._readings is None:
            return
        if self._worker is None:
            self._worker = LatestWorker(self.update, name="measurements").start()
        self._worker.submit(frame)

    @property
    def idle(self) -> bool:
        """No picture waits to be read and no reading is under way."""
        return self._worker is None or not self._worker.busy

    def close(self) -> None:
        """Stop the ``measurements`` thread (a reading under way finishes)."""
        if self._worker is not None:
            self._worker.stop()

    def update(self, frame: SpotFrame) -> None:
        """Read the regions on ``frame`` (throttled, see the module docstring) and track the
        alarms; a region outside the picture is reported, the others are read."""
        t = frame.stamp_ns * 1e-9
        with self._lock:
            regions, params, tracker = self._regions, self._params, self._tracker
            if not regions:
                self._readings = None
                return
            if self._last_s is not None and 0 <= t - self._last_s < self.wait_s:
                return
            self._last_s = t
        cpu0 = time.thread_time()
        readings = _read(frame, regions, params)
        cost_s = time.thread_time() - cpu0  # the first reading's includes making tables
        self.wait_s = min(MAX_WAIT_S, max(self.interval_s, cost_s / MAX_SHARE))
        with self._lock:
            if tracker is not self._tracker or regions is not self._regions:
                return  # changed meanwhile: the next picture reads with the new ones
            events = tracker.update(t, {n: m.object for n, m in readings.regions.items()})
            self._readings = readings
            self._events.extend((next(self._seq), e) for e in events)
        if self.on_note is not None:
            for e in events:
                level = "warning" if e.state == "raised" else "info"
                self.on_note(Note(frame.stamp_ns, ALARM_NOTE, level, e.as_dict()))

    def read_now(self, frame: SpotFrame) -> Readings | None:
        """The regions read on ``frame`` now (no alarm tracked, nothing kept): for a client
        asking before the fusion thread read any picture with these regions. None without
        a region."""
        regions, params = self._regions, self._params
        return _read(frame, regions, params) if regions else None

    @property
    def readings(self) -> Readings | None:
        """The last readings (None before the first, or with no region)."""
        return self._readings

    def events(self, after: int = 0) -> list[dict[str, object]]:
        """Alarm events numbered above ``after`` (oldest first), as JSON-able dicts."""
        with self._lock:
            return [{"seq": k, **e.as_dict()} for k, e in self._events if k > after]

    def status(self) -> dict[str, object]:
        """For ``/api/status``: regions, the active alarms and the newest events."""
        with self._lock:
            active = sorted(self._tracker.active)
            recent = list(self._events)[-STATUS_EVENTS:]
            readings = self._readings
        return {
            "regions": len(self._regions),
            "active_alarms": active,
            "events": [{"seq": k, **e.as_dict()} for k, e in recent],
            "readings_stamp_ns": None if readings is None else readings.stamp_ns,
        }


def _read(frame: SpotFrame, regions: Sequence[Region], params: ObjectParameters) -> Readings:
    """Each region read on ``frame``; one outside the picture is an error line, the others
    are read."""
    read: dict[str, Measurement] = {}
    errors: dict[str, str] = {}
    for region in regions:
        try:
            read.update(measure_regions(frame, [region], params))
        except ValueError as exc:
            errors[region.name] = str(exc)
    return Readings(frame.stamp_ns, read, errors, params)
