"""app.latest_worker.LatestWorker: the newest items win, waiting ones are processed oldest
first, errors are reported, stop ends (and joins) the thread, and nothing runs without an
item, a wake or a period. Every wait is on an event the worker sets (no sleeps)."""

from __future__ import annotations

import logging
import threading

import pytest
from support import WAIT_S

from trifuse.app.latest_worker import LatestWorker


class Recorder:
    """A ``process`` that records its items and, for the items in ``hold``, waits for
    :attr:`release` first (so the test knows what is waiting meanwhile)."""

    def __init__(self, hold: tuple[object, ...] = ()) -> None:
        self.items: list[object] = []
        self.hold = hold
        self.entered = threading.Event()  # an item held has entered process
        self.release = threading.Event()
        self.done = threading.Event()  # set after every item
        self.threads: set[str] = set()

    def __call__(self, item: object) -> None:
        self.threads.add(threading.current_thread().name)
        if item in self.hold:
            self.entered.set()
            assert self.release.wait(WAIT_S)
        self.items.append(item)
        self.done.set()

    def wait_for(self, item: object) -> None:
        while item not in self.items:
            assert self.done.wait(WAIT_S), f"item {item!r} never processed: {self.items}"
            self.done.clear()


def test_the_newest_item_wins_while_the_worker_is_busy() -> None:
    rec = Recorder(hold=(1,))
    w = LatestWorker(rec, name="test-latest").start()
    try:
        assert w.submit(1) is False
        assert rec.entered.wait(WAIT_S)  # 1 is being processed
        assert w.busy
        assert [w.submit(k) for k in (2, 3, 4)] == [False, True, True]
        assert w.pending == 1
        rec.release.set()
        rec.wait_for(4)
    finally:
        w.stop()
    assert rec.items == [1, 4]
    assert (w.submitted, w.dropped, w.processed, w.failed) == (4, 2, 2, 0)
    assert rec.threads == {"test-latest"}
    assert not w.busy


def test_a_larger_inbox_keeps_the_newest_in_order() -> None:
    rec = Recorder(hold=("a",))
    w = LatestWorker(rec, name="test-keep", keep=2).start()
    try:
        w.submit("a")
        assert rec.entered.wait(WAIT_S)
        for item in "bcde":
            w.submit(item)
        assert w.pending == 2 and w.dropped == 2
        rec.release.set()
        rec.wait_for("e")
    finally:
        w.stop()
    assert rec.items == ["a", "d", "e"]  # the two newest, oldest of them first


def test_stop_joins_the_thread_and_ignores_later_items() -> None:
    rec = Recorder()
    w = LatestWorker(rec, name="test-stop").start()
    w.submit(1)
    rec.wait_for(1)
    assert w.alive
    w.stop()
    assert not w.alive
    assert w.submit(2) is False
    w.stop()  # idempotent
    assert rec.items == [1] and w.submitted == 1


def test_stop_leaves_waiting_items_unless_asked_to_finish_them() -> None:
    for finish, expected in ((False, [0]), (True, [0, 1, 2])):
        rec = Recorder(hold=(0,))
        w = LatestWorker(rec, name="test-finish", keep=2, finish_on_stop=finish).start()
        w.submit(0)
        assert rec.entered.wait(WAIT_S)
        w.submit(1)
        w.submit(2)
        stopper = threading.Thread(target=w.stop, kwargs={"timeout_s": WAIT_S})
        stopper.start()
        rec.release.set()
        stopper.join(WAIT_S)
        assert not stopper.is_alive() and not w.alive
        assert rec.items == expected


def test_a_worker_never_started_stops_without_waiting() -> None:
    w = LatestWorker(Recorder(), name="test-unstarted")
    w.stop()
    assert not w.alive


def test_stop_from_inside_the_worker_does_not_deadlock() -> None:
    w: LatestWorker[int]
    ended = threading.Event()

    def process(item: int) -> None:
        w.stop()  # from the worker thread: no join on itself
        ended.set()

    w = LatestWorker(process, name="test-self-stop").start()
    w.submit(1)
    assert ended.wait(WAIT_S)
    w.stop(timeout_s=WAIT_S)
    assert not w.alive


def test_errors_are_reported_and_the_worker_goes_on() -> None:
    seen: list[Exception] = []
    rec = Recorder()

    def process(item: int) -> None:
        if item == 1:
            raise ValueError("no board in view 1")
        rec(item)

    w = LatestWorker(process, name="test-error", keep=2, on_error=seen.append).start()
    try:
        w.submit(1)
        w.submit(2)  # room for both: 1 fails, 2 is still processed
        rec.wait_for(2)
    finally:
        w.stop()
    assert [str(e) for e in seen] == ["no board in view 1"]
    assert w.failed == 1 and w.last_error == "ValueError: no board in view 1"


def test_errors_without_a_handler_are_logged(caplog: pytest.LogCaptureFixture) -> None:
    failed = threading.Event()

    def process(item: int) -> None:
        failed.set()
        raise RuntimeError("encoder gone")

    done = Recorder()  # housekeeping: after the failing item's pass
    w = LatestWorker(process, name="test-log", housekeeping=lambda: done(None))
    with caplog.at_level(logging.ERROR, logger="trifuse.app.latest_worker"):
        w.start()
        w.submit(1)
        assert failed.wait(WAIT_S)
        done.wait_for(None)
        w.stop()
    assert [r.getMessage() for r in caplog.records] == ["test-log: RuntimeError: encoder gone"]
    assert caplog.records[0].exc_info is not None  # with the traceback
    assert w.failed == 1 and w.alive is False


def test_housekeeping_runs_only_after_an_item_a_wake_or_the_period() -> None:
    passes: list[int] = []
    ran = threading.Event()

    def housekeeping() -> None:
        passes.append(len(rec.items))
        ran.set()

    rec = Recorder()
    w = LatestWorker(rec, name="test-housekeeping", housekeeping=housekeeping).start()
    try:
        w.submit("x")
        assert ran.wait(WAIT_S)
        ran.clear()
        w.wake()
        assert ran.wait(WAIT_S)
        ran.clear()
        w.submit("y")
        rec.wait_for("y")
        assert ran.wait(WAIT_S)
    finally:
        w.stop()
    # Without a period the thread waited: one pass per item and one for the wake, no more.
    assert passes == [1, 1, 2]


def test_a_period_brings_housekeeping_without_items() -> None:
    asked = threading.Event()
    passes = threading.Semaphore(0)

    def period() -> float:
        asked.set()
        return 0.001

    w = LatestWorker(
        Recorder(), name="test-period", housekeeping=passes.release, period_s=period
    ).start()
    try:
        assert asked.wait(WAIT_S)
        for _ in range(3):
            assert passes.acquire(timeout=WAIT_S)
    finally:
        w.stop()
    assert w.submitted == 0


def test_keep_must_be_positive() -> None:
    with pytest.raises(ValueError, match="keep: expected at least 1 item, got 0"):
        LatestWorker(Recorder(), name="x", keep=0)
