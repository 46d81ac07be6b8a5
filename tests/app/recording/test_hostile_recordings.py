"""Hostile and damaged recordings (issue 29): image headers are checked against the rig
before anything is decoded, chunks are capped before they are decompressed and their records
walked with a bound, a bad message is skipped, counted and reported instead of ending the
replay, and what a damage exception holds is small. Peak memory and CPU time of the commands
are measured in child processes (``ru_maxrss``) against the same command on the legitimate
recording. The hostile files are made here from a small legitimate one."""

from __future__ import annotations

import gc
import resource
import struct
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import lz4.frame
import numpy as np
import pytest
import zstandard
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory

from tests.support import ROOT, assert_same_frame, run_cli, small_rig, synth_frames, wait_until
from trifuse.app.recording import RecordingDamaged, RecordingWriter, ReplaySource
from trifuse.app.recording.errors import ImageSizeError
from trifuse.app.recording.images import plane_from_compressed, raw_plane, rgb_from_compressed
from trifuse.app.recording.map3d import MAX_IMAGE_AGE_S
from trifuse.app.recording.mcapindex import MAX_CHUNK_BYTES
from trifuse.app.recording.pieces import plan_fuse, plan_map
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame
from trifuse.app.storage.rigfile import save_rig
from trifuse.calib.rig import Rig
from trifuse.calib.units import encode_amplitude

GIB = 2**30
SLACK_MB = 60
"""Peak memory a hostile input may add to the legitimate run's (noise: a few MB)."""
SLACK_CPU_S = 10.0
"""CPU seconds it may add: "refused at once", where the unfixed code took minutes."""


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


def _recording(path: Path, rig: Rig, compression: str) -> tuple[Path, list[Frame]]:
    """1 s of the small head with the head's pose at every TOF frame (so that a map job
    splits it), chunks of 256 KiB (a 1 GiB zstd bomb, 32 KB, fits in one)."""
    frames = synth_frames(rig, 1.0, seed=11)
    with RecordingWriter(path, rig, chunk_size=256 * 1024, compression=compression) as w:
        for f in frames:
            if f.sensor == "tof":
                T = np.eye(4)
                T[0, 3] = (f.stamp_ns - frames[0].stamp_ns) / 1e9 * 0.1  # 0.1 m/s sideways
                w.write_pose(f.stamp_ns, T)
            w.write(f)
    return path, frames


@pytest.fixture(scope="module")
def legit(tmp_path_factory, rig) -> tuple[Path, list[Frame]]:
    return _recording(tmp_path_factory.mktemp("legit") / "legit.mcap", rig, "zstd")


@pytest.fixture(scope="module")
def legit_lz4(tmp_path_factory, rig) -> tuple[Path, list[Frame]]:
    return _recording(tmp_path_factory.mktemp("legit") / "legit-lz4.mcap", rig, "lz4")


# -- making hostile files -------------------------------------------------------------------


def rewrite(src: Path, dst: Path, change: Callable[[str, int, Any], bytes | None]) -> Path:
    """``src`` written again message by message, ``change(topic, n, decoded)`` giving the
    bytes of the ``n``-th message of ``topic`` (None: left out); schemas, channels,
    attachments and metadata as they were."""
    decoders = DecoderFactory()
    with src.open("rb") as f, dst.open("wb") as out:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        w = Writer(out, chunk_size=256 * 1024)
        w.start(profile=reader.get_header().profile, library="hostile")
        sids = {
            i: w.register_schema(s.name, s.encoding, s.data) for i, s in summary.schemas.items()
        }
        cids = {
            i: w.register_channel(c.topic, c.message_encoding, sids[c.schema_id], c.metadata)
            for i, c in summary.channels.items()
        }
        for a in reader.iter_attachments():
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        for m in reader.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        seen: dict[str, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            n = seen[channel.topic] = seen.get(channel.topic, -1) + 1
            decoded = decoders.decoder_for(channel.message_encoding, schema)(message.data)
            data = change(channel.topic, n, decoded)
            if data is not None:
                w.add_message(cids[channel.id], message.log_time, data, message.publish_time)
        w.finish()
    return dst


def edited(src: Path, dst: Path, edits: dict[tuple[str, int], Callable[[Any], None]]) -> Path:
    """``src`` with the messages ``(topic, n)`` edited in place (decoded, changed, encoded)."""

    def change(topic: str, n: int, msg: Any) -> bytes:
        if (topic, n) in edits:
            edits[(topic, n)](msg)
        return msg.SerializeToString()

    return rewrite(src, dst, change)


def jpeg_claiming(width: int, height: int) -> bytes:
    """A 629-byte JPEG of 8 x 8 pixels whose frame header claims ``width`` x ``height``."""
    data = bytearray(cv2.imencode(".jpg", np.full((8, 8, 3), 128, np.uint8))[1].tobytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def png_claiming(width: int, height: int) -> bytes:
    """A small PNG whose IHDR claims ``width`` x ``height`` (its CRC fixed to match)."""
    import zlib

    data = bytearray(cv2.imencode(".png", np.zeros((8, 8), np.uint16))[1].tobytes())
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


def zeros_zstd(n: int, content_size: bool = True) -> bytes:
    """A zstd frame of ``n`` zero bytes (a 1 GiB one is 32 KB), made without holding them."""
    c = zstandard.ZstdCompressor(level=1, write_content_size=content_size)
    obj = c.compressobj(size=n if content_size else -1)
    block = bytes(2**20)
    parts = [obj.compress(block[: min(2**20, n - k)]) for k in range(0, n, 2**20)]
    return b"".join([*parts, obj.flush()])


def patch_chunk(
    src: Path, dst: Path, k: int, records: bytes, declared: int, crc: int = 0
) -> tuple[Path, int]:
    """``src`` with chunk ``k``'s records replaced in place by ``records`` (compressed as
    the chunk says), declaring ``declared`` bytes uncompressed and the CRC ``crc``; the
    file keeps its size and its summary. Returns (dst, the chunk's log start time)."""
    with ReplaySource(src, realtime=False) as s:
        chunk = s.index.chunks[k]
    data = bytearray(src.read_bytes())
    head = chunk.offset + 9 + 16
    data[head : head + 12] = struct.pack("<QI", declared, crc)
    (name_len,) = struct.unpack_from("<I", data, head + 12)
    at = head + 16 + name_len
    assert at + 8 + len(records) <= chunk.offset + 9 + chunk.length, "the chunk is too small"
    data[at : at + 8] = struct.pack("<Q", len(records))
    data[at + 8 : at + 8 + len(records)] = records
    dst.write_bytes(bytes(data))
    return dst, chunk.start_ns


# -- measuring --------------------------------------------------------------------------------

_CHILD = """
import resource, sys
from trifuse.app.cli import main
code = 1
try:
    code = main(sys.argv[1:])
finally:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    sys.stderr.write(f"\\nRUSAGE {ru.ru_maxrss} {ru.ru_utime + ru.ru_stime}\\n")
sys.exit(code)
"""


@dataclass
class Child:
    """A ``trifuse`` command run in a child process, and what it took."""

    code: int
    out: str
    err: str
    peak_mb: float
    cpu_s: float


def child(argv: list[str]) -> Child:
    """``trifuse argv`` in a child process (address space capped at 4 GiB so that a
    regression fails instead of taking the machine): exit status, output, peak resident
    memory (``ru_maxrss``) and CPU time."""

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (4 * GIB, 4 * GIB))

    p = subprocess.run(
        [sys.executable, "-c", _CHILD, *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        preexec_fn=cap,
        timeout=600,
    )
    err, _, usage = p.stderr.rpartition("RUSAGE ")
    assert usage, p.stderr[-2000:]
    kb, cpu = usage.split()
    return Child(p.returncode, p.stdout, err, int(kb) / 1024, float(cpu))


@pytest.fixture(scope="module")
def legit_fuse(legit, tmp_path_factory) -> Child:
    run = child(["fuse", str(legit[0]), "--out", str(tmp_path_factory.mktemp("f") / "out")])
    assert run.code == 0 and "Wrote 30 fused frames" in run.out, run.err
    return run


def replay(path: Path, rig: Rig | None = None) -> tuple[list[Frame], ReplaySource]:
    """Every frame of ``path`` (checked against ``rig`` if given), and the closed source
    (its ``damage`` and ``skipped``)."""
    got: list[Frame] = []
    with ReplaySource(path, realtime=False, on_damage="stop") as src:
        if rig is not None:
            src.expect(rig)
        got = list(src.frames())
    return got, src


# -- image headers ------------------------------------------------------------------------------


def test_image_headers_are_checked_against_the_rig_before_decoding():
    rig_size = (128, 96)
    t0 = time.process_time()
    with pytest.raises(ImageSizeError, match="JPEG of 30000x30000 pixels, the rig says 128x96"):
        rgb_from_compressed(jpeg_claiming(30000, 30000), rig_size)
    with pytest.raises(ImageSizeError, match="more than the 50000000 pixels"):
        rgb_from_compressed(jpeg_claiming(30000, 30000))  # no rig: the rig limit
    with pytest.raises(ImageSizeError, match="PNG of 60000x60000 pixels, the rig says 96x72"):
        plane_from_compressed(png_claiming(60000, 60000), "png", (96, 72))
    with pytest.raises(ImageSizeError, match="PNG of 60000x60000 pixels: more than"):
        rgb_from_compressed(png_claiming(60000, 60000))
    with pytest.raises(ImageSizeError, match="raw image of 30000x30000 pixels, the rig says"):
        raw_plane(b"\0" * 64, 30000, 30000, 60000, "16UC1", size=(96, 72))
    assert time.process_time() - t0 < 1.0  # nothing was decoded
    # other formats OpenCV would decode (each with a header of its own) are refused
    bmp = cv2.imencode(".bmp", np.zeros((96, 128, 3), np.uint8))[1].tobytes()
    with pytest.raises(ValueError, match="expected JPEG or PNG"):
        rgb_from_compressed(bmp, rig_size)
    with pytest.raises(ValueError, match="no frame header"):
        rgb_from_compressed(jpeg_claiming(128, 96)[:20], rig_size)
    # the legitimate images decode as before
    image = np.random.default_rng(0).integers(0, 255, (96, 128, 3), dtype=np.uint8)
    for ext in (".jpg", ".png"):
        data = cv2.imencode(ext, image)[1].tobytes()
        assert rgb_from_compressed(data, rig_size).shape == (96, 128, 3)
    thermal = np.arange(96 * 72, dtype=np.uint16).reshape(72, 96)
    data = cv2.imencode(".png", thermal)[1].tobytes()
    np.testing.assert_array_equal(plane_from_compressed(data, "png", (96, 72)), thermal)


def test_a_jpeg_claiming_30000x30000_pixels_is_skipped_at_its_header(legit, legit_fuse, tmp_path):
    """Unfixed: ``trifuse fuse`` went to 10.7 GB (here: past its 4 GiB address space)."""
    path, _ = legit
    bomb = jpeg_claiming(30000, 30000)
    assert len(bomb) < 700

    def swap(msg: Any) -> None:
        msg.data = bomb

    bad = edited(path, tmp_path / "bomb.mcap", {("/ccd_left/image", 5): swap})
    run = child(["fuse", str(bad), "--out", str(tmp_path / "out")])
    assert run.code == 0, run.err
    assert "Wrote 29 fused frames" in run.out  # the set of the lost reference frame only
    line = "1 message of ccd_left skipped: JPEG of 30000x30000 pixels, the rig says 128x96"
    assert f"trifuse: warning: {line}" in run.err
    assert run.peak_mb < legit_fuse.peak_mb + SLACK_MB, (run.peak_mb, legit_fuse.peak_mb)
    assert run.cpu_s < legit_fuse.cpu_s + SLACK_CPU_S


# -- chunks -------------------------------------------------------------------------------------


def test_a_chunk_of_1_gib_is_refused_before_it_is_decompressed(legit, legit_fuse, tmp_path):
    """The issue's zstd chunk: 32 KB declaring (and holding) 1 GiB of zeros. Unfixed:
    1.3 GB of memory and 105 s of CPU walking the zeros as 119 million empty records."""
    path, frames = legit
    bad, start_ns = patch_chunk(path, tmp_path / "gib.mcap", 2, zeros_zstd(GIB), GIB)
    assert bad.stat().st_size == path.stat().st_size
    run = child(["fuse", str(bad), "--out", str(tmp_path / "out")])
    assert run.code == 0, run.err  # the frames before the chunk are fused
    assert "recording damaged at byte" in run.err
    assert f"declares {GIB} bytes of records uncompressed, more than a chunk may hold" in run.err
    assert run.peak_mb < legit_fuse.peak_mb + SLACK_MB, (run.peak_mb, legit_fuse.peak_mb)
    assert run.cpu_s < legit_fuse.cpu_s + SLACK_CPU_S
    # the replay gives every frame before the chunk, then names the damage
    got, src = replay(bad)
    assert isinstance(src.damage, RecordingDamaged) and src.damage.offset is not None
    want = {(f.sensor, f.stamp_ns): f for f in frames}
    for f in got:
        assert_same_frame(f, want[(f.sensor, f.stamp_ns)])
    assert {(f.sensor, f.stamp_ns) for f in frames if f.stamp_ns < start_ns} <= {
        (f.sensor, f.stamp_ns) for f in got
    }


@pytest.mark.parametrize(
    ("how", "reason"),
    [
        ("zstd says more", "holds a zstd frame of 1073741824 bytes, but declares 100000"),
        ("zstd without size", "cannot be decompressed (ZstdError: decompression error"),
        ("lz4 gives more", "decompresses to more than 100000 bytes, but declares 100000"),
        ("over the cap", f"declares {MAX_CHUNK_BYTES + 1} bytes of records uncompressed"),
    ],
)
@pytest.mark.parametrize("indexed_by", ["summary", "scan"])
def test_a_chunk_never_decompresses_past_what_it_declares(
    legit, legit_lz4, tmp_path, how, reason, indexed_by
):
    """zstd's and lz4's own frame headers are not believed: a chunk declaring 100 kB whose
    frame holds 1 GiB (or 16 MiB) stops at its declared size, whether the file is indexed
    by its summary or scanned (cut short); the replay's memory stays within a few MB."""
    path, frames = legit_lz4 if how.startswith("lz4") else legit
    declared = 100_000
    if how == "zstd says more":
        records = zeros_zstd(GIB)
    elif how == "zstd without size":
        records = zeros_zstd(9 * declared, content_size=False)
    elif how == "lz4 gives more":
        records = lz4.frame.compress(bytes(16 * 2**20))
    else:
        records, declared = zeros_zstd(2**20), MAX_CHUNK_BYTES + 1
    bad, _ = patch_chunk(path, tmp_path / "bad.mcap", 2, records, declared)
    if indexed_by == "scan":
        bad.write_bytes(bad.read_bytes()[:-200])
    tracemalloc.start()
    try:
        got, src = replay(bad)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert src.index.indexed_by == indexed_by
    assert src.damage is not None and reason in src.damage.reason, src.damage
    assert 0 < len(got) < len(frames)
    assert peak < 20 * 2**20, peak  # the whole replay, of a 3 MB file


def test_a_chunk_of_zeros_is_damage_not_silence(legit, tmp_path):
    """64 MiB of zeros in a chunk that declares them (within the cap): unfixed, its 7.5
    million empty "records" took seconds and the chunk's frames vanished without a word;
    now the first record of type 0 is damage."""
    path, frames = legit
    zeros = zeros_zstd(MAX_CHUNK_BYTES)
    bad, start_ns = patch_chunk(path, tmp_path / "z.mcap", 2, zeros, MAX_CHUNK_BYTES)
    t0 = time.process_time()
    got, src = replay(bad)
    assert time.process_time() - t0 < 5.0
    assert src.damage is not None
    assert "holds a record of type 0x00" in src.damage.reason
    assert {(f.sensor, f.stamp_ns) for f in frames if f.stamp_ns < start_ns} <= {
        (f.sensor, f.stamp_ns) for f in got
    }


def test_a_chunk_of_a_million_tiny_messages_is_refused(legit, tmp_path):
    """600,000 empty messages on a colour channel, 2 kB compressed: unfixed, a quarter of a
    GB of message objects and seconds of failed decoding per chunk; now more records than
    the chunk's bytes allow are damage at once."""
    path, frames = legit
    with ReplaySource(path, realtime=False) as src:
        channel = next(i for i, c in src.index.channels.items() if c.topic == "/ccd_left/image")
        t = src.index.chunks[2].start_ns
    record = struct.pack("<BQHIQQ", 5, 22, channel, 0, t, t)  # a message without data
    raw = record * 600_000
    flood = zstandard.ZstdCompressor(level=3).compress(raw)
    assert len(flood) < 4096
    bad, start_ns = patch_chunk(path, tmp_path / "flood.mcap", 2, flood, len(raw))
    del raw
    tracemalloc.start()
    t0 = time.process_time()
    try:
        got, src = replay(bad)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.process_time() - t0 < 5.0
    assert src.damage is not None and "holds more than" in src.damage.reason
    assert src.skipped == {}  # refused before any of them was decoded
    assert peak < 40 * 2**20, peak  # the chunk decompressed (19 MB), no message objects
    assert {(f.sensor, f.stamp_ns) for f in frames if f.stamp_ns < start_ns} <= {
        (f.sensor, f.stamp_ns) for f in got
    }


def test_the_damage_does_not_keep_the_chunk_in_memory(legit, tmp_path):
    """A 48 MiB chunk that fails its CRC: the damage the replay keeps (the console holds its
    source for its whole life) holds none of it."""
    path, _ = legit
    size = 48 * 2**20
    bad, _ = patch_chunk(path, tmp_path / "crc.mcap", 2, zeros_zstd(size), size, crc=12345)
    frames: list[Frame] = []
    tracemalloc.start()
    try:
        with ReplaySource(bad, realtime=False) as src:  # as the console opens it
            before = tracemalloc.get_traced_memory()[0]
            with pytest.raises(RecordingDamaged):
                for f in src.frames():
                    frames.append(f)
            gc.collect()
            held = tracemalloc.get_traced_memory()[0] - before
            peak = tracemalloc.get_traced_memory()[1]
            assert src.damage is not None and "fails its CRC" in src.damage.reason
    finally:
        tracemalloc.stop()
    assert frames and peak > size  # the chunk was decompressed ...
    assert held < 4 * 2**20, held  # ... and nothing of it is kept


# -- bad messages: skipped, counted, reported -------------------------------------------------


def _bad_messages(path: Path, dst: Path) -> Path:
    """Three bad messages: thermal_left #3 undecodable, ccd_right #4 a JPEG of 64x48, the
    TOF distance #2 a raw image of 22x18."""
    small = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))[1].tobytes()

    def smaller_jpeg(msg: Any) -> None:
        msg.data = small

    def smaller_raw(msg: Any) -> None:
        msg.width, msg.height, msg.step = 22, 18, 44
        msg.data = bytes(44 * 18)

    out = edited(
        path, dst, {("/ccd_right/image", 4): smaller_jpeg, ("/tof/distance", 2): smaller_raw}
    )
    return rewrite(  # a message that is no protobuf at all
        out,
        dst.with_name("bad.mcap"),
        lambda topic, n, msg: (
            b"\x0a\xff\xff\xff"
            if (topic, n) == ("/thermal_left/temperature", 3)
            else msg.SerializeToString()
        ),
    )


SKIPPED = {
    "ccd_right": {"JPEG of 64x48 pixels, the rig says 128x96": 1},
    "tof": {"raw image of 22x18 pixels, the rig says 44x36": 1},
    "thermal_left": {
        "cannot be decoded (DecodeError: Error parsing message with type "
        "'foxglove.RawImage': Wire format was corrupt)": 1
    },
}


def test_bad_messages_are_skipped_and_counted_and_the_replay_goes_on(legit, tmp_path):
    path, frames = legit
    bad = _bad_messages(path, tmp_path / "edit.mcap")
    got, src = replay(bad)
    assert src.damage is None
    assert src.skipped == SKIPPED
    nth = {n: sorted(f.stamp_ns for f in frames if f.sensor == n) for n in SKIPPED}
    lost = {("ccd_right", nth["ccd_right"][4]), ("thermal_left", nth["thermal_left"][3])}
    want = {(f.sensor, f.stamp_ns): f for f in frames}
    assert {(f.sensor, f.stamp_ns) for f in got} == set(want) - lost
    for f in got:
        w = want[(f.sensor, f.stamp_ns)]
        if (f.sensor, f.stamp_ns) == ("tof", nth["tof"][2]):  # its distance was skipped
            assert f.distance_m is None
            np.testing.assert_array_equal(encode_amplitude(f.image), encode_amplitude(w.image))
        else:
            assert_same_frame(f, w)
    # the console's sensor health reads this: rejected since the last frame delivered
    stats = src.stats()["rejected_by_sensor"]
    assert set(stats) == set(SKIPPED)
    assert all(s["since_accepted"] == 0 and s["last_rejected_s"] for s in stats.values())


def test_fuse_map_and_record_report_the_skipped_messages(legit, tmp_path, capsys):
    path, _ = legit
    bad = _bad_messages(path, tmp_path / "edit.mcap")
    lines = [f"{n} message of {s} skipped: {r}" for s, rs in SKIPPED.items() for r, n in rs.items()]
    code, out, err = run_cli(["fuse", str(bad), "--out", str(tmp_path / "f")], capsys)
    assert code == 0 and "Wrote 30 fused frames" in out, err
    for line in lines:
        assert f"trifuse: warning: {line}" in err
    code, out, err = run_cli(["map", str(bad), "--out", str(tmp_path / "m.ply")], capsys)
    assert code == 0 and "Mapped 14 of 14 TOF frames" in out, err + out  # 15, one skipped
    for line in lines:
        assert f"trifuse: warning: {line}" in err
    rec = tmp_path / "again.mcap"
    code, out, err = run_cli(["record", "--source", f"replay:{bad}", "--out", str(rec)], capsys)
    assert code == 0, err
    for line in lines:
        assert f"trifuse: warning: {line}; the other frames were recorded" in err
    got, src = replay(rec)
    assert src.skipped == {} and src.damage is None
    assert len(got) == len(legit[1]) - 2  # all but the two frames lost whole


@pytest.mark.parametrize("command", ["fuse", "map"])
def test_a_split_job_counts_each_skipped_message_once(legit, tmp_path, capsys, command):
    """Pieces of 0.3 s replay 0.5 s before their range (fuse) or 0.2 s (map): a bad message
    there is read by two pieces and counted by one."""
    path, frames = legit

    def garbage(msg: Any) -> None:
        msg.data = b"not an image"

    stamps = sorted(f.stamp_ns for f in frames if f.sensor == "ccd_right")
    picks = [k for k, t in enumerate(stamps) if 0.25e9 < t - stamps[0] < 0.9e9 and k % 3 == 0]
    bad = edited(path, tmp_path / "bad.mcap", {("/ccd_right/image", k): garbage for k in picks})
    with ReplaySource(bad, realtime=False) as src:  # the job splits in pieces
        assert len(plan_fuse(src, "ccd_left", 0.3, 0.5, 1)) == 4
        assert len(plan_map([src], "tof", 0.3, MAX_IMAGE_AGE_S, estimate=False)) == 4
    reports = []
    for chunk_s in ("0", "0.3"):
        target = tmp_path / f"{command}-{chunk_s}"
        out_args = ["--out", str(target)] if command == "fuse" else ["--out", f"{target}.ply"]
        code, _out, err = run_cli([command, str(bad), *out_args, "--chunk-s", chunk_s], capsys)
        assert code == 0, err
        reports.append([line for line in err.splitlines() if "skipped" in line])
    assert (
        reports[0]
        == reports[1]
        == [
            f"trifuse: warning: {len(picks)} messages of ccd_right skipped: cannot be decoded "
            "(ValueError: compressed image: expected JPEG or PNG, the first bytes are "
            "b'not an i')"
        ]
    )


def test_a_fuse_where_every_frame_is_bad_exits_2_saying_why(legit, tmp_path, capsys):
    """Fused with the rig of another head (every image twice the size): nothing fuses."""
    path, _ = legit
    head = small_rig()
    bigger = Rig(
        sensors={
            n: replace(s, image_size=(2 * s.image_size[0], 2 * s.image_size[1]))
            for n, s in head.sensors.items()
        },
        reference=head.reference,
        eyes=head.eyes,
    )
    rig_file = tmp_path / "bigger.yaml"
    save_rig(rig_file, bigger)
    out_dir = tmp_path / "f"
    argv = ["fuse", str(path), "--rig", str(rig_file), "--out", str(out_dir)]
    code, _out, err = run_cli(argv, capsys)
    assert code == 2
    assert err.startswith("trifuse: error: ") and err.count("\n") == 1  # one line
    assert "no frame set could be fused" in err
    assert "30 messages of ccd_left skipped: JPEG of 128x96 pixels, the rig says 256x192" in err
    assert list(out_dir.glob("*.jpg")) == []


def test_the_console_shows_a_replays_skipped_messages_as_failing(legit, rig, tmp_path):
    """Every thermal_left message undecodable: ``failing`` with the reason in the console's
    sensor health, while the other sensors are fused."""
    path, _ = legit
    bad = rewrite(
        path,
        tmp_path / "bad.mcap",
        lambda topic, n, msg: (
            b"\x0a\xff" if topic == "/thermal_left/temperature" else msg.SerializeToString()
        ),
    )
    replay_src = ReplaySource(bad, loop=True, realtime=True)
    hub = FrameHub()
    pipeline = FusionPipeline(SourceTap(replay_src), rig, hub).start()
    control = SourceControl(pipeline, hub, f"replay of {bad}")
    try:
        health = wait_until(
            lambda: (
                (h := control.sensor_health())["thermal_left"].state == "failing"
                and h["ccd_left"].ok
                and h
            ),
            "thermal_left failing",
        )
        assert "rejected (cannot be decoded (DecodeError" in health["thermal_left"].reason
        assert all(health[s].ok for s in ("ccd_left", "ccd_right", "thermal_right", "tof"))
        assert "thermal_left" in control.health_notes()
    finally:
        pipeline.stop()
        replay_src.close()
