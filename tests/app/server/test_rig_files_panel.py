"""The console's Rig files folder (app/server/panels/rig_files.py): the rig in use goes out
as a zip in each format, and comes back in as a new rig version with its eyes."""

from __future__ import annotations

import bz2
import io
import struct
import zipfile
import zlib
from types import SimpleNamespace

import numpy as np
import pytest
import viser

from tests.support import measure_in_child
from trifuse.app.server.panels.rig_files import (
    MAX_UPLOAD_BYTES,
    RigFilesPanel,
    UploadError,
    parse_eyes,
    uploaded_files,
    zip_files,
)
from trifuse.app.sources.sim.head import default_rig
from trifuse.calib.rig_formats import IMPORT_FORMATS, RIG_FORMATS


@pytest.fixture(scope="module")
def server():
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


def panel_with(server, saved: list):
    rig = default_rig()

    def save_rig(r, report):
        saved.append((r, report))
        return SimpleNamespace(name=f"rig-{len(saved):04d}")

    ctx = SimpleNamespace(server=server, pipeline=SimpleNamespace(rig=rig), save_rig=save_rig)
    return RigFilesPanel(ctx), rig  # type: ignore[arg-type]


@pytest.mark.parametrize("fmt", RIG_FORMATS)
def test_export_sends_the_formats_files_as_a_zip(server, fmt) -> None:
    panel, _rig = panel_with(server, [])
    panel.fmt.value = fmt
    sent = {}
    client = SimpleNamespace(send_file_download=lambda name, data, **_kw: sent.update({name: data}))
    message = panel.export(client)
    (name, data) = next(iter(sent.items()))
    assert name == f"rig-{fmt}.zip" and f"in {fmt}" in message
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        assert z.namelist() and all(z.read(n) for n in z.namelist())


@pytest.mark.parametrize("fmt", IMPORT_FORMATS)
def test_an_exported_zip_imports_as_the_next_rig_version(server, fmt) -> None:
    saved: list = []
    panel, rig = panel_with(server, saved)
    panel.fmt.value = fmt
    sent = {}
    panel.export(SimpleNamespace(send_file_download=lambda n, d, **_kw: sent.update({n: d})))
    upload = SimpleNamespace(name=f"rig-{fmt}.zip", content=next(iter(sent.values())))
    message = panel.import_upload(upload)
    assert "rig-0001" in message
    ((imported, report),) = saved
    assert report["format"] == fmt and report["imported_from"] == upload.name
    assert imported.eyes == rig.eyes  # from the Eyes field
    assert list(imported.sensors) == list(rig.sensors)
    for name, s in rig.sensors.items():
        got = imported[name]
        assert got.modality == s.modality and got.image_size == s.image_size
        np.testing.assert_allclose(got.T_rig_sensor, s.T_rig_sensor, atol=1e-9)
        np.testing.assert_allclose(
            [got.intrinsics.fx, got.intrinsics.fy, got.intrinsics.cx, got.intrinsics.cy],
            [s.intrinsics.fx, s.intrinsics.fy, s.intrinsics.cx, s.intrinsics.cy],
            atol=1e-9,
        )


def test_bad_uploads_and_eyes_are_refused_with_a_reason(server) -> None:
    panel, _ = panel_with(server, [])
    panel.fmt.value = "urdf"
    panel.upload_rig(SimpleNamespace(name="x.urdf", content=b"<robot/>"))
    assert "Not done" in panel.message.content and "export only" in panel.message.content
    with pytest.raises(ValueError, match="not a text file"):
        uploaded_files("x.bin", b"\xff\xfe\x00")
    with pytest.raises(ValueError, match="empty zip"):
        uploaded_files("x.zip", zip_files({}))
    with pytest.raises(ValueError, match="EYE=COLOUR:THERMAL"):
        parse_eyes("left=ccd_left")
    assert parse_eyes("") == {}
    assert parse_eyes("left=a:b, right=c:d") == {"left": ("a", "b"), "right": ("c", "d")}


# -- hostile uploads (issue 29): caps on members, actual unpacked bytes, methods -----------

FOUR_MIB = 4 << 20


def raw_zip(members: list[tuple[str, int, bytes, int, int]]) -> bytes:
    """A zip written byte by byte from ``(name, method, stored payload, crc32, declared
    uncompressed size)`` members, so that a test can declare what it likes and reuse one
    compressed payload for many members."""
    body, directory = bytearray(), bytearray()
    for name, method, payload, crc, size in members:
        raw = name.encode()
        sizes = (crc, len(payload), size, len(raw), 0)
        directory += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0,
                                 *sizes, 0, 0, 0, 0, len(body)) + raw  # fmt: skip
        body += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0, *sizes) + raw
        body += payload
    end = struct.pack(
        "<IHHHHIIH", 0x06054B50, 0, 0, len(members), len(members), len(directory), len(body), 0
    )
    return bytes(body + directory + end)


def zeros_compressed(method: int, n: int) -> bytes:
    """``n`` zero bytes compressed with ``method`` (a zip member's payload), made in 1 MiB
    steps."""
    c = (
        bz2.BZ2Compressor()
        if method == zipfile.ZIP_BZIP2
        else zlib.compressobj(9, zlib.DEFLATED, -15)
    )
    block = bytes(1 << 20)
    return b"".join(c.compress(block) for _ in range(n >> 20)) + c.flush()


def bombs() -> dict[str, bytes]:
    """The issue's zips and their variants below the member cap."""
    zeros_crc = zlib.crc32(bytes(FOUR_MIB))
    bz, deflated = (
        zeros_compressed(m, FOUR_MIB) for m in (zipfile.ZIP_BZIP2, zipfile.ZIP_DEFLATED)
    )
    return {
        # 77 kB: 500 bzip2 members of 4 MiB zeros each (every declared size under the cap)
        "500 bzip2 members": raw_zip(
            [(f"m{i:04d}.yaml", zipfile.ZIP_BZIP2, bz, zeros_crc, FOUR_MIB) for i in range(500)]
        ),
        # 4 MiB of entries declaring 106 GiB
        "27235 members": raw_zip(
            [(f"m{i:05d}.yaml", zipfile.ZIP_STORED, bytes(50), 0, FOUR_MIB) for i in range(27235)]
        ),
        # under the member cap: the method is refused before anything is unpacked
        "48 bzip2 members": raw_zip(
            [(f"m{i:02d}.yaml", zipfile.ZIP_BZIP2, bz, zeros_crc, FOUR_MIB) for i in range(48)]
        ),
        # deflate, honest sizes: 192 MiB in all, stopped once 8 MiB are unpacked
        "48 deflated members": raw_zip(
            [
                (f"m{i:02d}.yaml", zipfile.ZIP_DEFLATED, deflated, zeros_crc, FOUR_MIB)
                for i in range(48)
            ]
        ),
    }


@pytest.mark.parametrize(
    ("bomb", "refusal"),
    [
        ("500 bzip2 members", "a zip of 500 entries; at most 64"),
        ("27235 members", "a zip of 27235 entries; at most 64"),
        ("48 bzip2 members", "m00.yaml: compression method 12; expected stored or deflated"),
        ("48 deflated members", "its files unpack to more than 8388608 bytes"),
    ],
)
def test_zip_bombs_are_refused_at_once_in_bounded_memory(tmp_path, bomb, refusal) -> None:
    """Each zip is refused, fast, and the process's peak memory grows by a few MiB (before
    the caps: +2007 MiB and 8 s for the 500 bzip2 members, +197 MiB for the 48 deflated or
    bzip2 ones, all three accepted)."""
    data = bombs()[bomb]
    assert len(data) <= MAX_UPLOAD_BYTES  # within the upload cap: the zip caps must hold
    path = tmp_path / "bomb.zip"
    path.write_bytes(data)
    got = measure_in_child(
        "from app.server.panels.rig_files import UploadError, uploaded_files\n"
        f"data = open({str(path)!r}, 'rb').read()",
        "f\"accepted {len(uploaded_files('bomb.zip', data))} files\"",
        "UploadError",
    )
    assert got["outcome"] == f"bomb.zip: {refusal}"
    assert got["grew_mib"] < 40, got
    assert got["took_s"] < 5, got  # refused at once: unpacking all of it took seconds or more


def test_damaged_zips_are_refused_as_upload_errors() -> None:
    """Truncated and bit-flipped zips (seeded) are taken or refused with an UploadError,
    never another exception (the panel shows ValueErrors; anything else escaped into
    Viser's thread pool before)."""
    good = zip_files({"a.yaml": "x: 1\n" * 200, "b.yaml": "y: 2\n" * 200})
    rng = np.random.default_rng(29)
    for i in range(1000):
        data = bytearray(good)
        if i % 4 == 0:
            data = data[: rng.integers(1, len(data))]
        for _ in range(rng.integers(1, 8)):
            data[rng.integers(0, len(data))] ^= 1 << int(rng.integers(0, 8))
        try:
            uploaded_files("x.zip", bytes(data))
        except UploadError:
            pass
    with pytest.raises(UploadError, match="a zip inside the zip"):
        uploaded_files("x.zip", zip_files({"inner.zip": "PK\x03\x04 and more"}))
    with pytest.raises(UploadError, match="not a UTF-8 text file"):
        uploaded_files(
            "x.zip", raw_zip([("a.bin", zipfile.ZIP_STORED, b"\xff", zlib.crc32(b"\xff"), 1)])
        )
    with pytest.raises(UploadError, match="at most 4194304"):
        uploaded_files("big.yaml", bytes(MAX_UPLOAD_BYTES + 1))
    assert uploaded_files("dir/rig.yaml", b"a: 1\n") == {"rig.yaml": "a: 1\n"}


def test_a_deep_opencv_rig_is_refused_and_the_panel_imports_the_next(server) -> None:
    """The issue's 372-byte zip: an OpenCV rig nested 40,000 levels deep killed the console
    (cv2.FileStorage segfaults). Through the panel it is one line, and the panel goes on
    (imports run in a child process: app.workflows.rig_import)."""
    saved: list = []
    panel, _ = panel_with(server, saved)
    panel.fmt.value = "opencv"
    deep = "%YAML:1.0\nrig: " + "[" * 40_000 + "]" * 40_000 + "\n"
    upload = SimpleNamespace(name="deep.zip", content=zip_files({"rig.yml": deep}))
    assert len(upload.content) < 1000
    panel.upload_rig(upload)
    assert "Not done" in panel.message.content and "nest" in panel.message.content
    assert saved == []
    sent = {}
    panel.export(SimpleNamespace(send_file_download=lambda n, d, **_kw: sent.update({n: d})))
    panel.upload_rig(SimpleNamespace(name="ok.zip", content=sent["rig-opencv.zip"]))
    assert "rig-0001" in panel.message.content and len(saved) == 1
