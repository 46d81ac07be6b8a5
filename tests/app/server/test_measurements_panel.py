"""The console's Measurements panel (app/server/panels/measurements.py) on a real Viser
server over the console's Measurements: the fields set the object parameters (a material
its emissivity), a refused value says why and changes nothing, a change made over REST is
shown, and the raised alarms and the regions' readings appear."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from tests.measure_support import panel_boxes, render
from trifuse.app.server.panels.measurements import MeasurementsPanel
from trifuse.app.server.runtime.measurements import Measurements
from trifuse.app.sources.sim.head import default_rig
from trifuse.fusion.alarms import AlarmRule
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.regions import Region
from trifuse.fusion.spot import SpotMeter
from trifuse.fusion.stereo import StereoFusion
from trifuse.fusion.thermography import ObjectParameters


@pytest.fixture()
def panel(server) -> MeasurementsPanel:
    fusion = SimpleNamespace(size=(1280, 960))
    pipeline = SimpleNamespace(measurements=Measurements(), fusion=fusion)
    ctx = SimpleNamespace(server=server, pipeline=pipeline)
    return MeasurementsPanel(ctx)  # type: ignore[arg-type]


def test_fields_set_the_parameters_and_a_material_its_emissivity(panel) -> None:
    panel.air.value = 15.0
    panel.humidity.value = 95.0
    panel.material.value = "oxidised steel"
    p = panel.m.params
    assert p.emissivity == 0.8 and p.air_k == pytest.approx(288.15) and p.humidity_pct == 95.0
    assert panel.emissivity.value == 0.8


def test_a_refused_value_says_why_and_changes_nothing(panel) -> None:
    before = panel.m.params
    panel.humidity.value = 120.0  # beyond the field's bound, as a script could send
    assert "humidity_pct: expected 0 to 100" in panel.message.content
    assert panel.m.params == before


def test_a_change_over_rest_is_shown(panel) -> None:
    panel.m.set_params(ObjectParameters(emissivity=0.5, reflected_k=250.0))
    panel.tick()
    assert panel.emissivity.value == 0.5 and panel.reflected.value == pytest.approx(-23.15)
    assert panel.m.params.emissivity == 0.5  # the sync wrote no half-changed parameters


def test_readings_and_a_raised_alarm_are_shown(panel) -> None:
    rig = default_rig()
    frames, truth = render()
    fusion = StereoFusion(rig)
    fusion.update_depth(frames["tof"].distance_m, frames["tof"].image)
    colors = {e: frames[rig.eyes[e].color].image for e in fusion.eyes}
    thermals = {e: frames[rig.eyes[e].thermal].image for e in fusion.eyes}
    fusion.compose(colors, thermals, DisplaySettings())
    m = panel.m
    m.set_regions([Region("hot", "left", "box", panel_boxes(truth)["hot"], 0.95)], fusion.size)
    panel.press_add()  # before the region is offered: refused, one line
    assert "Alarm not added" in panel.message.content and m.rules == ()
    panel.tick()  # the region is offered
    panel.alarm_region.value, panel.alarm_kind.value = "hot", "above"
    panel.alarm_value.value = 400.0 - 273.15
    panel.press_add()
    [rule] = m.rules
    assert (rule.region, rule.kind, rule.threshold) == ("hot", "above", pytest.approx(400.0))
    m.update(SpotMeter(fusion).capture(0))
    panel.tick()
    assert "hot above 400" in panel.alarms.content
    assert "| hot |" in panel.table.content and "°C" in panel.table.content
    assert panel.alert.visible and "ALARM: hot above 400" in panel.alert.content

    panel.press_clear()
    m.update(SpotMeter(fusion).capture(10**9))
    panel.tick()
    assert m.rules == () and not panel.alert.visible and panel.alarms.content == "No alarm."


def test_a_regions_emissivity_is_set_from_the_panel(panel) -> None:
    m = panel.m
    m.set_regions([Region("pipe", "left", "box", ((10.0, 10.0), (90.0, 60.0)))], (1280, 960))
    panel.tick()
    panel.region.value = "pipe"
    assert panel.region_name.value == "pipe" and panel.region_emissivity.value == 1.0
    panel.region_emissivity.value, panel.region_reflected.value = 0.8, -20.0
    panel.press_set_region()
    assert m.regions[0].emissivity == 0.8 and panel.message.content == ""
    assert m.regions[0].reflected_k == pytest.approx(253.15)
    m.set_rules([AlarmRule("pipe", "above", 350.0)])
    panel.region_name.value = "main pipe"
    panel.press_rename()  # the alarm follows
    assert [r.name for r in m.regions] == ["main pipe"] and m.rules[0].region == "main pipe"
    panel.tick()
    assert panel.region.value == "main pipe" and panel.message.content == ""
    panel.region_emissivity.value = 0.001  # as a script could send: refused, one line
    panel.press_set_region()
    assert "emissivity: expected 0.01 to 1" in panel.message.content
    assert m.regions[0].emissivity == 0.8
    m.set_rules([])
    m.set_regions([], (1280, 960))  # gone meanwhile (REST): refused, one line
    panel.press_set_region()
    assert "Not set" in panel.message.content and m.regions == ()
