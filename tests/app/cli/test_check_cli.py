"""``trifuse check`` end to end (issue 34 item 3): a recording of the simulated inspection
room in which the left thermal imager sits turned 0.3 degrees about its y axis
(``trifuse record --source sim --drift``, every frame turned to its own instant as the live
recording does) is checked against the calibrated rig it stores: thermal_left ``drifted``
within 0.1 degrees of the truth the recording's metadata gives, exit 3, the JSON the issue
names; ``--refine`` writes the corrected rig (never over another file), with which the same
recording checks clean; a rig without a TOF gets ``undecided`` with the reason, never a
guess. The full resolution: at half of it a thermal imager's 0.3 degrees is one pixel and
the check misreads the others by up to 0.2 degrees (measured)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from trifuse.app.cli import main
from trifuse.app.recording import ReplaySource
from trifuse.app.sources.sim.drift import SensorDrift, moved_rig
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import invert, rotation_angle_deg

pytestmark = pytest.mark.slow

TURN = (0.0, 0.3, 0.0)


@pytest.fixture(scope="module")
def drifted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2 s of the inspection room, thermal_left turned from the start (about 30 s of
    rendering on an idle 2-core machine)."""
    out = tmp_path_factory.mktemp("check") / "drifted.mcap"
    argv = ["record", "--source", "sim", "--duration", "2", "--pose-hz", "2", "--seed", "4"]
    assert main([*argv, "--drift", "thermal_left:0,0.3,0", "--out", str(out)]) == 0
    return out


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def truth() -> Rig:
    return moved_rig(default_rig(), SensorDrift("thermal_left", TURN))


def test_a_turned_thermal_imager_is_found_and_the_refined_rig_checks_clean(
    drifted: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    refined_path = tmp_path / "refined.yaml"
    code, out, err = run(
        ["check", str(drifted), "--every-s", "0.2", "--json", "--refine", str(refined_path)],
        capsys,
    )
    assert code == 3, err
    result = json.loads(out[: out.rindex("}") + 1])
    sensors = result["sensors"]
    assert set(sensors) == set(default_rig().names)
    tl = sensors["thermal_left"]
    assert tl["verdict"] == "drifted", result
    assert np.linalg.norm(np.subtract(tl["rotation_deg"], TURN)) < 0.1, tl
    assert len(tl["sigma_deg"]) == 3 and max(tl["sigma_deg"]) < 0.05, tl
    for name in ("tof", "ccd_left", "ccd_right", "thermal_right"):
        assert sensors[name]["verdict"] != "drifted", sensors[name]
    assert f"rig with the drift of thermal_left corrected written to {refined_path}" in out
    # the refined rig: thermal_left within 0.1 degrees of where the simulator put it
    refined, true = load_rig(refined_path), truth()
    R = refined["thermal_left"].T_rig_sensor[:3, :3].T @ true["thermal_left"].T_rig_sensor[:3, :3]
    assert rotation_angle_deg(R) < 0.1
    # the recording holds the calibrated rig: the one checked by default
    with ReplaySource(drifted, realtime=False) as src:
        assert src.rig == default_rig()
    # checked again with the refined rig: nothing drifted, exit 0
    code, out, err = run(
        ["check", str(drifted), "--rig", str(refined_path), "--every-s", "0.2"], capsys
    )
    assert code == 0, out + err
    assert "DRIFTED" not in out and "thermal_left   ok" in out, out
    # --refine never overwrites another file
    code, out, err = run(["check", str(drifted), "--refine", str(refined_path)], capsys)
    assert code == 2 and "exists; refusing to overwrite" in err


def test_a_rig_without_a_tof_is_undecided_with_the_reason(
    drifted: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = default_rig()
    base = invert(rig["ccd_left"].T_rig_sensor)  # the new reference's frame is the rig's
    sensors = {
        n: dataclasses.replace(s, T_rig_sensor=base @ s.T_rig_sensor)
        for n, s in rig.sensors.items()
        if n != "tof"
    }
    no_tof = dataclasses.replace(rig, sensors=sensors, reference="ccd_left")
    path = save_rig(tmp_path / "no-tof.yaml", no_tof)
    code, out, err = run(["check", str(drifted), "--rig", str(path), "--json"], capsys)
    assert code == 0, err
    sensors = json.loads(out)["sensors"]
    for name, s in sensors.items():
        assert s["verdict"] == "undecided" and s["rotation_deg"] is None, (name, s)
        assert "no TOF in the rig" in s["reason"], (name, s)
