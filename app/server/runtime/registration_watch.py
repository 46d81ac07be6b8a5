"""The registration uncertainty of the live fusion, estimated in the background.

How far each eye's thermal values may land from where they belong (the registration sigma,
colour pixels: :mod:`fusion.registration`) depends on the rig, its calibration covariance,
the TOF's range error and the depth the TOF sees now. :class:`RegistrationWatch` estimates
it every :data:`PERIOD_S` at most (and within :data:`CPU_SHARE` of a core), while the
fusion is wanted
(:mod:`app.server.runtime.demand`) and a depth mapping exists:

1. in the fusion thread (a set listener of :class:`~app.server.runtime.pipeline.
   FusionPipeline`, where the mappings in use are read safely), each eye's coarse cells of
   its colour <- thermal mapping (:meth:`fusion.mapping.ViewMapping.coarse_cells`: depth
   and whether the cell is usable; two small arrays) are taken, when the depth behind the
   pictures changed since the last estimate;
2. in the worker thread ``registration-sigma`` (a :class:`~app.latest_worker.LatestWorker`
   keeping the newest job), :func:`fusion.registration.registration_sigma` for each eye
   with ``rig.covariance`` and :func:`fusion.registration.range_error`, every
   ``stride``-th cell so that at most :data:`MAX_CELLS` cells with depth are evaluated
   (:func:`stride_for`: every 5th on the simulated head, about 2300 cells; 0.04 s an eye
   without a covariance on an idle core, about 0.2 s beside the running fusion on a busy
   2-core machine), then its overlay for the ``registration`` display mode
   (:class:`fusion.registration_overlay.SigmaOverlay`) handed to the fusion
   (:meth:`fusion.stereo.StereoFusion.set_registration`).

The pictures never wait for it. The newest result of each eye is kept (:meth:`status`,
``GET /api/status`` ``registration``); a rig put in use (``pipeline.set_rig``) makes a new
fusion, and the results of the old one are dropped (an estimate under way for it is
discarded). A failure is worded (:func:`app.errors.describe_error`) in :attr:`error` and
counted; the next estimate is tried as usual.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.set_watch import SetWatch
from trifuse.app.sources.frames import FrameSet
from trifuse.calib.parameter_covariance import ParameterCovariance
from trifuse.calib.rig import Rig
from trifuse.fusion.registration import RegistrationSigma, range_error, registration_sigma
from trifuse.fusion.registration_overlay import SigmaOverlay
from trifuse.fusion.stereo import EYE_ORDER, StereoFusion

PERIOD_S = 2.0
"""Shortest time between two estimates, seconds."""
CPU_SHARE = 0.05
"""The share of one core the estimates may take: after an estimate that took ``t`` seconds
(both eyes), the next one waits at least ``t / CPU_SHARE`` (a rig with a full covariance
takes about 0.13-0.28 s an eye beside the busy fusion: one estimate every 5-11 s)."""
MAX_CELLS = 3000
"""The most coarse cells with depth one eye's estimate evaluates (:func:`stride_for`)."""
NO_COVARIANCE = "no calibration covariance in the rig: only range and footprint shares"
"""What the console says when the rig carries no covariance of an eye's sensors."""


def stride_for(ok: np.ndarray, max_cells: int = MAX_CELLS) -> int:
    """The smallest stride ``s`` (>= 1) with at most ``max_cells`` true cells in
    ``ok[::s, ::s]`` ((hc, wc) bool: the coarse cells with depth)."""
    s = 1
    while np.count_nonzero(ok[::s, ::s]) > max_cells:
        s += 1
    return s


def covers(covariance: ParameterCovariance | None, sensors: tuple[str, ...]) -> bool:
    """Whether ``covariance`` holds parameters of any of ``sensors`` (else the estimate has
    no calibration share: :func:`fusion.registration.registration_sigma`)."""
    return covariance is not None and bool(set(sensors) & set(covariance.sensors))


@dataclass(frozen=True)
class _Job:
    """One estimate to make: the fusion and rig it is for, the TOF's name, eye -> (coarse
    depth (hc, wc) float32 m, usable (hc, wc) bool, colour pixels per cell side)."""

    fusion: StereoFusion
    rig: Rig
    tof: str
    cells: dict[str, tuple[np.ndarray, np.ndarray, int]]
    version: int = 0
    """The depth's version (``step.depth.version``)."""


@dataclass(frozen=True, eq=False)
class EyeRegistration:
    """One eye's newest estimate.

    Attributes:
        sigma: the estimate (:class:`fusion.registration.RegistrationSigma`).
        overlay: what the ``registration`` mode draws of it.
        stride: every ``stride``-th coarse cell was evaluated.
        computed_at_s: when it was done (the watch's clock, seconds).
        compute_s: how long it took, seconds.
        fusion: the fusion it was made for (a new rig makes another).
    """

    sigma: RegistrationSigma
    overlay: SigmaOverlay
    stride: int
    computed_at_s: float
    compute_s: float
    fusion: StereoFusion

    def as_dict(self, now_s: float) -> dict[str, Any]:
        """``median_px``, ``p95_px``, ``cells``, ``range_source``,
        ``calibration_covariance`` and ``age_s`` (seconds since it was done)."""
        j = self.overlay.as_json()
        return {
            "median_px": j["median_px"],
            "p95_px": j["p95_px"],
            "cells": j["cells"],
            "range_source": j["range_source"],
            "calibration_covariance": j["calibration_covariance"],
            "age_s": round(max(0.0, now_s - self.computed_at_s), 3),
        }


class RegistrationWatch(SetWatch[_Job]):
    """Estimates each eye's registration sigma in the background (see the module doc).

    Args:
        pipeline: the console's fusion pipeline (its set listener is added here).
        period_s: shortest time between two estimates, seconds.
        max_cells: the most cells with depth an eye's estimate evaluates.
        clock: monotonic seconds (tests pass their own).

    Attributes:
        error: the newest estimate's failure (``"<eye>: <type>: <message>"``), or None
            when it succeeded.
        error_count: failures so far (one per eye that failed).
        estimates: estimates made so far (one per eye).
    """

    def __init__(
        self,
        pipeline: FusionPipeline,
        period_s: float = PERIOD_S,
        max_cells: int = MAX_CELLS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(pipeline, "registration-sigma", self._compute)
        self.period_s, self.max_cells, self.clock = period_s, max_cells, clock
        self.estimates = 0
        self._lock = threading.Lock()
        self._results: dict[str, EyeRegistration] = {}
        self._due_s = -float("inf")
        self._taken: tuple[StereoFusion, int] | None = None  # the depth last estimated
        self._pending: _Job | None = None  # the newest depth met while an estimate ran
        self._listen()

    # -- the fusion thread -------------------------------------------------------------------

    def _on_set(self, _fs: FrameSet) -> None:
        """A frame set arrived (fusion thread): take the eyes' coarse cells when an estimate
        is due and the depth changed since the last one; while an estimate runs, keep the
        newest depth for when it ends (:meth:`_compute`), so that an estimate longer than
        the period never queues the next one past :data:`CPU_SHARE`."""
        p = self.pipeline
        if not p.wanted:
            return
        now = self.clock()
        if now < self._due_s:
            return
        step = p.step
        fusion = step.fusion
        if not fusion.ready:
            return
        taken = self._taken
        if taken is not None and taken[0] is fusion and taken[1] == step.depth.version:
            return  # the same depth: the estimates still hold
        cells = {}
        for e in fusion.eyes:
            mapping = fusion.fusion[e].forward
            z, ok, _ = mapping.coarse_cells()  # new arrays at each update: safe to hand on
            cells[e] = (z, ok, mapping.options.scale)
        job = _Job(fusion, step.rig, fusion.tof, cells, step.depth.version)
        with self._lock:
            self._taken = (fusion, step.depth.version)
            if self._worker.busy:
                self._pending = job
                return
            self._due_s = now + self.period_s
        self._worker.submit(job)

    # -- the worker thread -------------------------------------------------------------------

    def _compute(self, job: _Job) -> None:
        errors: list[str] = []
        started = self.clock()
        try:
            self._estimate(job, errors)
        finally:
            spent = self.clock() - started
            now = self.clock()
            with self._lock:
                self._due_s = max(self._due_s, now + spent / CPU_SHARE)
                pending, self._pending = self._pending, None
                if pending is not None and pending.fusion is not self.pipeline.fusion:
                    pending = None  # made for a rig no longer in use
                elif pending is not None and now < self._due_s:
                    self._taken = None  # not due yet: taken again by the next set when due
                    pending = None
                elif pending is not None:
                    self._due_s = now + self.period_s
        self.error = "; ".join(errors) or None
        if pending is not None:
            self._worker.submit(pending)

    def _estimate(self, job: _Job, errors: list[str]) -> None:
        rig = job.rig
        range_err = range_error(rig, job.tof)
        for e, (z, ok, scale) in job.cells.items():
            if job.fusion is not self.pipeline.fusion:
                return  # a new rig came meanwhile: this estimate describes the old one
            eye = rig.eyes[e]
            sensors = (eye.color, eye.thermal, job.tof)
            try:
                t0 = self.clock()
                stride = stride_for(ok, self.max_cells)
                sigma = registration_sigma(
                    rig, rig.covariance, *sensors, z, ok, scale, range_err, stride
                )
                with_cov = covers(rig.covariance, sensors)
                overlay = SigmaOverlay.of(sigma, job.fusion.size, z, stride, with_cov)
                t1 = self.clock()
            except Exception as exc:  # reported in the status; the other eye goes on
                errors.append(f"{e}: {describe_error(exc)}")
                self.error_count += 1
                continue
            job.fusion.set_registration(e, overlay)
            with self._lock:
                self._results[e] = EyeRegistration(sigma, overlay, stride, t1, t1 - t0, job.fusion)
            self.estimates += 1

    # -- any thread --------------------------------------------------------------------------

    def results(self) -> dict[str, EyeRegistration | None]:
        """Eye (``left``, ``right``) -> its newest estimate for the rig in use, or None."""
        fusion = self.pipeline.fusion
        with self._lock:
            stale = [e for e, r in self._results.items() if r.fusion is not fusion]
            for e in stale:  # a new rig is in use: dropped
                del self._results[e]
            return {e: self._results.get(e) for e in EYE_ORDER}

    def status(self) -> dict[str, Any]:
        """``{"left": ..., "right": ..., "error": ...}``: per eye
        :meth:`EyeRegistration.as_dict` or None (not estimated yet), and :attr:`error`."""
        now = self.clock()
        out: dict[str, Any] = {
            e: (None if r is None else r.as_dict(now)) for e, r in self.results().items()
        }
        out["error"] = self.error
        return out

    def summary_text(self) -> str:
        """One line per eye for a panel (markdown-free): ``left: median 0.08 px, p95 4.5
        px (2293 cells)`` or ``left: not estimated yet``, then :data:`NO_COVARIANCE` when
        it applies, and the error."""
        lines = []
        without = False
        for e, r in self.results().items():
            if r is None:
                lines.append(f"{e}: not estimated yet")
                continue
            j = r.overlay.as_json()
            if j["median_px"] is None:
                lines.append(f"{e}: no cell with depth seen by the thermal imager")
            else:
                lines.append(
                    f"{e}: median {j['median_px']:.2f} px, p95 {j['p95_px']:.2f} px "
                    f"({j['cells']} cells)"
                )
            without |= not j["calibration_covariance"]
        if without:
            lines.append(NO_COVARIANCE)
        if self.error:
            lines.append(f"failed: {self.error}")
        return "\n".join(lines)
