"""Measurements over a recording (``trifuse measure``, issue 35): each frame set fused as the
console fuses it, its regions read with the object parameters given (not those in force
when it was recorded: a recording keeps what the imagers measured, so emissivity, the
regions and the alarms may be chosen afterwards), one table row per frame set and region.

The plan file (YAML; :func:`plan_from_yaml`)::

    parameters:            # optional: fusion.thermography.ObjectParameters' defaults
      emissivity: 0.95
      reflected_k: 250.0
      air_k: 288.15
      humidity_pct: 95
      default_distance_m: 3.0
    regions:               # at least one
      - {name: plate, eye: left, shape: box, points: [[500, 600], [760, 780]], emissivity: 0.95}
      - {name: pipe, shape: polygon, points: [[10, 10], [200, 12], [190, 40]]}
    alarms:                # optional
      - {region: plate, kind: above, threshold: 400.0, hysteresis: 0.5}

The table (CSV, :data:`COLUMNS`): per frame set and region, the set's stamp and time from
the first set, the corrected (object) maximum, minimum and mean with where the extremes are,
the apparent mean, the pixels read and those that took the default distance, and the alarm
events of that set for that region (``raised above 400``; several joined by ``;``) and the
alarms active after it.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import yaml

from trifuse.app.recording.offline_sets import pictured_sets
from trifuse.app.recording.player import MessageReplay
from trifuse.calib.rig import Rig
from trifuse.fusion.alarms import AlarmRule, AlarmTracker
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.measure import Measurement, measure_regions
from trifuse.fusion.regions import Region
from trifuse.fusion.spot import SpotMeter
from trifuse.fusion.stereo_step import OFFLINE, StereoStep
from trifuse.fusion.thermography import ObjectParameters

READING_COLUMNS = (
    "pixels",
    "max_k",
    "min_k",
    "mean_k",
    "max_x",
    "max_y",
    "min_x",
    "min_y",
    "apparent_mean_k",
    "default_distance_px",
)
"""One region's reading in a table (:func:`reading_fields`)."""
COLUMNS = ("stamp_ns", "time_s", "region", *READING_COLUMNS, "events", "active_alarms")


@dataclass(frozen=True)
class MeasurePlan:
    """What to measure: the object parameters, the regions, the alarm rules."""

    params: ObjectParameters
    regions: tuple[Region, ...]
    rules: tuple[AlarmRule, ...] = ()


def _mapping(value: object, what: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ValueError(f"{what}: expected a mapping, got {type(value).__name__}")
    return value


def _build(cls: type, fields: Mapping[str, Any], what: str) -> Any:
    """``cls(**fields)`` with a bad key or value said in one line naming ``what``."""
    try:
        return cls(**fields)
    except TypeError as exc:  # an unknown or missing key: "X.__init__() got an ..."
        said = re.sub(r"^\S*__init__\(\) ", "", str(exc))
        raise ValueError(f"{what}: {said}") from None
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from None


def plan_from_yaml(text: str) -> MeasurePlan:
    """The plan of a plan file's text (module docstring); ValueError in one line saying
    what is wrong and where."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"not YAML: {' '.join(str(exc).split())}") from None
    return plan_from_mapping(data)


def plan_from_mapping(data: object) -> MeasurePlan:
    """The plan of a plan file's content (or of a recording's measurement settings note,
    which has the same keys); ValueError in one line."""
    data = _mapping(data, "the plan")
    unknown = sorted(set(data) - {"parameters", "regions", "alarms"})
    if unknown:
        raise ValueError(f"unknown keys {unknown}: expected parameters, regions, alarms")
    params = _build(ObjectParameters, _mapping(data.get("parameters") or {}, "parameters"),
                    "parameters")  # fmt: skip
    listed = data.get("regions")
    if not isinstance(listed, list) or not listed:
        raise ValueError("regions: expected a list of at least one region")
    regions = []
    for k, item in enumerate(listed):
        fields = dict(_mapping(item, f"regions[{k}]"))
        fields.setdefault("eye", "left")
        points = fields.get("points")
        if not isinstance(points, list) or not all(
            isinstance(p, list | tuple) and len(p) == 2 for p in points
        ):
            raise ValueError(f"regions[{k}]: points: expected a list of [x, y] pairs")
        fields["points"] = tuple((p[0], p[1]) for p in points)
        regions.append(_build(Region, fields, f"regions[{k}]"))
    names = [r.name for r in regions]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"regions: names must be unique, {', '.join(twice)} more than once")
    rules = []
    for k, item in enumerate(data.get("alarms") or []):
        rule = _build(AlarmRule, _mapping(item, f"alarms[{k}]"), f"alarms[{k}]")
        if rule.region not in names:
            raise ValueError(f"alarms[{k}]: no region named {rule.region!r}")
        rules.append(rule)
    return MeasurePlan(params, tuple(regions), tuple(rules))


def _number(value: float | None) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.3f}"


def reading_fields(m: Measurement) -> dict[str, str]:
    """One region's reading as text fields (:data:`READING_COLUMNS`; the snapshot's table
    has them too)."""
    o = m.object
    return {
        "pixels": str(o.pixels),
        "max_k": _number(o.max_k),
        "min_k": _number(o.min_k),
        "mean_k": _number(o.mean_k),
        "max_x": "" if o.max_at is None else str(o.max_at[0]),
        "max_y": "" if o.max_at is None else str(o.max_at[1]),
        "min_x": "" if o.min_at is None else str(o.min_at[0]),
        "min_y": "" if o.min_at is None else str(o.min_at[1]),
        "apparent_mean_k": _number(m.apparent.mean_k),
        "default_distance_px": str(m.default_distance_px),
    }


def measure_recording(
    source: MessageReplay, rig: Rig, plan: MeasurePlan, every: int = 1
) -> Iterator[dict[str, str]]:
    """One table row (:data:`COLUMNS` -> text) per region of every ``every``-th frame set
    of ``source`` that makes a picture (:data:`fusion.stereo_step.OFFLINE`: both eyes'
    colour and thermal frames after the first depth), in order. ValueError for a region
    outside the rig's pictures (before any set is read), or ``every`` below 1."""
    step = StereoStep(rig, DisplaySettings(mode="thermal", agc="linear"), OFFLINE)
    size = step.fusion.size
    for region in plan.regions:
        region.mask(*size)  # ValueError naming it
    meter = SpotMeter(step.fusion)
    tracker = AlarmTracker(list(plan.rules))
    first_ns: int | None = None
    for fs, _ in pictured_sets(source, step, every):
        frame = meter.capture(fs.stamp_ns)
        read = measure_regions(frame, plan.regions, plan.params)
        first_ns = fs.stamp_ns if first_ns is None else first_ns
        t = (fs.stamp_ns - first_ns) * 1e-9
        events = tracker.update(t, {n: m.object for n, m in read.items()})
        for region in plan.regions:
            said = [f"{e.state} {e.rule.kind} {e.rule.threshold:g}" for e in events
                    if e.rule.region == region.name]  # fmt: skip
            active = [r.key for r in plan.rules
                      if r.region == region.name and r.key in tracker.active]  # fmt: skip
            yield {
                "stamp_ns": str(fs.stamp_ns),
                "time_s": f"{t:.6f}",
                "region": region.name,
                **reading_fields(read[region.name]),
                "events": "; ".join(said),
                "active_alarms": "; ".join(active),
            }


def table_text(rows: Iterator[dict[str, str]]) -> str:
    """The rows as CSV text with the header :data:`COLUMNS`."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()
