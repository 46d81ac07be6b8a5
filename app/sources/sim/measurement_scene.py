"""A scene for checking object temperatures (issue 35): panels of different emissivity at
known distances, in cool humid air, reflecting a cold sky.

The head at the world's origin looks along +z (``T_world_rig`` the identity). Each panel faces
it, in a part of the picture of its own (no panel hides another from any sensor); its place is
given as the angles it spans (tangents, x right, y down) and its distance along z:

* ``paint``: matte paint (emissivity 0.95) at 45 C, 2 m away, upper left;
* ``steel``: oxidised steel (0.80) at 60 C, 4.5 m, upper middle;
* ``half``: a surface of emissivity 0.50 at 100 C, 7.5 m, upper right;
* ``hot``: a hot plate (0.95) at 150 C, 9 m, lower middle;
* ``backdrop``: a wall (0.92) at 20 C, 9.6 m, behind them all (its far corners beyond the
  TOF's 10 m: no depth there).

The scene's :class:`~app.sources.sim.scene.Atmosphere`: the surfaces reflect a clear sky's
-23 C (250 K); the air is 15 C at 95 % relative humidity, a foggy morning (its transmission
over 9 m is about 0.98, :func:`fusion.thermography.transmission`).
"""

from __future__ import annotations

from dataclasses import dataclass

from trifuse.app.sources.sim.scenarios import quad
from trifuse.app.sources.sim.scene import Atmosphere, Material, Scene

SKY_K = 250.0
AIR_K = 288.15
HUMIDITY_PCT = 95.0


@dataclass(frozen=True)
class Panel:
    """A panel of the scene: its solid's name, surface, distance along z (metres) and the
    angles it spans (x0, x1, y0, y1: tangents of the angles off the head's axis)."""

    name: str
    emissivity: float
    temperature_k: float
    z_m: float
    span: tuple[float, float, float, float]


PANELS = (
    Panel("paint", 0.95, 318.15, 2.0, (-0.40, -0.16, -0.30, 0.0)),
    Panel("steel", 0.80, 333.15, 4.5, (-0.10, 0.10, -0.30, 0.0)),
    Panel("half", 0.50, 373.15, 7.5, (0.16, 0.40, -0.30, 0.0)),
    Panel("hot", 0.95, 423.15, 9.0, (-0.15, 0.15, 0.08, 0.30)),
    Panel("backdrop", 0.92, 293.15, 9.6, (-0.6, 0.6, -0.5, 0.5)),
)


def measurement_scene() -> Scene:
    """The scene of the module's docstring (solids named as :data:`PANELS`)."""
    solids = []
    for p in PANELS:
        x0, x1, y0, y1 = (a * p.z_m for a in p.span)
        material = Material((0.5, 0.5, 0.5), p.temperature_k, p.emissivity, 0.6, pattern=(0.2, 0.2))
        centre = ((x0 + x1) / 2, (y0 + y1) / 2, p.z_m)
        solids.append(quad(p.name, centre, (0.0, 0.0, 0.0), (x1 - x0) / 2, (y1 - y0) / 2, material))
    return Scene(solids, atmosphere=Atmosphere(SKY_K, AIR_K, HUMIDITY_PCT))
