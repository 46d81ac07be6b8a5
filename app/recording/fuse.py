"""Offline fusion of a whole recording (``trifuse fuse``): JPEG frames and a video.

The recording is replayed as fast as possible and grouped into frame sets around the left
eye's colour frames (:func:`app.sources.base.frame_sets`). Each new TOF frame updates both
eyes' mappings (:meth:`fusion.stereo.StereoFusion.update_depth`, with the rig's range
correction); every ``every``-th set with both eyes' colour and thermal frames (through the
rig's radiometry) is composed into the side-by-side picture, which
is written as ``DIR/NNNNNN.jpg`` and appended to ``DIR/fused.mp4`` (OpenCV ``mp4v``, when
that codec is at hand). ``DIR/frames.csv`` lists each picture's time stamps.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from app.recording.errors import RecordingDamaged, RecordingError
from app.recording.player import MessageReplay
from app.sources.base import frame_sets
from app.storage.atomic import atomic_write_bytes, atomic_write_text, fsync_dir
from calib.radiometry import Radiometry
from calib.rig import Rig
from fusion.compose import DisplaySettings
from fusion.stereo import EYE_ORDER, StereoFusion

VIDEO_NAME = "fused.mp4"
JPEG_QUALITY = 90


@dataclass
class FuseResult:
    """What :func:`fuse_recording` did.

    Attributes:
        frames: pictures written (JPEGs, and video frames if ``video``).
        sets: colour reference frame sets seen.
        tof_updates: TOF frames used to update the mapping.
        skipped: reason -> count of sets chosen for composing but not composed.
        video: the video's path, or None.
        video_problem: why there is no video.
        fps: the video's frame rate.
        damage: the recording's damage, if the replay stopped at one.
    """

    frames: int = 0
    sets: int = 0
    tof_updates: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    video: Path | None = None
    video_problem: str | None = None
    fps: float = 30.0
    damage: RecordingDamaged | None = None


def expected_sets(source: MessageReplay, rig: Rig) -> tuple[int | None, float | None]:
    """(number of reference colour frames, their rate in Hz) from the file's statistics."""
    ref = rig.eyes[EYE_ORDER[0]].color
    count = getattr(source, "message_count", lambda *_: None)(ref, "color")
    rate = (count - 1) / source.duration_s if count and count > 1 and source.duration_s else None
    return count, rate


def fuse_recording(
    source: MessageReplay,
    rig: Rig,
    out_dir: str | Path,
    settings: DisplaySettings,
    every: int = 1,
    progress: Callable[[int, int | None], None] | None = None,
) -> FuseResult:
    """Fuse ``source`` (replayed as fast as possible) into ``out_dir`` (must exist, empty).

    ``progress(pictures_done, pictures_expected_or_None)`` is called after each set
    considered for composing. Damage in the recording ends the fusion where it is; the
    result's ``damage`` says so (nothing is raised for it).
    """
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    out_dir = Path(out_dir)
    fusion = StereoFusion(rig)
    eyes = {e: rig.eyes[e] for e in EYE_ORDER}
    tof = fusion.tof
    radiometry = {e.thermal: rig[e.thermal].radiometry or Radiometry() for e in eyes.values()}
    kelvin = {n: np.empty(rig[e.thermal].image_size[::-1], np.float32) for n, e in eyes.items()}
    ref = eyes[EYE_ORDER[0]].color
    sensors = [ref] + [s for e in eyes.values() for s in (e.color, e.thermal) if s != ref] + [tof]
    source.realtime = False
    count, rate = expected_sets(source, rig)
    expected = math.ceil(count / every) if count else None
    result = FuseResult(fps=(rate or 30.0) / every)
    w, h = fusion.size
    video_tmp = out_dir / f".{VIDEO_NAME}.partial.mp4"
    video = cv2.VideoWriter(
        str(video_tmp), cv2.VideoWriter_fourcc(*"mp4v"), result.fps, (w * len(eyes), h)
    )
    if not video.isOpened():
        video = None
        result.video_problem = "OpenCV has no mp4v encoder here"
        video_tmp.unlink(missing_ok=True)
    rows = ["index,stamp_ns,tof_stamp_ns"]
    last_tof: int | None = None
    bgr = np.empty((h, w * len(eyes), 3), np.uint8)
    try:
        for i, fs in enumerate(frame_sets(source, sensors, reference=ref)):
            result.sets += 1
            if tof in fs and fs[tof].stamp_ns != last_tof and fs[tof].distance_m is not None:
                fusion.update_depth(fs[tof].distance_m, fs[tof].image)
                last_tof = fs[tof].stamp_ns
                result.tof_updates += 1
            if i % every:
                continue
            missing = [s for s in sensors[:-1] if s not in fs]
            if missing:
                reason = f"no frame of {', '.join(missing)}"
            elif not fusion.ready:
                reason = "no TOF frame yet"
            else:
                reason = None
            if reason is not None:
                result.skipped[reason] = result.skipped.get(reason, 0) + 1
            else:
                for eye in eyes.values():
                    check_frame_size(fs[eye.color].image, rig, eye.color)
                    check_frame_size(fs[eye.thermal].image, rig, eye.thermal)
                colors = {e: fs[eye.color].image for e, eye in eyes.items()}
                thermals = {
                    e: radiometry[eye.thermal].apply(fs[eye.thermal].image, out=kelvin[e])
                    for e, eye in eyes.items()
                }
                picture = fusion.compose(colors, thermals, settings, fs.stamp_ns)
                cv2.cvtColor(picture, cv2.COLOR_RGB2BGR, dst=bgr)
                ok, jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
                if not ok:
                    raise RuntimeError("OpenCV could not encode a fused frame as JPEG")
                atomic_write_bytes(out_dir / f"{result.frames:06d}.jpg", jpg.tobytes(), False)
                if video is not None:
                    video.write(bgr)
                rows.append(f"{result.frames},{fs.stamp_ns},{last_tof}")
                result.frames += 1
            if progress is not None:
                progress(result.frames + sum(result.skipped.values()), expected)
    except RecordingDamaged as exc:
        result.damage = exc
    finally:
        if video is not None:
            video.release()
    atomic_write_text(out_dir / "frames.csv", "\n".join(rows) + "\n", overwrite=False)
    if video is not None:
        if result.frames:
            with video_tmp.open("rb") as f:  # durable before it gets its name
                os.fsync(f.fileno())
            os.replace(video_tmp, out_dir / VIDEO_NAME)
            fsync_dir(out_dir)
            result.video = out_dir / VIDEO_NAME
        else:
            video_tmp.unlink(missing_ok=True)
            result.video_problem = "no frames were fused"
    return result


def check_frame_size(image: np.ndarray, rig: Rig, sensor: str) -> None:
    """RecordingError (a ValueError) unless ``image`` has ``sensor``'s size in ``rig``: a
    recording replayed with another head's rig."""
    w, h = rig[sensor].image_size
    if image.shape[:2] != (h, w):
        raise RecordingError(
            f"frame of {sensor!r} is {image.shape[1]}x{image.shape[0]}, but the rig says "
            f"{w}x{h}: is this the recording's rig?"
        )
