"""Property-based tests of every file loader (issue 8, "Bad input, everywhere").

Each loader gets valid inputs made by the project's own writers, then mutated (keys
deleted, values replaced by junk, text truncated, bytes flipped, images swapped), and
fully random inputs. The contract: bad input raises the loader's documented error type
(a ``ValueError`` subclass: ``RigError``, ``CaptureError``, ``RecordingError``,
``TopicMapError``, ``PushError``) whose message names the file (or, for pushed frames, says
what is wrong); nothing else escapes (no KeyError, TypeError, OverflowError, RecursionError,
numpy or OpenCV errors ...); what is accepted is well-formed; a refused write leaves no file.

The tests are deterministic (``derandomize=True``, no example database). Cases per test
(``max_examples``) are in :data:`EXAMPLES`; each test counts the cases it ran and the counts
are printed at the end of the module (``pytest -q tests/test_fuzz_loaders.py``; add
``--hypothesis-show-statistics`` for hypothesis' own statistics).
"""

from __future__ import annotations

import copy
import json
import os
import re
import shutil
import struct
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from app.recording import RecordingError, ReplaySource, TopicMapError, load_topic_map
from app.recording.ros2 import Ros2BagSource
from app.recording.topicmap import topic_map_from_yaml
from app.sources.camera import CameraError, load_cameras_config
from app.sources.frames import Frame, FrameSet
from app.sources.push import PREFIX, PushError, PushSource, encode_frame
from app.sources.sim.head import default_rig
from app.storage.capture import (
    BOARD_FILE,
    RIG_FILE,
    CaptureError,
    load_board_file,
    load_capture,
    load_ground_truth,
    write_board,
    write_ground_truth,
    write_rig,
    write_view,
)
from app.storage.rigfile import load_rig, save_rig
from calib.board import Board
from calib.errors import RigError
from calib.range_correction import RangeCorrection, offset_grid_shape
from calib.rig import Rig, rig_from_yaml, rig_to_dict, rig_to_yaml
from calib.transforms import make_T, rotation_from_euler_deg
from tests.test_capture import BOARD
from tests.test_capture import make_frames as capture_frames
from tests.test_capture import small_rig as capture_rig
from tests.test_recording import small_rig as recording_rig
from tests.test_recording import synth_frame, synth_frames, write_recording
from tests.test_ros2_replay import TOPIC_MAP, make_bag

EXAMPLES = {
    "rig_content": 250,
    "rig_bytes": 200,
    "rig_names": 100,
    "rig_save": 50,
    "board": 300,
    "ground_truth": 150,
    "capture_image": 200,
    "capture": 200,
    "write_view": 100,
    "recording": 500,
    "ros2_bag": 300,
    "topic_map": 300,
    "cameras": 300,
    "push_random": 400,
    "push_header": 400,
    "push_payload": 300,
    "numbers": 150,
}
"""Cases (hypothesis ``max_examples``) per test."""

CASES: Counter[str] = Counter()
"""Cases each test actually ran (printed at the end of the module)."""


def fuzz(name: str) -> settings:
    """Deterministic settings with :data:`EXAMPLES` ``[name]`` cases."""
    return settings(
        max_examples=EXAMPLES[name],
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


@pytest.fixture(scope="module", autouse=True)
def _report_cases(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    lines = [f"  {name}: {n} cases" for name, n in sorted(CASES.items())]
    text = "\n".join(["", "fuzzed loaders (cases run per test):", *lines])
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    if reporter is None or capture is None:
        print(text)
        return
    with capture.global_and_fixture_disabled():
        reporter.write_line(text)


# -- strategies -------------------------------------------------------------------------------

SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.sampled_from([0, -1, 1, 2, 2**31, 2**63, 2**64, 10**400, -(10**400)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 5e-324]),
    st.text(max_size=12),
)
NASTY = st.sampled_from(
    [10**400, -(10**400), 2**64, -1, 0, float("nan"), float("inf"), 1e308, True, None, "", [], {}]
).map(copy.deepcopy)  # a fresh [] / {} each time: mutations must not change the constants
"""The values that most often break a loader, drawn often."""
JUNK = st.one_of(
    NASTY,
    st.recursive(
        SCALARS,
        lambda inner: (
            st.lists(inner, max_size=6)
            | st.dictionaries(st.text(max_size=6) | st.integers(-3, 3), inner, max_size=4)
        ),
        max_leaves=12,
    ),
    # lists of numbers of the wrong length or shape, as a size, distortion or pose would be
    st.lists(st.floats(-1e3, 1e3) | st.integers(-5, 2000), max_size=9),
    st.lists(st.lists(st.floats(-2, 2) | st.integers(-1, 1), min_size=3, max_size=5), max_size=5),
)
"""JSON-like junk: None, bools, huge / negative / NaN / inf numbers, strings, nested lists
and mappings, number lists of the wrong length."""


KEYS = st.one_of(
    st.sampled_from(["", "x_distance", "a/b", "../x", ".", "tof", "ccd_left", "null", "1"]),
    st.text(max_size=8),
    st.integers(),
)
"""Keys for a mapping: odd names, names that exist elsewhere, numbers."""


def _paths(node: Any, prefix: tuple = ()) -> Iterator[tuple]:
    """Every location in a nested dict / list document, the root included; of a long list
    only the first two items and the last (so that a grid of numbers does not drown the
    other fields)."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        indices = range(len(node)) if len(node) <= 4 else (0, 1, len(node) - 1)
        for i in indices:
            yield from _paths(node[i], (*prefix, i))


def _mutate_once(doc: Any, data: st.DataObject, junk: st.SearchStrategy = JUNK) -> Any:
    """Delete, replace or add one thing somewhere in ``doc`` (changed in place; returned).
    The depth is drawn first, so that the top levels are changed as often as the leaves."""
    by_depth: dict[int, list[tuple]] = {}
    for p in _paths(doc):
        by_depth.setdefault(len(p), []).append(p)
    depth = data.draw(st.sampled_from(sorted(by_depth)), label="depth")
    path = data.draw(st.sampled_from(by_depth[depth]), label="path")
    op = data.draw(st.sampled_from(["replace", "delete", "add", "rename"]), label="op")
    parent = None
    target = doc
    for key in path:
        parent, target = target, target[key]
    if op == "rename" and isinstance(target, dict) and target:
        old = data.draw(st.sampled_from(list(target)), label="renamed key")
        new_key = data.draw(KEYS, label="new name")
        target[new_key] = target.pop(old)
    elif op in ("add", "rename") and isinstance(target, dict):
        new_key = data.draw(KEYS, label="new key")
        target[new_key] = data.draw(junk, label="new value")
    elif op in ("add", "rename") and isinstance(target, list):
        at = data.draw(st.integers(0, len(target)), label="at")
        target.insert(at, data.draw(junk, label="item"))
    elif parent is None:  # the whole document
        return data.draw(junk, label="document")
    elif op == "delete":
        del parent[path[-1]]
    elif op == "replace":
        parent[path[-1]] = data.draw(junk, label="value")
    else:  # add beside a scalar: it becomes a list
        parent[path[-1]] = [target, data.draw(junk, label="second")]
    return doc


def mutate_document(doc: Any, data: st.DataObject, junk: st.SearchStrategy = JUNK) -> Any:
    """One to three structural mutations of a parsed YAML / JSON document, new values
    drawn from ``junk``."""
    doc = copy.deepcopy(doc)
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        doc = _mutate_once(doc, data, junk)
    return doc


def mutate_bytes(base: bytes, data: st.DataObject, *, header: int = 0) -> bytes:
    """Truncate, flip bytes, overwrite a range, insert bytes, or replace everything.

    ``header`` bytes at the start are left alone by flips (to get past a magic number
    more often; truncation and replacement still reach them).
    """
    op = data.draw(
        st.sampled_from(["truncate", "flip", "overwrite", "insert", "random", "flip+truncate"]),
        label="byte op",
    )
    out = bytearray(base)
    if op == "random":
        return data.draw(st.binary(max_size=300), label="random bytes")
    if op in ("flip", "flip+truncate"):
        lo = min(header, len(out) - 1)
        for _ in range(data.draw(st.integers(1, 4), label="flips")):
            i = data.draw(st.integers(lo, len(out) - 1), label="flip at")
            out[i] ^= data.draw(st.integers(1, 255), label="xor")
    if op == "overwrite":
        i = data.draw(st.integers(0, len(out) - 1), label="overwrite at")
        chunk = data.draw(st.binary(min_size=1, max_size=64), label="overwrite with")
        out[i : i + len(chunk)] = chunk
    if op == "insert":
        i = data.draw(st.integers(0, len(out)), label="insert at")
        out[i:i] = data.draw(st.binary(min_size=1, max_size=32), label="inserted")
    if op in ("truncate", "flip+truncate"):
        out = out[: data.draw(st.integers(0, len(out)), label="cut at")]
    return bytes(out)


def rejects(
    call: Callable[[], Any], errors: type[BaseException] | tuple[type[BaseException], ...]
) -> tuple[Any, BaseException | None]:
    """``(result, None)`` or ``(None, error)`` for the documented ``errors`` only; any other
    exception propagates and fails the test. An error must have a message."""
    try:
        return call(), None
    except errors as exc:
        assert str(exc).strip(), f"{type(exc).__name__} without a message"
        return None, exc


def _scratch(tmp_root: Path) -> Path:
    return Path(tempfile.mkdtemp(dir=tmp_root))


YAML_BOMBS = [
    "[" * 5000,  # unterminated and deep
    "[" * 3000 + "]" * 3000,  # deep but valid
    "{a: " * 3000 + "1" + "}" * 3000,
    "a: &x [*x]\n",  # a list that contains itself
    "&x {a: *x}\n",
    "\n".join(
        ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
        + [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
    ),  # "billion laughs": 10^9 strings through shared aliases
]
"""YAML that a parser or a validator walking the document can choke on."""


# -- rig files --------------------------------------------------------------------------------


def rich_rig() -> Rig:
    """The simulated head with every optional block (radiometry, range correction,
    uncertainty), so that their parsers are fuzzed too."""
    rig = default_rig()
    tof = rig["tof"]
    rows, cols = offset_grid_shape(*tof.image_size, 16)
    rc = RangeCorrection(
        image_size=tof.image_size,
        distance_start_m=0.9,
        distance_step_m=0.5,
        distance_coeffs_m=np.linspace(0.01, -0.01, 6),
        offset_step_px=16,
        offset_nodes_m=np.zeros((rows, cols)),
        amplitude_ref=1800.0,
        amplitude_log_range=(-1.0, 1.0),
        amplitude_coeffs_m=(0.001, -0.0005),
        fit={"views": 3, "residual_rms_mm": 7.0},
    )
    sensors = dict(rig.sensors)
    sensors["tof"] = replace(tof, range_correction=rc.to_dict())
    sensors["thermal_left"] = replace(
        sensors["thermal_left"], radiometry={"gain": 1.0, "balance_offset_k": -0.5}
    )
    sensors["ccd_left"] = replace(
        sensors["ccd_left"],
        uncertainty={"fx": 0.3, "distortion": [0.001, 0.002, 0.0, 0.0, 0.0], "rms_px": 0.2},
    )
    return Rig(sensors=sensors, reference=rig.reference, eyes=dict(rig.eyes))


RIG = rich_rig()
RIG_DOC = rig_to_dict(RIG)
RIG_TEXT = rig_to_yaml(RIG)


def check_rig_file(path: Path) -> Rig | None:
    """Load a rig file: a Rig, or RigError starting with the path; an accepted rig is
    well-formed and survives save -> load."""
    rig, err = rejects(lambda: load_rig(path), RigError)
    if err is not None:
        assert str(err).startswith(str(path)), err
        return None
    assert isinstance(rig, Rig) and rig.reference in rig.sensors
    for s in rig.sensors.values():
        assert re.fullmatch(r"[A-Za-z0-9._-]+", s.name) and not s.name.endswith("_distance")
        assert s.modality in ("color", "thermal", "tof")
        w, h = s.image_size
        assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0
        assert s.T_rig_sensor.shape == (4, 4) and np.all(np.isfinite(s.T_rig_sensor))
    again = path.with_name(path.name + ".again.yaml")
    save_rig(again, rig)
    assert load_rig(again).names == rig.names
    again.unlink()
    return rig


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

BOARD_DOC = {
    "pattern": "checkerboard",
    "inner_corners": [9, 6],
    "square_size_m": 0.06,
    "thermal_black_is_hot": True,
}


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


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A small valid capture: board, rig, ground truth, two views (one without distance)."""
    d = tmp_path_factory.mktemp("capture")
    rig = capture_rig()
    write_board(d, BOARD)
    write_rig(d, rig)
    frames = capture_frames()
    write_view(d, "0001", frames, rig)
    second = dict(frames.frames)
    second["tof"] = Frame("tof", 1, second["tof"].image)
    write_view(d, "0002", FrameSet(5, second), rig)
    pose = make_T(rotation_from_euler_deg(10, -5, 3), (0.1, 0.0, 1.2))
    write_ground_truth(d, rig, [("0001", pose), ("0002", pose)], BOARD)
    assert len(load_capture(d, verify=True)) == 2
    return d


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


# -- recordings (MCAP) ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A small recording of the five sensors (a path: hypothesis prints its arguments)."""
    rig = recording_rig()
    path = tmp_path_factory.mktemp("rec") / "rec.mcap"
    write_recording(path, rig, synth_frames(rig, 0.15, seed=1), chunk_size=16 * 1024)
    return path


def _replay(path: Path, on_damage: str) -> list[Frame]:
    with ReplaySource(path, realtime=False, on_damage=on_damage) as src:
        got = list(src.frames())
        assert src.sensors is not None
        return got


def test_undamaged_recording_and_bag_replay_completely(recording, ros2_bag):
    """The bases of the recording fuzzing replay in full."""
    CASES["recording_intact"] += 1
    assert len(_replay(recording, "raise")) > 20
    with Ros2BagSource(ros2_bag, topic_map_from_yaml(TOPIC_MAP), realtime=False) as src:
        assert len(list(src.frames())) >= 12


@fuzz("recording")
@given(data=st.data(), on_damage=st.sampled_from(["raise", "stop"]))
def test_recording_truncated_and_flipped(tmp_path_factory, recording, data, on_damage):
    """Opening and replaying a damaged recording raises RecordingError (RecordingDamaged)
    naming the file, or ends; every frame delivered has the documented types."""
    CASES["recording"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "rec.mcap"
    path.write_bytes(mutate_bytes(recording.read_bytes(), data, header=8))
    frames, err = rejects(lambda: _replay(path, on_damage), RecordingError)
    if err is not None:
        assert str(path) in str(err), err
    for f in frames or []:
        assert isinstance(f, Frame) and isinstance(f.image, np.ndarray)
        assert f.image.dtype in (np.uint8, np.float32)
    shutil.rmtree(d)


@pytest.fixture(scope="module")
def ros2_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bag") / "bag.mcap"
    make_bag(path, n=3, chunk_size=8 * 1024)
    return path


@fuzz("ros2_bag")
@given(data=st.data())
def test_ros2_bag_truncated_and_flipped(tmp_path_factory, ros2_bag, data):
    CASES["ros2_bag"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "bag.mcap"
    path.write_bytes(mutate_bytes(ros2_bag.read_bytes(), data, header=8))
    tmap = topic_map_from_yaml(TOPIC_MAP)

    def replay() -> list[Frame]:
        with Ros2BagSource(path, tmap, realtime=False) as src:
            return list(src.frames())

    _, err = rejects(replay, RecordingError)
    if err is not None:
        assert str(path) in str(err), err
    shutil.rmtree(d)


TOPIC_MAP_DOC = yaml.safe_load(TOPIC_MAP)


@fuzz("topic_map")
@given(data=st.data(), as_bytes=st.booleans())
def test_topic_map_fuzzed(tmp_path_factory, data, as_bytes):
    """Mutated topic maps: TopicMapError naming the file, or a consistent map."""
    CASES["topic_map"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "topics.yaml"
    if as_bytes:
        path.write_bytes(mutate_bytes(TOPIC_MAP.encode(), data))
    else:
        doc = mutate_document(TOPIC_MAP_DOC, data)
        path.write_text(yaml.safe_dump(doc, allow_unicode=True))
    tmap, err = rejects(lambda: load_topic_map(path), TopicMapError)
    if err is not None:
        assert str(path) in str(err), err
    else:
        for topic, spec in tmap.topics.items():
            assert topic.startswith("/") and spec.sensor in tmap.modalities
            assert np.isfinite(spec.scale) and spec.scale != 0 and np.isfinite(spec.offset)
    shutil.rmtree(d)


# -- live camera configurations ---------------------------------------------------------------

CAMERAS_DOC = {
    "format": "trifuse-cameras/1",
    "open_timeout_s": 10,
    "stall_timeout_s": 2.5,
    "sensors": {
        "ccd_left": {
            "device": 0,
            "modality": "color",
            "width": 1280,
            "height": 960,
            "fps": 30,
            "fourcc": "MJPG",
            "backend": "v4l2",
        },
        "ccd_right": {"device": "/dev/video2", "modality": "color"},
        "thermal_left": {"device": "/dev/video4", "modality": "thermal", "scale": 0.01},
        "thermal_right": {
            "device": "thermal_right/frame_%04d.png",
            "max_rate_hz": 27,
            "loop": True,
        },
    },
}


def check_cameras_file(path: Path) -> None:
    """CameraError naming the file, or a configuration of sane values."""
    cfg, err = rejects(lambda: load_cameras_config(path), CameraError)
    if err is not None:
        assert str(path) in str(err), err
        return
    for c in cfg.sensors:
        assert isinstance(c.sensor, str) and c.modality in ("color", "thermal")
        assert np.isfinite(c.scale) and c.scale != 0 and np.isfinite(c.offset)


@fuzz("cameras")
@given(data=st.data(), as_bytes=st.booleans())
def test_camera_config_fuzzed(tmp_path_factory, data, as_bytes):
    """The live camera configuration (trifuse-cameras/1): mutated content, damaged bytes."""
    CASES["cameras"] += 1
    d = _scratch(tmp_path_factory.getbasetemp())
    path = d / "cameras.yaml"
    if as_bytes:
        path.write_bytes(mutate_bytes(yaml.safe_dump(CAMERAS_DOC).encode(), data))
    else:
        path.write_text(yaml.safe_dump(mutate_document(CAMERAS_DOC, data), allow_unicode=True))
    check_cameras_file(path)
    shutil.rmtree(d)


@pytest.mark.parametrize("bomb", YAML_BOMBS, ids=range(len(YAML_BOMBS)))
def test_camera_config_yaml_bombs(tmp_path, bomb):
    CASES["cameras_yaml_bombs"] += 1
    path = tmp_path / "cameras.yaml"
    path.write_text(bomb)
    _, err = rejects(lambda: load_cameras_config(path), CameraError)
    assert err is not None and str(path) in str(err)


# -- pushed frames ----------------------------------------------------------------------------

PUSH_RIG = recording_rig()
LIMIT = 1 << 20


def _push_messages() -> list[bytes]:
    """Valid messages of every sensor and encoding of the small rig."""
    rng = np.random.default_rng(7)
    out = []
    stamp = 1_000
    for name, s in PUSH_RIG.sensors.items():
        frame = synth_frame(PUSH_RIG, name, stamp, rng)
        if s.modality == "color":
            for enc in ("jpeg", "png", "raw8"):
                out.append(encode_frame(frame, "color", color_encoding=enc))
        else:
            for enc in ("png16", "raw16", "raw32f"):
                out.append(encode_frame(frame, s.modality, value_encoding=enc))
        stamp += 1
    return out


PUSH_MESSAGES = _push_messages()


def _split(message: bytes) -> tuple[dict, bytes]:
    _magic, hlen = PREFIX.unpack_from(message, 0)
    return json.loads(message[PREFIX.size : PREFIX.size + hlen]), message[PREFIX.size + hlen :]


def _frame_message(header: Any, payload: bytes, hlen_delta: int = 0) -> bytes:
    head = json.dumps(header).encode()
    return PREFIX.pack(b"TFP1", max(0, len(head) + hlen_delta)) + head + payload


def check_push(message: bytes) -> None:
    """Accept or reject one message; a rejection raises PushError, counts one rejection and
    changes no sensor's frame; an accepted frame has the rig's size and the types of its
    modality and replaces its own sensor's frame only."""
    source = PushSource(PUSH_RIG, max_message_bytes=LIMIT)
    for m in PUSH_MESSAGES[::3]:  # one frame of every sensor waiting
        source.accept(m)
    before = {s: source.peek(s) for s in source.sensors}
    result, err = rejects(lambda: source.accept(message, {}), PushError)
    after = {s: source.peek(s) for s in source.sensors}
    if err is not None:
        assert source.stats()["rejected"] == 1
        assert all(after[s] is before[s] for s in source.sensors)
        return
    _header, frame, replaced = result
    assert replaced
    sensor = PUSH_RIG[frame.sensor]
    assert after[frame.sensor] is frame
    assert all(after[s] is before[s] for s in source.sensors if s != frame.sensor)
    h, w = frame.image.shape[:2]
    assert (w, h) == sensor.image_size
    if sensor.modality == "color":
        assert frame.image.dtype == np.uint8 and frame.image.shape[2] == 3
    else:
        assert frame.image.dtype == np.float32 and frame.image.ndim == 2
    if frame.distance_m is not None:
        assert frame.distance_m.shape == frame.image.shape


@fuzz("push_random")
@given(data=st.binary(max_size=200) | st.builds(lambda b: b"TFP1" + b, st.binary(max_size=200)))
@example(data=b"")
@example(data=PREFIX.pack(b"TFP1", 5) + b"[[[[[")
@example(data=PREFIX.pack(b"TFP1", 60000) + b"[" * 60000)
@example(data=PREFIX.pack(b"TFP1", 5006) + b'{"a":' + b"1" * 5000 + b"}")  # int too long
def test_push_random_bytes(data):
    CASES["push_random"] += 1
    check_push(data)


HEADER_JUNK = st.one_of(
    JUNK,
    st.sampled_from([0, -1, 2**32, 10**30, 16384, 16385, 1 << 25, "png16", "image", "distance"]),
    st.sampled_from(["jpeg", "png", "raw8", "raw16", "raw32f", "bmp", ""]),
)


@fuzz("push_header")
@given(
    index=st.integers(0, len(PUSH_MESSAGES) - 1),
    data=st.data(),
    hlen_delta=st.sampled_from([0, 0, 0, -1, 1, -8, 100]),
)
def test_push_mutated_headers(index, data, hlen_delta):
    """Valid messages whose JSON header has keys deleted, junk values (unknown encodings,
    wrong / huge sizes, wrong lengths, NaN scales ...) or whose header length is off."""
    CASES["push_header"] += 1
    header, payload = _split(PUSH_MESSAGES[index])
    header = mutate_document(header, data, HEADER_JUNK)
    check_push(_frame_message(header, payload, hlen_delta))


@fuzz("push_payload")
@given(index=st.integers(0, len(PUSH_MESSAGES) - 1), data=st.data())
def test_push_damaged_payload(index, data):
    """Payload bytes flipped, truncated, overwritten (the header kept, or its lengths made
    to match the damaged payload)."""
    CASES["push_payload"] += 1
    header, payload = _split(PUSH_MESSAGES[index])
    damaged = mutate_bytes(payload, data)
    if data.draw(st.booleans(), label="fix lengths") and len(header["parts"]) == 1:
        header["parts"][0]["length"] = len(damaged)
    check_push(_frame_message(header, damaged))


def test_valid_push_messages_are_accepted():
    CASES["push_valid"] += 1
    for m in PUSH_MESSAGES:
        check_push(m)


def test_rig_text_round_trip_is_exact():
    """The base of the rig fuzzing is a valid, exactly round-tripping rig."""
    CASES["rig_round_trip"] += 1
    assert rig_from_yaml(RIG_TEXT) == RIG


# -- every number of every format -------------------------------------------------------------

NUMBERS = st.one_of(
    st.sampled_from(
        [10**400, -(10**400), 2**64, 2**63, 2**31, -1, 0, 1, 1e308, -1e308, 5e-324, -0.0]
    ),
    st.sampled_from([float("nan"), float("inf"), -float("inf"), True, False, None, "1", "x"]),
    st.sampled_from([[], [1], [1.5, 2.5], {}, {"a": 1}]).map(copy.deepcopy),
    st.integers(),
    st.floats(),
)
"""What a number of a file or header may be replaced by."""


def _numeric_paths(doc: Any) -> list[tuple]:
    return [p for p in _paths(doc) if isinstance(_at(doc, p), int | float)]


def _at(doc: Any, path: tuple) -> Any:
    for key in path:
        doc = doc[key]
    return doc


def _check_rig_doc(doc: Any, d: Path, capture_dir: Path) -> None:
    path = d / "rig.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    check_rig_file(path)


def _check_board_doc(doc: Any, d: Path, capture_dir: Path) -> None:
    path = d / BOARD_FILE
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    _, err = rejects(lambda: load_board_file(path), CaptureError)
    assert err is None or str(path) in str(err), err


def _check_topic_map_doc(doc: Any, d: Path, capture_dir: Path) -> None:
    path = d / "topics.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    _, err = rejects(lambda: load_topic_map(path), TopicMapError)
    assert err is None or str(path) in str(err), err


def _check_ground_truth_doc(doc: Any, d: Path, capture_dir: Path) -> None:
    cap = d / "cap"
    shutil.copytree(capture_dir, cap)
    (cap / "ground_truth.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    _, err = rejects(lambda: load_ground_truth(cap), (CaptureError, RigError))
    assert err is None or str(cap) in str(err), err


def _check_push_doc(doc: Any, d: Path, capture_dir: Path) -> None:
    check_push(_frame_message(doc, PUSH_PAYLOAD))


def _check_cameras_doc(doc: Any, d: Path, capture_dir: Path) -> None:
    path = d / "cameras.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    check_cameras_file(path)


def _ground_truth_doc() -> dict:
    pose = make_T(rotation_from_euler_deg(10, -5, 3), (0.1, 0.0, 1.2)).tolist()
    return {
        "format": "trifuse-ground-truth/1",
        "rig": "ground_truth_rig.yaml",
        "board": BOARD.to_dict(),
        "views": {"0001": {"T_rig_board": pose}},
    }


PUSH_HEADER, PUSH_PAYLOAD = _split(PUSH_MESSAGES[1])  # TOF amplitude + distance, raw16
NUMERIC_DOCS: dict[str, tuple[Any, Callable[[Any, Path, Path], None]]] = {
    "rig": (RIG_DOC, _check_rig_doc),
    "board": (BOARD_DOC, _check_board_doc),
    "topic_map": (TOPIC_MAP_DOC, _check_topic_map_doc),
    "ground_truth": (_ground_truth_doc(), _check_ground_truth_doc),
    "push_header": (PUSH_HEADER, _check_push_doc),
    "cameras": (CAMERAS_DOC, _check_cameras_doc),
}


@pytest.mark.parametrize("kind", list(NUMERIC_DOCS))
@fuzz("numbers")
@given(data=st.data())
def test_every_number_replaced(tmp_path_factory, capture_dir, kind, data):
    """One or two numbers of a valid document (any of them: sizes, intrinsics, poses,
    corrections, scales, stamps, lengths) replaced by huge / negative / NaN / inf numbers,
    bools, strings, lists."""
    CASES[f"numbers[{kind}]"] += 1
    doc, check = NUMERIC_DOCS[kind]
    doc = copy.deepcopy(doc)
    for _ in range(data.draw(st.integers(1, 2), label="replacements")):
        path = data.draw(st.sampled_from(_numeric_paths(doc) or [()]), label="path")
        if not path:
            break
        _at(doc, path[:-1])[path[-1]] = data.draw(NUMBERS, label="number")
    d = _scratch(tmp_path_factory.getbasetemp())
    check(doc, d, capture_dir)
    shutil.rmtree(d)
