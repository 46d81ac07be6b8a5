"""The thermal 3D map in the console, in a real browser (Debian's chromium driven by
Playwright): the "Thermal map" folder's Build map starts it, the map appears in the scene
and grows, the hot-spot highlight counts what lies above 50 C, Pause holds it, Save writes
the map file and the PLY, Reset empties it. Screenshots go to /tmp/shots (map-none.png,
map-above.png, map-hot.png; docs/screenshots/ holds copies a person looked at)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.browser_support import (
    choose,
    console_running,
    drawn_fraction,
    needs_chromium,
    open_scene,
    shot_when,
    tick_box,
    wait_on_page,
)

pytestmark = [needs_chromium, pytest.mark.slow]

SHOTS = Path("/tmp/shots")


def map_status(page) -> tuple[str, int]:
    """(state, occupied voxels) as the folder's status line shows them."""
    text = page.inner_text("body")
    m = re.search(r"Map \((\w+)\): ([\d,]+) occupied voxels", text)
    if m is None:
        return "off", 0
    return m.group(1), int(m.group(2).replace(",", ""))


def iron_fraction(pixels: np.ndarray) -> float:
    """The fraction of a (H, W, 3) BGR screenshot in the iron palette's purples to
    oranges (blue and red well above green)."""
    b, g, r = (pixels[..., k].astype(int) for k in range(3))
    return float(((b - g > 40) & (r - g > 20)).mean())


def wait_status(page, ok, what: str, timeout_s: float = 120.0) -> tuple[str, int]:
    """Polls the status line until ``ok(state, occupied)``; returns them."""
    return wait_on_page(
        page,
        lambda: ok(*(shown := map_status(page))) and shown,
        lambda: f"{what}: the map shows {map_status(page)}",
        timeout_s,
    )


def test_the_map_appears_grows_highlights_pauses_saves_and_resets(browser, tmp_path) -> None:
    SHOTS.mkdir(exist_ok=True)
    workdir = tmp_path / "work"
    with console_running(["--workdir", str(workdir)]) as console:
        page = open_scene(browser, console.signin("/console/"))
        # The thermal feeds' pictures in the scene are iron-coloured too: hidden, the only
        # iron colours in the view are the map's. Before the map: the room's cloud alone.
        page.get_by_label("Live images").uncheck()
        page.get_by_role("button", name="View from above").click()
        shot_when(
            page,
            SHOTS / "map-none.png",
            lambda p: drawn_fraction(p) > 0.15 and iron_fraction(p) < 0.005,
            "the TOF cloud without the live images",
        )
        page.get_by_text("Thermal map", exact=True).click()
        tick_box(page, page.get_by_label("Build map"), "Build map")
        _, first = wait_status(page, lambda s, n: s == "building" and n > 1000, "a map")
        wait_status(page, lambda s, n: n > first * 1.05, "the map to grow")
        # purple-to-yellow iron colours of the room, not only the grey of the TOF cloud (the
        # map's points may reach the browser a few frames after the cloud's)
        pixels = shot_when(
            page,
            SHOTS / "map-above.png",
            lambda p: drawn_fraction(p) > 0.15 and iron_fraction(p) > 0.02,
            "the map drawn in iron colours",
        )
        assert iron_fraction(pixels) > 0.02

        page.get_by_text("Highlight hot spots", exact=True).click()
        # counted at the next redraw ("Counting the points ..." until then); the pipe (85 C),
        # the kettle (68 C) and the radiator (60 C) are in the map once the head has looked
        # at them, which on a loaded machine may take a few more TOF frames
        page.wait_for_function(
            "() => /[1-9][\\d,]* points at or above 50 °C/.test(document.body.innerText)"
        )
        page.wait_for_timeout(1500)
        page.screenshot(path=str(SHOTS / "map-hot.png"))

        page.get_by_role("button", name="Pause", exact=True).click()
        _state, held = wait_status(page, lambda s, n: s == "paused", "paused")
        frames = console.get("/api/map")["frames"]
        page.wait_for_timeout(2000)
        assert console.get("/api/map")["frames"] == frames
        assert map_status(page)[1] == held

        page.get_by_role("button", name="Save map", exact=True).click()
        page.wait_for_function("() => /Saved map-.*\\.map\\.npz/.test(document.body.innerText)")
        saved = sorted((workdir / "maps").iterdir())
        assert [p.suffix for p in saved] == [".npz", ".ply"]
        from trifuse.app.storage.map_file import load_map

        loaded = load_map(saved[0])
        assert int(loaded.occupied().sum()) == held

        page.get_by_role("button", name="Reset map", exact=True).click()
        wait_status(page, lambda s, n: n == 0, "an empty map")
        status = console.get("/api/map")
        assert status["occupied"] == 0 and status["frames"] == 0


def big_map_file(path: Path, n: int = 1_000_000) -> int:
    """A saved map of about ``n`` occupied 2 cm voxels (the walls, floor and ceiling of a
    24 x 3 x 24 m hall, 1 m thick), warm spots included; returns the occupied count."""
    from trifuse.app.storage.map_file import save_map
    from trifuse.fusion.voxel_map import MapSettings, VoxelMap

    rng = np.random.default_rng(4)
    m = VoxelMap(MapSettings(voxel_m=0.02, max_voxels=2 * n))
    pts = rng.uniform(-12.0, 12.0, size=(n, 3))
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -12.0, 12.0) + rng.uniform(-0.5, 0.5, n)
    pts[:, 1] *= 0.125
    temps = rng.uniform(290.0, 300.0, n)
    temps[:2000] = 340.0
    for _ in range(2):  # two hits: occupied
        m.integrate(np.eye(4), pts, 0.0, temps)
    save_map(path, m)
    return int(m.occupied().sum())


def test_a_map_of_a_million_voxels_loads_and_the_scene_stays_interactive(browser, tmp_path) -> None:
    workdir = tmp_path / "work"
    (workdir / "maps").mkdir(parents=True)
    occupied = big_map_file(workdir / "maps" / "hall.map.npz")
    assert occupied > 900_000
    with console_running(["--workdir", str(workdir)]) as console:
        page = open_scene(browser, console.signin("/console/"))
        page.get_by_text("Thermal map", exact=True).click()
        choose(page, "Saved maps", "hall")
        page.get_by_role("button", name="Load map", exact=True).click()
        page.wait_for_function(
            "() => /shown as [\\d,]+ cells of \\d+ voxels/.test(document.body.innerText)",
            timeout=120_000,
        )
        text = page.inner_text("body")
        shown = int(re.search(r"shown as ([\d,]+) cells", text).group(1).replace(",", ""))
        assert 0 < shown <= 300_000
        assert map_status(page) == ("paused", occupied)
        # the browser still answers: a view button moves its camera and the picture changes
        page.get_by_role("button", name="View from above").click()
        above = shot_when(
            page, SHOTS / "map-million.png", lambda p: drawn_fraction(p) > 0.2, "the hall drawn"
        )
        page.get_by_role("button", name="View from side").click()
        shot_when(
            page,
            SHOTS / "map-million-side.png",
            lambda p: np.abs(p.astype(int) - above.astype(int)).mean() > 5,
            "the view to move",
        )
