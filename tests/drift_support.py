"""Shared by the drift tests: the simulated inspection room rendered with a turned sensor,
and the drift check run over its instants."""

from __future__ import annotations

import dataclasses

import numpy as np

from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import rotation_from_rvec
from trifuse.fusion.drift import DriftCheck, DriftReport

TIMES_S = (1.0, 6.0, 11.0, 16.0, 21.0, 26.0)
"""Instants over the head's 30 s pan (different views of the room)."""


def turned(rig: Rig, name: str, rotation_deg: tuple[float, float, float]) -> Rig:
    s = rig[name]
    T = s.T_rig_sensor.copy()
    T[:3, :3] = T[:3, :3] @ rotation_from_rvec(np.radians(rotation_deg))
    return rig.with_sensor(dataclasses.replace(s, T_rig_sensor=T))


def render(rig: Rig, times: tuple[float, ...]) -> list[tuple[float, dict]]:
    scenario = InspectionScenario(rig=rig, live=True, seed=5)
    return [(t, scenario.render(t)[0].frames) for t in times]


def run(rig: Rig, frames: list[tuple[float, dict]]) -> DriftReport:
    check = DriftCheck(rig)
    for t, fs in frames:
        check.measure(t, fs)
    return check.report()
