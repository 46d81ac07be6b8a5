"""Recordings: MCAP writing with Foxglove's schemas, replay, damage, the record/fuse commands."""

from __future__ import annotations

import dataclasses
import logging
import re
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from tests.support import (
    RATES_HZ,
    WAIT_S,
    FakeClock,
    assert_same_frame,
    small_rig,
    synth_frame,
    synth_frames,
    write_recording,
)
from trifuse.app.cli import main
from trifuse.app.recording import (
    RecordingDamaged,
    RecordingError,
    RecordingWriter,
    ReplaySource,
)
from trifuse.app.recording import reader as reader_module
from trifuse.app.recording.mcapindex import MAX_CHUNK_BYTES
from trifuse.app.recording.player import MAX_LAG_S
from trifuse.app.recording.simrecord import (
    head_model_for,
    plan_simulation,
    pose_index,
    record_simulation,
    sim_schedule,
)
from trifuse.app.recording.writer import MAX_CHUNK_SIZE, MAX_MESSAGE_BYTES
from trifuse.app.sources.base import frame_sets
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.storage.rigfile import save_rig
from trifuse.calib.rig import Rig
from trifuse.calib.units import encode_amplitude


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, rig) -> tuple[Path, list[Frame]]:
    frames = synth_frames(rig, 0.4, seed=3)
    # small chunks (a few frames each), as a full-resolution recording has
    path = tmp_path_factory.mktemp("rec") / "mission.mcap"
    write_recording(path, rig, frames, chunk_size=32 * 1024)
    return path, frames


# -- round trip -----------------------------------------------------------------------------


def test_round_trip_gives_the_same_frames_and_stamps(recorded, rig):
    path, frames = recorded
    with ReplaySource(path, realtime=False) as src:
        got = list(src.frames())
        assert src.rig == rig and src.rig_source == "attachment"
        assert src.sensors == rig.names and src.recorded_sensors
        assert src.notes == [] and src.damage is None
        assert src.start_ns == frames[0].stamp_ns
        assert src.duration_s == pytest.approx((frames[-1].stamp_ns - frames[0].stamp_ns) / 1e9)
    assert len(got) == len(frames)
    stamps = [f.stamp_ns for f in got]
    assert stamps == sorted(stamps)
    want = {(f.sensor, f.stamp_ns): f for f in frames}
    assert {(f.sensor, f.stamp_ns) for f in got} == set(want)
    for f in got:
        assert_same_frame(f, want[(f.sensor, f.stamp_ns)])


def test_real_scenario_frames_round_trip(tmp_path, rig):
    from trifuse.app.sources.sim.inspection import InspectionScenario

    fs, _ = InspectionScenario(rig=rig, model=head_model_for(rig), seed=1).render(0.5)
    path = tmp_path / "sim.mcap"
    with RecordingWriter(path, rig) as w:
        assert w.write_set(fs) == 5
    with ReplaySource(path, realtime=False) as src:
        got = {f.sensor: f for f in src.frames()}
    assert set(got) == set(rig.names)
    for name, f in got.items():
        # the room's 128 x 96 pictures are dense with sharp edges (two people, the window,
        # the rack: 34.8 dB at worst, 35.6 before issue 19 added them): 34 dB here
        assert_same_frame(f, fs[name], min_psnr_db=34.0)


def test_frame_sets_of_a_replay(recorded, rig):
    path, _ = recorded
    with ReplaySource(path, realtime=False) as src:
        sets = list(frame_sets(src, reference="ccd_left"))
    assert len(sets) == 12  # 0.4 s of 30 Hz
    assert all(not fs.missing for fs in sets[1:])
    assert all(fs.frames.keys() == set(rig.names) for fs in sets[1:])


def test_rig_rebuilt_from_calibration_messages(recorded, rig, monkeypatch):
    import trifuse.app.recording.reader as reader

    monkeypatch.setattr(reader, "RIG_ATTACHMENT", "absent.yaml")
    path, _ = recorded
    with ReplaySource(path, realtime=False) as src:
        got = src.rig
        assert src.rig_source == "messages"
    assert got is not None and got.reference == "tof" and got.eyes == rig.eyes
    assert sorted(got.names) == sorted(rig.names)
    for name in rig.names:
        assert got[name].modality == rig[name].modality
        assert got[name].image_size == rig[name].image_size
        assert got[name].intrinsics == rig[name].intrinsics
        np.testing.assert_allclose(got[name].T_rig_sensor, rig[name].T_rig_sensor, atol=1e-12)


def test_calibration_messages_of_no_real_camera_make_no_rig(tmp_path, rig, monkeypatch):
    import trifuse.app.recording.reader as reader

    monkeypatch.setattr(reader, "RIG_ATTACHMENT", "absent.yaml")
    absurd = dataclasses.replace(rig["ccd_left"].intrinsics, fx=1e300)
    bad = dataclasses.replace(
        rig,
        sensors={
            **rig.sensors,
            "ccd_left": dataclasses.replace(rig["ccd_left"], intrinsics=absurd),
        },
    )
    path = tmp_path / "absurd.mcap"
    write_recording(path, bad, synth_frames(rig, 0.1, seed=4))
    with ReplaySource(path, realtime=False) as src:
        assert src.rig is None
        assert any("ccd_left" in n and "do not make a rig" in n for n in src.notes), src.notes


def test_tof_without_distance_and_32FC1_thermal(tmp_path, rig):
    rng = np.random.default_rng(1)
    tof = synth_frame(rig, "tof", 5, rng)
    th = synth_frame(rig, "thermal_left", 5, rng)
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, rig, thermal_encoding="32FC1", compression="lz4") as w:
        w.write(Frame("tof", 5, tof.image))
        w.write(th)
    with ReplaySource(path, realtime=False) as src:
        got = {f.sensor: f for f in src.frames()}
    assert got["tof"].distance_m is None
    np.testing.assert_array_equal(encode_amplitude(got["tof"].image), encode_amplitude(tof.image))
    np.testing.assert_array_equal(got["thermal_left"].image, th.image)  # float32 exact


# -- the file as Foxglove sees it -------------------------------------------------------------


def test_file_layout_with_the_plain_mcap_reader(recorded, rig):
    from scipy.spatial.transform import Rotation

    path, _ = recorded

    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        topics = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
        assert topics["/ccd_left/image"] == "foxglove.CompressedImage"
        assert topics["/thermal_right/temperature"] == "foxglove.RawImage"
        assert topics["/tof/distance"] == "foxglove.RawImage"
        assert topics["/tof/amplitude"] == "foxglove.RawImage"
        assert topics["/tof/calibration"] == "foxglove.CameraCalibration"
        assert topics["/tf"] == "foxglove.FrameTransform"
        assert len(topics) == 2 + 2 + 2 + 5 + 1  # images, calibrations, /tf
        atts = list(reader.iter_attachments())
        assert [a.name for a in atts] == ["rig.yaml"]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["trifuse.recording"]["format"] == "trifuse-recording/1"
        seen_tf, seen_cal = {}, {}
        for _schema, channel, message, msg in reader.iter_decoded_messages():
            stamp = msg.timestamp.seconds * 10**9 + msg.timestamp.nanos
            assert stamp == message.log_time
            if channel.topic == "/tf":
                seen_tf[msg.child_frame_id] = msg
                continue
            sensor = channel.topic.split("/")[1]
            assert msg.frame_id == sensor
            if channel.topic.endswith("/calibration"):
                seen_cal[sensor] = msg
            elif channel.topic.endswith("/image"):
                assert msg.format == "jpeg" and msg.data[:2] == b"\xff\xd8"
            else:
                assert msg.encoding == "16UC1" and msg.step == 2 * msg.width
    assert set(seen_tf) == set(rig.names) == set(seen_cal)
    for name, tf in seen_tf.items():
        assert tf.parent_frame_id == "rig"
        T = rig[name].T_rig_sensor
        q = tf.rotation
        R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
        t = tf.translation
        np.testing.assert_allclose([t.x, t.y, t.z], T[:3, 3], atol=1e-15)
    cal = seen_cal["thermal_left"]
    assert cal.distortion_model == "plumb_bob" and len(cal.D) == 5
    assert (cal.width, cal.height) == rig["thermal_left"].image_size
    np.testing.assert_array_equal(np.reshape(cal.K, (3, 3)), rig["thermal_left"].intrinsics.K)
    assert seen_cal["thermal_right"].distortion_model == "rational_polynomial"


# -- the writer -------------------------------------------------------------------------------


def test_writer_is_atomic_and_never_overwrites(tmp_path, rig):
    path = tmp_path / "a.mcap"
    frame = synth_frame(rig, "ccd_left", 0, np.random.default_rng(0))
    w = RecordingWriter(path, rig, jpeg_quality=50)
    w.write(frame)
    assert not path.exists() and w.temp_path.parent == tmp_path and w.temp_path.exists()
    w.close()
    assert path.exists() and not w.temp_path.exists() and list(tmp_path.iterdir()) == [path]
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        RecordingWriter(path, rig)
    # a file appearing while recording is not replaced either
    other = tmp_path / "b.mcap"
    w = RecordingWriter(other, rig)
    other.write_bytes(b"someone else's")
    with pytest.raises(FileExistsError, match="appeared while recording"):
        w.close()
    assert other.read_bytes() == b"someone else's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]


def test_writer_abort_and_exceptions_leave_no_file(tmp_path, rig):
    path = tmp_path / "a.mcap"
    with pytest.raises(ZeroDivisionError), RecordingWriter(path, rig):
        1 / 0  # noqa: B018
    assert list(tmp_path.iterdir()) == []
    w = RecordingWriter(path, rig)
    w.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(KeyboardInterrupt), RecordingWriter(path, rig) as w:
        w.write(synth_frame(rig, "tof", 7, np.random.default_rng(0)))
        raise KeyboardInterrupt
    assert path.exists()  # what was recorded is kept


def test_writer_checks_frames(tmp_path, rig):
    rng = np.random.default_rng(0)
    with RecordingWriter(tmp_path / "a.mcap", rig) as w:
        with pytest.raises(
            RecordingError, match="'nope': the sensor is not in the recording's rig"
        ):
            w.write(Frame("nope", 0, np.zeros((2, 2), np.float32)))
        with pytest.raises(RecordingError, match=r"expected an array of shape \(72, 96\)"):
            w.write(Frame("thermal_left", 0, np.zeros((10, 10), np.float32)))
        with pytest.raises(RecordingError, match=r"uint8 \(96, 128, 3\) RGB, got float32"):
            w.write(Frame("ccd_left", 0, np.zeros((96, 128, 3), np.float32)))
        with pytest.raises(RecordingError, match="stamp_ns: expected an integer"):
            w.write(Frame("ccd_left", 0.5, synth_frame(rig, "ccd_left", 0, rng).image))  # type: ignore[arg-type]
        with pytest.raises(RecordingError, match="has no distance_m"):
            f = synth_frame(rig, "thermal_left", 0, rng)
            w.write(Frame("thermal_left", 0, f.image, f.image))
        assert w.frames_written == 0
    with pytest.raises(RecordingError, match="jpeg_quality"):
        RecordingWriter(tmp_path / "b.mcap", rig, jpeg_quality=0)


def test_the_writer_keeps_its_chunks_within_what_a_reader_takes(tmp_path, rig):
    """A chunk holds at most ``chunk_size`` plus one message; both are bounded so that
    every chunk written is under the reader's cap (issue 29: chunks larger are refused)."""
    assert MAX_CHUNK_SIZE + MAX_MESSAGE_BYTES < MAX_CHUNK_BYTES
    with pytest.raises(
        RecordingError, match=f"chunk_size: expected an integer 1024..{MAX_CHUNK_SIZE}"
    ):
        RecordingWriter(tmp_path / "a.mcap", rig, chunk_size=MAX_CHUNK_SIZE + 1)
    s = rig["ccd_left"]
    big = Rig(
        sensors={**rig.sensors, "ccd_left": dataclasses.replace(s, image_size=(8000, 6000))},
        reference=rig.reference,
        eyes=rig.eyes,
    )
    with pytest.raises(
        RecordingError, match="'ccd_left': its 8000x6000 color frames take up to 144000000 bytes"
    ):
        RecordingWriter(tmp_path / "a.mcap", big)
    assert list(tmp_path.iterdir()) == []  # refused before any file


def test_write_set_skips_repeated_frames(tmp_path, rig):
    rng = np.random.default_rng(0)
    slow = synth_frame(rig, "tof", 0, rng)
    path = tmp_path / "a.mcap"
    with RecordingWriter(path, rig) as w:
        for k in range(3):
            fs = FrameSet(k * 33_333_333, {"tof": slow})
            fs.frames["ccd_left"] = synth_frame(rig, "ccd_left", k * 33_333_333, rng)
            w.write_set(fs)
        assert (w.frames_written, w.duplicates_skipped) == (4, 2)
    with ReplaySource(path, realtime=False) as src:
        assert [f.sensor for f in src.frames()].count("tof") == 1


# -- damage -----------------------------------------------------------------------------------


def _replay_all(path: Path, **kw) -> tuple[list[Frame], RecordingDamaged | None]:
    got: list[Frame] = []
    with ReplaySource(path, realtime=False, **kw) as src:
        try:
            for f in src.frames():
                got.append(f)
        except RecordingDamaged as exc:
            assert exc is src.damage
            return got, exc
    return got, None


def _check_prefix(got: list[Frame], frames: list[Frame]) -> None:
    """Every delivered frame is an original one, in order, with nothing skipped before it."""
    want = {(f.sensor, f.stamp_ns): f for f in frames}
    for f in got:
        assert_same_frame(f, want[(f.sensor, f.stamp_ns)])
    stamps = [f.stamp_ns for f in got]
    assert stamps == sorted(stamps)
    if got:
        last = got[-1].stamp_ns
        # everything strictly before the last delivered instant was delivered
        earlier = {(f.sensor, f.stamp_ns) for f in frames if f.stamp_ns < last}
        assert earlier <= {(f.sensor, f.stamp_ns) for f in got}


@pytest.mark.parametrize("fraction", [0.004, 0.05, 0.3, 0.5, 0.77, 0.95])
def test_truncated_recording_replays_up_to_the_cut(recorded, tmp_path, fraction):
    path, frames = recorded
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    got, damage = _replay_all(cut)
    assert damage is not None, "a truncated recording must say so"
    assert "truncated" in str(damage) and str(cut) in str(damage)
    assert damage.frames_delivered == len(got) < len(frames)
    _check_prefix(got, frames)
    if fraction >= 0.3:
        assert len(got) > len(frames) * (fraction - 0.25)


def test_recording_cut_after_its_data_plays_completely(recorded, tmp_path):
    path, frames = recorded
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:-100])  # inside the summary: every message is still there
    got, damage = _replay_all(cut)
    assert damage is None and len(got) == len(frames)
    with ReplaySource(cut) as src:
        assert src.index.indexed_by == "scan"
        assert any("truncated" in n for n in src.notes)


def test_truncated_recording_can_stop_with_a_warning(recorded, tmp_path, caplog):
    path, frames = recorded
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with (
        caplog.at_level(logging.WARNING),
        ReplaySource(cut, realtime=False, on_damage="stop") as src,
    ):
        got = list(src.frames())
        assert isinstance(src.damage, RecordingDamaged)
        assert src.rig is not None  # the rig attachment is at the start
    assert 0 < len(got) < len(frames)
    assert "recording damaged" in caplog.text


@pytest.mark.parametrize("fraction", [0.2, 0.45, 0.7, 0.9])
def test_corrupted_chunk_replays_up_to_the_damage(recorded, tmp_path, fraction):
    path, frames = recorded
    with ReplaySource(path) as src:
        chunks = src.index.chunks
    chunk = chunks[int(len(chunks) * fraction)]
    data = bytearray(path.read_bytes())
    i = chunk.offset + 9 + chunk.length // 2  # inside the chunk's compressed messages
    data[i : i + 3] = bytes(b ^ 0x5A for b in data[i : i + 3])
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    got, damage = _replay_all(bad)
    assert damage is not None and "corrupted" in damage.reason
    assert damage.offset == chunk.offset and f"at byte {chunk.offset}" in str(damage)
    _check_prefix(got, frames)
    assert {(f.sensor, f.stamp_ns) for f in frames if f.stamp_ns < chunk.start_ns} <= {
        (f.sensor, f.stamp_ns) for f in got
    }
    assert len(got) < len(frames)


@pytest.mark.parametrize("seed", range(6))
def test_flipped_bytes_anywhere_never_give_wrong_frames(recorded, tmp_path, seed):
    path, frames = recorded
    data = bytearray(path.read_bytes())
    rng = np.random.default_rng(seed)
    i = int(rng.integers(8, len(data) - 8))
    data[i] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    try:
        got, damage = _replay_all(bad)
    except RecordingError as exc:  # the header itself: not a recording any more
        assert i < 16, exc
        return
    _check_prefix(got, frames)
    if damage is None:  # the flip hit bytes no frame depends on
        assert len(got) == len(frames)


def test_damaged_summary_is_rebuilt_by_scanning(recorded, tmp_path):
    path, frames = recorded
    data = bytearray(path.read_bytes())
    data[-60] ^= 0xFF  # inside the summary section
    bad = tmp_path / "summary.mcap"
    bad.write_bytes(bytes(data))
    with ReplaySource(bad, realtime=False) as src:
        assert src.index.indexed_by == "scan"
        assert any("summary" in n for n in src.notes)
        got = list(src.frames())
    assert len(got) == len(frames)


def test_not_a_recording(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello, world, this is no mcap")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        ReplaySource(p)
    with pytest.raises(RecordingError, match="cannot open"):
        ReplaySource(tmp_path / "missing.mcap")


def test_recording_missing_a_sensor_plays_the_others(tmp_path, rig):
    frames = synth_frames(rig, 0.2, seed=5, skip=("thermal_right",))
    path = write_recording(tmp_path / "m.mcap", rig, frames)
    with ReplaySource(path, realtime=False) as src:
        assert "thermal_right" in src.sensors and "thermal_right" not in src.recorded_sensors
        assert any("thermal_right" in n for n in src.notes)
        sets = list(frame_sets(src, reference="ccd_left"))
    assert len(sets) == 6
    for fs in sets:
        assert "thermal_right" in fs.missing and "thermal_right" not in fs.frames
        assert "thermal_left" in fs.frames or fs is sets[0]


# -- rate, pause, seek, loop --------------------------------------------------------------------


def test_seek_by_fraction_and_stamp(recorded):
    path, frames = recorded
    with ReplaySource(path, realtime=False) as src:
        mid = src.seek(0.5)
        assert mid == src.start_ns + (src.end_ns - src.start_ns) // 2
        assert src.position_ns == mid
        got = list(src.frames())
        assert got[0].stamp_ns >= mid and len(got) < len(frames)
        assert {(f.sensor, f.stamp_ns) for f in got} == {
            (f.sensor, f.stamp_ns) for f in frames if f.stamp_ns >= mid
        }
        # seeking while iterating: back to the start
        it = src.frames()
        first = [next(it) for _ in range(10)]
        assert src.position_ns == first[-1].stamp_ns
        src.seek(src.start_ns)
        again = [next(it) for _ in range(10)]
        assert [(f.sensor, f.stamp_ns) for f in again] == [(f.sensor, f.stamp_ns) for f in first]
        assert src.seek(10**18) == src.end_ns and src.seek(0) == src.start_ns
        with pytest.raises(RecordingError, match="fraction"):
            src.seek(1.5)
        with pytest.raises(RecordingError, match="seek"):
            src.seek("middle")  # type: ignore[arg-type]


def test_loop_starts_again(recorded):
    path, frames = recorded
    with ReplaySource(path, realtime=False, loop=True) as src:
        it = src.frames()
        got = [next(it) for _ in range(2 * len(frames) + 5)]
    keys = [(f.sensor, f.stamp_ns) for f in got]
    n = len(frames)
    assert keys[:n] == keys[n : 2 * n] and keys[2 * n :] == keys[:5]


def test_rate_is_checked(recorded):
    path, _ = recorded
    with ReplaySource(path) as src:
        for bad in (0, -1, float("nan"), float("inf"), True):
            with pytest.raises(RecordingError, match="rate"):
                src.rate = bad
        src.rate = 0.5
        assert src.rate == 0.5


def _paced(path: Path, rate: float, busy_s: dict[int, float] | None = None) -> list[float]:
    """When each frame of a real-time replay at ``rate`` is released, on a simulated clock
    (its own seconds); ``busy_s``: how long the consumer takes after frame ``k``."""
    clock = FakeClock(100.0)
    released = []
    with ReplaySource(path, rate=rate, clock=clock, sleep=clock.sleep) as src:
        for k, _ in enumerate(src.frames()):
            released.append(clock.now)
            clock.advance((busy_s or {}).get(k, 0.0))
    return released


def test_realtime_pacing_follows_the_rate(tmp_path, rig):
    """Each frame is released when the clock reaches its log time, scaled by the rate."""
    rng = np.random.default_rng(0)
    frames = [synth_frame(rig, "tof", k * 1_000_000_000 // 15, rng) for k in range(10)]
    path = write_recording(tmp_path / "tof.mcap", rig, frames)
    offsets = [(f.stamp_ns - frames[0].stamp_ns) / 1e9 for f in frames]
    for rate in (1.0, 2.0, 0.5):
        released = _paced(path, rate)
        assert len(released) == len(frames)
        want = [released[0] + t / rate for t in offsets]
        assert released == pytest.approx(want, abs=1e-9), rate


def test_a_late_consumer_is_not_caught_up_in_a_burst(tmp_path, rig):
    """A consumer busy for longer than MAX_LAG_S gets the next frame at once, then the
    replay plays on at its rate from there: no burst of the frames it was late for."""
    rng = np.random.default_rng(0)
    frames = [synth_frame(rig, "tof", k * 1_000_000_000 // 15, rng) for k in range(8)]
    path = write_recording(tmp_path / "tof.mcap", rig, frames)
    gaps = np.diff([f.stamp_ns for f in frames]) / 1e9
    released = _paced(path, 1.0, busy_s={2: 1.0})
    assert len(released) == len(frames)  # late frames are delivered, not skipped
    steps = np.diff(released)
    assert steps[:2] == pytest.approx(gaps[:2], abs=1e-9)
    assert steps[2] == pytest.approx(1.0, abs=1e-9)  # at once when the consumer is back
    assert steps[3:] == pytest.approx(gaps[3:], abs=1e-9)  # re-anchored: at the rate


def test_a_consumer_late_by_less_than_the_lag_catches_up(tmp_path, rig):
    """Late by less than MAX_LAG_S, the replay keeps its schedule: the next frames come
    at once until it is on time again."""
    rng = np.random.default_rng(0)
    frames = [synth_frame(rig, "tof", k * 1_000_000_000 // 15, rng) for k in range(6)]
    path = write_recording(tmp_path / "tof.mcap", rig, frames)
    offsets = [(f.stamp_ns - frames[0].stamp_ns) / 1e9 for f in frames]
    late = 0.5 * MAX_LAG_S
    assert offsets[1] < late < offsets[-1]  # misses a frame's time, back on time later
    released = _paced(path, 1.0, busy_s={0: late})
    t0 = released[0]
    want = [t0] + [t0 + max(t, late) for t in offsets[1:]]
    assert released == pytest.approx(want, abs=1e-9)


def _slow_consumer(
    path: Path, busy_s: float, keep_time: bool
) -> tuple[list[tuple[float, Frame]], dict[str, int]]:
    """(release time, frame) of a real-time replay whose consumer spends ``busy_s`` (on a
    simulated clock) on each colour frame, and the frames the replay dropped."""
    clock = FakeClock(100.0)
    got = []
    with ReplaySource(path, clock=clock, sleep=clock.sleep, keep_time=keep_time) as src:
        for f in src.frames():
            got.append((clock.now, f))
            if f.sensor.startswith("ccd_"):
                clock.advance(busy_s)
        return got, src.dropped


@pytest.mark.parametrize("busy_s", [0.025, 0.4])
def test_keeping_time_drops_the_frames_a_slow_consumer_has_no_time_for(
    tmp_path, rig, monkeypatch, busy_s
):
    """A consumer that needs ``busy_s`` per colour frame (two cameras at 30 Hz: 50 ms of
    each 33, or 0.8 s, longer than a plain replay's MAX_LAG_S) slows a plain real-time
    replay down; with ``keep_time`` the replay stays on time (a frame is late by less than
    its period and one pair's work), every frame it gives was the
    newest of its sensor due when its instant was judged, the two cameras of an instant are
    kept or dropped together (and decoded on two threads, to the same pixels), and the frames
    it drops are counted, never decoded."""
    frames = synth_frames(rig, 1.0, seed=3)
    path = write_recording(tmp_path / "full.mcap", rig, frames)
    duration_s = (frames[-1].stamp_ns - frames[0].stamp_ns) / 1e9
    plain, none_dropped = _slow_consumer(path, busy_s, keep_time=False)
    assert len(plain) == len(frames) and none_dropped == {}
    assert plain[-1][0] - plain[0][0] > 1.4 * duration_s  # the clock slowed with the consumer

    decoded = []
    color_rgb = reader_module._DECODERS["color"]
    monkeypatch.setitem(
        reader_module._DECODERS,
        "color",
        lambda m, size=None: decoded.append(1) or color_rgb(m, size),
    )
    kept, dropped = _slow_consumer(path, busy_s, keep_time=True)
    t0 = kept[0][0]
    start_ns = frames[0].stamp_ns
    period_s = {
        s: float(np.median(np.diff([f.stamp_ns for f in frames if f.sensor == s]))) / 1e9
        for s in rig.sensors
    }
    last_ns = {s: max(f.stamp_ns for f in frames if f.sensor == s) for s in rig.sensors}
    for released, f in kept:  # behind by less than its period and one stereo pair's work
        if f.stamp_ns == last_ns[f.sensor]:
            continue  # the file's last: nothing newer to give instead, however late
        late_s = released - t0 - (f.stamp_ns - start_ns) / 1e9
        assert late_s < period_s[f.sensor] + 2 * busy_s + 1e-9, (f.sensor, late_s)
    colors = [f for _, f in kept if f.sensor.startswith("ccd_")]
    assert len(decoded) == len(colors)  # the dropped ones were never decoded
    n_color = sum(f.sensor.startswith("ccd_") for f in frames)
    assert dropped["ccd_left"] + dropped["ccd_right"] == n_color - len(colors) > 0
    assert dropped["ccd_left"] == dropped["ccd_right"]  # pairs kept or dropped together
    assert len(colors) / 2 <= duration_s / (2 * busy_s) + 2  # what the consumer has time for
    assert sum(dropped.values()) + len(kept) == len(frames)
    for released, f in kept:  # the newest due when its instant was judged (<= a pair's work ago)
        now_ns = start_ns + round((released - t0 - 2 * busy_s) * 1e9)
        newer = [
            g.stamp_ns for g in frames if g.sensor == f.sensor and f.stamp_ns < g.stamp_ns <= now_ns
        ]
        assert not newer, (f.sensor, f.stamp_ns, released - t0)
    for sensor in rig.sensors:  # each sensor's frames still come in time order
        stamps = [f.stamp_ns for _, f in kept if f.sensor == sensor]
        assert stamps == sorted(stamps) and len(stamps) >= 2
    with ReplaySource(path, realtime=False) as src:  # the pair decoded on two threads: the same
        every = {(f.sensor, f.stamp_ns): f for f in src.frames()}
    for _, f in kept:
        assert np.array_equal(f.image, every[f.sensor, f.stamp_ns].image, equal_nan=True)


def test_keeping_time_drops_nothing_for_a_consumer_on_time_and_seeks_cleanly(tmp_path, rig):
    """A consumer that keeps up loses no frame to ``keep_time``, before and after a seek."""
    frames = synth_frames(rig, 1.0, seed=4)
    path = write_recording(tmp_path / "seek.mcap", rig, frames)
    clock = FakeClock(100.0)
    with ReplaySource(path, clock=clock, sleep=clock.sleep, keep_time=True) as src:
        it = src.frames()
        first = [next(it) for _ in range(20)]
        clock.advance(0.004)  # a little work, well within a frame period
        mid = src.seek(0.5)
        rest = list(it)
        assert src.dropped == {}
    keys = [(f.sensor, f.stamp_ns) for f in first + rest]
    want = [(f.sensor, f.stamp_ns) for f in frames]
    assert keys[:20] == want[:20]
    assert keys[20:] == [k for k in want if k[1] >= mid]


def test_pause_and_resume(tmp_path, rig):
    """Paused after the third frame, the replay holds; resumed, it plays the rest at its
    rate from the moment of the resume (the pause is not caught up)."""
    rng = np.random.default_rng(0)
    frames = [synth_frame(rig, "tof", k * 20_000_000, rng) for k in range(20)]  # 0.4 s
    path = write_recording(tmp_path / "tof.mcap", rig, frames)
    clock = FakeClock(100.0)
    got: list[tuple[float, Frame]] = []
    paused = threading.Event()
    with ReplaySource(path, rate=1.0, clock=clock, sleep=clock.sleep) as src:

        def consume() -> None:
            for f in src.frames():
                got.append((clock.now, f))
                if len(got) == 3:
                    src.pause()  # before asking for the next frame
                    paused.set()

        worker = threading.Thread(target=consume)
        worker.start()
        assert paused.wait(WAIT_S)
        assert src.paused and src.position_ns == got[-1][1].stamp_ns
        clock.advance(60.0)  # a minute of pause: nothing comes, the clock is not caught up
        assert len(got) == 3 and src.position_ns == frames[2].stamp_ns
        resumed_at = clock.now
        src.resume()
        worker.join(WAIT_S)
        assert not worker.is_alive()
    assert [f.stamp_ns for _, f in got] == [f.stamp_ns for f in frames]
    after = [t for t, _ in got[3:]]
    assert after == pytest.approx([resumed_at + 0.02 * k for k in range(17)], abs=1e-9)


# -- the commands -----------------------------------------------------------------------------


def test_sim_schedule_renders_each_instant_once(rig):
    sched = sim_schedule(rig, 0.2)
    stamps = [s for s, _ in sched]
    assert stamps == sorted(set(stamps))
    per_sensor = {n: sum(n in sensors for _, sensors in sched) for n in rig.names}
    assert per_sensor == {
        "tof": 3,
        "ccd_left": 6,
        "ccd_right": 6,
        "thermal_left": 6,  # 0, 1/27 ... 5/27 < 0.2
        "thermal_right": 6,
    }
    # colour and TOF share instants exactly
    assert dict(sched)[1_000_000_000 // 15] == ["tof", "ccd_left", "ccd_right"]


def test_record_simulation_live_mode_frames_stamps_and_noise(tmp_path, rig):
    """The default (live) mode writes every sensor's frames at the sensors' own rates,
    rendering the head pose only at 5 Hz, each frame turned to its own instant with fresh
    noise; the exact mode's plan renders every instant."""
    duration = 0.5
    plan = plan_simulation(rig, duration)
    schedule = sim_schedule(rig, duration)
    assert plan.schedule == schedule and not plan.exact and plan.pose_hz == 5.0
    assert plan.poses == len({pose_index(s, 5.0) for s, _ in schedule}) == 3  # 0, .2, .4 s
    assert plan.renders == 3 * len(rig.names)
    exact = plan_simulation(rig, duration, exact=True)
    assert exact.renders == plan.frames == sum(len(s) for _, s in schedule)
    assert exact.estimate_s > plan.estimate_s

    seen = []
    out = tmp_path / "live.mcap"
    writer = record_simulation(out, rig, duration, seed=5, progress=seen.append)
    assert [p.index for p in seen] == list(range(1, len(schedule) + 1))
    assert all(p.eta_s >= 0 for p in seen) and seen[-1].eta_s == 0.0
    assert writer.frames_written == plan.frames
    frames: dict[str, list[Frame]] = {}
    with ReplaySource(out, realtime=False) as src:
        for f in src.frames():
            frames.setdefault(f.sensor, []).append(f)
    for name in rig.names:
        expected = [stamp for stamp, sensors in schedule if name in sensors]
        assert [f.stamp_ns for f in frames[name]] == expected, name
        rate = RATES_HZ[rig[name].modality]
        assert expected == [k * 1_000_000_000 // rate for k in range(len(expected))]
        w, h = rig[name].image_size
        assert all(f.image.shape[:2] == (h, w) for f in frames[name])
    # Colour frames 1 and 2 (1/30 and 2/30 s) reuse the render of pose 0 (t = 0), turned a
    # little (0.14 deg, 0.3 px here) and with fresh noise: they differ by about the noise.
    # Mid-grey (linear 0.3) has sigma = sqrt(0.004^2 + 0.0004 * 0.3) = 0.0117 linear, 2.6
    # levels after the gamma curve; two independent draws differ by sqrt(2) * sigma * sqrt(2
    # / pi) = 2.9 levels on average (bright walls a little more, JPEG q90 adds about 1).
    a, b = (frames["ccd_left"][i].image.astype(np.float64) for i in (1, 2))
    assert pose_index(frames["ccd_left"][1].stamp_ns, 5.0) == 0
    assert pose_index(frames["ccd_left"][2].stamp_ns, 5.0) == 0
    diff = np.abs(a - b)
    assert (diff > 0).mean() > 0.3 and diff.mean() < 6.0
    # Seeded: the same recording again is the same, frame for frame.
    again = tmp_path / "again.mcap"
    record_simulation(again, rig, duration, seed=5)
    with ReplaySource(again, realtime=False) as src:
        replayed = [f for f in src.frames() if f.sensor == "thermal_left"]
    pairs = zip(replayed, frames["thermal_left"], strict=True)
    assert all(np.array_equal(x.image, y.image) for x, y in pairs)


def test_record_sim_and_fuse_commands(tmp_path, rig, capsys):
    rig_path = save_rig(tmp_path / "rig.yaml", rig)
    out = tmp_path / "mission.mcap"
    code = main(
        [
            "record",
            "--source",
            "sim",
            "--out",
            str(out),
            "--duration",
            "0.07",
            "--rig",
            str(rig_path),
        ]
    )
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "Wrote" in printed.out
    # it says at the start how long it will take, and the progress lines give the time left
    first = printed.out.splitlines()[0]
    estimate = re.search(r"Estimated time: about (\d+) s \((\d+)x real time\)", first)
    assert estimate is not None, first
    plan = plan_simulation(rig, 0.07)
    assert int(estimate.group(1)) == round(plan.estimate_s) and 0 < plan.estimate_s < 60
    assert "head poses rendered at 5 Hz (1 poses" in first and "--exact" in first
    # in a pipe a few lines (app.cli.progress), the last one at the end
    progress = [line for line in printed.out.splitlines() if line.startswith("[")]
    n = len(sim_schedule(rig, 0.07))
    assert 1 <= len(progress) <= n and progress[-1].startswith(f"[{n}/{n}] t = ")
    assert all(re.search(r"elapsed \d+ s, ETA \d+ s$", line) for line in progress), progress
    assert progress[-1].endswith("ETA 0 s")
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schemas == {
        "foxglove.CompressedImage",
        "foxglove.RawImage",
        "foxglove.CameraCalibration",
        "foxglove.FrameTransform",
    }
    topics = {c.topic for c in summary.channels.values()}
    assert {
        "/ccd_left/image",
        "/thermal_left/temperature",
        "/tof/distance",
        "/tof/amplitude",
    } <= topics
    counts = {
        c.topic: summary.statistics.channel_message_counts[c.id] for c in summary.channels.values()
    }
    assert counts["/ccd_left/image"] == 3 and counts["/tof/distance"] == 2
    assert counts["/thermal_right/temperature"] == 2

    # refuses to overwrite; bad sources are one line and exit 2
    assert main(["record", "--source", "sim", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "exists; refusing to overwrite" in err and err.count("\n") == 1
    assert main(["record", "--source", "camera", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "expected 'sim', 'replay:FILE' or 'live:CONFIG'" in capsys.readouterr().err

    # re-record
    again = tmp_path / "again.mcap"
    assert main(["record", "--source", f"replay:{out}", "--out", str(again)]) == 0
    with ReplaySource(again, realtime=False) as src:
        assert src.rig == rig and len(list(src.frames())) == 3 + 3 + 2 + 2 + 2
    capsys.readouterr()

    # fuse
    fused = tmp_path / "fused"
    code = main(["fuse", str(out), "--rig", str(rig_path), "--out", str(fused), "--mode", "blend"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    jpgs = sorted(p.name for p in fused.glob("*.jpg"))
    assert jpgs == ["000000.jpg", "000001.jpg", "000002.jpg"]
    assert "3/3 frames" in printed.err and "[####" in printed.err
    import cv2

    img = cv2.imread(str(fused / "000000.jpg"))
    assert img.shape == (96, 2 * 128, 3)
    assert (fused / "frames.csv").read_text().count("\n") == 4
    if (fused / "fused.mp4").exists():
        assert "Video:" in printed.out
        cap = cv2.VideoCapture(str(fused / "fused.mp4"))
        assert cap.isOpened() and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3
    else:
        assert "No video" in printed.out
    # a non-empty DIR is refused; --every
    assert main(["fuse", str(out), "--out", str(fused)]) == 2
    assert "not empty" in capsys.readouterr().err
    fused2 = tmp_path / "fused2"
    assert main(["fuse", str(out), "--out", str(fused2), "--every", "2", "--mode", "edges"]) == 0
    assert len(list(fused2.glob("*.jpg"))) == 2


def test_fuse_a_damaged_recording_says_so(recorded, tmp_path, capsys):
    path, _ = recorded
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    code = main(["fuse", str(cut), "--out", str(tmp_path / "f"), "--every", "3"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "warning:" in printed.err and "truncated" in printed.err
    assert 0 < len(list((tmp_path / "f").glob("*.jpg"))) < 4


def test_fuse_with_nothing_to_fuse_is_an_error(tmp_path, capsys):
    rig = small_rig()
    rng = np.random.default_rng(3)
    frames = [synth_frame(rig, "tof", k * 66_666_667, rng) for k in range(5)]  # no colour
    path = write_recording(tmp_path / "tof-only.mcap", rig, frames)
    assert main(["fuse", str(path), "--out", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("trifuse: error: ") and "no frame set could be fused" in err
    assert list((tmp_path / "f").glob("*.jpg")) == []


def test_recording_benchmark_is_registered():
    from trifuse.app.devtools.bench import REGISTRY

    assert "recording" in REGISTRY


def test_record_live_cameras_from_a_config(tmp_path):
    """`trifuse record --source live:CONFIG`: OpenCV devices (here a video file and a
    16-bit PNG sequence) recorded for a duration, then replayed."""
    from trifuse.app.cli import main as cli_main
    from trifuse.app.sources.sim.head import default_rig
    from trifuse.app.storage.rigfile import save_rig
    from trifuse.calib.rig import Rig

    full = default_rig()
    rig = Rig({n: full[n] for n in ("tof", "ccd_left", "thermal_left")}, "tof")
    save_rig(tmp_path / "rig.yaml", rig)
    writer = cv2.VideoWriter(
        str(tmp_path / "ccd.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30, (1280, 960)
    )
    assert writer.isOpened()
    for k in range(20):
        writer.write(np.full((960, 1280, 3), 10 * k, np.uint8))
    writer.release()
    (tmp_path / "th").mkdir()
    for k in range(10):
        cv2.imwrite(
            str(tmp_path / "th" / f"f_{k:03d}.png"), np.full((288, 382), 30000 + k, np.uint16)
        )
    (tmp_path / "cams.yaml").write_text(
        "format: trifuse-cameras/1\n"
        "sensors:\n"
        "  ccd_left: {device: ccd.avi, max_rate_hz: 30, loop: true}\n"
        "  thermal_left: {device: th/f_%03d.png, max_rate_hz: 27, loop: true}\n"
    )
    out = tmp_path / "live.mcap"
    assert (
        cli_main(
            [
                "record",
                "--source",
                f"live:{tmp_path / 'cams.yaml'}",
                "--rig",
                str(tmp_path / "rig.yaml"),
                "--duration",
                "1.0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    with ReplaySource(out, realtime=False) as src:
        frames = list(src.frames())
    sensors = {f.sensor for f in frames}
    assert sensors == {"ccd_left", "thermal_left"}
    thermal = [f for f in frames if f.sensor == "thermal_left"]
    assert 300.0 <= float(thermal[0].image[0, 0]) <= 300.1  # 30000..30009 centi-kelvin
    assert len([f for f in frames if f.sensor == "ccd_left"]) >= 10
