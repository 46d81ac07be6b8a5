"""Property-based tests of the file loaders (issue 8, "Bad input, everywhere"): rig files,
board files, capture directories (images, YAML, added files and folders), ground truth, and
refused writes of rigs and views.

The contract, the strategies and the mutators are in tests/fuzz_support.py; the streams
(recordings, ROS 2 bags, topic maps, live camera configurations, pushed frames) and every
number of every format are fuzzed by tests/app/recording/test_fuzz_streams.py. The tests are
deterministic; cases per test are in ``fuzz_support.EXAMPLES``, and the cases each test ran
are printed at the end of the module (``pytest -q tests/app/storage/test_fuzz_files.py``; add
``--hypothesis-show-statistics`` for hypothesis' own statistics).
"""

from __future__ import annotations

import copy
import os
import re
import shutil
import struct
from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import assume, example, given
from hypothesis import strategies as st

from tests.fuzz_support import (
    BOARD_DOC,
    KEYS,
    RIG,
    RIG_DOC,
    RIG_TEXT,
    YAML_BOMBS,
    _scratch,
    case_report,
    check_rig_file,
    fuzz,
    mutate_bytes,
    mutate_document,
    rejects,
    write_capture,
)
from tests.support import CAPTURE_BOARD as BOARD
from tests.support import capture_frames
from tests.support import small_capture_rig as capture_rig
from trifuse.app.recording import TopicMapError, load_topic_map
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.storage.capture import (
    BOARD_FILE,
    RIG_FILE,
    CaptureError,
    load_board_file,
    load_capture,
)
from trifuse.app.storage.capture_writer import write_board, write_view
from trifuse.app.storage.ground_truth import load_ground_truth
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.board import Board
from trifuse.calib.errors import RigError
from trifuse.calib.rig import rig_from_yaml

CASES: Counter[str] = Counter()
"""Cases each test actually ran (printed at the end of the module)."""
_report_cases = case_report(CASES)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A small valid capture: board, rig, ground truth, two views (one without distance)."""
    return write_capture(tmp_path_factory.mktemp("capture"))


# -- rig files (the rich rig of fuzz_support) -------------------------------------------------


def test_rig_text_round_trip_is_exact():
    """The base of the rig fuzzing is a valid, exactly round-tripping rig."""
    CASES["rig_round_trip"] += 1
    assert rig_from_yaml(RIG_TEXT) == RIG


@fuzz("rig_content")
@given(data=st.data())
def test_rig_file_with_mutated_content(tmp_path_factory, data):
    """Keys deleted, values replaced by junk, keys added: RigError naming the file."""
    CASES["rig_content"] += 1
    doc = mutate_document(RIG_DOC, data)
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "rig.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False, allow_unicode=True), encoding="utf-8")
    check_rig_file(path)
    shutil.rmtree(d)


@fuzz("rig_bytes")
@given(data=st.data())
@example(data=None)  # the unchanged file loads
def test_rig_file_with_damaged_bytes(tmp_path_factory, data):
    """Truncated text, flipped / inserted / overwritten bytes, random bytes."""
    CASES["rig_bytes"] += 1
    raw = RIG_TEXT.encode() if data is None else mutate_bytes(RIG_TEXT.encode(), data)
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "rig.yaml"
    path.write_bytes(raw)
    rig = check_rig_file(path)
    if data is None:
        assert rig == RIG
    shutil.rmtree(d)


def _renamed(doc: dict, old: str, new: Any) -> dict:
    """The rig document with sensor ``old`` called ``new`` everywhere (key, reference, eyes)."""
    doc = copy.deepcopy(doc)
    doc["sensors"] = {(new if k == old else k): v for k, v in doc["sensors"].items()}
    if doc["reference"] == old:
        doc["reference"] = new
    for eye in doc["eyes"].values():
        for role, sensor in eye.items():
            if sensor == old:
                eye[role] = new
    return doc


@fuzz("rig_names")
@given(
    old=st.sampled_from(list(RIG_DOC["sensors"])),
    new=KEYS | st.text(st.characters(codec="ascii"), min_size=1, max_size=10),
)
def test_rig_sensor_names(tmp_path_factory, old, new):
    """A sensor renamed consistently: accepted exactly when the name is a file name as the
    format says (letters, digits, '.', '_', '-', not ending in '_distance')."""
    CASES["rig_names"] += 1
    assume(str(new) == old or str(new) not in RIG_DOC["sensors"])  # a mapping has no twins
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "rig.yaml"
    path.write_text(yaml.safe_dump(_renamed(RIG_DOC, old, new), sort_keys=False))
    rig = check_rig_file(path)
    name = str(new)
    valid = re.fullmatch(r"[A-Za-z0-9._-]+", name) and not name.endswith("_distance")
    odd_reference = old == RIG_DOC["reference"] and not isinstance(new, str)  # a number
    assert (rig is not None) == bool(valid and not odd_reference), (name, rig)
    shutil.rmtree(d)


@pytest.mark.parametrize("bomb", YAML_BOMBS, ids=range(len(YAML_BOMBS)))
def test_rig_file_yaml_bombs(tmp_path, bomb):
    """Deep nesting and self-referential / exponentially shared aliases, as the whole file
    and inside an optional block that takes any plain YAML."""
    CASES["rig_yaml_bombs"] += 1
    path = tmp_path / "rig.yaml"
    path.write_text(bomb)
    assert check_rig_file(path) is None
    # inside ccd_left's uncertainty block
    doc_text = yaml.safe_dump(RIG_DOC, sort_keys=False)
    marker = "    uncertainty:\n"
    assert marker in doc_text
    lines = "\n".join("      " + line for line in bomb.splitlines())
    path = tmp_path / "rig2.yaml"
    path.write_text(doc_text.replace(marker, f"{marker}      bomb:\n{lines}\n", 1))
    assert check_rig_file(path) is None


def test_rig_file_missing_unreadable_and_not_utf8(tmp_path):
    CASES["rig_paths"] += 1
    for path in (tmp_path / "nope.yaml", tmp_path):
        _, err = rejects(lambda p=path: load_rig(p), RigError)
        assert err is not None and str(path) in str(err)
    path = tmp_path / "latin1.yaml"
    path.write_bytes(RIG_TEXT.replace("tof", "t\xf6f").encode("latin-1"))
    assert check_rig_file(path) is None


@fuzz("rig_save")
@given(data=st.data())
def test_refused_rig_save_leaves_no_file(tmp_path_factory, data):
    """save_rig onto an existing file (overwrite=False) is refused and leaves the directory
    as it was: the old file intact, no temporary file."""
    CASES["rig_save"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    old = data.draw(st.binary(max_size=50), label="existing content")
    (d / "rig.yaml").write_bytes(old)
    before = sorted(os.listdir(d))
    _, err = rejects(lambda: save_rig(d / "rig.yaml", RIG), FileExistsError)
    assert err is not None and "rig.yaml" in str(err)
    assert sorted(os.listdir(d)) == before and (d / "rig.yaml").read_bytes() == old
    shutil.rmtree(d)


# -- board files ------------------------------------------------------------------------------


@fuzz("board")
@given(data=st.data(), as_bytes=st.booleans())
def test_board_file_fuzzed(tmp_path_factory, data, as_bytes):
    """Mutated content or damaged bytes: CaptureError naming the file; an accepted board is
    a sane checkerboard."""
    CASES["board"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / BOARD_FILE
    if as_bytes:
        text = yaml.safe_dump(BOARD_DOC, sort_keys=False).encode()
        path.write_bytes(mutate_bytes(text, data))
    else:
        path.write_text(yaml.safe_dump(mutate_document(BOARD_DOC, data), allow_unicode=True))
    board, err = rejects(lambda: load_board_file(path), CaptureError)
    if err is not None:
        assert str(path) in str(err), err
    else:
        assert isinstance(board, Board)
        assert board.cols >= 2 and board.rows >= 2
        assert isinstance(board.square_size_m, float)
        assert np.isfinite(board.square_size_m) and board.square_size_m > 0
    shutil.rmtree(d)


@pytest.mark.parametrize("bomb", YAML_BOMBS, ids=range(len(YAML_BOMBS)))
def test_board_and_topic_map_yaml_bombs(tmp_path, bomb):
    CASES["board_topic_map_yaml_bombs"] += 1
    path = tmp_path / BOARD_FILE
    path.write_text(bomb)
    _, err = rejects(lambda: load_board_file(path), CaptureError)
    assert err is not None and str(path) in str(err)
    path = tmp_path / "topics.yaml"
    path.write_text(bomb)
    _, err = rejects(lambda: load_topic_map(path), TopicMapError)
    assert err is not None and str(path) in str(err)


# -- capture directories ----------------------------------------------------------------------


IMAGE_FILES = [
    "0001/ccd_left.png",
    "0001/thermal_left.png",
    "0001/tof.png",
    "0001/tof_distance.png",
    "0002/ccd_left.png",
    "0002/tof.png",
]
SIZES = {s.name: s.image_size for s in capture_rig().sensors.values()}


@st.composite
def encoded_images(draw, size: tuple[int, int] | None = None) -> bytes:
    """A PNG or JPEG of any size (or ``size``), bit depth and channel count."""
    if size is None or draw(st.booleans()):
        size = (draw(st.integers(1, 70)), draw(st.integers(1, 70)))
    w, h = size
    fmt = draw(st.sampled_from([".png", ".jpg"]))
    channels = draw(st.sampled_from([1, 3, 4] if fmt == ".png" else [1, 3]))
    dtype = draw(st.sampled_from([np.uint8, np.uint16] if fmt == ".png" else [np.uint8]))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    shape = (h, w) if channels == 1 else (h, w, channels)
    top = 256 if dtype == np.uint8 else 65536
    if draw(st.booleans()):  # grey in 3 channels, as a thermal "false colour" check sees it
        grey = rng.integers(0, top, (h, w)).astype(dtype)
        image = grey if channels == 1 else np.repeat(grey[:, :, None], channels, axis=2)
    else:
        image = rng.integers(0, top, shape).astype(dtype)
    ok, buf = cv2.imencode(fmt, image)
    assert ok
    return buf.tobytes()


def _png_with_header(width: int, height: int, depth: int, colour: int) -> bytes:
    """A PNG whose IHDR claims any size (its data is a token)."""
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body)
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


HUGE_PNG_HEADERS = st.builds(
    lambda size, depth, colour: _png_with_header(*size, depth, colour),
    st.sampled_from(
        [
            (40_000, 40_000),  # within libpng's limits, beyond OpenCV's 2^30 pixels
            (100_000, 100_000),
            (1_000_000, 2_000),
            (65_535, 65_535),
            (2**31 - 1, 2**31 - 1),  # beyond libpng's limits
            (1, 2**32 - 1),
            (0, 5),
            (7, 1),
        ]
    ),
    st.sampled_from([8, 16, 1, 3]),
    st.sampled_from([0, 2, 6, 3, 4, 5]),
)
"""PNG files whose header claims a huge (or zero) size; the data is a token."""


def _mutate_capture(d: Path, data: st.DataObject) -> None:
    """Without rig.yaml (half of the cases: modalities then come from the names, sizes
    are not checked against a rig), one to three changes to the files."""
    if data.draw(st.booleans(), label="drop rig.yaml"):
        (d / RIG_FILE).unlink()
    for _ in range(data.draw(st.integers(1, 3), label="changes")):
        op = data.draw(
            st.sampled_from(
                [
                    "delete",
                    "damage image",
                    "other image",
                    "huge header",
                    "yaml bytes",
                    "yaml content",
                    "add file",
                    "add folder",
                ]
            ),
            label="capture op",
        )
        if op in ("delete", "damage image", "other image", "huge header"):
            rel = data.draw(st.sampled_from([*IMAGE_FILES, RIG_FILE, BOARD_FILE]), label="file")
            path = d / rel
            if not path.exists():
                continue
            if op == "delete":
                path.unlink()
            elif op == "damage image":
                path.write_bytes(mutate_bytes(path.read_bytes(), data, header=8))
            elif op == "other image":
                sensor = path.stem.removesuffix("_distance")
                path.write_bytes(data.draw(encoded_images(SIZES.get(sensor)), label="image"))
            else:
                path.write_bytes(data.draw(HUGE_PNG_HEADERS, label="huge png"))
        elif op in ("yaml bytes", "yaml content"):
            name = data.draw(
                st.sampled_from([RIG_FILE, BOARD_FILE, "ground_truth.yaml"]), label="yaml"
            )
            path = d / name
            if not path.is_file():
                continue
            if op == "yaml bytes":
                path.write_bytes(mutate_bytes(path.read_bytes(), data))
            else:
                try:
                    doc = yaml.safe_load(path.read_text())
                except (ValueError, yaml.YAMLError):  # damaged by an earlier change
                    continue
                text = yaml.safe_dump(mutate_document(doc, data), allow_unicode=True)
                path.write_text(text)
        elif op == "add file":
            folder = data.draw(st.sampled_from(["0001", "0002", "."]), label="folder")
            stem = data.draw(
                st.sampled_from(["ccd_right", "tof", "tof_distance", "thermal_left", "x", "_"])
                | st.text(st.characters(codec="ascii", exclude_characters="/\0."), max_size=8),
                label="stem",
            )
            suffix = data.draw(st.sampled_from([".png", ".jpg", ".jpeg", ".PNG", ".txt"]))
            target = d / folder / f"{stem}{suffix}"
            if target.exists() or target.name.startswith("."):
                continue
            content = data.draw(
                encoded_images() | st.binary(max_size=64) | HUGE_PNG_HEADERS, label="content"
            )
            target.write_bytes(content)
        else:
            name = data.draw(st.sampled_from(["0003", "zz", "ccd_left.png", "0001/sub"]))
            (d / name).mkdir(exist_ok=True)


def check_capture(d: Path) -> None:
    """Index (lazily, then verifying) and decode every view of ``d``: CaptureError (RigError
    for rig.yaml) naming a file of ``d``, or frames of the documented types (and the rig's
    sizes); then the ground truth likewise."""
    for verify in (False, True):
        cap, err = rejects(lambda v=verify: load_capture(d, verify=v), (CaptureError, RigError))
        if err is not None:
            assert str(d) in str(err), err
            continue
        for view in cap.views:
            for sensor in view.sensors:
                frame, err = rejects(lambda v=view, s=sensor: v.frame(s), CaptureError)
                if err is not None:
                    assert str(d) in str(err), err
                    continue
                modality = cap.modalities[sensor]
                if modality == "color":
                    assert frame.image.dtype == np.uint8 and frame.image.ndim == 3
                else:
                    assert frame.image.dtype == np.float32 and frame.image.ndim == 2
                if frame.distance_m is not None:
                    assert frame.distance_m.shape == frame.image.shape
                if cap.rig is not None:
                    h, w = frame.image.shape[:2]
                    assert (w, h) == cap.rig[sensor].image_size
    gt, err = rejects(lambda: load_ground_truth(d), (CaptureError, RigError))
    if err is not None:
        assert str(d) in str(err), err
    else:
        for T in gt.T_rig_board.values():
            assert T.shape == (4, 4) and np.all(np.isfinite(T))


@fuzz("capture_image")
@given(
    data=st.data(),
    rel=st.sampled_from(IMAGE_FILES),
    with_rig=st.booleans(),
    how=st.sampled_from(["huge header", "other image", "damaged"]),
)
def test_capture_image_swapped(tmp_path_factory, capture_dir, data, rel, with_rig, how):
    """One image replaced by a header claiming a huge size, an image of another size /
    depth / channel count / format, or its own bytes damaged; with and without rig.yaml."""
    CASES["capture_image"] += 1
    d = _scratch(tmp_path_factory.getbasetemp()) / "cap"
    shutil.copytree(capture_dir, d)
    if not with_rig:
        (d / RIG_FILE).unlink()
    path = d / rel
    if how == "huge header":
        path.write_bytes(data.draw(HUGE_PNG_HEADERS, label="huge png"))
    elif how == "other image":
        sensor = path.stem.removesuffix("_distance")
        path.write_bytes(data.draw(encoded_images(SIZES[sensor]), label="image"))
    else:
        path.write_bytes(mutate_bytes(path.read_bytes(), data, header=8))
    check_capture(d)
    shutil.rmtree(d.parent)


@fuzz("capture")
@given(data=st.data())
def test_capture_directory_fuzzed(tmp_path_factory, capture_dir, data):
    """Images deleted, damaged, swapped for other sizes / depths / channels or for headers
    claiming huge sizes; YAML damaged; files and folders added (several at once)."""
    CASES["capture"] += 1
    d = _scratch(tmp_path_factory.getbasetemp()) / "cap"
    shutil.copytree(capture_dir, d)
    _mutate_capture(d, data)
    check_capture(d)
    shutil.rmtree(d.parent)


@fuzz("ground_truth")
@given(data=st.data())
def test_ground_truth_file_with_mutated_content(tmp_path_factory, capture_dir, data):
    CASES["ground_truth"] += 1
    d = _scratch(tmp_path_factory.getbasetemp()) / "cap"
    shutil.copytree(capture_dir, d)
    path = d / "ground_truth.yaml"
    doc = mutate_document(yaml.safe_load(path.read_text()), data)
    path.write_text(yaml.safe_dump(doc, allow_unicode=True))
    gt, err = rejects(lambda: load_ground_truth(d), (CaptureError, RigError))
    if err is not None:
        assert str(d) in str(err), err
    else:
        for T in gt.T_rig_board.values():
            assert T.shape == (4, 4) and np.all(np.isfinite(T))
    shutil.rmtree(d.parent)


@pytest.mark.parametrize("name", ["a\0b", "..", "", "missing.yaml", "board.yaml", "0001"])
def test_ground_truth_names_an_odd_rig_file(tmp_path, capture_dir, name):
    CASES["ground_truth_rig_names"] += 1
    d = tmp_path / "cap"
    shutil.copytree(capture_dir, d)
    path = d / "ground_truth.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["rig"] = name
    path.write_text(yaml.safe_dump(doc))
    _, err = rejects(lambda: load_ground_truth(d), (CaptureError, RigError))
    assert err is not None and str(d) in str(err), err


@fuzz("write_view")
@given(data=st.data())
def test_refused_view_write_leaves_nothing(tmp_path_factory, data):
    """A view whose frames do not fit the rig (sizes, dtypes, channels, sensors) is refused
    before anything appears: no view folder, no hidden staging folder."""
    CASES["write_view"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    rig = capture_rig()
    write_board(d, BOARD)
    before = sorted(os.listdir(d))
    frames = dict(capture_frames().frames)
    sensor = data.draw(st.sampled_from([*frames, "ccd_right", "tof_distance"]), label="sensor")
    h, w = data.draw(st.integers(1, 70), label="h"), data.draw(st.integers(1, 70), label="w")
    shape = data.draw(st.sampled_from([(h, w), (h, w, 3), (h, w, 4), (h,), (h, w, 1)]))
    dtype = data.draw(st.sampled_from([np.uint8, np.uint16, np.float32, np.float64, bool]))
    image = np.zeros(shape, dtype)
    distance = data.draw(st.sampled_from([None, "same", "other"]), label="distance")
    dist = {None: None, "same": np.ones(image.shape[:2], np.float32), "other": np.ones((3, 3))}
    frames[sensor] = Frame(sensor, 1, image, dist[distance])
    try:
        write_view(d, "0001", FrameSet(1, frames), rig)
    except CaptureError as exc:
        assert str(exc)
        assert sorted(os.listdir(d)) == before, os.listdir(d)
    else:  # it fitted after all: a complete view
        assert len(load_capture(d, verify=True).views) == 1
    shutil.rmtree(d)
