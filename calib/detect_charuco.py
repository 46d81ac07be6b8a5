"""ChArUco board detection (``cv2.aruco.CharucoDetector``) in colour, thermal and TOF images.

Called by :func:`calib.detect.detect_board` for a board with ``pattern == "charuco"``.
A view may see part of the board (the board leaving the image is how the image's corners
get covered): the detection is ``(board.n_corners, 2)`` pixels with NaN rows for the inner
corners not seen, indexed as OpenCV's corner ids (calib.board: row-major, the
checkerboard's order). The markers fix the ordering: no polarity or half-turn decision
follows in the calibration.

Pipeline:

* **image**: calib.detect's preparation: colour -> grey; thermal -> fixed-pattern stripes
  removed, flattened (the image minus a wide blur, on the float data before any 8-bit
  stretch), stretched to 8 bit, upsampled; TOF -> flattened log amplitude, stretched,
  upsampled; the board's black dark.
* **polarity**: the detector wants black marker borders on white. An inverted board (white
  markers on black squares) is searched on the inverted image, which found as many boards
  or more than OpenCV's ``detectInvertedMarker`` (caliscope cam_3: 40 of 57 views against
  15; /work/notes/30-scout.md). Thermal and TOF try both polarities (a heated board's black
  reads hot, a cooled one's cold): the expected one first.
* **acceptance**: at least ``calib.board.MIN_POSE_POINTS`` corners, not all on one line
  (:meth:`calib.board.Board.pose_problem`), or the detection is rejected with the reason.
* **resolution**: when no board is found, the marker-like quads the ArUco detector saw but
  could not decode tell the marker size in pixels; when their cells are under
  ``MIN_CELL_PX`` the reason says that this sensor cannot resolve the markers at that
  distance (e.g. 6-pixel markers in a TOF amplitude image), not merely "not found".

Pure: arrays in, (corners, reason, method) out; :func:`calib.detect.detect_board` prepares
the image and wraps the result (this module does not import it: no circle).
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.calib.board import Board, aruco_dictionary

MIN_CELL_PX = 2.0
"""Smallest marker cell (one bit of the code, native pixels) the markers can be read at:
below it the bits blur into each other (OpenCV reads a bit from the cell's centre
pixels after a perspective removal to ``perspectiveRemovePixelPerCell`` pixels)."""


def _detector(board: Board) -> cv2.aruco.CharucoDetector:
    return cv2.aruco.CharucoDetector(
        board.opencv_charuco(), cv2.aruco.CharucoParameters(), cv2.aruco.DetectorParameters()
    )


def _resolution_problem(image: np.ndarray, board: Board, scale: int) -> str | None:
    """Why the markers cannot be read, from the quads the ArUco detector saw but could not
    decode (their median side, native pixels): cells under :data:`MIN_CELL_PX`; or None."""
    d = aruco_dictionary(board.dictionary)  # type: ignore[arg-type]
    det = cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters())
    _corners, _ids, rejected = det.detectMarkers(image)
    if rejected is None or len(rejected) < 3:
        return None
    q = np.asarray(rejected, dtype=np.float64).reshape(-1, 4, 2)
    side = float(np.median(np.linalg.norm(q - np.roll(q, 1, axis=1), axis=2))) / scale
    # A quad is a marker (side = marker) or a black square (side = square): the cell is at
    # most side / (bits + 2).
    cell = side / (int(d.markerSize) + 2)
    if cell >= MIN_CELL_PX:
        return None
    return (
        f"ChArUco markers not resolvable: quads of about {side:.1f} px seen, marker cells of "
        f"at most {cell:.1f} px, under the {MIN_CELL_PX:g} px a marker's bits need (this "
        "sensor cannot read the markers at this distance: bring the board nearer or use a "
        "board with larger markers)"
    )


def find_charuco(
    image: np.ndarray, scale: int, board: Board, try_inverted: bool
) -> tuple[np.ndarray | None, str | None, str | None]:
    """Find a (possibly partial) ChArUco board in a prepared image.

    Args:
        image: (H, W) uint8, ``scale`` x the sensor image, the board's black dark
            (calib.detect's preparation: grey; thermal and TOF flattened, stretched,
            upsampled).
        scale: integer upsampling of ``image``.
        board: a board with ``pattern == "charuco"``.
        try_inverted: also search the inverted image (thermal, TOF: the polarity may be
            the other way).

    Returns:
        (corners, reason, method): corners ``(board.n_corners, 2)`` float64 in the sensor
        image's pixels (pixel centres at integers), NaN rows for corners not seen, or None
        with the reason (not found, too few corners, markers not resolvable).
    """
    # The detector wants the markers' black cells dark: an inverted board is searched on
    # the inverted image.
    first = 255 - image if board.inverted else image
    images = [("", first)] + ([("-inverted", 255 - first)] if try_inverted else [])
    detector = _detector(board)
    rejection: tuple[None, str, str] | None = None
    tried = []
    for label, img in images:
        method = "charuco" + label + (f"-x{scale}" if scale != 1 else "")
        tried.append(method)
        corners, ids, _mc, _mi = detector.detectBoard(img)
        if ids is None or len(ids) == 0:
            continue
        ids = np.asarray(ids, dtype=np.int64).ravel()
        uv = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
        if scale != 1:
            uv = (uv + 0.5) / scale - 0.5
        out = np.full((board.n_corners, 2), np.nan)
        out[ids] = uv
        problem = board.pose_problem(np.isfinite(out[:, 0]))
        if problem is None:
            return out, None, method
        if rejection is None:
            rejection = (None, f"ChArUco board seen but {problem}", method)
    if rejection is not None:
        return rejection
    why = _resolution_problem(first, board, scale)
    if why is not None:
        return None, why, None
    sx, sy = board.squares
    return (
        None,
        f"ChArUco board ({sx}x{sy} squares, {board.dictionary}) not found "
        f"(tried {', '.join(tried)})",
        None,
    )
