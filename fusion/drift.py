"""Calibration drift found without a board: does each sensor still sit where the rig says?

A bump, a loose screw or a warm-up turns a sensor by a few tenths of a degree (0.3 degrees
is 7 colour pixels of misregistration); the fused picture goes wrong quietly. This module
notices it on ordinary scenes:

1. every few seconds (:class:`DriftCheck.measure`) each *pair* of cameras is compared on the
   frames of one instant: the thermal imager of each eye against its colour camera, the two
   colour cameras, the two thermal imagers. The other camera's picture is brought to the
   pixels of the first through the TOF depth and the rotation that best aligns their edges
   is measured (:mod:`fusion.drift_align`): ``delta_a - delta_b`` (rig frame), where
   ``delta_s`` is the small rotation by which sensor ``s`` is really turned against the rig
   (its own frame: ``T_rig_s(true) = T_rig_s @ [[R(delta_s), 0], [0, 1]]``, ``R`` Rodrigues);
2. over the last :data:`WINDOW_S` seconds, each pair's measurements are combined
   (:func:`combine`: a robust random-effects mean, so that instants that really differ, as
   the views of a real rig that is not rigid do, widen the uncertainty instead of bending
   the mean);
3. the sensors' rotations are solved from the pairs (least squares), in the gauge where
   they are smallest together (the geometric median of the sensors' rotations is taken
   out: the sensors that did not move agree and define "unmoved");
4. each sensor gets a verdict (:func:`verdict`): ``drifted`` when its rotation exceeds
   :data:`DRIFT_DEG` by :data:`SIGNIFICANCE` standard deviations, ``ok`` when it is below
   :data:`DRIFT_DEG` and known to :data:`UNDECIDED_SIGMA_DEG`, else ``undecided`` with the
   reason (no TOF depth, a camera missing, too little structure yet, a sensor compared with
   only one other so that which of the two moved cannot be told).

The TOF is compared with the first two colour cameras through its own depth edges
(:mod:`fusion.drift_tof`: where its mixed pixels put an object's outline against where the
camera sees it); those measurements join the pairs' as ``delta_tof - delta_camera``. A TOF
turned 0.3 degrees reads within 0.03 degrees in an instant on the simulator, about the
optical axis within 0.1.

Only rotations are estimated. A sensor shifted by 2 mm moves its picture by 0.8 thermal
pixels at 1 m and 0.2 at 4 m (fx 400), a turn of 0.1 degrees by 0.7 pixels at any depth: on
scenes 1-10 m away a small shift looks like a smaller turn and cannot be told apart from it
with the TOF's depth errors (tens of millimetres), so a bump's shift is absorbed into the
rotation that best restores the agreement over the depths seen.

:func:`refined_rig` applies the drifted sensors' corrections (the next rig version); a
correction larger than :data:`REFUSE_DEG` is refused: that needs a recalibration.

Pure core: frames in, numbers out; the console runs it off the fusion thread
(:mod:`app.server.runtime.drift_watch`) and ``trifuse check`` over a recording.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

import cv2
import numpy as np

from trifuse.calib.rig import Rig
from trifuse.calib.transforms import invert, make_T, rotation_from_rvec
from trifuse.fusion.drift_align import PairProbe, PairRotation, work_image
from trifuse.fusion.drift_tof import TofEdgeProbe
from trifuse.fusion.geometry import tof_sensor_name
from trifuse.fusion.mapping import MappingOptions, TofGrid

Verdict = Literal["ok", "drifted", "undecided"]

WINDOW_S = 60.0
"""Measurements older than this (seconds) no longer count."""
DRIFT_DEG = 0.15
"""A sensor turned by more than this, degrees, is drifted (0.15 degrees is 3.5 colour pixels
of misregistration at the simulated head's 1333 px focal length)."""
SIGNIFICANCE = 4.0
"""... when the rotation exceeds DRIFT_DEG by this many standard deviations along it."""
UNDECIDED_SIGMA_DEG = 0.05
"""A sensor whose rotation is known worse than this (1-sigma, any axis, degrees) is
undecided unless clearly drifted: not enough structure seen yet."""
MIN_MEASUREMENTS = 4
"""A pair counts once it has this many measurements in the window (with three, a scatter
is barely known: a refined rig 0.11 degrees off was seen once, where four gave 0.02)."""
PAIR_FLOOR_DEG = 0.02
"""The part of a pair's error that averaging does not remove (1-sigma per axis, degrees):
the check's systematic error on the simulator, about 0.02 degrees (docs/FINDINGS.md),
added to each measurement's covariance and to every pair's combined one. A sensor compared
with two others is then known to 0.014 degrees at best, and ``drifted`` needs at least
0.21 degrees."""
REFUSE_DEG = 2.0
"""A correction larger than this, degrees, is refused by :func:`refined_rig`: recalibrate."""
OUTLIER_D = 4.0
"""A measurement farther than this (Mahalanobis, 3 degrees of freedom: 99.9 % of normal
ones are nearer) from a pair's mean is left out of the spread :func:`combine` estimates."""
MAX_SPREAD_S = 0.012
"""An instant is measured only when its frames' stamps lie within this many seconds of each
other (:func:`synchronous`): a head turning at 4 degrees a second turns 0.05 degrees in
12 ms, which two sensors' frames taken that far apart would read as drift."""


def synchronous(frames: Mapping[str, Any], max_spread_s: float = MAX_SPREAD_S) -> bool:
    """Whether the frames (objects with ``stamp_ns``) were taken within ``max_spread_s``."""
    stamps = [f.stamp_ns for f in frames.values()]
    return len(stamps) < 2 or (max(stamps) - min(stamps)) / 1e9 <= max_spread_s


def camera_pairs(rig: Rig) -> list[tuple[str, str]]:
    """The pairs compared, (work, other) with the coarser camera first: each eye's thermal
    imager against its colour camera, the first two colour cameras, the first two thermal
    imagers (a ring: every camera is compared with two others)."""
    pairs: list[tuple[str, str]] = [(e.thermal, e.color) for e in rig.eyes.values()]
    for modality in ("color", "thermal"):
        names = rig.by_modality(modality)
        if len(names) >= 2:
            pairs.append((names[0], names[1]))
    seen: set[frozenset[str]] = set()
    out = []
    for a, b in pairs:
        key = frozenset((a, b))
        if a != b and key not in seen:
            seen.add(key)
            out.append((a, b))
    return out


def tof_partners(rig: Rig, tof: str | None) -> list[tuple[str, str]]:
    """The TOF's measurements, (tof, camera): against the first two colour cameras
    (:mod:`fusion.drift_tof`); none without a TOF."""
    if tof is None:
        return []
    return [(tof, c) for c in rig.by_modality("color")[:2]]


def grey(image: np.ndarray) -> np.ndarray:
    """A colour camera's picture (h, w, 3) RGB or (h, w) as (h, w) uint8/float grey."""
    a = np.ascontiguousarray(image)
    return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a


@dataclass(frozen=True)
class PairEstimate:
    """A pair's combined measurements over the window: ``theta`` (3,) radians, rig frame,
    ``delta_work - delta_other``; ``cov`` (3, 3) rad^2; ``count`` measurements."""

    work: str
    other: str
    theta: np.ndarray
    cov: np.ndarray
    count: int


def _psd(a: np.ndarray) -> np.ndarray:
    """The symmetric (3, 3) matrix ``a`` with its negative eigenvalues set to 0."""
    vals, vecs = np.linalg.eigh(0.5 * (a + a.T))
    return (vecs * np.maximum(vals, 0.0)) @ vecs.T


def combine(measurements: list[PairRotation], huber_k: float = 2.0) -> PairEstimate | None:
    """A pair's measurements combined as a random-effects mean: each measurement's covariance
    is its own plus :data:`PAIR_FLOOR_DEG`'s, plus ``Q``, the spread of the instants' true
    values that the measurements' own covariances do not explain (the scene, the sensors'
    sync, a rig that is not rigid),
    estimated from the scatter of the measurements nearer than :data:`OUTLIER_D` (three or
    more; started from the per-axis median absolute deviation); Huber weights on each
    measurement's Mahalanobis distance. The mean's covariance is the weighted information's
    inverse plus :data:`PAIR_FLOOR_DEG`'s. When the scatter is explained (``Q`` = 0) this is
    the information-weighted mean; when it dominates, close to the plain mean with the
    scatter over the count as covariance (weighting by the formal information alone, whose
    correlations are then wrong, moved a real pair's roll by 0.5 degrees: docs/FINDINGS.md).
    None when empty."""
    if not measurements:
        return None
    th = np.stack([m.theta for m in measurements])
    # no instant is known better than the check's systematic error: a measurement whose
    # patches claimed 0.00004 degrees along one direction once pulled a pair's roll by
    # 0.75 degrees through its bounded Huber weight (BENCHMARKS.md, drift, session 33)
    C = np.stack([m.cov for m in measurements]) + np.eye(3) * math.radians(PAIR_FLOOR_DEG) ** 2
    n = len(th)
    w = np.ones(n)
    mean = np.median(th, axis=0)
    # a robust start for Q (the per-axis median absolute deviation), so that a spread the
    # own covariances do not explain is not first taken for outliers
    mad = 1.4826 * np.median(np.abs(th - mean), axis=0) if n >= 3 else np.zeros(3)
    Q = _psd(np.diag(mad**2) - C.mean(axis=0) * np.eye(3))
    for _ in range(12):
        info = np.linalg.inv(C + Q)
        N = np.einsum("n,nij->ij", w, info)
        mean = np.linalg.solve(N, np.einsum("n,nij,nj->i", w, info, th))
        r = th - mean
        d = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, info, r), 0.0))
        w = np.minimum(1.0, huber_k * math.sqrt(3.0) / np.maximum(d, 1e-12))
        keep = d < OUTLIER_D  # Q from the measurements that are not outliers
        if n >= 3 and keep.sum() >= 3:
            scatter = r[keep].T @ r[keep] / (keep.sum() - 1.0)
            Q = _psd(scatter - C[keep].mean(axis=0))
    cov = np.linalg.inv(N) + np.eye(3) * math.radians(PAIR_FLOOR_DEG) ** 2
    m0 = measurements[0]
    return PairEstimate(m0.work, m0.other, mean, cov, n)


@dataclass(frozen=True)
class SensorCheck:
    """One sensor's state.

    Attributes:
        verdict: ``ok``, ``drifted`` or ``undecided``.
        rotation_deg: (3,) the estimated rotation, degrees, the sensor's own frame (the
            correction: the sensor really sits at ``T_rig_s @ R(rotation)``); None when not
            estimated.
        sigma_deg: (3,) its 1-sigma per axis, degrees; None when not estimated.
        reason: why, in a sentence.
        pairs: the partners it was compared with in the window.
    """

    verdict: Verdict
    rotation_deg: tuple[float, float, float] | None
    sigma_deg: tuple[float, float, float] | None
    reason: str
    pairs: tuple[str, ...] = ()

    @property
    def angle_deg(self) -> float | None:
        """The rotation's angle, degrees."""
        return None if self.rotation_deg is None else float(np.linalg.norm(self.rotation_deg))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: verdict, rotation_deg [x, y, z], angle_deg, sigma_deg [x, y, z] (the
        largest of them as ``sigma_max_deg``), reason, pairs."""
        return {
            "verdict": self.verdict,
            "rotation_deg": None if self.rotation_deg is None else list(self.rotation_deg),
            "angle_deg": self.angle_deg,
            "sigma_deg": None if self.sigma_deg is None else list(self.sigma_deg),
            "sigma_max_deg": None if self.sigma_deg is None else max(self.sigma_deg),
            "reason": self.reason,
            "pairs": list(self.pairs),
        }


@dataclass(frozen=True)
class DriftReport:
    """Every sensor's :class:`SensorCheck` (rig order), the pairs' estimates, how many
    instants were measured in the window and the problems met (missing frames, pairs without
    structure), newest last."""

    sensors: dict[str, SensorCheck]
    pairs: tuple[PairEstimate, ...]
    instants: int
    problems: tuple[str, ...] = ()

    @property
    def drifted(self) -> list[str]:
        return [n for n, s in self.sensors.items() if s.verdict == "drifted"]

    @property
    def all_ok(self) -> bool:
        return all(s.verdict == "ok" for s in self.sensors.values())

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: ``{"sensors": {name: SensorCheck.as_dict()}, "instants": n,
        "pairs": [{"work", "other", "rotation_deg", "sigma_deg", "count"}], "problems"}``."""
        return {
            "sensors": {n: s.as_dict() for n, s in self.sensors.items()},
            "instants": self.instants,
            "pairs": [
                {
                    "work": p.work,
                    "other": p.other,
                    "rotation_deg": np.degrees(p.theta).round(4).tolist(),
                    "sigma_deg": np.degrees(np.sqrt(np.diag(p.cov))).round(4).tolist(),
                    "count": p.count,
                }
                for p in self.pairs
            ],
            "problems": list(self.problems),
        }


def _geometric_median(x: np.ndarray, iterations: int = 50) -> np.ndarray:
    """Weiszfeld: the point (3,) minimising the summed distances to the rows of x (n, 3)."""
    m = np.median(x, axis=0)
    for _ in range(iterations):
        d = np.maximum(np.linalg.norm(x - m, axis=1), 1e-12)
        m = (x / d[:, None]).sum(axis=0) / (1.0 / d).sum()
    return m


def solve_sensors(
    estimates: list[PairEstimate],
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Each compared sensor's rotation (3,) radians, rig frame, and its covariance (3, 3):
    least squares over the pairs (``theta = delta_work - delta_other``), in each connected
    group of sensors (:func:`groups`) the geometric median of its sensors' rotations taken
    out (module docstring, step 3). A sensor's covariance is that of its own pairs with the
    partners held: ``(sum C_p^-1)^-1``."""
    rot: dict[str, np.ndarray] = {}
    cov: dict[str, np.ndarray] = {}
    for names in groups(estimates):
        idx = {n: i for i, n in enumerate(names)}
        k = len(names)
        N = np.zeros((3 * k, 3 * k))
        rhs = np.zeros(3 * k)
        own = {n: np.zeros((3, 3)) for n in names}
        for p in estimates:
            if p.work not in idx:
                continue
            W = np.linalg.inv(p.cov)
            i, j = 3 * idx[p.work], 3 * idx[p.other]
            for a, sa in ((i, 1.0), (j, -1.0)):
                rhs[a : a + 3] += sa * (W @ p.theta)
                for b, sb in ((i, 1.0), (j, -1.0)):
                    N[a : a + 3, b : b + 3] += sa * sb * W
            own[p.work] += W
            own[p.other] += W
        scale = np.trace(N) / (3 * k)
        A = np.kron(np.ones((k, k)), np.eye(3)) * 1e-6 * scale  # the group's sum = 0
        delta = np.linalg.solve(N + A, rhs).reshape(k, 3)
        delta -= _geometric_median(delta)
        for n in names:
            rot[n] = delta[idx[n]]
            cov[n] = np.linalg.pinv(own[n])
    return rot, cov


def verdict(
    rotation_rig: np.ndarray, cov_rig: np.ndarray, partners: int, component: int
) -> tuple[Verdict, str]:
    """A sensor's verdict from its rotation (3,) and covariance (3, 3), radians, the number
    of distinct sensors it was compared with and the size of its connected group of
    sensors (module docstring, step 4)."""
    angle = math.degrees(float(np.linalg.norm(rotation_rig)))
    sig = np.degrees(np.sqrt(np.maximum(np.diag(cov_rig), 0.0)))
    if angle > 1e-9:
        u = rotation_rig / np.linalg.norm(rotation_rig)
        along = math.degrees(math.sqrt(max(float(u @ cov_rig @ u), 0.0)))
    else:
        along = float(sig.max())
    text = f"turned {angle:.3f}° ± {along:.3f}°"
    if component < 3 or partners < 2:
        return (
            "undecided",
            f"{text} against its only partner: which of the two moved cannot be told "
            "without a third camera",
        )
    if angle > DRIFT_DEG + SIGNIFICANCE * along:
        return "drifted", f"{text}: more than {DRIFT_DEG}° (recalibrate or refine)"
    if sig.max() > UNDECIDED_SIGMA_DEG:
        return "undecided", f"{text}: not enough structure seen yet (σ up to {sig.max():.2f}°)"
    if angle <= DRIFT_DEG:
        return "ok", f"{text}: within {DRIFT_DEG}°"
    return "undecided", f"{text}: above {DRIFT_DEG}° but not by {SIGNIFICANCE:g} σ yet"


def groups(estimates: list[PairEstimate]) -> list[list[str]]:
    """The connected groups of sensors in the graph of measured pairs, each sorted."""
    parent: dict[str, str] = {}

    def root(x: str) -> str:
        while parent.setdefault(x, x) != x:
            x = parent[x]
        return x

    for p in estimates:
        parent[root(p.work)] = root(p.other)
    out: dict[str, list[str]] = {}
    for n in sorted(parent):
        out.setdefault(root(n), []).append(n)
    return list(out.values())


class DriftCheck:
    """Measures a rig's cameras against each other on frame sets and keeps the last
    :data:`WINDOW_S` seconds (module docstring).

    :meth:`measure` per instant (a frame set with every camera's image and the TOF's
    distance and amplitude; about 0.3 s of one core for the simulated head's four pairs and
    the TOF's two); :meth:`report` whenever a verdict is wanted. Not thread-safe: one thread
    measures and reports.
    """

    def __init__(self, rig: Rig, window_s: float = WINDOW_S) -> None:
        self.rig = rig
        self.window_s = float(window_s)
        self.tof: str | None
        try:
            self.tof = tof_sensor_name(rig)
        except (KeyError, ValueError):
            self.tof = None
        self.pairs = camera_pairs(rig)
        self.tof_pairs = tof_partners(rig, self.tof)
        self._probes: list[PairProbe] | None = None
        self._tof_probes: list[TofEdgeProbe] = []
        self._grid: TofGrid | None = None
        self._history: deque[tuple[float, list[PairRotation]]] = deque()
        self._problems: deque[str] = deque(maxlen=8)
        self._edge_rel = MappingOptions().edge_rel

    def _ensure_probes(self) -> tuple[list[PairProbe], TofGrid]:
        """The pairs' probes and the TOF's rays, made at the first measure."""
        if self._probes is None or self._grid is None:
            assert self.tof is not None
            self._grid = TofGrid(self.rig, self.tof)
            self._probes = [PairProbe(self.rig, a, b, self._grid) for a, b in self.pairs]
            self._tof_probes = [TofEdgeProbe(self.rig, a, b) for a, b in self.tof_pairs]
        return self._probes, self._grid

    def measure(self, t_s: float, frames: Mapping[str, Any]) -> list[PairRotation]:
        """Measure every pair on one instant's frames (``frames[name]``: an object with
        ``image`` and, for the TOF, ``distance_m``, as :class:`app.sources.frames.Frame`);
        ``t_s`` its time, seconds (any clock, increasing). Returns the pairs measured; the
        problems (a frame missing, no structure) are kept for :meth:`report`."""
        if self.tof is None:
            self._problem("no TOF in the rig: pictures cannot be compared without depth")
            return []
        tof = frames.get(self.tof)
        if tof is None or getattr(tof, "distance_m", None) is None:
            self._problem(f"no TOF depth ({self.tof}) at this instant")
            return []
        probes, grid = self._ensure_probes()
        points = grid.points(tof.distance_m, self._edge_rel)
        if len(points) < 100:
            self._problem(f"the TOF ({self.tof}) sees almost nothing ({len(points)} points)")
            return []
        images: dict[str, np.ndarray] = {}
        out: list[PairRotation] = []
        for probe in probes:
            missing = [n for n in (probe.work, probe.other) if frames.get(n) is None]
            if missing:
                self._problem(f"no frame of {', '.join(missing)} at this instant")
                continue
            for n in (probe.work, probe.other):
                if n not in images:
                    images[n] = work_image(self.rig[n], frames[n].image)
            r = probe.measure(images[probe.work], images[probe.other], points)
            if isinstance(r, str):
                self._problem(r)
            else:
                out.append(r)
        amplitude = getattr(tof, "image", None)
        if amplitude is not None and np.shape(amplitude) != np.shape(tof.distance_m):
            amplitude = None
        for tp in self._tof_probes:
            cam = frames.get(tp.other)
            if cam is None:
                self._problem(f"no frame of {tp.other} at this instant")
                continue
            r = tp.measure(tof.distance_m, amplitude, grey(cam.image))
            if isinstance(r, str):
                self._problem(r)
            else:
                out.append(r)
        self._history.append((float(t_s), out))
        self._expire(float(t_s))
        return out

    def _problem(self, text: str) -> None:
        if not self._problems or self._problems[-1] != text:
            self._problems.append(text)

    def _expire(self, now_s: float) -> None:
        while self._history and self._history[0][0] < now_s - self.window_s:
            self._history.popleft()

    def reset(self) -> None:
        """Forget every measurement (e.g. after the rig was refined)."""
        self._history.clear()
        self._problems.clear()

    def report(self, now_s: float | None = None) -> DriftReport:
        """Every sensor's verdict over the window ending at ``now_s`` (default: the last
        measurement's time)."""
        if now_s is not None:
            self._expire(float(now_s))
        by_pair: dict[tuple[str, str], list[PairRotation]] = {}
        for _, rs in self._history:
            for r in rs:
                by_pair.setdefault((r.work, r.other), []).append(r)
        estimates = [
            e
            for ms in by_pair.values()
            if len(ms) >= MIN_MEASUREMENTS and (e := combine(ms)) is not None
        ]
        rot, cov = solve_sensors(estimates)
        comp = {n: len(g) for g in groups(estimates) for n in g}
        partners: dict[str, set[str]] = {}
        for p in estimates:
            partners.setdefault(p.work, set()).add(p.other)
            partners.setdefault(p.other, set()).add(p.work)
        problems = tuple(self._problems)
        sensors: dict[str, SensorCheck] = {}
        for name in self.rig.names:
            s = self.rig[name]
            if name not in rot:
                if not any(name in pair for pair in self.pairs + self.tof_pairs):
                    why = "not compared: no pair of this rig includes it"
                elif not self._history:
                    why = problems[-1] if problems else "nothing measured yet"
                else:
                    why = f"fewer than {MIN_MEASUREMENTS} measurements with structure yet"
                    if problems:
                        why += f" (last problem: {problems[-1]})"
                sensors[name] = SensorCheck("undecided", None, None, why)
                continue
            R = s.T_rig_sensor[:3, :3]
            v, reason = verdict(rot[name], cov[name], len(partners[name]), comp[name])
            local = R.T @ rot[name]
            local_cov = R.T @ cov[name] @ R
            sensors[name] = SensorCheck(
                v,
                tuple(float(x) for x in np.degrees(local)),
                tuple(float(x) for x in np.degrees(np.sqrt(np.diag(local_cov)))),
                reason,
                tuple(sorted(partners[name])),
            )
        return DriftReport(sensors, tuple(estimates), len(self._history), problems)


class RefineRefused(ValueError):
    """A correction too large to be a drift (:data:`REFUSE_DEG`): recalibrate."""


def refined_rig(rig: Rig, report: DriftReport, max_deg: float = REFUSE_DEG) -> Rig:
    """The rig with each ``drifted`` sensor turned by its estimated rotation
    (``T_rig_s @ R(rotation)``, the sensor's own frame), re-expressed so that the reference
    sensor still defines the rig frame. :class:`RefineRefused` when a correction exceeds
    ``max_deg`` degrees, ValueError when no sensor is drifted."""
    moved = {n: s for n, s in report.sensors.items() if s.verdict == "drifted"}
    if not moved:
        raise ValueError("refine: no sensor is drifted; the rig stays as it is")
    for n, s in moved.items():
        assert s.angle_deg is not None
        if s.angle_deg > max_deg:
            raise RefineRefused(
                f"refine: {n} would turn by {s.angle_deg:.2f}°, more than {max_deg:g}°: "
                "that is not a drift to correct but a moved sensor; recalibrate with the board"
            )
    poses = {n: rig[n].T_rig_sensor.copy() for n in rig.names}
    for n, s in moved.items():
        assert s.rotation_deg is not None
        poses[n] = poses[n] @ make_T(rotation_from_rvec(np.radians(s.rotation_deg)), np.zeros(3))
    base = invert(poses[rig.reference])
    out = rig
    for n in rig.names:
        T = base @ poses[n]
        if not np.array_equal(T, rig[n].T_rig_sensor):
            out = out.with_sensor(replace(rig[n], T_rig_sensor=T))
    return out
