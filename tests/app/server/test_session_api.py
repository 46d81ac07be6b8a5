"""REST routes of the calibration session (/api/captures, /api/calibrate, /api/rigs)."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from tests.support import wait_searched, wait_until
from trifuse.app.server.routers.session_api import make_session_router
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.workflows.calib_session import CalibrationSession
from trifuse.calib.rig import Rig


@pytest.fixture
def api(tmp_path, calibration_frame_sets):
    """A client over a fresh session whose "newest frames" are chosen by the test."""
    rig = default_rig()
    session = CalibrationSession(tmp_path, rig, CALIBRATION_BOARD)
    state: dict = {"latest": None, "used": []}

    def use(new: Rig) -> None:
        if set(new.names) != set(rig.names):
            raise ValueError("wrong sensors")
        state["used"].append(new)

    app = FastAPI()
    app.include_router(make_session_router(session, lambda: state["latest"], use))
    with TestClient(app) as client:
        yield client, session, state, calibration_frame_sets
    session.close()


def test_captures_take_list_delete(api) -> None:
    client, session, state, frames = api
    r = client.post("/api/captures")
    assert r.status_code == 409 and "no frames yet" in r.json()["detail"]
    state["latest"] = frames[0]
    r = client.post("/api/captures")
    assert r.status_code == 201 and r.json()["name"] == "0001"
    assert (session.captures / "0001" / "tof_distance.png").is_file()  # on disk already
    wait_searched(session)
    listing = client.get("/api/captures").json()
    assert [v["name"] for v in listing["views"]] == ["0001"]
    assert all(d["found"] for d in listing["views"][0]["sensors"].values())
    assert listing["coverage"]["ccd_left"]["views"] == 1
    assert client.delete("/api/captures/0042").status_code == 404
    r = client.delete("/api/captures/0001")
    assert r.status_code == 200 and "deleted" in r.json()["moved_to"]
    assert client.get("/api/captures").json()["views"] == []


@pytest.mark.slow  # a calibration of simulated views through the API: about 6 s
def test_calibrate_save_and_use_a_version(api) -> None:
    client, session, state, frames = api
    r = client.post("/api/calibrate")
    assert r.status_code == 409 and "at least 3" in r.json()["detail"]
    assert client.get("/api/calibrate/result").status_code == 404
    assert client.post("/api/rigs").status_code == 409  # nothing to save
    for fs in frames:
        state["latest"] = fs
        assert client.post("/api/captures").status_code == 201
    r = client.post("/api/calibrate")
    assert r.status_code == 202 and r.json()["state"] == "running"
    assert client.post("/api/calibrate").status_code == 409  # one run at a time
    status = wait_until(
        lambda: (s := client.get("/api/calibrate").json())["state"] != "running" and s,
        "the calibration run to end",
        timeout_s=600.0,
    )
    assert status["state"] == "done", status
    assert status["progress"] == 1.0 and len(status["views"]) == len(frames)
    report = client.get("/api/calibrate/result").json()
    assert report["format"] == "trifuse-calibration-report/1"
    assert set(report["sensors"]) == set(default_rig().names)

    r = client.post("/api/rigs")
    assert r.status_code == 201 and r.json()["name"] == "rig-0001"
    assert client.post("/api/rigs").status_code == 409  # saved already
    versions = client.get("/api/rigs").json()
    assert [v["name"] for v in versions] == ["rig-0001"]
    assert versions[0]["rms_px"] == pytest.approx(report["rms_px"])
    rig = client.get("/api/rigs/rig-0001").json()
    assert set(rig["sensors"]) == set(default_rig().names)
    assert client.get("/api/rigs/rig-0009").status_code == 404
    assert client.post("/api/rigs/rig-0001/use").json() == {"in_use": "rig-0001"}
    assert state["used"] and state["used"][0].names == default_rig().names
    wait_searched(session)
