"""Each console setting's limits, declared once: the REST models (:mod:`app.server.routers`)
take their ``Field(ge, le, description)`` from here and the Viser panels
(:mod:`app.server.panels`) their slider and number-input ranges.

The numbers themselves come from where the value is checked (the pure core's constants,
:mod:`fusion.agc`, :mod:`fusion.compose`, :mod:`calib.radiometry`; the replay's speed from
:mod:`app.server.runtime.source_control`); the core's checks and their messages stay where
they are (a bad value sent past the API or the GUI is refused there). Where a GUI control
shows a narrower range than the API accepts (a slider's useful part), or none at all (a
free number input), the declaration says so in ``gui``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import Field

from trifuse.app.server.runtime.source_control import RATE_MAX, RATE_MIN
from trifuse.calib.radiometry import MAX_TRIM_K
from trifuse.fusion.agc import MAX_MAX_GAIN, MIN_MAX_GAIN, MIN_PLATEAU
from trifuse.fusion.compose import MAX_EDGE_STRENGTH

Number = int | float


@dataclass(frozen=True)
class Setting:
    """One setting's limits, in the unit of the API (the core's unit).

    Attributes:
        name: the API field name.
        min, max: the API's inclusive limits (None: unbounded).
        step: the GUI control's step, in GUI units (None: no GUI control).
        description: the API field's description (None: the field has none).
        gui: the GUI control's ``(min, max)`` in GUI units where it differs from the API's
            limits (a slider over the useful part; ``(None, None)``: a free number input);
            None: the API's limits times ``gui_scale``.
        gui_scale: GUI units per API unit (100: a fraction shown in percent).
        default: the API field's default, when it has one.
    """

    name: str
    min: Number | None = None
    max: Number | None = None
    step: float | None = None
    description: str | None = None
    gui: tuple[Number | None, Number | None] | None = None
    gui_scale: float = 1.0
    default: Any = ...

    def field(self, **extra: Any) -> Any:
        """``pydantic.Field`` with this setting's limits, description and default (plus
        ``extra``: ``default``, ``allow_inf_nan``, ...)."""
        kw: dict[str, Any] = {}
        if self.default is not ...:
            kw["default"] = self.default
        if self.min is not None:
            kw["ge"] = self.min
        if self.max is not None:
            kw["le"] = self.max
        if self.description is not None:
            kw["description"] = self.description
        return Field(**{**kw, **extra})

    @property
    def gui_limits(self) -> tuple[Number | None, Number | None]:
        """The GUI control's ``(min, max)`` in GUI units (None: unbounded)."""
        if self.gui is not None:
            return self.gui
        lo, hi, scale = self.min, self.max, self.gui_scale
        return (None if lo is None else lo * scale), (None if hi is None else hi * scale)

    def slider(self) -> tuple[float, float, float]:
        """``(min, max, step)``: the leading arguments of ``gui.add_slider``."""
        lo, hi = self.gui_limits
        if lo is None or hi is None or self.step is None:
            raise ValueError(f"{self.name}: a slider needs both GUI limits and a step")
        return float(lo), float(hi), self.step

    def number(self) -> dict[str, float]:
        """``min``, ``max``, ``step`` keywords of ``gui.add_number`` (the unbounded ones
        left out)."""
        lo, hi = self.gui_limits
        kw = {"min": lo, "max": hi, "step": self.step}
        return {k: float(v) for k, v in kw.items() if v is not None}


# -- the fused picture (PUT /api/fusion; the Display panel's "Fusion" folder) --------------

OPACITY = Setting("opacity", 0.0, 1.0, step=0.05)
EDGE_STRENGTH = Setting("edge_strength", 0.0, MAX_EDGE_STRENGTH, step=0.5)
PLATEAU = Setting(
    "plateau",
    MIN_PLATEAU,
    1.0,
    step=0.1,
    description="plateau and dde: the largest share of the pixels one 0.1 K bin counts "
    "with (1: plain histogram equalization); omitted: unchanged",
    gui=(0.1, 100.0),
    gui_scale=100.0,
    default=None,
)
MAX_GAIN = Setting(
    "max_gain",
    MIN_MAX_GAIN,
    MAX_MAX_GAIN,
    step=1.0,
    description="plateau and dde: the steepest the mapping may be, palette steps per "
    "kelvin (a flat scene is not stretched into noise); omitted: unchanged",
    gui=(1.0, 100.0),
    default=None,
)

# -- the thermal imagers (PUT /api/thermal; the Display panel's "Thermal" folder) ----------

SPAN_SMOOTHING_S = Setting("span_smoothing_s", 0.0, 60.0, step=0.5, gui=(0.0, 10.0), default=None)
MANUAL_OFFSET_K = Setting("offset_k", -MAX_TRIM_K, MAX_TRIM_K, step=0.05, gui=(None, None))

# -- the replay (POST /api/source/rate, /seek; the Source panel) ---------------------------

REPLAY_RATE = Setting(
    "rate", RATE_MIN, RATE_MAX, step=0.25, description="replay speed, x real time"
)
SEEK_POSITION_S = Setting(
    "position_s", 0.0, None, description="seconds from the recording's start"
)  # the upper limit is the recording's length

# -- the range calibration (POST /api/range) -----------------------------------------------

HOLDOUT_EVERY = Setting("holdout_every", 2, 50, default=4)

SETTINGS: tuple[Setting, ...] = (
    OPACITY,
    EDGE_STRENGTH,
    PLATEAU,
    MAX_GAIN,
    SPAN_SMOOTHING_S,
    MANUAL_OFFSET_K,
    REPLAY_RATE,
    SEEK_POSITION_S,
    HOLDOUT_EVERY,
)
"""Every declared setting (the tests compare each with the OpenAPI schema and the GUI)."""
