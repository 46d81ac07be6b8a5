"""The REST API: typed settings, validation with 422, the same state as the panels."""

from __future__ import annotations

import json
import re

import pytest
from fastapi.testclient import TestClient

from tests.support import ListSource
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.sim.head import default_rig


@pytest.fixture()
def client_and_pipeline():
    rig = default_rig()
    pipeline = FusionPipeline(ListSource(), rig, FrameHub())
    return TestClient(create_app(FrameHub(), None, pipeline)), pipeline


def test_fusion_settings_round_trip_and_validation(client_and_pipeline) -> None:
    client, pipeline = client_and_pipeline
    s = client.get("/api/fusion").json()
    assert s["mode"] == "blend"
    s.update(mode="isotherm", palette="lava", isotherm_k=[305.0, 312.0])
    assert client.put("/api/fusion", json=s).status_code == 200
    assert pipeline.settings.mode == "isotherm" and pipeline.settings.palette == "lava"
    bad = {**s, "opacity": 3.0}
    r = client.put("/api/fusion", json=bad)
    assert r.status_code == 422 and "opacity" in r.text
    assert pipeline.settings.opacity == pytest.approx(0.6)  # unchanged
    r = client.put("/api/fusion", json={**s, "isotherm_k": [312.0, 305.0]})
    assert r.status_code == 422 and pipeline.settings.isotherm_k == (305.0, 312.0)


def test_thermal_balance_and_rig(client_and_pipeline) -> None:
    client, pipeline = client_and_pipeline
    r = client.put(
        "/api/thermal", json={"span_k": [290.0, 320.0], "offset_k": {"thermal_left": -0.75}}
    )
    assert r.status_code == 200
    assert pipeline.settings.span_k == (290.0, 320.0)
    assert pipeline.radiometry["thermal_left"].manual_offset_k == -0.75
    assert r.json()["offset_k"]["thermal_left"] == -0.75
    assert r.json()["radiometry"]["thermal_left"]["balance_offset_k"] == 0.0
    r = client.put("/api/thermal", json={"offset_k": {"ccd_left": 1.0}})
    assert r.status_code == 422 and "ccd_left" in r.text
    rig = client.get("/api/rig").json()
    assert rig["format"] == "trifuse-rig/1" and rig["reference"] == "tof"
    assert "/api/fusion" in client.get("/openapi.json").json()["paths"]


def test_non_finite_numbers_get_422_not_500(client_and_pipeline) -> None:
    client, pipeline = client_and_pipeline
    s = client.get("/api/fusion").json()
    body = json.dumps({**s, "opacity": float("nan")})  # Python's json writes NaN
    r = client.put("/api/fusion", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422 and "opacity" in r.text
    assert pipeline.settings.opacity == pytest.approx(0.6)
    r = client.put(
        "/api/thermal",
        content='{"span_k": [Infinity, 300.0]}',
        headers={"content-type": "application/json"},
    )
    assert r.status_code == 422 and "span_k" in r.text and pipeline.settings.span_k is None


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"offset_k": {"thermal_left": 1e308}}, "offset_k"),  # overflowed a float32 cast
        ({"offset_k": {"thermal_left": -51.0}}, "offset_k"),  # a trim, not a calibration
        ({"span_k": [0.0, 1e-300]}, "span_k"),  # narrower than 0.01 K
        ({"span_k": [-5.0, 300.0]}, "span_k"),  # below absolute zero
        ({"span_k": [290.0, 2e4]}, "span_k"),
        ({"span_smoothing_s": 1e-320}, "span_smoothing_s"),  # 0 (none) or >= 0.01 s
        ({"span_k": [290.0, 320.0], "offset_k": {"thermal_right": 1e9}}, "offset_k"),
    ],
)
def test_absurd_thermal_settings_are_refused_and_change_nothing(
    client_and_pipeline, body, field
) -> None:
    client, pipeline = client_and_pipeline
    before = (pipeline.settings, dict(pipeline.radiometry))
    r = client.put("/api/thermal", json=body)
    assert r.status_code == 422 and field in r.text, r.text
    assert (pipeline.settings, dict(pipeline.radiometry)) == before
    ok = client.put("/api/thermal", json={"span_k": [290.0, 290.01], "span_smoothing_s": 0.01})
    assert ok.status_code == 200  # the limits themselves are allowed


@pytest.mark.parametrize("path", ["/docs", "/redoc"])
def test_docs_pages_use_only_this_servers_scripts(client_and_pipeline, path) -> None:
    client, _ = client_and_pipeline
    r = client.get(path)
    assert r.status_code == 200
    assert "script-src 'self'" in r.headers["content-security-policy"]
    scripts = re.findall(r"<script([^>]*)>(.*?)</script>", r.text, re.S)
    assert scripts and all(body.strip() == "" for _, body in scripts)  # no inline script
    assert "http" not in r.text  # no CDN
    for src in re.findall(r'(?:src|href)="([^"]+)"', r.text):
        if src != "/openapi.json":
            assert client.get(src).status_code == 200, src
