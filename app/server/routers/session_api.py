"""REST routes of the calibration session: captures, calibration runs, saved rig versions.

``/api/captures`` (list, take, delete), ``/api/calibrate`` (start, status, result, ``report.html``),
``/api/range`` (the TOF range calibration: start, status, result, save) and ``/api/rigs``
(list versions, save, get one, use one; ``/api/thermal/save``: the rig in use with the
imagers' current radiometry). Typed models; a request that cannot
be done now gets 409 with the reason, an unknown view or version 404 (also any name not of
the form of a view, ``0001``, or of a version, ``rig-0001``: such a name never reaches
the file system).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any, Literal, TypeVar

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, ConfigDict, Field

from trifuse.app.server.middleware.limits import require_json
from trifuse.app.server.settings_spec import HOLDOUT_EVERY
from trifuse.app.sources.frames import FrameSet
from trifuse.app.workflows.calib_session import (
    CalibrationJob,
    CalibrationSession,
    RangeJob,
    RigVersion,
    SessionError,
    ViewInfo,
    radiometry_report,
)
from trifuse.app.workflows.report_html import CSP, REPORT_HTML_NAME, session_report_html
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig, rig_to_dict

# What a view's and a saved version's name look like (ASCII digits; a name of more digits
# than a file name can hold is no name of this session either).
_VIEW_NAME = re.compile(r"[0-9]{4,20}")
_VERSION_NAME = re.compile(r"rig-[0-9]{4,20}")


T = TypeVar("T")


def _answer(
    fn: Callable[[], T],
    conflicts: tuple[type[Exception], ...] = (SessionError,),
    not_found: bool = False,
) -> T:
    """``fn()``; its ``conflicts`` answer 409 with their message and, with ``not_found``,
    a KeyError 404 with its message."""
    try:
        return fn()
    except KeyError as exc:
        if not not_found:
            raise
        raise HTTPException(404, exc.args[0]) from None
    except conflicts as exc:
        raise HTTPException(409, str(exc)) from None


def _finished_report(job: CalibrationJob | RangeJob, what: str) -> dict[str, Any]:
    """A finished job's report, else 404 naming ``what`` and the job's state."""
    if job.state != "done" or job.report is None:
        raise HTTPException(404, f"no finished {what} (state: {job.state})")
    return job.report


def _checked(name: str, pattern: re.Pattern[str], what: str, example: str) -> str:
    """``name`` if it has the form of a view's or version's name, else 404 saying so."""
    if not pattern.fullmatch(name):
        shown = name if len(name) <= 60 else name[:50] + "..."
        raise HTTPException(404, f"no {what} {shown!r}: names are like {example!r}")
    return name


class SensorDetection(BaseModel):
    """Whether the board was found in one sensor's image of a view (None: still searching)."""

    found: bool | None
    reason: str | None = None


class View(BaseModel):
    name: str
    sensors: dict[str, SensorDetection]


class SensorCoverage(BaseModel):
    """ROS-style coverage bars (0-1) and the image regions never reached."""

    x: float
    y: float
    size: float
    skew: float
    views: int
    good_enough: bool
    empty_regions: list[str]


class Captures(BaseModel):
    directory: str
    views: list[View]
    coverage: dict[str, SensorCoverage]
    interrupted: list[str] = Field(
        default_factory=list,
        description="staging folders of views a crash interrupted: kept, never used as views",
    )


class Job(BaseModel):
    """The calibration run: state, what it does now and how far it is (0-1)."""

    state: Literal["idle", "running", "done", "failed"]
    stage: str
    progress: float
    views: list[str]
    error: str | None
    rms_px: float | None
    seconds: float | None
    saved_as: str | None


class Version(BaseModel):
    name: str
    path: str
    saved: str
    rms_px: float | None
    views: int | None


def view_model(v: ViewInfo) -> View:
    return View(
        name=v.name,
        sensors={
            s: SensorDetection(
                found=v.found(s),
                reason=v.detections[s].reason if s in v.detections else None,
            )
            for s in v.sensors
        },
    )


_JOB_FIELDS = ("state", "stage", "progress", "views", "error", "saved_as")
"""What :class:`Job` and :class:`RangeStatus` take from their job as it is."""


def _job_fields(job: CalibrationJob | RangeJob) -> dict[str, Any]:
    return {name: getattr(job, name) for name in _JOB_FIELDS}


def job_model(job: CalibrationJob) -> Job:
    end, start = job.finished, job.started
    return Job(
        **_job_fields(job),
        rms_px=job.result.rms_px if job.result is not None else None,
        seconds=(end - start) if end is not None and start is not None else None,
    )


class RangeStatus(BaseModel):
    """The range calibration run; ``holdout`` and ``fit``: per accuracy region (1-4, then
    0 = regions 1-3) the RMS distance error before and after, millimetres."""

    state: Literal["idle", "running", "done", "failed"]
    stage: str
    progress: float
    views: list[str]
    error: str | None
    holdout: list[dict[str, Any]] | None
    saved_as: str | None


class RangeStart(BaseModel):
    model_config = ConfigDict(extra="forbid")

    holdout_every: int = HOLDOUT_EVERY.field()


def range_model(job: RangeJob) -> RangeStatus:
    holdout = [e.to_dict() for e in job.run.holdout] if job.run is not None else None
    return RangeStatus(**_job_fields(job), holdout=holdout)


def version_model(v: RigVersion) -> Version:
    return Version(name=v.name, path=str(v.path), saved=v.saved, rms_px=v.rms_px, views=v.views)


def make_session_router(
    session: CalibrationSession,
    latest: Callable[[], FrameSet | None],
    use_rig: Callable[[Rig], None],
    rig_in_use: Callable[[], Rig] | None = None,
    rig_with_radiometry: Callable[[], Rig] | None = None,
) -> APIRouter:
    """Routes over ``session``; ``latest()`` gives the frame set a capture takes,
    ``use_rig(rig)`` makes the console fuse with a saved rig (ValueError if it cannot),
    ``rig_in_use()`` is the rig a range calibration starts from and
    ``rig_with_radiometry()`` the rig in use with the imagers' current radiometry."""
    router = APIRouter(prefix="/api")

    @router.get("/captures")
    def list_captures() -> Captures:
        """The captured views (per sensor: board found or not) and every sensor's coverage."""
        cov = session.coverage()
        return Captures(
            directory=str(session.captures),
            views=[view_model(v) for v in session.views()],
            interrupted=[p.name for p in session.interrupted],
            coverage={
                s: SensorCoverage(
                    x=c.x,
                    y=c.y,
                    size=c.size,
                    skew=c.skew,
                    views=c.n_views,
                    good_enough=c.good_enough,
                    empty_regions=c.empty_regions,
                )
                for s, c in cov.items()
            },
        )

    @router.post("/captures", status_code=201)
    def take_capture() -> View:
        """Capture the newest frames as a new view (written to disk before the reply)."""
        frames = latest()
        if frames is None:
            raise HTTPException(409, "no frames yet: the source has not delivered any")
        return view_model(_answer(lambda: session.take(frames)))

    @router.delete("/captures/{name}")
    def delete_capture(name: str) -> dict[str, str]:
        """Move a view out of the capture (into the work directory's ``deleted/``)."""
        _checked(name, _VIEW_NAME, "view", "0001")
        moved = _answer(lambda: session.delete(name), not_found=True)
        return {"deleted": name, "moved_to": str(moved)}

    @router.post("/calibrate", status_code=202)
    def start_calibration() -> Job:
        """Calibrate every captured view in the background; poll ``GET /api/calibrate``."""
        return job_model(_answer(session.start_calibration))

    def job_routes(
        path: str,
        name: str,
        job: Callable[[], CalibrationJob | RangeJob],
        model: Callable[[Any], BaseModel],
        status: type[BaseModel],
        what: str,
        report: str,
    ) -> None:
        """``GET path`` (``<name>_status``): the job's state; ``GET path/result``
        (``<name>_result``): the report of the finished ``what`` (``report`` describes it),
        404 before."""
        router.add_api_route(
            path,
            lambda: model(job()),
            methods=["GET"],
            name=f"{name}_status",
            response_model=status,
        )
        router.add_api_route(
            f"{path}/result",
            lambda: _finished_report(job(), what),
            methods=["GET"],
            name=f"{name}_result",
            response_model=dict[str, Any],
            description=report,
        )

    job_routes(
        "/calibrate",
        "calibration",
        lambda: session.job,
        job_model,
        Job,
        "calibration",
        "The finished calibration's report (``report.json`` layout, docs/FORMATS.md).",
    )

    @router.get("/calibrate/report.html", response_class=HTMLResponse)
    def calibration_report_html() -> HTMLResponse:
        """The finished calibration's report as one self-contained HTML page to read and
        print (the Calibration panel's Download report sends the same); 404 before."""
        job = session.job
        _finished_report(job, "calibration")
        return HTMLResponse(
            session_report_html(job),
            headers={
                "Content-Security-Policy": CSP,
                "Content-Disposition": f'inline; filename="{REPORT_HTML_NAME}"',
            },
        )

    @router.post("/range", status_code=202, dependencies=[Depends(require_json)])
    def start_range(body: RangeStart | None = None) -> RangeStatus:
        """Calibrate the TOF's distances on the captured views with the rig in use (its
        board poses); poll ``GET /api/range``."""
        if rig_in_use is None:
            raise HTTPException(409, "no rig to calibrate the range with")
        every = (body or RangeStart()).holdout_every
        return range_model(_answer(lambda: session.start_range_calibration(rig_in_use(), every)))

    job_routes(
        "/range",
        "range",
        lambda: session.range_job,
        range_model,
        RangeStatus,
        "range calibration",
        "The finished range calibration's report (``range.json`` layout).",
    )

    @router.post("/range/save", status_code=201)
    def save_range() -> Version:
        """Save the rig with the fitted range correction as a new rig version."""
        return version_model(_answer(session.save_range))

    @router.post("/thermal/save", status_code=201)
    def save_radiometry() -> Version:
        """Save the rig in use with the imagers' current radiometry as a new rig version."""
        if rig_with_radiometry is None:
            raise HTTPException(409, "no rig to save")
        rig = rig_with_radiometry()
        return version_model(session.save_rig(rig, radiometry_report(rig)))

    @router.get("/rigs")
    def list_versions() -> list[Version]:
        """Saved rig versions, oldest first."""
        return [version_model(v) for v in session.versions()]

    @router.post("/rigs", status_code=201)
    def save_version() -> Version:
        """Save the finished calibration as a new rig version (never overwrites one)."""
        return version_model(_answer(session.save))

    @router.get("/rigs/{name}")
    def get_version(name: str) -> dict[str, Any]:
        _checked(name, _VERSION_NAME, "saved rig", "rig-0001")
        return rig_to_dict(_answer(lambda: session.load_version(name), (RigError,), True))

    @router.post("/rigs/{name}/use")
    def use_version(name: str) -> dict[str, str]:
        """Fuse with a saved rig from the next frame on."""
        _checked(name, _VERSION_NAME, "saved rig", "rig-0001")
        _answer(lambda: use_rig(session.load_version(name)), (RigError, ValueError), True)
        return {"in_use": name}

    return router
