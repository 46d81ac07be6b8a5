"""``trifuse rig export`` / ``trifuse rig import`` (app/cli/rig.py, issue 21): round trips
through the files, what is printed as lost, refusals to overwrite, bad formats and files."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.support import run_cli
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.camera import Intrinsics
from trifuse.calib.rig import Rig, Sensor

EYES_ARG = "left=ccd_left:thermal_left,right=ccd_right:thermal_right"


def assert_same_rig(got: Rig, want: Rig, tol: float = 1e-9) -> None:
    assert got.names == want.names and got.reference == want.reference
    assert got.eyes == want.eyes
    for name in want.names:
        g, w = got[name], want[name]
        assert (g.modality, g.image_size, g.intrinsics) == (w.modality, w.image_size, w.intrinsics)
        np.testing.assert_allclose(g.T_rig_sensor, w.T_rig_sensor, atol=tol, err_msg=name)


def snapshot(root: Path) -> list[tuple[Path, bytes]]:
    return sorted(
        (p.relative_to(root), p.read_bytes() if p.is_file() else b"") for p in root.rglob("*")
    )


@pytest.fixture
def rig_file(tmp_path: Path) -> Path:
    return save_rig(tmp_path / "rig.yaml", default_rig())


def one_error_line(code: int, out: str, err: str) -> str:
    assert code == 2 and out == "", (code, out, err)
    assert err.startswith("trifuse") and len(err.strip().splitlines()) == 1, err
    return err


# -- kalibr round trip --------------------------------------------------------------------------


def test_kalibr_round_trip_through_the_command_line(
    rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "kalibr"
    code, out, err = run_cli(
        ["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(out_dir)], capsys
    )
    assert code == 0 and err == ""
    assert [p.name for p in out_dir.iterdir()] == ["camchain.yaml"]
    assert f"wrote {out_dir / 'camchain.yaml'}" in out
    assert "not in the kalibr files:" in out
    assert "  - eyes (left: ccd_left + thermal_left, right: ccd_right + thermal_right)" in out
    assert list(yaml.safe_load((out_dir / "camchain.yaml").read_text())) == [
        f"cam{i}" for i in range(5)
    ]

    rig_out = tmp_path / "back.yaml"
    code, out, err = run_cli(
        ["rig", "import", str(out_dir), "--format", "kalibr", "--out", str(rig_out),
         "--eyes", EYES_ARG],
        capsys,
    )  # fmt: skip
    assert code == 0 and err == ""
    assert f"written to {rig_out}" in out and "reference tof" in out
    assert "not in the files:" in out and "range_correction of tof" in out
    assert_same_rig(load_rig(rig_out), default_rig())


def test_export_to_a_file_name_and_import_of_that_file(
    rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    chain = tmp_path / "head-camchain.yaml"
    code, out, _ = run_cli(
        ["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(chain)], capsys
    )
    assert code == 0 and chain.is_file() and f"wrote {chain}" in out
    code, out, _ = run_cli(
        ["rig", "import", str(chain), "--format", "kalibr", "--out", str(tmp_path / "r.yaml"),
         "--reference", "thermal_left", "--names", "0=tof_main",
         "--modalities", "tof_main=tof"],
        capsys,
    )  # fmt: skip
    assert code == 0, out
    rig = load_rig(tmp_path / "r.yaml")
    assert rig.reference == "thermal_left" and rig.names[0] == "tof_main"
    assert rig["tof_main"].modality == "tof" and rig.eyes == {}
    assert "eyes: a camchain has none" in out
    want = default_rig()
    np.testing.assert_allclose(
        rig.T("tof_main", "ccd_right"), want.T("tof", "ccd_right"), atol=1e-12
    )


def k3_rig_file(path: Path) -> Path:
    rig = default_rig()
    s = rig["thermal_left"]
    i = s.intrinsics
    intr = Intrinsics(i.fx, i.fy, i.cx, i.cy, (*i.distortion[:4], 0.05))
    return save_rig(path, rig.with_sensor(Sensor(s.name, s.modality, s.image_size, intr,
                                                 s.T_rig_sensor)))  # fmt: skip


def test_a_dropped_k3_is_printed_and_strict_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = k3_rig_file(tmp_path / "k3.yaml")
    argv = ["rig", "export", str(rig), "--format", "kalibr", "--out", str(tmp_path / "o")]
    err = one_error_line(*run_cli([*argv, "--strict"], capsys))
    assert "thermal_left" in err and "k3 = 0.05" in err and "0.855 px" in err
    assert not (tmp_path / "o").exists()
    code, out, _ = run_cli(argv, capsys)
    assert code == 0
    assert "  - distortion of thermal_left: Kalibr's radtan has only k1 k2 p1 p2; k3 = 0.05 " in out
    assert "(0, 287) by 0.855 px" in out


# -- refusals -----------------------------------------------------------------------------------


def test_never_overwrites_without_force(
    rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir, chain, rig_out = tmp_path / "k", tmp_path / "c.yaml", tmp_path / "back.yaml"
    assert run_cli(["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(out_dir)],
                   capsys)[0] == 0  # fmt: skip
    assert run_cli(["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(chain)],
                   capsys)[0] == 0  # fmt: skip
    imp = ["rig", "import", str(chain), "--format", "kalibr", "--out", str(rig_out)]
    assert run_cli(imp, capsys)[0] == 0
    (out_dir / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    for argv, flag in [
        (["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(out_dir)], "--out"),
        (["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(chain)], "--out"),
        (["rig", "export", "missing.yaml", "--format", "kalibr", "--out", str(chain)], "--out"),
        (imp, "--out"),
        (["rig", "import", "missing", "--format", "kalibr", "--out", str(rig_out)], "--out"),
    ]:
        err = one_error_line(*run_cli(argv, capsys))
        assert err.startswith(f"trifuse: error: {flag} {tmp_path}/") and "refusing to" in err
    assert snapshot(tmp_path) == before

    # --force replaces what it writes, and only that
    (out_dir / "camchain.yaml").write_text("old")
    code, _, _ = run_cli(
        ["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(out_dir), "--force"],
        capsys,
    )
    assert code == 0 and (out_dir / "notes.txt").read_text() == "mine"
    assert (out_dir / "camchain.yaml").read_text() == chain.read_text()
    rig_out.write_text("old")
    assert run_cli([*imp, "--force"], capsys)[0] == 0
    want = default_rig()
    assert_same_rig(load_rig(rig_out), Rig(want.sensors, want.reference))  # no --eyes


def test_never_overwrites_what_it_reads_even_with_force(
    rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = rig_file.read_bytes()
    err = one_error_line(*run_cli(["rig", "export", str(rig_file), "--format", "kalibr",
                                   "--out", str(rig_file), "--force"], capsys))  # fmt: skip
    assert "is the rig file read" in err
    chain = tmp_path / "c.yaml"
    run_cli(["rig", "export", str(rig_file), "--format", "kalibr", "--out", str(chain)], capsys)
    err = one_error_line(*run_cli(["rig", "import", str(chain), "--format", "kalibr",
                                   "--out", str(chain), "--force"], capsys))  # fmt: skip
    assert "is a file read" in err
    assert rig_file.read_bytes() == before and chain.read_text().startswith("cam0:")


# -- bad arguments and bad files ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["rig"], "trifuse rig: expected a command"),
        (["rig", "export", "r.yaml", "--format", "bogus", "--out", "o"], "invalid choice: 'bogus'"),
        (["rig", "import", "p", "--format", "urdf", "--out", "r.yaml"], "invalid choice: 'urdf'"),
        (["rig", "export", "r.yaml", "--out", "o"], "required: --format"),
        (["rig", "import", "p", "--format", "kalibr", "--out", "r.yaml", "--eyes", "left=a"],
         "expected EYE=COLOR:THERMAL"),
        (["rig", "import", "p", "--format", "kalibr", "--out", "r.yaml", "--names", "a=b"],
         "expected INDEX=NAME"),
        (["rig", "import", "p", "--format", "kalibr", "--out", "r.yaml", "--modalities",
          "a=sonar"], "with MODALITY one of color, thermal, tof"),
        (["rig", "import", "p", "--format", "kalibr", "--out", "r.yaml", "--names", "0=a,0=b"],
         "0 given twice"),
    ],
)  # fmt: skip
def test_bad_arguments(argv: list[str], match: str, capsys: pytest.CaptureFixture[str]) -> None:
    err = one_error_line(*run_cli(argv, capsys))
    assert match in err


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        ("chain.yaml", b"cam0: [1, 2\n", "chain.yaml: not valid YAML"),
        ("chain.yaml", b"format: trifuse-rig/1\n", "chain.yaml: key 'format': expected only cam0"),
        ("chain.yaml", b"\xff\xfe cam0", "chain.yaml: file is not UTF-8 text"),
        ("chain.yaml", b"cam0:\n  camera_model: pinhole\n  distortion_model: equidistant\n"
         b"  distortion_coeffs: [0, 0, 0, 0]\n  intrinsics: [400.0, 400.0, 320.0, 240.0]\n"
         b"  resolution: [640, 480]\n  rostopic: /cam0/image_raw\n",
         "chain.yaml: cam0.distortion_model: 'equidistant' cannot be imported"),
    ],
)  # fmt: skip
def test_bad_files_are_one_line_and_write_nothing(
    name: str, content: bytes, match: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / name).write_bytes(content)
    out_rig = tmp_path / "r.yaml"
    err = one_error_line(*run_cli(
        ["rig", "import", str(tmp_path / name), "--format", "kalibr", "--out", str(out_rig)],
        capsys))  # fmt: skip
    assert match in err and err.startswith("trifuse: error: ")
    assert not out_rig.exists()


def test_bad_paths(rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    for argv, match in [
        (["rig", "import", str(tmp_path / "nope"), "--format", "kalibr", "--out",
          str(tmp_path / "r.yaml")], "nope: no such file or directory"),
        (["rig", "import", str(tmp_path / "empty"), "--format", "kalibr", "--out",
          str(tmp_path / "r.yaml")], "a directory without .yaml, .yml, .urdf, .xml files"),
        (["rig", "import", str(rig_file), "--format", "kalibr", "--out", str(tmp_path)],
         "a directory; expected a rig file name"),
        (["rig", "export", str(tmp_path / "nope.yaml"), "--format", "kalibr", "--out",
          str(tmp_path / "o")], "nope.yaml: cannot read rig file"),
    ]:  # fmt: skip
        assert match in one_error_line(*run_cli(argv, capsys))
    assert not (tmp_path / "r.yaml").exists() and not (tmp_path / "o").exists()


# -- the other formats, where they exist --------------------------------------------------------

HAVE = {f: importlib.util.find_spec(f"trifuse.calib.rig_formats.{f}_format") is not None
        for f in ("ros", "opencv", "urdf")}  # fmt: skip


@pytest.mark.parametrize("fmt", ["ros", "opencv"])
def test_other_formats_round_trip_through_the_command_line(
    fmt: str, rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if not HAVE[fmt]:
        pytest.skip(f"calib/rig_formats/{fmt}_format.py is not there yet")
    out_dir = tmp_path / fmt
    code, out, _ = run_cli(
        ["rig", "export", str(rig_file), "--format", fmt, "--out", str(out_dir)], capsys
    )
    assert code == 0 and len(list(out_dir.iterdir())) >= 5 and f"not in the {fmt} files" in out
    rig_out = tmp_path / "back.yaml"
    code, out, _ = run_cli(
        ["rig", "import", str(out_dir), "--format", fmt, "--out", str(rig_out), "--eyes",
         EYES_ARG], capsys)  # fmt: skip
    assert code == 0, out
    assert_same_rig(load_rig(rig_out), default_rig())
    # an option the format does not take is refused by name
    err = one_error_line(*run_cli(
        ["rig", "import", str(out_dir), "--format", fmt, "--out", str(tmp_path / "x.yaml"),
         "--names", "0=a"], capsys))  # fmt: skip
    assert f"--names: the {fmt} format does not take it" in err


def test_urdf_export(rig_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    if not HAVE["urdf"]:
        pytest.skip("calib/rig_formats/urdf_format.py is not there yet")
    target = tmp_path / "head.urdf"
    code, out, _ = run_cli(
        ["rig", "export", str(rig_file), "--format", "urdf", "--out", str(target)], capsys
    )
    assert code == 0 and target.read_text().lstrip().startswith("<")
    assert f"wrote {target}" in out
