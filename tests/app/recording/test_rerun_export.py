"""``trifuse fuse --rerun OUT.rrd`` (app/recording/rerun_export.py, app/recording/rerun_log.py) on a
recording of the simulated measurement scene (tests/measure_support.py: four panels of known
temperature at 2-9 m, imagers without offset), read back from the file with rerun's own
reader: every sensor's pose and pinhole are the rig's; the fused pictures are those `trifuse
fuse` writes; the TOF's points lie at the measured distances and are coloured by the
temperature the left thermal imager reads on each panel (the hot plate's 142.8 C apparent,
the paint's 42.3 C: FINDINGS "Object temperatures"), which checks the registration through
the rig; the colour image logged is undistorted onto K, as OpenCV undistorts it (rerun's
pinhole has no distortion). Refusals: an existing file, several recordings, no rerun-sdk:
one line, nothing written."""

from __future__ import annotations

import csv
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest

from tests.measure_support import panel_boxes, render
from tests.support import run_cli, write_recording
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.sim.head import default_rig
from trifuse.fusion.palettes import palette
from trifuse.fusion.span import auto_span

pytest.importorskip("rerun", reason="the [rerun] extra (in the test extra)")
from rerun.chunk import RrdReader

STEP_NS = 100_000_000
APPARENT_C = {"hot": 142.75, "paint": 42.29}  # the imager's mean on each panel (FINDINGS)


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict:
    """A recording of three frame sets of the scene, fused with --rerun; the file's rows
    per entity path (pyarrow record batches as lists of dicts)."""
    rig = default_rig()
    fs, truth = render()
    frames = [
        Frame(n, k * STEP_NS, fs.frames[n].image, fs.frames[n].distance_m)
        for k in range(3)
        for n in rig.names
    ]
    root = tmp_path_factory.mktemp("rerun")
    rec = write_recording(root / "scene.mcap", rig, frames)
    rrd = root / "scene.rrd"
    from trifuse.app.cli import main

    assert main(["fuse", str(rec), "--out", str(root / "fused"), "--rerun", str(rrd)]) == 0
    rows: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        columns = {  # timelines as int64 nanoseconds (pyarrow's datetimes stop at us)
            n: c.cast(pa.int64()) if pa.types.is_timestamp(c.type) else c
            for n, c in zip(batch.schema.names, batch.columns, strict=True)
        }
        rows[chunk.entity_path] += pa.table(columns).to_pylist()
    with (root / "fused" / "frames.csv").open() as f:
        pictures = list(csv.DictReader(f))
    return {"rig": rig, "fs": fs, "truth": truth, "rows": rows, "rrd": rrd, "rec": rec,
            "root": root, "pictures": pictures}  # fmt: skip


def _having(rows: dict[str, list[dict]], path: str, column: str) -> list[dict]:
    """The rows of ``path`` that hold ``column``, in the file's order: rerun's batcher
    writes an entity's components in chunks whose order depends on its flush timing."""
    return [r for r in rows[path] if r.get(column) is not None]


def _mat(column_major: list) -> np.ndarray:
    return np.asarray(column_major, dtype=np.float64).reshape(3, 3).T


def test_every_sensor_is_a_pinhole_at_its_pose(exported) -> None:
    rig, rows = exported["rig"], exported["rows"]
    [axes] = _having(rows, "/rig", "ViewCoordinates:xyz")
    assert axes["ViewCoordinates:xyz"] == [[3, 2, 5]]  # RDF: OpenCV's axes
    for name, s in rig.sensors.items():
        [pose] = _having(rows, f"/rig/{name}", "Transform3D:mat3x3")
        np.testing.assert_allclose(_mat(pose["Transform3D:mat3x3"][0]), s.T_rig_sensor[:3, :3],
                                   atol=1e-6)  # fmt: skip
        np.testing.assert_allclose(pose["Transform3D:translation"][0], s.T_rig_sensor[:3, 3],
                                   atol=1e-6)  # fmt: skip
        [pinhole] = _having(rows, f"/rig/{name}/image", "Pinhole:image_from_camera")
        np.testing.assert_allclose(_mat(pinhole["Pinhole:image_from_camera"][0]),
                                   s.intrinsics.K, rtol=1e-6)  # fmt: skip
        assert pinhole["Pinhole:resolution"][0] == list(s.image_size)


def test_the_fused_pictures_are_those_fuse_writes(exported) -> None:
    fused = _having(exported["rows"], "/fused", "EncodedImage:blob")
    stamps = sorted(r["sensor_time"] for r in fused)
    assert stamps == [int(p["stamp_ns"]) for p in exported["pictures"]] and len(stamps) >= 2
    jpeg = bytes(fused[0]["EncodedImage:blob"][0])
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (960, 2560, 3)


def test_the_cloud_lies_at_the_distances_and_shows_each_panels_temperature(exported) -> None:
    rig, fs, rows = exported["rig"], exported["fs"], exported["rows"]
    cloud = _having(rows, "/rig/tof/cloud", "Points3D:positions")[-1]
    points = np.asarray(cloud["Points3D:positions"], np.float64)
    colours = np.asarray(cloud["Points3D:colors"], np.uint32)
    d = fs.frames["tof"].distance_m
    assert 0.9 * np.isfinite(d).sum() < len(points) <= np.isfinite(d).sum()
    norms = np.linalg.norm(points, axis=1)  # radial: |P| is the distance measured
    measured = np.sort(d[np.isfinite(d)].astype(np.float64))
    k = np.clip(np.searchsorted(measured, norms), 1, len(measured) - 1)
    nearest = np.minimum(np.abs(measured[k] - norms), np.abs(measured[k - 1] - norms))
    assert nearest.max() <= 0.5e-3 + 1e-5  # recordings keep distances in 1 mm steps
    # each panel's points (those the left colour camera sees inside its box): their colour,
    # read back through the iron palette over the imagers' span, is the imager's reading
    T = rig.T("ccd_left", "tof")
    uv = rig["ccd_left"].intrinsics.project(points @ T[:3, :3].T + T[:3, 3])
    kelvin = [fs.frames[n].image for n in ("thermal_left", "thermal_right")]
    low, high = auto_span(kelvin, default=(273.15, 313.15))
    table = palette("iron").astype(np.int64)
    rgb = np.stack([(colours >> s) & 0xFF for s in (24, 16, 8)], axis=1).astype(np.int64)
    index = np.argmin(((rgb[:, None, :] - table[None]) ** 2).sum(-1), axis=1)
    celsius = low + index * (high - low) / 255 - 273.15
    boxes = panel_boxes(exported["truth"])
    for name, want in APPARENT_C.items():
        (x0, y0), (x1, y1) = boxes[name]
        inside = (uv[:, 0] >= x0) & (uv[:, 0] <= x1) & (uv[:, 1] >= y0) & (uv[:, 1] <= y1)
        assert inside.sum() > 20, name
        step = (high - low) / 255
        assert abs(np.median(celsius[inside]) - want) < 1.0 + step, (name, step)


def test_the_colour_image_is_undistorted_onto_its_pinhole(exported) -> None:
    rig, fs, rows = exported["rig"], exported["fs"], exported["rows"]
    s = rig["ccd_left"]
    logged = _having(rows, "/rig/ccd_left/image", "EncodedImage:blob")[-1]
    image = cv2.imdecode(np.frombuffer(bytes(logged["EncodedImage:blob"][0]), np.uint8),
                         cv2.IMREAD_COLOR)[..., ::-1]  # fmt: skip
    original = fs.frames["ccd_left"].image
    reference = cv2.undistort(original, s.intrinsics.K, s.intrinsics.dist)
    inner = (slice(40, -40), slice(40, -40))  # the remap's and undistort's borders differ
    diff = np.abs(image.astype(int) - reference.astype(int))[inner].mean()
    moved = np.abs(image.astype(int) - original.astype(int))[inner].mean()
    assert diff < 2.0 < 3 * diff < moved, (diff, moved)  # JPEG's error; the distortion's


def test_refusals_are_one_line_and_write_nothing(exported, tmp_path, capsys, monkeypatch) -> None:
    rec, rrd = exported["rec"], exported["rrd"]
    before = rrd.read_bytes()
    code, _, err = run_cli(["fuse", str(rec), "--out", str(tmp_path / "a"), "--rerun", str(rrd)],
                           capsys)  # fmt: skip
    assert code != 0 and "exists; refusing to overwrite it" in err
    assert rrd.read_bytes() == before and not (tmp_path / "a").exists()
    other = tmp_path / "other.mcap"
    other.write_bytes(rec.read_bytes())
    code, _, err = run_cli(["fuse", str(rec), str(other), "--out", str(tmp_path / "b"),
                            "--rerun", str(tmp_path / "b.rrd")], capsys)  # fmt: skip
    assert code != 0 and "--rerun: takes one recording, got 2" in err
    monkeypatch.setitem(sys.modules, "rerun", None)  # the extra not installed
    out_rrd = tmp_path / "c.rrd"
    code, _, err = run_cli(["fuse", str(rec), "--out", str(tmp_path / "c"), "--rerun",
                            str(out_rrd)], capsys)  # fmt: skip
    assert code != 0 and "pip install -e '.[rerun]'" in err
    assert len(err.strip().splitlines()) == 1
    assert not out_rrd.exists() and not (tmp_path / "c").exists()
    assert not list(Path(tmp_path).glob(".*.tmp"))


def test_the_thermal_map_of_the_recording_ends_the_file(exported) -> None:
    """The recording holds no head pose: the map's poses are estimated from the TOF clouds;
    the head stood still (three sets of one render), so the rig stays at the world's origin
    (the first frame's rig frame) and the map's voxels lie at the TOF's distances, coloured."""
    rows = exported["rows"]
    [cloud] = _having(rows, "/map", "Points3D:positions")
    points = np.asarray(cloud["Points3D:positions"], np.float64)
    distance = np.linalg.norm(points, axis=1)
    d = exported["fs"].frames["tof"].distance_m
    assert len(points) > 1000
    assert np.nanmin(d) - 0.05 < distance.min() and distance.max() < np.nanmax(d) + 0.05
    pose = _having(rows, "/rig", "Transform3D:translation")[0]
    assert np.linalg.norm(pose["Transform3D:translation"][0]) < 0.01
    assert len(_having(rows, "/map/path", "LineStrips3D:strips")[0]["LineStrips3D:strips"][0]) >= 2
