"""The console's thermal balance: measured twice a second on the newest frames, applied
to the fused picture when automatic.

Each tick takes the newest frame set and the TOF points behind the current mapping,
finds the points both thermal imagers see (:func:`fusion.balance.measure_balance`),
estimates the left-right relation on calibrated temperatures, and filters it over frame
time (:class:`fusion.balance.BalanceFilter`). With ``auto`` on, the filtered estimate
becomes both imagers' balance terms (split evenly, or onto a reference imager). A frame
whose estimate is refused (no overlap, too few TOF points) changes nothing; the status
says why. The live left-right difference is measured over the same points, as displayed
(calibration, balance and the operator's trims).

The console balances automatically by default, unless the rig brings a balance of its own
(:func:`balance_in_rig`): two units of one imager model differ by about 1.5 K, which paints
the two eyes in different colours. With nobody reading the balance, a settled automatic
balance is measured every :data:`SETTLED_PERIOD_S`. With ``auto`` off the balance is only
read: it is measured while someone reads it (its ``listeners``: a Viser client, a REST
client of ``/api/thermal``), and once more before a measurement older than :data:`STALE_S`
is applied. :meth:`ThermalBalancer.describe` says which balance the pictures show (the
viewer's overlay).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from trifuse.app.server.runtime.demand import Demand
from trifuse.app.server.runtime.periodic import Periodic
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.calib.rig import Rig
from trifuse.fusion.balance import BalanceEstimate, BalanceFilter, balance_terms, measure_balance

MIN_SHARED_POINTS = 200
STALE_S = 1.5
"""A measurement older than this (seconds) is taken again before it is applied once."""
SETTLED_PERIOD_S = 2.0
"""Seconds between measurements of a settled automatic balance that nobody reads."""


def balance_in_rig(rig: Rig) -> bool:
    """Whether a thermal imager of ``rig`` carries a balance (a rig saved with one)."""
    return any(
        s.radiometry is not None
        and (s.radiometry.balance_gain != 1.0 or s.radiometry.balance_offset_k != 0.0)
        for s in rig.sensors.values()
    )


@dataclass(frozen=True)
class BalanceStatus:
    """The newest measurement, for the panel and ``GET /api/thermal``.

    Attributes:
        difference_k: median left - right as displayed over the shared points (NaN: none).
        points: shared points of the newest frame set.
        estimate: the newest frame's own estimate (refused ones carry the reason).
        filtered: the filtered estimate, None before the first usable one.
        waiting: why nothing was measured (no frames yet ...), else None.
    """

    difference_k: float = math.nan
    points: int = 0
    estimate: BalanceEstimate | None = None
    filtered: BalanceEstimate | None = None
    waiting: str | None = "waiting for frames"

    def difference_text(self) -> str:
        """The live difference line, markdown."""
        if self.waiting:
            return f"Left - right: {self.waiting}"
        if not math.isfinite(self.difference_k):
            return f"Left - right: no shared points ({self._why()})"
        return f"Left - right: **{self.difference_k:+.2f} K** over {self.points} shared points"

    def _why(self) -> str:
        e = self.estimate
        return e.reason if e is not None and e.reason else "the imagers see nothing in common"


class ThermalBalancer(Periodic):
    """Measures (and, when ``auto``, applies) the balance at ``rate_hz``, while the
    pipeline's pictures are wanted (its ``demand``: the balance changes only pictures, and
    the depth it measures on is mapped only then) and, with ``auto`` off, while
    ``listeners`` is wanted (None: always).

    Args:
        auto: apply the filtered estimate continuously from the start; None: unless the
            pipeline's rig carries a balance (:func:`balance_in_rig`).

    Attributes:
        auto: apply the filtered estimate continuously.
        reference: None (split the correction evenly) or the imager left unchanged.
        status: the newest :class:`BalanceStatus`.
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        rate_hz: float = 2.0,
        time_constant_s: float = 3.0,
        listeners: Demand | None = None,
        auto: bool | None = False,
    ) -> None:
        super().__init__("thermal-balance", 1.0 / rate_hz, pipeline.demand)
        self.pipeline = pipeline
        self.listeners = listeners
        in_rig = balance_in_rig(pipeline.rig)
        self.auto = not in_rig if auto is None else bool(auto)
        self._held = "rig" if in_rig else "off"  # the balance shown while auto is off
        self.reference: str | None = None
        self.filter = BalanceFilter(time_constant_s)
        self.status = BalanceStatus()
        self._seen: tuple | None = None
        self._measured_at = -math.inf  # time.monotonic() of the newest measurement
        self._lock = threading.Lock()  # one measurement at a time: the thread's, a request's

    def touch(self) -> None:
        """Someone reads the balance: measure it for the next few seconds."""
        if self.listeners is not None:
            self.listeners.touch()

    def set_auto(self, on: bool) -> None:
        """Turn automatic balancing on (from a fresh estimate) or off (the balance stays)."""
        if on and not self.auto:
            self.filter.reset()
            self._seen = None  # measure the frames on screen again, even if unchanged
        elif self.auto and not on:
            self._held = "applied"  # the balance stays as it was
        self.auto = bool(on)

    def apply_filtered(self) -> BalanceEstimate:
        """Apply the filtered estimate once, measured again first if its newest measurement
        is older than :data:`STALE_S` (SessionError-like ValueError when none)."""
        self.touch()
        if time.monotonic() - self._measured_at > STALE_S:
            self._measure()
        state = self.filter.state
        if state is None:
            raise ValueError(
                "no balance estimate yet: "
                + (self.filter.last_reason or "waiting for frames with both imagers and depth")
            )
        self._apply(state)
        self._held = "applied"
        return state

    def reset_balance(self) -> None:
        """Both imagers back to no balance (their calibration and trims stay)."""
        self.set_auto(False)
        self.pipeline.set_balance({s: (1.0, 0.0) for s in self.pipeline.radiometry})
        self._held = "off"

    def describe(self) -> dict[str, object]:
        """Which balance the pictures show, for the viewer: ``mode`` (``auto``; ``rig``:
        the rig's; ``applied``: once, by the operator; ``off``) and ``correction_k``, the
        balance's left offset minus the right one, kelvin (0.0 when off), and while off
        ``difference_k``, the left - right difference measured last (None: none)."""
        rad, rig = self.pipeline.radiometry, self.pipeline.rig
        left, right = (rad.get(rig.eyes[e].thermal) for e in ("left", "right"))
        correction = 0.0
        if left is not None and right is not None:
            correction = left.balance_offset_k - right.balance_offset_k
        mode = "auto" if self.auto else self._held
        out: dict[str, object] = {"mode": mode, "correction_k": round(correction, 3)}
        if mode == "off":
            d = self.status.difference_k
            out["difference_k"] = round(d, 3) if math.isfinite(d) else None
        return out

    def _apply(self, state: BalanceEstimate) -> None:
        p = self.pipeline
        left, right = (p.rig.eyes[e].thermal for e in ("left", "right"))
        p.set_balance(balance_terms(state, left, right, self.reference))

    def tick(self) -> None:
        listened = self.listeners is None or self.listeners.wanted
        if not (self.auto or listened):
            return
        settled = self.filter.state is not None
        if not listened and settled and time.monotonic() - self._measured_at < SETTLED_PERIOD_S:
            return
        self._measure()

    def _measure(self) -> None:
        with self._lock:
            self._measure_locked()

    def _measure_locked(self) -> None:
        self._measured_at = time.monotonic()
        p = self.pipeline
        fs, fusion = p.latest_set, p.fusion
        rig = p.rig
        left, right = rig.eyes["left"].thermal, rig.eyes["right"].thermal
        if fs is None or left not in fs.frames or right not in fs.frames or not fusion.ready:
            self.status = BalanceStatus(waiting="needs both thermal imagers and a TOF frame")
            return
        points = fusion.points
        images = (fs.frames[left].image, fs.frames[right].image)
        seen = (points, *images, tuple(sorted(p.radiometry.items())))
        last = self._seen
        if last is not None and all(a is b for a, b in zip(seen[:3], last[:3], strict=True)):
            if seen[3] == last[3]:
                return  # the very same frames and radiometry (a source repeating them)
        m = measure_balance(
            rig, p.tof, points, left, right, *images, p.radiometry, min_points=MIN_SHARED_POINTS
        )
        filtered = self.filter.update(m.estimate, fs.stamp_ns)
        self.status = BalanceStatus(m.difference_k, m.shared.n_points, m.estimate, filtered, None)
        self._seen = seen
        if self.auto and m.estimate.ok and filtered is not None:
            self._apply(filtered)
