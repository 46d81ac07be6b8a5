"""Where a frame set's time goes in a ``trifuse fuse`` piece, node by node (part 3 of the
``ray`` benchmark, :mod:`app.devtools.bench_ray`): small loops over a recording with
OpenCV on one thread, as in a Ray task.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

DECODE_SETS = 15
"""Frame sets whose messages the decode loop decodes."""
NODE_SETS = 8
"""Decoded frame sets the compose, JPEG, video and file loops cycle through."""
VIDEO_FRAMES = 30
"""Pictures per timed video (its opening and closing included)."""


def _median_ms(samples: list[float]) -> float:
    return statistics.median(samples) * 1e3


def node_breakdown(recording: Path, repeat: int, tmp: Path, settings: Any) -> dict[str, float]:
    """ms per frame set of each node of a piece, in dedicated loops over ``recording``
    (OpenCV on one thread, as in a Ray task); medians over ``repeat`` loops; ``settings``:
    the display settings of the fusion runs."""
    import cv2
    import numpy as np

    from trifuse.app.recording import ReplaySource
    from trifuse.app.recording.fuse import JPEG_QUALITY
    from trifuse.app.recording.player import FRAME_KINDS
    from trifuse.app.sources.base import frame_sets
    from trifuse.app.storage.atomic import atomic_write_bytes
    from trifuse.fusion.geometry import tof_sensor_name
    from trifuse.fusion.stereo import EYE_ORDER
    from trifuse.fusion.stereo_step import OFFLINE, Skip, StereoStep

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ReplaySource(recording, realtime=False) as src:
            rig = src.rig
            assert rig is not None
            eyes = [rig.eyes[e] for e in EYE_ORDER]
            ref = eyes[0].color
            tof = tof_sensor_name(rig)
            sets = src.message_count(ref, "color") or 0
            tof_frames = src.message_count(tof, "tof_distance") or 0
            if not sets:
                raise RuntimeError(f"{recording}: no colour frames of {ref}")

            # MCAP read + decompress: every message, none decoded
            read = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                n = sum(1 for _m in src.index.messages())
                read.append((time.perf_counter() - t0) / sets)
            messages_per_set = n / sets

            # decode: the frame messages of the first DECODE_SETS sets, through the
            # replay's own routes (protobuf parse + JPEG / 16-bit conversion)
            msgs = []
            seen = 0
            for m in src.index.messages():
                route = src._route_of(m.channel_id)  # the replay's decoder of that channel
                if route is None or route.kind not in FRAME_KINDS:
                    continue
                if route.kind == "color" and route.sensor == ref:
                    seen += 1
                    if seen > DECODE_SETS:
                        break
                msgs.append((route, m))
            colour, other = [], []
            for _ in range(repeat):
                c = o = 0.0
                for route, m in msgs:
                    t0 = time.perf_counter()
                    route.decode(m)
                    dt = time.perf_counter() - t0
                    if route.kind == "color":
                        c += dt
                    else:
                        o += dt
                colour.append(c / DECODE_SETS)
                other.append(o / DECODE_SETS)

            # the replay as a piece reads it: read + decode + grouping into frame sets
            sensors = [ref] + [s for e in eyes for s in (e.color, e.thermal) if s != ref]
            sensors.append(tof)
            replay = []
            kept: list[Any] = []
            for r in range(repeat):
                t0 = time.perf_counter()
                count = 0
                for fs in frame_sets(src, sensors, reference=ref):
                    count += 1
                    if r == 0 and len(kept) < NODE_SETS and all(s in fs for s in sensors):
                        kept.append(fs)
                replay.append((time.perf_counter() - t0) / max(count, 1))
        if len(kept) < NODE_SETS:
            raise RuntimeError(f"{recording}: fewer than {NODE_SETS} complete frame sets")

        # fusion (trifuse fuse's step): the TOF mapping update, then radiometry + compose of
        # both eyes
        step = StereoStep(rig, settings, OFFLINE)
        fusion = step.fusion
        tofs = list({fs[tof].stamp_ns: fs[tof] for fs in kept}.values())
        update = []
        for _ in range(repeat):
            for f in tofs:
                t0 = time.perf_counter()
                fusion.update_depth(f.distance_m, f.image)
                update.append(time.perf_counter() - t0)
        compose, pictures = [], []
        for r in range(repeat + 1):  # the first pass warms the composer (not timed)
            for fs in kept:
                t0 = time.perf_counter()
                inputs = step.inputs(fs)
                if isinstance(inputs, Skip):
                    raise RuntimeError(f"{recording}: a complete frame set skipped: {inputs}")
                picture = step.render(inputs)
                if r:
                    compose.append(time.perf_counter() - t0)
                else:
                    pictures.append(picture.copy())

        # JPEG encode (to BGR first, as fuse_piece does)
        h, w = pictures[0].shape[:2]
        bgr = np.empty((h, w, 3), np.uint8)
        params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
        jpeg, jpgs, bgrs = [], [], []
        for r in range(repeat):
            for p in pictures:
                t0 = time.perf_counter()
                cv2.cvtColor(p, cv2.COLOR_RGB2BGR, dst=bgr)
                ok, jpg = cv2.imencode(".jpg", bgr, params)
                jpeg.append(time.perf_counter() - t0)
                if not ok:
                    raise RuntimeError("OpenCV could not encode a picture as JPEG")
                if r == 0:
                    jpgs.append(jpg.tobytes())
                    bgrs.append(bgr.copy())

        # video: mp4v of VIDEO_FRAMES pictures, opening and closing included
        video = []
        for r in range(repeat):
            path = tmp / f"video{r}.mp4"
            t0 = time.perf_counter()
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (w, h))
            if not writer.isOpened():
                raise RuntimeError("OpenCV has no mp4v encoder here")
            for i in range(VIDEO_FRAMES):
                writer.write(bgrs[i % len(bgrs)])
            writer.release()
            video.append((time.perf_counter() - t0) / VIDEO_FRAMES)
            path.unlink()

        # the driver's writing of a picture (FusedWriter: one atomic file each)
        files = []
        out = tmp / "jpegs"
        for r in range(repeat):
            for i, data in enumerate(jpgs):
                t0 = time.perf_counter()
                atomic_write_bytes(out / f"{r}-{i:06d}.jpg", data, False)
                files.append(time.perf_counter() - t0)
    finally:
        cv2.setNumThreads(threads)
    return {
        "node_read_ms": _median_ms(read),
        "node_decode_colour_ms": _median_ms(colour),
        "node_decode_thermal_tof_ms": _median_ms(other),
        "node_tof_update_ms": _median_ms(update) * tof_frames / sets,
        "node_compose_ms": _median_ms(compose),
        "node_jpeg_ms": _median_ms(jpeg),
        "node_video_ms": _median_ms(video),
        "node_file_write_ms": _median_ms(files),
        "replay_ms": _median_ms(replay),
        "messages_per_set": messages_per_set,
        "tof_per_set": tof_frames / sets,
    }
