"""The spot meter (fusion/spot.py) on the simulated inspection room, against its ground truth.

One fused picture of the room (seed 0, live quality) at t = 18 s: the head turned 11.8
degrees to the left, so the second person stands in front of the window's right end, the
hot pipe crosses the picture and the fridge (colder than the window) is out of view.

Tolerances follow from the simulator: an imager reads ``(eps T^4 + (1 - eps) T_amb^4)^(1/4)``
plus its offset (+0.75 K left, -0.75 K right) and noise of NETD 0.08 K (0.4 K is five
sigma); the TOF's distance carries the systematic error of
:class:`~app.sources.sim.tof_error.RangeErrorModel` (bias, wiggling, the bowl and border
of its pixel offsets, a fixed pattern of 5 mm sigma, the amplitude term) and noise:
:func:`range_error_bound_m` adds up their largest values.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from trifuse.app.sources.sim.inspection import (
    INSPECTION_WALL_K,
    PERSON2_SKIN_K,
    WINDOW_K,
    InspectionScenario,
)
from trifuse.app.sources.sim.render import HeadModel
from trifuse.app.sources.sim.tof_error import RangeErrorModel
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.spot import SpotError, SpotFrame, SpotMeter, nearest_cells, robust_extremes
from trifuse.fusion.stereo import StereoFusion

T_S = 18.0
OFFSET_K = HeadModel().thermal_offset_k  # thermal_left +0.75, thermal_right -0.75
COLOR = {"left": "ccd_left", "right": "ccd_right"}
THERMAL = {"left": "thermal_left", "right": "thermal_right"}
NOISE_K = 0.4  # 5 x NETD 0.08 K


def apparent_k(t_k: float, emissivity: float, eye: str) -> float:
    """What the eye's imager reads on a surface at ``t_k`` kelvin."""
    t4 = emissivity * t_k**4 + (1 - emissivity) * INSPECTION_WALL_K**4
    return float(t4**0.25) + OFFSET_K[THERMAL[eye]]


def range_error_bound_m(amplitude: float) -> float:
    """The largest systematic error plus 4 sigma of noise of the simulated TOF at a return
    of ``amplitude`` (inside the colour cameras' view, which reaches 0.9 of the TOF's
    half width: the border term at most ((0.9 - 0.8) / 0.2)^2 of its full value)."""
    m, model = RangeErrorModel(), HeadModel()
    systematic = (
        abs(m.bias_m)
        + sum(abs(a) for a, _, _ in m.wiggle)
        + m.radial_m
        + 0.25 * m.border_m
        + 4 * m.pixel_sigma_m
        + abs(m.amplitude_m * np.log10(m.amplitude_ref / amplitude))
    )
    noise = model.tof_noise_m * np.sqrt(model.tof_noise_ref / amplitude)
    return float(systematic + 4 * noise)


@dataclasses.dataclass
class Room:
    scenario: InspectionScenario
    frames: object
    truth: dict
    fusion: StereoFusion
    spots: SpotFrame
    names: list[str]

    def mask(self, eye: str, name: str, erode_px: int = 9) -> np.ndarray:
        """(H, W) bool: the colour pixels of ``eye`` that see solid ``name``, away from its
        outline by ``erode_px``."""
        m = (self.truth[COLOR[eye]].solid == self.names.index(name)).astype(np.uint8)
        return cv2.erode(m, np.ones((erode_px, erode_px), np.uint8)).astype(bool)

    def centre(self, eye: str, name: str) -> tuple[int, int]:
        """The pixel of ``name``'s eroded mask nearest its centroid."""
        ys, xs = np.nonzero(self.mask(eye, name))
        k = np.argmin((xs - xs.mean()) ** 2 + (ys - ys.mean()) ** 2)
        return int(xs[k]), int(ys[k])

    def solid_at(self, eye: str, x: int, y: int) -> str:
        k = int(self.truth[COLOR[eye]].solid[y, x])
        return self.names[k] if k >= 0 else "nothing"


def fuse(
    scenario: InspectionScenario, frames, thermals: dict | None = None
) -> tuple[StereoFusion, SpotFrame]:
    fusion = StereoFusion(scenario.rig)
    fusion.update_depth(frames["tof"].distance_m, frames["tof"].image)
    colors = {e: frames[COLOR[e]].image for e in fusion.eyes}
    thermals = thermals or {e: frames[THERMAL[e]].image for e in fusion.eyes}
    fusion.compose(colors, thermals, DisplaySettings())
    return fusion, SpotMeter(fusion).capture(frames.stamp_ns)


@pytest.fixture(scope="module")
def room() -> Room:
    scenario = InspectionScenario(seed=0, live=True)
    frames, truth = scenario.render(T_S)
    fusion, spots = fuse(scenario, frames)
    return Room(scenario, frames, truth, fusion, spots, [s.name for s in scenario.scene.solids])


@pytest.mark.parametrize("eye", ["left", "right"])
def test_spot_on_the_second_person_reads_skin_and_distance(room: Room, eye: str) -> None:
    x, y = room.centre(eye, "person2_head")
    r = room.spots.spot(eye, x, y)
    assert (r.eye, r.x, r.y, r.depth) == (eye, x, y, "measured")
    assert r.temperature_k == pytest.approx(apparent_k(PERSON2_SKIN_K, 0.98, eye), abs=NOISE_K)
    assert r.temperature_c == pytest.approx(r.temperature_k - 273.15)
    assert 33.0 < r.temperature_c < 35.5  # "about 34 C"
    truth_m = float(room.truth[COLOR[eye]].range_m[y, x])
    # the head's return: NIR reflectance 0.45 at about 3.5 m (amplitude 20000 rho / d^2)
    bound = range_error_bound_m(20000 * 0.45 / truth_m**2)
    assert bound < 0.2
    assert r.distance_m == pytest.approx(truth_m, abs=bound)
    # the same 3D point in both eyes: its own pixel, and the person's head in the other
    assert r.eyes_px[eye] == pytest.approx((x, y), abs=0.01)
    other = "right" if eye == "left" else "left"
    ox, oy = r.eyes_px[other]
    assert room.solid_at(other, round(ox), round(oy)) == "person2_head"


def test_distances_over_the_room_follow_the_tof(room: Room) -> None:
    """Over the second person's body, the back wall and the rack, the distance read is the
    truth within the TOF's error bound (the bowl and wiggling differ pixel by pixel). Away
    from outlines by 20 px: a TOF pixel (8 colour pixels wide) straddling a near, bright
    object reads that object's distance, which fattens it in the depth by up to one."""
    for name, rho in (("person2_body", 0.4), ("wall_back", 0.55), ("rack", 0.3)):
        ys, xs = np.nonzero(room.mask("left", name, erode_px=41))
        pick = np.linspace(0, len(xs) - 1, 40).astype(int)
        truth_m = room.truth["ccd_left"].range_m[ys[pick], xs[pick]]
        got = [room.spots.spot("left", int(xs[k]), int(ys[k])) for k in pick]
        # at 8 m the wall's and the dark rack's weakest returns fall under the TOF's
        # amplitude threshold: those pixels have the fallback depth and no distance
        measured = np.array([g.depth == "measured" for g in got])
        assert measured.mean() > (1 - 1e-9 if name == "person2_body" else 0.75), name
        assert all(g.distance_m is None for g, m in zip(got, measured, strict=True) if not m)
        err = np.array([g.distance_m for g in got if g.depth == "measured"]) - truth_m[measured]
        bound = range_error_bound_m(20000 * rho / float(truth_m.max()) ** 2)
        assert np.abs(err).max() < bound, (name, np.abs(err).max(), bound)


def test_the_window_has_no_depth_only_a_temperature(room: Room) -> None:
    """Glass returns too little near infrared for the TOF: the mapping used its fallback
    depth there, and the spot says so instead of giving a distance."""
    x, y = room.centre("left", "window")
    r = room.spots.spot("left", x, y)
    assert r.depth == "fallback" and r.distance_m is None
    assert r.temperature_k == pytest.approx(apparent_k(WINDOW_K, 0.9, "left"), abs=NOISE_K)
    assert r.eyes_px["left"] is not None  # from the fallback depth: a guess, still a place


def test_box_max_min_and_mean(room: Room) -> None:
    """A box over the second person's head and the window behind it: the hottest pixel is
    on the head, the coldest on the window; both are the box's plain extremes."""
    x, y = room.centre("left", "person2_head")
    x0, y0, x1, y1 = x - 80, y - 70, x + 80, y + 30
    a = room.spots.area("left", x1, y1, x0, y0)  # corners in any order
    assert a.box == (x0, y0, x1, y1) and a.pixels == 161 * 101
    patch = room.fusion.thermal_on_color["left"][y0 : y1 + 1, x0 : x1 + 1]
    assert a.thermal_pixels == int(np.isfinite(patch).sum()) > 0.9 * a.pixels
    assert a.max is not None and a.min is not None and a.mean_k is not None
    assert a.max.temperature_k == pytest.approx(float(np.nanmax(patch)), abs=1e-3)
    assert a.min.temperature_k == pytest.approx(float(np.nanmin(patch)), abs=1e-3)
    assert a.mean_k == pytest.approx(float(np.nanmean(patch)), abs=1e-3)
    assert room.solid_at("left", a.max.x, a.max.y) == "person2_head"
    assert room.solid_at("left", a.min.x, a.min.y) == "window"
    assert a.max.depth == "measured" and a.max.distance_m == pytest.approx(3.45, abs=0.2)
    # a one-pixel box is the spot
    s = room.spots.area("left", x, y, x, y)
    assert s.pixels == 1 and s.max == s.min == room.spots.spot("left", x, y)
    d = a.as_dict()
    assert d["max"]["temperature_c"] == pytest.approx(a.max.temperature_k - 273.15)
    assert d["mean_c"] == pytest.approx(a.mean_k - 273.15)


@pytest.mark.parametrize("eye", ["left", "right"])
def test_hot_spot_is_the_pipe_and_cold_spot_the_window(room: Room, eye: str) -> None:
    hot, cold = room.spots.hot[eye], room.spots.cold[eye]
    assert hot is not None and cold is not None
    assert room.solid_at(eye, hot.x, hot.y) == "hot_pipe"
    assert room.solid_at(eye, cold.x, cold.y) == "window"
    assert hot.temperature_k == pytest.approx(apparent_k(358.0, 0.9, eye), abs=NOISE_K)
    assert cold.temperature_k == pytest.approx(apparent_k(WINDOW_K, 0.9, eye), abs=NOISE_K)
    assert hot.depth == "measured"
    assert hot.distance_m == pytest.approx(
        float(room.truth[COLOR[eye]].range_m[hot.y, hot.x]), abs=range_error_bound_m(200.0)
    )
    meta = room.spots.extremes()
    assert meta["hot"][eye] == {
        "x": hot.x,
        "y": hot.y,
        "temperature_k": hot.temperature_k,
        "distance_m": hot.distance_m,
        "depth": "measured",
    }
    assert meta["cold"][eye]["depth"] == "fallback" and meta["cold"][eye]["distance_m"] is None


def test_single_outlying_pixels_do_not_make_the_spots(room: Room) -> None:
    """One dead-hot and one dead-cold thermal pixel on the back wall: the plain extremes
    of the picture move onto them, the robust hot and cold spots do not."""
    frames = room.frames
    thermals = {e: frames[THERMAL[e]].image.copy() for e in ("left", "right")}
    wall = room.truth["thermal_left"].solid == room.names.index("wall_back")
    inner = cv2.erode(wall.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    ys, xs = np.nonzero(inner)
    (hy, hx), (cy, cx) = (ys[10], xs[10]), (ys[-10], xs[-10])
    thermals["left"][hy, hx] = 600.0
    thermals["left"][cy, cx] = 200.0
    fusion, spots = fuse(room.scenario, frames, thermals)
    kelvin = fusion.thermal_on_color["left"]
    plain_hot = np.unravel_index(np.nanargmax(kelvin), kelvin.shape)
    plain_cold = np.unravel_index(np.nanargmin(kelvin), kelvin.shape)
    assert room.solid_at("left", int(plain_hot[1]), int(plain_hot[0])) == "wall_back"
    assert room.solid_at("left", int(plain_cold[1]), int(plain_cold[0])) == "wall_back"
    assert room.solid_at("left", spots.hot["left"].x, spots.hot["left"].y) == "hot_pipe"
    assert room.solid_at("left", spots.cold["left"].x, spots.cold["left"].y) == "window"


def test_robust_extremes_of_synthetic_pictures() -> None:
    rng = np.random.default_rng(0)
    k = (295.0 + 0.08 * rng.standard_normal((96, 128))).astype(np.float32)
    k[40:60, 80:100] = 330.0  # a hot object, 20 x 20 px
    k[10:30, 10:26] = 280.0  # a cold one
    k[70, 20] = 1000.0  # a dead pixel
    k[5, 120] = 100.0
    k[:, :4] = np.nan  # no thermal view
    hot, cold = robust_extremes(k, cell_px=4)
    assert hot is not None and cold is not None
    assert 80 <= hot[0] < 100 and 40 <= hot[1] < 60 and hot[2] == pytest.approx(330.0)
    assert 10 <= cold[0] < 26 and 10 <= cold[1] < 30 and cold[2] == pytest.approx(280.0)
    assert robust_extremes(np.full((96, 128), np.nan, np.float32)) == (None, None)
    # a picture whose only view is one cell: its own mean
    lone = np.full((96, 128), np.nan, np.float32)
    lone[8:12, 8:12] = 301.0
    (hx, hy, ht), (cx, cy, ct) = robust_extremes(lone, cell_px=4)
    assert (hx, hy, ht) == (cx, cy, ct) == (10, 10, pytest.approx(301.0))


def test_a_spot_rests_on_a_uniform_object_and_follows_a_hotter_one() -> None:
    """Two hot objects 0.1 K apart: without a previous spot the hotter wins; with one on the
    other, it stays there (within hold_k); an object hotter by more than that takes it."""
    k = np.full((96, 128), 295.0, np.float32)
    k[20:40, 20:40] = 330.0
    k[60:80, 90:110] = 330.1
    (hx, hy, _), _ = robust_extremes(k)
    assert 90 <= hx < 110 and 60 <= hy < 80
    (hx, hy, ht), _ = robust_extremes(k, previous=((30, 30), None), hold_k=0.3)
    assert (hx, hy, ht) == (30, 30, pytest.approx(330.0))
    k[60:80, 90:110] = 331.0
    (hx, hy, _), _ = robust_extremes(k, previous=((30, 30), None), hold_k=0.3)
    assert 90 <= hx < 110 and 60 <= hy < 80
    # the cold spot likewise, and a previous spot outside any view is let go
    k[:, 64:] = np.nan
    _, (cx, _, _) = robust_extremes(k, previous=(None, (100, 10)), hold_k=0.3)
    assert cx < 64


def test_without_thermal_the_distance_remains(room: Room) -> None:
    """An eye without its thermal imager (NaN): no temperature, no hot spot, the depth
    still read."""
    nan = {e: np.full_like(room.frames[THERMAL[e]].image, np.nan) for e in ("left", "right")}
    _, spots = fuse(room.scenario, room.frames, nan)
    x, y = room.centre("left", "person2_head")
    r = spots.spot("left", x, y)
    assert r.temperature_k is None and r.temperature_c is None and r.depth == "measured"
    assert spots.hot == {"left": None, "right": None} == spots.cold
    a = spots.area("left", 0, 0, 99, 99)
    assert (a.thermal_pixels, a.max, a.min, a.mean_k) == (0, None, None, None)
    assert spots.extremes() == {"hot": {"left": None, "right": None}, "cold": spots.hot}


def test_a_new_tof_frame_renews_the_depth_a_repeated_picture_keeps_it(room: Room) -> None:
    meter = SpotMeter(room.fusion)
    first = meter.capture(1)
    again = meter.capture(2)
    assert again._states["left"].z_m is first._states["left"].z_m  # not taken again
    assert not again._states["left"].kelvin.flags.writeable
    room.fusion.update_depth(room.frames["tof"].distance_m, room.frames["tof"].image)
    renewed = meter.capture(3)
    assert renewed._states["left"].z_m is not first._states["left"].z_m
    assert renewed.stamp_ns == 3


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda s: s.spot("middle", 1, 1), "eye: expected one of ['left', 'right'], got 'middle'"),
        (lambda s: s.spot("left", -1, 0), "x: expected a colour pixel 0..1279, got -1"),
        (lambda s: s.spot("left", 1280, 0), "x: expected a colour pixel 0..1279, got 1280"),
        (lambda s: s.spot("right", 0, 960), "y: expected a colour pixel 0..959, got 960"),
        (lambda s: s.spot("left", 1.5, 0), "x: expected an integer pixel, got 1.5"),
        (lambda s: s.spot("left", True, 0), "x: expected an integer pixel, got True"),
        (lambda s: s.area("left", 0, 0, 1280, 5), "x1: expected a colour pixel 0..1279"),
        (lambda s: s.area("up", 0, 0, 5, 5), "eye: expected one of"),
    ],
)
def test_errors_say_what_was_expected(room: Room, call, message: str) -> None:
    with pytest.raises(SpotError) as e:
        call(room.spots)
    assert message in str(e.value)
    assert isinstance(e.value, ValueError)


@pytest.mark.parametrize(
    ("size", "cells"),
    [((1280, 960), (240, 320)), ((382, 288), (72, 96)), ((1000, 750), (188, 250))],
)
def test_a_pixel_reads_the_cell_opencv_brings_to_it(size, cells) -> None:
    """The spot meter keeps each eye's depth at the mapping's coarse cells and reads a pixel
    from the cell ``cv2.resize(..., INTER_NEAREST)`` would put there: the same value as the
    full-resolution depth, without making it."""
    w, h = size
    coarse = np.random.default_rng(4).random(cells).astype(np.float32)
    full = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_NEAREST)
    ys, xs = np.mgrid[0:h, 0:w]
    rows, cols = nearest_cells(xs.ravel(), ys.ravel(), size, cells)
    np.testing.assert_array_equal(coarse[rows, cols].reshape(h, w), full)
