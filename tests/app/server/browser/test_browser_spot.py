"""The viewer's spot meter in a real browser (Debian's chromium driven by Playwright, against
a real console): a click on the second person of the inspection room reads about 34 C and
the distance the simulator's truth gives, a drag draws a box with its hottest and coldest
point, the hot- and cold-spot markers follow the metadata, Clear removes the spot; the
WebXR gaze and controller rays map to the pixels a picture drawn over each eye's view
shows under them.

The console replays a recording of one moment of the room (seed 0, t = 18 s, live quality;
tests/fusion/test_spot.py's picture), so the picture stands still and its ground truth is known:
a click lands where the truth says the person is. Screenshots go to /tmp/shots/viewer-spot.png
and viewer-spot-labels.png (docs/screenshots/spot-meter.png is a copy a person looked at).
"""

from __future__ import annotations

import re
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.browser_support import console_running, needs_chromium
from tests.support import RATES_HZ, write_recording
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.inspection import InspectionScenario

pytestmark = [needs_chromium, pytest.mark.slow]

T_S = 18.0
SHOT = Path("/tmp/shots/viewer-spot.png")
LABELS_SHOT = Path("/tmp/shots/viewer-spot-labels.png")
DURATION_S = 1.0
READING = re.compile(r"spot (-?\d+\.\d) °C, (\d+\.\d\d) m \(left (\d+), (\d+)\)")


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The room's picture at T_S, its truth, and a recording of it (DURATION_S, every
    sensor at its rate; the replay loops over it)."""
    scenario = InspectionScenario(seed=0, live=True)
    fs, truth = scenario.render(T_S)
    frames = []
    for name, f in fs.frames.items():
        rate = RATES_HZ[scenario.rig[name].modality]
        for i in range(int(DURATION_S * rate)):
            stamp = fs.stamp_ns + i * 1_000_000_000 // rate
            frames.append(Frame(name, stamp, f.image, f.distance_m))
    frames.sort(key=lambda f: (f.stamp_ns, f.sensor))
    path = tmp_path_factory.mktemp("spot") / "room.mcap"
    write_recording(path, scenario.rig, frames)
    names = [s.name for s in scenario.scene.solids]
    return {"path": path, "truth": truth, "names": names}


@pytest.fixture(scope="module")
def console(room, tmp_path_factory: pytest.TempPathFactory):
    workdir = tmp_path_factory.mktemp("spot-work")
    with console_running(["--replay", str(room["path"]), "--workdir", str(workdir)]) as c:
        yield c


def _inner_centre(mask: np.ndarray, erode: int = 15) -> tuple[int, int]:
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((erode, erode), np.uint8)).astype(bool)
    ys, xs = np.nonzero(inner)
    k = np.argmin((xs - xs.mean()) ** 2 + (ys - ys.mean()) ** 2)
    return int(xs[k]), int(ys[k])


def _settled_areas(console: Any) -> list[dict]:
    """Both eyes' ``/api/area`` once the paused pipeline has published its last picture:
    the same stamp twice, 0.5 s apart (a busy console fuses the sets in flight after the
    pause for a while)."""
    areas = [console.get(f"/api/area?eye={e}") for e in ("left", "right")]
    for _ in range(40):
        time.sleep(0.5)
        again = [console.get(f"/api/area?eye={e}") for e in ("left", "right")]
        if [a["stamp_ns"] for a in again] == [a["stamp_ns"] for a in areas]:
            return again
        areas = again
    pytest.fail(f"the paused console kept publishing pictures ({areas[0]['stamp_ns']})")


def _hold_a_whole_picture(console: Any, page: Any) -> None:
    """Pause the replay on a picture fused from every sensor, shown by the page (the first
    frame set after a looping replay jumps back to its start lacks some sensors: not the
    picture to hold)."""
    for _ in range(30):
        console.post("/api/source/pause")
        areas = _settled_areas(console)
        whole = all(a["thermal_pixels"] > 0.5 * a["pixels"] for a in areas)
        if whole and not console.status()["missing"]:
            page.wait_for_function(
                "(s) => window.trifuseStats.meta && window.trifuseStats.meta.stamp_ns === s",
                arg=areas[0]["stamp_ns"],
            )
            return
        console.post("/api/source/resume")
        time.sleep(0.3)
    pytest.fail("the replay never paused on a picture of every sensor")


def _client_xy(page: Any, eye: str, x: float, y: float) -> tuple[float, float]:
    """Where on the page colour pixel (x, y) of ``eye`` is shown."""
    r = page.evaluate(
        "() => { const b = document.getElementById('spot-overlay').getBoundingClientRect();"
        " return [b.left, b.top, b.width, b.height]; }"
    )
    left, top, width, height = r
    half = width / 2
    return (
        left + (half if eye == "right" else 0) + (x + 0.5) * half / 1280,
        top + (y + 0.5) * height / 960,
    )


def _overlay_rgba(page: Any, x: float, y: float) -> list[int]:
    """The marker canvas's pixel over picture pixel (x, y) of the 2560 x 960 side-by-side
    picture (the canvas has the size it is shown at)."""
    return page.evaluate(
        "([x, y]) => { const c = document.getElementById('spot-overlay');"
        " return Array.from(c.getContext('2d').getImageData("
        "Math.floor(x * c.width / 2560), Math.floor(y * c.height / 960), 1, 1).data); }",
        [x, y],
    )


def test_click_box_markers_and_clear(console, browser, room) -> None:
    page = browser.new_page(viewport={"width": 1400, "height": 700})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(console.signin("/"))
    page.wait_for_function(
        "() => window.trifuseStats.frames > 3 && window.trifuseStats.meta"
        " && window.trifuseStats.meta.spots && window.trifuseSpot"
    )
    _hold_a_whole_picture(console, page)
    truth, names = room["truth"], room["names"]

    # a click on the second person's face, in the left eye
    head = truth["ccd_left"].solid == names.index("person2_head")
    x, y = _inner_centre(head)
    page.mouse.click(*_client_xy(page, "left", x, y))
    page.wait_for_function("() => window.trifuseSpot.state.spotReading !== null")
    state = page.evaluate("() => window.trifuseSpot.state")
    spot, reading = state["spot"], state["spotReading"]
    assert spot["eye"] == "left" and abs(spot["x"] - x) <= 1 and abs(spot["y"] - y) <= 1
    assert reading["depth"] == "measured" and 33.0 < reading["temperature_c"] < 35.5
    truth_m = float(truth["ccd_left"].range_m[spot["y"], spot["x"]])
    assert abs(reading["distance_m"] - truth_m) < 0.2  # the TOF's error bound, test_spot.py
    page.wait_for_function(
        "() => /spot \\d+\\.\\d °C, \\d+\\.\\d\\d m/.test("
        "document.getElementById('spot-readout').textContent)"
    )
    text = page.locator("#spot-readout").text_content()
    m = READING.search(text)
    assert m, text
    assert 33.0 < float(m.group(1)) < 35.5 and abs(float(m.group(2)) - truth_m) < 0.2
    # the spot is marked in both eyes, the other eye where the same point is
    right = reading["eyes_px"]["right"]
    assert truth["ccd_right"].solid[round(right[1]), round(right[0])] == names.index("person2_head")

    # the hot-spot marker: a red triangle under the metadata's hot spot of each eye
    meta = page.evaluate("() => window.trifuseStats.meta.spots")
    for eye in ("left", "right"):
        hot, cold = meta["hot"][eye], meta["cold"][eye]
        assert names[truth[f"ccd_{eye}"].solid[hot["y"], hot["x"]]] == "hot_pipe"
        assert names[truth[f"ccd_{eye}"].solid[cold["y"], cold["x"]]] == "window"
        cx = (1280 if eye == "right" else 0) + hot["x"] + 0.5
        q = 2560 / 100
        r, g, b, a = _overlay_rgba(page, cx, hot["y"] + 0.5 + 1.0 * q)  # inside the triangle
        assert a == 255 and r > 200 and g < 120 and b < 120, (eye, r, g, b, a)
    assert "hot " in text and "cold " in text

    # a box over the person's head and the window behind it: max on the head, min the window
    x0, y0 = _client_xy(page, "left", x - 80, y - 70)
    x1, y1 = _client_xy(page, "left", x + 80, y + 30)
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move((x0 + x1) / 2, (y0 + y1) / 2, steps=4)
    page.mouse.move(x1, y1, steps=4)
    page.mouse.up()
    page.wait_for_function("() => window.trifuseSpot.state.boxReading !== null")
    box = page.evaluate("() => window.trifuseSpot.state.boxReading")
    assert abs(box["x1"] - box["x0"] - 160) <= 2 and abs(box["y1"] - box["y0"] - 100) <= 2
    assert names[truth["ccd_left"].solid[box["max"]["y"], box["max"]["x"]]] == "person2_head"
    assert names[truth["ccd_left"].solid[box["min"]["y"], box["min"]["x"]]] == "window"
    page.wait_for_function(
        "() => /box max/.test(document.getElementById('spot-readout').textContent)"
    )
    assert page.evaluate("() => window.trifuseSpot.state.spot") is not None  # both at once

    SHOT.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SHOT))

    page.get_by_role("button", name="Clear spot").click()
    state = page.evaluate("() => window.trifuseSpot.state")
    assert state["spot"] is None and state["box"] is None
    page.get_by_role("button", name="Hot/cold ✓").click()
    assert page.evaluate("() => window.trifuseSpot.state.extremes") is False
    assert errors == []
    page.close()


_LABELS = """() => {
  const box = (e) => { const r = e.getBoundingClientRect(); return [r.x, r.y, r.right, r.bottom]; };
  const o = document.getElementById('spot-overlay');
  return {labels: window.trifuseSpot.state.labels, w: o.width, h: o.height, overlay: box(o),
          scales: [...document.querySelectorAll('.scale')].map(box)};
}"""


def _overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _labels_apart(page: Any, want: int) -> list[dict[str, Any]]:
    """The overlay's labels (at least ``want`` of them): each inside its eye's half of the
    picture, none over another, none over a colour scale (drawn beside the picture)."""
    page.wait_for_function(f"() => window.trifuseSpot.state.labels.length >= {want}")
    got = page.evaluate(_LABELS)
    w, h, ov, labels = got["w"], got["h"], got["overlay"], got["labels"]
    for i, a in enumerate(labels):
        x0, y0, x1, y1 = a["rect"]
        lo = w / 2 if a["eye"] == "right" else 0
        assert lo <= x0 < x1 <= lo + w / 2 and 0 <= y0 < y1 <= h, a
        for b in labels[i + 1 :]:
            assert not _overlap(a["rect"], b["rect"]), (a, b)
        sx, sy = (ov[2] - ov[0]) / w, (ov[3] - ov[1]) / h  # canvas px to the page's
        shown = [ov[0] + x0 * sx, ov[1] + y0 * sy, ov[0] + x1 * sx, ov[1] + y1 * sy]
        for sc in got["scales"]:
            assert not _overlap(shown, sc), (a, sc)
    return labels


def test_labels_move_apart_near_the_hot_spot(console, browser) -> None:
    """A spot just beside the hot spot and a box just beside the cold spot: their labels would
    take the same place as the hot and cold spots' (above right of the marker); the later
    ones move (beside or below their marker), none covers another or a colour scale."""
    console.post("/api/source/resume")  # frames again (another test may have paused them)
    page = browser.new_page(viewport={"width": 1400, "height": 700})
    page.goto(console.signin("/"))
    page.wait_for_function(
        "() => window.trifuseStats.frames > 3 && window.trifuseStats.meta"
        " && window.trifuseStats.meta.spots && window.trifuseSpot"
    )
    _hold_a_whole_picture(console, page)
    spots = page.evaluate("() => window.trifuseStats.meta.spots")
    hot, cold = spots["hot"]["left"], spots["cold"]["left"]
    page.evaluate(
        "([x, y]) => window.trifuseSpot.setSpot('left', x, y)", [hot["x"] + 12, hot["y"] + 4]
    )
    page.wait_for_function("() => window.trifuseSpot.state.spotReading !== null")
    labels = _labels_apart(page, 6)  # hot and cold in each eye, the spot in each eye
    texts = [a["text"] for a in labels]
    assert sum(t.startswith("▲") for t in texts) == 2 and sum(" m" in t for t in texts) == 2, texts
    page.evaluate(
        "([x, y]) => window.trifuseSpot.setBox('left', x - 40, y - 30, x + 40, y + 20)",
        [cold["x"], cold["y"]],
    )
    page.wait_for_function("() => window.trifuseSpot.state.boxReading !== null")
    labels = _labels_apart(page, 8)  # and the box's max and min
    assert {a["text"].split()[0] for a in labels} >= {"max", "min", "▲", "▼"}, labels
    LABELS_SHOT.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(LABELS_SHOT))
    page.close()


def _perspective(fov_y_deg: float, aspect: float, shift_x: float = 0.0) -> list[float]:
    """A WebXR-style projection matrix (column-major, near 0.1, far 100), optionally with
    an off-centre frustum (``shift_x``: straight ahead lands at NDC x = -shift_x, as on a
    head-mounted display whose eyes look through their lenses off-centre)."""
    f = 1 / np.tan(np.radians(fov_y_deg) / 2)
    n, fa = 0.1, 100.0
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = f / aspect, f
    m[0, 2] = shift_x
    m[2, 2], m[2, 3] = (fa + n) / (n - fa), 2 * fa * n / (n - fa)
    m[3, 2] = -1.0
    return m.T.ravel().tolist()  # column-major


def test_xr_gaze_and_controller_rays_map_to_pixels(console, browser) -> None:
    """The pure mapping of the WebXR pointer (a picture drawn over each eye's whole view):
    the gaze is the middle of a symmetric view and off it by the projection's shift; a
    controller's ray turned 10 degrees to the right lands where the projection puts it."""
    page = browser.new_page(viewport={"width": 800, "height": 400})
    page.goto(console.signin("/"))
    page.wait_for_function("() => window.trifuseSpot")
    aspect = 1280 / 960
    sym, shifted = _perspective(90, aspect), _perspective(90, aspect, 0.1)
    to_px = "([p, d]) => window.trifuseSpot.xrDirToPixel(p, d, 1280, 960)"
    assert page.evaluate(to_px, [sym, [0, 0, -1]]) == pytest.approx([639.5, 479.5])
    # an off-centre frustum puts straight ahead at NDC x = -0.1: 0.45 of the width
    assert page.evaluate(to_px, [shifted, [0, 0, -1]]) == pytest.approx([0.45 * 1280 - 0.5, 479.5])
    a = np.radians(10.0)
    d = [float(np.sin(a)), 0.0, float(-np.cos(a))]
    want_x = (np.tan(a) / aspect + 1) / 2 * 1280 - 0.5  # f = 1 at 90 degrees
    assert page.evaluate(to_px, [sym, d]) == pytest.approx([want_x, 479.5], abs=1e-6)
    assert page.evaluate(to_px, [sym, [0, 0, 1]]) is None  # behind
    assert page.evaluate(to_px, [sym, [0, 1, -0.1]]) is None  # above the picture
    # the colour scale's strip under the picture (a tenth of its height): the middle of the
    # view is lower in the picture, the view's bottom is on the scale
    under = "([p, d]) => window.trifuseSpot.xrDirToPixel(p, d, 1280, 960, 0.1)"
    assert page.evaluate(under, [sym, [0, 0, -1]]) == pytest.approx([639.5, 0.55 * 960 - 0.5])
    low = float(np.tan(np.radians(44)))  # 1 degree above the view's bottom edge
    assert page.evaluate(under, [sym, [0, -low, -1]]) is None

    # one XR frame with a fake session: the gaze, then a controller turned 10 degrees right
    fake = """([proj, ctrl]) => {
      const id = {x: 0, y: 0, z: 0, w: 1};
      const views = ['left', 'right'].map((eye) => ({eye, projectionMatrix: proj,
                                                      transform: {orientation: id}}));
      const s = Math.sin(-ctrl / 2), c = Math.cos(-ctrl / 2);  // about y: + turns left
      const src = {targetRayMode: 'tracked-pointer', targetRaySpace: 'ray'};
      const session = {inputSources: ctrl === null ? [] : [src], addEventListener() {}};
      const turned = {transform: {orientation: {x: 0, y: s, z: 0, w: c}}};
      const frame = {session, getPose: () => turned};
      return window.trifuseSpot.xrFrame(frame, {views, transform: {orientation: id}}, 'local');
    }"""
    gaze = page.evaluate(fake, [sym, None])
    assert gaze["mode"] == "gaze"
    assert gaze["px"]["left"] == pytest.approx([639.5, 479.5])
    assert gaze["px"]["right"] == pytest.approx([639.5, 479.5])
    ray = page.evaluate(fake, [sym, float(a)])
    assert ray["mode"] == "controller"
    assert ray["px"]["left"] == pytest.approx([want_x, 479.5], abs=1e-6)
    # the reading under the XR pointer is fetched and drawn into the XR texture
    page.wait_for_function("() => window.trifuseSpot.state.xrReading !== null")
    drawn = page.evaluate(
        "() => { const c = document.createElement('canvas'); c.width = 2560; c.height = 960;"
        " const g = c.getContext('2d'); window.trifuseSpot.drawXr(g, 2560, 960);"
        " const d = g.getImageData(0, 0, 2560, 960).data; let n = 0;"
        " for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }"
    )
    assert drawn > 500  # crosshairs and labels in both eyes
    page.close()


MEASURE_SHOT = Path("/tmp/shots/viewer-regions.png")


def test_a_box_kept_as_a_region_is_outlined_read_and_alarms(console, browser, room) -> None:
    """Issue 35 in the viewer: a box dragged over the second person's head, kept with
    "Box → region" from the Measure panel, becomes the console's region "box 1", outlined on
    the left eye with its corrected maximum (emissivity 0.98 of skin: a little above the
    imager's 34 C); an alarm above 300 K set over REST turns it red and shows the banner;
    Snapshot downloads the ZIP; Line plots a profile; Lock span fixes the span shown. Then
    the panel's own tools and forms: a polygon and a spot drawn on the head, a region renamed
    (its alarm follows), a material and a reflected temperature for one, the difference of
    two chosen, an alarm added and removed, a watched region refused removal; Clear regions
    keeps the regions alarms watch."""
    console.post("/api/source/resume")  # frames again (another test may have paused them)
    page = browser.new_page(viewport={"width": 1400, "height": 700})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(console.signin("/"))
    page.wait_for_function("() => window.trifuseStats.frames > 3 && window.trifuseMeasure")
    _hold_a_whole_picture(console, page)
    truth, names = room["truth"], room["names"]
    x, y = _inner_centre(truth["ccd_left"].solid == names.index("person2_head"))
    console.request("/api/object-parameters", "PUT", {"material": "human skin"})
    x0, y0 = _client_xy(page, "left", x - 20, y - 20)
    x1, y1 = _client_xy(page, "left", x + 20, y + 20)
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move(x1, y1, steps=6)
    page.mouse.up()
    page.wait_for_function("() => window.trifuseSpot.state.box !== null")
    page.get_by_role("button", name="Measure").click()
    assert page.locator("#measure-panel").is_visible()
    page.wait_for_function(
        "() => document.getElementById('measure-material').value === 'human skin'"
    )
    page.get_by_role("button", name="Box → region").click()
    page.wait_for_function(
        "() => window.trifuseMeasure.state.readings"
        " && window.trifuseMeasure.state.readings.regions['box 1']"
    )
    [region] = console.get("/api/regions")
    assert (region["name"], region["eye"], region["shape"]) == ("box 1", "left", "box")
    (rx0, ry0), (rx1, ry1) = region["points"]  # the pointer lands within a pixel
    assert max(abs(rx0 - x + 20), abs(ry0 - y + 20), abs(rx1 - x - 20), abs(ry1 - y - 20)) <= 1
    reading = page.evaluate("() => window.trifuseMeasure.state.readings.regions['box 1']")
    apparent, corrected = reading["apparent"]["max_k"], reading["object"]["max_k"]
    assert 33.0 < apparent - 273.15 < 35.5  # the imager's (+0.75 K offset), as /api/spot
    assert 0.05 < corrected - apparent < 1.0  # e 0.98 in a 20 C room: a little warmer
    # the outline in cyan on the overlay, around the box's corner
    cx, cy = _client_xy(page, "left", x - 20, y)
    px = page.evaluate(
        "([x, y]) => { const c = document.getElementById('measure-overlay');"
        " const r = c.getBoundingClientRect(); const s = c.width / r.width;"
        " const d = c.getContext('2d').getImageData(Math.round((x - r.left) * s) - 3,"
        " Math.round((y - r.top) * s) - 3, 7, 7).data; let best = 0;"
        " for (let i = 0; i < d.length; i += 4) if (d[i + 2] > 200 && d[i] < 120) best = d[i + 3];"
        " return best; }",
        [cx, cy],
    )
    assert px > 0, "no cyan outline at the box's left edge"
    # the hottest pixel marked in red (a ring with a plus), where the reading says it is
    hx, hy = _client_xy(page, "left", *reading["object"]["max_at"])
    red = page.evaluate(
        "([x, y]) => { const c = document.getElementById('measure-overlay');"
        " const r = c.getBoundingClientRect(); const s = c.width / r.width;"
        " const d = c.getContext('2d').getImageData(Math.round((x - r.left) * s) - 4,"
        " Math.round((y - r.top) * s) - 4, 9, 9).data; let n = 0;"
        " for (let i = 0; i < d.length; i += 4)"
        " if (d[i] > 200 && d[i + 1] < 100 && d[i + 3] > 200) n++;"
        " return n; }",
        [hx, hy],
    )
    assert red > 5, "no red marker at the box's hottest pixel"

    status, _ = console.request(
        "/api/alarms", "PUT", [{"region": "box 1", "kind": "above", "threshold": 300.0}]
    )
    assert status == 200
    page.wait_for_function(
        "() => document.getElementById('alarm-banner').textContent"
        ".includes('box 1 max above 26.9 °C')"
    )
    assert page.locator("#alarm-banner").is_visible()
    MEASURE_SHOT.parent.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(MEASURE_SHOT))
    with page.expect_download() as download:  # the snapshot's ZIP
        page.get_by_role("button", name="Snapshot").click()
    assert re.fullmatch(r"trifuse-snapshot-\d+\.zip", download.value.suggested_filename)
    with zipfile.ZipFile(download.value.path()) as z:
        assert "object_left.png" in z.namelist() and "regions.csv" in z.namelist()
    # a line across the head: its profile plotted, the head's temperature in its middle
    page.get_by_role("button", name="Line").click()
    a, b = _client_xy(page, "left", x - 60, y), _client_xy(page, "left", x + 60, y)
    page.mouse.move(*a)
    page.mouse.down()
    page.mouse.move(*b, steps=6)
    page.mouse.up()
    page.wait_for_function("() => window.trifuseMeasure.state.profile !== null")
    profile = page.evaluate("() => window.trifuseMeasure.state.profile")
    n = len(profile["object_k"])
    assert 118 <= n <= 122 and profile["eye"] == "left"
    middle = [v for v in profile["object_k"][n // 2 - 5 : n // 2 + 5] if v is not None]
    assert middle and all(33.0 < v - 273.15 < 36.5 for v in middle), middle
    assert page.locator("#profile-plot").is_visible()
    page.screenshot(path=str(MEASURE_SHOT.with_name("viewer-profile.png")))
    page.get_by_role("button", name="Line").click()  # line mode off: the spot meter again
    assert not page.locator("#profile-plot").is_visible()
    # span lock: the span shown becomes the operator's; the button then unlocks it
    page.get_by_role("button", name="Lock span").click()
    page.wait_for_function("() => window.trifuseStats.meta.span_auto === false")
    page.get_by_role("button", name="Unlock span").click()
    page.wait_for_function("() => window.trifuseStats.meta.span_auto === true")
    _panel_tools_and_forms(console, page, x, y)
    page.get_by_role("button", name="Clear regions").click()  # the alarm's region stays
    page.wait_for_function("() => window.trifuseMeasure.state.regions.length === 1")
    assert [r["name"] for r in console.get("/api/regions")] == ["head box"]
    console.request("/api/alarms", "PUT", [])
    page.get_by_role("button", name="Clear regions").click()
    page.wait_for_function("() => window.trifuseMeasure.state.regions.length === 0")
    assert console.get("/api/regions") == []
    console.request("/api/object-parameters", "PUT", {})
    console.post("/api/source/resume")
    assert errors == []
    page.close()


def _panel_tools_and_forms(console: Any, page: Any, x: int, y: int) -> None:
    """The Measure panel on the held picture, the second person's head at left pixel (x, y)
    and "box 1" (an alarm above 300 K on it) kept: a polygon (four clicks and a double
    click) and a spot (a click) drawn on the head read its temperature; "box 1" renamed in
    its row takes its alarm along; a material and a reflected temperature set in a row are
    the region's; the difference of two chosen regions is the console's; an alarm added
    from the form, a watched region's × refused with the console's line, the alarm's ×."""
    measure = "window.trifuseMeasure.state"
    page.get_by_role("button", name="Polygon").click()
    corners = [(x - 25, y), (x, y - 25), (x + 25, y), (x, y + 25)]
    for cx, cy in corners[:-1]:
        page.mouse.click(*_client_xy(page, "left", cx, cy))
    page.mouse.dblclick(*_client_xy(page, "left", *corners[-1]))
    page.wait_for_function(f"() => {measure}.regions.some((r) => r.name === 'polygon 1')")
    page.get_by_role(
        "button", name="Spot", exact=True
    ).click()  # the polygon tool off, the spot's on
    page.mouse.click(*_client_xy(page, "left", x, y))
    page.wait_for_function(f"() => {measure}.regions.some((r) => r.name === 'spot 1')")
    page.get_by_role("button", name="Spot", exact=True).click()  # no tool: the spot meter's again
    regions = {r["name"]: r for r in console.get("/api/regions")}
    polygon, spot = regions["polygon 1"], regions["spot 1"]
    assert polygon["shape"] == "polygon" and polygon["eye"] == "left"
    assert len(polygon["points"]) == 4  # the double click's twin corner dropped
    assert all(abs(px - cx) <= 1 and abs(py - cy) <= 1
               for (px, py), (cx, cy) in zip(polygon["points"], corners, strict=True))  # fmt: skip
    assert (
        spot["shape"] == "spot"
        and max(abs(spot["points"][0][0] - x), abs(spot["points"][0][1] - y)) <= 1
    )
    page.wait_for_function(
        f"() => ['polygon 1', 'spot 1'].every((n) => {measure}.readings"
        f" && {measure}.readings.regions[n])"
    )
    read = page.evaluate(f"() => {measure}.readings.regions")
    for name in ("polygon 1", "spot 1"):
        assert 33.5 < read[name]["object"]["mean_k"] - 273.15 < 36.5, (name, read[name])
    # rename the watched box in its row: the alarm follows it
    row = page.locator("#measure-regions tr[data-region='box 1']")
    row.get_by_label("region name").fill("head box")
    row.get_by_label("region name").press("Enter")
    page.wait_for_function(
        "() => document.getElementById('alarm-banner').textContent.includes('head box max above')"
    )
    assert [a["region"] for a in console.get("/api/alarms")["rules"]] == ["head box"]
    # the spot's surface: a material, then a reflected temperature of its own
    row = page.locator("#measure-regions tr[data-region='spot 1']")
    row.get_by_label("spot 1 surface").select_option("oxidised steel")
    page.wait_for_function(
        "() => window.trifuseMeasure.state.regions.some((r) => r.emissivity === 0.8)"
    )
    row = page.locator("#measure-regions tr[data-region='spot 1']")
    row.get_by_label("spot 1 reflected °C").fill("-20")
    row.get_by_label("spot 1 reflected °C").press("Enter")
    page.wait_for_function(
        "() => window.trifuseMeasure.state.regions.some((r) => r.reflected_k !== null)"
    )
    spot = next(r for r in console.get("/api/regions") if r["name"] == "spot 1")
    assert spot["emissivity"] == 0.8 and abs(spot["reflected_k"] - 253.15) < 1e-6
    # the difference of the spot and the polygon, their maxima
    page.locator("#measure-delta-a").select_option("spot 1")
    page.locator("#measure-delta-b").select_option("polygon 1")
    page.locator("#measure-delta-stat").select_option("max")
    page.wait_for_function(
        f"() => {measure}.delta && {measure}.delta.a === 'spot 1' && {measure}.delta.stat === 'max'"
    )
    want = console.get("/api/measurements/delta?a=spot%201&b=polygon%201&stat=max")["delta_k"]
    shown = page.locator("#measure-delta").text_content()
    assert shown == f"{'+' if want >= 0 else '−'}{abs(want):.2f} K", (shown, want)
    # an alarm from the form: the spot's minimum below 0 °C; its removal is refused meanwhile
    page.locator("#measure-alarm-region").select_option("spot 1")
    page.locator("#measure-alarm-kind").select_option("below")
    page.locator("#measure-alarm-threshold").fill("0")
    page.get_by_role("button", name="Add alarm").click()
    page.wait_for_function(f"() => {measure}.rules.length === 2")
    rules = console.get("/api/alarms")["rules"]
    assert (rules[1]["region"], rules[1]["kind"]) == ("spot 1", "below")
    assert abs(rules[1]["threshold"] - 273.15) < 1e-9
    page.get_by_role("button", name="remove spot 1").click()
    page.wait_for_function(
        "() => document.getElementById('measure-hint').textContent.includes('alarms watch spot 1')"
    )
    assert "spot 1" in [r["name"] for r in console.get("/api/regions")]
    page.screenshot(path=str(MEASURE_SHOT.with_name("viewer-measure-panel.png")))
    page.get_by_role("button", name="remove alarm spot 1 min below 0.0 °C").click()
    page.wait_for_function(f"() => {measure}.rules.length === 1")
    page.get_by_role("button", name="remove spot 1").click()
    page.wait_for_function(f"() => !{measure}.regions.some((r) => r.name === 'spot 1')")
