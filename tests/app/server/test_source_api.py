"""The source REST routes on a real pipeline over a short recording: status, pause, seek,
rate (validated), recording start/stop into the work directory (never overwriting)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from tests.support import (
    ListSource,
    assert_same_frame,
    small_rig,
    synth_frames,
    wait_until,
    write_recording,
)
from trifuse.app.recording import ReplaySource
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig

DURATION_S = 3.0


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


@pytest.fixture(scope="module")
def recording(tmp_path_factory, rig) -> tuple[Path, list[Frame]]:
    """A 3 s recording of the five sensors at their own rates (tenth resolution)."""
    frames = synth_frames(rig, DURATION_S, seed=5)
    path = tmp_path_factory.mktemp("src") / "short.mcap"
    return write_recording(path, rig, frames), frames


class Console:
    """The app over a looping real-time replay, as ``trifuse serve --replay`` builds it."""

    def __init__(self, path: Path, rig: Rig, workdir: Path) -> None:
        self.replay = ReplaySource(path, loop=True, realtime=True)
        self.hub = FrameHub()
        self.pipeline = FusionPipeline(SourceTap(self.replay), rig, self.hub).start()
        self.control = SourceControl(self.pipeline, self.hub, f"replay of {path}", workdir)
        self.client = TestClient(create_app(self.hub, None, self.pipeline, self.control))
        self.workdir = workdir

    def status(self) -> dict:
        r = self.client.get("/api/status")
        assert r.status_code == 200, r.text
        return r.json()

    def wait(self, what) -> dict:
        """The status once ``what(status)`` holds."""
        seen: list[dict] = []

        def status() -> dict | None:
            seen[:] = [self.status()]
            return seen[0] if what(seen[0]) else None

        return wait_until(status, lambda: f"a status like that; the last one: {seen}")

    def close(self) -> None:
        self.control.stop()
        self.pipeline.stop()


@pytest.fixture()
def console(recording, rig, tmp_path) -> Iterator[Console]:
    c = Console(recording[0], rig, tmp_path / "work")
    try:
        yield c
    finally:
        c.close()


def test_status_reports_source_rates_and_the_old_keys(console) -> None:
    s = console.wait(lambda s: s["frames_out"] > 10 and s["rates_hz"].get("tof", 0) > 5)
    for key in ("viewers", "frames_out", "fps", "missing", "error"):  # the first route's keys
        assert key in s
    assert s["viewers"] == 0 and s["error"] is None
    src = s["source"]
    assert src["kind"] == "replay" and src["description"].startswith("replay of")
    assert src["duration_s"] == pytest.approx(DURATION_S, abs=0.05)
    assert src["paused"] is False and src["rate"] == 1.0
    assert 0.0 <= src["position_s"] <= DURATION_S
    assert set(s["rates_hz"]) == {"tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"}
    assert s["recording"]["available"] and not s["recording"]["active"]
    # measured rates (how high depends on the machine): every sensor's, in the recording's
    # proportions (colour 30 Hz, TOF 15 Hz: the replay delivers every frame, late or not)
    s = console.wait(lambda s: all(r > 0 for r in s["rates_hz"].values()) and s["fps"] > 0)
    assert s["rates_hz"]["ccd_left"] > s["rates_hz"]["tof"]


def test_pause_holds_the_position_and_seek_moves_it(console) -> None:
    console.wait(lambda s: s["source"]["position_s"] > 0.3)
    r = console.client.post("/api/source/pause")
    assert r.status_code == 200 and r.json()["paused"] is True
    held = console.status()["source"]["position_s"]  # the replay stops at once
    # nothing fused while paused: the stream's rate falls to 0 once its window has passed
    s = console.wait(lambda s: s["fps"] == 0.0)
    assert s["source"]["position_s"] == held and s["source"]["paused"]

    r = console.client.post("/api/source/seek", json={"position_s": 2.0})
    assert r.status_code == 200 and r.json()["position_s"] == pytest.approx(2.0)
    assert console.status()["source"]["position_s"] == pytest.approx(2.0)
    r = console.client.post("/api/source/resume")
    assert r.status_code == 200 and r.json()["paused"] is False
    s = console.wait(lambda s: s["source"]["position_s"] > 2.05 or s["source"]["position_s"] < 1)
    assert s["source"]["position_s"] > 2.0  # went on from the seek target

    r = console.client.post("/api/source/seek", json={"position_s": DURATION_S + 5})
    assert r.status_code == 422 and "position_s" in r.text and "0..2.9" in r.text
    r = console.client.post("/api/source/seek", json={"position_s": -1})
    assert r.status_code == 422 and "position_s" in r.text
    r = console.client.post("/api/source/seek", json={"where": 1.0})
    assert r.status_code == 422


@pytest.mark.parametrize("body", ['{"rate": 0}', '{"rate": NaN}', '{"rate": 5}', '{"rate": "x"}'])
def test_rate_is_validated(console, body) -> None:
    r = console.client.put(
        "/api/source/rate", content=body, headers={"content-type": "application/json"}
    )
    assert r.status_code == 422 and "rate" in r.text
    assert console.replay.rate == 1.0


def test_rate_changes_the_replay_speed(console) -> None:
    r = console.client.put("/api/source/rate", json={"rate": 2.0})
    assert r.status_code == 200 and r.json()["rate"] == 2.0
    assert console.replay.rate == 2.0
    # the pacing at a rate: tests/app/recording/test_recording.py (a simulated clock)
    s = console.status()
    assert s["source"]["rate"] == 2.0


def test_replay_controls_on_a_live_source_say_why_not(rig) -> None:
    pipeline = FusionPipeline(SourceTap(ListSource()), rig, FrameHub())
    client = TestClient(create_app(FrameHub(), None, pipeline))
    for method, url, body in [
        ("post", "/api/source/pause", None),
        ("post", "/api/source/resume", None),
        ("post", "/api/source/seek", {"position_s": 1.0}),
        ("put", "/api/source/rate", {"rate": 1.0}),
    ]:
        r = getattr(client, method)(url, json=body)
        assert r.status_code == 409, (url, r.text)
        assert "not a replay" in r.json()["detail"], r.text
    s = client.get("/api/status").json()
    assert s["source"]["kind"] == "live" and s["source"]["position_s"] is None
    # without a work directory there is nothing to record into
    assert s["recording"]["available"] is False
    r = client.post("/api/recording/start")
    assert r.status_code == 409 and "work directory" in r.json()["detail"]


def test_recording_from_the_console_reads_back(console, recording) -> None:
    _, originals = recording
    by_key = {(f.sensor, f.stamp_ns): f for f in originals}
    console.wait(lambda s: s["frames_out"] > 3)
    r = console.client.post("/api/recording/start")
    assert r.status_code == 200, r.text
    assert r.json()["active"] and r.json()["path"].endswith(".mcap")
    r = console.client.post("/api/recording/start")
    assert r.status_code == 409 and "already recording" in r.json()["detail"]
    s = console.wait(lambda s: s["recording"]["frames_written"] > 60)
    assert s["recording"]["active"] and s["recording"]["size_bytes"] > 0
    r = console.client.post("/api/recording/stop")
    assert r.status_code == 200, r.text
    first = r.json()
    # (a disk too slow for the stream drops frames, counted: tests/app/server/test_source_panel.py)
    assert not first["active"] and first["error"] is None and first["frames_dropped"] >= 0
    assert console.client.post("/api/recording/stop").status_code == 409

    files = [Path(f) for f in first["files"]]
    assert files and all(f.parent == console.workdir / "recordings" for f in files)
    got: list[Frame] = []
    for f in files:
        with ReplaySource(f, realtime=False) as src:
            got += list(src.frames())
    assert len(got) == first["frames_written"]
    for frame in got:  # the very frames the console received, losslessly where possible
        assert_same_frame(frame, by_key[(frame.sensor, frame.stamp_ns)])
    assert {f.sensor for f in got} == {
        "tof",
        "ccd_left",
        "ccd_right",
        "thermal_left",
        "thermal_right",
    }
    recorded = sorted(p for p in (console.workdir / "recordings").iterdir())
    assert recorded == sorted(files)  # no temporary or reservation files left behind

    before = {f: f.read_bytes() for f in files}
    r = console.client.post("/api/recording/start")
    assert r.status_code == 200
    console.wait(lambda s: s["recording"]["frames_written"] > 10)
    second = console.client.post("/api/recording/stop").json()
    assert second["files"] and not set(second["files"]) & set(first["files"])
    for f, data in before.items():
        assert f.read_bytes() == data  # the first recording is untouched
    assert len(list((console.workdir / "recordings").glob("*.mcap"))) == len(files) + len(
        second["files"]
    )
    assert console.status()["recording"]["files"] == second["files"]


def test_a_recording_keeps_the_measurement_settings_and_the_alarm_events(console) -> None:
    """Issue 35: while the console records, the settings in force (at the start and at each
    change) and every alarm event go into the recording as ``foxglove.Log`` notes on
    /trifuse/measurements, at the pictures' times."""
    from trifuse.app.recording.notes import read_notes

    console.wait(lambda s: s["frames_out"] > 3)
    w, h = console.pipeline.fusion.size
    region = {"name": "all", "shape": "box", "points": [[0, 0], [w - 1, h - 1]]}
    assert console.client.put("/api/regions", json=[region]).status_code == 200
    assert console.client.post("/api/recording/start").status_code == 200
    alarm = [{"region": "all", "kind": "above", "threshold": 100.0}]  # any reading: raised
    assert console.client.put("/api/alarms", json=alarm).status_code == 200
    console.wait(lambda s: s["measurements"]["active_alarms"] == ["all above 100"])
    console.wait(lambda s: s["recording"]["frames_written"] > 30)
    files = console.client.post("/api/recording/stop").json()["files"]
    notes = [n for f in files for n in read_notes(f)]
    settings = [n for n in notes if n.name == "trifuse.measurement_settings"]
    alarms = [n for n in notes if n.name == "trifuse.alarm"]
    assert [len(n.body["alarms"]) for n in settings] == [0, 1]  # at the start; the alarm set
    assert settings[0].body["regions"][0]["name"] == "all"
    assert [(n.level, n.body["state"], n.body["region"]) for n in alarms] == [
        ("warning", "raised", "all")
    ]
    assert alarms[0].body["value"] > 100.0
    stamps = [n.stamp_ns for n in notes]
    assert stamps == sorted(stamps) and stamps[0] > 0  # on the recording's timeline
