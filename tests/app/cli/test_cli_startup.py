"""``trifuse --help``, ``trifuse COMMAND --help`` and a refused argument import only what
the parser needs: no numpy, OpenCV, SciPy, fusion, calibration, recordings or simulator
(they took most of a second, four on a busy machine). The choices copied for it
(app.cli.choices) agree with the modules that own them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.support import ROOT, run_cli

HEAVY = (
    "numpy",
    "cv2",
    "scipy",
    "yaml",
    "av",
    "mcap",
    "uvicorn",
    "viser",
    "trifuse.fusion",
    "trifuse.calib",
    "trifuse.app.recording",
    "trifuse.app.sources",
    "trifuse.app.server",
    "trifuse.app.workflows",
    "trifuse.app.devtools",
    "importlib.metadata",
)

PROBE = """
import contextlib, io, json, sys
from trifuse.app.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    code = main(sys.argv[1:])
print(json.dumps([code, sorted(sys.modules)]))
"""


@pytest.mark.parametrize(
    "argv",
    [
        ["--help"],
        ["calibrate", "--help"],
        ["record", "--help"],
        ["map", "--help"],
        ["rig", "export", "--help"],
        ["calibrate", "cap", "--reprot", "r.json"],
        ["serve", "--port", "80000"],
        ["record", "--source", "sim", "--out", "o.mcap", "--scenario", "survy"],
    ],
    ids=" ".join,
)
def test_the_parser_imports_nothing_heavy(argv: list[str]) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    code, modules = json.loads(proc.stdout)
    assert code == (0 if "--help" in argv else 2)
    heavy = [m for m in modules if any(m == h or m.startswith(f"{h}.") for h in HEAVY)]
    assert heavy == []


def test_the_copied_choices_are_their_owners() -> None:
    from trifuse.app.cli import choices
    from trifuse.app.recording import map3d, open_source, pieces, simrecord
    from trifuse.calib import rig, rig_formats
    from trifuse.fusion import compose

    offline = tuple(m for m in compose.DISPLAY_MODES if m not in compose.CONSOLE_ONLY_MODES)
    assert choices.DISPLAY_MODES == offline
    assert choices.SIM_SCENARIOS == simrecord.SIM_SCENARIOS
    assert choices.SCENARIOS == open_source.SCENARIOS
    assert choices.POSE_MODES == map3d.POSE_MODES
    assert choices.MODALITIES == rig.MODALITIES
    assert choices.RIG_FORMATS == rig_formats.RIG_FORMATS
    assert choices.IMPORT_FORMATS == rig_formats.IMPORT_FORMATS
    assert choices.DEFAULT_CHUNK_S == pieces.DEFAULT_CHUNK_S


def test_bench_help_still_lists_the_benchmarks(capsys: pytest.CaptureFixture[str]) -> None:
    """The list needs the registry, which imports every benchmark: it is filled in when
    the help is shown, not when the parser is built."""
    from trifuse.app.devtools.bench import REGISTRY

    code, out, _ = run_cli(["bench", "--help"], capsys)
    assert code == 0
    listed = " ".join(out.split()).replace("- ", "-")  # argparse wraps the help
    assert all(f"{name} (" in listed for name in REGISTRY), listed


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    code, out, err = run_cli(["--version"], capsys)
    assert code == 0 and out == f"trifuse {version('trifuse')}\n" and err == ""
