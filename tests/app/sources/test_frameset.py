"""Grouping frames that arrive at different rates into frame sets."""

from __future__ import annotations

import numpy as np
import pytest

from tests.support import ListSource
from trifuse.app.sources.base import FrameSetAssembler, frame_sets
from trifuse.app.sources.frames import Frame

IMG = np.zeros((2, 2), np.float32)


def stream(rates: dict[str, float], seconds: float, drop: dict[str, float] | None = None):
    """Frames of each sensor at its rate, merged in time order; ``drop`` stops a sensor
    after that many seconds (a sensor that dies)."""
    frames = []
    for s, hz in rates.items():
        for k in range(int(seconds * hz)):
            t = k / hz
            if drop and s in drop and t >= drop[s]:
                break
            frames.append(Frame(s, round(t * 1e9), IMG))
    return sorted(frames, key=lambda f: f.stamp_ns)


def test_sensors_at_different_rates_are_grouped_by_nearest_time() -> None:
    rates = {"ccd_left": 30.0, "thermal_left": 27.0, "tof": 15.0}
    src = ListSource(stream(rates, 2.0))
    sets = list(frame_sets(src, ["ccd_left", "thermal_left", "tof"], tolerance_s=0.04))
    assert len(sets) == 60  # one per reference (colour) frame
    for fs in sets:
        assert not fs.missing, fs.missing
        for s, f in fs.frames.items():
            # Nearest frame: within half the sensor's period of the reference time.
            assert abs(f.stamp_ns - fs.stamp_ns) <= 0.5e9 / rates[s] + 1, s


def test_a_dead_sensor_is_reported_and_never_blocks_the_others() -> None:
    rates = {"ccd_left": 30.0, "tof": 15.0}
    frames = stream(rates, 2.0, drop={"tof": 1.0})
    asm = FrameSetAssembler(["ccd_left", "tof"], tolerance_s=0.05)
    emitted = []
    for f in frames:
        emitted += asm.push(f)
    emitted += asm.flush()
    assert len(emitted) == 60
    late = [fs for fs in emitted if fs.stamp_ns > 1.1e9]
    assert late and all("tof" in fs.missing and "tof" not in fs.frames for fs in late)
    assert "s old" in late[-1].missing["tof"]


def test_a_sensor_never_seen_is_reported() -> None:
    asm = FrameSetAssembler(["ccd_left", "thermal_left"])
    sets = asm.push(Frame("ccd_left", 0, IMG)) + asm.push(Frame("ccd_left", 33_000_000, IMG))
    assert sets[0].missing == {"thermal_left": "no frame received yet"}


def test_unknown_sensors_are_ignored_and_bad_arguments_rejected() -> None:
    asm = FrameSetAssembler(["ccd_left"])
    assert asm.push(Frame("lidar", 0, IMG)) == []
    with pytest.raises(ValueError, match="reference"):
        FrameSetAssembler(["ccd_left"], reference="tof")
    with pytest.raises(ValueError, match="at least one"):
        FrameSetAssembler([])
