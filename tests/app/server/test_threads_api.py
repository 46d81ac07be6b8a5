"""``GET /api/threads`` (app/server/routers/threads_api.py): every live Python thread of the
console by name, with the CPU seconds it has used, as ``/proc`` counts them."""

from __future__ import annotations

import threading
import time

from fastapi.testclient import TestClient

from trifuse.app.server.app_factory import create_app
from trifuse.app.server.runtime.stream import FrameHub

SPIN_S = 0.3


def _spin(done: threading.Event, go: threading.Event) -> None:
    """Use SPIN_S of this thread's CPU, then wait until told to end."""
    t0 = time.thread_time()
    while time.thread_time() - t0 < SPIN_S:
        pass
    go.set()
    done.wait(10)


def test_each_thread_with_the_cpu_time_it_used() -> None:
    done, spun = threading.Event(), threading.Event()
    busy = threading.Thread(target=_spin, args=(done, spun), name="busy-test", daemon=True)
    idle = threading.Thread(target=done.wait, args=(10,), name="idle-test", daemon=True)
    busy.start(), idle.start()
    try:
        assert spun.wait(10)
        with TestClient(create_app(FrameHub())) as client:
            body = client.get("/api/threads").json()
        by_name = {t["name"]: t for t in body}
        assert {"MainThread", "busy-test", "idle-test"} <= set(by_name)
        assert by_name["busy-test"]["native_id"] == busy.native_id
        # the kernel counts in clock ticks (10 ms): the spin's 0.3 s within two of them
        assert SPIN_S - 0.02 <= by_name["busy-test"]["cpu_s"] <= SPIN_S + 0.05
        assert 0 <= by_name["idle-test"]["cpu_s"] < 0.05
    finally:
        done.set()
