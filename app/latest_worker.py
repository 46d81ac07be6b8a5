"""A worker thread with a latest-inbox: producers hand it items without ever waiting, it
keeps only the newest few, processes them one at a time (oldest waiting first) and stops
cleanly.

The shape of every consumer that must not slow its producer down (the fusion thread, a
source's frame thread): the thermal map (one TOF frame waiting), the Foxglove live
publisher (two frame sets), the recorder's fused-video tap (a few pictures, finished on
stop). A full inbox drops its oldest item, counted. A module at the bottom of ``app``
(standard library only, besides :func:`~app.errors.describe_error`) so that the server and
the recording both use it.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, Self, TypeVar

from trifuse.app.errors import describe_error

log = logging.getLogger(__name__)

T = TypeVar("T")


class LatestWorker(Generic[T]):
    """A thread that processes the newest ``keep`` items submitted, oldest of them first.

    Args:
        process: called in the worker thread with each item, one at a time.
        name: the thread's name.
        keep: how many items may wait (>= 1); a submit to a full inbox drops the oldest.
        on_error: called in the worker thread with what ``process`` or ``housekeeping``
            raised (an ``Exception``); the thread goes on. None: the error is logged (with
            its traceback). Counted in :attr:`failed` and worded in :attr:`last_error`
            either way.
        housekeeping: called in the worker thread after every pass: after each item, after
            :meth:`wake`, and after ``period_s`` without an item.
        period_s: longest wait without an item before a housekeeping pass, seconds (a
            callable is asked before each wait); None: wait for an item or :meth:`wake`.
        finish_on_stop: True: :meth:`stop` lets the items already waiting be processed
            first; False: they are left unprocessed.

    Attributes:
        submitted, dropped, processed, failed: items submitted, dropped from a full inbox
            (never processed), processed (``process`` returned or raised), and exceptions
            caught.
        last_error: the newest exception caught, worded (None: none).
    """

    def __init__(
        self,
        process: Callable[[T], None],
        *,
        name: str,
        keep: int = 1,
        on_error: Callable[[Exception], None] | None = None,
        housekeeping: Callable[[], None] | None = None,
        period_s: float | Callable[[], float] | None = None,
        finish_on_stop: bool = False,
    ) -> None:
        if keep < 1:
            raise ValueError(f"keep: expected at least 1 item, got {keep}")
        self.process, self.keep = process, keep
        self.on_error, self.housekeeping = on_error, housekeeping
        self.period_s, self.finish_on_stop = period_s, finish_on_stop
        self.submitted = self.dropped = self.processed = self.failed = 0
        self.last_error: str | None = None
        self._cv = threading.Condition()
        self._inbox: deque[T] = deque()
        self._woken = self._working = self._stopping = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    # -- any thread ---------------------------------------------------------------------

    def start(self) -> Self:
        """Start the thread; returns self."""
        self._thread.start()
        return self

    def submit(self, item: T) -> bool:
        """Hand ``item`` over (never waits). True when an older waiting item was dropped to
        make room; after :meth:`stop` the item is ignored (False)."""
        with self._cv:
            if self._stopping:
                return False
            full = len(self._inbox) >= self.keep
            if full:
                self._inbox.popleft()
                self.dropped += 1
            self._inbox.append(item)
            self.submitted += 1
            self._cv.notify()
        return full

    def wake(self) -> None:
        """Run a housekeeping pass soon, without an item."""
        with self._cv:
            self._woken = True
            self._cv.notify()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Take no more items, end the thread (after the waiting items with
        ``finish_on_stop``) and wait for it up to ``timeout_s``; not from the worker thread
        itself, not if it never started. Idempotent."""
        with self._cv:
            self._stopping = True
            self._cv.notify_all()
        t = self._thread
        if t.ident is not None and t is not threading.current_thread():
            t.join(timeout_s)

    @property
    def pending(self) -> int:
        """Items waiting."""
        with self._cv:
            return len(self._inbox)

    @property
    def busy(self) -> bool:
        """An item is waiting or being processed."""
        with self._cv:
            return bool(self._inbox) or self._working

    @property
    def stopping(self) -> bool:
        """:meth:`stop` has been called."""
        return self._stopping

    @property
    def alive(self) -> bool:
        """The thread runs."""
        return self._thread.is_alive()

    # -- the worker thread --------------------------------------------------------------

    def _wait_s(self) -> float | None:
        p = self.period_s
        return p() if callable(p) else p

    def _run(self) -> None:
        while True:
            with self._cv:
                while not (self._inbox or self._woken or self._stopping):
                    if not self._cv.wait(self._wait_s()):
                        break  # the period ran out: a housekeeping pass
                if self._stopping and not (self.finish_on_stop and self._inbox):
                    return
                has_item = bool(self._inbox)
                item = self._inbox.popleft() if has_item else None
                self._woken = False
                self._working = has_item
            try:
                if has_item:
                    self._call(self.process, item)
                    self.processed += 1
                if self.housekeeping is not None and not self._stopping:
                    self._call(self.housekeeping)
            finally:
                with self._cv:
                    self._working = False

    def _call(self, fn: Callable[..., None], *args: object) -> None:
        try:
            fn(*args)
        except Exception as exc:  # reported (on_error or the log); the thread goes on
            self.failed += 1
            self.last_error = describe_error(exc)
            if self.on_error is not None:
                self.on_error(exc)
            else:
                log.error("%s: %s", self._thread.name, self.last_error, exc_info=exc)
