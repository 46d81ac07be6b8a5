"""The spot meter's REST routes (/api/spot, /api/area) and the hot and cold spots in the
stream's metadata, on a console pipeline fusing the simulated inspection room (seed 0, the
picture of tests/fusion/test_spot.py)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.support import WAIT_S, ListSource
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.inspection import InspectionScenario

T_S = 18.0


@pytest.fixture(scope="module")
def room() -> tuple[InspectionScenario, FrameSet, dict]:
    scenario = InspectionScenario(seed=0, live=True)
    frames, truth = scenario.render(T_S)
    return scenario, frames, truth


def _again(fs: FrameSet, dt_ns: int) -> FrameSet:
    """The same pictures ``dt_ns`` later (the assembler closes a set on the next one)."""
    stamp = fs.stamp_ns + dt_ns
    return FrameSet(
        stamp, {n: Frame(n, stamp, f.image, f.distance_m) for n, f in fs.frames.items()}
    )


@pytest.fixture(scope="module")
def console(room) -> Iterator[tuple[TestClient, FusionPipeline, FrameHub]]:
    scenario, frames, _ = room
    hub = FrameHub()
    sets = [frames, _again(frames, 33_333_333), _again(frames, 66_666_667)]
    pipeline = FusionPipeline(ListSource.of_sets(sets), scenario.rig, hub)
    client = TestClient(create_app(hub, None, pipeline))
    r = client.get("/api/spot", params={"eye": "left", "x": 640, "y": 480})
    assert r.status_code == 503 and "no fused picture yet" in r.json()["detail"]
    with hub.watching():
        pipeline.start()
        # all three sets fused (a route read before the last would race with it)
        assert pipeline.join(WAIT_S), "the pipeline did not fuse the three sets"
    yield client, pipeline, hub
    pipeline.stop()


def _head_centre(room, eye: str = "left") -> tuple[int, int]:
    scenario, _, truth = room
    k = [s.name for s in scenario.scene.solids].index("person2_head")
    ys, xs = np.nonzero(truth[f"ccd_{eye}"].solid == k)
    return int(np.median(xs)), int(np.median(ys))


def test_spot_route_reads_the_person(console, room) -> None:
    client, pipeline, _ = console
    x, y = _head_centre(room)
    r = client.get("/api/spot", params={"eye": "left", "x": x, "y": y})
    assert r.status_code == 200, r.text
    s = r.json()
    assert (s["eye"], s["x"], s["y"], s["depth"]) == ("left", x, y, "measured")
    assert 33.0 < s["temperature_c"] < 35.5  # 34 C skin, +0.75 K imager offset
    assert s["temperature_k"] == pytest.approx(s["temperature_c"] + 273.15)
    truth_m = float(room[2]["ccd_left"].range_m[y, x])
    assert s["distance_m"] == pytest.approx(truth_m, abs=0.2)  # tests/fusion/test_spot.py's bound
    assert s["stamp_ns"] == pipeline.spots.stamp_ns
    assert s["eyes_px"]["left"] == pytest.approx([x, y])
    assert len(s["eyes_px"]["right"]) == 2


def test_area_route_finds_the_box_extremes(console, room) -> None:
    client, _, _ = console
    x, y = _head_centre(room)
    params = {"eye": "left", "x0": x + 80, "y0": y + 30, "x1": x - 80, "y1": y - 70}
    r = client.get("/api/area", params=params)
    assert r.status_code == 200, r.text
    a = r.json()
    assert (a["x0"], a["y0"], a["x1"], a["y1"]) == (x - 80, y - 70, x + 80, y + 30)
    assert a["pixels"] == 161 * 101 and a["thermal_pixels"] > 0.9 * a["pixels"]
    assert 33.0 < a["max"]["temperature_c"] < 35.5  # the head
    assert 9.0 < a["min"]["temperature_c"] < 12.0  # the 9 C window behind it reads ~10.3 C
    assert a["min"]["temperature_c"] < a["mean_c"] < a["max"]["temperature_c"]
    assert a["max"]["stamp_ns"] == a["stamp_ns"]


@pytest.mark.parametrize(
    ("path", "params", "says"),
    [
        ("/api/spot", {"eye": "middle", "x": 1, "y": 1}, "eye: expected one of ['left', 'right']"),
        ("/api/spot", {"eye": "left", "x": 1280, "y": 1}, "x: expected a colour pixel 0..1279"),
        ("/api/spot", {"eye": "right", "x": 0, "y": -1}, "y: expected a colour pixel 0..959"),
        ("/api/spot", {"eye": "left", "x": "1.5", "y": 1}, "x"),
        ("/api/area", {"eye": "left", "x0": 0, "y0": 0, "x1": 5, "y1": 960}, "y1: expected"),
        ("/api/area", {"eye": "up", "x0": 0, "y0": 0, "x1": 5, "y1": 5}, "eye: expected"),
    ],
)
def test_bad_queries_get_422_saying_why(console, path, params, says) -> None:
    client, _, _ = console
    r = client.get(path, params=params)
    assert r.status_code == 422
    assert says in str(r.json()["detail"])


def test_defaults_are_the_middle_and_the_whole_picture(console) -> None:
    client, pipeline, _ = console
    s = client.get("/api/spot").json()
    assert (s["eye"], s["x"], s["y"]) == ("left", 639, 479)
    assert client.get("/api/spot", params={"eye": "right", "y": 3}).json()["x"] == 639
    a = client.get("/api/area", params={"eye": "right"}).json()
    assert (a["x0"], a["y0"], a["x1"], a["y1"], a["pixels"]) == (0, 0, 1279, 959, 1280 * 960)
    whole = pipeline.spots.area("right", 0, 0, 1279, 959)
    assert a["max"]["temperature_k"] == whole.max.temperature_k


def test_hot_and_cold_spots_in_the_stream_metadata(console, room) -> None:
    _, pipeline, hub = console
    frame = hub.latest
    assert frame is not None
    spots = frame.meta["spots"]
    assert set(spots) == {"hot", "cold"} and set(spots["hot"]) == {"left", "right"}
    scenario, _, truth = room
    names = [s.name for s in scenario.scene.solids]
    for eye in ("left", "right"):
        hot, cold = spots["hot"][eye], spots["cold"][eye]
        assert set(hot) == {"x", "y", "temperature_k", "distance_m", "depth"}
        assert names[truth[f"ccd_{eye}"].solid[hot["y"], hot["x"]]] == "hot_pipe"
        assert names[truth[f"ccd_{eye}"].solid[cold["y"], cold["x"]]] == "window"
        assert 350.0 < hot["temperature_k"] < 356.0 and 4.0 < hot["distance_m"] < 5.5
        assert cold["depth"] == "fallback" and cold["distance_m"] is None
    assert spots == pipeline.spots.extremes()
