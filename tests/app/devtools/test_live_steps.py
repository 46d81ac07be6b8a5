"""What a fused frame set needs, from its steps measured alone (benchmark ``live``)."""

from __future__ import annotations

import math

import pytest

from trifuse.app.devtools.live_steps import necessary_ms

COSTS = {
    "read_ccd_left_ms": 5.0,
    "read_ccd_right_ms": 5.0,
    "read_thermal_left_ms": 0.2,
    "read_tof_ms": 0.1,
    "map_ms": 30.0,
    "compose_ms": 16.0,
    "h264_ms": 11.0,
}


def test_each_step_is_weighed_by_how_often_a_set_needs_it() -> None:
    """At 20 sets a second from colour at 20 Hz, thermal at 27 Hz and TOF at 15 Hz of which
    10 a second were mapped: both colour frames, 1.35 thermal frames, 0.75 TOF frames read,
    half a mapping, one composition, and the encoding only for a video viewer."""
    rates = {"ccd_left": 20.0, "ccd_right": 20.0, "thermal_left": 27.0, "tof": 15.0}
    alone = 5.0 + 5.0 + 0.2 * 27 / 20 + 0.1 * 15 / 20 + 30.0 * 10 / 20 + 16.0
    assert necessary_ms(COSTS, rates, 20.0, 10.0, h264=False) == pytest.approx(alone)
    assert necessary_ms(COSTS, rates, 20.0, 10.0, h264=True) == pytest.approx(alone + 11.0)
    # a sensor without a measured read (another recording's) costs nothing here
    assert necessary_ms(COSTS, {**rates, "other": 30.0}, 20.0, 10.0, False) == pytest.approx(alone)
    assert math.isnan(necessary_ms(COSTS, rates, 0.0, 10.0, h264=False))  # nothing fused
