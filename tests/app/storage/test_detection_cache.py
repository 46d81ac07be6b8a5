"""Board detections kept by image content (app.storage.detection_cache): a search's result
comes back for the same pixels, board and modality, from memory or disk, never for
anything else; a damaged or unwritable cache only costs a search again."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support import OPENCV_LEFT_9X6
from trifuse.app.storage import detection_cache as dc
from trifuse.calib.board import Board
from trifuse.calib.polarity import detect_board_configured

BOARD = Board(9, 6, 0.025)


@pytest.fixture
def searches(monkeypatch) -> list[tuple[int, ...]]:
    """The real detector, each call recorded (the image's shape)."""
    calls: list[tuple[int, ...]] = []

    def counted(image, board, modality):
        calls.append(image.shape)
        return detect_board_configured(image, board, modality)

    monkeypatch.setattr(dc, "detect_board_configured", counted)
    return calls


@pytest.fixture(scope="module")
def photo() -> np.ndarray:
    """A real 640 x 480 photograph of the 9 x 6 board (OpenCV's sample)."""
    return cv2.imread(str(OPENCV_LEFT_9X6 / "left01.jpg"), cv2.IMREAD_GRAYSCALE)


def _same(a, b) -> bool:
    corners_equal = (a.corners is None and b.corners is None) or (
        a.corners is not None and b.corners is not None and np.array_equal(a.corners, b.corners)
    )
    return corners_equal and (a.reason, a.method) == (b.reason, b.method)


def test_a_second_search_of_the_same_pixels_is_not_made(tmp_path, searches, photo) -> None:
    cache = dc.DetectionCache(tmp_path)
    first = cache.detect(photo, BOARD, "color")
    assert first.found and len(searches) == 1
    again = cache.detect(photo.copy(), BOARD, "color")  # another array, the same pixels
    assert _same(first, again) and len(searches) == 1
    again.corners += 5.0  # a caller changing its corners changes no one else's
    assert _same(first, cache.detect(photo, BOARD, "color"))
    blank = np.full_like(photo, 128)
    missed = cache.detect(blank, BOARD, "color")
    assert not missed.found and len(searches) == 2
    assert _same(missed, cache.detect(blank, BOARD, "color")) and len(searches) == 2


def test_another_image_board_or_modality_is_searched(tmp_path, searches, photo) -> None:
    cache = dc.DetectionCache(tmp_path)
    cache.detect(photo, BOARD, "color")
    touched = photo.copy()
    touched[0, 0] ^= 1  # one grey level of one pixel
    cache.detect(touched, BOARD, "color")
    assert len(searches) == 2
    small = np.full((48, 64), 100, np.uint8)  # quick to search in vain
    cache.detect(small, BOARD, "color")
    cache.detect(small, Board(9, 6, 0.030), "color")
    cache.detect(small, dataclasses.replace(BOARD, thermal_black_is_hot=False), "color")
    cache.detect(small.astype(np.float32), BOARD, "thermal")
    cache.detect(small.astype(np.float32), BOARD, "tof")
    cache.detect(small.astype(np.float64), BOARD, "tof")
    cache.detect(small.reshape(64, 48), BOARD, "color")
    assert len(searches) == 9


def test_a_new_process_finds_the_results_on_disk(tmp_path, searches, photo) -> None:
    first = dc.DetectionCache(tmp_path).detect(photo, BOARD, "color")
    fresh = dc.DetectionCache(tmp_path)  # empty memory, as a restarted console
    assert _same(first, fresh.detect(photo, BOARD, "color"))
    assert len(searches) == 1
    files = list(fresh.folder.glob("*.json"))
    assert len(files) == 1 and files[0].stem == dc.detection_key(photo, BOARD, "color")


def test_a_damaged_file_is_searched_again_and_rewritten(tmp_path, searches, photo) -> None:
    first = dc.DetectionCache(tmp_path).detect(photo, BOARD, "color")
    (path,) = dc.DetectionCache(tmp_path).folder.glob("*.json")
    for damage in ("", '{"corners": [[1, 2, 3]], "reason": null, "method": "sb"}', "not json"):
        path.write_text(damage)
        assert _same(first, dc.DetectionCache(tmp_path).detect(photo, BOARD, "color"))
    assert len(searches) == 4
    assert _same(first, dc.DetectionCache(tmp_path).detect(photo, BOARD, "color"))
    assert len(searches) == 4  # rewritten whole


def test_live_frames_stay_in_memory(tmp_path, searches, photo) -> None:
    cache = dc.DetectionCache(tmp_path)
    cache.detect(photo, BOARD, "color", keep=False)
    cache.detect(photo, BOARD, "color", keep=False)
    assert len(searches) == 1
    assert not any(tmp_path.rglob("*.json"))


def test_memory_keeps_the_newest_results(searches) -> None:
    cache = dc.DetectionCache(None, memory_entries=2)
    images = [np.full((48, 64), v, np.uint8) for v in (10, 20, 30)]
    for image in images:
        cache.detect(image, BOARD, "color")
    cache.detect(images[2], BOARD, "color")
    cache.detect(images[0], BOARD, "color")  # the oldest went
    assert len(searches) == 4


def test_an_unwritable_cache_still_detects(tmp_path, searches, photo, caplog) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("a file where the cache's folder should be")
    cache = dc.DetectionCache(blocked)
    with caplog.at_level(logging.WARNING, logger=dc.__name__):
        first = cache.detect(photo, BOARD, "color")
        cache.detect(np.full_like(photo, 7), BOARD, "color")
    assert first.found and cache.folder is None
    assert len([r for r in caplog.records if "not kept on disk" in r.message]) == 1
    assert _same(first, cache.detect(photo, BOARD, "color")) and len(searches) == 2


def test_a_malformed_image_raises_and_is_not_kept(tmp_path) -> None:
    cache = dc.DetectionCache(tmp_path)
    for _ in range(2):
        with pytest.raises(ValueError, match="color image: expected"):
            cache.detect(np.zeros((48, 64, 2), np.uint8), BOARD, "color")
    with pytest.raises(ValueError, match="expected a numpy array"):
        cache.detect([[0]], BOARD, "color")
    assert not any(tmp_path.rglob("*.json"))


def test_where_the_cache_is(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv(dc.CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert dc.default_cache_dir() == tmp_path / "trifuse" / "detections"
    monkeypatch.setenv(dc.CACHE_ENV, str(tmp_path / "mine"))
    assert dc.shared_cache().folder.parent == tmp_path / "mine"
    monkeypatch.setenv(dc.CACHE_ENV, "off")
    assert dc.default_cache_dir() is None and dc.shared_cache().folder is None


def test_other_code_versions_and_old_results_are_pruned(monkeypatch, tmp_path, photo) -> None:
    for name in ("old-1", "old-2"):
        (tmp_path / name).mkdir()
    dc.DetectionCache(tmp_path).detect(photo, BOARD, "color")
    kept = sorted(p.name for p in tmp_path.iterdir())
    assert len(kept) == dc.KEEP_FINGERPRINTS and dc.code_fingerprint()[:24] in kept
    monkeypatch.setattr(dc, "MAX_FILES", 3)
    cache = dc.DetectionCache(tmp_path)
    images = [np.full((48, 64), v, np.uint8) for v in range(6)]
    for image in images:
        cache.detect(image, BOARD, "color")
    (cache.folder / ".x.json.123.abcdef.tmp").write_text("interrupted")
    cache.prune()
    left = {p.stem for p in Path(cache.folder).iterdir()}
    assert left == {dc.detection_key(im, BOARD, "color") for im in images[-3:]}
