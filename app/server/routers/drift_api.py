"""``POST /api/drift/refine``: correct the drift the console found (OpenAPI at /docs).

The calibration's health (``drift`` in ``GET /api/status``, app/server/runtime/drift_watch.py)
names the cameras that have turned against the rig in use. Refining turns each drifted
camera back by its estimated rotation (:func:`fusion.drift.refined_rig`), saves the result
as the session's next rig version (``rigs/rig-NNNN.yaml``, never over an existing file; its
report ``rig-NNNN.report.json`` holds the check), puts it in use (as ``POST
/api/rigs/{name}/use`` does) and starts the check again. It answers 409 with the reason,
changing nothing, when no sensor is drifted, when the rig in use has not been checked yet,
or when a correction would exceed 2 degrees (that is a moved sensor: recalibrate with the
board); the Calibration panel's Refine rig shows the same text.
"""

from __future__ import annotations

from collections.abc import Callable

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, Field

from trifuse.app.server.routers.source_api import DriftSensor
from trifuse.app.server.runtime.drift_watch import DriftWatch, refine_text, sensor_status
from trifuse.app.workflows.calib_session import RigVersion
from trifuse.calib.rig import Rig


class Refined(BaseModel):
    """What a refine did."""

    saved_as: str = Field(description="the new rig version, e.g. rig-0002, now in use")
    path: str = Field(description="its rig file")
    in_use: str = Field(description="the rig the console fuses with now (saved_as)")
    corrected: dict[str, DriftSensor] = Field(
        description="each corrected sensor's check: rotation_deg is the correction applied"
    )
    message: str = Field(description="what was done, in words")


def make_drift_router(
    watch: DriftWatch,
    save_rig: Callable[[Rig, dict], RigVersion],
    use_rig: Callable[[Rig], None],
) -> APIRouter:
    """The route over the console's drift ``watch``; ``save_rig`` writes the session's next
    rig version, ``use_rig`` puts a rig in use (``ConsoleContext.use_rig``)."""
    router = APIRouter(prefix="/api/drift", tags=["calibration"])

    @router.post("/refine", status_code=201)
    def refine() -> Refined:
        """Turn the drifted cameras back by their estimated rotation, save the rig as the
        next version and fuse with it (201); 409 with the reason, nothing changed, when no
        sensor is drifted, the rig in use is not checked yet, or a correction exceeds 2°."""
        try:
            result = watch.refine(save_rig, use_rig)
        except ValueError as exc:  # RefineRefused, nothing drifted, not checked yet
            raise HTTPException(409, str(exc)) from None
        return Refined(
            saved_as=result.version.name,
            path=str(result.version.path),
            in_use=result.version.name,
            corrected={n: DriftSensor(**sensor_status(s)) for n, s in result.corrected.items()},
            message=refine_text(result),
        )

    return router
