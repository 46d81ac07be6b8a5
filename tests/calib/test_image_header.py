"""calib.image_header: the size a PNG or JPEG claims, read before anything is decoded."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from trifuse.calib.image_header import ImageHeaderError, image_header


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
