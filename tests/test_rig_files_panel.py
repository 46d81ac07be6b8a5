"""The console's Rig files folder (app/server/panels/rig_files.py): the rig in use goes out
as a zip in each format, and comes back in as a new rig version with its eyes."""

from __future__ import annotations

import io
import zipfile
from types import SimpleNamespace

import numpy as np
import pytest
import viser

from app.server.panels.rig_files import RigFilesPanel, parse_eyes, uploaded_files, zip_files
from app.sources.sim.head import default_rig
from calib.rig_formats import IMPORT_FORMATS, RIG_FORMATS


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
    panel._act(lambda: panel.import_upload(SimpleNamespace(name="x.urdf", content=b"<robot/>")))
    assert "Not done" in panel.message.content and "export only" in panel.message.content
    with pytest.raises(ValueError, match="not a text file"):
        uploaded_files("x.bin", b"\xff\xfe\x00")
    with pytest.raises(ValueError, match="empty zip"):
        uploaded_files("x.zip", zip_files({}))
    with pytest.raises(ValueError, match="EYE=COLOUR:THERMAL"):
        parse_eyes("left=ccd_left")
    assert parse_eyes("") == {}
    assert parse_eyes("left=a:b, right=c:d") == {"left": ("a", "b"), "right": ("c", "d")}
