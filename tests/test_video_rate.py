"""The video rate controller against simulated links (app/server/runtime/video_rate.py).

A link is a FIFO queue of ``capacity`` bit/s with a base round trip: a frame waits for the
frames before it, takes ``bits / capacity`` to cross, and its ack returns half a round trip
later. The sender sends a frame of the controller's bitrate / fps whenever the controller
lets it (the encoder hitting its target, +-20 % seeded noise). Simulated time only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pytest

from app.server.runtime.video_encoder import LEVELS, MIN_BPS
from app.server.runtime.video_rate import WINDOW, RateController

STEP_S = 0.001


@dataclass
class Trace:
    t: list[float] = field(default_factory=list)
    bitrate: list[int] = field(default_factory=list)
    level: list[str] = field(default_factory=list)
    rtt: list[tuple[float, float]] = field(default_factory=list)  # (t_ack, rtt)
    in_flight_max: int = 0

    def bitrate_at(self, t: float) -> int:
        return self.bitrate[int(np.searchsorted(self.t, t))]


def simulate(
    ctl: RateController,
    capacity: Callable[[float], float],
    rtt_s: float,
    duration_s: float,
    seed: int = 0,
    losses: tuple[tuple[float, float], ...] = (),
) -> Trace:
    """Run the sender over the link for ``duration_s``; the controller's trace.

    ``losses``: ``(share, late_s)`` pairs: that share of the frames loses a packet and is
    delivered ``late_s`` late (TCP resends the packet while the link carries on); the frames
    behind it wait for it (TCP delivers in order)."""
    rng = np.random.default_rng(seed)
    trace = Trace()
    link_free = 0.0
    delivered = 0.0  # when the last frame sent reached the viewer
    acks: list[tuple[float, int]] = []  # (t_ack, seq), in order (FIFO link)
    seq = 0
    for i in range(int(duration_s / STEP_S)):
        t = i * STEP_S
        while acks and acks[0][0] <= t:
            t_ack, s = acks.pop(0)
            ctl.on_ack(s, t_ack)
            trace.rtt.append((t_ack, ctl.last_rtt_s or 0.0))
        target = ctl.target(t)
        trace.t.append(t)
        trace.bitrate.append(target.bitrate_bps)
        trace.level.append(target.level.name)
        if ctl.can_send(t):
            seq += 1
            nbytes = int(target.bitrate_bps / target.fps / 8 * rng.uniform(0.8, 1.2))
            ctl.on_sent(seq, nbytes, t)
            start = max(t + rtt_s / 2, link_free)
            link_free = start + nbytes * 8 / capacity(start)
            draw = rng.random()
            late = 0.0
            for share, late_s in losses:
                if draw < share:
                    late = late_s
                    break
                draw -= share
            delivered = max(link_free + late, delivered)
            acks.append((delivered + rtt_s / 2, seq))
            trace.in_flight_max = max(trace.in_flight_max, ctl.in_flight)
    return trace


def test_steady_10_mbit_stays_at_cap_with_base_rtt() -> None:
    ctl = RateController("auto")
    trace = simulate(ctl, lambda t: 10e6, 0.030, 20.0)
    late = [b for t, b in zip(trace.t, trace.bitrate, strict=True) if t > 5.0]
    assert max(late) <= LEVELS[0].max_bps
    assert min(late) >= 0.8 * LEVELS[0].max_bps  # it uses the link
    rtts = [r for t, r in trace.rtt if t > 5.0]
    # base 30 ms + one frame's transmission (33 kB at 10 Mbit/s: 27 ms), no queue
    assert np.median(rtts) < 0.030 + 0.040
    assert trace.level[-1] == "8"
    assert trace.in_flight_max <= WINDOW


def test_capacity_drop_is_followed_within_a_second_and_recovered() -> None:
    def capacity(t: float) -> float:
        return 3e6 if 10.0 <= t < 20.0 else 10e6

    ctl = RateController("auto")
    trace = simulate(ctl, capacity, 0.060, 40.0, seed=1)
    assert trace.bitrate_at(9.9) >= 6e6
    assert trace.bitrate_at(11.0) < 3e6  # below the new capacity within 1 s
    during = [b for t, b in zip(trace.t, trace.bitrate, strict=True) if 11.0 <= t < 20.0]
    assert max(during) < 3.5e6  # it does not keep overshooting the link
    assert trace.level[int(np.searchsorted(trace.t, 15.0))] in ("4", "2")
    rtts = [r for t, r in trace.rtt if 14.0 <= t < 20.0]
    assert np.median(rtts) < 0.060 + 0.2  # the queue drained: latency stays bounded
    assert trace.bitrate_at(39.9) >= 6e6  # the link came back: so did the bitrate
    assert trace.level[-1] == "8"
    assert trace.in_flight_max <= WINDOW


@pytest.mark.parametrize("seed", [5, 6])
def test_loss_is_not_taken_for_a_queue(seed: int) -> None:
    """The issue's 10 Mbit/s, 30 ms, 1 % loss link: a frame of about 25 packets loses one
    with a probability of about 0.2. TCP resends most such packets after a round trip (fast
    retransmit); one lost among the last few packets of a frame waits for the resend
    timer (at least 200 ms). Those late frames are not a queue: the bitrate keeps most of
    the link."""
    ctl = RateController("auto")
    losses = ((0.18, 0.060), (0.03, 0.26))
    trace = simulate(ctl, lambda t: 10e6, 0.060, 30.0, seed=seed, losses=losses)
    late = [b for t, b in zip(trace.t, trace.bitrate, strict=True) if t > 5.0]
    assert np.median(late) >= 5e6
    levels = trace.level[int(np.searchsorted(trace.t, 5.0)) :]
    assert levels.count("8") >= 0.5 * len(levels)


def test_fixed_preset_caps_bitrate_and_keeps_level() -> None:
    ctl = RateController("2")
    trace = simulate(ctl, lambda t: 1.2e6 if t >= 5.0 else 10e6, 0.030, 15.0, seed=2)
    assert max(trace.bitrate) <= 2_000_000
    assert set(trace.level) == {"2"}
    assert trace.bitrate_at(6.0) < 1.2e6


@pytest.mark.parametrize("seed", [3, 4])
def test_never_below_the_floor(seed: int) -> None:
    ctl = RateController("auto")
    trace = simulate(ctl, lambda t: 0.1e6, 0.100, 20.0, seed=seed)
    assert min(trace.bitrate) >= MIN_BPS
    assert trace.level[-1] == "1"
    assert trace.in_flight_max <= WINDOW


def test_stalled_link_steps_down_without_acks() -> None:
    ctl = RateController("auto")
    ctl.on_sent(1, 30_000, 0.0)
    ctl.on_ack(1, 0.05)
    ctl.target(0.05)
    for seq in range(2, 2 + WINDOW):
        ctl.on_sent(seq, 30_000, 0.05 + seq * 0.033)
    assert not ctl.can_send(0.4)
    before = ctl.bitrate_bps
    ctl.target(1.0)  # nothing acknowledged for ~0.9 s
    assert ctl.bitrate_bps < before
    ctl.on_ack(1 + WINDOW, 1.1)  # acknowledges the older frames too
    assert ctl.in_flight == 0 and ctl.can_send(1.1)


def test_bad_preset_and_window_rejected() -> None:
    with pytest.raises(ValueError, match="unknown video preset"):
        RateController("16")
    with pytest.raises(ValueError, match="window"):
        RateController("auto", window=0)
