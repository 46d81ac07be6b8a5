"""The console's Measurements panel (issue 35): the object parameters a thermographer sets
(a material or an emissivity, the reflected temperature, the air's temperature and humidity,
the distance where the TOF has none), each region's corrected reading, and the raised alarms
in an alert box. The same state as ``/api/object-parameters``, ``/api/measurements`` and
``/api/alarms`` (:class:`app.server.runtime.measurements.Measurements`), and alarms on the
regions (above, below: °C; rise: K/s); the regions come from the viewer or REST.
"""

from __future__ import annotations

import dataclasses

from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.panels.drift_health import alert_html
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.measurements import Measurements, Readings
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.fusion.alarms import AlarmRule
from trifuse.fusion.thermography import MATERIALS, ObjectParameters

K0 = 273.15
OWN = "(emissivity below)"
"""The material choice that leaves the emissivity as typed."""


def readings_md(readings: Readings | None, regions: int) -> str:
    """The regions' corrected readings as a markdown table (°C)."""
    if not regions:
        return (
            "No measurement region: draw one in the viewer (Measure: Spot, Polygon, Box → region)."
        )
    if readings is None:
        return "Reading the regions…"
    lines = ["| region | max | min | mean | no TOF px |", "|:--|--:|--:|--:|--:|"]
    for name, m in readings.regions.items():
        o = m.object
        if o.max_k is None or o.min_k is None or o.mean_k is None:
            lines.append(f"| {md_text(name)} | – | – | – | {m.default_distance_px} |")
            continue
        values = " | ".join(f"{v - K0:.1f} °C" for v in (o.max_k, o.min_k, o.mean_k))
        lines.append(f"| {md_text(name)} | {values} | {m.default_distance_px} |")
    for name, why in readings.errors.items():
        lines.append(f"| {md_text(name)} | {md_text(why)} | | | |")
    return "\n".join(lines)


class MeasurementsPanel(Periodic):
    """Builds the Measurements folder; :meth:`tick` shows the readings and alarms."""

    def __init__(self, ctx: ConsoleContext, rate_hz: float = 2.0) -> None:
        super().__init__("measurements-panel", 1.0 / rate_hz)
        self.m: Measurements = ctx.pipeline.measurements
        self.pipeline = ctx.pipeline  # its fusion's size: an eye's picture (after a new rig too)
        p = self.m.params
        gui = ctx.server.gui
        with gui.add_folder("Measurements", expand_by_default=False):
            self.alert = gui.add_html("", visible=False)
            self.material = gui.add_dropdown("Material", (OWN, *MATERIALS), initial_value=OWN)
            self.emissivity = gui.add_number(
                "Emissivity", p.emissivity, min=0.01, max=1.0, step=0.01
            )
            self.reflected = gui.add_number(
                "Reflected (°C)", round(p.reflected_k - K0, 2), step=0.1
            )
            self.air = gui.add_number("Air (°C)", round(p.air_k - K0, 2), step=0.1)
            self.humidity = gui.add_number(
                "Humidity (%)", p.humidity_pct, min=0.0, max=100.0, step=1.0
            )
            self.distance = gui.add_number(
                "No-TOF distance (m)", p.default_distance_m, min=0.0, max=10_000.0, step=0.1
            )
            self.message = gui.add_markdown("")
            self.table = gui.add_markdown(readings_md(None, 0))
            self.region = gui.add_dropdown("Region", ("(no region)",))
            self.region_emissivity = gui.add_number(
                "Its emissivity", 0.95, min=0.01, max=1.0, step=0.01
            )
            self.region_reflected = gui.add_number("Its reflected (°C)", 20.0, step=0.1)
            self.set_region = gui.add_button("Set the region's surface")
            self.region_name = gui.add_text("Rename it to", "")
            self.rename = gui.add_button("Rename the region")
            self.alarm_region = gui.add_dropdown("Alarm on", ("(no region)",))
            self.alarm_kind = gui.add_dropdown("When", ("above", "below", "rise"))
            self.alarm_value = gui.add_number("Threshold (°C; rise K/s)", 60.0, step=0.1)
            self.add_alarm = gui.add_button("Add alarm")
            self.clear_alarms = gui.add_button("Clear alarms")
            self.alarms = gui.add_markdown("")
        for handle in (self.emissivity, self.reflected, self.air, self.humidity, self.distance):
            handle.on_update(lambda _e: self.apply())
        self.material.on_update(lambda _e: self.choose())
        self._syncing = False  # tick() writes the fields: not an operator's change
        self.set_region.on_click(lambda _e: self.press_set_region())
        self.rename.on_click(lambda _e: self.press_rename())
        self.region.on_update(lambda _e: self.show_region())
        self.add_alarm.on_click(lambda _e: self.press_add())
        self.clear_alarms.on_click(lambda _e: self.press_clear())

    def _edit_region(self, what: str, **changes: object) -> None:
        """The chosen region with ``changes`` (Measurements.edit_region: alarms follow a
        new name); one line under the fields when refused."""
        name = self.region.value
        region = next((r for r in self.m.regions if r.name == name), None)
        try:
            if region is None:
                raise ValueError(f"no region named {name!r}")
            new = dataclasses.replace(region, **changes)  # type: ignore[arg-type]
            self.m.edit_region(name, new, self.pipeline.fusion.size)
        except (KeyError, ValueError) as exc:  # gone meanwhile, a value out of range
            self.message.content = f"**{what}:** {md_text(exc)}"
            return
        self.message.content = ""

    def press_set_region(self) -> None:
        """The chosen region gets the emissivity and reflected temperature typed (its own
        surface)."""
        self._edit_region(
            "Not set",
            emissivity=float(self.region_emissivity.value),
            reflected_k=float(self.region_reflected.value) + K0,
        )

    def press_rename(self) -> None:
        """The chosen region gets the name typed."""
        self._edit_region("Not renamed", name=self.region_name.value.strip())
        if not self.message.content:
            self.region.value = self.region_name.value.strip()

    def show_region(self) -> None:
        """The chosen region's surface (the global one's where it has none) in its fields."""
        region = next((r for r in self.m.regions if r.name == self.region.value), None)
        if region is None:
            return
        p = self.m.params
        eps = p.emissivity if region.emissivity is None else region.emissivity
        reflected = p.reflected_k if region.reflected_k is None else region.reflected_k
        self.region_emissivity.value = eps
        self.region_reflected.value = round(reflected - K0, 2)
        self.region_name.value = region.name

    def press_add(self) -> None:
        """Add the alarm the fields describe to the rules in force."""
        kind = self.alarm_kind.value
        value = float(self.alarm_value.value)
        threshold = value if kind == "rise" else value + K0
        try:
            rule = AlarmRule(self.alarm_region.value, kind, threshold)  # type: ignore[arg-type]
            self.m.set_rules([*self.m.rules, rule])
        except ValueError as exc:
            self.message.content = f"**Alarm not added:** {md_text(exc)}"
            return
        self.message.content = ""

    def press_clear(self) -> None:
        self.m.set_rules([])

    def choose(self) -> None:
        """A material sets the emissivity field (and the parameters)."""
        if self.material.value in MATERIALS:
            self.emissivity.value = MATERIALS[self.material.value]
        self.apply()

    def apply(self) -> None:
        """The fields as the object parameters; one line under them when refused."""
        if self._syncing:
            return
        try:
            params = ObjectParameters(
                emissivity=float(self.emissivity.value),
                reflected_k=float(self.reflected.value) + K0,
                air_k=float(self.air.value) + K0,
                humidity_pct=float(self.humidity.value),
                default_distance_m=float(self.distance.value),
            )
        except (TypeError, ValueError) as exc:
            self.message.content = f"**Not applied:** {md_text(exc)}"
            return
        if params != self.m.params:
            self.m.set_params(params)
        self.message.content = ""

    def tick(self) -> None:
        """The readings' table and the alert box of the raised alarms; fields that another
        client (REST) changed follow."""
        text = readings_md(self.m.readings, len(self.m.regions))
        if self.table.content != text:
            self.table.content = text
        names = tuple(r.name for r in self.m.regions) or ("(no region)",)
        for choice in (self.alarm_region, self.region):
            if tuple(choice.options) != names:
                choice.options = names
        rules = self.m.rules
        listed = "\n".join(f"- {md_text(r.key)}" for r in rules) or "No alarm."
        if self.alarms.content != listed:
            self.alarms.content = listed
        active = self.m.status()["active_alarms"]
        box = alert_html([f"⚠ ALARM: {key}" for key in active])  # type: ignore[union-attr]
        if self.alert.content != box:
            self.alert.content = box
        self.alert.visible = bool(box)
        p = self.m.params
        fields = (
            (self.emissivity, p.emissivity),
            (self.reflected, round(p.reflected_k - K0, 2)),
            (self.air, round(p.air_k - K0, 2)),
            (self.humidity, p.humidity_pct),
            (self.distance, p.default_distance_m),
        )
        self._syncing = True
        try:
            for handle, value in fields:
                if abs(float(handle.value) - value) > 1e-9:
                    handle.value = value
        finally:
            self._syncing = False
