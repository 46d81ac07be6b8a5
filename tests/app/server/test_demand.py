"""Work on demand: the console fuses, encodes, balances and searches for the board only
while someone listens (app.server.runtime.demand); a background loop records its errors
and goes on (app.server.runtime.periodic)."""

from __future__ import annotations

import collections
import queue
import threading
from collections.abc import Callable, Iterator

import numpy as np
from fastapi import FastAPI
from fastapi.testclient import TestClient

from tests.support import FakeClock, small_rig, synth_frame, wait_until
from trifuse.app.errors import describe_error
from trifuse.app.server.routers.stream_routes import make_stream_router
from trifuse.app.server.runtime.board_watch import BoardWatch
from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.stream import FrameHub
from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.calib.board import Board
from trifuse.calib.detect import Detection

RIG = small_rig()


def wait_for(condition: Callable[[], object], what: str, timeout_s: float = 20.0) -> None:
    wait_until(condition, what, timeout_s, poll_s=0.01)


class _CountingDemand(Demand):
    """A demand that counts the waits of the threads it keeps idle (:meth:`Demand.wait`),
    in all and by thread name."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.waits = 0
        self.waits_by: collections.Counter[str] = collections.Counter()

    def wait(self, timeout_s: float) -> bool:
        self.waits += 1
        self.waits_by[threading.current_thread().name] += 1
        return super().wait(timeout_s)


class _CountingHub(FrameHub):
    """A hub that counts the frames published to it."""

    def __init__(self, demand: Demand) -> None:
        super().__init__(demand)
        self.published = 0

    def publish(self, *args, **kwargs):
        self.published += 1
        return super().publish(*args, **kwargs)


def test_holds_and_leases_make_a_demand_wanted() -> None:
    clock = FakeClock(10.0)
    d = Demand("test", clock=clock)
    turned: list[bool] = []
    d.on_wanted.append(lambda: turned.append(True))
    assert not d.wanted and d.holds == 0
    a, b = d.hold(), d.hold()
    assert d.wanted and d.holds == 2 and len(turned) == 1  # told once, when it turned
    a.release()
    a.release()  # idempotent
    assert d.wanted and d.holds == 1
    with b:
        pass
    assert not d.wanted and d.holds == 0
    d.touch(5.0)
    assert d.wanted and len(turned) == 2
    clock.now = 12.0
    d.touch(1.0)  # a shorter lease never shortens the one there is
    clock.now = 14.9
    assert d.wanted
    clock.now = 15.0
    assert not d.wanted
    assert not d.wait(0.01)


def test_periodic_records_a_failing_tick_and_goes_on() -> None:
    class Flaky(Periodic):
        def __init__(self) -> None:
            super().__init__("flaky", 0.01)
            self.ticks = 0

        def tick(self) -> None:
            self.ticks += 1
            if self.ticks <= 2:
                raise ValueError(f"bad tick {self.ticks}")

    loop = Flaky().start()
    try:
        wait_for(lambda: loop.ticks > 4, "ticks after the failures")
    finally:
        loop.stop()
    assert loop.error_count == 2 and loop.last_error == "ValueError: bad tick 2"
    assert describe_error(KeyError()) == "KeyError"


def test_periodic_ticks_only_while_its_demand_is_wanted() -> None:
    demand = _CountingDemand("test")

    class Counter(Periodic):
        ticks = 0

        def tick(self) -> None:
            self.ticks += 1

    loop = Counter("counter", 0.01, demand).start()
    try:
        # unwanted: the loop waits for the demand, and again once the first wait timed out
        wait_for(lambda: demand.waits >= 2, "the loop waiting for its demand a second time")
        assert loop.ticks == 0
        with demand.hold():
            wait_for(lambda: loop.ticks >= 3, "ticks while wanted")
    finally:
        loop.stop()


class _Fed(FrameSource):
    """Frames the test hands over (``put``), until ``close``."""

    def __init__(self) -> None:
        self.sensors = list(RIG.names)
        self.rig = RIG
        self._q: queue.Queue[Frame | None] = queue.Queue()
        self.asked = 0
        """How many frames the consumer has asked for: one more than it was given means it
        has done with every frame given."""

    def put_set(self, k: int, rng: np.random.Generator) -> int:
        stamp = 1_000_000_000 + k * 100_000_000
        for s in RIG.names:
            self._q.put(synth_frame(RIG, s, stamp, rng))
        return stamp

    def frames(self) -> Iterator[Frame]:
        while True:
            self.asked += 1
            if (f := self._q.get()) is None:
                return
            yield f

    def close(self) -> None:
        self._q.put(None)


def _stamp_of(pipeline: FusionPipeline) -> int | None:
    fs: FrameSet | None = pipeline.latest_set
    return None if fs is None else fs.stamp_ns


def test_the_pipeline_fuses_only_while_wanted_and_catches_up_at_once() -> None:
    """Unwanted: frame sets are grouped (the newest set, the status) but not fused. A
    listener arriving gets the newest set fused at once, even when the source then sends
    nothing (a paused replay); once nobody listens, the stream forgets its picture."""
    demand, source, rng = Demand("fusion"), _Fed(), np.random.default_rng(1)
    hub = _CountingHub(demand)
    pipeline = FusionPipeline(source, RIG, hub, demand=demand).start()
    try:
        stamps = [source.put_set(k, rng) for k in range(5)]
        wait_for(lambda: _stamp_of(pipeline) == stamps[-1], "the newest set")
        given = len(stamps) * len(RIG.names)
        wait_for(lambda: source.asked > given, "the pipeline to be done with every frame")
        assert hub.latest is None and pipeline.status.frames_out == 0
        assert pipeline.status.last_stamp_ns == stamps[-1]
        with demand.hold():  # a viewer arrives; the source sends nothing more
            wait_for(lambda: hub.latest is not None, "the catch-up picture", 10.0)
            assert hub.latest.meta["stamp_ns"] == stamps[-1]
            assert pipeline.status.pictures_out == 1
            assert hub.published == 1  # nothing fused while unwanted reached the hub later
        source.put_set(5, rng)
        source.put_set(6, rng)
        wait_for(lambda: hub.latest is None, "the stream to forget its picture")
        assert pipeline.status.pictures_out == 1 and pipeline.status.error is None
    finally:
        pipeline.stop()


def test_a_stream_viewer_holds_the_hubs_demand() -> None:
    hub = FrameHub()
    app = FastAPI()
    app.include_router(make_stream_router(hub))
    with TestClient(app) as client:
        assert not hub.demand.wanted
        with client.websocket_connect("/stream") as ws:
            hub.publish(b"\xff\xd8\xff\xd9", {"k": 1})
            ws.receive_text()
            ws.receive_bytes()
            assert hub.demand.holds == 1 and hub.viewers == 1
            ws.send_text("ack")
        wait_for(lambda: hub.demand.holds == 0 and hub.viewers == 0, "the viewer to leave")


def test_the_board_watch_searches_only_while_wanted() -> None:
    demand, searched = _CountingDemand("board search"), threading.Event()
    rng = np.random.default_rng(2)
    fs = FrameSet(1, {s: synth_frame(RIG, s, 1, rng) for s in RIG.names}, {})

    def detect(image: np.ndarray, board: Board, modality: str) -> Detection:
        searched.set()
        return Detection(None, "not here", "stand-in")

    watch = BoardWatch(lambda: fs, RIG, Board(9, 6, 0.04), detect=detect, demand=demand)
    watch.start()
    try:
        # unwanted: both loops (pose, full search) wait for the demand, and again once the
        # first wait timed out, without a search
        wait_for(
            lambda: len(demand.waits_by) == 2 and min(demand.waits_by.values()) >= 2,
            "both loops waiting for their demand a second time",
        )
        assert not searched.is_set()
        demand.touch(2.0)  # a client asked: a lease
        assert searched.wait(10.0)
        wait_for(lambda: watch.latest is not None, "the sighting")
    finally:
        watch.stop()
