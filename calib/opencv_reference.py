"""Plain OpenCV reference figures for real captures: detection, single-camera and stereo.

What a careful user would compute with OpenCV alone, so that trifuse's results on real data
sets (app/devtools/real_sets.py, tests/data) have a baseline measured in the same run. It
complements :mod:`calib.opencv_baseline` (full checkerboards, multiview poses) with what
that module does not cover: boards whose corner order is ambiguous (even x even or odd x
odd inner corners), partial views (ChArUco), downscaled detection of large images, and a
pairwise ``cv2.stereoCalibrate``.

Corners are returned in the order OpenCV's detector gives them; nothing here reorders
them. For one sensor the order does not matter; for a pair of sensors on a symmetric
board the detector's orders may disagree by a half turn, and :func:`stereo_calibrate_opencv`
uses them as they come, as a plain script would (its RMS then shows it).

Pure: arrays in, dataclasses out; no file I/O, no printing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import CalibrationError
from trifuse.calib.transforms import make_T, rotation_angle_deg

FLATTEN_SIGMA_PX = 25.0
"""Sigma of the Gaussian blur subtracted from thermal images before detection, pixels
(as FIELD-NOTES and :mod:`calib.detect_baseline`)."""
STRETCH_PERCENTILES = (1.0, 99.5)
"""Percentiles of the flattened thermal image mapped to 0 and 255."""
SUBPIX_HALF_WINDOW_PX = 11
"""Half-width of cornerSubPix's window when corners found on a downscaled copy are refined
at full resolution: OpenCV's tutorial value, (11, 11). Measured on the 12 MP views of
czha626-thermal-visible (corner spacing about 180 px): RMS 1.48 px; a window of 0.4 x the
spacing (71 px) reached beyond the board and gave 6.3 px; no refinement 1.85 px."""
SUBPIX_WINDOW_FRACTION = 0.4
"""Cap of that half-width as a fraction of the corner spacing (FIELD-NOTES: a window wider
than half the spacing converges to a neighbouring corner)."""
_DIST_FLAGS = {4: cv2.CALIB_FIX_K3, 5: 0, 8: cv2.CALIB_RATIONAL_MODEL}
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


@dataclass(frozen=True)
class CharucoTarget:
    """A ChArUco board as OpenCV's ``cv2.aruco.CharucoBoard`` describes it.

    Attributes:
        squares: (across, down) number of squares; inner corners are one fewer each.
        square_m: side of a square, metres.
        marker_m: side of a marker, metres.
        dictionary: OpenCV's predefined dictionary name, e.g. ``"DICT_4X4_1000"``.
        inverted: markers white on black (detected on the inverted image).
    """

    squares: tuple[int, int]
    square_m: float
    marker_m: float
    dictionary: str
    inverted: bool = False

    def __post_init__(self) -> None:
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(
                f"dictionary: expected an OpenCV predefined dictionary such as "
                f"'DICT_4X4_1000', got {self.dictionary!r}"
            )
        if not 0.0 < self.marker_m < self.square_m:
            raise ValueError(
                f"marker_m: expected 0 < marker < square ({self.square_m} m), got {self.marker_m!r}"
            )

    def opencv_board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square_m, self.marker_m, d)

    def corner_points(self) -> np.ndarray:
        """Inner corners (N, 3) in the board frame, metres, indexed by OpenCV's corner id."""
        return np.asarray(self.opencv_board().getChessboardCorners(), dtype=np.float64)


@dataclass(frozen=True)
class CameraReference:
    """``cv2.calibrateCamera`` on one sensor's views.

    Attributes:
        intrinsics: focal lengths, principal point (pixels) and distortion (OpenCV order).
        rms_px: OpenCV's RMS reprojection error, pixels (per corner, 2-D).
        n_views: views used.
        per_view_rms_px: (n_views,) RMS per view, pixels.
    """

    intrinsics: Intrinsics
    rms_px: float
    n_views: int
    per_view_rms_px: tuple[float, ...]


@dataclass(frozen=True)
class StereoReference:
    """``cv2.stereoCalibrate`` of a pair with both sensors' intrinsics held fixed.

    Attributes:
        T_b_a: (4, 4) pose mapping points from sensor a's frame into sensor b's, metres
            (OpenCV's R, T). Frozen dataclass holding an array: compare its fields.
        rms_px: OpenCV's RMS over both sensors' corners, pixels.
        n_views: views both sensors saw (with at least ``min_common`` shared corners).
    """

    T_b_a: np.ndarray
    rms_px: float
    n_views: int

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres, metres."""
        return float(np.linalg.norm(self.T_b_a[:3, 3]))

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation between the two sensors, degrees."""
        return rotation_angle_deg(self.T_b_a[:3, :3])


def _grey(image: np.ndarray) -> np.ndarray:
    """(H, W) grey: uint8 as given (colour converted), other dtypes as float32, NaN filled."""
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
        raise ValueError(
            f"image: expected an (H, W) or (H, W, 3) array, got "
            f"{getattr(image, 'shape', type(image).__name__)}"
        )
    if image.ndim == 3:
        if image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"image: expected (H, W, 3) uint8 RGB, got {image.shape} {image.dtype}"
            )
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if image.dtype == np.uint8:
        return image
    if image.dtype.kind not in "fiu":
        raise ValueError(f"image: expected a real dtype, got {image.dtype}")
    x = image.astype(np.float32)
    bad = ~np.isfinite(x)
    if bad.all():
        raise ValueError("image: expected finite pixels, got none")
    x[bad] = np.median(x[~bad])
    return x


def _stretch_u8(x: np.ndarray) -> np.ndarray:
    """Percentile stretch (:data:`STRETCH_PERCENTILES`) of a float image to uint8."""
    lo, hi = np.percentile(x, STRETCH_PERCENTILES)
    return np.clip((x - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)


def _u8(grey: np.ndarray) -> np.ndarray:
    return grey if grey.dtype == np.uint8 else _stretch_u8(grey)


def _spacing_px(corners: np.ndarray, pattern: tuple[int, int]) -> float:
    G = corners.reshape(pattern[1], pattern[0], 2)
    d = np.concatenate(
        [
            np.linalg.norm(np.diff(G, axis=1), axis=2).ravel(),
            np.linalg.norm(np.diff(G, axis=0), axis=2).ravel(),
        ]
    )
    return float(np.median(d))


def find_chessboard_opencv(
    image: np.ndarray,
    pattern: tuple[int, int],
    *,
    thermal: bool = False,
    max_side_px: int | None = None,
) -> tuple[np.ndarray | None, str | None]:
    """Find a checkerboard as a plain OpenCV script would; any inner-corner counts.

    Tries, in order, the variants of the image (as is; for ``thermal`` also inverted, then
    flattened by subtracting a wide blur, as is and inverted), each with the classic
    detector (``findChessboardCorners``, default flags) then the sector-based one
    (``findChessboardCornersSB``). With ``max_side_px`` a larger image is detected on a
    copy downscaled to that longest side, and the corners are refined at full resolution
    with ``cornerSubPix`` (:data:`SUBPIX_HALF_WINDOW_PX`, capped by the corner spacing).

    Args:
        image: (H, W, 3) uint8 RGB, (H, W) uint8 grey, or (H, W) thermal of any real dtype.
        pattern: (cols, rows) inner corners, as OpenCV takes it.
        thermal: also try the inverted and flattened variants.
        max_side_px: longest side to detect at, or None for full resolution.

    Returns:
        ((cols * rows, 2) float64 pixels in OpenCV's order, variant name) or (None, None).
    """
    cols, rows = pattern
    if min(cols, rows) < 2:
        raise ValueError(f"pattern: expected (cols, rows) >= 2 inner corners, got {pattern!r}")
    grey = _grey(image)
    scale = 1.0
    small = grey
    if max_side_px is not None and max(grey.shape) > max_side_px:
        scale = max_side_px / max(grey.shape)
        size = (round(grey.shape[1] * scale), round(grey.shape[0] * scale))
        small = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    base = _u8(small)
    variants = [("as-is", base)]
    if thermal:
        x = small.astype(np.float32)
        # Flatten the float data before any 8-bit stretch: on 16-bit LWIR the board's
        # contrast is a few counts beside a hot spot of thousands.
        flat = _stretch_u8(
            x - cv2.GaussianBlur(x, (0, 0), FLATTEN_SIGMA_PX, borderType=cv2.BORDER_REFLECT)
        )
        variants += [("inverted", 255 - base), ("flattened", flat), ("flattened-inv", 255 - flat)]
    for name, img in variants:
        for detector in ("classic", "sb"):
            if detector == "classic":
                ok, raw = cv2.findChessboardCorners(img, pattern)
            else:
                ok, raw = cv2.findChessboardCornersSB(img, pattern)
            if ok and raw is not None:
                corners = np.asarray(raw, dtype=np.float64).reshape(-1, 2)
                if scale != 1.0:
                    corners = (corners + 0.5) / scale - 0.5
                    cap = round(SUBPIX_WINDOW_FRACTION * _spacing_px(corners, pattern))
                    half = max(2, min(SUBPIX_HALF_WINDOW_PX, cap))
                    refined = cv2.cornerSubPix(
                        grey,  # uint8, or float32 (see _grey)
                        corners.astype(np.float32).reshape(-1, 1, 2),
                        (half, half),
                        (-1, -1),
                        _SUBPIX_CRITERIA,
                    )
                    corners = refined.reshape(-1, 2).astype(np.float64)
                return corners, f"{detector}-{name}"
    return None, None


def find_charuco_opencv(
    image: np.ndarray, target: CharucoTarget, *, min_corners: int = 6
) -> tuple[np.ndarray, np.ndarray] | None:
    """Find a (possibly partial) ChArUco board with ``cv2.aruco.CharucoDetector``.

    Args:
        image: (H, W, 3) uint8 RGB or (H, W) uint8 grey.
        target: the board.
        min_corners: fewer interpolated corners than this count as not found.

    Returns:
        (ids (M,) int, corners (M, 2) float64 pixels) or None.
    """
    grey = _u8(_grey(image))
    if target.inverted:
        # Measured on caliscope's inverted board (tests/data/caliscope-charuco-4cam):
        # inverting the image finds as many boards or more than detectInvertedMarker
        # (one camera: 40 of 57 views against 15).
        grey = 255 - grey
    detector = cv2.aruco.CharucoDetector(
        target.opencv_board(), cv2.aruco.CharucoParameters(), cv2.aruco.DetectorParameters()
    )
    corners, ids, _marker_corners, _marker_ids = detector.detectBoard(grey)
    if ids is None or len(ids) < min_corners:
        return None
    return np.asarray(ids, dtype=np.int64).ravel(), np.asarray(corners, np.float64).reshape(-1, 2)


def calibrate_camera_opencv(
    object_points: Sequence[np.ndarray],
    image_points: Sequence[np.ndarray],
    image_size: tuple[int, int],
    dist_coeffs: int = 5,
) -> CameraReference:
    """``cv2.calibrateCamera`` with OpenCV's default flags (plus the distortion model).

    Args:
        object_points: per view, (N_i, 3) board points, metres.
        image_points: per view, (N_i, 2) pixels, same order.
        image_size: (width, height) pixels.
        dist_coeffs: 4 (k1 k2 p1 p2), 5 (+ k3) or 8 (rational model).

    Raises:
        ValueError: mismatched shapes or an unknown ``dist_coeffs``.
        CalibrationError: fewer than 3 views, or OpenCV failed.
    """
    if dist_coeffs not in _DIST_FLAGS:
        raise ValueError(f"dist_coeffs: expected one of {sorted(_DIST_FLAGS)}, got {dist_coeffs!r}")
    if len(object_points) != len(image_points):
        raise ValueError(
            f"object_points and image_points: expected as many views, got "
            f"{len(object_points)} and {len(image_points)}"
        )
    if len(object_points) < 3:
        raise CalibrationError(f"calibrateCamera needs at least 3 views, got {len(object_points)}")
    objs = [np.asarray(o, np.float32).reshape(-1, 3) for o in object_points]
    imgs = [np.asarray(i, np.float32).reshape(-1, 2) for i in image_points]
    for k, (o, i) in enumerate(zip(objs, imgs, strict=True)):
        if len(o) != len(i) or len(o) < 4:
            raise ValueError(
                f"view {k}: expected as many (>= 4) object as image points, got {len(o)} and "
                f"{len(i)}"
            )
    try:
        rms, K, dist, _rv, _tv, _si, _se, per_view = cv2.calibrateCameraExtended(
            objs, imgs, tuple(int(v) for v in image_size), None, None,
            flags=_DIST_FLAGS[dist_coeffs],
        )  # fmt: skip
    except cv2.error as exc:
        raise CalibrationError(f"cv2.calibrateCamera failed: {exc}") from None
    d = np.asarray(dist, np.float64).ravel()[:dist_coeffs]
    return CameraReference(
        Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                   tuple(float(v) for v in d)),
        float(rms),
        len(objs),
        tuple(float(v) for v in np.asarray(per_view).ravel()),
    )  # fmt: skip


def stereo_calibrate_opencv(
    object_points: Sequence[np.ndarray],
    points_a: Sequence[np.ndarray],
    points_b: Sequence[np.ndarray],
    intrinsics_a: Intrinsics,
    intrinsics_b: Intrinsics,
    image_size_a: tuple[int, int],
) -> StereoReference:
    """``cv2.stereoCalibrate`` with ``CALIB_FIX_INTRINSIC``: the pose of b relative to a.

    Args:
        object_points: per shared view, (N_i, 3) board points, metres.
        points_a, points_b: per shared view, (N_i, 2) pixels in sensors a and b, the same
            board points in the same order.
        intrinsics_a, intrinsics_b: held fixed.
        image_size_a: (width, height) of sensor a (OpenCV's ``imageSize``; unused when the
            intrinsics are fixed, but required).

    Raises:
        ValueError: mismatched view counts or shapes.
        CalibrationError: fewer than 1 shared view, or OpenCV failed.
    """
    n = len(object_points)
    if not n == len(points_a) == len(points_b):
        raise ValueError(
            f"object_points, points_a, points_b: expected as many views, got "
            f"{n}, {len(points_a)}, {len(points_b)}"
        )
    if n < 1:
        raise CalibrationError("stereoCalibrate needs at least one view both sensors saw")
    objs = [np.asarray(o, np.float32).reshape(-1, 3) for o in object_points]
    pa = [np.asarray(p, np.float32).reshape(-1, 2) for p in points_a]
    pb = [np.asarray(p, np.float32).reshape(-1, 2) for p in points_b]
    dist_a = np.asarray(intrinsics_a.distortion, np.float64)
    dist_b = np.asarray(intrinsics_b.distortion, np.float64)
    try:
        out = cv2.stereoCalibrate(
            objs, pa, pb, intrinsics_a.K, dist_a, intrinsics_b.K, dist_b,
            tuple(int(v) for v in image_size_a), flags=cv2.CALIB_FIX_INTRINSIC,
        )  # fmt: skip
    except cv2.error as exc:
        raise CalibrationError(f"cv2.stereoCalibrate failed: {exc}") from None
    rms, R, T = out[0], out[5], out[6]
    return StereoReference(make_T(np.asarray(R), np.asarray(T).ravel()), float(rms), n)
