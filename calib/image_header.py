"""What a PNG, JPEG or binary PGM/PPM says of its picture before anything is decoded.

Every reader of images that come from outside (capture directories, recordings, pushed
frames) checks the size an image claims against what it expects before OpenCV allocates
anything: a 631-byte JPEG may claim 30000 x 30000 pixels. :func:`image_header` reads the
claim from the bytes: a PNG's IHDR chunk, a JPEG's first frame header (SOFn), skipping the
segments before it (APPn, DQT, DHT, ...). It reads only the header, so it takes any buffer
(``bytes``, a ``memoryview``, an ``mmap`` of a file). :func:`pnm_header` reads a binary
PGM or PPM's (``P5``, ``P6``: what thermal and machine-vision cameras' SDKs save, 16-bit
too); only capture directories take those.

:func:`image_damage` says whether a PNG or PNM holds its whole picture (a file cut short, a
PNG chunk that fails its CRC) before a decoder meets the damage: libpng writes its own
complaint straight to stderr, outside OpenCV's logging.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import Literal

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
"""PNG colour type -> samples per pixel as OpenCV's IMREAD_UNCHANGED decodes it (a palette
decodes to BGR)."""
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
"""JPEG start-of-frame markers (baseline, extended, progressive, lossless ...), not DHT
(C4), JPG (C8) or DAC (CC)."""
_JPEG_STANDALONE = {0x01, 0xD8, *range(0xD0, 0xD8)}
"""Markers without a length: TEM, SOI, RST0-7."""


class ImageHeaderError(ValueError):
    """Bytes that are not a PNG or JPEG with a readable size; the message says why (the
    caller names the file or message)."""


@dataclass(frozen=True)
class ImageHeader:
    """A PNG's or JPEG's picture as its header describes it.

    Attributes:
        format: ``"png"``, ``"jpeg"`` or ``"pnm"``.
        width, height: pixels (both positive).
        bit_depth: bits per sample as OpenCV decodes it (a palette PNG or one of fewer than
            8 bits: 8).
        channels: samples per pixel as OpenCV's IMREAD_UNCHANGED decodes it (1 grey, 2 grey
            and alpha, 3, 4).
        png_colour_type: the IHDR's colour type (0 grey, 2 RGB, 3 palette, 4 grey and
            alpha, 6 RGBA); None for a JPEG or PNM.
        data_offset: a PNM's: the byte its pixels start at; None for a PNG or JPEG.
    """

    format: Literal["png", "jpeg", "pnm"]
    width: int
    height: int
    bit_depth: int
    channels: int
    png_colour_type: int | None = None
    data_offset: int | None = None


def image_header(data: bytes | bytearray | memoryview) -> ImageHeader:
    """The header of a PNG or JPEG in ``data`` (ImageHeaderError for anything else, or a
    header without a size)."""
    if bytes(data[:8]) == PNG_SIGNATURE:
        return _png(data)
    if bytes(data[:2]) == b"\xff\xd8":
        return _jpeg(data)
    raise ImageHeaderError(f"expected JPEG or PNG, the first bytes are {bytes(data[:8])!r}")


def _png(data: bytes | bytearray | memoryview) -> ImageHeader:
    if len(data) < 26 or bytes(data[12:16]) != b"IHDR":
        raise ImageHeaderError("corrupt PNG: no IHDR chunk after the signature")
    width, height, bit_depth, colour_type = struct.unpack_from(">IIBB", data, 16)
    if width == 0 or height == 0 or colour_type not in _PNG_CHANNELS:
        raise ImageHeaderError(
            f"corrupt PNG header (width {width}, height {height}, colour type {colour_type})"
        )
    depth = 8 if colour_type == 3 or bit_depth < 8 else bit_depth
    return ImageHeader("png", width, height, depth, _PNG_CHANNELS[colour_type], colour_type)


def _jpeg(data: bytes | bytearray | memoryview) -> ImageHeader:
    i, n = 2, len(data)
    while i + 4 <= n and data[i] == 0xFF:
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before
            break
        (length,) = struct.unpack_from(">H", data, i + 2)
        if marker in _JPEG_SOF:
            if length < 8 or i + 10 > n:
                break
            precision, height, width, components = struct.unpack_from(">BHHB", data, i + 4)
            if width == 0 or height == 0:
                break
            return ImageHeader("jpeg", width, height, precision, components)
        if length < 2:
            break
        i += 2 + length
    raise ImageHeaderError("corrupt JPEG: no frame header (width, height) before its data")


_PNM_CHANNELS = {b"P5": 1, b"P6": 3}
"""Binary PGM (grey) and PPM (RGB) magic -> samples per pixel."""
_PNM_HEADER_MAX = 4096
"""A PNM header (magic, width, height, maxval and comments) longer than this is refused."""


def pnm_header(data: bytes | bytearray | memoryview) -> ImageHeader:
    """The header of a binary PGM (``P5``) or PPM (``P6``) in ``data``: width, height and
    maxval (1-65535; above 255: 16 bits a sample), separated by whitespace, ``#`` comments
    to the end of their line; ImageHeaderError for anything else."""
    magic = bytes(data[:2])
    if magic not in _PNM_CHANNELS:
        raise ImageHeaderError(
            f"expected a binary PGM or PPM (P5, P6), the first bytes are {magic!r}"
        )
    head = bytes(data[2:_PNM_HEADER_MAX])
    fields: list[int] = []
    i = 0
    while len(fields) < 3:
        while i < len(head) and head[i : i + 1].isspace():
            i += 1
        if head[i : i + 1] == b"#":
            end = head.find(b"\n", i)
            if end < 0:
                break
            i = end + 1
            continue
        j = i
        while j < len(head) and head[j : j + 1].isdigit():
            j += 1
        if j == i or j >= len(head) or not head[j : j + 1].isspace():
            break
        fields.append(int(head[i:j]))
        i = j
    if len(fields) < 3:
        raise ImageHeaderError(
            f"corrupt {magic.decode()} header: expected width, height and maxval within "
            f"its first {_PNM_HEADER_MAX} bytes"
        )
    width, height, maxval = fields
    if width == 0 or height == 0 or not 0 < maxval < 65536:
        raise ImageHeaderError(
            f"corrupt {magic.decode()} header (width {width}, height {height}, maxval {maxval})"
        )
    depth = 16 if maxval > 255 else 8
    # one whitespace byte after maxval, then the pixels
    return ImageHeader("pnm", width, height, depth, _PNM_CHANNELS[magic], data_offset=2 + i + 1)


_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
"""The whole IEND chunk (no data, so always the same 12 bytes), a PNG's last."""
_PNG_MAX_CHUNK = 0x7FFFFFFF
"""The PNG specification's largest chunk length, bytes."""


def image_damage(
    data: bytes | bytearray | memoryview, header: ImageHeader, crc: bool = True
) -> str | None:
    """Why the image in ``data`` (whose ``header`` :func:`image_header` or
    :func:`pnm_header` read) cannot be decoded whole, in a phrase that names the format
    ("a PNG cut short: the file ends inside its IDAT chunk (6307 of 8192 bytes present)"),
    or None when nothing says so.

    A PNG's chunks are walked from the signature to IEND: one that the file ends inside, a
    length or type that is no chunk's, no IDAT before IEND, and with ``crc`` a critical
    chunk (IHDR, PLTE, IDAT, IEND) failing its CRC check are damage; bytes after IEND and
    ancillary chunks failing their CRC are not (libpng ignores them too). Without ``crc`` a
    file ending in the IEND chunk is taken as whole without the walk (what a file's last
    bytes show: a PNG cut short never ends so). A PNM is damaged when it is shorter than
    its header and pixels; a JPEG is not checked (None).
    """
    if header.format == "pnm" and header.data_offset is not None:
        need = header.width * header.height * header.channels * (header.bit_depth // 8)
        have = len(data) - header.data_offset
        if have < need:
            return f"a PGM/PPM cut short: {max(have, 0)} of its {need} bytes of pixels present"
        return None
    if header.format != "png":
        return None
    n = len(data)
    if not crc and n >= 20 and bytes(data[n - 12 :]) == _PNG_IEND:
        return None
    pos, image_data = len(PNG_SIGNATURE), False
    while True:
        if pos + 8 > n:
            return f"a PNG cut short: the file ends after {n} bytes, before its IEND chunk"
        length, kind = struct.unpack_from(">I4s", data, pos)
        if not kind.isalpha() or length > _PNG_MAX_CHUNK:
            return f"a corrupted PNG: no chunk at byte {pos} (length {length}, type {kind!r})"
        name = kind.decode("ascii")
        end = pos + 12 + length
        if end > n:
            present = min(max(n - pos - 8, 0), length)
            return (
                f"a PNG cut short: the file ends inside its {name} chunk ({present} of "
                f"{length} bytes present)"
            )
        if crc and name[0].isupper():
            (stored,) = struct.unpack_from(">I", data, pos + 8 + length)
            if zlib.crc32(memoryview(data)[pos + 4 : pos + 8 + length]) != stored:
                return f"a corrupted PNG: its {name} chunk at byte {pos} fails its CRC check"
        if name == "IEND":
            return None if image_data else "a corrupted PNG: no image data (IDAT) before IEND"
        image_data = image_data or name == "IDAT"
        pos = end
