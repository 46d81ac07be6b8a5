"""How far the TOF is turned against a colour camera, from its depth edges (issue 34).

The camera pairs of :mod:`fusion.drift_align` compare pictures through the TOF depth, which a
turned TOF hardly changes (it only moves the parallax correction). The TOF's own turn shows
where its depth jumps: at an object's outline the TOF's depth edge and the colour camera's
picture edge are the same 3D line. The TOF's pixels are coarse (0.35 degrees), but a pixel
on the outline mixes the two surfaces, and how much of each it holds says where in the pixel
the outline lies:

1. **Outline points** (:func:`depth_edges`): along every row and every column, a *mixed*
   pixel ``M`` between a flat foreground (nearer) pair of pixels and a flat background pair,
   the two sides differing by more than :data:`EDGE_REL`. A continuous-wave TOF pixel reads
   the amplitude-weighted mean of what it sees, ``d_M = (f a1 d1 + (1 - f) a2 d2) /
   (f a1 + (1 - f) a2)``, so the foreground's share of the pixel is ``f = a2 (d2 - d_M) /
   (a1 (d_M - d1) + a2 (d2 - d_M))`` and the outline crosses the scan line ``f`` of a pixel
   from ``M``'s foreground side (a share of a pixel's area is the crossing at its middle row).
   A jump with no pixel between (``f`` 0 or 1) lands on the pixels' common border. The point
   lies on the foreground at its distance (the near side's two pixels extrapolated).
2. **Where the camera sees the outline**: the point, through the rig, in the colour camera
   at full resolution; along the scan line's image there, the strongest change of brightness
   (the gradient along it, after a blur of :data:`BLUR_PX`) nearest to the prediction, among
   peaks at least :data:`PEAK_FRACTION` of the line's strongest, within :data:`SEARCH_PX`;
   sub-pixel by a parabola.
3. **The rotation**: ``r = J theta`` for the points' offsets ``r`` along their lines, ``J``
   how a rotation of the TOF's points about its centre moves them there; weighted by each
   offset's uncertainty (:data:`POSITION_SIGMA_PX`, plus the parallax a range error of
   :data:`RANGE_SIGMA_M` makes at the point's distance: near outlines count less), Huber
   then Tukey (an outline the colour picture hardly shows, a texture edge beside it). Three
   rounds, each predicting with the last estimate, so that a turn of a few tenths of a
   degree is followed rather than taken for a neighbouring edge.

``theta`` is ``delta_tof - R_tof_cam delta_cam`` (their own frames, :mod:`fusion.drift`'s
convention); in the rig frame, ``delta_tof^rig - delta_cam^rig``: a pair measurement like the
cameras' (:class:`fusion.drift_align.PairRotation`, work = the TOF).

Measured on the simulated inspection room (docs/FINDINGS.md): one instant reads a 0.3
degree turn of the TOF about any axis within about 0.02 degrees (x, y) and 0.07 (about its
optical axis); the true rig reads at most 0.04.

Pure: arrays in, arrays out; per-pixel work in numpy and OpenCV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.calib.rig import Rig
from trifuse.fusion.drift_align import PairRotation

EDGE_REL = 0.05
"""A depth jump: the background farther than the foreground by more than this fraction."""
FLAT_REL = 0.02
"""Each side of a jump is flat: its two pixels differ by less than this fraction (a slanted
floor's steep depth, or a side that is itself mixed, is not an outline)."""
MIN_DISTANCE_M = 0.2
"""Outline points nearer than this are left out."""
BLUR_PX = 1.0
"""The Gaussian blur of the colour picture before its gradient (full-resolution pixels)."""
SEARCH_PX = 20
"""How far along the line the colour outline is looked for (full-resolution pixels: 0.9
degrees at the simulated head's 1333 px)."""
PEAK_FRACTION = 0.3
"""A gradient peak counts when at least this fraction of the line's strongest (and 2 grey
levels a pixel)."""
POSITION_SIGMA_PX = 1.2
"""An outline point's offset, 1-sigma, colour pixels: the TOF's sub-pixel edge (about 0.1 of
its pixel, 0.9 colour pixels) and the colour edge's."""
RANGE_SIGMA_M = 0.05
"""The TOF range error whose parallax is added to a point's uncertainty (an uncorrected TOF
reads 4 cm long at 0.65 m: 7 colour pixels of parallax across the colour camera's 67 mm)."""
ROUNDS = 3
"""Predict, search, fit: this many times."""
MIN_POINTS = 30
"""Fewer outline points seen by the camera: no measurement."""


@dataclass(frozen=True)
class DepthEdges:
    """Outline points of a TOF frame (:func:`depth_edges`), N each.

    Attributes:
        x, y: (N,) float64 the point, TOF pixels (pixel centres at integers).
        distance_m: (N,) float64 the foreground's radial distance there, metres.
        axis: (N,) int 0 when found along a row (``x`` is sub-pixel), 1 along a column.
        side: (N,) float64 +1 when the foreground lies towards increasing ``x`` (axis 0) or
            ``y`` (axis 1), else -1.
    """

    x: np.ndarray
    y: np.ndarray
    distance_m: np.ndarray
    axis: np.ndarray
    side: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def depth_edges(distance_m: np.ndarray, amplitude: np.ndarray | None = None) -> DepthEdges:
    """The outline points of a TOF frame (module docstring, step 1).

    Args:
        distance_m: (H, W) radial distances, metres, NaN invalid.
        amplitude: (H, W) amplitudes (any unit); None, or not positive, weighs the two
            surfaces of a mixed pixel equally.
    """
    d = np.asarray(distance_m, dtype=np.float64)
    a = np.ones_like(d) if amplitude is None else np.asarray(amplitude, dtype=np.float64)
    if a.shape != d.shape:
        raise ValueError(f"amplitude: expected shape {d.shape}, got {a.shape}")
    parts = []
    for axis in (0, 1):
        D, A = (d, a) if axis == 0 else (d.T, a.T)
        n = D.shape[1] - 4
        L2, L, M, R, R2 = (D[:, i : i + n] for i in range(5))
        aL, aR = A[:, 1 : 1 + n], A[:, 3 : 3 + n]
        with np.errstate(invalid="ignore", divide="ignore"):
            fg_left = L < R
            d1, d2 = np.where(fg_left, L, R), np.where(fg_left, R, L)
            d1o = np.where(fg_left, L2, R2)  # the foreground's other pixel
            d2o = np.where(fg_left, R2, L2)
            a1, a2 = np.where(fg_left, aL, aR), np.where(fg_left, aR, aL)
            equal = ~((a1 > 0) & (a2 > 0))
            a1, a2 = np.where(equal, 1.0, a1), np.where(equal, 1.0, a2)
            f = a2 * (d2 - M) / (a1 * (M - d1) + a2 * (d2 - M))
            ok = (
                (d2 - d1 > EDGE_REL * d1)
                & (np.abs(d1o - d1) < FLAT_REL * d1)
                & (np.abs(d2o - d2) < FLAT_REL * d2)
                & (f >= 0.0)
                & (f < 1.0)
                & (d1 > MIN_DISTANCE_M)
            )
        rows, cols = np.nonzero(ok)
        fl = fg_left[rows, cols]
        ff = f[rows, cols]
        xm = cols + 2.0
        pos = np.where(fl, xm - 0.5 + ff, xm + 0.5 - ff)
        near = d1[rows, cols]
        slope = near - d1o[rows, cols]  # per pixel, away from the outline
        dist = near + slope * np.abs(pos - np.where(fl, xm - 1.0, xm + 1.0))
        side = np.where(fl, -1.0, 1.0)
        line = rows.astype(np.float64)
        xy = (pos, line) if axis == 0 else (line, pos)
        parts.append((*xy, dist, np.full(len(pos), axis), side))
    x, y, dist, ax, side = (np.concatenate(v) for v in zip(*parts, strict=True))
    return DepthEdges(x, y, dist, ax.astype(np.int64), side)


def gradient(grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gradient (gx, gy) (H, W) float32, grey levels a pixel, of a picture after a
    Gaussian blur of :data:`BLUR_PX`."""
    g = cv2.GaussianBlur(np.asarray(grey, np.float32), (0, 0), BLUR_PX)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return gx, gy


def _robust_fit(r: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int] | None:
    """``theta`` (3,), its covariance (3, 3), the normalised residual and the points used
    for normalised offsets r (n,) and Jacobian J (n, 3): ten Huber steps from 0 (convex: a
    minority of points that all moved, e.g. the horizontal outlines of a tilt, is not
    dropped), then eight Tukey steps. None when singular."""
    theta = np.zeros(3)
    w = np.ones(len(r))
    N = np.eye(3)
    for it in range(18):
        res = r - J @ theta
        s = max(1.0, 1.4826 * float(np.median(np.abs(res))))
        if it < 10:
            w = np.minimum(1.0, 1.345 * s / np.maximum(np.abs(res), 1e-12))
        else:
            u = res / (4.685 * s)
            w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        N = (J * w[:, None]).T @ J
        try:
            theta = np.linalg.solve(N, (J * w[:, None]).T @ r)
        except np.linalg.LinAlgError:
            return None
    res = r - J @ theta
    used = int((w > 0).sum())
    if used < MIN_POINTS:
        return None
    scale = float(np.sum(w * res * res) / max(1.0, w.sum() - 3.0))
    try:
        cov = np.linalg.inv(N) * max(1.0, scale)
    except np.linalg.LinAlgError:
        return None
    return theta, cov, math.sqrt(scale), used


class TofEdgeProbe:
    """Measures the TOF's rotation against one colour camera (module docstring).

    Made once per rig; :meth:`measure` per instant. Not thread-safe.
    """

    def __init__(self, rig: Rig, tof: str, camera: str) -> None:
        self.work, self.other = tof, camera
        self.tof, self.camera = rig[tof], rig[camera]
        self.range_correction = self.tof.range_correction
        T = rig.T(camera, tof)
        self.R_cam_tof, self.t_cam_tof = T[:3, :3], T[:3, 3]
        self.R_rig_tof = self.tof.T_rig_sensor[:3, :3].copy()
        self.baseline_m = float(np.linalg.norm(self.t_cam_tof))
        self.offsets = np.arange(-SEARCH_PX, SEARCH_PX + 1, dtype=np.float32)

    def _project(self, P: np.ndarray, R: np.ndarray) -> np.ndarray:
        """TOF-frame points (N, 3) turned by R (3, 3), in camera pixels (N, 2)."""
        return self.camera.intrinsics.project(P @ (self.R_cam_tof @ R).T + self.t_cam_tof)

    def _offsets(self, uv: np.ndarray, s: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
        """Where along each line (points uv (N, 2), unit directions s (N, 2)) the nearest
        strong gradient peak lies, pixels from uv; NaN where there is none."""
        ts = self.offsets
        su = (uv[:, None, 0] + ts[None] * s[:, None, 0]).astype(np.float32)
        sv = (uv[:, None, 1] + ts[None] * s[:, None, 1]).astype(np.float32)
        GX = cv2.remap(gx, su, sv, cv2.INTER_LINEAR, borderValue=np.nan)
        GY = cv2.remap(gy, su, sv, cv2.INTER_LINEAR, borderValue=np.nan)
        prof = np.abs(GX * s[:, None, 0] + GY * s[:, None, 1])
        inside = np.isfinite(prof).all(axis=1)
        prof = np.nan_to_num(prof)
        peak = np.zeros(prof.shape, bool)
        peak[:, 1:-1] = (prof[:, 1:-1] >= prof[:, :-2]) & (prof[:, 1:-1] > prof[:, 2:])
        peak &= prof >= np.maximum(2.0, PEAK_FRACTION * prof.max(axis=1, keepdims=True))
        far = np.where(peak, np.abs(ts)[None], np.inf)
        k = np.argmin(far, axis=1)
        found = inside & np.isfinite(far.min(axis=1))
        k = np.clip(k, 1, len(ts) - 2)
        i = np.arange(len(k))
        a, b, c = prof[i, k - 1], prof[i, k], prof[i, k + 1]
        den = a - 2.0 * b + c
        sub = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
        return np.where(found, ts[k] + sub, np.nan)

    def measure(
        self, distance_m: np.ndarray, amplitude: np.ndarray | None, grey: np.ndarray
    ) -> PairRotation | str:
        """One measurement from the TOF's distance and amplitude (H, W) and the colour
        camera's grey picture (h, w) at full resolution, of the same instant. Returns the
        rotation (rig frame, ``delta_tof - delta_camera``), or why there is none."""
        who = f"{self.work} against {self.other}"
        if grey.shape[:2] != (self.camera.height, self.camera.width):
            raise ValueError(
                f"{self.other}: expected a {self.camera.width}x{self.camera.height} picture, "
                f"got {grey.shape[1]}x{grey.shape[0]}"
            )
        d = np.asarray(distance_m, np.float32)
        if self.range_correction is not None:
            d = self.range_correction.apply(d, amplitude)
        e = depth_edges(d, amplitude)
        if len(e) < MIN_POINTS:
            return f"{who}: too few depth edges ({len(e)} outline points)"
        intr = self.tof.intrinsics
        P = intr.unproject(np.stack([e.x, e.y], axis=1)) * e.distance_m[:, None]
        half = 0.5 * np.stack([e.axis == 0, e.axis == 1], axis=1)
        P2 = intr.unproject(np.stack([e.x, e.y], axis=1) + half) * e.distance_m[:, None]
        sigma = np.hypot(
            POSITION_SIGMA_PX,
            self.camera.intrinsics.fx * self.baseline_m * RANGE_SIGMA_M / e.distance_m**2,
        )
        gx, gy = gradient(grey)
        theta = np.zeros(3)
        fit = None
        for _ in range(ROUNDS):
            R = cv2.Rodrigues(theta)[0]
            uv = self._project(P, R)
            s = self._project(P2, R) - uv
            s /= np.maximum(np.linalg.norm(s, axis=1, keepdims=True), 1e-12)
            r = self._offsets(uv, s, gx, gy)
            J = np.empty((len(P), 3))
            h = 1e-4
            for j in range(3):
                w = np.zeros(3)
                w[j] = h
                J[:, j] = ((self._project(P, cv2.Rodrigues(w)[0] @ R) - uv) / h * s).sum(axis=1)
            ok = np.isfinite(r) & np.isfinite(J).all(axis=1)
            if ok.sum() < MIN_POINTS:
                return f"{who}: the camera shows too few of the TOF's outlines"
            fit = _robust_fit(r[ok] / sigma[ok], J[ok] / sigma[ok, None])
            if fit is None:
                return f"{who}: the outlines seen do not fix a rotation"
            theta = theta + fit[0]
        assert fit is not None
        _, cov, scale, used = fit
        Rr = self.R_rig_tof
        return PairRotation(self.work, self.other, Rr @ theta, Rr @ cov @ Rr.T, used, scale)
