"""``trifuse measure`` (app/cli/measure.py, app/recording/measure.py) on a recording of the
simulated measurement scene (app/sources/sim/measurement_scene.py; imagers without offset)
in which the 150 C hot plate turns 10 K hotter halfway: the table's readings are the
panels' true temperatures within issue 35's 0.5 K (tests/fusion/test_measure.py says why
that holds), its alarm is raised when the plate passes 428 K, and the emissivity chosen
after the recording changes the readings. Bad plans and outputs: one line, nothing
written."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import pytest

from tests.measure_support import panel_boxes, render
from tests.support import run_cli, write_recording
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.sources.sim.measurement_scene import (
    AIR_K,
    HUMIDITY_PCT,
    PANELS,
    SKY_K,
    measurement_scene,
)

TOLERANCE_K = 0.5
STEP_NS = 100_000_000  # frame sets 0.1 s apart
HOTTER_K = 10.0


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, dict[str, list[list[float]]]]:
    """Four frame sets 0.1 s apart: the scene as it is twice, then with the hot plate 10 K
    hotter twice (each pair one render, its frames given two stamps); and a box well inside
    each panel (left eye's pixels)."""
    rig = default_rig()
    hotter = measurement_scene()
    plate = next(s for s in hotter.solids if s.name == "hot")
    plate.material = dataclasses.replace(
        plate.material, temperature_k=plate.material.temperature_k + HOTTER_K
    )
    frames: list[Frame] = []
    boxes: dict[str, list[list[float]]] = {}
    for k, s in enumerate((None, hotter)):
        fs, truth = render(s, seed=k)
        for stamp in (2 * k * STEP_NS, (2 * k + 1) * STEP_NS):
            frames += [Frame(n, stamp, fs.frames[n].image, fs.frames[n].distance_m)
                       for n in rig.names]  # fmt: skip
        boxes = boxes or {n: [list(a), list(b)] for n, (a, b) in panel_boxes(truth).items()}
    path = write_recording(tmp_path_factory.mktemp("rec") / "scene.mcap", rig, frames)
    return path, boxes


def _plan(boxes, emissivity: dict[str, float] | None = None) -> str:
    eps = emissivity or {p.name: p.emissivity for p in PANELS}
    lines = [
        "parameters:",
        f"  reflected_k: {SKY_K}",
        f"  air_k: {AIR_K}",
        f"  humidity_pct: {HUMIDITY_PCT}",
        "regions:",
    ]
    for name, ((x0, y0), (x1, y1)) in boxes.items():
        lines.append(
            f"  - {{name: {name}, shape: box, points: [[{x0}, {y0}], [{x1}, {y1}]], "
            f"emissivity: {eps[name]}}}"
        )
    lines += ["alarms:", "  - {region: hot, kind: above, threshold: 428.0}"]
    return "\n".join(lines) + "\n"


def _table(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_table_reads_the_true_temperatures_and_the_alarm(recording, tmp_path, capsys) -> None:
    rec, boxes = recording
    plan = tmp_path / "plan.yaml"
    plan.write_text(_plan(boxes))
    table = tmp_path / "table.csv"
    code, out, _ = run_cli(["measure", str(rec), "--regions", str(plan), "--out", str(table)],
                           capsys)  # fmt: skip
    assert code == 0, out
    rows = _table(table)
    sets = sorted({int(r["stamp_ns"]) for r in rows})
    # the first set has no depth yet (its TOF frame closes it): the others are read
    assert len(sets) >= 3 and len(rows) == 4 * len(sets)
    assert f"Wrote {len(rows)} rows" in out
    for r in rows:
        true_k = {p.name: p.temperature_k for p in PANELS}[r["region"]]
        if r["region"] == "hot" and int(r["stamp_ns"]) >= 2 * STEP_NS:
            true_k += HOTTER_K
        assert float(r["mean_k"]) == pytest.approx(true_k, abs=TOLERANCE_K), r
        assert float(r["apparent_mean_k"]) < true_k - 1.0
        assert int(r["pixels"]) > 2000 and r["default_distance_px"] == "0"
    hot = [r for r in rows if r["region"] == "hot"]
    raised = [r for r in hot if r["events"]]
    assert [r["events"] for r in raised] == ["raised above 428"]
    assert int(raised[0]["stamp_ns"]) == 2 * STEP_NS  # the first hotter set
    assert all(r["active_alarms"] == ("hot above 428" if int(r["stamp_ns"]) >= 2 * STEP_NS
                                      else "") for r in hot)  # fmt: skip


def test_another_emissivity_afterwards_changes_the_reading(recording, tmp_path, capsys) -> None:
    """The recording keeps the imagers' apparent temperatures: read with emissivity 1
    instead of 0.5, the 'half' panel reads far colder (the same apparent temperature)."""
    rec, boxes = recording
    eps = {p.name: p.emissivity for p in PANELS} | {"half": 1.0}
    plan = tmp_path / "plan.yaml"
    plan.write_text(_plan(boxes, eps))
    table = tmp_path / "table.csv"
    run_cli(["measure", str(rec), "--regions", str(plan), "--out", str(table)], capsys)
    half = [r for r in _table(table) if r["region"] == "half"]
    assert all(float(r["mean_k"]) < 373.15 - 30 for r in half)


@pytest.mark.parametrize(
    ("plan", "says"),
    [
        ("regions: []\n", "regions: expected a list of at least one region"),
        ("parameters: {emissivity: 2}\nregions: [{name: a, shape: spot, points: [[1, 1]]}]\n",
         "parameters: emissivity: expected 0.01 to 1, got 2"),
        ("parameters: {humidity_pct: 101}\nregions: [{name: a, shape: spot, points: [[1, 1]]}]\n",
         "humidity_pct: expected 0 to 100, got 101"),
        ("regions: [{name: a, shape: box, points: [[5000, 1], [5100, 9]]}]\n",
         "a: outside the 1280x960 image"),
        ("regions: [{name: a, shape: spot, points: [[1, 1]]}]\n"
         "alarms: [{region: b, kind: above, threshold: 300}]\n", "no region named 'b'"),
        ("regions: [{name: a, shape: spot, points: [[1, 1]], colour: red}]\n",
         "regions[0]: got an unexpected keyword argument 'colour'"),
        ("regions: [: :\n", "not YAML"),
    ],
)  # fmt: skip
def test_a_bad_plan_is_one_line_and_writes_nothing(recording, tmp_path, capsys, plan, says) -> None:
    rec, _ = recording
    path = tmp_path / "plan.yaml"
    path.write_text(plan)
    table = tmp_path / "table.csv"
    code, _, err = run_cli(
        ["measure", str(rec), "--regions", str(path), "--out", str(table)], capsys
    )
    assert code != 0 and says in err and len(err.strip().splitlines()) == 1, err
    assert not table.exists()


def test_an_existing_table_is_not_overwritten(recording, tmp_path, capsys) -> None:
    rec, boxes = recording
    plan = tmp_path / "plan.yaml"
    plan.write_text(_plan(boxes))
    table = tmp_path / "table.csv"
    table.write_text("mine\n")
    code, _, err = run_cli(
        ["measure", str(rec), "--regions", str(plan), "--out", str(table)], capsys
    )
    assert code != 0 and "refusing to overwrite" in err
    assert table.read_text() == "mine\n"


def test_without_a_plan_the_recordings_own_settings_are_used(tmp_path, capsys) -> None:
    """A recording with the console's measurement settings note: `trifuse measure` without
    --regions reads the regions and parameters the console used; a recording without one
    is refused in one line."""
    from trifuse.app.recording import RecordingWriter
    from trifuse.app.recording.layout import SETTINGS_NOTE
    from trifuse.app.recording.writer import Note

    rig = default_rig()
    fs, truth = render()
    (x0, y0), (x1, y1) = panel_boxes(truth)["steel"]
    settings = {
        "parameters": {"emissivity": 0.8, "reflected_k": SKY_K, "air_k": AIR_K,
                       "humidity_pct": HUMIDITY_PCT, "default_distance_m": 3.0},
        "regions": [{"name": "steel", "eye": "left", "shape": "box",
                     "points": [[x0, y0], [x1, y1]], "emissivity": None, "reflected_k": None}],
        "alarms": [],
    }  # fmt: skip
    rec = tmp_path / "noted.mcap"
    with RecordingWriter(rec, rig) as w:
        for k in range(3):
            for n in rig.names:
                f = fs.frames[n]
                w.write(Frame(n, k * STEP_NS, f.image, f.distance_m))
        w.write_note(Note(0, SETTINGS_NOTE, "info", settings))
    table = tmp_path / "t.csv"
    code, _, err = run_cli(["measure", str(rec), "--out", str(table)], capsys)
    assert code == 0, err
    rows = _table(table)
    assert rows and {r["region"] for r in rows} == {"steel"}
    assert all(float(r["mean_k"]) == pytest.approx(333.15, abs=TOLERANCE_K) for r in rows)
    plain = write_recording(tmp_path / "plain.mcap", rig, [fs.frames[n] for n in rig.names])
    code, _, err = run_cli(["measure", str(plain), "--out", str(tmp_path / "u.csv")], capsys)
    assert code != 0 and "holds no measurement settings" in err


def test_fuse_measures_the_same_frame_sets_beside_its_pictures(recording, tmp_path, capsys) -> None:
    """`trifuse fuse --measure PLAN.yaml`: the pictures and DIR/measurements.csv, the very
    table `trifuse measure` writes with that plan; `--measure` alone on a recording without
    the console's settings is refused in one line before anything is written."""
    rec, boxes = recording
    plan = tmp_path / "plan.yaml"
    plan.write_text(_plan(boxes))
    table = tmp_path / "table.csv"
    assert run_cli(["measure", str(rec), "--regions", str(plan), "--out", str(table)],
                   capsys)[0] == 0  # fmt: skip
    out_dir = tmp_path / "fused"
    code, out, err = run_cli(
        ["fuse", str(rec), "--out", str(out_dir), "--measure", str(plan)], capsys
    )
    assert code == 0, err
    assert sorted(out_dir.glob("*.jpg")) and "measurements.csv" in out
    assert (out_dir / "measurements.csv").read_text() == table.read_text()
    bare = tmp_path / "bare"
    code, _, err = run_cli(["fuse", str(rec), "--out", str(bare), "--measure"], capsys)
    assert code != 0 and "holds no measurement settings" in err
    assert len(err.strip().splitlines()) == 1 and not bare.exists()
