"""The REST API under /api/: typed request and response models (OpenAPI at /docs).

Routes for what the console runs now: the rig, the fusion display settings and the manual
thermal balance. They change the same pipeline state as the Viser panels; bad values get a
422 with the field named, and nothing changes.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from app.server.pipeline import FusionPipeline
from calib.rig import rig_to_dict


class FusionSettings(BaseModel):
    """Display settings of the fused picture (temperatures in kelvin)."""

    model_config = ConfigDict(allow_inf_nan=False)

    mode: Literal["blend", "edges", "thermal", "threshold", "isotherm", "pip", "color"]
    palette: Literal["iron", "rainbow", "white_hot", "black_hot", "arctic", "lava"]
    opacity: float = Field(ge=0.0, le=1.0)
    threshold_k: tuple[float, float]
    threshold_direction: Literal["above", "below", "inside"]
    isotherm_k: tuple[float, float]
    edge_strength: float = Field(ge=0.0, le=10.0)
    mark_fallback: bool


class ThermalBalance(BaseModel):
    """The shared colour span (None: automatic over both eyes) and each imager's offset."""

    model_config = ConfigDict(allow_inf_nan=False)

    span_k: tuple[float, float] | None = None
    offset_k: dict[str, float] = Field(default_factory=dict)


def make_api_router(pipeline: FusionPipeline) -> APIRouter:
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
        )

    @router.put("/fusion")
    def put_fusion(body: FusionSettings) -> FusionSettings:
        try:
            pipeline.settings = dataclasses.replace(pipeline.settings, **body.model_dump())
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        return get_fusion()

    @router.get("/thermal")
    def get_thermal() -> ThermalBalance:
        return ThermalBalance(
            span_k=pipeline.settings.span_k, offset_k=dict(pipeline.thermal_offset_k)
        )

    @router.put("/thermal")
    def put_thermal(body: ThermalBalance) -> ThermalBalance:
        unknown = sorted(set(body.offset_k) - set(pipeline.thermal_offset_k))
        if unknown:
            raise HTTPException(
                422,
                f"offset_k: not thermal imagers of the rig: {unknown} "
                f"(imagers: {sorted(pipeline.thermal_offset_k)})",
            )
        try:
            settings = dataclasses.replace(pipeline.settings, span_k=body.span_k)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        pipeline.settings = settings
        pipeline.thermal_offset_k.update(body.offset_k)
        return get_thermal()

    return router
