"""The inspection room of the simulated head, and the scenario that pans the head in it.

:func:`inspection_scene`: a room with warm and cold objects 0.5-8 m away (two people, a hot
pipe, a kettle, warm electronics, a cold window, a wet patch on the wall);
:class:`InspectionScenario`: the head panning slowly in it so parallax matters, optionally
with one sensor moving during the run (``drift``: :mod:`app.sources.sim.drift`). The
calibration scenario is in :mod:`app.sources.sim.scenarios`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.drift import SensorDrift, moved_rig
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.live import CleanImage, LiveDeveloper
from trifuse.app.sources.sim.render import HeadModel, Renderer, SensorTruth
from trifuse.app.sources.sim.scenarios import quad, room
from trifuse.app.sources.sim.scene import (
    BlotchMaterial,
    Box,
    Cylinder,
    Material,
    Scene,
    Solid,
    Sphere,
)
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_euler_deg


def _box(name: str, mat: Material, centre, half_size, yaw_deg: float = 0.0) -> Box:
    """A box of half sizes ``half_size`` (x, y, z, metres) centred at ``centre`` (world,
    metres), turned by ``yaw_deg`` degrees about the vertical (y) axis."""
    R = rotation_from_euler_deg(0, yaw_deg, 0) if yaw_deg else np.eye(3)
    return Box(name, mat, make_T(R, centre), half_size)


INSPECTION_WALL_K = 293.5
"""The inspection room's walls (20.35 C, 0.4 K warmer per metre towards the ceiling)."""
PERSON2_SKIN_K = 307.15
"""The second person's skin (34 C): ``person2_head``."""
PERSON2_CLOTHES_K = 302.15
"""The second person's clothes (29 C, cooler than the skin): ``person2_body``."""
RACK_K = 315.15
"""The electronics rack (42 C at its middle, 1.5 K warmer per metre upwards): ``rack``."""
PSU_K = 318.15
"""The power supply on the table (45 C): ``psu``."""
WINDOW_K = 282.15
"""The window's glass (9 C, emissivity 0.9: it reads about 283.4 K): ``window``."""
WET_PATCH_K = 290.15
"""The wet patch's core (17 C, about 3 K below the wall around it, which it fades into
over its edge): ``wet_patch``."""


def inspection_scene() -> Scene:
    """A room 7 m wide and 9.7 m deep with warm, hot and cold objects at 0.5-8 m.

    A thin pole 0.6 m in front of the head occludes the room differently for each sensor
    (parallax and occlusion at their worst). Solids by name (the render's truth labels
    each pixel with its solid's index in ``scene.solids``; temperatures of the surface, an
    imager reads ``(eps T^4 + (1 - eps) T_amb^4)^(1/4)``):

    * ``person_body`` (33 C clothes) and ``person_head`` (37 C skin) at 3 m, left;
    * ``person2_body`` (29 C clothes) and ``person2_head`` (34 C skin) at 3.5 m, in front
      of the window's right end;
    * ``hot_pipe`` (85 C) across the room under the ceiling, 4.5 m;
    * ``kettle`` (68 C, low in front), ``radiator`` (60 C, behind the first person);
    * ``rack`` (warm electronics, 42 C, warmer at the top) at the back left, 7.6 m, and
      ``psu`` (45 C) on the ``table`` at the right;
    * ``window`` (9 C glass) on the back wall above the ``cabinet``, 8.2 m;
    * ``wet_patch`` (17 C core fading into the 20 C wall) low on the back wall between the
      cabinet and the ``fridge`` (6 C);
    * ``ice_ball`` (-2 C) low on the left, seen by the TOF only.
    """
    solids = room(3.5, 1.1, -1.6, -1.5, 8.2, INSPECTION_WALL_K)
    skin = Material((0.76, 0.57, 0.45), 310.15, 0.98, 0.45)
    cloth = Material((0.2, 0.28, 0.5), 306.0, 0.95, 0.4, pattern=(0.12, 0.15))
    crate = Material((0.6, 0.42, 0.22), 294.5, 0.92, 0.5, pattern=(0.08, 0.2))
    wood = Material((0.45, 0.3, 0.18), 294.0, 0.92, 0.4, pattern=(0.3, 0.15))
    enamel = Material((0.92, 0.92, 0.95), 279.0, 0.9, 0.7)
    radiator = Material((0.9, 0.9, 0.88), 333.0, 0.92, 0.6)
    green = Material((0.3, 0.45, 0.3), 292.0, 0.93, 0.5, pattern=(0.25, 0.1))
    solids += [
        Cylinder("person_body", cloth, make_T(np.eye(3), (-0.7, 0.0, 3.0)), 0.2, (-0.45, 1.1)),
        Sphere("person_head", skin, (-0.7, -0.58, 3.0), 0.12),
        Cylinder(
            "hot_pipe",
            Material((0.5, 0.5, 0.52), 358.0, 0.9, 0.5),
            make_T(rotation_from_euler_deg(0, 0, 90), (0.0, -1.0, 4.5)),
            0.06,
            (-3.4, 3.4),
        ),
        _box("near_crate", crate, (0.45, 0.85, 0.85), (0.25, 0.25, 0.25), yaw_deg=25),
        Sphere("kettle", Material((0.75, 0.75, 0.78), 341.0, 0.85, 0.6), (0.45, 0.45, 0.85), 0.14),
        _box("table", wood, (1.3, 0.7, 2.2), (0.45, 0.4, 0.35)),
        _box("fridge", enamel, (2.2, 0.2, 5.6), (0.4, 0.9, 0.35), yaw_deg=-10),
        _box("radiator", radiator, (-1.9, 0.45, 8.1), (0.6, 0.3, 0.06)),
        _box("cabinet", green, (0.9, 0.3, 7.6), (0.5, 0.8, 0.3)),
        Cylinder(
            "pole",
            Material((0.7, 0.15, 0.1), 292.5, 0.95, 0.6),
            make_T(np.eye(3), (-0.12, 0.0, 0.6)),
            0.03,
            (-1.6, 1.1),
        ),
        Sphere("ice_ball", Material((0.85, 0.9, 0.95), 271.0, 0.96, 0.6), (-1.6, 0.85, 1.6), 0.25),
    ]
    solids += _inspection_additions()
    return Scene(solids, ambient_k=INSPECTION_WALL_K, light_dir_world=(0.2, 1.0, 0.3))


def _inspection_additions() -> list[Solid]:
    """What the room holds for the display's equalization to show (issue 19): a second
    person, warm electronics, a cold window and a wet patch (see :func:`inspection_scene`)."""
    skin2 = Material((0.55, 0.38, 0.28), PERSON2_SKIN_K, 0.98, 0.45)
    clothes2 = Material((0.5, 0.14, 0.12), PERSON2_CLOTHES_K, 0.95, 0.4, pattern=(0.1, 0.2))
    rack = Material(
        (0.16, 0.17, 0.19),
        RACK_K,
        0.9,
        0.3,
        pattern=(0.05, 0.35),
        temperature_gradient_k_per_m=-1.5,
    )
    glass = Material((0.62, 0.76, 0.9), WINDOW_K, 0.9, 0.1)
    # The wall around the patch: its temperature at the patch's height (0.4 K per metre
    # warmer upwards from the wall's middle at y = -0.25 m), its plain colour.
    wall_there_k = INSPECTION_WALL_K - 0.4 * (0.7 + 0.25)
    wet = BlotchMaterial(
        (0.42, 0.4, 0.36),
        WET_PATCH_K,
        0.96,
        0.4,
        surround_k=wall_there_k,
        surround_rgb=(0.62, 0.6, 0.55),
        half_axes_m=(0.32, 0.3),
        centre_st_m=(0.0, 0.02),
    )
    return [
        Cylinder("person2_body", clothes2, make_T(np.eye(3), (0.3, 0.0, 3.5)), 0.19, (-0.4, 1.1)),
        Sphere("person2_head", skin2, (0.3, -0.52, 3.5), 0.115),
        _box("rack", rack, (-2.9, 0.25, 7.6), (0.3, 0.85, 0.35)),
        _box("psu", Material((0.25, 0.25, 0.27), PSU_K, 0.9, 0.4), (1.15, 0.24, 2.05),
             (0.15, 0.06, 0.12), yaw_deg=15),
        quad("window", (0.5, -0.95, 8.18), (0, 0, 0), 0.75, 0.4, glass),
        quad("wet_patch", (2.0, 0.7, 8.19), (0, 0, 0), 0.38, 0.38, wet),
    ]  # fmt: skip


class InspectionScenario:
    """The inspection room seen by a head that pans slowly (yaw +-20 deg, 30 s period).

    ``live``: render in the live (demo) quality (no edge supersampling, see
    :class:`~app.sources.sim.render.Renderer`) and give frames the fast noise of
    :class:`~app.sources.sim.live.LiveDeveloper`; the default is the accurate quality.

    ``drift``: one sensor moves during the run (:class:`~app.sources.sim.drift.SensorDrift`:
    from scenario time ``drift.at_s`` on it is rendered from :attr:`drifted_rig`, the rig with
    that sensor's pose moved; every other sensor, and the truth of the others, as without
    it). :attr:`rig` stays the rig as calibrated (the one a console would use);
    :meth:`rig_at` is the rig the sensors are rendered from at a time. ValueError if the
    drift names a sensor the rig does not have.
    """

    def __init__(
        self,
        rig: Rig | None = None,
        model: HeadModel | None = None,
        seed: int = 0,
        pan_deg: float = 20.0,
        pan_period_s: float = 30.0,
        *,
        live: bool = False,
        drift: SensorDrift | None = None,
    ) -> None:
        self.rig = rig or default_rig()
        self.renderer = Renderer(self.rig, model, live=live)
        self.live = live
        self.developer = LiveDeveloper(self.renderer, noise_seed=seed) if live else None
        self.scene = inspection_scene()
        self.seed = seed
        self.pan_deg = pan_deg
        self.pan_period_s = pan_period_s
        self.drift = drift
        """The sensor that moves during the run, or None."""
        self.drifted_rig: Rig | None = None if drift is None else moved_rig(self.rig, drift)
        """The rig with :attr:`drift`'s sensor moved (None without a drift)."""
        self._drifted_renderer: Renderer | None = None
        if self.drifted_rig is not None:  # the same physics; ray grids shared (same intrinsics)
            self._drifted_renderer = Renderer(self.drifted_rig, self.renderer.model, live=live)

    def drift_active(self, t_s: float) -> bool:
        """Whether :attr:`drift`'s sensor is moved at scenario time ``t_s`` (seconds)."""
        return self.drift is not None and self.drift.active(t_s)

    def rig_at(self, t_s: float) -> Rig:
        """The rig the sensors are rendered from at scenario time ``t_s`` (seconds):
        :attr:`drifted_rig` while the drift is active, else :attr:`rig`."""
        return self._rig(t_s, None)

    def _drifted(self, t_s: float, drifted: bool | None) -> bool:
        if drifted is None:
            return self.drift_active(t_s)
        if drifted and self.drift is None:
            raise ValueError("drifted=True: this scenario has no sensor drift")
        return drifted

    def _rig(self, t_s: float, drifted: bool | None) -> Rig:
        if self._drifted(t_s, drifted):
            assert self.drifted_rig is not None
            return self.drifted_rig
        return self.rig

    def T_world_rig(self, t_s: float) -> np.ndarray:
        """(4, 4) pose of the head at time ``t_s`` (seconds)."""
        yaw = self.pan_deg * np.sin(2 * np.pi * t_s / self.pan_period_s)
        return make_T(rotation_from_euler_deg(0.0, yaw, 0.0), (0.0, 0.0, 0.0))

    def max_turn_rad(self, dt_s: float) -> float:
        """The largest angle (radians) the head turns in ``dt_s`` seconds."""
        rate = np.radians(self.pan_deg) * 2 * np.pi / self.pan_period_s
        return float(min(rate * abs(dt_s), 2 * np.radians(self.pan_deg)))

    def render(
        self, t_s: float, sensors: list[str] | None = None, *, drifted: bool | None = None
    ) -> tuple[FrameSet, dict[str, SensorTruth]]:
        """Frames and exact ground truth at time ``t_s``; noise is seeded by (seed, t).

        ``drifted``: render with the drift's sensor moved (True) or as calibrated (False)
        whatever ``t_s`` (the simulated head's cache renders a looping head's poses in both
        states); default: as at ``t_s`` (:meth:`drift_active`). With the drift, the frames
        equal those of this scenario built with ``rig=drifted_rig`` and no drift.
        """
        rng = np.random.default_rng([self.seed, round(t_s * 1e6) % 2**63])
        stamp_ns = round(t_s * 1e9)
        if self.developer is None:
            renderer = self.renderer
            if self._drifted(t_s, drifted):
                assert self._drifted_renderer is not None
                renderer = self._drifted_renderer
            return renderer.render(self.scene, self.T_world_rig(t_s), stamp_ns, rng, sensors)
        frames: dict[str, Frame] = {}
        truths: dict[str, SensorTruth] = {}
        for name, clean in self.render_clean(t_s, sensors, drifted=drifted).items():
            frames[name] = self.developer.frame(clean, stamp_ns, rng)
            truths[name] = clean.truth
        return FrameSet(stamp_ns, frames), truths

    def render_clean(
        self,
        t_s: float,
        sensors: list[str] | None = None,
        margins: Mapping[str, int] | None = None,
        *,
        drifted: bool | None = None,
    ) -> dict[str, CleanImage]:
        """Live quality only: each sensor's noise-free picture at time ``t_s``, with
        ``margins[sensor]`` pixels more on every side (default 0), for
        :meth:`LiveDeveloper.frame <app.sources.sim.live.LiveDeveloper.frame>`; each
        sensor at its pose in :meth:`rig_at` ``(t_s)``, or with ``drifted`` as in
        :meth:`render`."""
        if self.developer is None:
            raise ValueError("render_clean: needs the live quality (InspectionScenario(live=True))")
        T_world_rig = self.T_world_rig(t_s)
        rig = self._rig(t_s, drifted)
        out = {}
        for name in sensors or self.rig.names:
            margin = (margins or {}).get(name, 0)
            T_world_sensor = T_world_rig @ rig[name].T_rig_sensor
            values, truth = self.renderer.render_raw(self.scene, name, T_world_sensor, margin)
            out[name] = self.developer.clean(name, values, truth, T_world_sensor, margin)
        return out
