"""Each setting's limits are declared once (app/server/settings_spec.py): the REST models'
schema limits and descriptions and the Viser controls' ranges are the declaration's."""

from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path
from typing import Any

import pytest
import viser

from tests.support import small_rig, synth_frames, write_recording
from trifuse.app.recording import ReplaySource
from trifuse.app.server.panels.display import Panels
from trifuse.app.server.panels.source import SourcePanel
from trifuse.app.server.routers.api import FusionSettings, ThermalSettings
from trifuse.app.server.routers.session_api import RangeStart
from trifuse.app.server.routers.source_api import RateRequest, SeekRequest
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl, check_rate
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.settings_spec import (
    EDGE_STRENGTH,
    HOLDOUT_EVERY,
    MANUAL_OFFSET_K,
    MAX_GAIN,
    OPACITY,
    PLATEAU,
    REPLAY_RATE,
    SEEK_POSITION_S,
    SETTINGS,
    SPAN_SMOOTHING_S,
    Setting,
)
from trifuse.calib.board import Board
from trifuse.calib.radiometry import Radiometry
from trifuse.fusion.compose import DisplaySettings

MODELS = {  # setting -> the API model that takes it
    OPACITY: FusionSettings,
    EDGE_STRENGTH: FusionSettings,
    PLATEAU: FusionSettings,
    MAX_GAIN: FusionSettings,
    SPAN_SMOOTHING_S: ThermalSettings,
    MANUAL_OFFSET_K: ThermalSettings,
    REPLAY_RATE: RateRequest,
    SEEK_POSITION_S: SeekRequest,
    HOLDOUT_EVERY: RangeStart,
}

GUI_LABELS = {  # setting -> the label of its Viser control
    OPACITY: "Opacity",
    EDGE_STRENGTH: "Edge strength",
    PLATEAU: "Plateau (%)",
    MAX_GAIN: "Max gain (steps/K)",
    SPAN_SMOOTHING_S: "Span smoothing (s)",
    MANUAL_OFFSET_K: "Offset thermal_left (K)",
    REPLAY_RATE: "Speed (x)",
}


def _property(setting: Setting) -> dict[str, Any]:
    """The JSON schema of the setting's field (a number: the non-null branch; the values of
    a per-imager map)."""
    prop = MODELS[setting].model_json_schema()["properties"][setting.name]
    if "additionalProperties" in prop:
        prop = prop["additionalProperties"]
    branches = [p for p in prop.get("anyOf", [prop]) if p.get("type") != "null"]
    assert len(branches) == 1
    return {**prop, **branches[0]}


def test_every_declared_setting_has_an_api_field() -> None:
    assert set(MODELS) == set(SETTINGS)


@pytest.mark.parametrize("setting", SETTINGS, ids=lambda s: s.name)
def test_the_api_limits_are_the_declaration(setting: Setting) -> None:
    prop = _property(setting)
    assert prop.get("minimum") == setting.min
    assert prop.get("maximum") == setting.max
    assert prop.get("description") == setting.description
    if setting.default is not ...:
        assert prop.get("default") == setting.default


@pytest.mark.parametrize("setting", SETTINGS, ids=lambda s: s.name)
def test_the_api_refuses_what_the_declaration_excludes(setting: Setting) -> None:
    model = MODELS[setting]
    for bad, word in ((setting.min, "greater"), (setting.max, "less")):
        if bad is None:
            continue
        outside = bad - 1 if word == "greater" else bad + 1
        value = {"x": outside} if setting is MANUAL_OFFSET_K else outside
        with pytest.raises(ValueError, match=f"{word} than or equal to"):
            model.model_validate({setting.name: value})


@pytest.fixture(scope="module")
def gui_controls(tmp_path_factory) -> dict[str, tuple]:
    """label -> (kind, min, max, step) of every slider and number input the Source panel
    (over a replay) and the Display panels make."""
    made: dict[str, tuple] = {}
    api = viser.GuiApi
    slider, number = api.add_slider, api.add_number

    def add_slider(self, label, min, max, step, initial_value, **kw):
        made[label] = ("slider", min, max, step)
        return slider(self, label, min, max, step, initial_value, **kw)

    def add_number(self, label, initial_value, min=None, max=None, step=None, **kw):
        made[label] = ("number", min, max, step)
        return number(self, label, initial_value, min=min, max=max, step=step, **kw)

    rig = small_rig()
    path = tmp_path_factory.mktemp("spec") / "r.mcap"
    write_recording(Path(path), rig, synth_frames(rig, 1.0, seed=3))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(api, "add_slider", add_slider)
        mp.setattr(api, "add_number", add_number)
        with contextlib.redirect_stdout(io.StringIO()):
            server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        try:
            pipeline = FusionPipeline(SourceTap(ReplaySource(path)), rig, FrameHub())
            ctx = ConsoleContext(
                server=server,
                source=pipeline.source,
                description="test",
                hub=pipeline.hub,
                pipeline=pipeline,
                board=Board(9, 6, 0.04),
                board_watch=None,
            )
            SourcePanel(ctx, SourceControl(pipeline, pipeline.hub, "test"))
            Panels(ctx)
        finally:
            server.stop()
    return made


@pytest.mark.parametrize("setting", list(GUI_LABELS), ids=lambda s: s.name)
def test_the_gui_limits_are_the_declaration(setting: Setting, gui_controls) -> None:
    kind, lo, hi, step = gui_controls[GUI_LABELS[setting]]
    if kind == "slider":
        assert (lo, hi, step) == setting.slider()
    else:
        n = setting.number()
        assert (lo, hi, step) == (n.get("min"), n.get("max"), n.get("step"))


def test_a_gui_range_narrower_than_the_api_is_inside_it() -> None:
    for setting in GUI_LABELS:
        lo, hi = setting.gui_limits
        s = setting.gui_scale
        assert lo is None or setting.min is None or lo >= setting.min * s
        assert hi is None or setting.max is None or hi <= setting.max * s


CORE_CHECKS = {  # setting -> the check that has the last word (the pure core, the runtime)
    OPACITY: lambda v: DisplaySettings(opacity=v),
    EDGE_STRENGTH: lambda v: DisplaySettings(edge_strength=v),
    PLATEAU: lambda v: DisplaySettings(plateau=v),
    MAX_GAIN: lambda v: DisplaySettings(max_gain=v),
    SPAN_SMOOTHING_S: lambda v: DisplaySettings(span_smoothing_s=v),
    MANUAL_OFFSET_K: lambda v: Radiometry(manual_offset_k=v),
    REPLAY_RATE: check_rate,
}


@pytest.mark.parametrize("setting", list(CORE_CHECKS), ids=lambda s: s.name)
def test_the_core_takes_the_declared_limits_and_refuses_beyond(setting: Setting) -> None:
    check = CORE_CHECKS[setting]
    assert setting.min is not None and setting.max is not None
    check(setting.min)
    check(setting.max)
    for beyond in (math.nextafter(setting.min, -math.inf), math.nextafter(setting.max, math.inf)):
        with pytest.raises(ValueError, match=setting.name):
            check(beyond)
