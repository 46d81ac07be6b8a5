"""``trifuse map`` end to end (issue 20): a short simulated survey recorded with the head's
pose, mapped into a PLY (read back by plyfile) whose points lie on the scene's true
surfaces with the temperatures an ideal imager reads there, and a map file that loads;
outputs never overwritten without --force; bad input refused in one line."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from tests.support import small_rig, synth_frames, write_recording
from trifuse.app.cli import main
from trifuse.app.recording import RecordingWriter, ReplaySource
from trifuse.app.recording.poses import read_poses
from trifuse.app.sources.sim.inspection import inspection_scene
from trifuse.app.storage.map_file import load_map, read_map_info
from trifuse.app.storage.rigfile import save_rig
from trifuse.fusion.mapping import TofGrid

SURVEY_S = 3.0
VOXEL = 0.037
"""37 mm: no multiple of it (or of half of it) meets the room's walls (at 3.5 m, 1.1 m,
8.2 m...), so voxel centres do not sit on them, or half a voxel off, by chance."""


@pytest.fixture(scope="module")
def survey(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first 3 s of the survey (the head pans 45 degrees left) recorded from the
    simulated head at a tenth of the real resolutions (44 x 36 TOF pixels, 45 frames):
    ``trifuse record --source sim --scenario survey``, about half a second."""
    d = tmp_path_factory.mktemp("survey")
    rig_path = save_rig(d / "rig.yaml", small_rig())
    out = d / "survey.mcap"
    argv = ["record", "--source", "sim", "--scenario", "survey", "--duration", str(SURVEY_S)]
    assert main([*argv, "--rig", str(rig_path), "--seed", "3", "--out", str(out)]) == 0
    return out


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def tof_error_m(path: Path) -> np.ndarray:
    """Distance (m) of every TOF point of the recording, placed by its recorded pose, from
    the nearest true surface: the error the TOF itself brings (the simulated TOF has no
    range calibration here: a bias of 31 mm, wiggling, a bowl towards the corners)."""
    poses = read_poses(path)
    assert poses is not None
    scene = inspection_scene()
    out = []
    with ReplaySource(path, realtime=False) as src:
        grid = TofGrid(src.rig, "tof")
        for f in src.frames():
            if f.sensor != "tof" or f.distance_m is None:
                continue
            p = grid.points(f.distance_m, 0.05).reshape(-1, 3).astype(np.float64)
            p = p[np.isfinite(p).all(axis=1)]
            T = poses.at(f.stamp_ns)
            assert T is not None
            out.append(scene.nearest_surface(p @ T[:3, :3].T + T[:3, 3])[0])
    return np.concatenate(out)


def test_the_map_lies_on_the_true_surfaces_with_their_temperatures(
    survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ply_path = tmp_path / "room.ply"
    code, out, err = run(
        ["map", str(survey), "--out", str(ply_path), "--voxel", str(VOXEL)], capsys
    )
    assert code == 0, err
    assert "Mapped 45 of 45 TOF frames" in out and "the recordings' poses (world -> rig)" in out
    assert "occupied" in out and "extent of the occupied: x " in out
    assert f"Wrote {ply_path}" in out and "room.map.npz" in out
    assert "Traceback" not in err and "45/45 frames" in err  # the progress bar

    v = PlyData.read(str(ply_path))["vertex"].data
    points = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    assert len(points) > 5000
    scene = inspection_scene()
    dist, index, nearest = scene.nearest_surface(points)
    # A voxel's centre lies within half its diagonal of a surface through it; a plane at a
    # random offset gives a median of a quarter edge. On top comes the TOF's own error
    # (its points' median distance from the surfaces, about 36 mm uncalibrated): the map
    # may add no more than the quarter voxel to it (a wrong pose, frame or axis would add
    # decimetres), and no voxel centre lies further from a surface than the TOF's 95th
    # percentile plus a voxel diagonal.
    tof = tof_error_m(survey)
    assert np.median(dist) < np.median(tof) + VOXEL / 4
    assert np.percentile(dist, 90) < np.percentile(tof, 95) + VOXEL * np.sqrt(3)
    names = {scene.solids[k].name for k in np.unique(index)}
    assert {"wall_back", "floor", "person_body"} <= names
    # Temperatures (degrees Celsius) against what an ideal imager reads there: the
    # imagers' offsets (+-0.75 K, opposite) average out where both eyes see a voxel, the
    # noise (NETD 0.08 K) over its points and frames; voxels at an edge mix two surfaces
    # (the tail). The TOF sees wider than the thermal imagers: a fifth of its view, at the
    # sides, has no temperature.
    seen = np.isfinite(v["temperature"])
    assert seen.mean() > 0.7
    truth_c = scene.apparent_temperature_k(index, nearest) - 273.15
    err_c = v["temperature"][seen] - truth_c[seen]
    assert abs(np.median(err_c)) < 0.1 and np.median(np.abs(err_c)) < 0.15
    assert (v["temperature_max"][seen] >= v["temperature"][seen] - 1e-4).all()
    assert (v["observations"] >= 2).mean() > 0.9  # occupied: hit in two frames or more
    assert ((v["red"] != 128) | (v["green"] != 128)).mean() > 0.5  # colour where seen

    m = load_map(tmp_path / "room.map.npz")
    assert m.settings.voxel_m == VOXEL and m.occupied().sum() == len(points)
    np.testing.assert_array_equal(m["centre"][m.occupied()], points.astype(np.float32))
    assert len(m.path) == 45
    info = read_map_info(tmp_path / "room.map.npz")
    assert info["pose_source"] == "recording" and info["recordings"] == [str(survey)]


def test_outputs_are_refused_unless_forced(
    survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ply, npz = tmp_path / "m.ply", tmp_path / "other.npz"
    base = ["map", str(survey), "--out", str(ply), "--map-file", str(npz), "--voxel", "0.1"]
    npz.write_bytes(b"precious")
    code, out, err = run(base, capsys)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1
    assert err.startswith(f"trifuse: error: --map-file {npz}: exists; refusing to overwrite")
    assert "--force" in err and npz.read_bytes() == b"precious" and not ply.exists()
    code, out, err = run([*base, "--force"], capsys)
    assert code == 0, err
    assert len(load_map(npz)) > 0 and len(PlyData.read(str(ply))["vertex"].data) > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply", "other.npz"]  # no temps
    code, _, err = run(base, capsys)
    assert code == 2 and f"--out {ply}: exists" in err
    # never a recording, not even with --force
    copy = shutil.copy(survey, tmp_path / "copy.mcap")
    before = Path(copy).read_bytes()
    code, _, err = run(["map", str(copy), "--out", str(copy), "--force"], capsys)
    assert code == 2 and "is one of the recordings" in err and Path(copy).read_bytes() == before
    code, _, err = run(["map", str(survey), "--out", str(ply), "--map-file", str(ply)], capsys)
    assert code == 2 and "the same file as --out" in err


def test_a_directory_maps_every_recording_in_it_and_pose_modes(
    survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A directory: every .mcap in it. A recording without poses is estimated (auto), is
    refused with --pose recording, and may not be mixed with one that has poses."""
    rig = small_rig()
    folder = tmp_path / "recs"
    folder.mkdir()
    shutil.copy(survey, folder / "a.mcap")
    # the survey again without its poses: its frames re-written
    bare = folder / "b.mcap"
    with ReplaySource(survey, realtime=False) as src, RecordingWriter(bare, rig) as w:
        for f in src.frames():
            w.write(f)
    assert read_poses(bare) is None
    (folder / "notes.txt").write_text("not a recording")

    code, _, err = run(["map", str(folder), "--out", str(tmp_path / "x.ply")], capsys)
    assert code == 2 and "b.mcap: no head poses" in err and "--pose estimate" in err
    code, out, err = run(
        ["map", str(folder), "--out", str(tmp_path / "x.ply"), "--pose", "estimate"], capsys
    )
    assert code == 0, err
    assert "Mapped 90 of 90 TOF frames" in out and "estimated from the TOF clouds" in out
    assert read_map_info(tmp_path / "x.map.npz")["recordings"] == [
        str(folder / "a.mcap"),
        str(bare),
    ]
    code, out, err = run(["map", str(bare), "--out", str(tmp_path / "y.ply")], capsys)
    assert code == 0 and "estimated from the TOF clouds" in out, err
    code, _, err = run(
        ["map", str(bare), "--out", str(tmp_path / "z.ply"), "--pose", "recording"], capsys
    )
    assert code == 2 and "no head poses in the recording" in err


def test_bad_input_is_one_line_and_exit_2(
    survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = small_rig()
    no_tof = write_recording(
        tmp_path / "no_tof.mcap",
        rig,
        [f for f in synth_frames(rig, 0.2, seed=1) if f.sensor != "tof"],
    )
    text = tmp_path / "text.mcap"
    text.write_text("not a recording")
    empty = tmp_path / "empty"
    empty.mkdir()
    out_ply = str(tmp_path / "out.ply")
    cases = [
        ([str(tmp_path / "missing.mcap")], "missing.mcap: no such recording"),
        ([str(text)], "not an MCAP file"),
        ([str(no_tof)], "no TOF distances of 'tof' in the recording"),
        ([str(empty)], "a directory without recordings"),
        ([str(survey), "--voxel", "0"], "expected a positive number"),
        ([str(survey), "--voxel", "0.00001"], "max_extent_m / voxel_m"),
        ([str(survey), "--rig", str(text)], "--rig"),
        ([str(survey), "--pose", "guess"], "invalid choice"),
    ]
    for args, message in cases:
        code, _, err = run(["map", *args, "--out", out_ply], capsys)
        assert code == 2, (args, err)
        assert message in err and len(err.strip().splitlines()) == 1, (args, err)
        assert "Traceback" not in err and err.startswith("trifuse"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "no_tof.mcap", "text.mcap"]


@pytest.mark.parametrize("damage", ["killed", "cut short"])
def test_a_damaged_recording_is_mapped_as_fuse_and_record_read_it(
    survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str
) -> None:
    """Issues 29 and 33: a recording left by a killed ``record`` (sealed, no summary
    section) or cut short. ``map`` reads it as ``fuse`` and ``record --source replay:`` do
    (it used to say "no TOF distances ... nothing to map"): it maps every TOF frame before
    the damage and names the damage in the same words."""
    bad = tmp_path / "bad.mcap"
    if damage == "killed":  # what a SIGKILL leaves: the file as sealed up to then
        poses = read_poses(survey)
        assert poses is not None
        with ReplaySource(survey, realtime=False) as src:
            assert src.rig is not None
            w = RecordingWriter(tmp_path / "never.mcap", src.rig)
            k = 0
            for f in src.frames():
                if f.stamp_ns - src.start_ns > 1.2e9:
                    break
                while k < len(poses) and poses.stamps_ns[k] <= f.stamp_ns:
                    w.write_pose(int(poses.stamps_ns[k]), poses.T_world_rig[k])
                    k += 1
                w.write(f)
            w.seal()
            shutil.copy(w.temp_path, bad)
            w.abort()
        said = "not finished"
    else:
        data = survey.read_bytes()
        bad.write_bytes(data[: len(data) * 2 // 5])
        said = "truncated"
    with ReplaySource(bad, realtime=False, on_damage="stop") as src:
        assert src.index.indexed_by == "scan" and src.message_count("tof", "tof_distance") is None
        tof = sum(f.sensor == "tof" and f.distance_m is not None for f in src.frames())
        assert src.damage is not None and said in str(src.damage)
        named = str(src.damage)
    assert 10 <= tof < 45

    code, out, err = run(["map", str(bad), "--out", str(tmp_path / "m.ply")], capsys)
    assert code == 0, err
    assert f"Mapped {tof} of {tof} TOF frames" in out
    assert f"trifuse: warning: {named}; the frames before it were mapped" in err
    code, out, err = run(["fuse", str(bad), "--out", str(tmp_path / "f")], capsys)
    assert code == 0, err
    assert f"trifuse: warning: {named}; the frames before it were fused" in err
    again = tmp_path / "again.mcap"
    code, out, err = run(["record", "--source", f"replay:{bad}", "--out", str(again)], capsys)
    assert code == 0, err
    assert f"trifuse: warning: {named}; the frames before it were recorded" in err


def test_the_map_in_a_rerun_file_is_the_maps_voxels_path_and_pose(
    survey: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--rerun OUT.rrd``: read back with rerun's reader, the map's points are the PLY's
    voxel centres, the path is the recorded poses' positions and the rig sits at the last
    recorded pose; an existing file is refused in one line before anything is mapped."""
    pytest.importorskip("rerun", reason="the [rerun] extra (in the test extra)")
    from rerun.chunk import RrdReader

    ply_path, rrd = tmp_path / "room.ply", tmp_path / "room.rrd"
    argv = ["map", str(survey), "--out", str(ply_path), "--voxel", str(VOXEL), "--rerun", str(rrd)]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert f"Rerun: {rrd}" in out
    rows: dict[str, dict] = {}
    for chunk in RrdReader(rrd).stream():
        for row in (
            chunk.to_record_batch()
            .drop_columns(
                [
                    n
                    for n in chunk.to_record_batch().schema.names
                    if n in ("log_time", "sensor_time")
                ]
            )
            .to_pylist()
        ):
            rows.setdefault(chunk.entity_path, {}).update(row)
    v = PlyData.read(str(ply_path))["vertex"].data
    ply = np.stack([v["x"], v["y"], v["z"]], axis=1)
    got = np.asarray(rows["/map"]["Points3D:positions"], np.float32)
    order = np.lexsort(got.T), np.lexsort(ply.T)
    np.testing.assert_array_equal(got[order[0]], ply[order[1]])
    poses = read_poses(survey)
    assert poses is not None
    with ReplaySource(survey, realtime=False) as src:
        stamps = [f.stamp_ns for f in src.frames() if f.sensor == "tof"]
    want = np.array([poses.at(s)[:3, 3] for s in stamps])
    [strip] = rows["/map/path"]["LineStrips3D:strips"]
    np.testing.assert_allclose(np.asarray(strip), want, atol=1e-5)
    last = poses.at(stamps[-1])  # world -> rig (the rig frame is the TOF's)
    np.testing.assert_allclose(rows["/rig"]["Transform3D:translation"][0], last[:3, 3], atol=1e-5)
    assert rows["/rig/tof"]["Transform3D:translation"] == [[0.0, 0.0, 0.0]]
    again = ["map", str(survey), "--out", str(tmp_path / "b.ply"), "--rerun", str(rrd)]
    code, _, err = run(again, capsys)  # the rerun file exists now
    assert code == 2 and f"--rerun {rrd}: exists; refusing to overwrite it" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "b.ply").exists()
