"""The thermal balance where it is used: the console's balancer (applied, or refused with
the reason and nothing changed), the fused pictures of both eyes painting the same
surface in the same colour once balanced, the smoothed shared span, and
``trifuse balance-thermal`` over a simulated recording."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.support import ListSource
from trifuse.app.cli import main
from trifuse.app.recording.writer import RecordingWriter
from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.server.runtime.thermal_balance import ThermalBalancer
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.fusion.balance import balance_terms, measure_balance
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.stereo import StereoFusion

# The simulator's imagers read +0.75 K (left) and -0.75 K (right) off; NETD 0.08 K.
SIM_DIFFERENCE_K = 1.5


@pytest.fixture(scope="module")
def inspection():
    """Two instants of the simulated inspection room (all sensors)."""
    scenario = InspectionScenario(seed=0)
    return scenario.rig, [scenario.render(t)[0] for t in (0.0, 1.0)]


def _pipeline_at(rig, fs: FrameSet) -> FusionPipeline:
    p = FusionPipeline(ListSource(), rig, FrameHub())
    p.fusion.update_depth(fs.frames["tof"].distance_m, fs.frames["tof"].image)
    p.latest_set = fs
    return p


def test_balancer_applies_the_filtered_balance(inspection) -> None:
    rig, (fs, _) = inspection
    p = _pipeline_at(rig, fs)
    b = ThermalBalancer(p)
    b.tick()
    assert abs(b.status.difference_k - SIM_DIFFERENCE_K) <= 0.03  # before: as the sim made it
    b.set_auto(True)
    b.tick()  # a fresh filter: the first estimate is taken as it is, and applied
    left, right = p.radiometry["thermal_left"], p.radiometry["thermal_right"]
    assert left.balance_offset_k == pytest.approx(-0.75, abs=0.015)
    assert right.balance_offset_k == pytest.approx(0.75, abs=0.015)
    b.tick()  # same frames, new radiometry: measured again, as displayed now
    assert abs(b.status.difference_k) < 0.2  # the bound (0.05 K measured)
    assert "Left - right: **+0.0" in b.status.difference_text() or "**-0.0" in (
        b.status.difference_text()
    )


def test_balance_is_measured_only_while_read_or_applied(inspection) -> None:
    rig, (fs, later) = inspection
    p = _pipeline_at(rig, fs)
    listeners = Demand("thermal balance")
    b = ThermalBalancer(p, listeners=listeners)
    b.tick()  # nobody reads it, auto off: nothing measured
    assert b.status.waiting == "waiting for frames" and b.filter.state is None
    with listeners.hold():  # a Viser client
        b.tick()
    assert abs(b.status.difference_k - SIM_DIFFERENCE_K) <= 0.03
    first = b.status
    p.latest_set = later  # newer frames, and nobody read the balance for 10 s
    b._measured_at -= 10.0
    b.apply_filtered()  # stale: measured again first, then applied
    assert b.status is not first and b.status.estimate.ok
    assert p.radiometry["thermal_left"].balance_offset_k == pytest.approx(-0.75, abs=0.015)
    assert listeners.wanted  # the request renewed the lease
    q = _pipeline_at(rig, fs)
    c = ThermalBalancer(q, listeners=Demand("nobody"))
    c.set_auto(True)  # applied continuously: measured whoever reads it
    c.tick()
    assert q.radiometry["thermal_right"].balance_offset_k == pytest.approx(0.75, abs=0.015)


def test_console_balances_by_default_unless_the_rig_brings_a_balance(inspection) -> None:
    rig, (fs, _) = inspection
    p = _pipeline_at(rig, fs)
    b = ThermalBalancer(p, listeners=Demand("nobody"), auto=None)  # as the console makes it
    assert b.auto and b.describe() == {"mode": "auto", "correction_k": 0.0}
    b.tick()  # nobody reads it, but it is applied: measured
    described = b.describe()
    assert described["mode"] == "auto"
    assert described["correction_k"] == pytest.approx(-SIM_DIFFERENCE_K, abs=0.03)
    first = b.status
    b.tick()  # settled, nobody reading: kept up every SETTLED_PERIOD_S, not at each tick
    assert b.status is first
    b.set_auto(False)  # off: the balance stays, applied
    assert b.describe()["mode"] == "applied"
    b.reset_balance()
    assert b.describe() == {
        "mode": "off",
        "correction_k": 0.0,
        "difference_k": pytest.approx(SIM_DIFFERENCE_K, abs=0.03),
    }
    # a rig saved with a balance: that one is shown, not replaced
    saved = p.rig_with_radiometry()
    for name, offset in (("thermal_left", -0.7), ("thermal_right", 0.7)):
        saved = saved.with_sensor(
            dataclasses.replace(saved[name], radiometry=Radiometry().with_balance(1.0, offset))
        )
    q = _pipeline_at(saved, fs)
    c = ThermalBalancer(q, auto=None)
    assert not c.auto and c.describe() == {"mode": "rig", "correction_k": -1.4}


def test_refused_estimate_leaves_the_balance_and_says_why(inspection) -> None:
    rig, (fs, _) = inspection
    p = _pipeline_at(rig, fs)
    p.set_balance({"thermal_left": (1.0, -0.5), "thermal_right": (1.0, 0.5)})
    before = dict(p.radiometry)
    b = ThermalBalancer(p)
    b.set_auto(True)
    # no valid TOF point: every distance NaN (a TOF looking at the sky, or failing)
    nan = np.full_like(fs.frames["tof"].distance_m, np.nan)
    p.fusion.update_depth(nan)
    b.tick()
    assert p.radiometry == before
    assert "only 0 points seen by both thermal imagers" in b.status.estimate.reason
    assert "no shared points" in b.status.difference_text()
    # no overlap: the right imager turned to look behind the head
    turned = dataclasses.replace(
        rig["thermal_right"],
        T_rig_sensor=rig["thermal_right"].T_rig_sensor
        @ make_T(rotation_from_euler_deg(0, 180, 0), (0, 0, 0)),
    )
    away = dataclasses.replace(rig, sensors={**rig.sensors, "thermal_right": turned})
    q = _pipeline_at(away, fs)
    q.set_balance({"thermal_left": (1.0, -0.5), "thermal_right": (1.0, 0.5)})
    before = dict(q.radiometry)
    c = ThermalBalancer(q)
    c.set_auto(True)
    c.tick()
    assert q.radiometry == before
    assert not c.status.estimate.ok and "their views do not overlap" in c.status.estimate.reason
    with pytest.raises(ValueError, match="no balance estimate yet"):
        c.apply_filtered()


def test_balanced_eyes_paint_the_same_surface_in_the_same_colour(inspection) -> None:
    rig, (fs, _) = inspection
    tof = fs.frames["tof"]
    fusion = StereoFusion(rig)
    fusion.update_depth(tof.distance_m, tof.image)
    colors = {e: fs.frames[rig.eyes[e].color].image for e in ("left", "right")}
    raw = {e: fs.frames[rig.eyes[e].thermal].image for e in ("left", "right")}
    left, right = rig.eyes["left"].thermal, rig.eyes["right"].thermal
    settings = DisplaySettings(mode="thermal", palette="iron", span_k=(288.0, 300.0))
    # TOF points both imagers see (shared, off edges) -> their pixels in each colour camera
    m = measure_balance(rig, "tof", fusion.points, left, right, raw["left"], raw["right"], {})
    pts = fusion.points[m.shared.index]
    uv = {}
    for e in ("left", "right"):
        cam = rig[rig.eyes[e].color]
        T = rig.T(cam.name, "tof")
        uv[e] = np.round(cam.intrinsics.project(pts @ T[:3, :3].T + T[:3, 3])).astype(int)
    w, h = rig[rig.eyes["left"].color].image_size
    inside = np.all(
        [(u[:, 0] >= 0) & (u[:, 0] < w) & (u[:, 1] >= 0) & (u[:, 1] < h) for u in uv.values()],
        axis=0,
    )

    def colour_gap(thermals) -> float:
        frame = fusion.compose(colors, thermals, settings).copy()
        halves = {"left": frame[:, :w], "right": frame[:, w:]}
        c = {e: halves[e][uv[e][inside, 1], uv[e][inside, 0]].astype(int) for e in halves}
        return float(np.median(np.abs(c["left"] - c["right"]).max(axis=1)))

    # 1.5 K over a 12 K span is 1/8 of the palette: about 30 levels in some channel
    assert colour_gap(raw) > 15
    terms = balance_terms(m.estimate, left, right)
    r = {s: Radiometry().with_balance(*terms[s]) for s in (left, right)}
    balanced = {"left": r[left].apply(raw["left"]), "right": r[right].apply(raw["right"])}
    # residual: noise and sampling (0.08 K NETD, bilinear) ~ 0.1 K -> a few levels at most
    assert colour_gap(balanced) <= 3


def test_auto_span_is_smoothed_over_frame_time(inspection) -> None:
    rig, (fs, _) = inspection
    tof = fs.frames["tof"]
    fusion = StereoFusion(rig)
    fusion.update_depth(tof.distance_m, tof.image)
    colors = {e: fs.frames[rig.eyes[e].color].image for e in ("left", "right")}
    cool = {e: fs.frames[rig.eyes[e].thermal].image for e in ("left", "right")}
    warm = {e: cool[e] + np.float32(4.0) for e in cool}
    s = DisplaySettings(span_smoothing_s=1.0)
    fusion.compose(colors, cool, s, stamp_ns=0)
    low0 = fusion.span_k[0]
    fusion.compose(colors, warm, s, stamp_ns=100_000_000)  # 0.1 s later: 1 - e^-0.1 = 9.5 %
    assert fusion.span_k[0] - low0 == pytest.approx(4.0 * (1 - np.exp(-0.1)), abs=0.01)
    assert not fusion.span_settled
    fusion.compose(colors, warm, s, stamp_ns=10_000_000_000)  # 10 s later: there
    assert fusion.span_k[0] - low0 == pytest.approx(4.0, abs=0.01) and fusion.span_settled
    fusion.compose(colors, cool, DisplaySettings(span_smoothing_s=0.0), stamp_ns=10_100_000_000)
    assert fusion.span_k[0] == pytest.approx(low0, abs=1e-6)  # 0: no smoothing


def _recording(path: Path, rig, sets: list[FrameSet]) -> Path:
    """The rendered instants as a 2 s recording: thermal and TOF at 5 Hz."""
    with RecordingWriter(path, rig) as w:
        for k in range(10):
            fs = sets[k % len(sets)]
            for name in ("thermal_left", "thermal_right", "tof", "ccd_left", "ccd_right"):
                f = fs.frames[name]
                w.write(Frame(name, k * 200_000_000, f.image, f.distance_m))
    return path


def test_balance_thermal_command(inspection, tmp_path: Path, capsys) -> None:
    rig, sets = inspection
    from trifuse.app.storage.rigfile import save_rig

    rec = _recording(tmp_path / "room.mcap", rig, sets)
    rig_path = save_rig(tmp_path / "rig.yaml", rig)
    assert main(["balance-thermal", str(rec), "--rig", str(rig_path), "--out", str(rig_path)]) == 0
    out = capsys.readouterr().out
    before, after = (
        float(x) for x in re.search(r"before ([+-][\d.]+) K, after ([+-][\d.]+) K", out).groups()
    )
    assert abs(before - SIM_DIFFERENCE_K) <= 0.03 and abs(after) < 0.2  # the bound
    assert (tmp_path / "rig.yaml.~1~").exists()  # the previous rig kept
    saved = yaml.safe_load(rig_path.read_text())
    for name, half in (("thermal_left", -0.75), ("thermal_right", 0.75)):
        assert saved["sensors"][name]["radiometry"]["balance_offset_k"] == pytest.approx(
            half, abs=0.015
        )
    # onto a reference imager: it stays, the other takes the whole 1.5 K
    ref = tmp_path / "ref.yaml"
    argv = ["balance-thermal", str(rec), "--rig", str(tmp_path / "rig.yaml.~1~")]
    assert main([*argv, "--out", str(ref), "--reference", "thermal_left"]) == 0
    saved = yaml.safe_load(ref.read_text())
    assert saved["sensors"]["thermal_left"]["radiometry"]["balance_offset_k"] == 0.0
    assert saved["sensors"]["thermal_right"]["radiometry"]["balance_offset_k"] == pytest.approx(
        1.5, abs=0.03
    )
    assert main([*argv, "--out", str(ref)]) == 2  # an existing other file is never replaced
