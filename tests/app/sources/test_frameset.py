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


def test_the_stereo_grouping_falls_back_to_the_right_camera() -> None:
    """The console's grouping: the left colour camera opens the sets; while it is silent
    (more than 0.5 s and 3 of the right camera's frames), the right one does."""
    asm = FrameSetAssembler.stereo(["ccd_left", "ccd_right", "tof"], tolerance_s=0.01)
    assert (asm.reference, asm.fallback, asm.tolerance_ns) == ("ccd_left", "ccd_right", 10**7)
    sets = asm.push(Frame("ccd_left", 0, IMG))
    for k in range(1, 40):  # the left camera has stopped
        sets += asm.push(Frame("ccd_right", k * 33_000_000, IMG))
    opened = [fs for fs in sets if "ccd_left" in fs.missing]
    assert opened and all(fs.stamp_ns > 500_000_000 for fs in opened)


def test_a_replay_that_loops_starts_a_new_time_line() -> None:
    """A looping replay goes back 2 s: the sets still waiting come out, and the first sets
    of the new pass wait for its own frames instead of reporting the old pass's as seconds
    in the future ("latest -1.97 s old")."""
    rates = {"ccd_left": 30.0, "thermal_left": 27.0, "tof": 15.0}
    one = stream(rates, 2.0)
    src = ListSource(one + one)  # the same 2 s twice: time goes back at the seam
    sets = list(frame_sets(src, ["ccd_left", "thermal_left", "tof"], tolerance_s=0.04))
    assert len(sets) == 120
    assert [fs.stamp_ns for fs in sets[60:]] == [fs.stamp_ns for fs in sets[:60]]
    for fs in sets:
        assert not fs.missing, (fs.stamp_ns, fs.missing)


def test_frames_late_by_less_than_a_second_stay_in_their_time_line() -> None:
    """A live device's frame that arrives after newer frames of other sensors (a thermal
    core's latency) is grouped as usual, not taken for a new time line."""
    asm = FrameSetAssembler(["ccd_left", "thermal_left"], tolerance_s=0.05)
    out = []
    for k in range(10):  # the thermal frame of each instant arrives 0.3 s (9 frames) late
        out += asm.push(Frame("ccd_left", k * 33_333_333, IMG))
    for k in range(10):
        out += asm.push(Frame("thermal_left", k * 33_333_333, IMG))
    out += asm.flush()
    assert len(out) == 10
    assert sum("thermal_left" in fs.frames for fs in out) >= 1  # the last set waited for it
