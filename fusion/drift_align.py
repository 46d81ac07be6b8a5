"""How far one sensor's picture is turned against another's, measured on ordinary scenes.

The building block of the drift check (:mod:`fusion.drift`). For a pair of sensors, the
*work* sensor (the coarser one) and the *other*, and a TOF frame:

1. every image is brought to a working resolution of about :data:`WORK_FX` pixels per
   radian (a colour camera's 1280 x 960 is averaged down by 4; thermal and TOF images are
   used as they are), with the rig's intrinsics scaled to match
   (:meth:`calib.camera.Intrinsics.scaled`);
2. the other sensor's image is resampled at the work sensor's pixels through the TOF depth
   (:class:`fusion.mapping.ViewMapping`, the fusion's own parallax-free mapping; blurred
   first when it is finer, so that it is not aliased), so that both pictures show the same
   3D point at the same pixel if the rig is right;
3. both are turned into edge strength (gradient magnitude after a Gaussian blur), which
   thermal and colour pictures share at object boundaries even where their intensities have
   nothing in common;
4. the picture is cut into square patches; in each, the shift ``t`` (work pixels) that makes
   the other's edges ``B(u + t)`` best match the work sensor's ``A(u)``, both normalised to
   zero mean and unit variance over the patch (Lucas-Kanade, coarse to fine over blurs of
   3, 1.5 and 1 pixels, from a global phase-correlation shift), with its information
   matrix (the structure tensor: a straight edge constrains the shift across it only);
5. the rotation ``theta`` (radians, the work sensor's frame) whose image motion
   ``J(u) theta`` best explains the patches' shifts, weighted by their information and
   made robust (Huber) against patches where the two modalities disagree.

A rotation moves a picture by nearly the same pixels at every depth (a camera turned by
0.3 degrees shows everything 2 thermal pixels over), so ``theta`` does not depend on the TOF
depth being exact; the depth only removes the parallax between the two sensors.

``theta`` measures ``delta_work - R_work_other delta_other``, where ``delta_s`` is the small
rotation (sensor ``s``'s own frame) by which the sensor really sits turned against the rig:
``T_rig_s(true) = T_rig_s @ [[R(delta_s), 0], [0, 1]]`` (``R`` Rodrigues). Brought to the rig
frame (``R_rig_work theta``) it is ``delta_work^rig - delta_other^rig``.

Pure: arrays in, arrays out. OpenCV does the per-pixel work; no per-pixel Python loops.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.calib.rig import Rig, Sensor
from trifuse.fusion.mapping import MappingOptions, TofGrid, ViewMapping

WORK_FX = 300.0
"""A camera finer than twice this focal length (pixels) is averaged down by powers of two
until it is not: the colour cameras' 1333 px by 4 (333 px), the thermal imagers' 400 px and
the TOF's 165 px as they are."""
LEVELS = (3.0, 1.5, 1.0)
"""The Gaussian blurs (work pixels) of the edge images, coarse to fine."""
ITERATIONS = 4
"""Lucas-Kanade steps per blur level."""
MIN_VALID = 0.7
"""A patch is used when this fraction of its pixels is seen by both sensors with TOF depth."""
MIN_ZNCC = 0.5
"""... and when its two edge images correlate at least this well after alignment."""
HUBER_K = 2.0
"""The Huber threshold of the rotation fit, in standard deviations of a patch's shift."""


def work_factor(sensor: Sensor) -> int:
    """The power of two the sensor's images are averaged down by (:data:`WORK_FX`)."""
    k = 1
    while sensor.intrinsics.fx / (2 * k) >= WORK_FX and sensor.width // (2 * k) >= 64:
        k *= 2
    return k


def work_sensor(sensor: Sensor) -> Sensor:
    """The sensor at its working resolution: image size divided by :func:`work_factor`,
    intrinsics scaled to match (pixel centres kept consistent)."""
    k = work_factor(sensor)
    if k == 1:
        return sensor
    return dataclasses.replace(
        sensor,
        image_size=(sensor.width // k, sensor.height // k),
        intrinsics=sensor.intrinsics.scaled(1.0 / k),
        uncertainty=None,
    )


def work_image(sensor: Sensor, image: np.ndarray) -> np.ndarray:
    """A sensor's image as (h, w) float32 at its working resolution: a colour image's
    luminance (0-255), a thermal image's kelvin, a TOF amplitude's logarithm. ValueError when
    the image does not have the sensor's size."""
    w, h = sensor.image_size
    if image.shape[:2] != (h, w):
        raise ValueError(
            f"{sensor.name}: expected a {w}x{h} image, got {image.shape[1]}x{image.shape[0]}"
        )
    if sensor.modality == "color":
        g = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32)
    elif sensor.modality == "tof":
        g = np.log(np.maximum(np.nan_to_num(image.astype(np.float32), nan=0.0), 1e-6))
    else:
        g = image.astype(np.float32, copy=True)
    k = work_factor(sensor)
    if k > 1:
        g = cv2.resize(g, (w // k, h // k), interpolation=cv2.INTER_AREA)
    return g


def edges(image: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Edge strength (h, w) float32: the gradient magnitude of ``image`` blurred by
    ``sigma`` pixels, the blur normalised over ``valid`` pixels (invalid ones neither count
    nor make edges at the border of the valid region)."""
    v = valid.astype(np.float32)
    filled = np.where(valid, image, 0.0).astype(np.float32)
    num = cv2.GaussianBlur(filled, (0, 0), sigma)
    den = cv2.GaussianBlur(v, (0, 0), sigma)
    g = num / np.maximum(den, 1e-3)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return cv2.magnitude(gx, gy)


def rotation_jacobian(sensor: Sensor, pixels: np.ndarray) -> np.ndarray:
    """(n, 2, 3) derivative of where pixels (n, 2) move, pixels per radian, when the points
    they see turn by a small rotation vector about the sensor's centre (its own frame):
    ``d pi(R(theta) X) / d theta`` at 0 (central differences; independent of depth)."""
    intr = sensor.intrinsics
    xy = intr.normalized(pixels)
    X = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    h = 1e-4
    J = np.empty((len(X), 2, 3))
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        Rp, _ = cv2.Rodrigues(w)
        Rm, _ = cv2.Rodrigues(-w)
        J[:, :, k] = (intr.project(X @ Rp.T) - intr.project(X @ Rm.T)) / (2 * h)
    return J


@dataclass(frozen=True)
class PatchShifts:
    """Per-patch alignment of a pair's edge images (work pixels).

    Attributes:
        centres: (n, 2) patch centres, work pixels.
        shifts: (n, 2) the shift ``t`` with ``B(u + t) ~ A(u)``.
        info: (n, 2, 2) the shift's information (inverse covariance), 1/px^2.
        zncc: (n,) correlation of the aligned edge images.
        index: (n,) each patch's place in the grid, row-major (``i * nx + j``).
    """

    centres: np.ndarray
    shifts: np.ndarray
    info: np.ndarray
    zncc: np.ndarray
    index: np.ndarray


def patch_centres(width: int, height: int, patch: int) -> np.ndarray:
    """(ny * nx, 2) centres (work pixels), row-major, of the grid of whole ``patch`` x
    ``patch`` patches centred in a ``width`` x ``height`` image."""
    ny, nx = height // patch, width // patch
    y0, x0 = (height - ny * patch) // 2, (width - nx * patch) // 2
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    c = np.stack([x0 + (jj + 0.5) * patch - 0.5, y0 + (ii + 0.5) * patch - 0.5], axis=-1)
    return c.reshape(-1, 2).astype(np.float64)


def _patch_sums(x: np.ndarray, ny: int, nx: int, p: int) -> np.ndarray:
    """(ny, nx) sums of the p x p patches of a (ny p, nx p) float32 image (an area
    resize: a patch's mean, times its pixels)."""
    return cv2.resize(x, (nx, ny), interpolation=cv2.INTER_AREA) * float(p * p)


def _per_pixel(x: np.ndarray, p: int) -> np.ndarray:
    """(ny, nx) patch values repeated over their p x p pixels, float32."""
    ny, nx = x.shape[:2]
    return cv2.resize(
        np.ascontiguousarray(x, dtype=np.float32), (nx * p, ny * p), interpolation=cv2.INTER_NEAREST
    )


def align_patches(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, patch: int
) -> PatchShifts | None:
    """Align ``b`` to ``a`` patch by patch (module docstring, step 4).

    Args:
        a: (h, w) float32 the work sensor's image (work resolution).
        b: (h, w) float32 the other sensor's image resampled at the work sensor's pixels.
        valid: (h, w) bool where both are meaningful.
        patch: the patches' side, pixels; the grid of whole patches is centred.

    Returns:
        the usable patches (:data:`MIN_VALID`, :data:`MIN_ZNCC`), or None when no patch fits.
    """
    h, w = a.shape
    ny, nx = h // patch, w // patch
    if ny == 0 or nx == 0:
        return None
    y0, x0 = (h - ny * patch) // 2, (w - nx * patch) // 2
    sl = (slice(y0, y0 + ny * patch), slice(x0, x0 + nx * patch))
    valid = np.ascontiguousarray(valid, dtype=bool)
    valid_f = valid.astype(np.float32)
    u, v = np.meshgrid(
        np.arange(x0, x0 + nx * patch, dtype=np.float32),
        np.arange(y0, y0 + ny * patch, dtype=np.float32),
    )
    t = np.zeros((ny, nx, 2), np.float32)
    # a global start: the phase correlation of the coarsest edge images
    ea = edges(a, valid, LEVELS[0])
    eb = edges(b, valid, LEVELS[0])
    win = cv2.createHanningWindow((w, h), cv2.CV_32F) * valid_f
    (gx, gy), response = cv2.phaseCorrelate(ea * valid_f, eb * valid_f, win)
    if response > 0.05 and max(abs(gx), abs(gy)) < patch / 2:
        t[...] = (gx, gy)
    n_pix = float(patch * patch)
    for level, sigma in enumerate(LEVELS):
        if level:
            ea = edges(a, valid, sigma)
            eb = edges(b, valid, sigma)
        # the blur spreads the border of the valid region into edges both images share:
        # only pixels farther from it than the blur reaches count
        r = int(np.ceil(2.0 * sigma)) + 1
        inner = cv2.erode(valid.view(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        inner_f = inner.astype(np.float32)
        A = ea[sl]
        for _ in range(ITERATIONS):
            mx = u + _per_pixel(t[..., 0], patch)
            my = v + _per_pixel(t[..., 1], patch)
            B = cv2.remap(eb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            m = (cv2.remap(inner_f, mx, my, cv2.INTER_LINEAR, borderValue=0.0) > 0.999) & (
                inner[sl] > 0
            )
            mf = m.astype(np.float32)
            cnt = np.maximum(_patch_sums(mf, ny, nx, patch), 1.0)
            ma = _patch_sums(A * mf, ny, nx, patch) / cnt
            mb = _patch_sums(B * mf, ny, nx, patch) / cnt
            Ac = (A - _per_pixel(ma, patch)) * mf
            Bc = (B - _per_pixel(mb, patch)) * mf
            sa = np.sqrt(_patch_sums(Ac * Ac, ny, nx, patch) / cnt) + 1e-9
            sb = np.sqrt(_patch_sums(Bc * Bc, ny, nx, patch) / cnt) + 1e-9
            An = Ac / _per_pixel(sa, patch)
            Bn = Bc / _per_pixel(sb, patch)
            gxb = cv2.Sobel(B, cv2.CV_32F, 1, 0, ksize=3, scale=0.125) * mf
            gyb = cv2.Sobel(B, cv2.CV_32F, 0, 1, ksize=3, scale=0.125) * mf
            inv = _per_pixel(np.where(sb > 1e-6, 1.0 / sb, 0.0).astype(np.float32), patch)
            gxb *= inv  # a patch without contrast gets no gradient (and no update)
            gyb *= inv
            e = An - Bn
            hxx = _patch_sums(gxb * gxb, ny, nx, patch)
            hxy = _patch_sums(gxb * gyb, ny, nx, patch)
            hyy = _patch_sums(gyb * gyb, ny, nx, patch)
            bx = _patch_sums(gxb * e, ny, nx, patch)
            by = _patch_sums(gyb * e, ny, nx, patch)
            lam = 1e-3 * (hxx + hyy) + 1e-6  # keeps a straight edge's solve finite
            det = (hxx + lam) * (hyy + lam) - hxy * hxy
            dx = ((hyy + lam) * bx - hxy * by) / det
            dy = ((hxx + lam) * by - hxy * bx) / det
            step = np.stack([dx, dy], axis=-1)
            limit = 2.0 * sigma
            norm = np.linalg.norm(step, axis=-1, keepdims=True)
            step *= np.minimum(1.0, limit / np.maximum(norm, 1e-12))
            t += step.astype(np.float32)
    # the last iteration's statistics describe the aligned patches
    zncc = _patch_sums(An * Bn, ny, nx, patch) / cnt
    resid = _patch_sums(e * e, ny, nx, patch) / cnt
    frac = cnt / n_pix
    use = (frac >= MIN_VALID) & (zncc >= MIN_ZNCC) & (np.abs(t).max(axis=-1) < patch / 2)
    if not use.any():
        return None
    info = np.stack([np.stack([hxx, hxy], -1), np.stack([hxy, hyy], -1)], -2)
    info = info / np.maximum(resid, 1e-6)[..., None, None]  # LK: cov(t) = s^2 H^-1
    flat = use.ravel()
    return PatchShifts(
        centres=patch_centres(w, h, patch)[flat],
        shifts=t.reshape(-1, 2)[flat].astype(np.float64),
        info=info.reshape(-1, 2, 2)[flat].astype(np.float64),
        zncc=zncc.ravel()[flat].astype(np.float64),
        index=np.flatnonzero(flat),
    )


@dataclass(frozen=True)
class PairRotation:
    """One measurement of a pair: ``theta`` (3,) radians and its covariance (3, 3) rad^2,
    in the rig frame (``delta_work^rig - delta_other^rig``, module docstring); ``patches``
    used (the TOF's outline points, :mod:`fusion.drift_tof`), ``scale``: the fit's
    normalised residual (about 1 when the patches' own uncertainties explain their scatter;
    the covariance includes it when above 1)."""

    work: str
    other: str
    theta: np.ndarray
    cov: np.ndarray
    patches: int
    scale: float


def fit_rotation(
    shifts: PatchShifts, jacobian: np.ndarray, iterations: int = 6
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The rotation (3,) radians, work sensor's frame, and its covariance (3, 3) that best
    explain the patches' shifts: ``t ~ J theta``, weighted by their information, Huber
    weights at :data:`HUBER_K`; the covariance scaled up by the normalised residual when it
    exceeds 1. ``jacobian``: (n, 2, 3) pixels per radian at the patch centres. None with
    fewer than 3 patches or a singular fit."""
    n = len(shifts.shifts)
    if n < 3:
        return None
    J, t, W = jacobian, shifts.shifts, shifts.info
    w = np.ones(n)
    for _ in range(iterations):
        WJ = W @ J  # (n, 2, 3)
        N = np.einsum("n,nik,nil->kl", w, J, WJ)
        rhs = np.einsum("n,nik,ni->k", w, WJ, t)
        try:
            theta = np.linalg.solve(N, rhs)
        except np.linalg.LinAlgError:
            return None
        r = t - J @ theta
        m = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", r, W, r), 0.0))
        w = np.minimum(1.0, HUBER_K / np.maximum(m, 1e-12))
    dof = max(1, 2 * n - 3)
    scale = float(np.sum(w * m * m) / dof)
    try:
        cov = np.linalg.inv(N) * max(1.0, scale)
    except np.linalg.LinAlgError:
        return None
    return theta, cov, float(np.sqrt(scale))


class PairProbe:
    """Measures one pair's relative rotation on frame sets (module docstring).

    Made once per rig (the mapping's rays, the patches' Jacobians); :meth:`measure` per TOF
    frame. Not thread-safe: one thread uses a probe.
    """

    def __init__(self, rig: Rig, work: str, other: str, grid: TofGrid) -> None:
        self.work, self.other, self.tof = work, other, grid.tof
        sw, so = work_sensor(rig[work]), work_sensor(rig[other])
        wr = rig
        for s in (sw, so):
            if s is not rig[s.name]:
                wr = wr.with_sensor(s)
        self.sensor = sw
        scale = max(1, round(sw.intrinsics.fx / rig[self.tof].intrinsics.fx))
        # the middle of the depths on smooth surfaces: the nearest is biased on slanted ones
        # (a turn of 0.1 degrees read between two cameras 120 mm apart: docs/FINDINGS.md)
        options = MappingOptions(scale=scale, smooth_middle=True)
        self.mapping = ViewMapping(wr, work, other, options=options, grid=grid)
        self.blur = 0.5 * so.intrinsics.fx / sw.intrinsics.fx
        self.patch = 16 if sw.modality == "tof" else 32
        self.R_rig_work = rig[work].T_rig_sensor[:3, :3].copy()
        self.jacobian = rotation_jacobian(sw, patch_centres(*sw.image_size, self.patch))

    def measure(
        self, work_image_: np.ndarray, other_image: np.ndarray, points_tof: np.ndarray
    ) -> PairRotation | str:
        """One measurement from the pair's work-resolution images (:func:`work_image`) and
        the TOF points (N, 3) TOF frame, metres, of the same instant. Returns the rotation,
        or why there is none (a sentence)."""
        m = self.mapping
        m.update_points(points_tof)
        b_src = other_image
        if self.blur > 0.6:
            b_src = cv2.GaussianBlur(b_src, (0, 0), self.blur)
        b = m.warp(b_src)
        valid = np.isfinite(b) & ~m.fallback & np.isfinite(work_image_)
        shifts = align_patches(work_image_, np.nan_to_num(b), valid, self.patch)
        if shifts is None:
            return f"{self.work} against {self.other}: no patch with structure seen by both"
        fit = fit_rotation(shifts, self.jacobian[shifts.index])
        if fit is None:
            return f"{self.work} against {self.other}: too few patches with structure"
        theta, cov, scale = fit
        R = self.R_rig_work
        return PairRotation(
            self.work, self.other, R @ theta, R @ cov @ R.T, len(shifts.shifts), scale
        )
