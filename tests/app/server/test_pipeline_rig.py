"""Replacing the rig the console fuses with (a new calibration put to use)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.support import ListSource, wait_until
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.rig import Rig


def test_set_rig_takes_effect_with_the_next_frame_set(calibration_frame_sets) -> None:
    rig = default_rig()
    pipeline = FusionPipeline(ListSource(), rig, FrameHub())
    T = rig["ccd_right"].T_rig_sensor.copy()
    T[0, 3] += 0.01
    moved = Rig(
        sensors={
            **rig.sensors,
            "ccd_right": dataclasses.replace(rig["ccd_right"], T_rig_sensor=T),
        },
        reference=rig.reference,
        eyes=rig.eyes,
    )
    pipeline.set_rig(moved)
    assert pipeline.rig is rig  # not before the fusion thread's next frame set
    pipeline.source = ListSource.of_sets(calibration_frame_sets[:3])
    pipeline.start()
    wait_until(lambda: pipeline.status.frames_out >= 2, "two fused frame sets")
    pipeline.stop()
    assert pipeline.status.error is None and pipeline.status.frames_out >= 2
    assert pipeline.rig is moved and pipeline.fusion.ready
    assert np.allclose(pipeline.fusion.rig["ccd_right"].T_rig_sensor, T)


def test_set_rig_refuses_other_sensors(calibration_frame_sets) -> None:
    rig = default_rig()
    pipeline = FusionPipeline(ListSource(), rig, FrameHub())
    fewer = Rig(
        sensors={n: s for n, s in rig.sensors.items() if n != "thermal_right"},
        reference=rig.reference,
        eyes={},
    )
    with pytest.raises(ValueError, match="must match the console's"):
        pipeline.set_rig(fewer)
    assert pipeline.rig is rig
    # nothing is left to swap in at the next frame sets: the rig stays
    pipeline.source = ListSource.of_sets(calibration_frame_sets[:3])
    pipeline.start()
    wait_until(lambda: pipeline.status.frames_out >= 2, "two fused frame sets")
    pipeline.stop()
    assert pipeline.status.error is None and pipeline.rig is rig
