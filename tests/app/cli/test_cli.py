"""The ``trifuse`` command line (app.cli) and the benchmark registry (app.devtools.bench)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.support import ROOT
from trifuse.app.cli import main
from trifuse.app.devtools import bench, benchmark

COMMANDS = [
    "simulate", "calibrate", "compare", "rig", "analyze", "record", "fuse", "map", "serve", "bench"
]  # fmt: skip


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


# -- help ---------------------------------------------------------------------------------


def test_main_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(["--help"], capsys)
    assert code == 0
    for command in COMMANDS:
        assert command in out
    assert "Run 'trifuse COMMAND --help'" in out


@pytest.mark.parametrize(
    ("argv", "mentions"),
    [
        (["simulate", "--help"], ["calibration"]),
        (["simulate", "calibration", "--help"], ["--views", "--out", "--seed", "--rig"]),
        (["bench", "--help"], ["--only", "--repeat", "render"]),
        (["map", "--help"], ["--out", "--voxel", "--pose", "--map-file", "--force", "PLY"]),
        (["record", "--help"], ["--scenario", "survey"]),
        (["serve", "--help"], ["--scenario", "survey"]),
    ],
)
def test_command_help(
    argv: list[str], mentions: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = run(argv, capsys)
    assert code == 0
    for word in mentions:
        assert word in out


def test_console_script_entry_point() -> None:
    """``python -m trifuse.app.cli`` is what the ``trifuse`` console script runs."""
    proc = subprocess.run(
        [sys.executable, "-m", "trifuse.app.cli", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0
    assert all(c in proc.stdout for c in COMMANDS)


# -- errors: one line on stderr, exit 2, no traceback -------------------------------------


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        ([], "expected a command"),
        (["bogus"], "invalid choice: 'bogus'"),
        (["simulate"], "expected a command"),
        (["simulate", "calibration"], "required: --out"),
        (["simulate", "calibration", "--views", "x", "--out", "o"], "expected a positive integer"),
        (["simulate", "calibration", "--views", "0", "--out", "o"], "expected a positive integer"),
        (["simulate", "calibration", "--seed", "-3", "--out", "o"], "expected an integer >= 0"),
        (["bench", "--repeat", "-1"], "expected a positive integer"),
        (["bench", "--only", "nope"], "unknown benchmark 'nope'"),
        # the console's own mode: the estimate it draws is made only in the console
        (["fuse", "r.mcap", "--out", "o", "--mode", "registration"], "got 'registration'"),
    ],
)
def test_bad_arguments(argv: list[str], match: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(argv, capsys)
    assert code == 2
    assert match in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err + out


def test_bad_arguments_in_a_real_process(tmp_path: Path) -> None:
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "trifuse.app.cli",
            "simulate",
            "calibration",
            "--views",
            "many",
            "--out",
            str(tmp_path / "o"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert "--views" in proc.stderr
    assert not (tmp_path / "o").exists()


def test_bad_rig_file_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rig = tmp_path / "rig.yaml"
    rig.write_text("format: trifuse-rig/1\nreference: tof\nsensors: {}\n")
    code, _, err = run(
        ["simulate", "calibration", "--out", str(tmp_path / "o"), "--rig", str(rig)], capsys
    )
    assert code == 2
    assert err.startswith("trifuse: error: ") and str(rig) in err and "no sensors" in err
    assert len(err.strip().splitlines()) == 1


def test_refuses_a_non_empty_output_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "precious.png").write_bytes(b"captured by hand")
    code, _, err = run(["simulate", "calibration", "--views", "1", "--out", str(tmp_path)], capsys)
    assert code == 2
    assert "not empty; refusing to write into it" in err
    assert [p.name for p in tmp_path.iterdir()] == ["precious.png"]
    assert (tmp_path / "precious.png").read_bytes() == b"captured by hand"


def test_refuses_an_output_that_is_a_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "file"
    target.write_text("x")
    code, _, err = run(["simulate", "calibration", "--out", str(target)], capsys)
    assert code == 2 and "is not a directory" in err


# Every command that writes refuses an existing output the same way: one line with the
# prefix of every other error, exit 2, the file untouched. (A FILE is made as "precious";
# a DIR as a directory holding one.) Inputs need not exist: the refusal comes first.
REFUSALS = [
    (["simulate", "calibration", "--out", "DIR"], "--out"),
    (["simulate", "calibration", "--out", "FILE"], "--out"),
    (["calibrate", "cap", "--out", "FILE"], "--out"),
    (["calibrate", "cap", "--out", "new.yaml", "--report", "FILE"], "--report"),
    (["calibrate-range", "cap", "--rig", "rig.yaml", "--out", "FILE"], "--out"),
    (["calibrate-range", "cap", "--rig", "r", "--out", "r2", "--report", "FILE"], "--report"),
    (["calibrate-range", "cap", "--rig", "r", "--out", "r2", "--plot", "FILE"], "--plot"),
    (["balance-thermal", "rec.mcap", "--out", "FILE"], "--out"),
    (["balance-thermal", "rec.mcap", "--rig", "r.yaml", "--out", "FILE"], "--out"),
    (["analyze", "rig.yaml", "--plot", "FILE"], "--plot"),
    (["record", "--source", "sim", "--out", "FILE"], "--out"),
    (["record", "--source", "replay:rec.mcap", "--out", "FILE"], "--out"),
    (["fuse", "rec.mcap", "--out", "DIR"], "--out"),
    (["fuse", "rec.mcap", "--out", "FILE"], "--out"),
    (["map", "rec.mcap", "--out", "FILE"], "--out"),
    (["map", "rec.mcap", "--out", "new.ply", "--map-file", "FILE"], "--map-file"),
]  # fmt: skip


@pytest.mark.parametrize(("argv", "flag"), REFUSALS, ids=[" ".join(a) for a, _ in REFUSALS])
def test_every_refusal_to_overwrite_is_one_prefixed_line(
    argv: list[str], flag: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "DIR").mkdir()
    (tmp_path / "DIR" / "precious.png").write_bytes(b"captured by hand")
    (tmp_path / "FILE").write_bytes(b"precious")
    before = sorted((p.relative_to(tmp_path), p.read_bytes() if p.is_file() else b"")
                    for p in tmp_path.rglob("*"))  # fmt: skip
    args = [str(tmp_path / a) if a in ("DIR", "FILE") else a for a in argv]
    code, out, err = run(args, capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"trifuse: error: {flag} {tmp_path}/"), err
    assert "refusing to" in err and len(err.strip().splitlines()) == 1
    after = sorted((p.relative_to(tmp_path), p.read_bytes() if p.is_file() else b"")
                   for p in tmp_path.rglob("*"))  # fmt: skip
    assert after == before


def test_a_rig_may_replace_itself_but_nothing_else(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """calibrate-range --out RIG --rig RIG is allowed (the old file is kept as a backup): it
    gets as far as reading the capture, not refused."""
    rig = tmp_path / "rig.yaml"
    rig.write_text("precious")
    code, _, err = run(
        ["calibrate-range", str(tmp_path / "nope"), "--rig", str(rig), "--out", str(rig)], capsys
    )
    assert code == 2 and "refusing" not in err and rig.read_text() == "precious"


def test_record_suggests_the_commands_that_use_the_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The summary after recording names trifuse commands, not Python classes, and each
    suggested command line is one the parser takes, for the file just written."""
    import shlex

    from tests.support import small_rig, synth_frames, write_recording
    from trifuse.app.cli import build_parser

    rig = small_rig()
    source = write_recording(tmp_path / "in.mcap", rig, synth_frames(rig, 0.1, seed=3))
    out = tmp_path / "mission.mcap"
    code, stdout, err = run(["record", "--source", f"replay:{source}", "--out", str(out)], capsys)
    assert code == 0, err
    assert "ReplaySource" not in stdout and "app.recording" not in stdout
    suggested = [line.strip() for line in stdout.splitlines() if line.startswith("  trifuse ")]
    assert suggested == [f"trifuse serve --replay {out}", f"trifuse fuse {out} --out DIR"]
    serve = build_parser().parse_args(shlex.split(suggested[0])[1:])
    fuse = build_parser().parse_args(shlex.split(suggested[1])[1:])
    assert serve.command == "serve" and Path(serve.replay) == out
    assert fuse.command == "fuse" and [Path(p) for p in fuse.recordings] == [out]


def test_analyze_prints_tof_pixels_rounded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A calibrated TOF's principal point has many decimals; the table shows one."""
    import dataclasses

    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.storage.rigfile import save_rig
    from trifuse.calib.rig import Rig

    rig = default_rig()
    tof = rig["tof"]
    calibrated = dataclasses.replace(
        tof, intrinsics=dataclasses.replace(tof.intrinsics, cx=88.00229228, cy=71.20371737)
    )
    path = save_rig(tmp_path / "rig.yaml", Rig({**rig.sensors, "tof": calibrated}, "tof", rig.eyes))
    code, out, err = run(["analyze", str(path)], capsys)
    assert code == 0, err
    pixels = [line.split(")")[0] + ")" for line in out.splitlines() if line.startswith("(")]
    assert pixels[0] == "(88.0, 71.2)" and len(pixels) == 2
    assert re.fullmatch(r"\(\d+\.\d, 71\.2\)", pixels[1]), pixels  # the region 3 edge
    assert "88.002" not in out


# -- simulate calibration end to end ------------------------------------------------------


@pytest.mark.slow  # renders a simulated capture: about 6 s
def test_simulate_calibration_writes_a_capture(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenarios = pytest.importorskip(
        "trifuse.app.sources.sim.scenarios",
        reason="the simulator module trifuse.app.sources.sim.scenarios is not in this checkout yet",
    )
    from trifuse.app.sources.sim.head import default_rig, nominal_rig
    from trifuse.app.storage.capture import load_capture
    from trifuse.app.storage.ground_truth import load_ground_truth

    out = tmp_path / "captures"
    code, stdout, err = run(
        ["simulate", "calibration", "--views", "2", "--out", str(out), "--seed", "1"], capsys
    )
    assert code == 0, err
    assert "[1/2] view 0001" in stdout and "[2/2] view 0002" in stdout
    assert f"to {out}/" in stdout and "load_capture" in stdout
    (hint,) = [line for line in stdout.splitlines() if "load_capture;" in line]
    shown = subprocess.run(shlex.split(hint), capture_output=True, text=True, timeout=120)
    assert shown.returncode == 0 and ": 2 views" in shown.stdout, shown.stderr  # the hint works

    cap = load_capture(out, verify=True)
    assert cap.board == scenarios.CALIBRATION_BOARD
    assert cap.rig == nominal_rig()
    assert [v.name for v in cap.views] == ["0001", "0002"]
    five = ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
    for view in cap.views:
        assert sorted(view.sensors) == sorted(five)
        assert view.files["tof"].distance is not None
    frames = cap.views[0].frames()
    assert frames["ccd_left"].image.shape == (960, 1280, 3)
    assert frames["thermal_left"].image.shape == (288, 382)
    assert 250.0 < float(frames["thermal_left"].image.mean()) < 350.0  # kelvin
    assert frames["tof"].distance_m.shape == (144, 176)

    data = yaml.safe_load((out / "ground_truth.yaml").read_text())
    assert data["format"] == "trifuse-ground-truth/1"
    assert sorted(data["views"]) == ["0001", "0002"]
    gt = load_ground_truth(out)
    assert gt.rig == default_rig()
    assert gt.T_rig_board["0001"].shape == (4, 4)


# -- bench --------------------------------------------------------------------------------


def _fake(repeat: int) -> dict[str, float]:
    return {"ours_ms": 2.0 * repeat, "theirs_ms": 4.0 * repeat}


def test_bench_registry_and_ratios(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(
        bench.REGISTRY,
        "fake",
        bench.Benchmark("fake", "a fake benchmark", _fake, (("ours_ms", "theirs_ms"),), 3),
    )
    result = bench.run_benchmark("fake")
    assert result.repeat == 3 and result.figures == {"ours_ms": 6.0, "theirs_ms": 12.0}
    assert result.ratios == {"ours_ms / theirs_ms": 0.5}
    code, out, _ = run(["bench", "--only", "fake", "--repeat", "2"], capsys)
    assert code == 0
    assert "ours_ms = 4.000" in out and "ours_ms / theirs_ms = 0.500" in out
    with pytest.raises(ValueError, match="registered twice"):
        bench.register("fake", "again")(_fake)


def test_median_ms_excludes_warmup() -> None:
    calls: list[int] = []
    assert benchmark.median_ms(calls.append, 3, warmup=1) >= 0.0
    assert calls == [-1, 0, 1, 2]
    assert "render" in bench.REGISTRY


def test_nominal_rig_applies_to_any_rig() -> None:
    """``--rig`` derives its starting rig by the rule of ``head.nominal_rig``."""
    from trifuse.app.sources.sim.head import default_rig, nominal_rig
    from trifuse.calib.rig import Rig

    truth = default_rig()
    one_eye = Rig({n: truth[n] for n in ("tof", "ccd_left", "thermal_left")}, "tof")
    start = nominal_rig(one_eye)
    assert start.names == ["tof", "ccd_left", "thermal_left"]
    for name in start.names:
        assert not any(start[name].intrinsics.distortion)
        np.testing.assert_array_equal(start[name].T_rig_sensor[:3, :3], np.eye(3))
        mean_f = (truth[name].intrinsics.fx + truth[name].intrinsics.fy) / 2
        assert start[name].intrinsics.fx == start[name].intrinsics.fy == round(mean_f)


def test_serve_refuses_conflicting_sources(capsys) -> None:
    from trifuse.app.cli import main as cli_main

    assert cli_main(["serve", "--replay", "a.mcap", "--push"]) == 2
    assert "choose one of" in capsys.readouterr().err
    assert cli_main(["serve", "--live", "cams.yaml"]) == 2
    assert "--live needs --rig" in capsys.readouterr().err
