"""A background thread that calls :meth:`Periodic.tick` at a fixed rate until stopped."""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod


class Periodic(ABC):
    """Calls :meth:`tick` every ``period_s`` seconds in a daemon thread."""

    def __init__(self, name: str, period_s: float) -> None:
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> Periodic:
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread.ident is not None:  # started
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.tick()

    @abstractmethod
    def tick(self) -> None:
        """One update (exceptions end the thread: catch what is expected)."""
