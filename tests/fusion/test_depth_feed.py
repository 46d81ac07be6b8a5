"""The TOF side of the stereo step mapped aside in a worker (the console's ``DepthFeed.submit``)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest

from trifuse.app.sources.sim.inspection import InspectionScenario
from trifuse.fusion.stereo import StereoFusion
from trifuse.fusion.stereo_step import DEPTH_MAX_LAG_S, DepthFeed


@dataclass
class Tof:
    stamp_ns: int
    image: np.ndarray
    distance_m: np.ndarray


@pytest.fixture(scope="module")
def tofs():
    scenario = InspectionScenario(seed=5)
    out = []
    for k, t in enumerate((3.0, 3.3, 3.6)):
        frames, _ = scenario.render(t)
        tof = frames["tof"]
        out.append(Tof(k * 66_000_000, tof.image, tof.distance_m))
    return scenario.rig, out


class GatedWorker:
    """One worker thread whose jobs wait for :attr:`gate` before they run."""

    def __init__(self) -> None:
        self.pool = ThreadPoolExecutor(1)
        self.gate = threading.Event()
        self.jobs: list[Future] = []

    def submit(self, fn: Callable[[], Callable[[], None]]) -> Future:
        def gated() -> Callable[[], None]:
            assert self.gate.wait(10.0)
            return fn()

        job = self.pool.submit(gated)
        self.jobs.append(job)
        return job


def _maps(fusion: StereoFusion) -> list[np.ndarray]:
    return [a.copy() for f in fusion.fusion.values() for a in (f.forward.map_x, f.forward.map_y)]


def test_pictures_go_on_with_the_depth_in_use_while_a_new_one_is_mapped(tofs) -> None:
    rig, (a, b, c) = tofs
    reference = StereoFusion(rig)
    reference.update_depth(b.distance_m, b.image)
    want_b = _maps(reference)

    feed = DepthFeed(StereoFusion(rig))
    worker = GatedWorker()
    feed.submit = worker.submit
    feed.note(a)
    worker.gate.set()
    assert feed.update(a.stamp_ns)  # no depth yet: waits for the first mapping
    assert (feed.version, feed.tof_stamp_ns) == (1, a.stamp_ns) and feed.fusion.ready
    maps_a = _maps(feed.fusion)

    worker.gate.clear()
    feed.note(b)
    assert not feed.update(b.stamp_ns)  # mapping b aside: the picture goes on with a
    assert (feed.version, feed.tof_stamp_ns) == (1, a.stamp_ns)
    assert all(np.array_equal(x, y) for x, y in zip(_maps(feed.fusion), maps_a, strict=True))
    feed.note(c)
    assert not feed.update(c.stamp_ns)  # the worker is busy: c waits its turn
    assert len(worker.jobs) == 2

    worker.gate.set()
    worker.jobs[-1].result(10.0)
    assert feed.update(c.stamp_ns)  # b is put in use, c starts aside
    assert (feed.version, feed.tof_stamp_ns) == (2, b.stamp_ns)
    assert all(np.array_equal(x, y) for x, y in zip(_maps(feed.fusion), want_b, strict=True))
    assert len(worker.jobs) == 3
    worker.jobs[-1].result(10.0)
    assert feed.update(c.stamp_ns) and (feed.version, feed.tof_stamp_ns) == (3, c.stamp_ns)
    assert not feed.update(c.stamp_ns)  # nothing new
    worker.pool.shutdown()


def test_a_depth_too_far_from_the_picture_is_waited_for(tofs) -> None:
    """After a rest (or a seek) the depth in use may be far from the picture's time: then the
    new mapping is waited for rather than composing with a stale one."""
    rig, (a, b, _c) = tofs
    feed = DepthFeed(StereoFusion(rig))
    worker = GatedWorker()
    feed.submit = worker.submit
    worker.gate.set()
    feed.note(a)
    feed.update(a.stamp_ns)
    late = Tof(a.stamp_ns + round(3 * DEPTH_MAX_LAG_S * 1e9), b.image, b.distance_m)
    worker.gate.clear()
    feed.note(late)
    threading.Timer(0.2, worker.gate.set).start()  # done a little after the picture asks
    assert feed.update(late.stamp_ns)
    assert (feed.version, feed.tof_stamp_ns) == (2, late.stamp_ns)
    worker.pool.shutdown()


def test_a_failed_mapping_is_raised_where_the_depth_is_put_in_use(tofs) -> None:
    rig, (a, _b, _c) = tofs
    feed = DepthFeed(StereoFusion(rig))
    pool = ThreadPoolExecutor(1)
    feed.submit = lambda fn: pool.submit(lambda: (_ for _ in ()).throw(RuntimeError("boom")))
    feed.note(a)
    with pytest.raises(RuntimeError, match="boom"):
        feed.update(a.stamp_ns)
    assert feed.version == 0 and not feed.fusion.ready
    pool.shutdown()
