"""A console's Foxglove port on a synthetic head, in a process of its own, for the memory
tests of tests/app/server/test_foxglove_live.py (issue 29): its resident memory is that process's.

``python -c "from tests.foxglove_caps_support import main; main()" [RATE_HZ]`` starts
:class:`~app.server.runtime.foxglove_live.FoxgloveLive` with the default head's rig
(full resolution: the real message sizes) on a free port, prints the port on one line, and
hands it a frame set of every sensor (seeded synthetic frames, new stamps) and a fused
picture RATE_HZ times a second (default 15) until its standard input ends.
"""

from __future__ import annotations

import sys
import threading
import time
from types import SimpleNamespace

import numpy as np

from tests.support import synth_frame
from trifuse.app.server.runtime.foxglove_live import FoxgloveLive
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig

VARIANTS = 3
"""Different frames per sensor (cycled)."""


def main() -> None:
    rate_hz = float(sys.argv[1]) if len(sys.argv) > 1 else 15.0
    rig = default_rig()
    rng = np.random.default_rng(29)
    frames = {n: [synth_frame(rig, n, k, rng) for k in range(VARIANTS)] for n in rig.names}
    w, h = rig[rig.eyes["left"].color].image_size
    pictures = [rng.integers(0, 256, (h // 2, w, 3), np.uint8) for _ in range(VARIANTS)]
    status = SimpleNamespace(last_stamp_ns=0, missing={})
    pipeline = SimpleNamespace(rig=rig, tof="tof", set_listeners=[], status=status, demand=None)
    hub = FrameHub()
    control = SimpleNamespace(
        pipeline=pipeline,
        hub=hub,
        source=None,
        sensor_health=dict,
        stream_rates=lambda: SimpleNamespace(stream_fps=rate_hz, new_fps=rate_hz),
    )
    live = FoxgloveLive(control, 0).start()  # type: ignore[arg-type]
    print(live.port, flush=True)
    stop = threading.Event()

    def feed() -> None:
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            stamp = 1_000_000_000 + int(k * 1e9 / rate_hz)
            fs = FrameSet(stamp)
            for name, variants in frames.items():
                f = variants[k % VARIANTS]
                fs.frames[name] = Frame(name, stamp, f.image, f.distance_m)
            status.last_stamp_ns = stamp
            for listener in list(pipeline.set_listeners):
                listener(fs)
            if hub.takers:  # the fused video is subscribed
                hub.publish(None, {"stamp_ns": stamp}, True, pictures[k % VARIANTS])
            k += 1
            stop.wait(max(0.0, t0 + k / rate_hz - time.monotonic()))

    feeder = threading.Thread(target=feed, name="synthetic-head", daemon=True)
    feeder.start()
    sys.stdin.read()
    stop.set()
    feeder.join()
    live.stop()
