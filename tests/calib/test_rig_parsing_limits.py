"""Rig files parsed within limits (issue 29, items 1 and 5).

OpenCV FileStorage text nested some 40,000 levels deep kills the process that parses it
(SIGSEGV), in YAML, XML and JSON: such text is refused before OpenCV sees it
(calib/rig_formats/filestorage_text.py), whose bound on the nesting is checked against
OpenCV's own on random documents. A rig import runs in a child process
(app/workflows/rig_import.py) that survives a parser crash, memory or time running out, and
answers what the in-process import answers. YAML is parsed by libyaml's C parser with the
limits counted as it goes (calib/yaml_text.py): a camera_info holding two million
integers is refused at once with bounded memory, and the C loader builds the same values
as the pure-Python one. Legitimate files (the exporter's, as FileStorage writes YAML, XML
and JSON; files like OpenCV's calibration sample) still import; base64 data, on which
OpenCV can loop for ever, is refused.
"""

from __future__ import annotations

import base64
import io
import json
import math
import random
import subprocess
import sys
import textwrap
import time
import zipfile
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from tests.support import DATA_DIR, ROOT, run_cli
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.workflows.rig_import import import_rig_isolated, run_isolated
from trifuse.calib import yaml_text
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig, rig_to_yaml
from trifuse.calib.rig_formats import export_rig, import_rig, opencv_format
from trifuse.calib.rig_formats.filestorage_text import (
    MAX_NESTING,
    MAX_TEXT_CHARS,
    check_filestorage_text,
    nesting_bound,
)
from trifuse.calib.yaml_text import YamlError, parse_yaml

READ = cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY
EYES = {"left": ("ccd_left", "thermal_left"), "right": ("ccd_right", "thermal_right")}
DEEP = 100_000
"""Levels of the hostile texts: OpenCV's YAML and XML parsers crash from about 40,000,
its JSON parser from about 70,000 (8 MiB of stack)."""


def deep_texts() -> dict[str, str]:
    """Texts nested DEEP levels, one per way OpenCV's parsers nest (each under 600 kB)."""
    n = DEEP
    return {
        "yaml flow sequences": "%YAML:1.0\n---\nR: " + "[" * n + "]" * n + "\n",
        "yaml flow mappings": "%YAML 1.2\n---\nR: " + "{a: " * n + "1" + "}" * n + "\n",
        "yaml inline mappings": "%YAML:1.0\n---\n" + "a:" * n + " 1\n",
        "yaml inline sequences": "R:\n   " + "- " * n + "1\n",
        "yaml dashes": "R:\n   " + "-" * n + "1\n",
        "xml": '<?xml version="1.0"?>\n<opencv_storage>\n'
        + "<a>" * n
        + "</a>" * n
        + "\n</opencv_storage>\n",
        "json sequences": '{"R": ' + "[" * n + "]" * n + "}",
        "json mappings": '{"R": ' + '{"a": ' * n + "1" + "}" * n + "}",
    }


DEEP_TEXTS = deep_texts()


def same_rig(a: Rig, b: Rig) -> bool:
    return (
        a.names == b.names
        and a.reference == b.reference
        and a.eyes == b.eyes
        and all(
            a[n].modality == b[n].modality
            and a[n].image_size == b[n].image_size
            and a[n].intrinsics == b[n].intrinsics
            and np.allclose(a[n].T_rig_sensor, b[n].T_rig_sensor, rtol=0, atol=1e-9)
            for n in a.names
        )
    )


# -- OpenCV FileStorage: the crash, and the check before it ------------------------------------


@pytest.mark.parametrize("kind", list(DEEP_TEXTS))
def test_the_deep_texts_crash_opencv_and_the_parent_survives(kind: str) -> None:
    """Each hostile text really kills the process that hands it to cv2.FileStorage (in a
    child): the guarded run says so in one line, and this process carries on."""
    call = partial(cv2.FileStorage, DEEP_TEXTS[kind], READ)
    with pytest.raises(RigError, match=r"^test: its process was killed by SIGSEGV") as err:
        run_isolated(call, what="test", timeout_s=60)
    assert "\n" not in str(err.value)
    # the parent is fine and the next isolated call works
    assert run_isolated(partial(len, "abc"), what="test") == 3


@pytest.mark.parametrize("kind", list(DEEP_TEXTS))
def test_deep_opencv_text_is_refused_before_opencv_reads_it(kind: str) -> None:
    """The check refuses each hostile text at once, without OpenCV; the import (in its
    child) answers that refusal, not a crash."""
    text = DEEP_TEXTS[kind]
    start = time.perf_counter()
    with pytest.raises(RigError, match=rf"^ccd_left\.yml: nested deeper than {MAX_NESTING} "):
        check_filestorage_text(text, "ccd_left.yml")
    assert time.perf_counter() - start < 2.0  # a refusal at once (it stops at level 33)
    with pytest.raises(RigError, match=rf"^ccd_left\.yml: nested deeper than {MAX_NESTING} "):
        import_rig_isolated({"ccd_left.yml": text}, "opencv", allow_no_poses=True)


def test_a_small_zip_of_a_deep_file_is_refused_in_the_consoles_path() -> None:
    """The issue's case: a few hundred bytes of zip unpack to a file that would crash
    OpenCV; the console's way (unpack the upload, import in a child) refuses it."""
    from trifuse.app.server.panels.rig_files import uploaded_files

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("ccd_left.yml", DEEP_TEXTS["yaml flow sequences"])
    content = buf.getvalue()
    assert len(content) < 1024
    files = uploaded_files("rig.zip", content)
    with pytest.raises(RigError, match=rf"nested deeper than {MAX_NESTING} levels"):
        import_rig_isolated(files, "opencv", eyes=EYES)


@pytest.mark.parametrize("kind", ["yaml flow sequences", "xml", "json mappings"])
def test_the_command_line_refuses_a_deep_file_in_one_line(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "ccd_left.yml"
    path.write_text(DEEP_TEXTS[kind])
    out_path = tmp_path / "rig.yaml"
    code, out, err = run_cli(
        ["rig", "import", str(path), "--format", "opencv", "--out", str(out_path)], capsys
    )
    assert code == 2 and out == "", (code, out, err)
    assert len(err.strip().splitlines()) == 1, err
    assert f"ccd_left.yml: nested deeper than {MAX_NESTING} levels" in err
    assert not out_path.exists()


# -- the bound against OpenCV's own depth ----------------------------------------------------

_JUNK = ["]", "}", "[", "{", "'", '"', "#", "!", ":", ",", "-", " ", "/", "*", "<", ">"]
_JUNK += ["</a>", "<!--", "-->", "x", "1"]


def _junk(rng: random.Random, n: int = 4) -> str:
    return "".join(rng.choice(_JUNK) for _ in range(rng.randint(0, n)))


def _yaml_value(rng: random.Random, d: int) -> str:
    """A flow value: scalars of every kind (strings full of brackets), lists, mappings."""
    if d <= 0 or rng.random() < 0.3:
        return rng.choice(
            [
                str(rng.randint(-9, 99)),
                f"{rng.uniform(-9, 9):.3e}",
                "'" + _junk(rng).replace("'", "''") + "'",
                '"' + _junk(rng).replace('"', "") + '"',
                "a" + "".join(c for c in _junk(rng) if c not in ",]}#:"),
            ]
        )
    if rng.random() < 0.5:
        sep = rng.choice([", ", ",\n" + " " * rng.randint(5, 9), " ,"])
        return "[ " + sep.join(_yaml_value(rng, d - 1) for _ in range(rng.randint(0, 3))) + " ]"
    keys = ["k" + "".join(c for c in _junk(rng, 2) if c not in ":,#") for _ in range(3)]
    items = [f"{k.strip() or 'k'}: {_yaml_value(rng, d - 1)}" for k in keys[: rng.randint(0, 3)]]
    return "{ " + ", ".join(items) + " }"


def _yaml_block(rng: random.Random, d: int, indent: int) -> str:
    pad, lines = " " * indent, []
    for i in range(rng.randint(1, 3)):
        key = f"k{i}" + rng.choice(["", "]", "[", "'", "x}"])
        head = f"{pad}{key}:" if rng.random() < 0.6 else f"{pad}-"
        r = rng.random()
        if d > 0 and r < 0.3:
            lines += [head, _yaml_block(rng, d - 1, indent + rng.randint(1, 4))]
        elif d > 0 and r < 0.45:
            lines.append(f"{head} n: - {_yaml_value(rng, d - 1)}")
        else:
            lines.append(f"{head} {_yaml_value(rng, d)}" + rng.choice(["", " # " + _junk(rng)]))
        if rng.random() < 0.2:
            lines.append(pad + "# " + _junk(rng))
    return "\n".join(lines)


def _json_value(rng: random.Random, d: int) -> str:
    if d <= 0 or rng.random() < 0.3:
        s = _junk(rng).replace("\\", "")
        s = s.replace('"', '\\"') if rng.random() < 0.5 else s.replace('"', "")
        return rng.choice([f'"{s}"', str(rng.randint(-9, 9)), "1.5", "true", "null"])
    sp = rng.choice([" ", "\n  ", ' /* ] } " */ ', ' // ] "\n '])
    items = [_json_value(rng, d - 1) for _ in range(rng.randint(0, 3))]
    if rng.random() < 0.5:
        return "[" + sp + ("," + sp).join(items) + sp + "]"
    pairs = (f'"k{i}{_junk(rng, 2)}": {v}' for i, v in enumerate(items))
    return "{" + sp + ("," + sp).join(pairs) + sp + "}"


def _xml_value(rng: random.Random, d: int) -> str:
    """An element's content: numbers and strings, or a mapping (named elements) or a
    sequence (``_`` elements), with comments between."""
    if d <= 0 or rng.random() < 0.3:
        values = ["1", "2.5", "abc", '"a b"', "&lt;x&gt;", '"[ ] {"']
        return " ".join(rng.choice(values) for _ in range(rng.randint(1, 3)))
    names = rng.choice([["_"] * 3, ["a", "b_c", "x-1"]])
    out = []
    for name in names[: rng.randint(1, 3)]:
        attrs = rng.choice(["", ' type_id="opencv-matrix"', " x='1'"])
        comment = rng.choice(["", "\n", " <!-- </a> <b> --> "])
        out.append(f"<{name}{attrs}>{_xml_value(rng, d - 1)}</{name}>{comment}")
    return "".join(out)


def _document(rng: random.Random) -> str:
    kind = rng.choice(["yaml", "yaml", "json", "xml"])
    if kind == "yaml":
        head = rng.choice(["%YAML:1.0\n---\n", "%YAML 1.2\n---\n", "", "---\n"])
        text = head + _yaml_block(rng, rng.randint(1, 6), 0) + "\n"
    elif kind == "json":
        text = "{" + ", ".join(f'"k{i}": {_json_value(rng, 6)}' for i in range(2)) + "}\n"
    else:
        body = "".join(f"<k{i}>{_xml_value(rng, 6)}</k{i}>\n" for i in range(2))
        text = f'<?xml version="1.0"?>\n<opencv_storage>\n{body}</opencv_storage>\n'
    chars = list(text)
    for _ in range(rng.choice([0, 0, 1, 2, 3])):  # half of them damaged a little
        i = rng.randrange(len(chars))
        chars[i : i + rng.randint(0, 1)] = [rng.choice([*_JUNK, "\n", "\r", "  "])]
    return "".join(chars)


def _depth(node: cv2.FileNode) -> int:
    """Levels of the tree under ``node`` (a mapping holding a number: 1)."""
    if node.isMap():
        return 1 + max((_depth(node.getNode(k)) for k in node.keys()), default=0)
    if node.isSeq():
        return 1 + max((_depth(node.at(i)) for i in range(node.size())), default=0)
    return 0


def test_the_bound_is_never_below_opencvs_depth() -> None:
    """Random documents in the three formats, full of brackets in strings, comments,
    keys and tags, some damaged: for every one OpenCV reads, the bound is at least the
    depth of the tree it built (shallow texts, no base64: this process is safe)."""
    rng = random.Random(29)
    read = {"yaml": 0, "json": 0, "xml": 0}
    for _ in range(1500):
        text = _document(rng)
        try:
            fs = cv2.FileStorage(text, READ)
            depth = _depth(fs.root()) if fs.isOpened() else None
        except (cv2.error, SystemError):
            depth = None
        if depth is None:
            continue
        assert nesting_bound(text) >= depth, text
        kind = "json" if text.startswith("{") else "xml" if text.startswith("<") else "yaml"
        read[kind] += 1
    assert min(read.values()) >= 100, read  # enough of each that OpenCV read


# -- legitimate files -------------------------------------------------------------------------


_FORMATS = {
    "yaml": cv2.FILE_STORAGE_FORMAT_YAML,
    "xml": cv2.FILE_STORAGE_FORMAT_XML,
    "json": cv2.FILE_STORAGE_FORMAT_JSON,
}


def _export(layout: str, binary: bool, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """The default rig's OpenCV files as FileStorage writes them in ``layout``."""
    flags = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | _FORMATS[layout]
    monkeypatch.setattr(opencv_format, "_WRITE", flags | (cv2.FILE_STORAGE_BASE64 * binary))
    files = export_rig(default_rig(), "opencv").files
    head = {"yaml": "%YAML", "xml": "<?xml", "json": "{"}[layout]
    assert all(text.startswith(head) for text in files.values())
    return files


@pytest.mark.parametrize("layout", list(_FORMATS))
def test_exported_rigs_round_trip_in_every_layout(
    layout: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The default rig exported as FileStorage writes YAML, XML and JSON imports back (in
    process and in the child) to the same rig; written with base64 matrices it is refused
    in one line (see the next test)."""
    files = _export(layout, False, monkeypatch)
    assert max(nesting_bound(text) for text in files.values()) <= 5
    assert same_rig(import_rig(files, "opencv").rig, default_rig())
    assert same_rig(import_rig_isolated(files, "opencv").rig, default_rig())
    with pytest.raises(RigError, match=r"^tof\.yml: holds base64 \(binary\) data"):
        import_rig(_export(layout, True, monkeypatch), "opencv")


def _base64_block(layout: str, header: bytes) -> str:
    """A FileStorage file holding one base64 block: ``header`` (the element type, padded
    to 24 bytes as OpenCV writes it) and one double."""
    data = base64.b64encode(header.ljust(24, b" ") + b"\0" * 8).decode()
    if layout == "yaml":
        return f"%YAML:1.0\n---\na: !!binary |\n   {data}\n"
    if layout == "json":
        return '{"a": "$base64$' + data + '"}'
    return (
        f'<?xml version="1.0"?>\n<opencv_storage><a type_id="binary">{data}</a></opencv_storage>\n'
    )


@pytest.mark.parametrize("layout", list(_FORMATS))
def test_base64_data_is_refused_because_opencv_can_loop_on_it(layout: str) -> None:
    """A base64 block whose header names no element type sends cv2.FileStorage into an
    endless loop (shown in a child, stopped after 1.5 s: parsing a text this short takes
    milliseconds); the check refuses any base64 block before OpenCV sees it."""
    endless = _base64_block(layout, b"")
    with pytest.raises(RigError, match=r"^test: took longer than 1.5 s; stopped$"):
        run_isolated(partial(cv2.FileStorage, endless, READ), what="test", timeout_s=1.5)
    for text in (endless, _base64_block(layout, b"1d")):
        with pytest.raises(RigError, match=r"^a\.yml: holds base64 \(binary\) data"):
            check_filestorage_text(text, "a.yml")


def _calibration_sample(fmt: int) -> str:
    """A file as OpenCV's calibration sample writes it (samples/cpp/calibration.cpp): a
    comment, the extrinsics and every view's corners, errors as floats."""
    rng = np.random.default_rng(3)
    fs = cv2.FileStorage("x", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | fmt)
    fs.write("calibration_time", "Mon Jan  1 00:00:00 2024")
    fs.write("nframes", 13)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.writeComment("flags: +fix_aspectRatio [0, 1) +zero_tangent_dist")
    fs.write("flags", 14)
    K = np.array([[536.07, 0.0, 342.37], [0.0, 536.02, 235.54], [0.0, 0.0, 1.0]])
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array([[-0.265], [-0.047], [0.0018], [-0.0003], [0.25]]))
    fs.write("avg_reprojection_error", 0.39)
    fs.write("per_view_reprojection_errors", rng.uniform(0, 1, (13, 1)).astype(np.float32))
    fs.write("extrinsic_parameters", rng.normal(size=(13, 6)))
    fs.write("image_points", rng.uniform(0, 640, (13, 54, 2)).astype(np.float32))
    return fs.releaseAndGetString()


@pytest.mark.parametrize("layout", ["yaml", "xml", "json"])
def test_a_calibration_sample_file_imports(layout: str) -> None:
    text = _calibration_sample(_FORMATS[layout])
    assert nesting_bound(text) <= 5
    imported = import_rig(
        {"out_camera_data.yml": text},
        "opencv",
        modalities={"out_camera_data": "color"},
        allow_no_poses=True,
    )
    assert imported.rig["out_camera_data"].image_size == (640, 480)


# -- other hostile FileStorage text -----------------------------------------------------------


def _sensor_text(**replace: str) -> str:
    """The default rig's ccd_left.yml with parts replaced."""
    text = export_rig(default_rig(), "opencv").files["ccd_left.yml"]
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    return text


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "a: 1\n" + "#" * MAX_TEXT_CHARS,
            rf"{MAX_TEXT_CHARS + 5} characters; expected at most {MAX_TEXT_CHARS}",
        ),
        ("%YAML:1.0\n---\na: b\x01c\n", r"not an OpenCV FileStorage file \(empty or binary\)"),
        ("   \n\n", r"not an OpenCV FileStorage file \(empty or binary\)"),
        (_sensor_text(**{"dt: d": "dt: u"}), r"camera_matrix: dt: expected one of \['d', 'f'\]"),
        (_sensor_text(**{"dt: d": 'dt: "3d"'}), r"camera_matrix: dt: expected one of"),
        (_sensor_text(**{"dt: d": 'dt: "4294967297d"'}), r"camera_matrix: dt: expected one of"),
        (
            _sensor_text(**{"rows: 3\n   cols: 3": "rows: 2147483647\n   cols: 2147483647"}),
            r"camera_matrix: rows: expected an integer from 1 to 16",
        ),
        (
            _sensor_text(**{"data: [ 1333., 0., 641.29999999999995": "data: [ 1333., 0."}),
            r"camera_matrix: not a valid matrix",
        ),
        (
            _sensor_text(**{"modality: color": 'modality: "' + "c" * 100_000 + '"'}),
            r"not an OpenCV FileStorage file: line \d+: Too long string literal",
        ),
    ],
    ids=[
        "too long",
        "control character",
        "blank",
        "dt u",
        "dt 3d",
        "dt overflowing",
        "huge rows and cols",
        "too few numbers",
        "100 kB string",
    ],
)
def test_other_hostile_filestorage_text_is_one_refusal(text: str, match: str) -> None:
    with pytest.raises(RigError, match=r"^ccd_left\.yml: " + match):
        opencv_format.import_({"ccd_left.yml": text}, allow_no_poses=True)


# -- the import in a child process ------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["ros", "kalibr", "opencv"])
def test_the_isolated_import_answers_what_the_import_answers(fmt: str) -> None:
    rig = default_rig()
    files = export_rig(rig, fmt).files
    options = {} if fmt == "opencv" else {"eyes": EYES}
    here, there = import_rig(files, fmt, **options), import_rig_isolated(files, fmt, **options)
    assert same_rig(there.rig, rig) and same_rig(there.rig, here.rig)
    assert there.lost == here.lost
    bad = dict(files)
    bad[sorted(bad)[-1]] = "a: [1, 2\n"
    with pytest.raises(RigError) as here_err:
        import_rig(bad, fmt, **options)
    with pytest.raises(RigError) as there_err:
        import_rig_isolated(bad, fmt, **options)
    assert str(there_err.value) == str(here_err.value)
    with pytest.raises(ValueError, match="format: expected one of"):
        import_rig_isolated(files, "urdf")  # type: ignore[arg-type]


def test_the_isolated_run_reports_memory_and_time_running_out() -> None:
    with pytest.raises(RigError, match=r"^test: needed more than 256 MiB of memory; refused$"):
        run_isolated(partial(bytearray, 1 << 30), what="test", memory_bytes=256 << 20)
    start = time.perf_counter()
    with pytest.raises(RigError, match=r"^test: took longer than 1 s; stopped$"):
        run_isolated(partial(time.sleep, 60), what="test", timeout_s=1.0)
    assert time.perf_counter() - start < 20  # stopped, not waited for
    with pytest.raises(RuntimeError, match=r"^test failed: ZeroDivisionError"):
        run_isolated(partial(divmod, 1, 0), what="test")


# -- YAML ---------------------------------------------------------------------------------------

_MEASURE = textwrap.dedent(
    """
    import json, resource, sys, time
    from trifuse.calib.rig_formats.ros_format import parse_camera_info
    from trifuse.calib.errors import RigError

    def status(key):
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(key))

    n = int(sys.argv[1])
    text = (  # made without a list of n strings
        "image_width: 640\\nimage_height: 480\\ncamera_name: c\\ndistortion_coefficients:\\n"
        "  rows: 1\\n  cols: 5\\n  data: [" + "1, " * (n - 1) + "1]\\n"
    )
    cap = status("VmSize:") * 1024 + (512 << 20)  # a MemoryError past 512 MiB more
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    rss = status("VmRSS:")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # the peak resident size starts again from here
    start = time.perf_counter()
    try:
        parse_camera_info(text, "c.yaml")
        error = None
    except RigError as exc:
        error = str(exc)
    print(json.dumps({
        "mib": len(text) / 2**20,
        "seconds": time.perf_counter() - start,
        "grew_mib": (status("VmHWM:") - rss) / 1024,
        "error": error,
    }))
    """
)


@pytest.mark.parametrize("n", [2_000_000, 1_200_000], ids=["2M", "1.2M"])
def test_millions_of_integers_are_refused_at_once_with_bounded_memory(n: int) -> None:
    """The issue's camera_info (2M integers, refused by libyaml's event count in C) and
    one just over the limit (counted event by event): refused in a second or two, the
    process's resident size growing by the text's copy, a few MiB (PyYAML's pure parser
    took 307 s and kept 0.9 GiB); past 512 MiB more it would fail with MemoryError."""
    proc = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(n)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    got = json.loads(proc.stdout)
    assert got["mib"] > 3.0
    assert got["error"] is not None and "more than 1000000 values" in got["error"], got
    assert got["seconds"] < 15, got  # minutes before
    assert got["grew_mib"] < 64, got  # 0.9 GiB before


def test_yaml_limits_are_counted_while_parsing() -> None:
    """Depth and values, aliases counted at every use and at the depth they stand, are
    refused before anything is built; just within the limits is accepted."""
    depth = yaml_text.MAX_DEPTH
    assert parse_yaml("[" * depth + "1" + "]" * depth) is not None  # the 1 at depth 100
    with pytest.raises(YamlError, match=f"nested deeper than {depth} levels"):
        parse_yaml("[" * (depth + 1) + "1" + "]" * (depth + 1))
    aliased = "a: &a " + "[" * 60 + "1" + "]" * 60 + "\nb: " + "[" * 40 + "*a" + "]" * 40
    with pytest.raises(YamlError, match=f"nested deeper than {depth} levels"):
        parse_yaml(aliased)
    assert parse_yaml(aliased.replace("[" * 40 + "*a" + "]" * 40, "[" * 38 + "*a" + "]" * 38))
    for itself in ("a: &x [*x]\n", "&x {a: *x}\n"):
        with pytest.raises(YamlError, match="an alias inside its own anchor"):
            parse_yaml(itself)
    # a list of 1000 values (with its 999 numbers) used k times: 1004 + 1000 k values
    base = "a: &a [" + ", ".join(["1"] * 999) + "]\n"
    assert len(parse_yaml(base + "b: [" + ", ".join(["*a"] * 998) + "]\n")["b"]) == 998
    with pytest.raises(YamlError, match="more than 1000000 values"):
        parse_yaml(base + "b: [" + ", ".join(["*a"] * 999) + "]\n")
    for kind in ("flow sequences", "flow mappings", "inline sequences"):
        with pytest.raises(YamlError, match="maximum nesting depth"):  # libyaml's, in C
            parse_yaml(
                DEEP_TEXTS[f"yaml {kind}"].replace("%YAML:1.0\n", "").replace("%YAML 1.2\n", "")
            )
    for kind in ("sequences", "mappings"):
        with pytest.raises(YamlError, match="maximum nesting depth"):
            parse_yaml(DEEP_TEXTS[f"json {kind}"])
    with pytest.raises(YamlError, match=f"expected at most {yaml_text.MAX_TEXT_CHARS}"):
        parse_yaml("#" * (yaml_text.MAX_TEXT_CHARS + 1))


_SCALARS = [
    "yes", "no", "on", "off", "true", "False", "TRUE", "y", "n", "~", "null", "",
    "0", "-0", "+1", "0o17", "017", "0x1F", "1_000", "0b101", "190:20:30",
    "1e-3", "1.0e-3", "1.5e+3", "6.8523015e+5", "685.230_15e+03", ".5", "-.5", "1.", ".nan",
    ".NaN", ".inf", "-.Inf", "+.inf", "1e400", "-1e-400",
    "2001-12-14t21:59:43.10-05:00", "2001-12-14 21:59:43.10 -5", "2002-12-14",
    "2001-12-15T02:59:43.1Z",
    "'quoted: [x]'", '"esc \\u00e9 \\x41 \\t"', "caf\u00e9", "'1e-3'", "!!float 1", "!!str 1.5",
    "!!int '7'", "!!binary aGVsbG8=", "[1, 2.5, [x]]", "{a: 1, b: [2]}", "!!set {a, b}",
    "!!omap [a: 1, b: 2]", "!!pairs [a: 1, a: 2]",
]  # fmt: skip


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or (
            a == b and math.copysign(1, a) == math.copysign(1, b)
        )
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)  # type: ignore[index]
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))  # type: ignore[arg-type]
    return a == b


def test_the_c_loader_builds_what_the_pure_one_builds() -> None:
    """Where PyYAML has libyaml, parse_yaml builds with it; for the scalars YAML 1.1
    resolves (booleans, nulls, ints in every base, floats such as 1e-3 (a string in YAML
    1.1), .nan, timestamps, tags) and for the project's files the values are those of the
    pure-Python SafeLoader, type for type."""
    assert yaml.__with_libyaml__ and yaml_text._Loader is yaml.CSafeLoader
    docs = [f"v: {s}\n" for s in _SCALARS] + ["- " + s.replace("\n", " ") + "\n" for s in _SCALARS]
    rig = default_rig()
    docs.append(rig_to_yaml(rig))
    for fmt in ("ros", "kalibr"):
        docs += [t for name, t in export_rig(rig, fmt).files.items() if name.endswith(".yaml")]
    data = DATA_DIR / "rig_formats"
    docs += [p.read_text() for p in sorted(data.rglob("*.yaml"))]
    for doc in docs:
        want = yaml.load(doc, Loader=yaml.SafeLoader)
        assert _same(parse_yaml(doc), want), doc


def test_without_libyaml_the_pure_parser_keeps_the_limits(monkeypatch: pytest.MonkeyPatch) -> None:
    """PyYAML built without libyaml: the same values and the same refusals (slower)."""
    monkeypatch.setattr(yaml_text, "_CParser", None)
    monkeypatch.setattr(yaml_text, "_Loader", yaml.SafeLoader)
    text = rig_to_yaml(default_rig())
    assert _same(parse_yaml(text), yaml.load(text, Loader=yaml.SafeLoader))
    with pytest.raises(YamlError, match="an alias inside its own anchor"):
        parse_yaml("a: &x [*x]\n")
    with pytest.raises(YamlError, match="nested deeper than 100 levels"):
        parse_yaml("[" * 5000 + "]" * 5000)
    base = "a: &a [" + ", ".join(["1"] * 999) + "]\n"
    with pytest.raises(YamlError, match="more than 1000000 values"):
        parse_yaml(base + "b: [" + ", ".join(["*a"] * 999) + "]\n")
