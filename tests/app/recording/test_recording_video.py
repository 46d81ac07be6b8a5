"""The fused stereo picture kept in recordings as H.264 (``/fused/video``,
``foxglove.CompressedVideo``): ``trifuse record --fused-video`` and the console's Record with
"Record fused video". The track is what Foxglove plays (one Annex B access unit per message,
the first a key frame with SPS and PPS, no B-frames), its pictures are the fused frames they
came from, the readers skip it, and a failure of the video never costs the sensors'
recording."""

from __future__ import annotations

import contextlib
import io
import itertools
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import av
import cv2
import numpy as np
import pytest
import viser
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from viser import GuiEvent

from tests.support import run_cli, small_rig, synth_frame, synth_frames, wait_until, write_recording
from trifuse.app.cli import main
from trifuse.app.devtools.image_quality import psnr, ssim
from trifuse.app.recording import RecordingError, RecordingWriter, ReplaySource
from trifuse.app.recording.layout import FUSED_VIDEO_TOPIC, parse_topic
from trifuse.app.recording.recorder import Recorder
from trifuse.app.recording.video_track import (
    FusedVideoEncoder,
    FusedVideoFuser,
    VideoSettings,
    nal_types,
)
from trifuse.app.server.panels.source import SourcePanel
from trifuse.app.server.runtime.board_watch import BoardWatch
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.fused_video_tap import FusedVideoSource
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.source_control import SourceControl
from trifuse.app.server.runtime.source_tap import SourceTap
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.base import FrameSetAssembler, frame_sets
from trifuse.app.storage.rigfile import save_rig
from trifuse.calib.board import Board
from trifuse.calib.rig import Rig
from trifuse.fusion.stereo_step import CONSOLE, Skip, StereoStep

DURATION_S = 2.5
SPS, PPS, IDR = 7, 8, 5


@pytest.fixture(scope="module")
def rig() -> Rig:
    return small_rig()


@pytest.fixture(scope="module")
def base(tmp_path_factory, rig) -> Path:
    """A recording of the sensors only (seeded)."""
    path = tmp_path_factory.mktemp("video") / "sensors.mcap"
    return write_recording(path, rig, synth_frames(rig, DURATION_S, seed=11))


@pytest.fixture(scope="module")
def with_video(base, tmp_path_factory) -> Path:
    """``base`` re-recorded with ``--fused-video`` (the CLI's replay path)."""
    out = tmp_path_factory.mktemp("video") / "with_video.mcap"
    argv = ["record", "--source", f"replay:{base}", "--out", str(out), "--fused-video"]
    assert main(argv) == 0
    return out


def video_messages(path: Path) -> list[tuple[int, object]]:
    """(log time, decoded foxglove.CompressedVideo) of ``/fused/video``, in file order."""
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [
            (m.log_time, msg)
            for _s, _c, m, msg in reader.iter_decoded_messages(topics=[FUSED_VIDEO_TOPIC])
        ]


def decode_all(messages: list[tuple[int, object]]) -> list[np.ndarray]:
    """Each message through one PyAV H.264 decoder from the first on: exactly one picture
    each, (H, W, 3) uint8 BGR."""
    decoder = av.CodecContext.create("h264", "r")
    pictures = []
    for _t, msg in messages:
        frames = decoder.decode(av.Packet(msg.data))
        assert len(frames) == 1  # one access unit, one picture, no reordering (no B-frames)
        pictures.append(frames[0].to_ndarray(format="bgr24"))
    return pictures


def fused_pictures(path: Path, rig: Rig) -> dict[int, np.ndarray]:
    """stamp -> the fused picture (BGR) of every frame set of a recording's sensors, made
    as the recorder makes them (the console's grouping, step and rules)."""
    step = StereoStep(rig, policy=CONSOLE)
    out = {}
    with ReplaySource(path, realtime=False) as src:
        asm = FrameSetAssembler.stereo(step.sensors)
        sets = [fs for f in src.frames() for fs in asm.push(f)] + list(asm.flush())
    for fs in sets:
        rgb = step.picture(fs)
        if not isinstance(rgb, Skip):
            out[fs.stamp_ns] = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    return out


# -- the track in the file ------------------------------------------------------------------


def test_the_track_has_foxglove_compressed_video(with_video, rig) -> None:
    with with_video.open("rb") as f:
        summary = make_reader(f).get_summary()
    (ch,) = [c for c in summary.channels.values() if c.topic == FUSED_VIDEO_TOPIC]
    schema = summary.schemas[ch.schema_id]
    assert schema.name == "foxglove.CompressedVideo"
    assert schema.encoding == "protobuf" and ch.message_encoding == "protobuf"
    assert ch.metadata["trifuse.kind"] == "fused_video"
    assert ch.metadata["trifuse.frame"] == rig.eyes["left"].color == "ccd_left"
    assert "trifuse.sensor" not in ch.metadata and parse_topic(FUSED_VIDEO_TOPIC) is None
    # one picture per left colour frame set: 30 Hz over the recording
    assert summary.statistics.channel_message_counts[ch.id] == round(30 * DURATION_S)


def test_messages_are_single_access_units_foxglove_plays_from_the_first(with_video) -> None:
    messages = video_messages(with_video)
    pictures = decode_all(messages)  # from the very first message on
    assert all(p.shape == (96, 2 * 128, 3) for p in pictures)
    first = messages[0][1]
    assert first.format == "h264" and first.frame_id == "ccd_left"
    types = nal_types(first.data)
    assert {SPS, PPS, IDR} <= set(types) and types.index(SPS) < types.index(IDR)
    assert first.data.startswith(b"\x00\x00\x00\x01")  # Annex B
    stamps = [t for t, _ in messages]
    assert all(a < b for a, b in itertools.pairwise(stamps))  # increasing
    for t, msg in messages:  # the schema's timestamp is the log time, the picture's stamp
        assert msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos == t
    # a key frame (IDR with SPS and PPS) every second of picture time, so Foxglove seeks
    keys = [t for t, msg in messages if IDR in nal_types(msg.data)]
    for t, msg in messages:
        has_sps = SPS in nal_types(msg.data)
        assert has_sps == (t in keys) and (PPS in nal_types(msg.data)) == has_sps
    assert len(keys) == int(DURATION_S) + 1  # at 1.0, 2.0 ... s after the first
    gaps_s = np.diff(keys) / 1e9
    assert np.all((gaps_s >= 1.0) & (gaps_s < 1.0 + 1.5 / 30))


def yuv420_psnr(bgr: np.ndarray) -> float:
    """PSNR of a picture through YUV 4:2:0 and back, without any coding: what the video's
    colour format alone costs (the best an H.264 picture of it can get)."""
    yuv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)
    return psnr(bgr, cv2.cvtColor(yuv, cv2.COLOR_YUV2BGR_I420))


def test_decoded_pictures_are_the_fused_frames(with_video, base, rig) -> None:
    """Each decoded picture is the fused frame of its set. The tolerance follows from the
    bitrate: 10 Mbit/s for a 256 x 96 picture at 30 Hz is 13 bits a pixel, so x264 loses
    next to nothing beyond the 4:2:0 colour format (41 dB here on its own): within 2 dB of
    it (measured: 1.3 dB below). At 0.2 Mbit/s (0.27 bits a pixel) the coding shows
    (measured: 34 dB). The full 2560 x 960 picture at 10 Mbit/s (1.3 bits a pixel) gets
    about 41 dB on the simulated scene (docs/FORMATS.md)."""
    want = fused_pictures(base, rig)
    messages = video_messages(with_video)
    assert [t for t, _ in messages] == sorted(want)  # every fused frame, at its set's stamp
    got = decode_all(messages)
    for (t, _), picture in zip(messages, got, strict=True):
        bound = yuv420_psnr(want[t])
        assert psnr(want[t], picture) > bound - 2.0, (t, psnr(want[t], picture), bound)
        assert ssim(want[t], picture) > 0.97
    # a lower bitrate costs quality, as it should
    enc = FusedVideoEncoder(VideoSettings(bitrate_bps=200_000))
    decoder = av.CodecContext.create("h264", "r")
    low, high = [], []
    for (t, _), picture in zip(messages, got, strict=True):
        (frame,) = decoder.decode(av.Packet(enc.encode(want[t], t).data))
        low.append(psnr(want[t], frame.to_ndarray(format="bgr24")))
        high.append(psnr(want[t], picture))
    assert 25.0 < np.mean(low) < np.mean(high) - 3.0


def test_readers_and_fuse_skip_the_video(with_video, base, tmp_path, capsys) -> None:
    with ReplaySource(with_video, realtime=False) as a, ReplaySource(base, realtime=False) as b:
        assert a.sensors == b.sensors and a.notes == [] and a.rig == b.rig
        got = [(f.sensor, f.stamp_ns) for f in a.frames()]
        assert got == [(f.sensor, f.stamp_ns) for f in b.frames()]
        assert a.message_count("ccd_left", "color") == b.message_count("ccd_left", "color")
    code, out, err = run_cli(["fuse", str(with_video), "--out", str(tmp_path / "f")], capsys)
    assert code == 0, err
    code, _, err = run_cli(["fuse", str(base), "--out", str(tmp_path / "g")], capsys)
    assert code == 0, err
    assert len(list((tmp_path / "f").glob("*.jpg"))) == len(list((tmp_path / "g").glob("*.jpg")))
    # re-recording a recording with video keeps its frames (the video only when asked)
    again = tmp_path / "again.mcap"
    argv = ["record", "--source", f"replay:{with_video}", "--out", str(again)]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert FUSED_VIDEO_TOPIC not in out


def test_record_sim_with_fused_video(tmp_path, rig, capsys) -> None:
    rig_path = save_rig(tmp_path / "rig.yaml", rig)
    out_path = tmp_path / "sim.mcap"
    argv = ["record", "--source", "sim", "--out", str(out_path), "--duration", "0.2"]
    argv += ["--rig", str(rig_path), "--fused-video", "--video-mbps", "4", "--video-mode", "edges"]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "Fused video: 6 pictures of 6 frame sets on /fused/video (H.264, 4 Mbit/s" in out
    assert "foxglove.CompressedVideo" in out and "warning" not in err
    messages = video_messages(out_path)
    assert len(decode_all(messages)) == 6
    with out_path.open("rb") as f:
        channels = make_reader(f).get_summary().channels.values()
    (ch,) = [c for c in channels if c.topic == FUSED_VIDEO_TOPIC]
    assert ch.metadata["trifuse.bitrate_bps"] == "4000000"
    code, out, err = run_cli([*argv[:5], "--fused-video", "--video-mbps", "0"], capsys)
    assert code == 2 and "--video-mbps" in err and "0.1 to 100" in err


def test_a_failing_encoder_never_costs_the_sensor_recording(rig, tmp_path, monkeypatch) -> None:
    frames = synth_frames(rig, 0.5, seed=2)

    def broken(self, bgr, stamp_ns):
        raise RuntimeError("the encoder broke")

    monkeypatch.setattr(FusedVideoEncoder, "encode", broken)
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, rig) as writer:
        fuser = FusedVideoFuser(writer)
        writer.observers.append(fuser)
        for f in frames:
            writer.write(f)
    assert fuser.error is not None and "the encoder broke" in fuser.error
    with ReplaySource(path, realtime=False) as src:
        assert len(list(src.frames())) == len(frames)


def test_the_track_keeps_the_chain_whole(rig, tmp_path) -> None:
    enc = FusedVideoEncoder(VideoSettings(keyint_s=1.0))
    pic = np.full((96, 256, 3), 128, np.uint8)
    a, b, c = (enc.encode(pic, s) for s in (10**9, 10**9 + 33_000_000, 10**9 + 66_000_000))
    assert a.key and not b.key and not c.key
    with RecordingWriter(tmp_path / "t.mcap", rig, fused_video=True) as w:
        track = w.fused_video
        assert not w.write_video(b.data, b.key, b.stamp_ns)  # no key frame yet
        assert w.write_video(a.data, a.key, a.stamp_ns + 1)
        assert not w.write_video(c.data, c.key, a.stamp_ns)  # back in time: refused ...
        assert track.awaiting_key and not w.write_video(c.data, c.key, c.stamp_ns)  # ... till a key
        with pytest.raises(RecordingError, match="Annex B"):
            w.write_video(b"\x01\x02\x03\x04\x05", True, c.stamp_ns)
        w.write(synth_frame(rig, "ccd_left", 10**9, np.random.default_rng(0)))
        assert (track.written, track.skipped) == (1, 3)
    with pytest.raises(ValueError, match="bitrate_bps"):
        VideoSettings(bitrate_bps=50)
    with pytest.raises(ValueError, match="keyint_s"):
        VideoSettings(keyint_s=0.0)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        enc.encode(np.zeros((96, 256), np.uint8), 2 * 10**9)


# -- the console ------------------------------------------------------------------------------


def _frames_of_file(path: str) -> tuple[list[int], list[bool]]:
    msgs = video_messages(Path(path))
    decode_all(msgs)  # every file decodes from its first message on
    return [t for t, _ in msgs], [IDR in nal_types(m.data) for _, m in msgs]


def test_console_video_survives_a_replay_going_back(rig, tmp_path) -> None:
    """Pictures go to the file of their time: when the source's time goes back, the new
    file's video starts with a key frame, and a late picture from before the jump is not
    written into it."""
    hub, demand = FrameHub(), Demand("fusion")
    recorder = Recorder(tmp_path / "rec")
    recorder.start(rig, FusedVideoSource(hub, demand, VideoSettings()))
    assert demand.wanted and hub.takers  # the console fuses; the recorder takes its pictures
    rng = np.random.default_rng(4)
    period = 1_000_000_000 // 30
    stamps = [1_000_000_000 + k * period for k in range(20)]
    published = 0

    def picture(stamp: int) -> None:
        nonlocal published
        bgr = np.full((96, 256, 3), 60, np.uint8)
        bgr[:, : (stamp // period) % 256] = 200  # a bar that grows with time
        bgr.flags.writeable = False
        hub.publish(b"", {"stamp_ns": stamp}, bgr=bgr)
        published += 1
        wait_until(
            lambda: (
                (lambda s: s.video_frames_written + s.video_frames_skipped)(recorder.state())
                == published
            ),
            "the picture written or refused",
        )

    for s in stamps:
        recorder.offer(synth_frame(rig, "ccd_left", s, rng))
        picture(s)
    recorder.offer(synth_frame(rig, "ccd_left", stamps[0], rng))  # the replay looped
    picture(stamps[-1] + period)  # a picture fused before the jump, published after it
    for s in stamps[:10]:
        if s != stamps[0]:
            recorder.offer(synth_frame(rig, "ccd_left", s, rng))
        picture(s)
    state = recorder.stop()
    assert hub.takers == [] and not demand.wanted  # released
    assert state.fused_video and state.video_error is None and len(state.files) == 2
    assert (state.video_frames_written, state.video_frames_skipped) == (30, 1)
    first, second = (_frames_of_file(f) for f in state.files)
    assert first[0] == stamps and second[0] == stamps[:10]
    assert first[1][0] and second[1][0]  # each file starts with a key frame


def test_console_video_failure_keeps_recording_sensors(rig, tmp_path, monkeypatch) -> None:
    def broken(self, bgr, stamp_ns):
        raise RuntimeError("no encoder here")

    monkeypatch.setattr(FusedVideoEncoder, "encode", broken)
    hub = FrameHub()
    recorder = Recorder(tmp_path / "rec")
    recorder.start(rig, FusedVideoSource(hub))
    rng = np.random.default_rng(5)
    hub.publish(b"", {"stamp_ns": 10**9}, bgr=np.zeros((96, 256, 3), np.uint8))
    wait_until(lambda: recorder.state().video_error is not None, "the video error")
    for k in range(5):
        recorder.offer(synth_frame(rig, "thermal_left", 10**9 + k * 37_000_000, rng))
    state = recorder.stop()
    assert state.frames_written == 5 and "no encoder here" in state.video_error
    assert state.error.startswith("fused video stopped (the sensors are still recorded)")
    assert hub.takers == []
    with ReplaySource(state.files[0], realtime=False) as src:
        assert len(list(src.frames())) == 5


def _server() -> viser.ViserServer:
    with contextlib.redirect_stdout(io.StringIO()):
        return viser.ViserServer(host="127.0.0.1", port=0, verbose=False)


def _fire(handle, value: object | None = None) -> None:
    """What a browser does to a GUI element: a new value (if any), its callbacks."""
    if value is not None:
        handle._impl.value = value
    for cb in handle._impl.update_cb:
        cb(GuiEvent(client=SimpleNamespace(), client_id=1, target=handle))


@pytest.fixture()
def console(base, rig, tmp_path) -> Iterator[tuple[SourcePanel, SourceControl, Path]]:
    """A console replaying ``base`` in a loop, with a work directory; nobody watches."""
    replay = ReplaySource(base, loop=True, realtime=True)
    demand = Demand("fusion")
    hub = FrameHub(demand)
    pipeline = FusionPipeline(SourceTap(replay), rig, hub, demand=demand).start()
    control = SourceControl(pipeline, hub, "replay", tmp_path / "work")
    server = _server()
    board = Board(9, 6, 0.04)
    ctx = ConsoleContext(
        server=server,
        source=pipeline.source,
        description="test",
        hub=hub,
        pipeline=pipeline,
        board=board,
        board_watch=BoardWatch(lambda: None, rig, board),
    )
    panel = SourcePanel(ctx, control)  # not started: ticks by hand
    try:
        yield panel, control, base
    finally:
        control.stop()
        pipeline.stop()
        server.stop()


def test_console_record_keeps_the_fused_video(console) -> None:
    """The Source panel's "Record fused video", then Record: nobody watches the stream,
    yet the console fuses while it records, and the file keeps what it published."""
    panel, control, base = console
    assert panel.record_video.value is False and control.fused_video is False
    _fire(panel.record_video, True)
    assert control.fused_video
    _fire(panel.record)
    assert panel.record.label == "Stop recording" and panel.record_video.disabled
    wait_until(lambda: control.recording_state().video_frames_written >= 20, "20 pictures")
    panel.tick()
    assert "fused video:" in panel.recording.content
    _fire(panel.record)
    state = control.recording_state()
    assert not state.active and state.fused_video and state.video_error is None
    assert not panel.record_video.disabled and control.hub.takers == []
    assert not control.pipeline.demand.wanted  # the recording's hold is released
    with ReplaySource(base, realtime=False) as src:
        sets = {fs.stamp_ns for fs in frame_sets(src, reference="ccd_left")}
    pictures = 0
    for path in state.files:  # more than one if the replay looped meanwhile
        stamps, keys = _frames_of_file(path)
        assert keys[:1] in ([], [True])  # each file's video starts with a key frame
        assert set(stamps) <= sets  # each picture at the stamp of the set it shows
        with ReplaySource(path, realtime=False) as src:  # the sensors are there as before
            assert src.sensors == ["tof", "ccd_left", "ccd_right", "thermal_left", "thermal_right"]
            assert sum(1 for _ in src.frames()) > 0
        pictures += len(stamps)
    assert pictures == state.video_frames_written >= 20
