"""The board in words (calib.board.Board.describe) for every pattern, used wherever a board
is named (capture summary, calibration errors, the console's session, the HTML report, the
simulator's listing), and a sensor left out of a calibration named with the reason most of
its views failed for (app.workflows.calibration_run.excluded_with_detection_reasons).
Small synthetic inputs only: no rendering, no calibration."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tests.support import capture_frames, small_capture_rig
from trifuse.app.cli.simulate import board_text
from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.capture import load_capture
from trifuse.app.storage.capture_writer import write_board, write_view
from trifuse.app.workflows.calib_session import _board_text as session_board_text
from trifuse.app.workflows.calibration_run import (
    DetectionRun,
    calibrate_capture,
    dominant_failure,
    excluded_with_detection_reasons,
)
from trifuse.app.workflows.report_sections import report_board_text as html_board_text
from trifuse.calib.board import Board
from trifuse.calib.errors import CalibrationError

BOARDS = {
    "checkerboard 9 x 6 inner corners of 60 mm": Board(9, 6, 0.06),
    "ChArUco 10 x 7 squares of 60 mm, markers 45 mm DICT_4X4_50, inverted": Board(
        9, 6, 0.06, pattern="charuco", marker_size_m=0.045, dictionary="DICT_4X4_50", inverted=True
    ),
    "ChArUco 5 x 7 squares of 40 mm, markers 30 mm DICT_5X5_100, legacy layout": Board(
        4, 6, 0.04, pattern="charuco", marker_size_m=0.03, dictionary="DICT_5X5_100", legacy=True
    ),
    "asymmetric circle grid 4 x 11, spacing 60 mm, circles 42 mm": Board(
        4, 11, 0.06, pattern="asymmetric_circles", circle_diameter_m=0.042
    ),
    "symmetric circle grid 10 x 8, spacing 25.4 mm, circles 12.7 mm": Board(
        10, 8, 0.0254, pattern="symmetric_circles", circle_diameter_m=0.0127
    ),
}


@pytest.mark.parametrize("words", list(BOARDS))
def test_the_board_describes_itself_and_every_place_says_the_same(words: str) -> None:
    board = BOARDS[words]
    assert board.describe() == words
    assert board_text(board) == "the " + words
    assert session_board_text(board) == words + " (polarity found from the data)"
    assert html_board_text(board.to_dict()) == words


def test_polarity_keys_follow_the_description() -> None:
    board = Board(9, 6, 0.06, thermal_black_is_hot=False)
    words = "checkerboard 9 x 6 inner corners of 60 mm"
    assert session_board_text(board) == words + " with thermal_black_is_hot: false"
    assert html_board_text(board.to_dict()) == words + " (thermal black is hot: False)"
    # a board the report format does not know: its keys as they are
    assert (
        html_board_text({"pattern": "hexagons", "size": 3}) == "board (pattern: hexagons, size: 3)"
    )


def test_capture_summary_and_not_found_error_name_a_charuco_board(tmp_path: Path) -> None:
    board = BOARDS["ChArUco 10 x 7 squares of 60 mm, markers 45 mm DICT_4X4_50, inverted"]
    rig, frames = small_capture_rig(), capture_frames()
    write_board(tmp_path, board)
    for name in ("0001", "0002", "0003"):  # noise: no board anywhere
        write_view(tmp_path, name, FrameSet(0, {"ccd_left": frames["ccd_left"]}), rig)
    capture = load_capture(tmp_path)
    assert f"3 views, board {board.describe()}, " in capture.summary()
    with pytest.raises(CalibrationError, match=r"the board \(ChArUco 10 x 7 squares of 60 mm, "):
        calibrate_capture(capture)


UNREAD = (
    "ChArUco markers not resolvable: quads of about {} px seen, marker cells of at most {} px, "
    "under the 2 px a marker's bits need (this sensor cannot read the markers at this "
    "distance: bring the board nearer or use a board with larger markers)"
)
NOT_FOUND = "ChArUco board (10x7 squares, DICT_4X4_50) not found (tried charuco, charuco-inv)"


def test_the_dominant_failure_is_named_with_the_range_of_its_numbers() -> None:
    reasons = [UNREAD.format(a, b) for a, b in (("3.5", "0.6"), ("7.9", "1.3"), ("1.8", "0.3"))]
    why = dominant_failure([*reasons, NOT_FOUND], 5)
    assert why is not None
    assert why.startswith(
        "ChArUco markers not resolvable in 3 of 5 views: quads of about 1.8-7.9 px seen, "
        "marker cells of at most 0.3-1.3 px, under the 2 px a marker's bits need"
    )
    # one kind, different wordings: the most common wording, counted with the others
    tried = "board (9x6 inner corners) not found (tried {})"
    found = [tried.format("sb-x3, classic-x3")] * 2 + [tried.format("sb")]
    assert dominant_failure(found, 4) == f"{tried.format('sb-x3, classic-x3')} (in 3 of 4 views)"
    assert dominant_failure(reasons, 6) is None  # half the views: no dominant reason
    assert dominant_failure([], 3) is None


def test_a_sensor_left_out_says_why_its_views_failed() -> None:
    views = [f"{k:04d}" for k in range(1, 19)]
    seen = np.zeros((54, 2))
    obs = {v: {"ccd_left": seen} for v in views}
    rejected: dict[str, dict[str, str]] = {}
    for k, v in enumerate(views):
        rejected[v] = {"thermal_left": NOT_FOUND}
        if k == 0:
            obs[v]["tof"] = seen  # the TOF read the board once
        elif k < 16:
            rejected[v]["tof"] = UNREAD.format(f"{2 + 0.1 * k:.1f}", f"{0.3 + 0.05 * k:.2f}")
        else:
            rejected[v]["tof"] = NOT_FOUND
    too_few = "board detected in 1 view(s); Zhang's method needs at least 3: too few views"
    result = SimpleNamespace(
        sensors={"ccd_left": None}, intrinsics_only={}, excluded_sensors={"tof": too_few}
    )
    out = excluded_with_detection_reasons(result, DetectionRun(obs, rejected, {}))  # type: ignore[arg-type]
    assert out["tof"].startswith(
        "ChArUco markers not resolvable in 15 of 18 views: quads of about 2.1-3.5 px seen, "
        "marker cells of at most 0.35-1.05 px, under the 2 px"
    )
    assert out["tof"].endswith("; " + too_few)
    # found in no view: unknown to the calibration, added with its reason
    assert out["thermal_left"] == (
        "ChArUco board (10x7 squares, DICT_4X4_50) not found (tried charuco, charuco-inv) "
        "(in 18 of 18 views)"
    )
    assert "ccd_left" not in out
