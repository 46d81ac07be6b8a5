"""The console, ``trifuse fuse`` and the recorded fused video make the same pictures from
the same frames (one stereo-picture step: fusion.stereo_step), also where sensors are
missing: a thermal imager, both, a colour camera (for less and for more than COLOR_GONE_S),
the TOF (before its first frame, and a stretch without it: TOF stamps that do not change).

The frames come from one recording (colour through JPEG), read back once and handed to
each path; pictures are compared before any encoding: the console's BGR, the video's RGB
(the step as ``record --fused-video`` runs it, what it encodes), and ``fuse``'s JPEG against the
console's picture encoded the same way.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from support import WAIT_S, ListSource, small_rig, synth_frames, write_recording

from trifuse.app.recording import ReplaySource
from trifuse.app.recording.fuse import JPEG_QUALITY, FusedFrame, PieceEnd, fuse_piece
from trifuse.app.recording.pieces import FusePiece
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.base import FrameSetAssembler
from trifuse.app.sources.frames import Frame
from trifuse.calib.rig import Rig
from trifuse.fusion.compose import DisplaySettings
from trifuse.fusion.geometry import tof_sensor_name
from trifuse.fusion.stereo_step import (
    COLOR_GONE_S,
    CONSOLE,
    OFFLINE,
    MissingSensors,
    Skip,
    StereoStep,
)

START_NS = 1_000_000_000
GAPS_S = {  # sensor -> stretches (seconds from the start) without its frames
    "tof": [(0.0, 0.1), (1.6, 1.9)],
    "thermal_right": [(0.3, 0.5), (0.6, 0.75)],
    "thermal_left": [(0.6, 0.75)],
    "ccd_right": [(0.8, 1.5)],  # longer than COLOR_GONE_S: its eye goes black
}
SETTINGS = DisplaySettings()  # the console's: blend, a smoothed automatic span


def _dropped(f: Frame) -> bool:
    t = (f.stamp_ns - START_NS) / 1e9
    return any(a <= t < b for a, b in GAPS_S.get(f.sensor, ()))


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> tuple[list[Frame], Rig, Path]:
    """The frames of a recording with gaps, as the replay reads them, and its rig."""
    rig = small_rig()
    path = tmp_path_factory.mktemp("same") / "gaps.mcap"
    kept = [f for f in synth_frames(rig, 2.2, seed=3, start_ns=START_NS) if not _dropped(f)]
    write_recording(path, rig, kept)
    with ReplaySource(path, realtime=False) as src:
        return list(src.frames()), rig, path


def _video(frames, rig, settings) -> tuple[dict[int, np.ndarray], list]:
    """stamp -> the recorded video's picture (RGB, before encoding); and every set."""
    step = StereoStep(rig, settings, CONSOLE)
    asm = FrameSetAssembler.stereo(step.sensors)
    sets = [fs for f in frames for fs in asm.push(f)] + list(asm.flush())
    out = {}
    for fs in sets:
        rgb = step.picture(fs)
        if not isinstance(rgb, Skip):
            out[fs.stamp_ns] = rgb.copy()
    return out, sets


def _console(frames, rig, settings) -> dict[int, np.ndarray]:
    """stamp -> the console's picture (BGR as published). A late colour frame after the
    recording's end closes its last frame set (the console waits for the next frame)."""
    left = [f for f in frames if f.sensor == rig.eyes["left"].color]
    late = Frame(left[-1].sensor, frames[-1].stamp_ns + 10**10, left[-1].image)
    hub = FrameHub()
    got: dict[int, np.ndarray] = {}
    hub.takers.append(lambda fr: got.setdefault(fr.meta["stamp_ns"], fr.bgr))
    pipeline = FusionPipeline(ListSource([*frames, late], rig=rig), rig, hub, settings).start()
    try:
        assert pipeline.join(WAIT_S), "the console's pipeline did not finish the frames"
    finally:
        pipeline.stop()
    assert pipeline.status.error is None
    return got


def _fuse(path: Path, rig, settings, policy: MissingSensors) -> tuple[dict[int, bytes], PieceEnd]:
    piece = FusePiece(str(path), 0, None, 0, 0, None, None)
    with ReplaySource(path, realtime=False) as src:
        items = list(fuse_piece(src, rig, piece, settings, policy=policy))
    end = items.pop()
    assert isinstance(end, PieceEnd) and all(isinstance(i, FusedFrame) for i in items)
    return {i.meta.stamp_ns: i.jpeg for i in items}, end


def test_console_fuse_and_video_make_the_same_pictures(frames) -> None:
    frames, rig, path = frames
    video, sets = _video(frames, rig, SETTINGS)
    console = _console(frames, rig, SETTINGS)
    fused, end = _fuse(path, rig, SETTINGS, CONSOLE)

    # the same sets make pictures everywhere: all but those within COLOR_GONE_S of the last
    # set with the right colour camera (a late frame: the console waits)
    right = rig.eyes["right"].color
    gone = [fs.stamp_ns for fs in sets if right not in fs]
    seen = max(fs.stamp_ns for fs in sets if right in fs and fs.stamp_ns < gone[0])
    waiting = {s for s in gone if s - seen <= COLOR_GONE_S * 1e9}
    assert len(waiting) > 10 and len(gone) > len(waiting) + 3  # some wait, later ones: black
    assert set(video) == set(console) == set(fused) == {fs.stamp_ns for fs in sets} - waiting
    for stamp, bgr in console.items():
        np.testing.assert_array_equal(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), video[stamp])
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        assert ok and jpeg.tobytes() == fused[stamp], stamp

    # what the gaps show: colour images side by side before the first depth; for the camera
    # gone, the palette blended over black (at most the opacity's share of full scale; the
    # fallback veil adds a few levels)
    w = rig[right].image_size[0]
    first = next(f for f in frames if f.sensor == rig.eyes["left"].color)
    np.testing.assert_array_equal(video[first.stamp_ns][:, :w], first.image)
    black = [s for s in gone if s not in waiting]
    dim = SETTINGS.opacity * 255 + 8
    assert black and all(video[s][:, w:].max() <= dim < video[s][:, :w].max() for s in black)
    # each TOF frame updates the mapping once, however many sets share its stamp
    tof = tof_sensor_name(rig)
    tofs = {fs[tof].stamp_ns for fs in sets if tof in fs}
    assert end.tof_updates == len(tofs) < sum(tof in fs for fs in sets)
    assert end.skipped == {f"no frame of {right}": len(waiting)}


def test_offline_fuse_keeps_the_complete_sets_with_the_consoles_pictures(frames) -> None:
    frames, rig, path = frames
    settings = DisplaySettings(span_smoothing_s=0.0)  # each picture its own span: comparable
    video, sets = _video(frames, rig, settings)
    fused, end = _fuse(path, rig, settings, OFFLINE)
    images = [s for e in ("left", "right") for s in (rig.eyes[e].color, rig.eyes[e].thermal)]
    tof_seen = next(i for i, fs in enumerate(sets) if tof_sensor_name(rig) in fs)
    complete = {fs.stamp_ns for fs in sets[tof_seen:] if all(s in fs for s in images)}
    assert set(fused) == complete and len(complete) < len(sets) - 10
    for stamp, jpeg in fused.items():
        bgr = cv2.cvtColor(video[stamp], cv2.COLOR_RGB2BGR)
        ok, want = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        assert ok and want.tobytes() == jpeg, stamp
    assert sum(end.skipped.values()) == len(sets) - len(complete)
    assert set(end.skipped) == {
        "no TOF frame yet",
        "no frame of thermal_right",
        "no frame of thermal_left, thermal_right",
        "no frame of ccd_right",
    }


@pytest.mark.parametrize(
    "kw",
    [
        {"color_gone_s": -1.0},
        {"color_gone_s": float("nan")},
        {"thermal": "grey"},
        {"no_depth": "wait"},
    ],
)
def test_a_policy_refuses_what_it_does_not_know(kw) -> None:
    with pytest.raises(ValueError, match=next(iter(kw))):
        MissingSensors(**kw)
