"""Who wants a piece of the console's background work done now.

The console does its costly work only while someone needs it (an idle console on the
simulated head used 1.2 cores before, searching for a board nobody looked for and fusing
pictures nobody watched). Each piece of work has a :class:`Demand`; each consumer says it
wants the work in one of two ways:

- a **hold** (:meth:`Demand.hold`) for as long as it listens: a stream viewer's
  connection, a Viser client's session, auto-capture switched on. The handle's
  :meth:`Hold.release` (or leaving its ``with`` block) ends it.
- a **lease** (:meth:`Demand.touch`): a request-response client (a REST route) renews the
  demand for :data:`LEASE_S` seconds with each request, so a script that polls keeps the
  work running, and one that stops polling lets it rest.

Workers ask :attr:`Demand.wanted` (cheap) before each piece of work, or wait for it
(:meth:`Demand.wait`). :attr:`Demand.on_wanted` callbacks run when the demand turns from
unwanted to wanted (in the thread that made it so: keep them short), so a worker can catch
up at once.

:class:`ConsoleDemand` groups the console's three demands; :func:`hold_while_connected`
gives each Viser client a hold for as long as it is connected.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

LEASE_S = 5.0
"""How long one request keeps a demand wanted (seconds)."""


class Hold:
    """One consumer's hold on a :class:`Demand`; :meth:`release` (idempotent) ends it."""

    def __init__(self, demand: Demand) -> None:
        self._demand: Demand | None = demand

    def release(self) -> None:
        demand, self._demand = self._demand, None
        if demand is not None:
            demand._release()

    def __enter__(self) -> Hold:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()


class Demand:
    """Whether anyone wants a piece of work now: counted holds and an expiring lease
    (thread-safe).

    Args:
        name: what the work is (for messages and the status).
        clock: monotonic seconds (tests pass their own).

    Attributes:
        on_wanted: called with no argument each time the demand turns wanted.
    """

    def __init__(self, name: str, clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self._clock = clock
        self._cond = threading.Condition()
        self._holds = 0
        self._lease_until = -float("inf")
        self.on_wanted: list[Callable[[], None]] = []

    @property
    def holds(self) -> int:
        """Consumers holding the demand now."""
        return self._holds

    @property
    def wanted(self) -> bool:
        """Someone holds the demand or a lease has not run out."""
        return self._holds > 0 or self._clock() < self._lease_until

    def hold(self) -> Hold:
        """Want the work until the returned handle is released."""
        with self._cond:
            was = self.wanted
            self._holds += 1
            self._cond.notify_all()
        if not was:
            self._turned_wanted()
        return Hold(self)

    def touch(self, lease_s: float = LEASE_S) -> None:
        """Want the work for the next ``lease_s`` seconds (renews, never shortens)."""
        with self._cond:
            was = self.wanted
            self._lease_until = max(self._lease_until, self._clock() + lease_s)
            self._cond.notify_all()
        if not was:
            self._turned_wanted()

    def _release(self) -> None:
        with self._cond:
            self._holds = max(0, self._holds - 1)

    def _turned_wanted(self) -> None:
        for callback in list(self.on_wanted):
            callback()

    def wait(self, timeout_s: float) -> bool:
        """Block until the work is wanted or ``timeout_s`` passed; returns ``wanted``."""
        with self._cond:
            return self._cond.wait_for(lambda: self.wanted, timeout_s)


def hold_while_connected(server: Any, *demands: Demand) -> None:
    """Hold each of ``demands`` for every Viser client of ``server`` (a
    :class:`viser.ViserServer`) from its connection to its disconnection."""
    holds: dict[int, list[Hold]] = {}
    lock = threading.Lock()

    async def connected(client: Any) -> None:  # async: run in order, in Viser's loop
        with lock:
            holds.setdefault(client.client_id, []).extend(d.hold() for d in demands)

    async def gone(client: Any) -> None:
        with lock:
            mine = holds.pop(client.client_id, [])
        for h in mine:
            h.release()

    server.on_client_connect(connected)
    server.on_client_disconnect(gone)


@dataclass
class ConsoleDemand:
    """The console's demands (each consumer holds or touches the ones it needs).

    Attributes:
        fusion: fused pictures, their JPEG encoding, the depth mapping behind the point
            cloud and the thermal balance: stream viewers, Viser clients, REST clients of
            the status and the thermal state.
        balance: the thermal balance's measurement while it is not applied automatically
            (the Thermal panel's live difference): Viser clients, REST clients of the
            thermal state.
        board: the live board search: Viser clients (the Calibration panel, the feeds'
            corners, the 3D board), auto-capture.
        gui: the Viser panels' and the 3D scene's updates: Viser clients.
    """

    fusion: Demand = field(default_factory=lambda: Demand("fusion"))
    balance: Demand = field(default_factory=lambda: Demand("thermal balance"))
    board: Demand = field(default_factory=lambda: Demand("board search"))
    gui: Demand = field(default_factory=lambda: Demand("console GUI"))
