"""Temperature alarms (fusion.alarms): raised on passing the limit, cleared only past the
hysteresis, rates of rise over their own window, nothing from a region without a reading."""

from __future__ import annotations

import numpy as np
import pytest

from trifuse.fusion.alarms import AlarmRule, AlarmTracker
from trifuse.fusion.regions import RegionReading


def reading(name: str, max_k: float | None, min_k: float | None = None) -> RegionReading:
    if max_k is None:
        return RegionReading(name, 0, None, None, None, None, None)
    low = max_k if min_k is None else min_k
    return RegionReading(name, 10, max_k, low, (max_k + low) / 2, (0, 0), (1, 1))


def test_above_is_raised_once_and_cleared_past_the_hysteresis() -> None:
    """Noise of 0.2 K on a 350 K limit raises once; it clears only below 349.5 K."""
    tracker = AlarmTracker([AlarmRule("pipe", "above", 350.0, hysteresis=0.5)])
    values = [349.0, 350.1, 349.9, 350.2, 349.8, 349.6, 349.4, 351.0]
    events = [
        (t, e.state)
        for t, v in enumerate(values)
        for e in tracker.update(t, {"pipe": reading("pipe", v)})
    ]
    assert events == [(1, "raised"), (6, "cleared"), (7, "raised")]


def test_below_watches_the_minimum() -> None:
    tracker = AlarmTracker([AlarmRule("tank", "below", 275.0)])
    e = tracker.update(0.0, {"tank": reading("tank", 290.0, 274.0)})
    assert [(x.state, x.value, x.as_dict()["kind"]) for x in e] == [("raised", 274.0, "below")]


def test_a_rise_faster_than_its_rate_over_its_window() -> None:
    """A maximum climbing 0.1 K/s, then 1 K/s: a 0.5 K/s rule over 5 s is raised once the
    window holds the faster climb (about 3 s into it), not before."""
    tracker = AlarmTracker([AlarmRule("motor", "rise", 0.5, hysteresis=0.1, window_s=5.0)])
    t = np.arange(0.0, 30.0, 0.5)
    v = np.where(t < 20, 300 + 0.1 * t, 302 + 1.0 * (t - 20))
    raised = [
        s
        for s, x in zip(t, v, strict=True)
        for e in tracker.update(float(s), {"motor": reading("motor", float(x))})
        if e.state == "raised"
    ]
    assert len(raised) == 1 and 21.0 <= raised[0] <= 23.5, raised


def test_a_region_without_a_reading_changes_nothing() -> None:
    tracker = AlarmTracker([AlarmRule("r", "above", 300.0)])
    assert tracker.update(0.0, {"r": reading("r", 310.0)})[0].state == "raised"
    assert tracker.update(1.0, {"r": reading("r", None)}) == []
    assert tracker.update(2.0, {}) == [] and tracker.active == {"r above 300"}


def test_new_rules_keep_the_raised_alarms_that_stay_and_follow_a_rename() -> None:
    """A rule added beside a raised one: the raised one raises no second event; a renamed
    region's raised alarm and its rise history follow it; a removed rule's state goes."""
    hot, rise = AlarmRule("pipe", "above", 350.0), AlarmRule("pipe", "rise", 0.5, window_s=5.0)
    tracker = AlarmTracker([hot, rise])
    for t, v in enumerate([351.0, 351.2]):  # raised; 0.2 K/s: the rise is not
        tracker.update(float(t), {"pipe": reading("pipe", v)})
    assert tracker.active == {"pipe above 350"}
    cold = AlarmRule("tank", "below", 275.0)
    tracker = tracker.with_rules([hot, rise, cold])
    assert tracker.update(2.0, {"pipe": reading("pipe", 351.4)}) == []
    renamed = [
        AlarmRule("main pipe", "above", 350.0),
        AlarmRule("main pipe", "rise", 0.5, window_s=5.0),
    ]
    tracker = tracker.with_rules(renamed, {"pipe": "main pipe"})
    assert tracker.active == {"main pipe above 350"}
    [event] = tracker.update(3.0, {"main pipe": reading("main pipe", 353.0)})  # 0.67 K/s
    assert (event.rule.kind, event.state) == ("rise", "raised")  # over the kept history
    tracker = tracker.with_rules([renamed[1]])
    assert tracker.active == {"main pipe rise 0.5"}
    tracker = tracker.with_rules(renamed)  # the above alarm added again: it starts anew
    assert [
        e.rule.kind for e in tracker.update(4.0, {"main pipe": reading("main pipe", 354.0)})
    ] == ["above"]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"kind": "hotter"}, "kind: expected above, below or rise"),
        ({"threshold": float("nan")}, "threshold: expected a finite number"),
        ({"window_s": 0.0}, "window_s: expected > 0"),
    ],
)
def test_a_wrong_rule_is_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        AlarmRule(**{"region": "r", "kind": "above", "threshold": 300.0, **kwargs})
