"""The Thermal map folder's hot-spot count (app/server/panels/map_panel.py): shown only once
it has been counted at the threshold on screen."""

from __future__ import annotations

import math
from types import SimpleNamespace

from trifuse.app.server.panels.map_panel import MapPanel
from trifuse.app.server.runtime.context import ConsoleBandwidth
from trifuse.app.server.runtime.map_worker import MapWorker
from trifuse.app.sources.sim.head import default_rig
from trifuse.fusion.compose import DisplaySettings


def test_the_hot_spot_count_waits_for_a_redraw_at_its_threshold(server, tmp_path) -> None:
    """Viser sets a control's value before its callback asks for a redraw; a status written
    in between said "0 points at or above 50 °C" of a map never counted (a browser test read
    that on a loaded machine). Until the map is drawn at the threshold shown, the status
    says it is counting."""
    pipeline = SimpleNamespace(rig=default_rig(), settings=DisplaySettings(), set_listeners=[])
    worker = MapWorker(pipeline, None, tmp_path)  # type: ignore[arg-type]
    ctx = SimpleNamespace(server=server, pipeline=pipeline, bandwidth=ConsoleBandwidth())
    panel = MapPanel(ctx, worker)  # type: ignore[arg-type]
    worker.set_enabled(True)
    panel.tick()  # drawn without the highlight: nothing counted
    assert "points at or above" not in panel.status_md.content
    panel.highlight.value = True  # the click has arrived (a value set here runs the
    panel._next_draw = math.inf  # callback at once: its redraw is undone, as if not yet run)
    panel.tick()
    assert "Counting the points at or above 50 °C" in panel.status_md.content
    panel._redraw_now()  # the callback
    panel.tick()
    assert "0 points at or above 50 °C" in panel.status_md.content  # an empty map, counted
    assert "Counting" not in panel.status_md.content
    panel.threshold_c.value = 60.0
    panel._next_draw = math.inf
    panel.tick()
    assert "Counting the points at or above 60 °C" in panel.status_md.content
