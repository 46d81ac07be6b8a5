"""The calibration report as one HTML page (app.workflows.report_html): from a real
one-sensor calibration (OpenCV's 9x6 left samples, ``trifuse calibrate --report-html``)
and a five-sensor one with outliers, a sensor left out and the ground truth; its numbers
against report.json and the truth, self-containment, well-formed HTML, the console's
download and route sending the same page, and headless Chromium opening it without a
single request."""

from __future__ import annotations

import json
import re
import shutil
import time
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from tests.browser_support import needs_chromium
from tests.support import OPENCV_LEFT_9X6
from trifuse.app.cli import main
from trifuse.app.server.routers.session_api import make_session_router
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.scenarios import CALIBRATION_BOARD, calibration_poses
from trifuse.app.workflows.calib_session import CalibrationJob, CalibrationSession
from trifuse.app.workflows.calibration_run import DetectionRun, build_report
from trifuse.app.workflows.report_html import (
    CSP,
    REPORT_HTML_NAME,
    render_report_html,
    session_report_html,
)
from trifuse.app.workflows.report_markup import pm
from trifuse.calib.rig_calibration import CalibrationOptions, SensorSpec, calibrate_rig
from trifuse.calib.rig_compare import compare_rigs
from trifuse.calib.transforms import transform_points

BOARD_9x6 = "pattern: checkerboard\ninner_corners: [9, 6]\nsquare_size_m: 0.025\n"
VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source"}


class Page(HTMLParser):
    """A page read back: tags balanced (``errors`` otherwise), ids, URLs in attributes,
    every table as rows of cell texts (by the table's id when it has one), all text."""

    def __init__(self, text: str) -> None:
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.ids: list[str] = []
        self.urls: list[str] = []
        self.tables: list[tuple[str | None, list[list[str]]]] = []
        self._cell: list[str] | None = None
        self._open_tables: list[tuple[str | None, list[list[str]]]] = []
        self.text: list[str] = []
        self.feed(text)
        self.close()
        if self.stack:
            self.errors.append(f"never closed: {self.stack}")

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if "id" in a:
            self.ids.append(str(a["id"]))
        self.urls += [str(v) for k, v in attrs if k in ("href", "src", "action", "xlink:href")]
        if tag == "table":
            self._open_tables.append((a.get("id"), []))
        elif tag == "tr" and self._open_tables:
            self._open_tables[-1][1].append([])
        elif tag in ("td", "th"):
            self._cell = []
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.urls += [str(v) for k, v in attrs if k in ("href", "src")]

    def handle_endtag(self, tag: str) -> None:
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:]}")
            return
        self.stack.pop()
        if tag in ("td", "th") and self._cell is not None and self._open_tables:
            self._open_tables[-1][1][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None
        elif tag == "table":
            self.tables.append(self._open_tables.pop())

    def handle_data(self, data: str) -> None:
        self.text.append(data)
        if self._cell is not None:
            self._cell.append(data)

    def table(self, table_id: str) -> list[list[str]]:
        return next(rows for i, rows in self.tables if i == table_id)

    def rows_starting(self, first: str) -> list[list[str]]:
        return [r for _, rows in self.tables for r in rows if r and r[0] == first]


def value_sigma(cell: str) -> tuple[float, float, int]:
    """``'533.18 ± 0.57'`` -> (533.18, 0.57, decimals 2)."""
    value, sigma = cell.split("±")
    return float(value), float(sigma), len(value.strip().split(".")[1])


def assert_self_contained(page: str) -> None:
    """Nothing that a browser would fetch: no script, stylesheet link, import or url();
    the only ``http`` is the SVG namespace."""
    assert "<script" not in page.lower() and "<link" not in page.lower()
    assert "@import" not in page and "url(" not in page
    assert set(re.findall(r"https?://[^\s\"'<>]*", page)) <= {"http://www.w3.org/2000/svg"}
    assert f'content="{CSP}"' in page


def assert_well_formed(p: Page) -> None:
    assert not p.errors, p.errors[:5]
    assert len(p.ids) == len(set(p.ids)), "duplicate ids"
    assert all(u.startswith("#") and u[1:] in p.ids for u in p.urls), p.urls


# -- a real one-sensor calibration: OpenCV's left samples ---------------------------------


@pytest.fixture(scope="module")
def real(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """``trifuse calibrate`` of OpenCV's 13 left images with --report and --report-html."""
    root = tmp_path_factory.mktemp("real")
    cap = root / "capture"
    cap.mkdir()
    (cap / "board.yaml").write_text(BOARD_9x6)
    for f in sorted(OPENCV_LEFT_9X6.glob("left*.jpg")):
        (cap / f.stem).mkdir()
        shutil.copy(f, cap / f.stem / "ccd_left.jpg")
    paths = {k: root / n for k, n in (("rig", "rig.yaml"), ("json", "r.json"), ("html", "r.html"))}
    argv = ["calibrate", str(cap), "--out", str(paths["rig"]), "--report", str(paths["json"])]
    assert main([*argv, "--report-html", str(paths["html"])]) == 0
    page = paths["html"].read_text(encoding="utf-8")
    return {
        "capture": cap,
        "argv": argv,
        "html_path": paths["html"],
        "page": page,
        "parsed": Page(page),
        "report": json.loads(paths["json"].read_text()),
    }


def test_real_page_shows_the_reports_numbers(real: dict) -> None:
    report, p = real["report"], real["parsed"]
    s = report["sensors"]["ccd_left"]
    assert {"summary", "sensor-ccd_left", "outliers", "views", "run"} <= set(p.ids)
    head, row = p.table("overview")[0], p.table("overview")[1]
    cells = dict(zip(head, row, strict=True))
    assert cells["sensor"] == "ccd_left" and cells["RMS px"] == f"{s['rms_px']:.3f}"
    assert cells["views used / found"] == f"{s['views_used']} / {s['views_detected']}"
    for key in ("fx", "fy"):
        value, sigma, d = value_sigma(cells[f"{key} px"])
        assert value == pytest.approx(s["intrinsics"][key], abs=0.51 * 10**-d)
        assert sigma == pytest.approx(s["sigma"][key], abs=0.51 * 10**-d)
        # two significant digits of sigma
        assert 10 <= sigma * 10**d < 100
    for key in ("cx", "cy"):
        (row,) = p.rows_starting(key)
        assert row[1] == pm(s["intrinsics"][key], s["sigma"][key])
    for v, per in report["views"].items():
        (row,) = p.rows_starting(v)
        assert row[1] == f"{per['ccd_left']['rms_px']:.3f}", v
    # one bar per view used, and every corner of them in the scatter
    sensor = real["page"].split("id='sensor-ccd_left'")[1].split("</section>")[0]
    bars = re.findall(r"<rect [^>]*><title>([^<]*) px</title>", sensor)
    assert len(bars) == s["views_used"] == len(report["views"])
    n_corners = 54 * s["views_used"]
    assert f"{n_corners} used" in sensor
    assert re.search(r"corners cover \d+ % of the image", sensor)
    assert real["page"].count("h0") >= 2 * n_corners  # scatter dots, then the corner dots


def test_real_page_is_self_contained_well_formed_and_small(real: dict) -> None:
    page = real["page"]
    assert_self_contained(page)
    assert_well_formed(real["parsed"])
    assert 20_000 < len(page.encode()) < 300_000  # 59 kB measured
    # the command as run, and what it ran on
    (row,) = real["parsed"].rows_starting("command")
    assert row[1].startswith("trifuse calibrate " + str(real["capture"]))
    assert f"--report-html {real['html_path']}" in row[1]
    (row,) = real["parsed"].rows_starting("software")
    assert "OpenCV" in row[1] and "numpy" in row[1]


def test_an_existing_page_is_not_overwritten(real: dict, capsys) -> None:
    before = real["html_path"].read_bytes()
    out = real["html_path"].with_name("rig2.yaml")
    argv = ["calibrate", str(real["capture"]), "--out", str(out)]
    assert main([*argv, "--report-html", str(real["html_path"])]) == 2
    assert "--report-html" in capsys.readouterr().err and not out.exists()
    assert real["html_path"].read_bytes() == before


# -- five sensors, outliers, one sensor left out, the ground truth ------------------------

RIG = default_rig()
NOISE = {"color": 0.08, "thermal": 0.06, "tof": 0.05}
BAD_VIEW, BAD_CORNERS_VIEW, MISSED_VIEW = "0003", "0005", "0006"


@pytest.fixture(scope="module")
def rig_run() -> dict:
    """Twelve views of the simulated head's board poses (corners projected with the true
    rig plus noise): ccd_left's view 0003 with noise of 1.5 px (an outlier view), two corners of
    thermal_left's view 0005 moved 2 px (outlier corners), ccd_right's board not found in
    0006, thermal_right seen in 4 views only (left out: at least 5 asked for)."""
    rng = np.random.default_rng(7)
    obs: dict[str, dict[str, np.ndarray]] = {}
    for i, T_rig_board in enumerate(calibration_poses(12, seed=1, rig=RIG)):
        v = f"{i + 1:04d}"
        for s in RIG.names:
            pts = transform_points(RIG.T(s, "tof") @ T_rig_board, CALIBRATION_BOARD.object_points())
            uv = RIG[s].intrinsics.project(pts)
            w, h = RIG[s].image_size
            if np.isfinite(uv).all() and (uv > 3).all() and (uv < (w - 4, h - 4)).all():
                obs.setdefault(v, {})[s] = uv + rng.normal(0, NOISE[RIG[s].modality], uv.shape)
    obs[BAD_VIEW]["ccd_left"] = obs[BAD_VIEW]["ccd_left"] + rng.normal(0, 1.5, (54, 2))
    obs[BAD_CORNERS_VIEW]["thermal_left"][[0, 7]] += 2.0
    del obs[MISSED_VIEW]["ccd_right"]
    seen = [v for v in sorted(obs) if "thermal_right" in obs[v]]
    for v in seen[4:]:
        del obs[v]["thermal_right"]
    specs = {n: SensorSpec(n, RIG[n].modality, RIG[n].image_size) for n in RIG.names}
    result = calibrate_rig(
        obs, CALIBRATION_BOARD, specs, CalibrationOptions(min_views=5), eyes=RIG.eyes
    )
    methods = {v: {s: "test" for s in per} for v, per in obs.items()}
    detections = DetectionRun(obs, {MISSED_VIEW: {"ccd_right": "not found (test)"}}, methods)
    capture = SimpleNamespace(
        path=Path("simulated"), board=CALIBRATION_BOARD, palette_report=dict, unreadable=[]
    )
    report = build_report(result, detections, capture)  # type: ignore[arg-type]
    report["comparison"] = {"truth": "true.yaml", **compare_rigs(result.rig(), RIG).as_dict()}
    page = render_report_html(report, result.corners, "test", {"trifuse": "test"}, "now")
    return {"result": result, "report": report, "page": page, "parsed": Page(page)}


def test_rig_page_has_every_section(rig_run: dict) -> None:
    report, p = rig_run["report"], rig_run["parsed"]
    sections = {"summary", "pairs", "decisions", "outliers", "views", "truth", "run"}
    assert sections | {f"sensor-{n}" for n in report["sensors"]} <= set(p.ids)
    assert "thermal_right" in report["excluded_sensors"]
    assert "sensor-thermal_right" not in p.ids
    assert report["excluded_sensors"]["thermal_right"] in "".join(p.text)
    assert_self_contained(rig_run["page"])
    assert_well_formed(p)
    assert len(rig_run["page"].encode()) < 600_000


def test_rig_page_shows_what_was_left_out_and_why(rig_run: dict) -> None:
    report, page, p = rig_run["report"], rig_run["page"], rig_run["parsed"]
    (bad,) = [o for o in report["outliers"] if o["corner"] is None]
    assert (bad["view"], bad["sensor"]) == (BAD_VIEW, "ccd_left")
    corners = [o for o in report["outliers"] if o["corner"] is not None]
    assert {(o["view"], o["sensor"], o["corner"]) for o in corners} == {
        (BAD_CORNERS_VIEW, "thermal_left", 0),
        (BAD_CORNERS_VIEW, "thermal_left", 7),
    }
    # the outliers table, the red bar, the red corners, the view left out in its section
    assert [BAD_VIEW, "ccd_left", f"{bad['error_px']:.2f}", bad["reason"]] in p.rows_starting(
        BAD_VIEW
    )
    ccd_left = page.split("id='sensor-ccd_left'")[1].split("</section>")[0]
    assert f"{BAD_VIEW}: {report['views'][BAD_VIEW]['ccd_left']['rms_px']:.3f} px (outlier)" in (
        ccd_left
    )
    assert f"view {BAD_VIEW} left out" in ccd_left
    thermal = page.split("id='sensor-thermal_left'")[1].split("</section>")[0]
    red = re.search(r'<path d="([^"]*)" stroke="#d62728"[^>]*><title>outlier corner', thermal)
    assert red is not None and red.group(1).count("h0") == 2
    ccd_right = page.split("id='sensor-ccd_right'")[1].split("</section>")[0]
    assert f"board not found in 1 view(s) ({MISSED_VIEW}): not found (test)" in ccd_right
    assert "× [1]" in next(r for r in p.rows_starting(MISSED_VIEW) if len(r) > 2)


def test_rig_page_poses_agree_with_the_truth(rig_run: dict) -> None:
    """Every pair's baseline on the page: within 3 sigma (and the rounding) of the true
    rig's, and the rotation angle likewise."""
    report, p = rig_run["report"], rig_run["parsed"]
    names = list(report["sensors"])
    checked = 0
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            (row,) = [r for r in p.rows_starting(f"{a} – {b}") if r[-1] in ("own", "joint", "≈")]
            T = RIG.T(a, b)
            base, s_base, d = value_sigma(row[4])
            assert abs(base - 1000 * np.linalg.norm(T[:3, 3])) < 3 * s_base + 10**-d, row
            angle, s_angle, d = value_sigma(row[1])
            true_angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
            assert abs(angle - true_angle) < 3 * s_angle + 10**-d, row
            checked += 1
    assert checked == len(names) * (len(names) - 1) // 2 >= 6
    # the comparison with the truth, as in report["comparison"]
    cmp = report["comparison"]
    for n, e in cmp["sensors"].items():
        (row,) = [r for r in p.rows_starting(n) if len(r) == 10]
        assert row[3] == f"{e['fx_percent']:.3f}" and row[6] == ("pass" if e["fx_ok"] else row[6])


def test_additions_to_the_report_are_shown(rig_run: dict) -> None:
    """Keys the report gains (a verdict, advice, a palette decision) appear without more
    work: at the top, in their sensor's section, under "Decisions and other findings"."""
    report = json.loads(json.dumps(rig_run["report"]))
    report["verdict"] = "usable: σ of the baseline 0.4 mm (good at ≤ 0.25 mm)"
    report["advice"] = ["capture 6 more views tilted about the vertical axis"]
    report["sensors"]["thermal_left"]["verdict"] = "poor: σ of fx 0.9 %"
    report["sensors"]["thermal_left"]["palette"] = {"name": "iron", "radiometric": False}
    report["thermal_palette"] = {"thermal_left": {"palette": "iron", "inverted": True}}
    page = render_report_html(report, rig_run["result"].corners)
    p = Page(page)
    assert_well_formed(p)
    summary = page.split("id='summary'")[1].split("</section>")[0]
    assert "box box-fair" in summary and report["verdict"] in summary
    assert "capture 6 more views tilted about the vertical axis" in summary
    thermal = page.split("id='sensor-thermal_left'")[1].split("</section>")[0]
    assert "box box-bad" in thermal and "poor: σ of fx 0.9 %" in thermal
    assert ["radiometric", "no"] in p.rows_starting("radiometric") and "Other figures" in thermal
    decisions = page.split("id='decisions'")[1].split("</section>")[0]
    assert "Thermal palette" in decisions and "inverted" in decisions


def test_a_report_read_back_without_residuals_still_renders(rig_run: dict) -> None:
    page = render_report_html(json.loads(json.dumps(rig_run["report"])))
    p = Page(page)
    assert_well_formed(p)
    assert "Per-corner residuals are not in report.json" in page
    assert "corners cover" in page and "RMS error per view" in page


def test_text_from_the_capture_is_escaped(rig_run: dict) -> None:
    report = json.loads(json.dumps(rig_run["report"]))
    report["notes"] = ["<script>alert(1)</script> & <img src=x>"]
    report["capture"] = "/tmp/<b>"
    page = render_report_html(report)
    assert "<script>" not in page and "<img" not in page and "/tmp/&lt;b&gt;" in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &amp; &lt;img src=x&gt;" in page
    assert_well_formed(Page(page))


# -- the console: the panel's download and the route send the same page -------------------


def test_panel_download_and_route_send_the_same_page(rig_run: dict, tmp_path: Path) -> None:
    from tests.scene_support import pipeline_for, scene_context
    from trifuse.app.server.panels.calibration import CalibrationPanel

    session = CalibrationSession(tmp_path, RIG, CALIBRATION_BOARD)
    ctx = scene_context(pipeline_for())
    try:
        app = FastAPI()
        app.include_router(make_session_router(session, lambda: None, lambda _rig: None))
        with TestClient(app) as client:
            assert client.get("/api/calibrate/report.html").status_code == 404
            panel = CalibrationPanel(ctx, session)
            sent: list[tuple[str, bytes]] = []
            fake = SimpleNamespace(send_file_download=lambda n, c, **_kw: sent.append((n, c)))
            panel.send_report(fake)
            assert not sent and "Not done" in panel.message.content
            finished = time.time()
            session.job = CalibrationJob(
                "done",
                "done",
                1.0,
                sorted(rig_run["report"]["views"]),
                report=rig_run["report"],
                started=finished - 1,
                finished=finished,
                result=rig_run["result"],
            )
            panel.tick()
            assert panel.download.visible
            panel.send_report(fake)
            reply = client.get("/api/calibrate/report.html")
        assert reply.status_code == 200 and reply.headers["content-security-policy"] == CSP
        assert reply.headers["content-type"].startswith("text/html")
        [(name, content)] = sent
        assert name == REPORT_HTML_NAME and content == reply.content
        assert content.decode() == session_report_html(session.job)
        assert "the console's calibration session (12 views)" in "".join(
            Page(content.decode()).text
        )
    finally:
        session.close()
        ctx.server.stop()


# -- headless Chromium: opens the file, fetches nothing -----------------------------------


@needs_chromium
def test_chromium_opens_the_page_without_a_request(real: dict, browser, tmp_path: Path) -> None:
    page = browser.new_page(viewport={"width": 900, "height": 1200})
    requests, problems = [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(str(e)))
    url = real["html_path"].as_uri()
    page.goto(url)
    page.wait_for_load_state("load")
    assert requests == [url] and not problems
    sizes = page.evaluate(
        "() => [...document.querySelectorAll('svg')].map(s => s.getBoundingClientRect().width)"
    )
    assert len(sizes) == 4 and min(sizes) > 200  # bars, scatter, vectors, coverage
    assert page.title().startswith("Calibration report")
    page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
    page.emulate_media(media="print")
    page.pdf(path=str(tmp_path / "report.pdf"), format="A4")
    assert (tmp_path / "report.pdf").stat().st_size > 10_000
    page.close()
