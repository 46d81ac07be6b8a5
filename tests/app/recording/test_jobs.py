"""Offline jobs in pieces (issue 22) without Ray: the plan from the MCAP message index,
split runs against unsplit ones, several recordings, storage schemes, and the commands
without the [ray] extra."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import directory_bytes, record_survey_archive, small_rig
from trifuse.app.cli import main
from trifuse.app.recording import ReplaySource
from trifuse.app.recording.fuse import FusedWriter, PieceEnd, fuse_piece
from trifuse.app.recording.jobs import LocalRunner, plan_fuse_job, run_fuse_job, run_map_job
from trifuse.app.recording.map3d import open_recordings
from trifuse.app.recording.pieces import FusePiece, plan_fuse, plan_map, ranges
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.voxel_map import MapSettings

DURATION_S = 3.0


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two 3 s recordings of the simulated survey (the head pans) at a tenth of the real
    resolutions: 90 colour frame sets and 45 TOF frames each, with the head's poses."""
    return record_survey_archive(tmp_path_factory.mktemp("archive"), (3, 4), DURATION_S)


def test_ranges_cover_every_index_once_in_pieces_of_chunk_seconds() -> None:
    times = np.arange(0, 95) * 33_333_334 + 5  # 95 frames at 30 Hz
    cuts = ranges(times, 1.0)
    assert cuts[0][0] == 0 and cuts[-1][1] == 95
    assert all(b == c for (_, b), (c, _) in itertools.pairwise(cuts))
    for a, b in cuts:  # each piece within one second of its first frame
        assert times[b - 1] - times[a] < 1_000_000_000
    assert [b - a for a, b in cuts] == [30, 30, 30, 5]
    assert ranges(times, 0) == [(0, 95)] and ranges(times[:0], 1.0) == [(0, 0)]


def test_the_fusion_plan_numbers_sets_by_the_index(recordings: list[Path]) -> None:
    rig = small_rig()
    with ReplaySource(recordings[0], realtime=False) as src:
        times = src.log_times("ccd_left", "color")
        assert times is not None and len(times) == src.message_count("ccd_left", "color") == 90
        assert np.all(np.diff(times) > 0)
        pieces = plan_fuse(src, rig.eyes["left"].color, 1.0, 0.5, every=4)
    assert [(p.start_set, p.end_set) for p in pieces] == [(0, 30), (30, 60), (60, None)]
    # the warm-up starts half a second (15 frames) before each later piece, at a frame
    assert [(p.first_set, p.seek_ns) for p in pieces[1:]] == [
        (15, int(times[15])),
        (45, int(times[45])),
    ]
    assert pieces[0].seek_ns is None and pieces[0].first_set == 0
    # every 4th set by its number in the recording: 0, 4, ... 88 -> 23 pictures in all
    assert [p.expected for p in pieces] == [8, 7, 8]


def test_a_recording_without_a_message_index_is_one_piece(
    recordings: list[Path], tmp_path: Path
) -> None:
    cut = tmp_path / "cut.mcap"  # cut short: no summary, the file is scanned
    data = recordings[0].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    with ReplaySource(cut, realtime=False) as src:
        assert src.log_times("ccd_left", "color") is None
        assert plan_fuse(src, "ccd_left", 1.0, 0.5, 1) == [
            FusePiece(str(cut.resolve()), 0, None, 0, 0, None, None)
        ]
        [piece] = plan_map([src], "tof", 1.0, 0.1, estimate=False)
        assert piece.spans[0].seek_ns is None and piece.spans[0].add_tof is None


def test_map_pieces_add_every_tof_frame_once(recordings: list[Path]) -> None:
    sources = [ReplaySource(p, realtime=False) for p in recordings]
    try:
        pieces = plan_map(sources, "tof", 1.0, 0.1, estimate=False)
        assert len(pieces) == 6 and sum(p.expected for p in pieces) == 90
        for src in sources:
            times = src.log_times("tof", "tof_distance")
            spans = [p.spans[0] for p in pieces if p.spans[0].recording == str(src.path)]
            for span in spans[1:]:  # read from 0.2 s before: 3 frames of context at 15 Hz
                first = np.searchsorted(times, span.seek_ns)
                assert span.skip_tof == 3 and times[first + 3] - span.seek_ns == 200_000_000
        [one] = plan_map(sources, "tof", 1.0, 0.1, estimate=True)  # KISS-ICP runs through
        assert [s.recording for s in one.spans] == [str(p) for p in recordings]
    finally:
        for src in sources:
            src.close()


def test_a_cut_recording_is_mapped_up_to_its_damage(recordings: list[Path], tmp_path: Path) -> None:
    """Issue 33: a recording cut short (``head -c`` of one: no summary, so no statistics)
    is mapped as ``trifuse fuse`` reads it: every TOF frame before the cut is added and the
    damage is named in the replay's words. (Counting the TOF distances by the statistics
    refused it: "no TOF distances ... nothing to map".)"""
    cut = tmp_path / "cut.mcap"
    data = recordings[0].read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 5])  # about the first 1.2 s of 3 s
    with ReplaySource(recordings[0], realtime=False) as whole:
        # as many as the machine recorded in 3 s (45 at the simulated head's full rate)
        tof_whole = whole.message_count("tof", "tof_distance")
    with ReplaySource(cut, realtime=False, on_damage="stop") as src:
        tof = sum(f.sensor == "tof" and f.distance_m is not None for f in src.frames())
        named = str(src.damage)
    assert tof_whole // 4 <= tof < tof_whole and "truncated" in named and str(cut) in named
    sources, rig = open_recordings([cut], None)
    try:
        assert sources[0].message_count("tof", "tof_distance") is None  # no statistics
        run = run_map_job(sources, rig, MapSettings(voxel_m=0.05), "auto", 1.0, LocalRunner())
    finally:
        for src in sources:
            src.close()
    assert run.pose_source == "recording" and run.tof_frames == run.integrated == tof
    assert [str(d) for d in run.damage] == [named]
    assert run.map.occupied().sum() > 1000


def test_split_fusion_writes_the_unsplit_sets_and_stamps(
    recordings: list[Path], tmp_path: Path
) -> None:
    """Pieces of one second, each warmed up over 0.8 s: the same pictures (numbered across
    the pieces), the same frames.csv (which set, which TOF frame), the first piece's
    pictures byte for byte, the later ones equal to the unsplit run's but for the display's
    smoothing (time constant 0.2 s, 4 of them of warm-up; the AGC table's renormalisation
    makes it settle more slowly than the span's e^-4: measured, the worst picture differs
    by 1.9 grey levels on average, those of the later pieces by 0.4), and one video of all
    of them."""
    settings = DisplaySettings(span_smoothing_s=0.2)
    out = {}
    for chunk_s in (0.0, 1.0):
        d = tmp_path / f"chunk{chunk_s:g}"
        d.mkdir()
        [planned] = plan_fuse_job([(recordings[0], d)], None, settings, 1, chunk_s)
        assert len(planned.pieces) == (1 if chunk_s == 0 else 3)
        assert [p.first_set for p in planned.pieces] == ([0] if chunk_s == 0 else [0, 6, 36])
        [result] = run_fuse_job([planned], settings, 1, LocalRunner())
        assert result.frames == 90 - result.skipped.get("no TOF frame yet", 0)
        out[chunk_s] = d
    whole, split = directory_bytes(out[0.0]), directory_bytes(out[1.0])
    assert sorted(whole) == sorted(split)
    assert whole["frames.csv"] == split["frames.csv"]
    with ReplaySource(recordings[0], realtime=False) as src:
        second_piece_ns = src.log_times("ccd_left", "color")[30]
    diffs = []
    for i, row in enumerate(whole["frames.csv"].decode().splitlines()[1:]):
        name = f"{i:06d}.jpg"
        if int(row.split(",")[1]) < second_piece_ns:
            assert whole[name] == split[name], name
            continue
        a = cv2.imdecode(np.frombuffer(whole[name], np.uint8), cv2.IMREAD_COLOR)
        b = cv2.imdecode(np.frombuffer(split[name], np.uint8), cv2.IMREAD_COLOR)
        diffs.append(np.abs(a.astype(int) - b.astype(int)).mean())
    assert len(diffs) == 60 and max(diffs) < 3.0 and np.mean(diffs) < 0.6, diffs
    cap = cv2.VideoCapture(str(out[1.0] / "fused.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == sum(n.endswith(".jpg") for n in split)
    assert not [n for n in split if n.startswith(".")]  # the pieces' videos are gone


def test_a_piece_that_fails_leaves_no_video_parts(recordings: list[Path], tmp_path: Path) -> None:
    rig = small_rig()
    writer = FusedWriter(tmp_path, 30.0)
    with ReplaySource(recordings[0], realtime=False) as src:
        piece = FusePiece(str(recordings[0]), 0, None, 0, 0, 20, 20)
        for item in fuse_piece(src, rig, piece, DisplaySettings(), 1):
            writer.add(item)
            if isinstance(item, PieceEnd):
                assert item.video is not None and item.sets == 20
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] != []
    writer.abort()
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_fuse_several_recordings_into_a_directory_each(
    recordings: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "fused"
    archive = recordings[0].parent
    assert main(["fuse", str(archive), "--out", str(out), "--every", "3", "--chunk-s", "1"]) == 0
    printed = capsys.readouterr()
    assert "6 pieces (1 s each; local)" in printed.out, printed.out
    for rec in recordings:
        d = out / rec.stem
        assert (d / "frames.csv").is_file() and (d / "fused.mp4").is_file()
        rows = (d / "frames.csv").read_text().splitlines()
        assert len(rows) - 1 == len(list(d.glob("*.jpg"))) >= 25
        assert f"{rec}: Wrote" in printed.out
    # file:// names a path; other URL schemes are refused in one line, saying what works
    again = tmp_path / "again"
    assert main(["fuse", recordings[0].as_uri(), "--out", str(again), "--every", "30"]) == 0
    assert len(list(again.glob("*.jpg"))) == 3
    capsys.readouterr()
    assert main(["fuse", "s3://bucket/mission.mcap", "--out", str(tmp_path / "s3")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "mount the store" in err and "same path" in err


def test_without_the_ray_extra_ray_is_refused_and_local_runs(
    recordings: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    argv = ["fuse", str(recordings[0]), "--every", "30"]
    assert main([*argv, "--out", str(tmp_path / "a"), "--ray"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install -e '.[ray]'" in err
    assert not (tmp_path / "a").exists()  # refused before anything was written
    assert main([*argv, "--out", str(tmp_path / "b")]) == 0
    assert len(list((tmp_path / "b").glob("*.jpg"))) == 3
    # --ray before the recordings takes the first as its address: said so, not tried
    capsys.readouterr()
    names = [str(p) for p in recordings]
    assert main(["fuse", "--ray", *names, "--out", str(tmp_path / "c")]) == 2
    assert "put --ray after the recordings" in capsys.readouterr().err


def test_an_unreadable_recording_names_the_machine(recordings: list[Path], tmp_path: Path) -> None:
    gone = tmp_path / "gone.mcap"
    gone.write_bytes(recordings[0].read_bytes())
    d = tmp_path / "out"
    d.mkdir()
    planned = plan_fuse_job([(gone, d)], None, DisplaySettings(), 1, 0.0)
    gone.unlink()  # planned here, then not there where the piece runs
    with pytest.raises(FileNotFoundError, match=r"cannot be read on .*same path"):
        run_fuse_job(planned, DisplaySettings(), 1, LocalRunner())
