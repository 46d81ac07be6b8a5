"""Property-based tests of the stream loaders (issue 8, "Bad input, everywhere"): recordings
(MCAP), ROS 2 bags, topic maps, live camera configurations and pushed frames; and every
number of every format (rig, board, topic map, ground truth, push header, cameras) replaced
by huge / negative / NaN / inf numbers and other junk.

The contract, the strategies and the mutators are in tests/fuzz_support.py; the rig, board,
capture and ground-truth files are fuzzed by tests/app/storage/test_fuzz_files.py. The tests are
deterministic; cases per test are in ``fuzz_support.EXAMPLES``, and the cases each test ran
are printed at the end of the module (``pytest -q tests/app/recording/test_fuzz_streams.py``; add
``--hypothesis-show-statistics`` for hypothesis' own statistics).
"""

from __future__ import annotations

import copy
import json
import shutil
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import example, given
from hypothesis import strategies as st

from tests.fuzz_support import (
    BOARD_DOC,
    JUNK,
    RIG_DOC,
    YAML_BOMBS,
    _paths,
    _scratch,
    case_report,
    check_rig_file,
    fuzz,
    mutate_bytes,
    mutate_document,
    rejects,
    write_capture,
)
from tests.ros2_support import TOPIC_MAP, make_bag
from tests.support import CAPTURE_BOARD as BOARD
from tests.support import small_rig as recording_rig
from tests.support import synth_frame, synth_frames, write_recording
from trifuse.app.recording import RecordingError, ReplaySource, TopicMapError, load_topic_map
from trifuse.app.recording.ros2 import Ros2BagSource
from trifuse.app.recording.topicmap import topic_map_from_yaml
from trifuse.app.sources.camera import CameraError, load_cameras_config
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.encode import encode_frame
from trifuse.app.sources.push.protocol import PREFIX, PushError
from trifuse.app.sources.push.source import PushSource
from trifuse.app.storage.capture import BOARD_FILE, CaptureError, load_board_file
from trifuse.app.storage.ground_truth import load_ground_truth
from trifuse.calib.errors import RigError
from trifuse.calib.transforms import make_T, rotation_from_euler_deg

CASES: Counter[str] = Counter()
"""Cases each test actually ran (printed at the end of the module)."""
_report_cases = case_report(CASES)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A small valid capture: board, rig, ground truth, two views (one without distance);
    the base of the ground truth whose numbers are replaced."""
    return write_capture(tmp_path_factory.mktemp("capture"))


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
