"""Binary PGM / PPM images in a capture directory (what camera SDKs save: the VimsLab
colour + LWIR rig of issue 30 is PPM colour and 16-bit PGM thermal).

Real images: czha626's LWIR views (tests/data/czha626-thermal-visible, BSD-3), stored as
16-bit PGM (the 8-bit values x 257, as a 16-bit core's counts) and as 8-bit PNG, calibrate
to the same result; OpenCV's plain pipeline on the same images is the baseline.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import DATA_DIR
from trifuse.app.cli import main
from trifuse.app.storage.capture import CaptureError, read_image_header
from trifuse.calib.board import Board
from trifuse.calib.image_header import ImageHeaderError, pnm_header
from trifuse.calib.opencv_reference import calibrate_camera_opencv, find_chessboard_opencv

THERMAL = DATA_DIR / "czha626-thermal-visible" / "thermal"
BOARD_YAML = "pattern: checkerboard\ninner_corners: [6, 5]\nsquare_size_m: 0.1\n"


@pytest.mark.parametrize(
    ("ext", "image", "depth", "channels"),
    [
        (".pgm", np.full((3, 5), 7, np.uint8), 8, 1),
        (".pgm", np.full((3, 5), 4000, np.uint16), 16, 1),
        (".ppm", np.full((3, 5, 3), 9, np.uint8), 8, 3),
    ],
)
def test_pnm_header_as_opencv_writes_it(
    ext: str, image: np.ndarray, depth: int, channels: int
) -> None:
    ok, data = cv2.imencode(ext, image)
    assert ok
    h = pnm_header(data.tobytes())
    assert (h.format, h.width, h.height, h.bit_depth, h.channels) == ("pnm", 5, 3, depth, channels)


def test_pnm_header_reads_comments_and_refuses_damage() -> None:
    h = pnm_header(b"P5\n# made by a camera SDK\n640 480\n# 14-bit core\n65535\n" + bytes(8))
    assert (h.width, h.height, h.bit_depth) == (640, 480, 16)
    for bad, why in [
        (b"P2\n2 2\n255\n1 2 3 4\n", "expected a binary PGM or PPM"),
        (b"P5\n0 480\n255\n", "width 0"),
        (b"P5\n640 480\n70000\n", "maxval 70000"),
        (b"P5\n640 480", "expected width, height and maxval"),
        (b"P5 " + b" " * 5000 + b"640 480 255\n", "expected width, height and maxval"),
    ]:
        with pytest.raises(ImageHeaderError, match=why):
            pnm_header(bad)


def test_a_damaged_pgm_in_a_capture_is_one_line_naming_it(tmp_path: Path) -> None:
    f = tmp_path / "thermal_left.pgm"
    f.write_bytes(b"P5\n640\n")
    with pytest.raises(CaptureError, match=r"thermal_left\.pgm: corrupt P5 header"):
        read_image_header(f)


def _capture(root: Path, ext: str) -> Path:
    root.mkdir()
    (root / "board.yaml").write_text(BOARD_YAML)
    for f in sorted(THERMAL.glob("*.jpg")):
        grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        view = root / f.stem
        view.mkdir()
        image = grey.astype(np.uint16) * 257 if ext == ".pgm" else grey
        assert cv2.imwrite(str(view / f"thermal_left{ext}"), image)
    return root


@pytest.mark.slow  # two calibrations of a real set: about 6 s
def test_16_bit_pgm_thermal_calibrates_as_its_png(tmp_path: Path) -> None:
    reports = {}
    for ext in (".pgm", ".png"):
        cap = _capture(tmp_path / ext[1:], ext)
        out = tmp_path / f"{ext[1:]}.json"
        assert main(["calibrate", str(cap), "--out", str(tmp_path / f"{ext[1:]}.yaml"),
                     "--report", str(out)]) == 0  # fmt: skip
        reports[ext] = json.loads(out.read_text())["sensors"]["thermal_left"]
    pgm, png = reports[".pgm"], reports[".png"]
    assert pgm["views_detected"] == png["views_detected"] >= 11
    assert pgm["intrinsics"]["fx"] == pytest.approx(png["intrinsics"]["fx"], rel=0.005)
    # OpenCV's plain pipeline on the same 8-bit images: trifuse's fx within 1 % of it
    found = []
    for f in sorted(THERMAL.glob("*.jpg")):
        grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        corners, _how = find_chessboard_opencv(grey, (6, 5), thermal=True)
        if corners is not None:
            found.append(corners.reshape(-1, 2))
    obj = Board(6, 5, 0.1).object_points()
    ref = calibrate_camera_opencv([obj] * len(found), found, (640, 480))
    assert pgm["views_detected"] >= len(found)
    assert pgm["intrinsics"]["fx"] == pytest.approx(ref.intrinsics.fx, rel=0.01)
