"""Calibrating a capture directory (app.workflows.calibration_run) through ``trifuse
calibrate``: an image file that cannot be read is skipped, named, and costs its view that
image only (issue 33)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import pytest

from tests.support import DATA_DIR
from trifuse.app.cli import main

STEREO = DATA_DIR / "boofcv-bumblebee2-chess"
"""Eleven real left/right views of a 4 x 6 inner-corner board, 30 mm squares."""
BOARD = "pattern: checkerboard\ninner_corners: [4, 6]\nsquare_size_m: 0.03\n"


@pytest.fixture(scope="module")
def stereo_png(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real stereo set as a capture directory of PNGs (the same pixels): views 01-11,
    each with ``ccd_left.png`` and ``ccd_right.png``. Copy it to change it."""
    cap = tmp_path_factory.mktemp("stereo") / "captures"
    cap.mkdir()
    (cap / "board.yaml").write_text(BOARD)
    for left in sorted(STEREO.glob("left*.jpg")):
        view = cap / left.stem.removeprefix("left")
        view.mkdir()
        for side in ("left", "right"):
            grey = cv2.imread(str(STEREO / f"{side}{view.name}.jpg"), cv2.IMREAD_GRAYSCALE)
            assert grey is not None and cv2.imwrite(str(view / f"ccd_{side}.png"), grey)
    return cap


DAMAGE = {
    "cut short": (
        lambda data: data[: len(data) // 2],
        "a PNG cut short: the file ends inside its IDAT chunk (",
    ),
    "empty": (lambda data: b"", "not an image: an empty file"),
    "text": (
        lambda data: b"calibration notes: the board moved in this view\n",
        "not an image: expected JPEG or PNG, the first bytes are b'calibrat'",
    ),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_an_unreadable_image_is_skipped_and_named(
    stereo_png: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str], damage: str
) -> None:
    """One PNG of view 05 cut short (what a full disk or a killed copy leaves), empty, or
    not an image at all: the calibration completes with both cameras, view 05 keeps its
    left image, and the file is named where images without a board are: the summary's
    list, the report's detections (and its ``unreadable_images``), the HTML report. Neither
    libpng nor OpenCV says anything on the terminal (it used to abort after "libpng error:
    PNG input buffer is incomplete")."""
    cap = tmp_path / "captures"
    shutil.copytree(stereo_png, cap)
    bad = cap / "05" / "ccd_right.png"
    spoil, why = DAMAGE[damage]
    bad.write_bytes(spoil(bad.read_bytes()))
    report_path, html_path = tmp_path / "report.json", tmp_path / "report.html"
    argv = ["calibrate", str(cap), "--out", str(tmp_path / "rig.yaml")]
    code = main([*argv, "--report", str(report_path), "--report-html", str(html_path)])
    out, err = capfd.readouterr()
    assert code == 0, err
    assert "libpng" not in err and "WARN" not in err and "ERROR" not in err, err
    assert "Traceback" not in out + err

    reason = f"unreadable image ccd_right.png, skipped: {why}"
    assert f"    05/ccd_right.png: {why}" in out  # what was indexed, before calibrating
    [line] = [line for line in out.splitlines() if line.startswith("  ccd_right, view 05: ")]
    assert line.startswith(f"  ccd_right, view 05: {reason}"), line
    assert out.index("images without a usable board") < out.index(line)

    report = json.loads(report_path.read_text())
    detection = report["detections"]["05"]["ccd_right"]
    assert detection["found"] is False and detection["reason"].startswith(reason)
    [entry] = report["unreadable_images"]
    assert entry["why"].startswith(why)
    assert {k: v for k, v in entry.items() if k != "why"} == {
        "view": "05",
        "sensor": "ccd_right",
        "file": "05/ccd_right.png",
        "distance": False,
    }
    # the view keeps its other camera; both cameras are calibrated
    assert report["detections"]["05"]["ccd_left"]["found"] is True
    assert "ccd_left" in report["views"]["05"] and "ccd_right" not in report["views"]["05"]
    assert report["sensors"]["ccd_left"]["views_detected"] == 11
    assert report["sensors"]["ccd_right"]["views_detected"] == 10
    assert not report["excluded_sensors"]
    html = html_path.read_text()
    assert "05/ccd_right.png" in html and "image not read in 1 view(s) (05)" in html
