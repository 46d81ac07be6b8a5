"""One sighting of the board: every sensor of a frame set searched, the pose, steadiness.

:func:`sighting` searches the sensors of a frame set in the order their detection is trusted
for the pose (:data:`POSE_PREFERENCE`: colour, thermal, TOF) and gives a
:class:`BoardSighting`: each sensor's corners (or why not), the board's pose in the rig frame
(:func:`board_pose`, from the most trusted sensor that found it) and whether the board held
still since the previous sighting (:data:`STEADY_PX`). :class:`LookCache` shares the looks
at each image between threads; :class:`~app.server.runtime.board_watch.BoardWatch` decides
when and on which threads the searches run.

Colour images of at least :data:`COARSE_MIN_WIDTH` pixels are searched at half resolution
first (:func:`first_look`), the corners then found at full resolution in a crop around the
board; a full-resolution search of the whole image only when the half-resolution one finds
nothing, and not where the pose from another sensor puts the board (partly) outside the
image (:func:`board_in_image`).

Which squares read hot or dark in a thermal or TOF image depends on the board
(calib.polarity): the images are searched with ``board.yaml``'s polarity keys when it sets
them, and otherwise each complete sighting puts every thermal and TOF detection in the
ordering that agrees with the board pose a colour camera found, through the rig in use
(:func:`orient_by_colour`), so that the Feeds panel, the steadiness and auto-capture see
the corners in the right order.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.app.sources.frames import FrameSet
from trifuse.calib.board import Board
from trifuse.calib.board_ordering import orient_to_pose
from trifuse.calib.detect import Detection
from trifuse.calib.polarity import detect_board_configured, override
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import invert, make_T, rotation_from_rvec

STEADY_PX = 2.0
"""A board is steady when no corner moved more than this many pixels (in any sensor that
saw it both times) since the previous sighting."""

POSE_PREFERENCE = ("color", "thermal", "tof")
"""Modalities in the order their detection is trusted for the board's pose."""

COARSE_MIN_WIDTH = 960
"""Colour images at least this wide are searched at half resolution first."""
COARSE_CROP_MARGIN = 2.0
"""The full-resolution crop around a board found at half resolution reaches this many
corner spacings (plus 8 px) beyond the outer corners: the outer squares, the board's
margin and a quiet zone for the detector."""

Detector = Callable[[np.ndarray, Board, str], Detection]


@dataclass(frozen=True, eq=False)
class BoardSighting:
    """One detection pass over a frame set.

    Attributes:
        frames: the frame set that was searched (what a capture of this sighting writes).
        detections: sensor -> :class:`~calib.detect.Detection` (corners (N, 2) px or a
            reason); a partial sighting has those of the sensors searched so far.
        T_rig_board: (4, 4) board pose in the rig frame, metres (from the most trusted
            sensor that found it, with the rig's intrinsics and pose), or None.
        pose_sensor: the sensor the pose comes from, or None.
        steady: found in at least one sensor, and no sensor that found it in the previous
            sighting too saw a corner move more than :data:`STEADY_PX`.
        complete: every sensor was searched (False: the pose was published early).
    """

    frames: FrameSet
    detections: dict[str, Detection]
    T_rig_board: np.ndarray | None
    pose_sensor: str | None
    steady: bool
    complete: bool = True

    @property
    def found(self) -> list[str]:
        """Sensors whose image shows the board."""
        return [s for s, d in self.detections.items() if d.found]


MIN_POSE_CORNERS = 6
"""A partial view (ChArUco) gives a pose from at least this many corners."""


def board_pose(rig: Rig, sensor: str, corners: np.ndarray, board: Board) -> np.ndarray | None:
    """(4, 4) ``T_rig_board`` from one sensor's corners (N, 2) pixels, NaN rows for corners
    not seen (a partial view: at least :data:`MIN_POSE_CORNERS`), by PnP with the rig's
    intrinsics; None when PnP fails or too few corners were seen."""
    intr = rig[sensor].intrinsics
    corners = np.asarray(corners, dtype=np.float64)
    seen = np.isfinite(corners).all(axis=1)
    if seen.sum() < min(MIN_POSE_CORNERS, len(corners)):
        return None
    ok, rvec, tvec = cv2.solvePnP(
        board.object_points()[seen].astype(np.float64),
        corners[seen].reshape(-1, 1, 2),
        intr.K,
        np.asarray(intr.distortion, dtype=np.float64),
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        return None
    return rig[sensor].T_rig_sensor @ make_T(rotation_from_rvec(rvec.ravel()), tvec.ravel())


def board_in_image(rig: Rig, sensor: str, T_rig_board: np.ndarray, board: Board) -> bool:
    """Whether every inner corner of the board at ``T_rig_board`` (4, 4) projects into
    ``sensor``'s image (in front of it, within its pixels), by the rig's calibration; of a
    board seen in part (ChArUco), whether at least :data:`MIN_POSE_CORNERS` do."""
    s = rig[sensor]
    T = invert(s.T_rig_sensor) @ np.asarray(T_rig_board, dtype=np.float64)
    P = board.object_points() @ T[:3, :3].T + T[:3, 3]
    uv = s.intrinsics.project(P)
    w, h = s.image_size
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    inside &= np.isfinite(uv).all(axis=1) & (P[:, 2] > 0)
    if board.partial_views:
        return int(inside.sum()) >= MIN_POSE_CORNERS
    return bool(np.all(inside))


def orient_by_colour(
    detections: dict[str, Detection],
    rig: Rig,
    board: Board,
    T_rig_board: np.ndarray | None,
    pose_sensor: str | None,
) -> dict[str, Detection]:
    """Thermal and TOF detections in the ordering that agrees with a colour camera's.

    Which squares read hot or dark in a thermal or TOF image depends on the board
    (calib.polarity); unless ``board.yaml`` fixes it, each such detection is compared with
    where the board pose ``T_rig_board`` (4, 4), found by the colour camera ``pose_sensor``,
    puts the corners in that sensor's image through the rig, and is reversed (relabelled by
    the half turn, method suffixed ``-turned``) when the reversed ordering is the one that
    agrees. Without a colour camera's pose, or where the expected corners do not tell, the
    detections stay as they are. A ChArUco board's markers name every corner: its
    detections are never turned.
    """
    if T_rig_board is None or pose_sensor is None or rig[pose_sensor].modality != "color":
        return detections
    if board.pattern == "charuco":
        return detections
    out = dict(detections)
    for name, det in detections.items():
        m = rig[name].modality
        if not det.found or m not in ("thermal", "tof") or override(board, m) is not None:
            continue
        T_sensor_board = invert(rig[name].T_rig_sensor) @ T_rig_board
        got = orient_to_pose(det.corners, rig[name].intrinsics, T_sensor_board, board)
        if got is not None and got[1]:
            out[name] = Detection(got[0], None, f"{det.method}-turned")
    return out


def _corner_spacing(corners: np.ndarray, board: Board) -> float:
    """Median distance between neighbouring points (N, 2) of the board's grid (along a row
    and down a column; corners not seen, NaN rows, left out), pixels."""
    G = corners.reshape(board.rows, board.cols, 2)
    dx = np.linalg.norm(np.diff(G, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(G, axis=0), axis=2)
    d = np.concatenate([dx.ravel(), dy.ravel()])
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else 0.0


def first_look(
    image: np.ndarray, board: Board, modality: str, detect: Detector = detect_board_configured
) -> tuple[Detection, bool]:
    """Search one sensor image, colour images of at least :data:`COARSE_MIN_WIDTH` pixels
    at half resolution first.

    Returns:
        (detection, coarse): the detection in the original image's pixels (as
        ``detect`` gives it, its method suffixed ``-crop`` when the corners come from the
        full-resolution crop around a board found at half resolution), and whether only
        the half-resolution image was searched and showed no board (a full-resolution
        search might still find a small one).
    Raises:
        ValueError: what ``detect`` raises for an image it cannot search.
    """
    a = np.asarray(image)
    coarse_ok = modality == "color" and a.dtype == np.uint8 and a.ndim in (2, 3)
    if not coarse_ok or a.shape[1] < COARSE_MIN_WIDTH:
        return detect(a, board, modality), False
    h, w = a.shape[:2]
    small = cv2.resize(a, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    coarse = detect(small, board, modality)
    if not coarse.found:
        return Detection(None, f"{coarse.reason} (half resolution)", coarse.method), True
    # pixel centres: full = (half + 0.5) * 2 - 0.5 (docs/CONVENTIONS.md)
    G = (coarse.corners + 0.5) * 2.0 - 0.5
    margin = COARSE_CROP_MARGIN * _corner_spacing(G, board) + 8.0
    x0 = max(0, int(np.floor(np.nanmin(G[:, 0]) - margin)))
    x1 = min(w, int(np.ceil(np.nanmax(G[:, 0]) + margin)) + 1)
    y0 = max(0, int(np.floor(np.nanmin(G[:, 1]) - margin)))
    y1 = min(h, int(np.ceil(np.nanmax(G[:, 1]) + margin)) + 1)
    fine = detect(np.ascontiguousarray(a[y0:y1, x0:x1]), board, modality)
    if fine.found:
        corners = fine.corners + np.array([x0, y0], dtype=np.float64)
        return Detection(corners, None, f"{fine.method}-crop"), False
    return detect(a, board, modality), False  # the crop misled (rare): the whole image


Looker = Callable[[str, np.ndarray, str], tuple[Detection, bool]]
"""(sensor, image, modality) -> :func:`first_look`'s (detection, coarse)."""


def safe_look(
    looker: Looker, name: str, image: np.ndarray, modality: str
) -> tuple[Detection, bool]:
    """``looker``'s result, or a detection saying why a malformed image was not searched."""
    try:
        return looker(name, image, modality)
    except ValueError as exc:  # a malformed frame: say so, keep watching
        return Detection(None, f"cannot search this image: {exc}", None), False


class LookCache:
    """Per sensor, the newest image looked at and its :func:`first_look` result, shared by
    the threads that ask for it: a second request for the very same image object waits
    for the first one's result instead of searching again.

    Args:
        board: the checkerboard.
        detect: the detector.
    """

    def __init__(self, board: Board, detect: Detector = detect_board_configured) -> None:
        self.board, self.detect = board, detect
        self._lock = threading.Lock()
        self._entries: dict[str, tuple[np.ndarray, Future]] = {}

    def __call__(self, name: str, image: np.ndarray, modality: str) -> tuple[Detection, bool]:
        with self._lock:
            entry = self._entries.get(name)
            mine = entry is None or entry[0] is not image
            if mine:
                entry = (image, Future())
                self._entries[name] = entry
        fut = entry[1]  # type: ignore[index]
        if mine:
            try:
                fut.set_result(first_look(image, self.board, modality, self.detect))
            except BaseException as exc:  # the waiting threads get it too
                fut.set_exception(exc)
        return fut.result()


class _Now:
    """A finished :class:`~concurrent.futures.Future` look-alike (no pool)."""

    def __init__(self, fn: Callable[..., Detection], *args: object) -> None:
        self._value = fn(*args)

    def result(self) -> Detection:
        return self._value


def trusted(rig: Rig, names: list[str]) -> list[str]:
    """``names`` in the order of :data:`POSE_PREFERENCE` (stable within a modality)."""
    rank = {m: i for i, m in enumerate(POSE_PREFERENCE)}
    return sorted(names, key=lambda n: rank.get(rig[n].modality, len(rank)))


def sighting(
    frames: FrameSet,
    rig: Rig,
    board: Board,
    previous: BoardSighting | None = None,
    pool: ThreadPoolExecutor | None = None,
    *,
    on_pose: Callable[[BoardSighting], None] | None = None,
    full_search: Collection[str] | None = None,
    detect: Detector = detect_board_configured,
    looker: Looker | None = None,
) -> BoardSighting:
    """Detect the board in every frame of ``frames`` (sensors of ``rig`` only).

    An image that is the very object the previous sighting searched (a source repeating a
    frame) keeps its detection. The sensors are searched in the order of
    :data:`POSE_PREFERENCE` (in ``pool``'s threads if given); as soon as the most trusted
    sensor showing the board is known, ``on_pose`` gets a partial sighting with the pose.

    Args:
        full_search: colour cameras that may get a full-resolution search when the
            half-resolution one finds nothing (:func:`first_look`), unless the pose from
            another sensor puts the board (partly) outside their image; None: all.
        detect: the detector (:func:`calib.detect.detect_board`'s signature; default
            :func:`calib.polarity.detect_board_configured`: with the board file's polarity
            overrides).
        looker: does the first look at a sensor's image (default :func:`first_look` with
            ``detect``); :class:`LookCache` shares looks between threads.
    """
    names = trusted(rig, [s for s in frames.frames if s in rig])
    first = looker or (lambda name, image, modality: first_look(image, board, modality, detect))

    def reused(name: str) -> Detection | None:
        if previous is None or name not in previous.detections:
            return None
        seen = previous.frames.frames.get(name)
        if seen is not None and seen.image is frames.frames[name].image:  # the same image
            return previous.detections[name]
        return None

    def look(name: str) -> tuple[Detection, bool]:
        old = reused(name)
        if old is not None:
            return old, False
        return safe_look(first, name, frames.frames[name].image, rig[name].modality)

    def full(name: str) -> Detection:
        try:
            return detect(frames.frames[name].image, board, rig[name].modality)
        except ValueError as exc:
            return Detection(None, f"cannot search this image: {exc}", None)

    def submit(fn: Callable[..., object], name: str) -> Future | _Now:
        return pool.submit(fn, name) if pool is not None else _Now(fn, name)  # type: ignore

    looks = {n: submit(look, n) for n in names}
    detections: dict[str, Detection] = {}
    missed: list[str] = []  # colour cameras searched at half resolution only, in vain
    pose_sensor: str | None = None
    pose: np.ndarray | None = None
    published = False
    for name in names:  # in order of trust: the first found gives the pose
        det, coarse = looks[name].result()  # type: ignore[misc]
        detections[name] = det
        if coarse:
            missed.append(name)
        if pose_sensor is None and det.found:
            pose = board_pose(rig, name, det.corners, board)
            if pose is not None:
                pose_sensor = name
        if pose is not None and not published and on_pose is not None:
            if len(detections) < len(names):  # more to come: publish now
                on_pose(BoardSighting(frames, dict(detections), pose, pose_sensor, False, False))
                published = True
    # a full-resolution search only where the board may be (too small at half resolution):
    # not where the pose from another sensor puts it (partly) outside the image
    retries = {
        n: submit(full, n)
        for n in missed
        if (full_search is None or n in full_search)
        and (pose is None or board_in_image(rig, n, pose, board))
    }
    if retries and pose is not None and not published and on_pose is not None:
        on_pose(BoardSighting(frames, dict(detections), pose, pose_sensor, False, False))
    if retries:
        for name, fut in retries.items():
            detections[name] = fut.result()  # type: ignore[assignment]
        pose_sensor, pose = None, None
        for name in names:
            det = detections[name]
            if det.found and (T := board_pose(rig, name, det.corners, board)) is not None:
                pose_sensor, pose = name, T
                break
    detections = orient_by_colour(detections, rig, board, pose, pose_sensor)
    moved = [
        _moved_px(det.corners, previous.detections[name].corners)
        for name, det in detections.items()
        if det.found
        and previous is not None
        and name in previous.detections
        and previous.detections[name].found
    ]
    steady = bool(moved) and max(moved) <= STEADY_PX
    ordered = {n: detections[n] for n in frames.frames if n in detections}
    return BoardSighting(frames, ordered, pose, pose_sensor, steady)


def _moved_px(now: np.ndarray, before: np.ndarray) -> float:
    """How far (pixels) the corners (N, 2) seen both times moved at most; inf when a partial
    view (NaN rows) shares no corner with the previous one."""
    d = np.linalg.norm(now - before, axis=1)
    d = d[np.isfinite(d)]
    return float(d.max()) if len(d) else math.inf
