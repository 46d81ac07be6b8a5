"""calib.image_header: the size a PNG or JPEG claims, read before anything is decoded."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from trifuse.calib.image_header import ImageHeaderError, image_damage, image_header, pnm_header


def _encode(ext: str, image: np.ndarray, params: tuple[int, ...] = ()) -> bytes:
    ok, data = cv2.imencode(ext, image, list(params))
    assert ok
    return data.tobytes()


@pytest.mark.parametrize(
    ("ext", "image", "params", "want"),
    [
        (".png", np.zeros((7, 11), np.uint16), (), ("png", 11, 7, 16, 1, 0)),
        (".png", np.zeros((7, 11, 3), np.uint8), (), ("png", 11, 7, 8, 3, 2)),
        (".png", np.zeros((7, 11, 4), np.uint8), (), ("png", 11, 7, 8, 4, 6)),
        (".jpg", np.zeros((7, 11, 3), np.uint8), (), ("jpeg", 11, 7, 8, 3, None)),
        (".jpg", np.zeros((7, 11), np.uint8), (), ("jpeg", 11, 7, 8, 1, None)),
        (
            ".jpg",
            np.zeros((9, 13, 3), np.uint8),
            (cv2.IMWRITE_JPEG_PROGRESSIVE, 1),
            ("jpeg", 13, 9, 8, 3, None),
        ),
    ],
)
def test_what_opencv_writes_reads_back(ext, image, params, want) -> None:
    h = image_header(_encode(ext, image, params))
    assert (h.format, h.width, h.height, h.bit_depth, h.channels, h.png_colour_type) == want
    decoded = cv2.imdecode(np.frombuffer(_encode(ext, image, params), np.uint8), -1)
    assert decoded.shape[:2] == (h.height, h.width)


def test_a_frame_header_after_large_metadata_segments_is_found() -> None:
    """Cameras put tens of kilobytes of EXIF (APP1) and more before the frame header."""
    jpeg = _encode(".jpg", np.zeros((5, 6, 3), np.uint8))
    app1 = b"\xff\xe1" + struct.pack(">H", 65535) + bytes(65533)
    data = jpeg[:2] + app1 * 3 + jpeg[2:]
    h = image_header(memoryview(data))
    assert (h.width, h.height) == (6, 5)


def test_a_claim_is_read_without_the_data() -> None:
    """The attack of issue 29: a small file claiming 30000 x 30000 pixels; the header gives
    the claim for the caller to refuse."""
    jpeg = bytearray(_encode(".jpg", np.zeros((8, 8, 3), np.uint8)))
    sof = jpeg.index(b"\xff\xc0")
    jpeg[sof + 5 : sof + 9] = struct.pack(">HH", 30000, 30000)
    h = image_header(bytes(jpeg[: sof + 20]))
    assert (h.width, h.height) == (30000, 30000)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "expected JPEG or PNG"),
        (b"GIF89a....", "expected JPEG or PNG"),
        (b"\x89PNG\r\n\x1a\n" + bytes(8), "no IHDR chunk"),
        (b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR" + bytes(8) + b"\x08\x02", "width 0, height 0"),
        (b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR" + struct.pack(">II", 4, 4) + b"\x08\x05", "type 5"),
        (b"\xff\xd8", "no frame header"),
        (b"\xff\xd8\xff\xda\0\x08" + bytes(8), "no frame header"),  # scan before a frame
        (b"\xff\xd8\xff\xe0\0\x01", "no frame header"),  # a length shorter than itself
        (b"\xff\xd8\xff\xc0\0\x11\x08\0\0\0\0\x03", "no frame header"),  # 0 x 0
        (b"\xff\xd8\xff\xc0\0\x11\x08\0\x10", "no frame header"),  # cut in the frame header
    ],
)
def test_what_is_no_readable_header_is_one_error(data, message) -> None:
    with pytest.raises(ImageHeaderError, match=message):
        image_header(data)


# -- damage: what a header cannot say (issue 33) --------------------------------------------


def _chunks(png: bytes) -> list[tuple[int, str, int]]:
    """(offset, type, length) of every chunk of a whole PNG."""
    out, pos = [], 8
    while pos < len(png):
        length, kind = struct.unpack_from(">I4s", png, pos)
        out.append((pos, kind.decode(), length))
        pos += 12 + length
    return out


def _with_chunk(png: bytes, kind: bytes, data: bytes, crc: int | None = None) -> bytes:
    """``png`` with a chunk inserted after IHDR (its right CRC unless ``crc`` is given)."""
    body = kind + data
    chunk = struct.pack(">I", len(data)) + body
    chunk += struct.pack(">I", zlib.crc32(body) if crc is None else crc)
    return png[:33] + chunk + png[33:]


def test_a_whole_png_is_whole_and_every_cut_of_it_is_not() -> None:
    """Every PNG OpenCV writes is whole, with or without CRCs checked, also with bytes after
    IEND (decoders ignore them); cut anywhere after its header, it is found cut short in
    the chunk the cut is in, before any decoder meets it."""
    rng = np.random.default_rng(1)
    for image in (
        rng.integers(0, 65535, (40, 50), dtype=np.uint16),
        rng.integers(0, 255, (60, 70, 3), dtype=np.uint8),
    ):
        png = _encode(".png", image)
        h = image_header(png)
        assert image_damage(png, h) is None and image_damage(png, h, crc=False) is None
        assert image_damage(png + b"trailing bytes", h) is None
        assert image_damage(png + b"trailing bytes", h, crc=False) is None
        chunks = _chunks(png)
        assert chunks[0][1] == "IHDR" and chunks[-1][1] == "IEND"
        for cut in range(33, len(png), 7):
            for crc in (True, False):
                why = image_damage(png[:cut], h, crc=crc)
                assert why is not None and why.startswith("a PNG cut short: "), (cut, why)
                inside = [k for pos, k, n in chunks if pos + 8 <= cut < pos + 12 + n]
                if inside:
                    assert f"inside its {inside[0]} chunk" in why, (cut, why)


def test_a_critical_chunk_failing_its_crc_is_corrupted_an_ancillary_one_is_not() -> None:
    png = _encode(".png", np.arange(30 * 20, dtype=np.uint8).reshape(30, 20))
    h = image_header(png)
    pos, _, length = next(c for c in _chunks(png) if c[1] == "IDAT")
    flipped = bytearray(png)
    flipped[pos + 8 + length // 2] ^= 0x01
    assert image_damage(bytes(flipped), h) == (
        f"a corrupted PNG: its IDAT chunk at byte {pos} fails its CRC check"
    )
    assert image_damage(bytes(flipped), h, crc=False) is None  # the length check only
    text = _with_chunk(png, b"tEXt", b"Comment\0hello", crc=0)
    assert image_damage(text, h) is None  # libpng warns and goes on: so do we
    assert image_damage(_with_chunk(png, b"x1y2", b"", None), h).startswith(
        "a corrupted PNG: no chunk at byte 33"
    )
    no_data = png[:33] + png[-12:]  # IHDR then IEND
    assert image_damage(no_data, h) == "a corrupted PNG: no image data (IDAT) before IEND"


def test_a_pnm_is_whole_when_it_holds_its_pixels_a_jpeg_is_not_checked() -> None:
    for image in (np.zeros((10, 12), np.uint16), np.zeros((10, 12, 3), np.uint8)):
        pnm = _encode(".pgm" if image.ndim == 2 else ".ppm", image)
        h = pnm_header(pnm)
        need = image.size * image.itemsize
        assert h.data_offset == len(pnm) - need and image_damage(pnm, h) is None
        assert image_damage(pnm[:-1], h) == (
            f"a PGM/PPM cut short: {need - 1} of its {need} bytes of pixels present"
        )
    jpeg = _encode(".jpg", np.zeros((8, 8, 3), np.uint8))
    assert image_damage(jpeg[:40], image_header(jpeg)) is None
