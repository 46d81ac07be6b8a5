"""Property-based tests of every API route (issue 8).

Every route of the app's OpenAPI schema (so new routes are covered without touching this
file) gets random JSON values, mutated valid bodies, non-JSON bodies, wrong content types,
random path parameters and random query strings. Whatever arrives: never a 5xx; a 4xx
carries a JSON ``detail`` and changes nothing (settings, replay, recording, views, saved
rigs, files); nothing is created outside the session's work directory, and no temporary
file is left in it. Also the request body limit (app/server/middleware/limits.py).
"""

from __future__ import annotations

import asyncio
import copy
import json
import os
import socket
import string
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, urlencode

import pytest
from fastapi import FastAPI
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.control import currently_in_test_context

from tests.support import serve, small_rig, synth_frames, write_recording
from trifuse.app.recording import ReplaySource
from trifuse.app.server.app_factory import create_app
from trifuse.app.server.middleware.limits import (
    DEFAULT_MAX_BODY_BYTES,
    BodyLimitMiddleware,
    add_body_limit,
    require_json,
)
from trifuse.app.server.routers.drift_api import make_drift_router
from trifuse.app.server.routers.session_api import make_session_router
from trifuse.app.server.runtime.drift_watch import DriftWatch
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.runtime.thermal_balance import ThermalBalancer
from trifuse.app.sources.frames import FrameSet
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD
from trifuse.app.workflows.calib_session import CalibrationSession
from trifuse.fusion.compose import DisplaySettings

MAX_BODY = DEFAULT_MAX_BODY_BYTES
FUZZ = settings(
    derandomize=True,
    deadline=None,
    database=None,
    max_examples=400,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
# Routes not to call with their own method: an endless multipart stream.
ENDLESS = {("GET", "/stream.mjpg")}
METHODS = ("GET", "POST", "PUT", "DELETE", "PATCH", "OPTIONS")
JSON = {"content-type": "application/json"}


# -- the console under test ----------------------------------------------------------------


@dataclass(frozen=True)
class Route:
    method: str
    path: str  # with {name} placeholders
    path_params: tuple[str, ...]
    has_body: bool
    fields: frozenset[str] = frozenset()  # the body's keys
    closed: bool = False  # the body schema forbids other keys

    def url(self, params: dict[str, str] | None = None) -> str:
        url = self.path
        for k, v in (params or {}).items():
            url = url.replace("{" + k + "}", v)
        return url

    def __str__(self) -> str:
        return f"{self.method} {self.path}"


def routes_of(app: FastAPI) -> list[Route]:
    """Every operation of the app's OpenAPI schema."""
    spec = app.openapi()
    schemas = spec.get("components", {}).get("schemas", {})
    out = []
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            params = tuple(p["name"] for p in op.get("parameters", []) if p["in"] == "path")
            body = op.get("requestBody")
            fields, closed = frozenset(), False
            if body is not None:
                refs = list(_refs(body))
                assert len(refs) == 1, f"{method} {path}: expected one body model, got {refs}"
                model = schemas[refs[0].rsplit("/", 1)[-1]]
                fields = frozenset(model.get("properties", {}))
                closed = model.get("additionalProperties") is False
            out.append(Route(method.upper(), path, params, body is not None, fields, closed))
    return out


def _refs(schema: object) -> Iterator[str]:
    if isinstance(schema, dict):
        for k, v in schema.items():
            if k == "$ref":
                yield v
            else:
                yield from _refs(v)
    elif isinstance(schema, list):
        for v in schema:
            yield from _refs(v)


def tree(root: Path, skip: str | None = None) -> dict[str, int | None]:
    """Every file and folder under ``root`` (relative path -> size; None for folders and
    for a recording being written), leaving out the top-level folder ``skip``."""
    out: dict[str, int | None] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        rel = Path(dirpath).relative_to(root)
        if skip is not None and rel == Path("."):
            dirnames[:] = [d for d in dirnames if d != skip]
            filenames = [f for f in filenames if f != skip]
        for d in dirnames:
            out[(rel / d).as_posix()] = None
        for f in filenames:
            p = rel / f
            growing = f.startswith(".") and p.parent.name == "recordings"
            out[p.as_posix()] = None if growing else (root / p).stat().st_size
    return out


class Console:
    """The console's app (all routers) over a replay of a short recording, with a
    calibration session holding a view (``0001``) and a saved rig (``rig-0001``). The
    pipeline does not run: the routes are under test, not the fusion."""

    def __init__(self, root: Path) -> None:
        self.root = root
        rig = small_rig()
        frames = synth_frames(rig, 1.0, seed=3)
        recording = write_recording(root / "input" / "short.mcap", rig, frames)
        (root / "outside").mkdir()
        (root / "outside" / "secret.txt").write_text("not to be touched\n")
        self.work = root / "work"
        self.replay = ReplaySource(recording, loop=True, realtime=True)
        self.hub = FrameHub()
        self.pipeline = FusionPipeline(SourceTap(self.replay), rig, self.hub)
        self.control = SourceControl(self.pipeline, self.hub, "replay of short.mcap", self.work)
        self.balancer = ThermalBalancer(self.pipeline)
        self.session = CalibrationSession(self.work, rig, CALIBRATION_BOARD)
        newest: dict = {}
        for f in frames:
            newest[f.sensor] = f
        self.frameset = FrameSet(max(f.stamp_ns for f in newest.values()), newest)
        self.session.take(self.frameset)
        self.session.save_rig(rig, {})
        self._fuse_once(newest)
        drift = DriftWatch(self.pipeline)  # not started: nothing checked, refine answers 409
        app = create_app(self.hub, None, self.pipeline, self.control, self.balancer, drift=drift)
        app.include_router(make_drift_router(drift, self.session.save_rig, self.pipeline.set_rig))
        app.include_router(
            make_session_router(
                self.session,
                lambda: self.frameset,
                self.pipeline.set_rig,
                lambda: self.pipeline.rig,
                self.pipeline.rig_with_radiometry,
            )
        )
        self.app = app  # create_app limits bodies to MAX_BODY
        self.client = TestClient(app, raise_server_exceptions=False)
        self.fusion = self.client.get("/api/fusion").json()  # a valid PUT /api/fusion body
        self.routes = routes_of(app)
        self.outside = tree(root, skip="work")
        self.field_names = sorted(
            {
                name
                for schema in app.openapi()["components"]["schemas"].values()
                for name in schema.get("properties", {})
            }
        )

    def _fuse_once(self, newest: dict) -> None:
        """One fused picture for the spot meter's routes (/api/spot, /api/area), which
        answer 503 without one: fused here, since the pipeline does not run."""
        fusion, eyes = self.pipeline.fusion, self.pipeline.rig.eyes
        fusion.update_depth(newest["tof"].distance_m, newest["tof"].image)
        colors = {e: newest[eyes[e].color].image for e in fusion.eyes}
        thermals = {e: newest[eyes[e].thermal].image for e in fusion.eyes}
        fusion.compose(colors, thermals, DisplaySettings())
        self.pipeline.spots = self.pipeline.spot_meter.capture(self.frameset.stamp_ns)

    def valid_body(self, route: Route) -> object:
        """A body the route accepts (mutated by the tests; always the same, as hypothesis
        needs)."""
        key = (route.method, route.path)
        if key == ("PUT", "/api/fusion"):
            return copy.deepcopy(self.fusion)
        if key == ("PUT", "/api/thermal"):
            imagers = sorted(self.pipeline.radiometry)
            return {
                "span_k": [290.0, 320.0],
                "span_smoothing_s": 2.0,
                "offset_k": dict.fromkeys(imagers, 0.25),
                "auto_balance": False,
                "balance_reference": imagers[0],
            }
        if key == ("POST", "/api/source/seek"):
            return {"position_s": 0.5}
        if key == ("PUT", "/api/source/rate"):
            return {"rate": 1.5}
        if key == ("POST", "/api/range"):
            return {"holdout_every": 4}
        if key == ("PUT", "/api/stream/settings"):
            return {"preset": "4"}
        if key == ("PUT", "/api/object-parameters"):
            return {"emissivity": 0.9, "reflected_k": 280.0, "air_k": 290.0, "humidity_pct": 70.0}
        if key == ("PUT", "/api/regions"):
            return [{"name": "a", "eye": "left", "shape": "box", "points": [[10, 10], [90, 60]]}]
        if key == ("PATCH", "/api/regions/{name}"):  # valid on region "a"
            return {"name": "b", "emissivity": 0.8, "reflected_k": 260.0}
        if key == ("PUT", "/api/alarms"):  # valid once region "a" is there
            return [{"region": "a", "kind": "above", "threshold": 320.0}]
        raise KeyError(f"{route} takes a body: add a valid one to Console.valid_body")

    def snapshot(self) -> dict:
        """What a request may change: the settings, replay, recording, session, files."""
        p = self.pipeline
        return {
            "settings": repr(p.settings),
            "stream_preset": self.hub.stream_settings.preset,
            "radiometry": repr({n: r.to_dict() for n, r in p.radiometry.items()}),
            "rig": id(p.rig),
            "balance": (self.balancer.auto, self.balancer.reference),
            "replay": (self.replay.paused, self.replay.rate, self.replay.position_ns),
            "recording": self.control.recorder.active,
            "views": [v.name for v in self.session.views()],
            "versions": [v.name for v in self.session.versions()],
            "files": tree(self.root),
            "measurements": (
                repr(p.measurements.params),
                p.measurements.regions,
                p.measurements.rules,
            ),
        }

    def check_files(self, what: str) -> None:
        """Nothing created or changed outside the work directory; no temporary files in
        it (but the recording being written)."""
        assert tree(self.root, skip="work") == self.outside, f"{what}: touched files outside"
        assert (self.root / "outside" / "secret.txt").read_text() == "not to be touched\n"
        recording = self.control.recorder.active
        for dirpath, dirnames, filenames in os.walk(self.work):
            for name in dirnames + filenames:
                if not name.startswith("."):
                    continue
                in_progress = recording and Path(dirpath).name == "recordings"
                assert in_progress and name.endswith((".reserved", ".partial")), (
                    f"{what}: stray temporary file {Path(dirpath) / name}"
                )

    def send(
        self,
        method: str,
        url: str,
        content: bytes | None = None,
        headers: dict[str, str] | None = None,
    ):
        """One request, checked: no 5xx; a 4xx has a JSON detail and changed nothing."""
        what = f"{method} {url[:300]} headers={headers} body={(content or b'')[:300]!r}"
        before = self.snapshot()
        r = self.client.request(method, url, content=content, headers=headers)
        if currently_in_test_context():
            event(f"{r.status_code // 100}xx")  # shown by --hypothesis-show-statistics
        assert r.status_code < 500, f"{what} -> {r.status_code} {r.text[:500]}"
        if r.status_code >= 400:
            assert r.headers.get("content-type", "").startswith("application/json"), (
                f"{what} -> {r.status_code} {r.headers.get('content-type')} {r.text[:200]}"
            )
            detail = r.json().get("detail")
            assert detail, f"{what} -> {r.status_code} without a detail: {r.text[:200]}"
            assert self.snapshot() == before, f"{what} -> {r.status_code}, but changed state"
        elif r.headers.get("content-type", "").startswith("application/json"):
            r.json()  # a success answers valid JSON
        self.check_files(what)
        return r

    def close(self) -> None:
        self.session.wait(30)
        self.control.stop()
        self.session.close()
        self.replay.close()


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    root = tmp_path_factory.mktemp("fuzz")
    cwd = root / "cwd"  # a route writing relative to the working directory would show here
    cwd.mkdir()
    old = os.getcwd()
    os.chdir(cwd)
    c = Console(root)
    try:
        yield c
    finally:
        os.chdir(old)
        c.close()


# -- strategies ----------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")
EDGE_VALUES = [
    None,
    True,
    False,
    0,
    -1,
    1,
    0.5,
    -0.0,
    1e308,
    -1e308,
    5e-324,
    2**53 + 1,
    2**63,
    -(2**63) - 1,
    NAN,
    INF,
    -INF,
    "",
    "0",
    "1.0",
    "nan",
    "thermal_left",
    "rig-0001",
    "\u00e9\u2603\U0001f525",
    "\ud800",  # a lone surrogate: json.dumps writes it as an escape
    "a\udfffb",
    [],
    {},
    [1.0],
    [1.0, 2.0, 3.0],
    [320.0, 290.0],
    [290.0, 320.0],
    [NAN, 300.0],
    {"thermal_left": 1.0},
]
# Bodies that are not (plain) JSON values: truncated, deep, huge numbers, odd bytes.
RAW_BODIES = [
    b"",
    b" ",
    b"null",
    b"NaN",
    b"-Infinity",
    b'{"a":',
    b'{"a":1,"a":2}',
    b"\xef\xbb\xbf{}",
    b"1" + b"0" * 5000,
    b'{"holdout_every": 1' + b"0" * 5000 + b"}",
    b"1e999999",
    b"[" * 50_000,
    b'{"x":' * 3000 + b"1" + b"}" * 3000,
    b'"\\ud800"',
    b'{"mode": "\\udfff", "span_k": "\\ud83d"}',
    b'{"\\ud800": 1}',
    b"\xff\xfe\x00\x01",
    b"\x00" * 64,
    b"a=1&b=2",
    b"<xml/>",
]
CONTENT_TYPES = [
    None,
    "application/json",
    "application/json; charset=latin-1",
    "application/problem+json",
    "text/plain",
    "text/json",
    "application/x-www-form-urlencoded",
    "multipart/form-data",
    "multipart/form-data; boundary=xyz",
    "application/octet-stream",
    "application/xml",
    "",
    "garbage",
    ";;;",
]
# Path parameters: traversal, encodings, NUL, long and unicode names, near-valid names.
NASTY_NAMES = [
    "..",
    "%2E%2E",
    "%2e%2e%2f%2e%2e%2fetc%2fpasswd",
    "..%2F..%2Fetc%2Fpasswd",
    "..%2F..%2Foutside%2Fsecret.txt",
    "..%2Foutside",
    "%2E%2E%2Frigs%2Frig-0001",
    "%00",
    "rig-0001%00",
    "%ZZ",
    "%C0%AE%C0%AE",
    "%FF",
    "~",
    ".",
    "%2E",
]
NAMES = [
    "..",
    "../../etc/passwd",
    "..\\..\\outside",
    "\x00",
    "rig-0001\x00.yaml",
    "0001",
    "rig-0001",
    "rig-9999",
    "9999",
    "rig-0001.yaml",
    "rig-" + "0" * 300 + "1",
    "0" * 300 + "1",
    "x" * 5000,
    "rig-\u0661\u0662\u0663\u0664",  # Arabic-Indic digits: \d, not a version name
    "\u0661\u0662\u0663\u0664",
    "\u00e9t\u00e9",
    "\U0001f525",
    " 0001",
    "0001\n",
    "rig-0001/use",
]


def huge_int(digits: int, negative: bool) -> int:
    return (-1 if negative else 1) * 10 ** (digits - 1) + 7


def long_text(n: int) -> str:
    return "x" * n


def json_values(keys: list[str]) -> st.SearchStrategy:
    """Any JSON value: null, booleans, numbers (huge ints, NaN, Infinity), strings, nested
    lists and objects whose keys are often the API's field names."""
    scalars = st.one_of(
        st.none(),
        st.booleans(),
        st.integers(),
        st.builds(huge_int, st.integers(19, 400), st.booleans()),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(max_size=20),
        st.integers(100, 5000).map(long_text),
        st.sampled_from(EDGE_VALUES),
    )
    key = st.one_of(st.sampled_from(keys), st.text(max_size=12))
    return st.recursive(
        scalars,
        lambda inner: st.one_of(
            st.lists(inner, max_size=4), st.dictionaries(key, inner, max_size=5)
        ),
        max_leaves=12,
    )


def _locations(value: object, at: tuple = ()) -> Iterator[tuple]:
    yield at
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _locations(v, (*at, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _locations(v, (*at, i))


def _at(value: object, where: tuple) -> object:
    for k in where:
        value = value[k]  # type: ignore[index]
    return value


@st.composite
def mutated(draw: st.DrawFn, valid: object, keys: list[str]) -> object:
    """``valid`` with 1-3 random changes: a value replaced (by any JSON value or an edge
    case), a key or element deleted, a key or element added, the whole body wrapped."""
    body = copy.deepcopy(valid)
    values = json_values(keys).map(copy.deepcopy)  # never change a value hypothesis keeps
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from(list(_locations(body))))
        target = _at(body, where)
        ops = ["replace", "edge"] + (["delete"] if where else ["wrap"])
        if isinstance(target, dict | list):
            ops.append("add")
        op = draw(st.sampled_from(ops))
        if op == "wrap":
            body = draw(st.sampled_from([[body], {"body": body}, json.dumps(body)]))
        elif op == "add":
            if isinstance(target, dict):
                target[draw(st.one_of(st.sampled_from(keys), st.text(max_size=8)))] = draw(values)
            else:
                target.insert(draw(st.integers(0, len(target))), draw(values))  # type: ignore[union-attr]
        else:
            new = draw(values if op == "replace" else st.sampled_from(EDGE_VALUES))
            new = copy.deepcopy(new)
            if not where:
                body = new
            elif op == "delete":
                del _at(body, where[:-1])[where[-1]]  # type: ignore[attr-defined]
            else:
                _at(body, where[:-1])[where[-1]] = new  # type: ignore[index]
    return body


def dumps(value: object) -> bytes:
    """JSON text as a careless client writes it: NaN and Infinity as bare words."""
    return json.dumps(value, allow_nan=True).encode()


def path_names() -> st.SearchStrategy[str]:
    """A path parameter, already in URL form."""
    return st.one_of(
        st.sampled_from(NASTY_NAMES),  # sent as written (percent escapes included)
        st.sampled_from(NAMES).map(lambda s: quote(s, safe="")),
        st.sampled_from(NAMES).map(lambda s: quote(s, safe="").replace(".", "%2E")),
        st.text(min_size=1, max_size=40).map(lambda s: quote(s, safe="")),
        st.text(string.digits, min_size=4, max_size=6),
        st.text(string.digits, min_size=4, max_size=6).map(lambda s: "rig-" + s),
    )


def query_strings() -> st.SearchStrategy[str]:
    pairs = st.lists(
        st.tuples(
            st.one_of(st.text(max_size=10), st.sampled_from(["name", "position_s", "rate"])),
            st.one_of(st.text(max_size=20), st.sampled_from(["1", "NaN", "-1", "1e999", ".."])),
        ),
        max_size=4,
    )
    raw = st.sampled_from(
        ["", "&&", "=", "a", "a=1&a=2", "%ZZ", "%00=%00", "x=" + "y" * 5000, "%FF%FE", "?"]
    )
    return st.one_of(pairs.map(urlencode), raw)


# Names that exist, or will: views and versions are numbered from 1 as they are made.
SESSION_NAMES = [f"{k:04d}" for k in range(1, 41)] + [f"rig-{k:04d}" for k in range(1, 41)]


def fill(route: Route, draw: st.DrawFn) -> str:
    """The route's URL with its path parameters: mostly names of the session's views and
    versions, else random ones (the same draws whatever the app's state: hypothesis
    replays them)."""
    names = st.one_of(st.sampled_from(SESSION_NAMES), path_names())
    return route.url({p: draw(names) for p in route.path_params})


def callable_routes(console: Console) -> list[Route]:
    return [r for r in console.routes if (r.method, r.path) not in ENDLESS]


# -- the properties ------------------------------------------------------------------------


def test_routes_are_enumerated_and_every_body_route_has_a_valid_body(console) -> None:
    paths = {r.path for r in console.routes}
    for expected in ("/api/fusion", "/api/status", "/api/captures/{name}", "/api/rigs/{name}"):
        assert expected in paths  # all routers are in the app under test
    for route in console.routes:
        if route.has_body:
            console.valid_body(route)  # KeyError: a new body route needs a valid body here
            assert route.closed, f"{route}: the body model must forbid unknown keys"
    for r in console.app.routes:
        if isinstance(r, APIRoute) and r.body_field is not None:
            calls = [d.call for d in r.dependant.dependencies]
            assert require_json in calls, f"{r.path}: add dependencies=[Depends(require_json)]"


@FUZZ
@given(data=st.data())
@pytest.mark.slow  # hundreds of fuzzed requests through the whole app: about 10 s
def test_random_json_bodies(console, data) -> None:
    route = data.draw(st.sampled_from(callable_routes(console)), label="route")
    value = data.draw(json_values(console.field_names), label="body")
    url = fill(route, data.draw)
    console.send(route.method, url, dumps(value), {"content-type": "application/json"})


@FUZZ
@given(data=st.data())
@pytest.mark.slow  # hundreds of fuzzed requests through the whole app: about 8 s
def test_mutated_valid_bodies(console, data) -> None:
    body_routes = [r for r in console.routes if r.has_body]
    route = data.draw(st.sampled_from(body_routes), label="route")
    valid = console.valid_body(route)
    body = data.draw(mutated(valid, console.field_names), label="body")
    r = console.send(route.method, route.url(), dumps(body), JSON)
    if isinstance(body, dict) and set(body) - route.fields:
        assert r.status_code == 422, f"{route} took unknown keys {set(body) - route.fields}"


@FUZZ
@given(data=st.data())
@pytest.mark.slow  # hundreds of fuzzed requests through the whole app: about 8 s
def test_non_json_bodies_and_content_types(console, data) -> None:
    route = data.draw(st.sampled_from(callable_routes(console)), label="route")
    body = data.draw(
        st.one_of(
            st.sampled_from(RAW_BODIES),
            st.binary(max_size=200),
            st.text(max_size=100).map(lambda s: s.encode("utf-8", "surrogatepass")),
            st.just(dumps(console.valid_body(route)) if route.has_body else b"{}"),
        ),
        label="body",
    )
    ctype = data.draw(st.sampled_from(CONTENT_TYPES), label="content-type")
    url = fill(route, data.draw)
    r = console.send(route.method, url, body, {} if ctype is None else {"content-type": ctype})
    if route.has_body and body and r.status_code < 300:
        assert ctype is not None and "json" in ctype, f"{route} took a {ctype!r} body"


@FUZZ
@given(data=st.data())
@pytest.mark.slow  # hundreds of fuzzed requests through the whole app: about 10 s
def test_random_path_parameters(console, data) -> None:
    routes = [r for r in callable_routes(console) if r.path_params]
    route = data.draw(st.sampled_from(routes), label="route")
    some = st.one_of(path_names(), st.sampled_from(SESSION_NAMES))
    names = {p: data.draw(some, label=p) for p in route.path_params}
    existing = {v.name for v in console.session.views()} | {
        v.name for v in console.session.versions()
    }
    r = console.send(route.method, route.url(names))
    answer = r.json() if r.status_code < 300 else None
    if isinstance(answer, dict):  # only ever a view or a version of the session itself
        named = answer.get("deleted") or answer.get("in_use")
        assert named is None or named in existing, (route, names, answer)


@FUZZ
@given(data=st.data())
@pytest.mark.slow  # hundreds of fuzzed requests through the whole app: about 10 s
def test_random_methods_and_query_strings(console, data) -> None:
    route = data.draw(st.sampled_from(callable_routes(console)), label="route")
    method = data.draw(st.sampled_from([route.method, *METHODS]), label="method")
    if (method, route.path) in ENDLESS:
        method = "DELETE"
    query = data.draw(query_strings(), label="query")
    url = fill(route, data.draw)
    body = dumps(console.valid_body(route)) if route.has_body and method == route.method else None
    headers = {"content-type": "application/json"} if body else None
    r = console.send(method, f"{url}?{query}" if query else url, body, headers)
    allowed = {x.method for x in console.routes if x.path == route.path}
    if method not in allowed and not route.path_params:  # ("/x/.." is another path)
        assert r.status_code == 405, (method, url, r.status_code)


def test_the_console_still_works_after_the_fuzzing(console) -> None:
    """Whatever was accepted, every plain GET still answers, and nothing stray remains
    once the recording (if one was started) is stopped."""
    if console.control.recorder.active:
        assert console.send("POST", "/api/recording/stop").status_code == 200
    for route in callable_routes(console):
        if route.method == "GET" and not route.path_params:
            r = console.send("GET", route.path)
            assert r.status_code in (200, 404), (route, r.status_code, r.text[:300])
    console.session.wait(30)
    console.check_files("after the fuzzing")
    assert console.pipeline.status.error is None


# -- regressions found by the fuzzing ------------------------------------------------------


@pytest.mark.parametrize(
    ("method", "url", "body", "ctype", "status"),
    [
        # a version name longer than a file name may be: OSError ENAMETOOLONG (500)
        ("GET", "/api/rigs/rig-" + "0" * 300 + "1", None, None, 404),
        ("POST", "/api/rigs/rig-" + "0" * 300 + "1/use", None, None, 404),
        ("GET", "/api/rigs/%2E%2E", None, None, 404),
        ("DELETE", "/api/captures/..%2F..%2Foutside", None, None, 404),
        ("DELETE", "/api/captures/%2E%2E", None, None, 404),
        # bytes that are no UTF-8, sent as text: FastAPI echoed them in its 422 (500)
        ("PUT", "/api/fusion", b"\xff\xfe", "text/plain", 415),
        ("POST", "/api/range", b"\xff", "application/octet-stream", 415),
        ("PUT", "/api/source/rate", b'{"rate": 2}', None, 415),
        # a lone surrogate echoed in the 422 could not be encoded (500)
        ("PUT", "/api/fusion", b'{"mode": "\\ud800"}', "application/json", 422),
        ("PUT", "/api/thermal", b'{"balance_reference": "\\udfff"}', "application/json", 422),
        # unknown keys were ignored (200): a misspelt span_k set the span to automatic
        ("PUT", "/api/thermal", b'{"span": [290, 320]}', "application/json", 422),
        ("POST", "/api/range", b'{"holdout": 4}', "application/json", 422),
    ],
)
def test_found_defects_get_4xx(console, method, url, body, ctype, status) -> None:
    r = console.send(method, url, body, {} if ctype is None else {"content-type": ctype})
    assert r.status_code == status, r.text


def test_a_misspelt_key_changes_nothing(console) -> None:
    assert console.send("PUT", "/api/thermal", b'{"span_k": [280, 330]}', JSON).is_success
    r = console.send("PUT", "/api/thermal", b'{"span": [290, 320]}', JSON)
    assert r.status_code == 422 and "span" in r.text
    assert console.pipeline.settings.span_k == (280.0, 330.0)


# -- the request body limit ----------------------------------------------------------------


def test_body_over_the_limit_is_refused_by_its_content_length(console) -> None:
    before = console.snapshot()
    body = b'{"rate": 2.0' + b" " * MAX_BODY + b"}"
    r = console.client.put(
        "/api/source/rate", content=body, headers={"content-type": "application/json"}
    )
    assert r.status_code == 413, r.text
    assert "too large" in r.json()["detail"] and "1 MiB" in r.json()["detail"]
    assert console.snapshot() == before
    # at the limit: the route decides
    body = b'{"rate": 2.0' + b" " * (MAX_BODY - 13) + b"}"
    assert len(body) == MAX_BODY
    r = console.client.put(
        "/api/source/rate", content=body, headers={"content-type": "application/json"}
    )
    assert r.status_code == 200 and r.json()["rate"] == 2.0
    console.client.put("/api/source/rate", json={"rate": 1.0})


def test_chunked_body_over_the_limit_is_refused_while_streaming(console) -> None:
    def chunks() -> Iterator[bytes]:  # no Content-Length: sent chunked
        yield b'{"position_s": 0.5, "pad": "'
        for _ in range(64):
            yield b"x" * (64 << 10)
        yield b'"}'

    before = console.snapshot()
    r = console.client.post(
        "/api/source/seek", content=chunks(), headers={"content-type": "application/json"}
    )
    assert r.status_code == 413, r.text
    assert "more than 1048576 bytes (1 MiB)" in r.json()["detail"]
    assert console.snapshot() == before


def test_streamed_body_is_cut_off_at_the_limit() -> None:
    """A plain ASGI app reading a chunked body: the middleware stops it after the chunk
    that passes the limit and answers 413 itself."""
    consumed = []

    async def app(scope, receive, send):
        while (await receive()).get("more_body"):
            pass
        raise AssertionError("the whole body was read")  # pragma: no cover

    async def receive():
        consumed.append(1)
        return {"type": "http.request", "body": b"x" * 1000, "more_body": True}

    out: list[dict] = []

    async def send(message):
        out.append(message)

    scope = {"type": "http", "method": "POST", "path": "/x", "headers": []}
    asyncio.run(BodyLimitMiddleware(app, 10_000)(scope, receive, send))
    assert len(consumed) == 11
    assert out[0]["status"] == 413 and b"more than 10000 bytes" in out[1]["body"]


def test_bad_content_length_is_refused() -> None:
    async def app(scope, receive, send):  # pragma: no cover - never reached
        raise AssertionError("the app must not be called")

    async def run(headers: list[tuple[bytes, bytes]]) -> tuple[int, dict]:
        out: list[dict] = []

        async def receive():
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(message):
            out.append(message)

        scope = {"type": "http", "method": "POST", "path": "/api/x", "headers": headers}
        await BodyLimitMiddleware(app, 100)(scope, receive, send)
        return out[0]["status"], json.loads(out[1]["body"])

    for headers in ([(b"content-length", b"-1")], [(b"content-length", b"1e3")]):
        status, body = asyncio.run(run(headers))
        assert status == 400 and "Content-Length" in body["detail"]
    two = [(b"content-length", b"5"), (b"content-length", b"6")]
    assert asyncio.run(run(two))[0] == 400
    assert asyncio.run(run([(b"content-length", b"101")]))[0] == 413
    with pytest.raises(ValueError, match="max_bytes"):
        BodyLimitMiddleware(app, -1)


def test_body_limit_leaves_websockets_alone() -> None:
    seen = []

    async def app(scope, receive, send):
        seen.append(scope["type"])

    asyncio.run(BodyLimitMiddleware(app, 0)({"type": "websocket"}, None, None))
    asyncio.run(BodyLimitMiddleware(app, 0)({"type": "lifespan"}, None, None))
    assert seen == ["websocket", "lifespan"]


def test_body_limit_on_a_real_server_chunked_and_declared() -> None:
    """uvicorn on 127.0.0.1: a chunked body is cut off with 413 once past the limit, a
    declared one at once; a small one passes."""
    app = FastAPI()

    @app.post("/echo")
    async def echo(body: dict) -> dict:
        return {"keys": sorted(body)}

    add_body_limit(app, 64 << 10)

    def request(head: bytes, chunks: list[bytes]) -> bytes:
        with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
            s.sendall(head)
            try:
                for c in chunks:
                    s.sendall(c)
            except OSError:  # the server may close once it has answered
                pass
            data = b""
            while not data.endswith(b"}") or b"\r\n\r\n" not in data:
                part = s.recv(65536)
                if not part:
                    break
                data += part
            return data

    chunk = b"%x\r\n%s\r\n" % (16 << 10, b" " * (16 << 10))
    with serve(app) as port:
        head = (
            b"POST /echo HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Transfer-Encoding: chunked\r\n\r\n"
        )
        answer = request(head, [b"1\r\n{\r\n", *[chunk] * 8, b"1\r\n}\r\n0\r\n\r\n"])
        assert answer.startswith(b"HTTP/1.1 413"), answer[:200]
        assert b"request body too large" in answer
        declared = (
            b"POST /echo HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 1000000\r\n\r\n"
        )
        answer = request(declared, [])
        assert answer.startswith(b"HTTP/1.1 413") and b"1000000 bytes" in answer
        small = b'{"a": 1}'
        ok = (
            b"POST /echo HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Connection: close\r\nContent-Length: %d\r\n\r\n%s" % (len(small), small)
        )
        answer = request(ok, [])
        assert answer.startswith(b"HTTP/1.1 200") and b'{"keys":["a"]}' in answer
