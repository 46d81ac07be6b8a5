"""Circle grid detection (``cv2.findCirclesGrid``) in colour, thermal and TOF images.

Called by :func:`calib.detect.detect_board` for a board with ``pattern ==
"asymmetric_circles"`` (mainly) or ``"symmetric_circles"``. The grid is found whole or not
at all: the detection is ``(board.n_corners, 2)`` circle centres in the board's order
(calib.board: point ``r * cols + c`` at ``((2 c + r % 2) s, r s)``, symmetric
``(c s, r s)``), never NaN.

Pipeline:

* **image**: calib.detect's preparation: colour -> grey; thermal -> stripes removed,
  flattened (image minus a wide blur), stretched to 8 bit, upsampled; TOF -> flattened
  log amplitude, upsampled; the marks dark.
* **polarity**: the blob detector looks for dark circles. Colour: dark circles on white.
  Thermal: a heated grid's circles are hot (bright) and a cooled one's cold: both
  polarities are tried, the board's own first (``black_is_hot``: the marks are hot). TOF:
  both, dark first.
* **blobs**: ``cv2.SimpleBlobDetector`` with OpenCV's defaults but its area limits from the
  image size (the defaults, 25-5000 px^2, miss the circles of a board that fills a large
  frame and find noise in a small one), then ``findCirclesGrid`` (asymmetric or symmetric
  grid), and again with ``CALIB_CB_CLUSTERING`` (more tolerant of perspective).
* **order**: an asymmetric grid's only self-map that keeps its layout (an odd number of
  rows) is the mirror about its middle row (a symmetric grid's: about its middle column,
  and the half turn, which the calibration decides); the labelling whose board axes are
  right-handed in the image (the camera sees the board's front) is kept, and it must fit
  a homography.
* **no refinement**: the blob detector's centres (means over its threshold steps) were
  kept. A darkness centroid in a disc of the circle's size around each was tried:
  synthetic colour views with blur and noise, median error 0.024 -> 0.028 px; in the
  flattened thermal image 0.04 -> 0.24 px (the flattening's halo biases it).

Pure: arrays in, (centres, reason, method) out; :func:`calib.detect.detect_board` prepares
the image and wraps the result (this module does not import it: no circle).
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.calib.board import Board

MIN_CIRCLE_PX = 4.0
"""Smallest circle diameter (native pixels) whose centre is trusted: below it the blob
detector's centres are unreliable and the circles merge into noise."""
MAX_FIT_ERROR = 0.1
"""Largest RMS error of a labelled grid against its homography, as a fraction of the
spacing ``s`` in the image: a labelling that does not fit the layout is wrong."""
_TERM = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)


def _blob_detector(shape: tuple[int, ...], scale: int) -> cv2.SimpleBlobDetector:
    """OpenCV's default blob detector (dark, convex, not too elongated blobs; the centres
    then equal a plain script's where both find the grid), but for its area limits: from
    ``MIN_CIRCLE_PX`` (native pixels) up to a tenth of the image's shorter side across."""
    p = cv2.SimpleBlobDetector_Params()
    d_min = MIN_CIRCLE_PX * scale
    d_max = 0.1 * min(shape[:2])
    p.minArea = float(np.pi / 4 * d_min**2 * 0.7)
    p.maxArea = float(np.pi / 4 * d_max**2)
    return cv2.SimpleBlobDetector_create(p)


def _labelled(centres: np.ndarray, board: Board) -> np.ndarray | None:
    """``centres`` (N, 2) in OpenCV's order, relabelled to the board's order: as given or
    mirrored (asymmetric grid: about the middle row, the only mirror that keeps its
    layout; symmetric: about the middle column), whichever has right-handed board axes in
    the image; None if neither fits the layout (:data:`MAX_FIT_ERROR`)."""
    obj = board.object_points()[:, :2]
    idx = np.arange(board.n_corners).reshape(board.rows, board.cols)
    mirror = idx[::-1] if board.pattern == "asymmetric_circles" else idx[:, ::-1]
    for order in (idx.ravel(), mirror.ravel()):
        uv = centres[order]
        H, _ = cv2.findHomography(obj, uv, 0)
        if H is None:
            continue
        q = np.c_[obj, np.ones(len(obj))] @ H.T
        fit = np.sqrt(np.mean(np.sum((q[:, :2] / q[:, 2:] - uv) ** 2, axis=1)))
        # Image directions of the board's +x and +y at the grid's centre.
        c = obj.mean(axis=0)
        p0, px, py = (np.array([*c, 1.0]), np.array([c[0] + 1e-3, c[1], 1.0]),
                      np.array([c[0], c[1] + 1e-3, 1.0]))  # fmt: skip
        img = [H @ p for p in (p0, px, py)]
        img = [v[:2] / v[2] for v in img]
        ex, ey = img[1] - img[0], img[2] - img[0]
        spacing = np.linalg.norm(ex) / 1e-3 * board.square_size_m
        if ex[0] * ey[1] - ex[1] * ey[0] > 0 and fit < MAX_FIT_ERROR * spacing:
            return uv.copy()
    return None


def find_circles(
    image: np.ndarray, scale: int, board: Board, try_inverted: bool
) -> tuple[np.ndarray | None, str | None, str | None]:
    """Find an asymmetric circle grid in a prepared image.

    Args:
        image: (H, W) uint8, ``scale`` x the sensor image, the board's marks (the circles)
            dark (calib.detect's preparation).
        scale: integer upsampling of ``image``.
        board: a circle grid (``pattern`` ``asymmetric_circles`` or ``symmetric_circles``).
        try_inverted: also search the inverted image (thermal, TOF: a heated or a cooled
            grid).

    Returns:
        (centres, reason, method): centres ``(board.n_corners, 2)`` float64 in the sensor
        image's pixels (pixel centres at integers), in the board's order (a symmetric grid:
        one of its orderings, decided across sensors by the calibration); or None with the
        reason.
    """
    images = [("", image)] + ([("-inverted", 255 - image)] if try_inverted else [])
    grid = cv2.CALIB_CB_ASYMMETRIC_GRID
    if board.pattern == "symmetric_circles":
        grid = cv2.CALIB_CB_SYMMETRIC_GRID
    tried = []
    blobs_seen = []
    for label, img in images:
        det = _blob_detector(img.shape, scale)
        for flags, name in (
            (grid, "circles"),
            (grid | cv2.CALIB_CB_CLUSTERING, "circles-clustering"),
        ):
            method = name + label + (f"-x{scale}" if scale != 1 else "")
            tried.append(method)
            ok, centres = cv2.findCirclesGrid(
                img, board.pattern_size, flags=flags, blobDetector=det
            )
            if not ok or centres is None:
                continue
            uv = _labelled(np.asarray(centres, np.float64).reshape(-1, 2), board)
            if uv is None:
                continue
            if scale != 1:
                uv = (uv + 0.5) / scale - 0.5
            return uv, None, method
        blobs_seen.append(det.detect(img))
    sizes = [k.size / scale for kps in blobs_seen for k in kps]
    n = max((len(kps) for kps in blobs_seen), default=0)
    if n >= board.n_corners // 2 and np.median(sizes) < 1.5 * MIN_CIRCLE_PX:
        return (
            None,
            f"circle grid not resolvable: blobs of about {np.median(sizes):.1f} px, circles "
            f"need at least {MIN_CIRCLE_PX:g} px across (bring the board nearer or use "
            "larger circles)",
            None,
        )
    seen = f"; {n} blob(s) seen" if n else ""
    return (
        None,
        f"{board.pattern.split('_')[0]} circle grid ({board.cols}x{board.rows}) not found{seen} "
        f"(tried {', '.join(tried)})",
        None,
    )
