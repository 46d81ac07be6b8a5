"""Balancing the two thermal imagers over a recording (``trifuse balance-thermal``).

The recording is replayed as fast as possible; each new TOF frame updates the depth (with
the rig's range correction), and each frame set with both thermal images and depth gives
one balance estimate on calibrated temperatures (:func:`fusion.balance.measure_balance`),
filtered over the recording's time (:class:`fusion.balance.BalanceFilter`). The filtered
estimate becomes both imagers' balance terms in the rig's ``radiometry`` blocks (their
radiometric calibration and manual offsets are kept).
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from trifuse.app.sources.base import FrameSource, frame_sets
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.rig import Rig
from trifuse.fusion.balance import BalanceEstimate, BalanceFilter, balance_terms, measure_balance
from trifuse.fusion.stereo import EYE_ORDER, StereoFusion
from trifuse.fusion.stereo_step import DepthFeed


@dataclass
class ThermalRun:
    """What :func:`balance_source` found.

    Attributes:
        estimate: the filtered estimate at the end (None: no usable frame set).
        terms: imager -> (balance_gain, balance_offset_k) from it (empty without one).
        used: frame sets whose estimate was usable; refused: reason -> count.
        before_k: median left - right per usable set, as the rig displayed it.
        after_k: the same with the new balance terms.
    """

    estimate: BalanceEstimate | None
    terms: dict[str, tuple[float, float]]
    used: int = 0
    refused: Counter[str] = field(default_factory=Counter)
    before_k: list[float] = field(default_factory=list)
    after_k: list[float] = field(default_factory=list)


def balance_source(
    source: FrameSource,
    rig: Rig,
    every: int = 1,
    time_constant_s: float = 3.0,
    reference: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> ThermalRun:
    """Estimate the balance over ``source``'s frame sets (every ``every``-th one)."""
    if every < 1:
        raise ValueError(f"every: expected a positive integer, got {every}")
    eyes = {e: rig.eyes[e] for e in EYE_ORDER}
    left, right = eyes["left"].thermal, eyes["right"].thermal
    fusion = StereoFusion(rig)
    tof = fusion.tof
    depth = DepthFeed(fusion)  # the console's: each new TOF stamp mapped once
    radiometry = {s: rig[s].radiometry or Radiometry() for s in (left, right)}
    flt = BalanceFilter(time_constant_s)
    run = ThermalRun(None, {})
    pairs: list[tuple[np.ndarray, np.ndarray, float]] = []
    for i, fs in enumerate(frame_sets(source, [left, right, tof], reference=left)):
        depth.note(fs.frames.get(tof))
        depth.update()
        if i % every:
            continue
        if progress:
            progress(i)
        if left not in fs or right not in fs or not fusion.ready:
            run.refused["a thermal image or the depth is missing"] += 1
            continue
        m = measure_balance(
            rig, tof, fusion.points, left, right, fs[left].image, fs[right].image, radiometry
        )
        flt.update(m.estimate, fs.stamp_ns)
        if not m.estimate.ok:
            run.refused[m.estimate.reason or "refused"] += 1
            continue
        run.used += 1
        run.before_k.append(m.difference_k)
        pairs.append((m.shared.t_left, m.shared.t_right, m.difference_k))
    run.estimate = flt.state
    if run.estimate is not None:
        run.terms = balance_terms(run.estimate, left, right, reference)
        gl, ol = run.terms[left]
        gr, orr = run.terms[right]
        for t_l, t_r, _ in pairs:  # calibrated samples -> with the new balance (no trims)
            run.after_k.append(float(np.median((gl * t_l + ol) - (gr * t_r + orr))))
    return run


def with_balance(rig: Rig, terms: dict[str, tuple[float, float]]) -> Rig:
    """A copy of ``rig`` whose imagers carry ``terms`` as their balance (their calibration
    and manual offsets kept)."""
    for name, (gain, offset) in terms.items():
        sensor = rig[name]
        r = (sensor.radiometry or Radiometry()).with_balance(gain, offset)
        rig = rig.with_sensor(dataclasses.replace(sensor, radiometry=r))
    return rig


def format_thermal_summary(run: ThermalRun, rig: Rig) -> str:
    """The terminal summary."""
    lines = []
    e = run.estimate
    if e is None:
        why = "; ".join(f"{n}x {r}" for r, n in run.refused.most_common(3)) or "no frame sets"
        return f"No balance estimate: {why}. The rig is unchanged."
    gain = f"gain {e.gain:.4f}" if e.gain_fitted else (e.note or "offset only")
    lines.append(
        f"Balance from {run.used} frame set(s): left - right {e.offset_k:+.3f} K at "
        f"{e.reference_k - 273.15:.1f} °C, {gain}, scatter {e.mad_k:.3f} K"
    )
    med = lambda xs: float(np.median(xs)) if xs else math.nan  # noqa: E731
    lines.append(
        f"median left - right over shared points: before {med(run.before_k):+.3f} K, "
        f"after {med(run.after_k):+.3f} K"
    )
    for name, (g, o) in run.terms.items():
        lines.append(f"  {name}: balance_gain {g:.5f}, balance_offset_k {o:+.4f}")
    if run.refused:
        lines.append("frame sets not used:")
        for reason, n in run.refused.most_common():
            lines.append(f"  {n}x {reason}")
    return "\n".join(lines)
