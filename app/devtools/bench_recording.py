"""Benchmark ``recording``: MCAP write and replay throughput of full-resolution frame sets."""

from __future__ import annotations

from trifuse.app.devtools.benchmark import benchmark, median_ms


@benchmark(
    "recording",
    "MCAP recording of full-resolution five-sensor frame sets: write and replay throughput "
    "(sets/s; 30 needed for real time)",
    baselines=(("write_ms_per_set", "jpeg_encode_ms"), ("read_ms_per_set", "jpeg_decode_ms")),
    default_repeat=5,
)
def recording(repeat: int) -> dict[str, float]:
    """Write and replay 30 frame sets of the inspection scene (two 1280 x 960 colour, two
    382 x 288 thermal, one 176 x 144 TOF frame with distance and amplitude; rendered once
    at t = 3 s, not timed) per repeat.

    ``write_sets_per_s`` / ``write_ms_per_set``: :class:`app.recording.RecordingWriter`
    (JPEG q90, 16-bit thermal and TOF, zstd chunks) including opening and closing the file;
    ``read_sets_per_s`` / ``read_ms_per_set``: :class:`app.recording.ReplaySource` as fast
    as possible (``realtime=False``), decoding every frame back to the program's arrays;
    ``mb_per_set``: file size per set; baselines: one colour frame's ``cv2.imencode``
    (``jpeg_encode_ms``) and ``cv2.imdecode`` (``jpeg_decode_ms``).
    """
    import tempfile
    from pathlib import Path

    import cv2
    import numpy as np

    from trifuse.app.recording import RecordingWriter, ReplaySource
    from trifuse.app.sources.frames import Frame
    from trifuse.app.sources.sim.inspection import InspectionScenario

    scenario = InspectionScenario(seed=0)
    frames, _ = scenario.render(3.0)
    rig = scenario.rig
    sets = 30
    period_ns = 1_000_000_000 // 30
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        paths: list[Path] = []

        def write(i: int) -> None:
            path = Path(tmp) / f"rec{i + 1}.mcap"
            with RecordingWriter(path, rig) as w:
                for k in range(sets):
                    for name, f in frames.frames.items():
                        w.write(Frame(name, k * period_ns, f.image, f.distance_m))
            paths.append(path)

        write_ms = median_ms(write, repeat)

        def read(i: int) -> None:
            with ReplaySource(paths[-1], realtime=False) as src:
                n = sum(1 for _ in src.frames())
            if n != sets * len(frames.frames):
                raise RuntimeError(f"replayed {n} frames, expected {sets * len(frames.frames)}")

        read_ms = median_ms(read, repeat)
        figures["write_sets_per_s"] = sets / (write_ms / 1e3)
        figures["read_sets_per_s"] = sets / (read_ms / 1e3)
        figures["write_ms_per_set"] = write_ms / sets
        figures["read_ms_per_set"] = read_ms / sets
        figures["mb_per_set"] = paths[-1].stat().st_size / 1e6 / sets
    bgr = cv2.cvtColor(frames["ccd_left"].image, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, 90]
    figures["jpeg_encode_ms"] = median_ms(lambda _i: cv2.imencode(".jpg", bgr, params), repeat)
    jpg = cv2.imencode(".jpg", bgr, params)[1]
    figures["jpeg_decode_ms"] = median_ms(
        lambda _i: cv2.imdecode(np.asarray(jpg), cv2.IMREAD_COLOR_RGB), repeat
    )
    return figures
