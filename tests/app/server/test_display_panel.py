"""The Thermal folder's Auto-balance checkbox (app/server/panels/display.py) against the
balancer it drives: an operator's click survives the panel's refresh, and a change made
elsewhere (the REST API) is shown."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from tests.panel_support import display_panels
from trifuse.app.server.panels.display import Panels
from trifuse.app.server.runtime.thermal_balance import BalanceStatus
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.radiometry import Radiometry
from trifuse.fusion.compose import DisplaySettings


class _Balancer:
    """The part of ``ThermalBalancer`` the panel uses."""

    def __init__(self, auto: bool) -> None:
        self.auto, self.reference, self.status = auto, None, BalanceStatus()

    def set_auto(self, on: bool) -> None:
        self.auto = bool(on)


def _panels(server, balancer: _Balancer) -> Panels:
    t0 = 1_000_000_000_000
    pipeline = SimpleNamespace(
        rig=default_rig(),
        settings=DisplaySettings(),
        radiometry={"thermal_left": Radiometry(), "thermal_right": Radiometry()},
        latest_set=FrameSet(t0, {"ccd_left": Frame("ccd_left", t0, np.zeros((96, 128, 3)))}),
        fusion=SimpleNamespace(span_k=None),
        set_manual_offset=lambda name, k: None,
    )
    return display_panels(server, pipeline, SimpleNamespace(latest=None, enabled=False), balancer)


def test_a_click_on_auto_balance_survives_a_refresh_before_its_callback(server) -> None:
    """Viser sets the checkbox's value from the browser's message, then runs the callback
    (``apply``) in its own thread; a refresh of the panel in between used to write the
    balancer's old ``auto`` back onto the checkbox, and the callback then applied that: the
    click was lost (seen on a loaded machine: auto-balance never came on)."""
    balancer = _Balancer(auto=False)
    panels = _panels(server, balancer)
    assert panels.auto_balance.value is False
    panels.auto_balance.value = True  # the click has arrived ...
    panels.tick()  # ... the panel refreshes ...
    assert panels.auto_balance.value is True
    panels.apply()  # ... then its callback runs
    assert balancer.auto is True and panels.auto_balance.value is True


def test_auto_balance_set_elsewhere_is_shown(server) -> None:
    balancer = _Balancer(auto=True)
    panels = _panels(server, balancer)
    assert panels.auto_balance.value is True
    balancer.set_auto(False)  # PUT /api/thermal
    panels.tick()
    assert panels.auto_balance.value is False
    balancer.set_auto(True)
    panels.tick()
    assert panels.auto_balance.value is True
