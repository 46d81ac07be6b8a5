"""Measurements over REST (app/server/routers/measure_api.py): object parameters, regions,
readings, the delta, alarms and their events in /api/status, on a console pipeline fusing
the simulated measurement scene (tests/fusion/test_measure.py's picture: four panels of
known temperature and emissivity at 2-9 m in humid air; imagers without offset). Bad input:
a 422 with one line, and nothing changed."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.measure_support import panel_boxes, render
from tests.support import WAIT_S, ListSource, wait_until
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime.measurements import Measurements
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.measurement_scene import (
    AIR_K,
    HUMIDITY_PCT,
    PANELS,
    SKY_K,
)
from trifuse.fusion.alarms import AlarmRule
from trifuse.fusion.regions import Region
from trifuse.fusion.spot import SpotFrame

TOLERANCE_K = 0.5  # issue 35's; tests/fusion/test_measure.py says why it holds
PARAMS = {
    "emissivity": 0.95,
    "reflected_k": SKY_K,
    "air_k": AIR_K,
    "humidity_pct": HUMIDITY_PCT,
    "default_distance_m": 3.0,
}
TRUE_K = {p.name: p.temperature_k for p in PANELS}


def _later(fs: FrameSet, dt_ns: int) -> FrameSet:
    stamp = fs.stamp_ns + dt_ns
    return FrameSet(
        stamp, {n: Frame(n, stamp, f.image, f.distance_m) for n, f in fs.frames.items()}
    )


@pytest.fixture(scope="module")
def scene() -> tuple[FrameSet, dict]:
    """One frame set of the scene and a box well inside each panel (left eye's pixels)."""
    frames, truth = render()
    return frames, panel_boxes(truth)


def _regions(boxes) -> list[dict]:
    eps = {p.name: p.emissivity for p in PANELS}
    return [
        {"name": n, "eye": "left", "shape": "box", "points": b, "emissivity": eps[n]}
        for n, b in boxes.items()
    ]


@pytest.fixture(scope="module")
def console(scene) -> Iterator[tuple[TestClient, FusionPipeline]]:
    """Regions, parameters and two alarms set before the pipeline fuses three sets 0.2 s
    apart (each one read: the readings' interval is 0.1 s of frame time)."""
    frames, boxes = scene
    hub = FrameHub()
    sets = [frames, _later(frames, 200_000_000), _later(frames, 400_000_000)]
    pipeline = FusionPipeline(ListSource.of_sets(sets), default_rig(), hub)
    client = TestClient(create_app(hub, None, pipeline))
    assert client.put("/api/object-parameters", json=PARAMS).status_code == 200
    r = client.put("/api/regions", json=_regions(boxes))
    assert r.status_code == 200, r.text
    r = client.get("/api/measurements")
    assert r.status_code == 503 and "no reading yet" in r.json()["detail"]
    alarms = [
        {"region": "hot", "kind": "above", "threshold": 400.0},  # 423 K: raised
        {"region": "paint", "kind": "below", "threshold": 300.0},  # 318 K: never
    ]
    assert client.put("/api/alarms", json=alarms).status_code == 200
    with hub.watching():
        pipeline.start()
        assert pipeline.join(WAIT_S), "the pipeline did not fuse the three sets"
    # the regions are read aside: wait until the reading thread has nothing left to do
    m = pipeline.measurements
    wait_until(
        lambda: m.readings is not None and m.idle,
        "the regions read",
    )
    yield client, pipeline
    pipeline.stop()


def test_readings_are_the_panels_true_temperatures(console) -> None:
    client, pipeline = console
    r = client.get("/api/measurements")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["stamp_ns"] == pipeline.measurements.readings.stamp_ns and body["errors"] == {}
    assert body["params"]["humidity_pct"] == HUMIDITY_PCT
    for name, reading in body["regions"].items():
        assert reading["object"]["mean_k"] == pytest.approx(TRUE_K[name], abs=TOLERANCE_K)
        assert reading["apparent"]["mean_k"] < TRUE_K[name] - 1.0  # uncorrected: too low
        assert reading["default_distance_px"] == 0
        x, y = reading["object"]["max_at"]
        (x0, y0), (x1, y1) = next(b["points"] for b in client.get("/api/regions").json()
                                  if b["name"] == name)  # fmt: skip
        assert x0 <= x <= x1 and y0 <= y <= y1


def test_delta_between_two_regions(console) -> None:
    client, _ = console
    r = client.get("/api/measurements/delta", params={"a": "hot", "b": "paint"})
    assert r.status_code == 200, r.text
    assert r.json()["delta_k"] == pytest.approx(TRUE_K["hot"] - TRUE_K["paint"], abs=1.0)
    r = client.get("/api/measurements/delta", params={"a": "hot", "b": "nowhere"})
    assert r.status_code == 404 and r.json()["detail"] == "no region named 'nowhere'"
    first_two = client.get("/api/measurements/delta", params={"stat": "max"}).json()
    assert (first_two["a"], first_two["b"]) == ("paint", "steel")


def test_alarm_raised_and_in_the_status(console) -> None:
    client, _ = console
    st = client.get("/api/status").json()["measurements"]
    assert st["regions"] == 4 and st["active_alarms"] == ["hot above 400"]
    [event] = st["events"]
    assert (event["region"], event["kind"], event["state"]) == ("hot", "above", "raised")
    assert event["value"] == pytest.approx(TRUE_K["hot"], abs=1.5)  # the maximum pixel
    alarms = client.get("/api/alarms", params={"after": event["seq"]}).json()
    assert alarms["events"] == [] and len(alarms["rules"]) == 2


@pytest.mark.parametrize(
    ("path", "body", "says"),
    [
        ("/api/object-parameters", PARAMS | {"emissivity": 0.005}, "emissivity"),
        ("/api/object-parameters", PARAMS | {"humidity_pct": 120}, "humidity_pct"),
        ("/api/object-parameters", PARAMS | {"material": "unobtainium"}, "material: expected"),
        (
            "/api/regions",
            [{"name": "far", "shape": "box", "points": [[5000, 10], [5100, 20]]}],
            "far: outside the 1280x960 image",
        ),
        (
            "/api/regions",
            [{"name": "a", "shape": "spot", "points": [[1, 1]]}] * 2,
            "names must be unique, a more than once",
        ),
        (
            "/api/regions",
            [{"name": "a", "shape": "box", "points": [[1, 1]]}],
            "a: a box takes 2 points, got 1",
        ),
        ("/api/alarms", [{"region": "nowhere", "kind": "above", "threshold": 1}], "no region"),
        ("/api/alarms", [{"region": "hot", "kind": "hotter", "threshold": 1}], "kind"),
    ],
)
def test_bad_input_is_a_422_and_changes_nothing(console, path, body, says) -> None:
    client, _ = console
    before = {p: client.get(p).json() for p in ("/api/object-parameters", "/api/regions")}
    rules = client.get("/api/alarms").json()["rules"]
    r = client.put(path, json=body)
    assert r.status_code == 422
    assert says in str(r.json()["detail"])
    assert {p: client.get(p).json() for p in before} == before
    assert client.get("/api/alarms").json()["rules"] == rules


def test_a_region_an_alarm_watches_is_not_removed(console) -> None:
    client, _ = console
    r = client.delete("/api/regions/hot")
    assert r.status_code == 422 and "alarms watch hot" in r.json()["detail"]
    assert client.delete("/api/regions/nowhere").status_code == 404


def test_material_sets_the_emissivity(console) -> None:
    client, _ = console
    try:
        r = client.put("/api/object-parameters", json=PARAMS | {"material": "human skin"})
        assert r.status_code == 200 and r.json()["emissivity"] == 0.98
    finally:
        client.put("/api/object-parameters", json=PARAMS)


def test_a_region_renamed_keeps_its_alarm_and_takes_another_surface(console) -> None:
    """PATCH /api/regions/{name}: a new name (the alarm watching it follows, still raised: no
    second event), a material for the region's emissivity, then null: the global
    emissivity again (the steel panel's reading falls back to 0.95's: too low). Bad edits:
    422 or 404 with one line, nothing changed."""
    client, pipeline = console
    m = pipeline.measurements
    before = client.get("/api/regions").json()
    rules = client.get("/api/alarms").json()["rules"]
    assert client.get("/api/materials").json()["oxidised steel"] == 0.8
    try:
        events = client.get("/api/alarms").json()["events"]
        r = client.patch("/api/regions/hot", json={"name": "hot plate"})
        assert r.status_code == 200, r.text
        assert [x["name"] for x in r.json()] == ["paint", "steel", "half", "hot plate"]
        alarms = client.get("/api/alarms").json()
        assert [a["region"] for a in alarms["rules"]] == ["hot plate", "paint"]
        wait_until(lambda: m.idle and m.status()["active_alarms"] == ["hot plate above 400"],
                   lambda: f"the renamed region's alarm raised: {m.status()}")  # fmt: skip
        assert client.get("/api/alarms").json()["events"] == events  # still raised: no event
        r = client.patch("/api/regions/steel", json={"emissivity": None})
        assert r.status_code == 200 and r.json()[1]["emissivity"] is None
        steel = lambda: m.readings.regions["steel"].object.mean_k - TRUE_K["steel"]  # noqa: E731
        wait_until(lambda: m.idle and steel() < -2, "steel read with the global emissivity 0.95")
        r = client.patch("/api/regions/steel", json={"material": "oxidised steel"})
        assert r.status_code == 200 and r.json()[1]["emissivity"] == 0.8
        wait_until(lambda: m.idle and abs(steel()) < TOLERANCE_K, "steel read with 0.8 again")
        now = client.get("/api/regions").json()
        for edit, status, says in [
            ({"name": "paint"}, 422, "name: another region is called 'paint'"),
            ({"material": "glass", "emissivity": 0.5}, 422, "not both"),
            ({"material": "cheese"}, 422, "material: expected one of"),
            ({"points": [[5000, 10], [5100, 20]]}, 422, "outside the 1280x960 image"),
            ({"emissivity": 1.5}, 422, "emissivity"),
            ({"name": None}, 422, "expected a value"),
            ({"colour": "red"}, 422, "colour"),
        ]:
            r = client.patch("/api/regions/steel", json=edit)
            assert r.status_code == status and says in str(r.json()["detail"]), (edit, r.text)
        r = client.patch("/api/regions/nowhere", json={"name": "x"})
        assert r.status_code == 404 and r.json()["detail"] == "no region named 'nowhere'"
        assert client.get("/api/regions").json() == now
    finally:
        client.patch("/api/regions/hot plate", json={"name": "hot"})
        assert client.get("/api/regions").json() == before
        assert client.get("/api/alarms").json()["rules"] == rules


def _frame_at(frame: SpotFrame, t_s: float) -> SpotFrame:
    out = SpotFrame.__new__(SpotFrame)
    out.__dict__.update(frame.__dict__, stamp_ns=round(t_s * 1e9))
    return out


def test_alarms_rise_clear_with_hysteresis_and_throttle(console, scene) -> None:
    """The console's Measurements on the same picture at chosen frame times: readings at
    most every 0.1 s; an alarm on a region raised once, cleared when the parameters move
    the reading back beyond the hysteresis."""
    _, pipeline = console
    frame = pipeline.spots
    m = Measurements()
    _, boxes = scene
    m.set_regions([Region("hot", "left", "box", tuple(boxes["hot"]), 0.95)], (1280, 960))
    m.set_params(dataclasses.replace(m.params, reflected_k=SKY_K, air_k=AIR_K))
    m.set_rules([AlarmRule("hot", "above", 420.0, hysteresis=1.0)])
    m.update(_frame_at(frame, 1.0))
    first = m.readings
    assert [e["state"] for e in m.events()] == ["raised"]
    m.update(_frame_at(frame, 1.05))  # within the interval: not read
    assert m.readings is first
    # an emissivity of 1 reads the plate about 7 K colder: cleared (beyond 1 K back)
    m.set_regions([Region("hot", "left", "box", tuple(boxes["hot"]), 1.0)], (1280, 960))
    m.update(_frame_at(frame, 1.06))  # a change reads at the next picture
    assert m.readings is not first
    assert [e["state"] for e in m.events()] == ["raised", "cleared"]
    assert m.status()["active_alarms"] == []


def test_snapshot_holds_the_pair_and_each_eyes_temperatures(console, scene) -> None:
    """GET /api/snapshot: the fused pair, each eye's apparent and object temperatures as
    16-bit centi-kelvin PNGs (the object map reads the panels' truth inside their regions,
    with their emissivities), the parameters and the regions' table."""
    import io
    import json
    import zipfile

    client, pipeline = console
    r = client.get("/api/snapshot")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    z = zipfile.ZipFile(io.BytesIO(r.content))
    names = set(z.namelist())
    assert names == {"fused.png", "apparent_left.png", "apparent_right.png", "object_left.png",
                     "object_right.png", "parameters.json", "regions.csv"}  # fmt: skip
    w, h = pipeline.fusion.size
    fused = cv2.imdecode(np.frombuffer(z.read("fused.png"), np.uint8), cv2.IMREAD_COLOR)
    assert fused.shape == (h, 2 * w, 3)
    maps = {}
    for n in ("apparent_left", "object_left"):
        png = cv2.imdecode(np.frombuffer(z.read(f"{n}.png"), np.uint8), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (h, w)
        maps[n] = png.astype(np.float64) / 100.0
    _, boxes = scene
    for name, ((x0, y0), (x1, y1)) in boxes.items():
        patch = maps["object_left"][int(y0) : int(y1) + 1, int(x0) : int(x1) + 1]
        assert patch.mean() == pytest.approx(TRUE_K[name], abs=TOLERANCE_K), name
        apparent = maps["apparent_left"][int(y0) : int(y1) + 1, int(x0) : int(x1) + 1]
        assert apparent.mean() < TRUE_K[name] - 1.0
    info = json.loads(z.read("parameters.json"))
    assert info["stamp_ns"] == pipeline.spots.stamp_ns
    assert info["parameters"]["humidity_pct"] == HUMIDITY_PCT and len(info["regions"]) == 4
    table = z.read("regions.csv").decode().splitlines()
    assert table[0].startswith("stamp_ns,region,pixels,max_k") and len(table) == 5


def test_span_lock_fixes_the_span_the_picture_shows(console) -> None:
    """POST /api/thermal/span-lock: the automatic span of the last picture becomes the
    manual one (to 0.01 K); PUT /api/thermal with span_k null unlocks it."""
    client, pipeline = console
    shown = pipeline.hub.latest.meta["span_k"]
    assert pipeline.hub.latest.meta["span_auto"] is True
    try:
        r = client.post("/api/thermal/span-lock")
        assert r.status_code == 200, r.text
        assert r.json()["span_k"] == pytest.approx(shown, abs=0.005)
        assert pipeline.settings.span_k == pytest.approx(shown, abs=0.005)
    finally:
        assert client.put("/api/thermal", json={"span_k": None}).status_code == 200
    assert pipeline.settings.span_k is None


def test_span_lock_before_a_picture_is_a_409() -> None:
    hub = FrameHub()
    pipeline = FusionPipeline(ListSource.of_sets([]), default_rig(), hub)
    r = TestClient(create_app(hub, None, pipeline)).post("/api/thermal/span-lock")
    assert r.status_code == 409 and "nothing to lock" in r.json()["detail"]


def test_profile_across_the_hot_plate(console, scene) -> None:
    """GET /api/profile: a line across the hot plate's box reads the plate's true
    temperature in the middle (corrected), the imager's lower one apparent; a point
    outside the picture is a 422."""
    client, _ = console
    _, boxes = scene
    (x0, y0), (x1, y1) = boxes["hot"]
    y = (y0 + y1) / 2
    r = client.get("/api/profile", params={"x0": x0, "y0": y, "x1": x1, "y1": y})
    assert r.status_code == 200, r.text
    p = r.json()
    n = len(p["distance_px"])
    assert n == int(np.ceil(x1 - x0)) + 1 and p["distance_px"][-1] == pytest.approx(x1 - x0)
    middle = np.array(p["object_k"][n // 4 : 3 * n // 4], float)
    assert np.abs(middle - TRUE_K["hot"]).mean() < TOLERANCE_K
    assert max(p["apparent_k"][n // 4 : 3 * n // 4]) < TRUE_K["hot"] - 1.0
    bad = client.get("/api/profile", params={"x0": -5, "y0": y, "x1": x1, "y1": y})
    assert bad.status_code == 422 and bad.json()["detail"].startswith("x0: expected a pixel")
