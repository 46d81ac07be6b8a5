"""A background thread that calls :meth:`Periodic.tick` at a fixed rate until stopped,
while someone wants its work (:class:`~app.server.runtime.demand.Demand`), recording what
goes wrong instead of dying."""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod

from trifuse.app.errors import describe_error
from trifuse.app.server.runtime.demand import Demand

DEMAND_POLL_S = 0.25
"""How often a thread whose work nobody wants looks whether it is stopping (seconds)."""


class Periodic(ABC):
    """Calls :meth:`tick` every ``period_s`` seconds in a daemon thread.

    Args:
        name: the thread's name.
        period_s: seconds between ticks.
        demand: tick only while it is wanted (the thread sleeps otherwise, and ticks as
            soon as it turns wanted); None: always.

    Attributes:
        last_error: the newest failure (:func:`app.errors.describe_error`, prefixed with
            where when :meth:`record_error` is given one), or None.
        error_count: failures so far. An exception from :meth:`tick` is recorded and the
            thread ticks on.
    """

    def __init__(self, name: str, period_s: float, demand: Demand | None = None) -> None:
        self.period_s = period_s
        self.demand = demand
        self.last_error: str | None = None
        self.error_count = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> Periodic:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread.ident is not None:  # started
            self._thread.join(timeout_s)

    def record_error(self, exc: BaseException, where: str | None = None) -> str:
        """Record ``exc`` as :attr:`last_error` (``"<where>: <type>: <message>"``); returns
        the text."""
        text = describe_error(exc) if where is None else f"{where}: {describe_error(exc)}"
        self.last_error = text
        self.error_count += 1
        return text

    def tick_once(self) -> bool:
        """One :meth:`tick`, its exception recorded; whether it returned normally."""
        try:
            self.tick()
        except Exception as exc:  # recorded; the thread goes on
            self.record_error(exc)
            return False
        return True

    def _run(self) -> None:
        demand = self.demand
        while not self._stop.wait(self.period_s):
            if demand is not None:
                while not demand.wanted and not self._stop.is_set():
                    demand.wait(DEMAND_POLL_S)
                if self._stop.is_set():
                    return
            self.tick_once()

    @abstractmethod
    def tick(self) -> None:
        """One update (an exception is recorded in :attr:`last_error`; the next tick
        follows)."""
