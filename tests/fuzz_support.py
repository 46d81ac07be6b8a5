"""Shared machinery of the property-based tests of every file loader (issue 8, "Bad input,
everywhere"): tests/app/storage/test_fuzz_files.py (rig, board and ground-truth files, capture
directories) and tests/app/recording/test_fuzz_streams.py (recordings, ROS 2 bags, topic maps,
live camera configurations, pushed frames, and every number of every format).

Each loader gets valid inputs made by the project's own writers, then mutated (keys
deleted, values replaced by junk, text truncated, bytes flipped, images swapped), and
fully random inputs. The contract: bad input raises the loader's documented error type
(a ``ValueError`` subclass: ``RigError``, ``CaptureError``, ``RecordingError``,
``TopicMapError``, ``PushError``) whose message names the file (or, for pushed frames, says
what is wrong); nothing else escapes (no KeyError, TypeError, OverflowError, RecursionError,
numpy or OpenCV errors ...); what is accepted is well-formed; a refused write leaves no file.

The tests are deterministic (``derandomize=True``, no example database). Cases per test
(``max_examples``) are in :data:`EXAMPLES`; each test counts the cases it ran in its module's
``CASES`` and the counts are printed at the end of each module by the fixture that
:func:`case_report` makes (``pytest -q tests/app/storage/test_fuzz_files.py
tests/app/recording/test_fuzz_streams.py``; add ``--hypothesis-show-statistics`` for
hypothesis' own statistics).

Here: :data:`EXAMPLES`, :func:`fuzz`, :func:`case_report`, the strategies (:data:`JUNK` ...),
the mutators (:func:`mutate_document`, :func:`mutate_bytes`), :func:`rejects`,
:data:`YAML_BOMBS`, and the bases both modules fuzz: the rich rig (:data:`RIG`,
:func:`check_rig_file`), the board document and the capture directory (a test module
makes its ``capture_dir`` fixture with :func:`write_capture`).
"""

from __future__ import annotations

import copy
import re
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from tests.support import CAPTURE_BOARD as BOARD
from tests.support import capture_frames
from tests.support import small_capture_rig as capture_rig
from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.storage.capture import load_capture
from trifuse.app.storage.capture_writer import write_board, write_rig, write_view
from trifuse.app.storage.ground_truth import write_ground_truth
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.errors import RigError
from trifuse.calib.radiometry import Radiometry
from trifuse.calib.range_correction import RangeCorrection, offset_grid_shape
from trifuse.calib.rig import Rig, rig_to_dict, rig_to_yaml
from trifuse.calib.transforms import make_T, rotation_from_euler_deg

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


def fuzz(name: str) -> settings:
    """Deterministic settings with :data:`EXAMPLES` ``[name]`` cases."""
    return settings(
        max_examples=EXAMPLES[name],
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


def case_report(cases: Counter[str]) -> Callable[..., Any]:
    """A module-scoped autouse fixture that prints ``cases`` (the cases each test of the
    module ran) at the end of the module. A test module has its own counter and report::

        CASES: Counter[str] = Counter()
        _report_cases = case_report(CASES)
    """

    @pytest.fixture(scope="module", autouse=True, name="_report_cases")
    def _report_cases(request: pytest.FixtureRequest) -> Iterator[None]:
        yield
        lines = [f"  {name}: {n} cases" for name, n in sorted(cases.items())]
        title = f"fuzzed loaders, {request.path.name} (cases run per test):"
        text = "\n".join(["", title, *lines])
        reporter = request.config.pluginmanager.get_plugin("terminalreporter")
        capture = request.config.pluginmanager.get_plugin("capturemanager")
        if reporter is None or capture is None:
            print(text)
            return
        with capture.global_and_fixture_disabled():
            reporter.write_line(text)

    return _report_cases


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


# -- the bases: a rich rig, a board, a capture ------------------------------------------------


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
    sensors["tof"] = replace(tof, range_correction=rc)
    sensors["thermal_left"] = replace(
        sensors["thermal_left"], radiometry=Radiometry(gain=1.0, balance_offset_k=-0.5)
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


BOARD_DOC = {
    "pattern": "checkerboard",
    "inner_corners": [9, 6],
    "square_size_m": 0.06,
    "thermal_black_is_hot": True,
}


def write_capture(d: Path) -> Path:
    """A small valid capture in ``d`` (returned): board, rig, ground truth, two views (one
    without distance). The ``capture_dir`` fixture of each test module."""
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
