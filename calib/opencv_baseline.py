"""The OpenCV 5 multiview calibration that trifuse's own rig calibration is benchmarked against.

Two stages, as FIELD-NOTES advise (OpenCV's joint solve of low-resolution intrinsics is poor):

1. Intrinsics per sensor with ``cv2.calibrateCamera`` from every view that sensor saw
   (``dist_coeffs`` = 4, 5 or 8 distortion coefficients, OpenCV's order).
2. Sensor poses with ``cv2.calibrateMultiviewExtended`` with those intrinsics held fixed.

OpenCV 5.0.0 facts this module relies on (verified numerically with synthetic rigs, see
tests/calib/test_opencv_baseline.py):

* Python signature::

      calibrateMultiviewExtended(objPoints, imagePoints, imageSize, detectionMask, models,
          Ks, distortions, Rs, Ts[, initializationPairs[, rvecs0[, tvecs0[, perFrameErrors
          [, flagsForIntrinsics[, flags[, criteria]]]]]]])
        -> retval, Ks, distortions, Rs, Ts, initializationPairs, rvecs0, tvecs0, perFrameErrors

  and ``calibrateMultiview(objPoints, imagePoints, imageSize, detectionMask, models, Ks,
  distortions, Rs, Ts[, flagsForIntrinsics[, flags[, criteria]]]) -> retval, Ks,
  distortions, Rs, Ts`` (the same without the four extra outputs). ``objPoints`` is
  frames x points x 3 float32, ``imagePoints`` cameras x frames x points x 2 and must be
  **float32** (float64 fails an assertion), missing views are (-1, -1) with a 0 in the
  uint8 cameras x frames ``detectionMask``; ``models`` is a uint8 array of
  ``cv2.CALIB_MODEL_PINHOLE``.
* ``flags=cv2.CALIB_USE_INTRINSIC_GUESS`` keeps the given ``Ks`` and ``distortions``
  unchanged (they are returned bit-identical); without it OpenCV re-estimates them.
* ``(Rs[i], Ts[i])`` (rotation vector, translation in the object points' unit) map points
  **from camera 0's frame into camera i's frame**: they are ``T_cami_cam0``. Camera 0 is
  the identity. ``rvecs0[f], tvecs0[f]`` are the board pose ``T_cam0_board`` of frame f.

So with the rig's reference sensor as camera 0, ``T_rig_sensor = inv(T_cami_cam0)``.

Image points are passed to OpenCV as float32: about 4e-5 px of rounding at 1280 px, far
below any detector's noise.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from trifuse.calib.board import Board
from trifuse.calib.camera import Intrinsics
from trifuse.calib.errors import CalibrationError
from trifuse.calib.numbers import is_integer
from trifuse.calib.transforms import invert, make_T, rotation_from_rvec, transform_points

MIN_VIEWS = 3
_DIST_FLAGS = {
    4: cv2.CALIB_FIX_K3,
    5: 0,
    8: cv2.CALIB_RATIONAL_MODEL,
}


@dataclass
class BaselineResult:
    """What the OpenCV baseline estimated.

    Attributes:
        intrinsics: per sensor, from ``cv2.calibrateCamera`` (stage 1).
        T_rig_sensor: per sensor, (4, 4) pose in the rig frame (= the reference sensor's
            frame; the reference is exactly the identity), metres.
        rms_px: RMS reprojection error over all corners of all observations, with the final
            intrinsics, sensor poses and OpenCV's board poses: ``sqrt(mean(du^2 + dv^2))``
            (OpenCV's definition, a per-corner 2-D error; about ``sqrt(2) * sigma`` for
            Gaussian noise of ``sigma`` px per axis).
        seconds: wall-clock time of the whole baseline (both stages).
        rms_px_by_sensor: the same RMS per sensor.
    """

    intrinsics: dict[str, Intrinsics]
    T_rig_sensor: dict[str, np.ndarray]
    rms_px: float
    seconds: float
    rms_px_by_sensor: dict[str, float] = field(default_factory=dict)


def _check_inputs(
    observations: Mapping[str, Mapping[str, np.ndarray]],
    board: Board,
    image_sizes: Mapping[str, tuple[int, int]],
    reference: str,
    dist_coeffs: int,
) -> tuple[list[str], list[str], dict[str, dict[str, np.ndarray]]]:
    """Validate; return (sensor names with the reference first, view names, clean copy)."""
    if dist_coeffs not in _DIST_FLAGS:
        raise ValueError(f"dist_coeffs: expected one of {sorted(_DIST_FLAGS)}, got {dist_coeffs!r}")
    if not isinstance(observations, Mapping):
        raise ValueError(
            f"observations: expected a mapping view -> sensor -> (N, 2) corners, "
            f"got {type(observations).__name__}"
        )
    for name, size in image_sizes.items():
        ok = (
            isinstance(size, tuple | list)
            and len(size) == 2
            and all(is_integer(v) for v in size)
            and min(size) > 0
        )
        if not ok:
            raise ValueError(
                f"image_sizes[{name!r}]: expected (width, height) positive integers, got {size!r}"
            )
    n = board.n_corners
    clean: dict[str, dict[str, np.ndarray]] = {}
    for view, per_sensor in observations.items():
        if not isinstance(per_sensor, Mapping):
            raise ValueError(
                f"observations[{view!r}]: expected a mapping sensor -> corners, "
                f"got {type(per_sensor).__name__}"
            )
        clean[view] = {}
        for sensor, corners in per_sensor.items():
            where = f"observations[{view!r}][{sensor!r}]"
            if sensor not in image_sizes:
                raise ValueError(
                    f"{where}: no image size for sensor {sensor!r} "
                    f"(image_sizes has {sorted(image_sizes)})"
                )
            c = np.asarray(corners, dtype=np.float64)
            if c.shape != (n, 2):
                raise ValueError(
                    f"{where}: expected shape ({n}, 2) (all corners of the {board.cols}x"
                    f"{board.rows} board, canonical order), got {c.shape}"
                )
            if not np.all(np.isfinite(c)):
                raise ValueError(f"{where}: contains NaN or infinity")
            clean[view][sensor] = c
        if not clean[view]:
            del clean[view]  # nobody saw the board: nothing to give OpenCV
    sensors = list(image_sizes)
    if reference not in image_sizes:
        raise ValueError(
            f"reference: sensor {reference!r} has no image size "
            f"(image_sizes has {sorted(image_sizes)})"
        )
    counts = {s: sum(s in obs for obs in clean.values()) for s in sensors}
    few = {s: k for s, k in counts.items() if k < MIN_VIEWS}
    if few:
        listed = ", ".join(f"{s!r} in {k}" for s, k in few.items())
        raise CalibrationError(
            f"every sensor needs the board in at least {MIN_VIEWS} views; seen: {listed}"
        )
    # Every sensor must be linked to the reference through views seen by two sensors.
    linked = {reference}
    frontier = [reference]
    while frontier:
        s = frontier.pop()
        for obs in clean.values():
            if s in obs:
                for other in obs:
                    if other not in linked:
                        linked.add(other)
                        frontier.append(other)
    isolated = [s for s in sensors if s not in linked]
    if isolated:
        raise CalibrationError(
            f"sensor(s) {isolated} never see the board together with the others "
            f"(no chain of shared views to the reference {reference!r}); linked: "
            f"{sorted(linked)}"
        )
    order = [reference] + [s for s in sensors if s != reference]
    return order, list(clean), clean


def _calibrate_intrinsics(
    corner_sets: list[np.ndarray],
    obj: np.ndarray,
    image_size: tuple[int, int],
    dist_coeffs: int,
    sensor: str,
) -> Intrinsics:
    obj32 = obj.astype(np.float32)
    try:
        _rms, K, dist, _rvecs, _tvecs = cv2.calibrateCamera(
            [obj32] * len(corner_sets),
            [c.astype(np.float32) for c in corner_sets],
            tuple(int(v) for v in image_size),
            None,
            None,
            flags=_DIST_FLAGS[dist_coeffs],
        )
    except cv2.error as exc:
        raise CalibrationError(f"sensor {sensor!r}: cv2.calibrateCamera failed: {exc}") from None
    d = np.asarray(dist, dtype=np.float64).ravel()
    return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(d[:dist_coeffs].tolist()))


def calibrate_multiview_opencv(
    observations: Mapping[str, Mapping[str, np.ndarray]],
    board: Board,
    image_sizes: Mapping[str, tuple[int, int]],
    reference: str,
    dist_coeffs: int = 5,
) -> BaselineResult:
    """Calibrate every sensor's intrinsics and pose with OpenCV 5 (the benchmark baseline).

    Args:
        observations: view name -> sensor name -> (N, 2) float64 corners in canonical board
            order (all ``board.n_corners``); a sensor that did not see the board in a view
            is absent from that view's dict.
        board: the checkerboard.
        image_sizes: sensor name -> (width, height) in pixels. Every sensor listed is
            calibrated, and every sensor observed must be listed.
        reference: the sensor whose frame is the rig frame (OpenCV's camera 0).
        dist_coeffs: distortion coefficients to estimate: 4 (k1 k2 p1 p2), 5 (+ k3) or
            8 (rational model).

    Returns:
        A ``BaselineResult``.

    Raises:
        ValueError: malformed input (shapes, NaN, unknown sensors, missing image sizes).
        CalibrationError: a sensor seen in fewer than 3 views, a sensor never linked to the
            reference through views shared with other sensors, or an OpenCV failure.
    """
    start = time.perf_counter()
    order, views, obs = _check_inputs(observations, board, image_sizes, reference, dist_coeffs)
    obj = board.object_points()

    intrinsics = {
        s: _calibrate_intrinsics(
            [o[s] for o in obs.values() if s in o], obj, image_sizes[s], dist_coeffs, s
        )
        for s in order
    }

    n_cam, n_frames, n_pts = len(order), len(views), board.n_corners
    image_points = np.full((n_cam, n_frames, n_pts, 2), -1.0, dtype=np.float32)
    mask = np.zeros((n_cam, n_frames), dtype=np.uint8)
    for f, view in enumerate(views):
        for c, s in enumerate(order):
            if s in obs[view]:
                image_points[c, f] = obs[view][s]
                mask[c, f] = 1
    object_points = np.repeat(obj.astype(np.float32)[None], n_frames, axis=0)
    Ks = [intrinsics[s].K for s in order]
    dists = [np.asarray(intrinsics[s].distortion, dtype=np.float64).reshape(1, -1) for s in order]
    sizes = [tuple(int(v) for v in image_sizes[s]) for s in order]
    models = np.full((n_cam,), cv2.CALIB_MODEL_PINHOLE, dtype=np.uint8)
    flags_intrinsics = np.full(
        (n_cam, 1), cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_INTRINSIC, dtype=np.int32
    )
    try:
        out = cv2.calibrateMultiviewExtended(
            object_points,
            image_points,
            sizes,
            mask,
            models,
            Ks,
            dists,
            None,
            None,
            flagsForIntrinsics=flags_intrinsics,
            flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        )
    except cv2.error as exc:
        raise CalibrationError(f"cv2.calibrateMultiviewExtended failed: {exc}") from None
    _rms, Ks_out, dists_out, Rs, Ts, _pairs, rvecs0, tvecs0, _per_frame = out
    for c, s in enumerate(order):
        # Pinned for OpenCV 5.0.0: CALIB_USE_INTRINSIC_GUESS leaves the intrinsics as given.
        same = np.array_equal(np.asarray(Ks_out[c]), Ks[c]) and np.array_equal(
            np.asarray(dists_out[c]).ravel(), dists[c].ravel()
        )
        if not same:
            raise CalibrationError(
                f"sensor {s!r}: cv2.calibrateMultiviewExtended changed the fixed intrinsics "
                f"(OpenCV {cv2.__version__}); this baseline needs them held fixed"
            )

    T_rig_sensor: dict[str, np.ndarray] = {}
    T_cam_ref: dict[str, np.ndarray] = {}
    for c, s in enumerate(order):
        if c == 0:
            T = np.eye(4)
        else:
            T = make_T(rotation_from_rvec(np.asarray(Rs[c]).ravel()), np.asarray(Ts[c]).ravel())
        T_cam_ref[s] = T
        T_rig_sensor[s] = invert(T)

    # Reprojection error with our own camera model (the same model as OpenCV's).
    sq_by_sensor: dict[str, list[np.ndarray]] = {s: [] for s in order}
    for f, view in enumerate(views):
        rv, tv = np.asarray(rvecs0[f]), np.asarray(tvecs0[f])
        if rv.size != 3 or tv.size != 3:
            continue  # OpenCV dropped the frame (degenerate in every camera)
        T_ref_board = make_T(rotation_from_rvec(rv.ravel()), tv.ravel())
        for s, uv in obs[view].items():
            P = transform_points(T_cam_ref[s] @ T_ref_board, obj)
            err = intrinsics[s].project(P) - uv
            sq_by_sensor[s].append(np.sum(err * err, axis=1))
    all_sq = np.concatenate([np.concatenate(v) for v in sq_by_sensor.values() if v])
    rms_by_sensor = {
        s: float(np.sqrt(np.mean(np.concatenate(v)))) if v else float("nan")
        for s, v in sq_by_sensor.items()
    }
    return BaselineResult(
        intrinsics={s: intrinsics[s] for s in image_sizes},
        T_rig_sensor={s: T_rig_sensor[s] for s in image_sizes},
        rms_px=float(np.sqrt(np.mean(all_sq))),
        seconds=time.perf_counter() - start,
        rms_px_by_sensor={s: rms_by_sensor[s] for s in image_sizes},
    )
