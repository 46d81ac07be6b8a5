"""Temperature alarms on measurement regions (issue 35, item 3): above a limit, below a
limit, or rising faster than a rate, each raised and cleared as events.

A rule watches one region's reading (:class:`fusion.regions.RegionReading`): ``above`` its
maximum, ``below`` its minimum, ``rise`` the rate of its maximum over the last
``window_s`` seconds (kelvin a second, from the oldest reading in the window to the newest).
An alarm is raised when the value passes the threshold and cleared only once it is back by
``hysteresis`` (kelvin, or kelvin a second), so that noise on the limit does not make a
stream of events. A region without a reading (no pixel with a temperature) changes
nothing.

Pure: readings and times in (seconds, any increasing clock), events out.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from trifuse.fusion.regions import RegionReading

__all__ = ["AlarmEvent", "AlarmRule", "AlarmTracker"]

Kind = Literal["above", "below", "rise"]


@dataclass(frozen=True)
class AlarmRule:
    """One alarm: ``region``'s value against ``threshold`` (kelvin; for ``rise`` kelvin a
    second), cleared ``hysteresis`` back; ``window_s`` the rate's window (``rise``)."""

    region: str
    kind: Kind
    threshold: float
    hysteresis: float = 0.5
    window_s: float = 10.0

    def __post_init__(self) -> None:
        if self.kind not in ("above", "below", "rise"):
            raise ValueError(f"kind: expected above, below or rise, got {self.kind!r}")
        for name in ("threshold", "hysteresis", "window_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name}: expected a finite number, got {getattr(self, name)}")
        if self.hysteresis < 0 or self.window_s <= 0:
            raise ValueError("hysteresis: expected >= 0; window_s: expected > 0")

    @property
    def key(self) -> str:
        return f"{self.region} {self.kind} {self.threshold:g}"


@dataclass(frozen=True)
class AlarmEvent:
    """An alarm raised or cleared at ``time_s``, with the value that did it."""

    time_s: float
    rule: AlarmRule
    state: Literal["raised", "cleared"]
    value: float

    def as_dict(self) -> dict[str, object]:
        return {
            "time_s": self.time_s,
            "region": self.rule.region,
            "kind": self.rule.kind,
            "threshold": self.rule.threshold,
            "state": self.state,
            "value": self.value,
        }


@dataclass
class AlarmTracker:
    """The rules' states over time; :meth:`update` with each picture's readings."""

    rules: list[AlarmRule]
    active: set[str] = field(default_factory=set)
    _history: dict[str, deque[tuple[float, float]]] = field(default_factory=dict)

    def update(self, time_s: float, readings: Mapping[str, RegionReading]) -> list[AlarmEvent]:
        """Events raised or cleared by the readings of one instant (``time_s`` seconds)."""
        events: list[AlarmEvent] = []
        for region, reading in readings.items():
            windows = [r.window_s for r in self.rules if r.region == region and r.kind == "rise"]
            if reading.max_k is None or not windows:
                continue
            h = self._history.setdefault(region, deque())
            h.append((time_s, reading.max_k))
            while h[0][0] < time_s - max(windows):
                h.popleft()
        for rule in self.rules:
            value = self._value(rule, time_s, readings.get(rule.region))
            if value is None:
                continue
            sign = -1.0 if rule.kind == "below" else 1.0
            over = sign * (value - rule.threshold)
            if rule.key not in self.active and over > 0:
                self.active.add(rule.key)
                events.append(AlarmEvent(time_s, rule, "raised", value))
            elif rule.key in self.active and over < -rule.hysteresis:
                self.active.discard(rule.key)
                events.append(AlarmEvent(time_s, rule, "cleared", value))
        return events

    def with_rules(
        self, rules: list[AlarmRule], renamed: Mapping[str, str] | None = None
    ) -> AlarmTracker:
        """A tracker of ``rules`` that carries this one's states over: an alarm raised
        here and still among the rules stays raised (no second event), a region's history
        of maxima is kept; ``renamed``: old region name -> new (the states follow)."""
        renamed = renamed or {}

        def key(k: str, region: str) -> str:
            return renamed[region] + k[len(region) :] if region in renamed else k

        kept = {a.key for a in rules}
        regions = {a.region for a in rules}
        active = {key(a.key, a.region) for a in self.rules if a.key in self.active}
        history = {renamed.get(r, r): h for r, h in self._history.items()}
        return AlarmTracker(
            list(rules),
            active & kept,
            {r: h for r, h in history.items() if r in regions},
        )

    def _value(self, rule: AlarmRule, time_s: float, reading: RegionReading | None) -> float | None:
        if reading is None or reading.max_k is None or reading.min_k is None:
            return None
        if rule.kind == "above":
            return reading.max_k
        if rule.kind == "below":
            return reading.min_k
        h = self._history.get(rule.region)
        if not h:
            return None
        t0, v0 = next((tv for tv in h if tv[0] >= time_s - rule.window_s), h[-1])
        t1, v1 = h[-1]
        return None if t1 - t0 <= 0 else (v1 - v0) / (t1 - t0)
