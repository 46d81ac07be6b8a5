"""The console's "Rig files" folder (issue 21): the rig in use exported in a robotics
format (ROS camera_info, Kalibr camchain, OpenCV FileStorage, URDF) as a zip the browser
downloads, and a rig imported from such files (a single file or a zip) saved as the
session's next rig version, which the Calibration panel's Saved rig then offers to use.

What a format cannot hold, or what imported files did not say, is listed under the
buttons (calib.rig_formats).
"""

from __future__ import annotations

import io
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import PurePosixPath

from trifuse.app.errors import describe_error
from trifuse.app.server.markdown_text import md_text
from trifuse.app.server.runtime.context import ConsoleContext
from trifuse.app.workflows.rig_import import import_rig_isolated
from trifuse.calib.errors import RigError
from trifuse.calib.rig import Rig
from trifuse.calib.rig_formats import IMPORT_FORMATS, RIG_FORMATS, export_rig

MAX_UPLOAD_BYTES = 4 << 20
"""Rig files are small: a larger upload is refused (the relay in front of Viser refuses it
before Viser buffers it, app.server.routers.viser_bridge)."""
MAX_MEMBERS = 64
"""Entries (files and folders) a zip may hold."""
MAX_UNPACKED_BYTES = 8 << 20
"""The bytes all of a zip's files may unpack to together, counted as they are read (the
sizes a zip declares are not trusted)."""
ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}
"""The compression methods taken. Python's zipfile inflates deflate in bounded steps but
bzip2 and LZMA in one call of any size: a 77 kB zip of bzip2 members grew the console by
1.8 GiB."""
_READ_BYTES = 64 << 10
_ZIP_SIGNATURES = (b"PK\x03\x04", b"PK\x05\x06", b"PK\x07\x08")


class UploadError(ValueError):
    """An upload the Rig files folder does not take (what was expected, what arrived)."""


def zip_files(files: Mapping[str, str]) -> bytes:
    """The files (relative path -> text) as a zip archive."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, text in sorted(files.items()):
            z.writestr(name, text)
    return buf.getvalue()


def uploaded_files(name: str, content: bytes) -> dict[str, str]:
    """An upload as files (base name -> UTF-8 text): the members of a zip, or the one file.

    Raises:
        UploadError: more than :data:`MAX_UPLOAD_BYTES`; a zip with more than
            :data:`MAX_MEMBERS` entries, a member compressed otherwise than
            :data:`ZIP_METHODS`, encrypted, itself a zip or not UTF-8, files unpacking to
            more than :data:`MAX_UNPACKED_BYTES` together, a damaged or empty zip; a
            single file that is not UTF-8.
    """
    if len(content) > MAX_UPLOAD_BYTES:
        raise UploadError(f"{name}: {len(content)} bytes; rig files are at most {MAX_UPLOAD_BYTES}")
    if not zipfile.is_zipfile(io.BytesIO(content)):
        try:
            return {PurePosixPath(name).name: content.decode("utf-8")}
        except UnicodeDecodeError:
            raise UploadError(f"{name}: not a text file or a zip") from None
    try:
        with zipfile.ZipFile(io.BytesIO(content)) as z:
            out = _zip_members(name, z)
    except UploadError:
        raise
    # what zipfile raises for damaged archives (ValueError: "negative seek value", a
    # name that is not UTF-8; NotImplementedError: flags or versions it cannot read)
    except (zipfile.BadZipFile, EOFError, zlib.error, ValueError, NotImplementedError) as exc:
        raise UploadError(f"{name}: a damaged zip ({exc})") from None
    if not out:
        raise UploadError(f"{name}: an empty zip")
    return out


def _zip_members(name: str, z: zipfile.ZipFile) -> dict[str, str]:
    infos = z.infolist()
    if len(infos) > MAX_MEMBERS:
        raise UploadError(f"{name}: a zip of {len(infos)} entries; at most {MAX_MEMBERS}")
    out, total = {}, 0
    for info in infos:
        if info.is_dir():
            continue
        member = f"{name}: {info.filename}"
        if info.compress_type not in ZIP_METHODS:
            raise UploadError(
                f"{member}: compression method {info.compress_type}; expected "
                f"{' or '.join(ZIP_METHODS.values())}"
            )
        if info.flag_bits & 0x1:
            raise UploadError(f"{member}: encrypted; expected a plain zip")
        data = bytearray()
        with z.open(info) as f:
            while chunk := f.read(_READ_BYTES):
                total += len(chunk)
                if total > MAX_UNPACKED_BYTES:
                    raise UploadError(
                        f"{name}: its files unpack to more than {MAX_UNPACKED_BYTES} bytes"
                    )
                data += chunk
        if bytes(data[:4]) in _ZIP_SIGNATURES:
            raise UploadError(f"{member}: a zip inside the zip; expected rig files")
        try:
            out[PurePosixPath(info.filename).name] = data.decode("utf-8")
        except UnicodeDecodeError:
            raise UploadError(f"{member}: not a UTF-8 text file") from None
    return out


def parse_eyes(text: str) -> dict[str, tuple[str, str]]:
    """``left=ccd_left:thermal_left,right=ccd_right:thermal_right`` -> {eye: (colour,
    thermal)}; empty text: no eyes."""
    eyes = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        eye, sep, pair = part.partition("=")
        color, sep2, thermal = pair.partition(":")
        if not (sep and sep2 and eye.strip() and color.strip() and thermal.strip()):
            raise ValueError(f"eyes: expected EYE=COLOUR:THERMAL[,...], got {part!r}")
        eyes[eye.strip()] = (color.strip(), thermal.strip())
    return eyes


def eyes_text(rig: Rig) -> str:
    """The rig's eyes as :func:`parse_eyes` reads them."""
    return ",".join(f"{name}={e.color}:{e.thermal}" for name, e in rig.eyes.items())


class RigFilesPanel:
    """Builds the Rig files folder (no periodic work: everything happens on a click)."""

    def __init__(self, ctx: ConsoleContext) -> None:
        self.ctx = ctx
        gui = ctx.server.gui
        with gui.add_folder("Rig files", expand_by_default=False):
            gui.add_markdown(
                "The rig in use for ROS, Kalibr, OpenCV or a URDF, and a rig from their "
                "files (one file or a zip), saved as the next rig version."
            )
            self.fmt = gui.add_dropdown("Format", RIG_FORMATS, initial_value="ros")
            self.export_button = gui.add_button("Export rig in use")
            self.eyes = gui.add_text("Eyes (import)", eyes_text(ctx.pipeline.rig))
            self.upload = gui.add_upload_button("Import rig files", mime_type="*/*")
            self.message = gui.add_markdown("")
        self.export_button.on_click(lambda e: self._act(lambda: self.export(e.client)))
        self.upload.on_upload(lambda e: self.upload_rig(e.target.value))

    def upload_rig(self, upload) -> None:
        """What the Upload button does with a file (``upload.name``, ``upload.content``
        bytes): import it (:meth:`import_upload`); what happened, or why not, shown in
        :attr:`message`."""
        self._act(lambda: self.import_upload(upload))

    def _act(self, action) -> None:
        try:
            self.message.content = action() or ""
        except (RigError, ValueError, KeyError, OSError) as exc:
            self.message.content = f"**Not done:** {md_text(describe_error(exc))}"

    def export(self, client) -> str:
        """Send the rig in use in the chosen format to ``client`` as a zip."""
        fmt = self.fmt.value
        exported = export_rig(self.ctx.pipeline.rig, fmt)
        client.send_file_download(
            f"rig-{fmt}.zip", zip_files(exported.files), save_immediately=True
        )
        return _listed(f"Exported {len(exported.files)} file(s) in {md_text(fmt)}.", exported.lost)

    def import_upload(self, upload) -> str:
        """Import an uploaded file or zip in the chosen format; save it as a rig version."""
        fmt = self.fmt.value
        if fmt not in IMPORT_FORMATS:
            raise ValueError(f"{fmt}: export only (import: {', '.join(IMPORT_FORMATS)})")
        if self.ctx.save_rig is None:
            raise ValueError("this console has no calibration session to save rigs in")
        files = uploaded_files(upload.name, upload.content)
        # in a child process: OpenCV's and libyaml's parsers are native code
        imported = import_rig_isolated(files, fmt, eyes=parse_eyes(self.eyes.value) or None)
        report = {"imported_from": upload.name, "format": fmt, "lost": imported.lost}
        version = self.ctx.save_rig(imported.rig, report)
        return _listed(
            f"Imported {md_text(upload.name)} ({md_text(fmt)}) as **{md_text(version.name)}**: "
            "pick it in the Calibration panel's Saved rig and Use this rig.",
            imported.lost,
        )


def _listed(head: str, lost: list[str]) -> str:
    if not lost:
        return head
    return head + "\n\nNot carried over:\n" + "\n".join(f"- {md_text(x)}" for x in lost)
