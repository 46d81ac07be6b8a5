"""The capture directory (app.storage.capture): writing, reading back, and every refusal."""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tests.support import CAPTURE_BOARD, capture_frames, small_capture_rig
from trifuse.app.sources.frames import FrameSet
from trifuse.app.storage.capture import (
    CaptureError,
    UnreadableImageError,
    ViewExistsError,
    load_capture,
    modality_from_name,
    quiet_opencv,
    read_image_header,
)
from trifuse.app.storage.capture_writer import write_board, write_rig, write_view
from trifuse.app.storage.ground_truth import (
    GROUND_TRUTH_FORMAT,
    load_ground_truth,
    write_ground_truth,
)
from trifuse.calib.board import Board
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import make_T, rotation_from_euler_deg
from trifuse.calib.units import encode_distance

# Half a centi-kelvin of rounding plus float32's resolution near 300 K (about 3e-5 K).
THERMAL_TOL_K = 0.005 + 3e-5
DISTANCE_TOL_M = 0.0005 + 1e-6


@pytest.fixture
def capture(tmp_path: Path) -> tuple[Path, Rig, FrameSet]:
    rig = small_capture_rig()
    frames = capture_frames()
    write_board(tmp_path, CAPTURE_BOARD)
    write_rig(tmp_path, rig)
    write_view(tmp_path, "0001", frames, rig)
    return tmp_path, rig, frames


# -- round trip ---------------------------------------------------------------------------


def test_round_trip_values(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, rig, frames = capture
    assert sorted(p.name for p in (path / "0001").iterdir()) == [
        "ccd_left.png",
        "thermal_left.png",
        "tof.png",
        "tof_distance.png",
    ]
    cap = load_capture(path)
    assert cap.board == CAPTURE_BOARD
    assert cap.rig == rig
    assert [v.name for v in cap.views] == ["0001"]
    view = cap.views[0]
    assert view.sensors == ["tof", "ccd_left", "thermal_left"]  # rig order

    got = view.frames()
    color = got["ccd_left"].image
    assert color.dtype == np.uint8 and color.shape == (48, 64, 3)
    np.testing.assert_array_equal(color, frames["ccd_left"].image)  # exact, RGB order

    thermal = got["thermal_left"].image
    want = frames["thermal_left"].image
    assert thermal.dtype == np.float32 and thermal.shape == want.shape
    assert view.thermal_is_kelvin("thermal_left")
    assert np.isnan(thermal[0, 0])
    assert np.array_equal(np.isnan(thermal), np.isnan(want))
    assert np.nanmax(np.abs(thermal - want)) <= THERMAL_TOL_K

    tof = got["tof"]
    assert tof.image.dtype == np.float32 and tof.distance_m is not None
    amp = frames["tof"].image
    np.testing.assert_array_equal(tof.image, np.clip(np.rint(amp), 0, 65535))
    dist, want_d = tof.distance_m, frames["tof"].distance_m
    assert dist.dtype == np.float32
    invalid = ~(np.isfinite(want_d) & (want_d > 0) & (want_d < 65.5))
    assert invalid[1, :4].all()
    np.testing.assert_array_equal(np.isnan(dist), invalid)
    assert np.nanmax(np.abs(dist - want_d)) <= DISTANCE_TOL_M


def test_files_hold_the_documented_encodings(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, _, frames = capture
    view = path / "0001"
    bgr = cv2.imread(str(view / "ccd_left.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(bgr[:, :, ::-1], frames["ccd_left"].image)  # BGR on disk
    ck = cv2.imread(str(view / "thermal_left.png"), cv2.IMREAD_UNCHANGED)
    assert ck.dtype == np.uint16 and ck[0, 0] == 0  # NaN -> 0
    assert ck[1, 1] == round(float(frames["thermal_left"].image[1, 1]) * 100)
    mm = cv2.imread(str(view / "tof_distance.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and (mm[1, :4] == 0).all()
    assert mm[2, 2] == round(float(frames["tof"].distance_m[2, 2]) * 1000)
    header = read_image_header(view / "thermal_left.png")
    assert (header.width, header.height, header.bit_depth, header.channels) == (38, 29, 16, 1)


def test_written_files_follow_the_umask(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, _, _ = capture
    mask = os.umask(0o022)
    os.umask(mask)
    for p in (path / "board.yaml", path / "0001" / "tof.png"):
        assert p.stat().st_mode & 0o777 == 0o666 & ~mask
    assert (path / "0001").stat().st_mode & 0o777 == 0o777 & ~mask
    assert not [p for p in path.rglob(".*")]  # no staging or temporary files left


def test_a_rig_of_another_head_is_refused_by_the_image_headers(
    capture: tuple[Path, Rig, FrameSet],
) -> None:
    path, rig, _ = capture
    loaded = load_capture(path)
    loaded.check_sizes(rig)  # the capture's own rig fits
    s = rig["thermal_left"]
    other = Rig(
        {**rig.sensors, "thermal_left": dataclasses.replace(s, image_size=(640, 512))}, "tof"
    )
    with pytest.raises(
        CaptureError, match=r"thermal_left.png: the rig says sensor 'thermal_left' takes 640x512"
    ):
        loaded.check_sizes(other)


def test_views_sorted_any_subset_and_non_views_ignored(tmp_path: Path) -> None:
    rig = small_capture_rig()
    frames = capture_frames()
    write_board(tmp_path, CAPTURE_BOARD)
    write_view(tmp_path, "0010", FrameSet(0, {"ccd_left": frames["ccd_left"]}), rig)
    write_view(tmp_path, "0002", frames, rig)
    write_view(tmp_path, "0003", FrameSet(0, {"tof": frames["tof"]}), rig)
    (tmp_path / "ground_truth.yaml").write_text("anything: 1\n")
    (tmp_path / "notes.txt").write_text("not a view\n")
    (tmp_path / ".0004.abc.partial").mkdir()  # an interrupted write
    (tmp_path / "0002" / "readme.txt").write_text("ignored\n")

    cap = load_capture(tmp_path)  # no rig.yaml: modalities from the names
    assert cap.rig is None
    assert [v.name for v in cap.views] == ["0002", "0003", "0010"]
    assert cap.modalities == {"ccd_left": "color", "thermal_left": "thermal", "tof": "tof"}
    assert cap.view("0010").sensors == ["ccd_left"]
    assert cap.view("0003").sensors == ["tof"]
    assert [v.name for v in cap.views_with("thermal_left")] == ["0002"]
    assert cap.view("0003").frame("tof").distance_m is not None
    with pytest.raises(KeyError, match="no image of sensor 'thermal_left'"):
        cap.view("0003").frame("thermal_left")
    assert "3 views" in cap.summary()


def test_grey_jpeg_colour_and_8bit_thermal(tmp_path: Path) -> None:
    write_board(tmp_path, CAPTURE_BOARD)
    view = tmp_path / "a"
    view.mkdir()
    grey = np.tile(np.arange(64, dtype=np.uint8) * 4, (48, 1))
    cv2.imwrite(str(view / "rgb_cam.jpg"), grey)
    cv2.imwrite(str(view / "lwir.png"), grey[:29, :38])
    cv2.imwrite(str(view / "thermal_b.png"), (grey[:29, :38].astype(np.uint16) * 100))

    cap = load_capture(tmp_path)
    v = cap.views[0]
    color = v.frame("rgb_cam").image
    assert color.shape == (48, 64, 3) and color.dtype == np.uint8  # grey becomes RGB
    assert np.array_equal(color[:, :, 0], color[:, :, 1])
    assert np.abs(color[:, :, 0].astype(int) - grey).max() <= 3  # JPEG loss
    lwir = v.frame("lwir").image
    assert lwir.dtype == np.float32 and not v.thermal_is_kelvin("lwir")
    np.testing.assert_array_equal(lwir, grey[:29, :38])  # 8-bit values, not kelvin
    counts = load_capture(tmp_path, thermal_encoding="counts").views[0]
    assert not counts.thermal_is_kelvin("thermal_b")
    assert counts.frame("thermal_b").image[0, 1] == 400.0
    assert v.frame("thermal_b").image[0, 1] == pytest.approx(4.0)


# -- refusals -----------------------------------------------------------------------------


def test_missing_board_yaml(tmp_path: Path) -> None:
    (tmp_path / "0001").mkdir()
    with pytest.raises(CaptureError, match=r"board\.yaml: missing") as exc:
        load_capture(tmp_path)
    assert str(tmp_path / "board.yaml") in str(exc.value)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("pattern: [unclosed\n", "not valid YAML"),
        ("pattern: checkerboard\ninner_corners: [9, 6]\n", r"missing key\(s\) \['square_size_m'\]"),
        ("pattern: circles\ninner_corners: [9, 6]\nsquare_size_m: 0.02\n", "expected one of"),
        ("- 1\n- 2\n", "expected a mapping, got list"),
    ],
)
def test_malformed_board_yaml(tmp_path: Path, text: str, match: str) -> None:
    (tmp_path / "board.yaml").write_text(text)
    with pytest.raises(CaptureError, match=match) as exc:
        load_capture(tmp_path)
    assert str(tmp_path / "board.yaml") in str(exc.value)


def test_not_a_capture_directory(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="no such directory"):
        load_capture(tmp_path / "nope")


def test_wrong_image_size_on_disk(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, _, _ = capture
    bad = path / "0001" / "thermal_left.png"
    cv2.imwrite(str(bad), np.zeros((30, 40), np.uint16))
    with pytest.raises(CaptureError, match=r"expected 38x29 .* got 40x30") as exc:
        load_capture(path)
    assert str(bad) in str(exc.value)


def test_wrong_image_size_refused_on_write(tmp_path: Path) -> None:
    rig = small_capture_rig()
    frames = capture_frames()
    frames.frames["ccd_left"].image = np.zeros((10, 10, 3), np.uint8)
    with pytest.raises(CaptureError, match=r"expected 64x48 .* got 10x10"):
        write_view(tmp_path, "0001", frames, rig)
    assert not (tmp_path / "0001").exists()


def test_wrong_dtype_refused_on_write(tmp_path: Path) -> None:
    frames = capture_frames()
    frames.frames["ccd_left"].image = np.zeros((48, 64, 3), np.float32)
    with pytest.raises(CaptureError, match=r"uint8 RGB .* got shape \(48, 64, 3\) float32"):
        write_view(tmp_path, "0001", frames, small_capture_rig())


def test_sensor_not_in_rig(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, rig, frames = capture
    with pytest.raises(CaptureError, match="sensor 'thermal_right' is not in the rig"):
        write_view(path, "0002", FrameSet(0, {"thermal_right": frames["thermal_left"]}), rig)
    cv2.imwrite(str(path / "0001" / "ccd_right.png"), np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(CaptureError, match=r"'ccd_right' is not in the capture's rig\.yaml"):
        load_capture(path)


def test_an_unreadable_image_is_set_aside_when_indexing(
    capture: tuple[Path, Rig, FrameSet],
) -> None:
    """Issue 33: a file that is no image, an empty one or a PNG cut short costs its view
    that image only: the view keeps its other sensors, and the file is named with why."""
    path, _, frames = capture
    view = path / "0001"
    (view / "tof.png").write_bytes(b"this is not an image at all")
    (view / "thermal_left.png").write_bytes(b"")
    data = (view / "ccd_left.png").read_bytes()
    (view / "ccd_left.png").write_bytes(data[:200])  # header intact, pixel data cut off
    cap = load_capture(path)
    [v] = cap.views
    assert v.sensors == [] and cap.sensors == []
    assert [(u.sensor, u.path.name, u.distance) for u in v.unreadable] == [
        ("ccd_left", "ccd_left.png", False),
        ("thermal_left", "thermal_left.png", False),
        ("tof", "tof.png", False),
    ]
    why = [u.why for u in v.unreadable]
    assert why[0].startswith("a PNG cut short: the file ends inside its IDAT chunk (")
    assert why[1] == "not an image: an empty file"
    assert why[2].startswith("not an image: expected JPEG or PNG")
    summary = cap.summary()
    for u in v.unreadable:
        assert f"0001/{u.path.name}: {u.why}" in summary
    # the distance image alone: the TOF keeps its amplitude
    write_view(path, "0002", frames, small_capture_rig())
    (path / "0002" / "tof_distance.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    cap = load_capture(path)
    two = cap.view("0002")
    assert two.sensors == ["tof", "ccd_left", "thermal_left"]
    assert two.files["tof"].distance is None and two.frame("tof").distance_m is None
    [u] = two.unreadable
    assert (u.sensor, u.path.name, u.distance) == ("tof", "tof_distance.png", True)
    assert "no IHDR chunk" in u.why


def test_a_corrupted_png_is_found_when_decoding_and_set_aside(
    capture: tuple[Path, Rig, FrameSet], capfd: pytest.CaptureFixture[str]
) -> None:
    """A PNG whole in length but corrupted inside (a flipped byte: its chunk fails its CRC
    check) is found before OpenCV decodes it, so libpng says nothing on stderr; frame()
    raises UnreadableImageError naming the file and sets the file aside; verify=True sets
    it aside when indexing."""
    path, _, _ = capture
    bad = path / "0001" / "ccd_left.png"
    data = bytearray(bad.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(data)
    cap = load_capture(path)  # headers only: still fine
    view = cap.views[0]
    with pytest.raises(
        UnreadableImageError, match=r"a corrupted PNG: its IDAT chunk at byte \d+ "
    ) as exc:
        view.frame("ccd_left")
    assert str(exc.value).startswith(f"{bad}: ") and exc.value.path == bad
    assert [(u.sensor, u.path) for u in view.unreadable] == [("ccd_left", bad)]
    assert view.frame("tof").image.size  # the view's other images are read
    cap = load_capture(path, verify=True)
    assert cap.views[0].sensors == ["tof", "thermal_left"]
    assert "0001/ccd_left.png: a corrupted PNG" in cap.summary()
    assert capfd.readouterr().err == ""


def test_opencv_is_quiet_inside_and_as_loud_as_before_after(
    capfd: pytest.CaptureFixture[str],
) -> None:
    """OpenCV's own log (an [ERROR] line for a PGM cut short) is kept off stderr inside
    quiet_opencv, nested and from threads, and its level is restored after."""
    ok, enc = cv2.imencode(".pgm", np.zeros((10, 12), np.uint8))
    assert ok
    cut = enc[: enc.size // 2]
    before = cv2.utils.logging.getLogLevel()
    with quiet_opencv():
        with quiet_opencv():
            assert cv2.imdecode(cut, cv2.IMREAD_UNCHANGED) is None
        with ThreadPoolExecutor(2) as pool:
            assert list(pool.map(lambda _: quiet_decode(cut), range(8))) == [None] * 8
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_SILENT
    assert cv2.utils.logging.getLogLevel() == before
    assert capfd.readouterr().err == ""


def quiet_decode(data: np.ndarray) -> np.ndarray | None:
    with quiet_opencv():
        return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)


def test_unknown_sensor_prefix_without_rig(tmp_path: Path) -> None:
    write_board(tmp_path, CAPTURE_BOARD)
    (tmp_path / "0001").mkdir()
    cv2.imwrite(str(tmp_path / "0001" / "camera3.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(CaptureError, match=r"'camera3': cannot tell its modality .*ccd\*"):
        load_capture(tmp_path)
    assert modality_from_name("LWIR_2") == "thermal"
    assert modality_from_name("depth") == "tof"


def test_distance_without_amplitude(tmp_path: Path) -> None:
    write_board(tmp_path, CAPTURE_BOARD)
    (tmp_path / "0001").mkdir()
    cv2.imwrite(str(tmp_path / "0001" / "tof_distance.png"), np.ones((4, 4), np.uint16))
    with pytest.raises(CaptureError, match=r"needs its amplitude image tof\.png"):
        load_capture(tmp_path)


def test_refuses_to_overwrite_a_view(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, rig, _ = capture
    before = {p.name: p.read_bytes() for p in (path / "0001").iterdir()}
    with pytest.raises(ViewExistsError, match="view exists already; refusing to overwrite"):
        write_view(path, "0001", capture_frames(seed=7), rig)
    assert {p.name: p.read_bytes() for p in (path / "0001").iterdir()} == before
    assert isinstance(ViewExistsError("x"), ValueError)


def test_bad_view_name(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match=r"view name '\.\./x'"):
        write_view(tmp_path, "../x", capture_frames(), small_capture_rig())


def test_board_and_rig_never_replaced(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, rig, _ = capture
    write_board(path, CAPTURE_BOARD)  # the same board again: fine
    write_rig(path, rig)
    with pytest.raises(CaptureError, match="exists with a different board"):
        write_board(path, Board(7, 5, 0.03))
    rig.sensors["ccd_left"].T_rig_sensor = np.eye(4)
    with pytest.raises(CaptureError, match="exists with a different rig"):
        write_rig(path, rig)


def test_encode_distance_edges() -> None:
    d = np.array([np.nan, -0.1, 0.0, 0.0004, 0.0006, 1.2344, 65.535, 65.6], np.float32)
    np.testing.assert_array_equal(encode_distance(d), [0, 0, 0, 0, 1, 1234, 65535, 0])


# -- ground truth -------------------------------------------------------------------------


def test_ground_truth_round_trip(capture: tuple[Path, Rig, FrameSet]) -> None:
    path, rig, _ = capture
    T = make_T(rotation_from_euler_deg(10, -20, 5), (0.1, -0.2, 1.5))
    gt_path, rig_path = write_ground_truth(path, rig, [("0001", T)], CAPTURE_BOARD)
    assert gt_path.name == "ground_truth.yaml" and rig_path.name == "ground_truth_rig.yaml"
    data = yaml.safe_load(gt_path.read_text())
    assert data["format"] == GROUND_TRUTH_FORMAT
    assert data["rig"] == "ground_truth_rig.yaml"
    assert data["board"] == CAPTURE_BOARD.to_dict()
    assert np.array(data["views"]["0001"]["T_rig_board"]).shape == (4, 4)
    gt = load_ground_truth(path)
    assert gt.rig == rig and gt.board == CAPTURE_BOARD
    np.testing.assert_array_equal(gt.T_rig_board["0001"], T)
    assert [v.name for v in load_capture(path).views] == ["0001"]  # still one view
    with pytest.raises(CaptureError, match="refusing to overwrite ground truth"):
        write_ground_truth(path, rig, [("0001", T)], CAPTURE_BOARD)


def test_ground_truth_rejects_non_rigid_pose(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="view '0001': T_rig_board is not a rigid"):
        write_ground_truth(
            tmp_path, small_capture_rig(), [("0001", np.diag([2.0, 1, 1, 1]))], CAPTURE_BOARD
        )
