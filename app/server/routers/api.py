"""The REST API under /api/: typed request and response models (OpenAPI at /docs).

Routes for what the console runs now: the rig, the fusion display settings, and the
thermal imagers' radiometry and balance (``/api/thermal``). They change the same pipeline
state as the Viser panels; bad values get a 422 with the field named, and nothing changes.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.runtime.pipeline import FusionPipeline
from trifuse.app.server.runtime.thermal_balance import ThermalBalancer
from trifuse.app.server.settings_spec import (
    EDGE_STRENGTH,
    MANUAL_OFFSET_K,
    MAX_GAIN,
    OPACITY,
    PLATEAU,
    SPAN_SMOOTHING_S,
)
from trifuse.calib.rig import rig_to_dict
from trifuse.fusion.agc import AgcMode
from trifuse.fusion.balance import BalanceEstimate
from trifuse.fusion.compose import DisplayMode, ThresholdDirection
from trifuse.fusion.palettes import PaletteName


class FusionSettings(BaseModel):
    """Display settings of the fused picture (temperatures in kelvin). ``agc``,
    ``plateau`` and ``max_gain`` (the AGC, :mod:`fusion.agc`) may be left out of a PUT:
    they stay as they are."""

    model_config = ConfigDict(allow_inf_nan=False, extra="forbid")

    mode: DisplayMode
    palette: PaletteName
    opacity: float = OPACITY.field()
    threshold_k: tuple[float, float]
    threshold_direction: ThresholdDirection
    isotherm_k: tuple[float, float]
    edge_strength: float = EDGE_STRENGTH.field()
    mark_fallback: bool
    agc: AgcMode | None = Field(
        default=None,
        description="linear, plateau (equalization over both eyes) or dde (detail "
        "enhancement); omitted: unchanged",
    )
    plateau: float | None = PLATEAU.field()
    max_gain: float | None = MAX_GAIN.field()


class Radiometry(BaseModel):
    """One imager's raw -> kelvin chain (docs/FORMATS.md ``radiometry``)."""

    gain: float
    offset_k: float
    balance_gain: float
    balance_offset_k: float
    manual_offset_k: float


class Estimate(BaseModel):
    """A balance estimate: left - right at the shared points' median temperature."""

    ok: bool
    reason: str | None
    offset_k: float | None
    gain: float
    gain_fitted: bool
    points: int
    scatter_k: float | None


class BalanceState(BaseModel):
    """The live balance: what the newest frames say, and what is applied."""

    auto: bool
    reference: str | None
    difference_k: float | None = Field(description="median left - right as displayed")
    points: int
    estimate: Estimate | None
    filtered: Estimate | None
    waiting: str | None


class ThermalSettings(BaseModel):
    """The shared colour span (None: automatic over both eyes, smoothed over
    ``span_smoothing_s``), each imager's manual offset (kelvin) and, when given, automatic
    balancing on or off and the imager it balances onto (None: split evenly). Unknown keys
    get a 422 (a misspelt ``span_k`` would otherwise set the span to automatic)."""

    model_config = ConfigDict(allow_inf_nan=False, extra="forbid")

    span_k: tuple[float, float] | None = None
    span_smoothing_s: float | None = SPAN_SMOOTHING_S.field()
    offset_k: dict[str, Annotated[float, MANUAL_OFFSET_K.field()]] = Field(default_factory=dict)
    auto_balance: bool | None = None
    balance_reference: str | None = None


class Thermal(BaseModel):
    span_k: tuple[float, float] | None
    span_smoothing_s: float
    offset_k: dict[str, float]
    radiometry: dict[str, Radiometry]
    balance: BalanceState | None


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def estimate_model(e: BalanceEstimate | None) -> Estimate | None:
    if e is None:
        return None
    return Estimate(
        ok=e.ok,
        reason=e.reason,
        offset_k=_finite(e.offset_k),
        gain=e.gain,
        gain_fitted=e.gain_fitted,
        points=e.n_inliers if e.ok else e.n_points,
        scatter_k=_finite(e.mad_k),
    )


def make_api_router(pipeline: FusionPipeline, balancer: ThermalBalancer | None = None) -> APIRouter:
    router = APIRouter(prefix="/api")

    @router.get("/rig")
    def get_rig() -> dict[str, Any]:
        """The rig the console fuses with (rig-file layout, docs/FORMATS.md)."""
        return rig_to_dict(pipeline.rig)

    @router.get("/fusion")
    def get_fusion() -> FusionSettings:
        s = pipeline.settings
        threshold = s.threshold_k if isinstance(s.threshold_k, tuple) else (s.threshold_k,) * 2
        return FusionSettings(
            mode=s.mode,
            palette=s.palette,
            opacity=s.opacity,
            threshold_k=threshold,
            threshold_direction=s.threshold_direction,
            isotherm_k=s.isotherm_k,
            edge_strength=s.edge_strength,
            mark_fallback=s.mark_fallback,
            agc=s.agc,
            plateau=s.plateau,
            max_gain=s.max_gain,
        )

    @router.put("/fusion", dependencies=[Depends(require_json)])
    def put_fusion(body: FusionSettings) -> FusionSettings:
        try:
            changes = body.model_dump(exclude_none=True)
            pipeline.settings = dataclasses.replace(pipeline.settings, **changes)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        return get_fusion()

    def thermal() -> Thermal:
        st = balancer.status if balancer is not None else None
        return Thermal(
            span_k=pipeline.settings.span_k,
            span_smoothing_s=pipeline.settings.span_smoothing_s,
            offset_k={n: r.manual_offset_k for n, r in pipeline.radiometry.items()},
            radiometry={n: Radiometry(**r.to_dict()) for n, r in pipeline.radiometry.items()},
            balance=None
            if st is None
            else BalanceState(
                auto=balancer.auto,
                reference=balancer.reference,
                difference_k=_finite(st.difference_k),
                points=st.points,
                estimate=estimate_model(st.estimate),
                filtered=estimate_model(st.filtered),
                waiting=st.waiting,
            ),
        )

    @router.get("/thermal")
    def get_thermal() -> Thermal:
        """Span, smoothing, each imager's radiometry and the live balance (a client asking
        for it is listening: the balance is measured for the next few seconds)."""
        pipeline.touch_demand()
        if balancer is not None:
            balancer.touch()
        return thermal()

    @router.put("/thermal", dependencies=[Depends(require_json)])
    def put_thermal(body: ThermalSettings) -> Thermal:
        """Set the span (None: automatic), manual offsets and automatic balancing."""
        imagers = sorted(pipeline.radiometry)
        unknown = sorted(set(body.offset_k) - set(imagers))
        if body.balance_reference is not None and body.balance_reference not in imagers:
            unknown.append(body.balance_reference)
        if unknown:
            raise HTTPException(
                422, f"not thermal imagers of the rig: {unknown} (imagers: {imagers})"
            )
        if body.auto_balance is not None and balancer is None:
            raise HTTPException(409, "no balance estimation runs in this console")
        changes: dict[str, Any] = {"span_k": body.span_k}
        if body.span_smoothing_s is not None:
            changes["span_smoothing_s"] = body.span_smoothing_s
        try:
            settings = dataclasses.replace(pipeline.settings, **changes)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        pipeline.settings = settings
        for name, offset in body.offset_k.items():
            pipeline.set_manual_offset(name, offset)
        if balancer is not None:
            if "balance_reference" in body.model_fields_set:
                balancer.reference = body.balance_reference
            if body.auto_balance is not None:
                balancer.set_auto(body.auto_balance)
        return thermal()

    @router.post("/thermal/span-lock")
    def lock_span() -> Thermal:
        """Span lock (issue 35): fix the palette's span at the one the last picture shows
        (the automatic span, as it is now), so that colours keep their temperatures; PUT
        ``/api/thermal`` with ``span_k`` null unlocks it. 409 before a picture with a colour
        scale."""
        latest = pipeline.hub.latest
        span = None if latest is None else latest.meta.get("span_k")
        if not span:
            raise HTTPException(409, "no picture with a colour scale yet: nothing to lock")
        low, high = (round(float(v), 2) for v in span)
        try:
            pipeline.settings = dataclasses.replace(pipeline.settings, span_k=(low, high))
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        return thermal()

    @router.post("/thermal/balance")
    def balance_now() -> Thermal:
        """Apply the filtered balance estimate once (409 with the reason when there is
        none: no overlap between the imagers, too few TOF points ...)."""
        if balancer is None:
            raise HTTPException(409, "no balance estimation runs in this console")
        try:
            balancer.apply_filtered()
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        return thermal()

    @router.delete("/thermal/balance")
    def reset_balance() -> Thermal:
        """Remove the balance (calibration and manual offsets stay); auto-balance off."""
        if balancer is None:
            pipeline.set_balance({s: (1.0, 0.0) for s in pipeline.radiometry})
        else:
            balancer.reset_balance()
        return thermal()

    return router
