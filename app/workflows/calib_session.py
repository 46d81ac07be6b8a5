"""A calibration session on disk: the views an operator captures and the rigs it saves.

Layout of the session's work directory (docs/FORMATS.md "Calibration session")::

    <workdir>/
      captures/            # a capture directory (board.yaml, rig.yaml, 0001/, 0002/ ...)
      rigs/                # saved calibrations, never overwritten
        rig-0001.yaml
        rig-0001.report.json
      deleted/             # views the operator deleted, moved here (not destroyed)
        0007-20261122T140312/

Every view is written the moment it is taken (atomically: a view appears complete or not
at all, see :func:`app.storage.capture_writer.write_view`), so a crash or a kill loses
nothing that was taken; a restarted session finds the views and saved rigs where they
were. What a crash can leave behind is never taken for data: temporary files of interrupted writes
(``.<name>.<random>.tmp``) are removed when the session opens again; a view whose staging
folder (``captures/.<view>.<random>.partial``) was not renamed into place was never
acknowledged and is not listed, but is kept (it may hold images) and named in
:attr:`CalibrationSession.interrupted` and a log line; a rig version is its ``.yaml`` (written
after its report), so a report without it is ignored and its number is not reused. The board is
searched in each view's images *as written* (decoded from disk), so a calibration from
the console and ``trifuse calibrate <workdir>/captures`` see the same corners; each image is
searched once (:mod:`app.storage.detection_cache`), so a restarted session has its views'
corners at once.

Auto-capture follows ROS ``camera_calibration``: a sighting of the board is taken when the
board is steady (:class:`~app.server.runtime.board_sighting.BoardSighting`) and, for at least
one sensor that sees it, its (X, Y, size, skew) differ from every view of that sensor taken
so far by more than :data:`~calib.coverage.NOVELTY_THRESHOLD` (L1 distance).
:meth:`CalibrationSession.assess` says which, and why a sighting is not taken in words an
operator can act on (:class:`CaptureVerdict`), the first that applies of: the board is not
seen, the views' searches are still running, the pose is captured already (the nearest
view, and how far its board pose is, from :attr:`ViewInfo.T_rig_board`), it is moving.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from trifuse.app.errors import describe_error
from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.atomic import atomic_write_text, fsync_dir, make_dirs, remove_temporaries
from trifuse.app.storage.capture import (
    BOARD_FILE,
    RIG_FILE,
    CaptureError,
    ViewExistsError,
    load_board,
    load_capture,
    load_view,
)
from trifuse.app.storage.capture_writer import write_board, write_rig, write_view
from trifuse.app.storage.detection_cache import detect_cached
from trifuse.app.storage.numbered import first_free, next_number, suffixed_names
from trifuse.app.storage.rigfile import load_rig
from trifuse.app.workflows.calibration_run import DetectionRun, calibrate_capture
from trifuse.app.workflows.range_run import (
    RangeRun,
    build_range_report,
    calibrate_range,
    with_range_correction,
)
from trifuse.calib.board import POLARITY_KEYS, Board
from trifuse.calib.board_pose import board_pose_single
from trifuse.calib.coverage import NOVELTY_THRESHOLD, Coverage, coverage, pose_novelty, view_params
from trifuse.calib.detect import Detection
from trifuse.calib.errors import CalibrationError
from trifuse.calib.palette_inverse import PaletteFit
from trifuse.calib.rig import Rig, rig_to_yaml
from trifuse.calib.rig_calibration import CalibrationOptions
from trifuse.calib.rig_result import CalibrationResult
from trifuse.calib.transforms import pose_error
from trifuse.calib.verdict import ZHANG_MIN_VIEWS

CAPTURES = "captures"
RIGS = "rigs"
DELETED = "deleted"
_VIEW_RE = re.compile(r"^\d{4,}$")
_VERSION_RE = re.compile(r"^rig-(\d{4,})\.yaml$")
_VERSION_FILE_RE = re.compile(r"^rig-(\d{4,})\.")  # the rig or its report: number taken
# app.storage.capture_writer.write_view's staging folders
_STAGING_RE = re.compile(r"^\.\d{4,}\..+\.partial$")

log = logging.getLogger(__name__)


class SessionError(ValueError):
    """A session operation that cannot be done now; the message says why."""


@dataclass
class ViewInfo:
    """One captured view.

    Attributes:
        name: folder name under ``captures/`` ("0001", ...).
        sensors: sensors with an image in the view.
        detections: sensor -> Detection of the board in the image as written; a sensor is
            missing while its search is still running.
        params: sensor -> (X, Y, size, skew) of the detection (calib.coverage).
        palettes: thermal sensor -> how its false-colour image was read back (not kelvin).
        T_rig_board: (4, 4) the board's pose in the rig frame, metres, by the session's
            rig from the finest sensor that found it (None: not found, or not searched
            yet).
    """

    name: str
    sensors: list[str]
    detections: dict[str, Detection] = field(default_factory=dict)
    params: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)
    palettes: dict[str, PaletteFit] = field(default_factory=dict)
    T_rig_board: np.ndarray | None = None

    @property
    def searched(self) -> bool:
        """Whether every sensor's image has been searched."""
        return all(s in self.detections for s in self.sensors)

    def found(self, sensor: str) -> bool | None:
        """True/False once searched, None while the search runs."""
        d = self.detections.get(sensor)
        return None if d is None else d.found


@dataclass(frozen=True)
class RigVersion:
    """A saved rig file of the session.

    Attributes:
        name: ``rig-0001`` ...
        path: the rig file.
        saved: local time it was written, ``YYYY-MM-DD HH:MM:SS``.
        rms_px: overall reprojection RMS of its calibration (from its report), or None.
        views: number of views its calibration used (from its report), or None.
    """

    name: str
    path: Path
    saved: str
    rms_px: float | None
    views: int | None

    @property
    def label(self) -> str:
        return f"{self.name} ({self.saved[:16]})"


VerdictKind = Literal["new pose", "not seen", "moving", "searching", "captured"]
"""Why a sighting is taken (``new pose``) or not: the board is seen by no sensor, it is
moving, the views' board searches are still running (novelty needs them), or the pose is
captured already."""


@dataclass(frozen=True)
class CaptureVerdict:
    """Whether auto-capture takes a sighting, and why (:meth:`CalibrationSession.assess`).

    Attributes:
        take: take it.
        kind: the reason's kind (:data:`VerdictKind`).
        reason: the reason for the operator, e.g. ``new pose for ccd_left, tof`` or
            ``already captured: view 0007 is 3.1 cm / 2.0° away``.
        nearest: the captured view nearest the sighting (``captured``), else None.
    """

    take: bool
    kind: VerdictKind
    reason: str
    nearest: str | None = None


JobState = Literal["idle", "running", "done", "failed"]


@dataclass
class Job:
    """A background run of the session (one of each kind at a time).

    Attributes:
        state: ``idle`` (never run), ``running``, ``done`` or ``failed``.
        stage: what it is doing now (human readable).
        progress: fraction done, 0-1.
        views: the views it works on.
        error: why it failed.
        report: its report when done.
        started, finished: ``time.time()`` seconds.
        saved_as: the rig version it was saved as, if it was.
    """

    state: JobState = "idle"
    stage: str = ""
    progress: float = 0.0
    views: list[str] = field(default_factory=list)
    error: str | None = None
    report: dict[str, Any] | None = None
    started: float | None = None
    finished: float | None = None
    saved_as: str | None = None


@dataclass
class CalibrationJob(Job):
    """The session's calibration run; ``result``: the calibration when done (``report``:
    the ``report.json`` content)."""

    result: CalibrationResult | None = None


@dataclass
class RangeJob(Job):
    """The session's TOF range calibration run; ``rig``: the rig the board poses come from
    (and that the correction is added to); ``run``: the fit and its validation when done
    (``report``: the ``range.json`` content)."""

    rig: Rig | None = None
    run: RangeRun | None = None


class CalibrationSession:
    """Views, detections, coverage, calibration runs and saved rigs of one work directory.

    Args:
        workdir: the session's directory (created if needed; reopened as it is).
        rig: the rig the console runs with: its sensor names, modalities, sizes and eyes
            are the capture's starting rig (``captures/rig.yaml``, written once).
        board: the checkerboard (``captures/board.yaml``); an existing session with another
            board is refused (use another work directory).
        workers: threads searching views for the board.

    Thread-safe: the console's GUI, REST routes and auto-capture call it concurrently.
    """

    def __init__(self, workdir: str | Path, rig: Rig, board: Board, workers: int = 2) -> None:
        self.workdir = Path(workdir)
        self.captures = self.workdir / CAPTURES
        self.rigs_dir = self.workdir / RIGS
        self.board, self.rig = board, rig
        self.interrupted = self._tidy_after_crash()
        """Staging folders of views a crash interrupted (kept, never listed as views)."""
        if (self.captures / BOARD_FILE).exists():
            existing = load_board(self.captures)
            if existing != board:
                raise SessionError(
                    f"{self.captures}: this session's board is {_board_text(existing)}, not "
                    f"{_board_text(board)}; start the console with another --workdir (or "
                    "--board)"
                )
        else:
            write_board(self.captures, board)
        if (self.captures / RIG_FILE).exists():
            self._check_starting_rig(load_rig(self.captures / RIG_FILE))
        else:
            write_rig(self.captures, rig)
        self._lock = threading.RLock()
        self._views: dict[str, ViewInfo] = {}
        self._pool = ThreadPoolExecutor(max(1, workers), thread_name_prefix="view-detect")
        self.job = CalibrationJob()
        self.range_job = RangeJob()
        self._job_thread: threading.Thread | None = None
        self.on_change: list[Callable[[], None]] = []
        for view in load_capture(self.captures).views:
            self._views[view.name] = ViewInfo(view.name, view.sensors)
            self._pool.submit(self._search, view.name)

    # -- set-up ---------------------------------------------------------------------------

    def _tidy_after_crash(self) -> list[Path]:
        """Remove temporary files of interrupted writes; report interrupted views."""
        staging = (
            sorted(p for p in self.captures.iterdir() if _STAGING_RE.match(p.name) and p.is_dir())
            if self.captures.is_dir()
            else []
        )
        removed = remove_temporaries(self.captures) + remove_temporaries(self.rigs_dir)
        for folder in staging:
            removed += remove_temporaries(folder)
        if removed:
            log.info("removed %d temporary file(s) of interrupted writes", len(removed))
        for folder in staging:
            log.warning(
                "%s: a view whose writing was interrupted (not part of the capture; kept "
                "as it is: its images may be incomplete; remove it when it is not needed)",
                folder,
            )
        return staging

    def _check_starting_rig(self, existing: Rig) -> None:
        mine = {n: (s.modality, s.image_size) for n, s in self.rig.sensors.items()}
        theirs = {n: (s.modality, s.image_size) for n, s in existing.sensors.items()}
        if mine != theirs:
            raise SessionError(
                f"{self.captures / RIG_FILE}: this session's sensors {theirs} differ from "
                f"the console's {mine}; start the console with another --workdir"
            )

    def close(self) -> None:
        """Stop searching; a running calibration finishes in the background (daemon)."""
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _changed(self) -> None:
        for fn in list(self.on_change):
            fn()

    # -- views ----------------------------------------------------------------------------

    def views(self) -> list[ViewInfo]:
        """The captured views, by name."""
        with self._lock:
            return [self._views[n] for n in sorted(self._views)]

    def view(self, name: str) -> ViewInfo:
        with self._lock:
            try:
                return self._views[name]
            except KeyError:
                raise KeyError(f"no view {name!r} (views: {sorted(self._views)})") from None

    def _next_name(self) -> str:
        """One more than the highest view number taken, in the capture, deleted or by a view
        a crash interrupted."""
        used = [
            int(p.name.split("-")[0])
            for root in (self.captures, self.workdir / DELETED)
            if root.is_dir()
            for p in root.iterdir()
            if _VIEW_RE.match(p.name.split("-")[0])
        ]
        used += [int(p.name.split(".")[1]) for p in self.interrupted]  # not reused either
        return f"{next_number(used):04d}"

    def take(self, frames: FrameSet) -> ViewInfo:
        """Write ``frames`` as a new view now; the board search follows in the background.

        Sensors not in the rig are left out. Raises SessionError if no frame is usable.
        """
        usable = FrameSet(
            frames.stamp_ns, {s: f for s, f in frames.frames.items() if s in self.rig}
        )
        if not usable.frames:
            raise SessionError(
                f"nothing to capture: no frame of the rig's sensors {self.rig.names} yet"
            )
        with self._lock:
            for _attempt in range(100):
                name = self._next_name()
                try:
                    write_view(self.captures, name, usable, self.rig)
                    break
                except ViewExistsError:
                    continue
            else:  # pragma: no cover - 100 concurrent writers
                raise SessionError(f"{self.captures}: could not find a free view name")
            info = ViewInfo(name, list(usable.frames))
            self._views[name] = info
        self._pool.submit(self._search, name)
        self._changed()
        return info

    def _search(self, name: str) -> None:
        """Search the view's images as written for the board (in a worker thread)."""
        try:
            view = load_view(self.captures, name, self.rig)
            found: dict[str, Detection] = {}
            params: dict[str, tuple[float, float, float, float]] = {}
            for sensor in view.sensors:
                s = self.rig[sensor]
                try:
                    image = view.frame(sensor).image
                    det = detect_cached(image, self.board, s.modality)
                except (CaptureError, ValueError) as exc:
                    det = Detection(None, f"cannot search this image: {exc}", None)
                found[sensor] = det
                if det.found:
                    params[sensor] = view_params(det.corners, self.board, s.image_size)
            pose = self._board_pose(found)
        except (CaptureError, KeyError, OSError) as exc:  # deleted meanwhile, or unreadable
            with self._lock:
                info = self._views.get(name)
                if info is not None:
                    info.detections = {s: Detection(None, str(exc), None) for s in info.sensors}
            self._changed()
            return
        with self._lock:
            info = self._views.get(name)
            if info is not None:
                info.detections, info.params, info.palettes = found, params, view.palettes
                info.T_rig_board = pose
        self._changed()

    def _board_pose(self, detections: dict[str, Detection]) -> np.ndarray | None:
        """(4, 4) ``T_rig_board`` by the session's rig from the finest sensor (largest
        focal length) whose corners give one, or None."""
        found = [n for n, d in detections.items() if d.found and n in self.rig]
        for name in sorted(found, key=lambda n: -self.rig[n].intrinsics.fx):
            try:
                T = board_pose_single(self.rig, name, detections[name].corners, self.board)
            except ValueError:
                continue
            if T is not None:
                return T
        return None

    def delete(self, name: str) -> Path:
        """Move a view out of the capture into ``deleted/`` (kept, not destroyed)."""
        with self._lock:
            self.view(name)
            if self.job.state == "running" and name in self.job.views:
                raise SessionError(f"view {name} is being calibrated; wait for the run to end")
            trash = self.workdir / DELETED
            make_dirs(trash)
            stem = f"{name}-{time.strftime('%Y%m%dT%H%M%S')}"
            target = trash / first_free(suffixed_names(stem), lambda n: (trash / n).exists())
            (self.captures / name).rename(target)
            fsync_dir(self.captures)
            fsync_dir(trash)
            del self._views[name]
        self._changed()
        return target

    # -- coverage and novelty ------------------------------------------------------------

    def coverage(self) -> dict[str, Coverage]:
        """Coverage of every sensor of the rig by the views' detections."""
        with self._lock:
            views = list(self._views.values())
        out = {}
        for name, s in self.rig.sensors.items():
            corners = [
                v.detections[name].corners
                for v in views
                if name in v.detections and v.detections[name].found
            ]
            out[name] = coverage(corners, self.board, s.image_size)
        return out

    def novelty(self, detections: dict[str, Detection]) -> dict[str, float]:
        """Per sensor that sees the board: ROS novelty against that sensor's views."""
        with self._lock:
            previous = {
                s: [v.params[s] for v in self._views.values() if s in v.params]
                for s in self.rig.names
            }
        out = {}
        for s, det in detections.items():
            if det.found and s in self.rig:
                p = view_params(det.corners, self.board, self.rig[s].image_size)
                out[s] = pose_novelty(p, previous[s])
        return out

    def worth_taking(self, detections: dict[str, Detection], steady: bool) -> str | None:
        """Why a sighting should be auto-captured (None: it should not)."""
        verdict = self.assess(detections, steady)
        return verdict.reason if verdict.take else None

    def assess(
        self,
        detections: dict[str, Detection],
        steady: bool,
        motion: str | None = None,
        T_rig_board: np.ndarray | None = None,
    ) -> CaptureVerdict:
        """Whether auto-capture takes a sighting, and why (module docstring).

        Args:
            detections: sensor -> the sighting's detection.
            steady: the board held still (the board watch's judgement, in frame time).
            motion: how it moved, in words, for the reason when it is not steady.
            T_rig_board: (4, 4) the sighting's board pose in the rig frame, metres: the
                distance to the nearest view's pose is named when the pose is captured
                already.
        """
        if not any(d.found for s, d in detections.items() if s in self.rig):
            return CaptureVerdict(False, "not seen", "the board is not seen")
        with self._lock:
            pending = sorted(n for n, v in self._views.items() if not v.searched)
        if pending:  # novelty needs every view's detections
            return CaptureVerdict(
                False,
                "searching",
                f"waiting for the board search of view {', '.join(pending)}",
            )
        novelty = self.novelty(detections)
        novel = {s: n for s, n in novelty.items() if n > NOVELTY_THRESHOLD}
        if not novel:  # before "moving": holding still here would not help
            return self._captured_already(detections, novelty, T_rig_board)
        if not steady:
            return CaptureVerdict(False, "moving", motion or "moving")
        return CaptureVerdict(True, "new pose", "new pose for " + ", ".join(sorted(novel)))

    def _captured_already(
        self,
        detections: dict[str, Detection],
        novelty: dict[str, float],
        T_rig_board: np.ndarray | None,
    ) -> CaptureVerdict:
        """The ``captured`` verdict: the view nearest the sighting (smallest X/Y/size/skew
        distance, the novelty's measure, in any sensor that sees the board) and how far
        its board pose is."""
        best: tuple[float, str] | None = None
        with self._lock:
            views = list(self._views.values())
        for s, det in detections.items():
            if not det.found or s not in self.rig:
                continue
            p = np.asarray(view_params(det.corners, self.board, self.rig[s].image_size))
            for v in views:
                if s in v.params:
                    d = float(np.sum(np.abs(np.asarray(v.params[s]) - p)))
                    if best is None or d < best[0]:
                        best = (d, v.name)
        worst = max(novelty.values(), default=0.0)
        if best is None:  # pragma: no cover - not novel means some view is near
            return CaptureVerdict(False, "captured", "already captured")
        name = best[1]
        where = f"view {name}"
        T_view = self.view(name).T_rig_board
        if T_rig_board is not None and T_view is not None:
            rot_deg, trans_m = pose_error(np.asarray(T_rig_board, float), T_view)
            where += f" is {100 * trans_m:.1f} cm / {rot_deg:.1f}° away"
        else:
            where += " looks alike"
        return CaptureVerdict(
            False,
            "captured",
            f"already captured: {where} (every sensor has a view within {worst:.2f} in X, "
            f"Y, size and skew; a new one needs > {NOVELTY_THRESHOLD:g} in one sensor)",
            name,
        )

    # -- calibration ----------------------------------------------------------------------

    def start_calibration(self, options: CalibrationOptions | None = None) -> CalibrationJob:
        """Calibrate the current views in a background thread, cross-validated (the report's
        ``cross_validation``: :mod:`app.workflows.cross_validation`); returns the new job."""
        with self._lock:
            if self.job.state == "running":
                raise SessionError("a calibration is running already; wait for it to end")
            names = sorted(self._views)
            if len(names) < ZHANG_MIN_VIEWS:
                raise SessionError(
                    f"{len(names)} view(s) captured; a calibration needs several views of "
                    f"the board (at least {ZHANG_MIN_VIEWS} to start: a sensor is calibrated "
                    f"from {ZHANG_MIN_VIEWS} views that show it the board, with a verdict on "
                    "how well; about 20 for a good calibration)"
                )
            job = CalibrationJob("running", "starting", 0.0, names, started=time.time())
            thread = threading.Thread(
                target=self._calibrate, args=(job, options), name="calibration", daemon=True
            )
            thread.start()
            # shown running only once :meth:`wait` can join its thread (another thread may
            # wait as soon as it sees the job running)
            self._job_thread, self.job = thread, job
        self._changed()
        return job

    def wait(self, timeout_s: float | None = None) -> CalibrationJob:
        """Block until the running calibration ends (or the timeout); returns the job."""
        if self._job_thread is not None:
            self._job_thread.join(timeout_s)
        return self.job

    def _calibrate(self, job: CalibrationJob, options: CalibrationOptions | None) -> None:
        def progress(stage: str, fraction: float) -> None:
            job.stage, job.progress = stage, max(job.progress, min(1.0, fraction))
            self._changed()

        try:
            for k, name in enumerate(job.views):  # searches still running: wait for them
                while not self.view(name).searched:
                    progress(f"searching view {name} for the board", 0.0)
                    time.sleep(0.1)
                progress("searching the views for the board", 0.2 * (k + 1) / len(job.views))
            capture = load_capture(self.captures)
            capture.views = [v for v in capture.views if v.name in job.views]
            for v in capture.views:  # the searches read the images: how palettes were read
                v.palettes.update(self.view(v.name).palettes)
            result, report = calibrate_capture(
                capture,
                options,
                progress=lambda what, f: progress(what, 0.2 + 0.8 * f),
                detections=self.detection_run(job.views),
                cross_validate=True,
            )
        except (CalibrationError, CaptureError, KeyError, ValueError) as exc:
            job.error, job.state = str(exc), "failed"
        except Exception as exc:  # a defect: say so, keep the console running
            job.error, job.state = describe_error(exc), "failed"
        else:
            job.result, job.report, job.state = result, report, "done"
            job.stage, job.progress = "done", 1.0
        job.finished = time.time()
        self._changed()

    def detection_run(self, names: list[str]) -> DetectionRun:
        """The views' detections as a calibration takes them (found corners, reasons)."""
        run = DetectionRun({}, {}, {})
        for name in names:
            for sensor, det in self.view(name).detections.items():
                if det.found:
                    run.observations.setdefault(name, {})[sensor] = det.corners
                    run.methods.setdefault(name, {})[sensor] = det.method or ""
                else:
                    run.rejected.setdefault(name, {})[sensor] = det.reason or "not found"
        return run

    # -- saved rigs -----------------------------------------------------------------------

    def versions(self) -> list[RigVersion]:
        """Saved rigs, oldest first."""
        if not self.rigs_dir.is_dir():
            return []
        out = []
        for p in sorted(self.rigs_dir.iterdir()):
            if not _VERSION_RE.match(p.name):
                continue
            rms = views = None
            report = p.with_name(p.name[: -len(".yaml")] + ".report.json")
            try:
                data = json.loads(report.read_text(encoding="utf-8"))
                rms, views = data.get("rms_px"), len(data.get("views", {})) or None
            except (OSError, ValueError, AttributeError):
                pass
            saved = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(p.stat().st_mtime))
            out.append(RigVersion(p.name[: -len(".yaml")], p, saved, rms, views))
        return out

    def version_path(self, name: str) -> Path:
        path = self.rigs_dir / f"{name}.yaml"
        if not _VERSION_RE.match(path.name) or not path.is_file():
            known = [v.name for v in self.versions()]
            raise KeyError(f"no saved rig {name!r} (saved: {known})")
        return path

    def load_version(self, name: str) -> Rig:
        """A saved rig (RigError if the file was damaged by hand)."""
        return load_rig(self.version_path(name))

    def save(self) -> RigVersion:
        """Write the finished calibration as a new rig version (and its report beside it)."""
        with self._lock:
            job = self.job
            if job.state != "done" or job.result is None:
                raise SessionError("nothing to save: run a calibration first")
            if job.saved_as is not None:
                raise SessionError(f"this calibration is saved already, as {job.saved_as}")
            version = self.save_rig(job.result.rig(), job.report or {})
            job.saved_as = version.name
        self._changed()
        return version

    def save_rig(self, rig: Rig, report: dict[str, Any]) -> RigVersion:
        """Write ``rig`` as the next rig version ``rigs/rig-NNNN.yaml``, its report beside
        it (``rig-NNNN.report.json``); existing versions are never replaced."""
        text = rig_to_yaml(rig)
        with self._lock:
            make_dirs(self.rigs_dir)
            for _attempt in range(100):
                numbers = [  # a report left alone by a crash takes its number too
                    int(m.group(1))
                    for p in self.rigs_dir.iterdir()
                    if (m := _VERSION_FILE_RE.match(p.name))
                ]
                name = f"rig-{next_number(numbers):04d}"
                path = self.rigs_dir / f"{name}.yaml"
                try:
                    atomic_write_text(
                        self.rigs_dir / f"{name}.report.json",
                        json.dumps(report, indent=1) + "\n",
                        overwrite=False,
                    )
                    atomic_write_text(path, text, overwrite=False)
                    break
                except FileExistsError:
                    continue
            else:  # pragma: no cover
                raise SessionError(f"{self.rigs_dir}: could not find a free version name")
        self._changed()
        return next(v for v in self.versions() if v.name == name)

    # -- range calibration ----------------------------------------------------------------

    def start_range_calibration(self, rig: Rig, holdout_every: int = 4) -> RangeJob:
        """Calibrate the TOF's distances on the current views with ``rig`` (a calibrated
        rig: the board poses come from it) in a background thread; returns the new job."""
        with self._lock:
            if self.range_job.state == "running":
                raise SessionError("a range calibration is running already; wait for it to end")
            names = sorted(self._views)
            if len(names) < holdout_every + 3:
                raise SessionError(
                    f"{len(names)} view(s) captured; a range calibration needs at least "
                    f"{holdout_every + 3} views with the board in the TOF's image (3 to fit, "
                    "1 held out to check), 20 or more for a good one"
                )
            self.range_job = job = RangeJob("running", "starting", 0.0, names, rig=rig)
            job.started = time.time()
        threading.Thread(
            target=self._range, args=(job, holdout_every), name="range-calibration", daemon=True
        ).start()
        self._changed()
        return job

    def _range(self, job: RangeJob, holdout_every: int) -> None:
        def progress(stage: str, fraction: float) -> None:
            job.stage, job.progress = stage, max(job.progress, min(1.0, fraction))
            self._changed()

        try:
            for name in job.views:
                while not self.view(name).searched:
                    progress(f"searching view {name} for the board", 0.0)
                    time.sleep(0.1)
            capture = load_capture(self.captures)
            capture.views = [v for v in capture.views if v.name in job.views]
            run = calibrate_range(
                capture,
                job.rig,
                holdout_every,
                progress=progress,
                detections=self.detection_run(job.views),
            )
        except (CaptureError, KeyError, ValueError) as exc:
            job.error, job.state = str(exc), "failed"
        except Exception as exc:  # a defect: say so, keep the console running
            job.error, job.state = describe_error(exc), "failed"
        else:
            job.run, job.report, job.state = run, build_range_report(run, capture), "done"
            job.stage, job.progress = "done", 1.0
        job.finished = time.time()
        self._changed()

    def save_range(self) -> RigVersion:
        """Write the job's rig with its range correction as a new rig version."""
        with self._lock:
            job = self.range_job
            if job.state != "done" or job.run is None or job.rig is None:
                raise SessionError("nothing to save: run a range calibration first")
            if job.saved_as is not None:
                raise SessionError(f"this range calibration is saved already, as {job.saved_as}")
            version = self.save_rig(with_range_correction(job.rig, job.run), job.report or {})
            job.saved_as = version.name
        self._changed()
        return version


def _board_text(board: Board) -> str:
    """:meth:`Board.describe` and the polarity keys it sets (board.yaml)."""
    keys = {k: v for k, v in board.to_dict().items() if k in POLARITY_KEYS}
    text = board.describe()
    if keys:
        text += " with " + ", ".join(f"{k}: {str(v).lower()}" for k, v in keys.items())
    else:
        text += " (polarity found from the data)"
    return text


def radiometry_report(rig: Rig) -> dict[str, Any]:
    """The report saved beside a rig version that records the imagers' radiometry."""
    return {
        "radiometry": {n: s.radiometry.to_dict() for n, s in rig.sensors.items() if s.radiometry}
    }
