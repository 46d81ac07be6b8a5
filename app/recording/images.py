"""Image payloads of recordings and ROS 2 bags -> the program's arrays (and back).

Raw images follow the ROS / Foxglove encodings (``mono8``, ``mono16``, ``16UC1``,
``16SC1``, ``32FC1``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``); rows may be padded
(``step``) and 16/32-bit samples big-endian. Compressed images are JPEG or PNG (8- or
16-bit). BGR appears only at the OpenCV calls.

Sizes before pixels: every decoder takes the size the rig gives the image's sensor
(``size``, ``(width, height)``) and compares it with what the image claims (a raw image's
width and height, a JPEG's frame header, a PNG's IHDR chunk) before anything is allocated:
another size raises :class:`~app.recording.errors.ImageSizeError`. Without a rig the claim
may not exceed :data:`calib.rig.MAX_IMAGE_PIXELS`. A compressed image of any other format
is refused (OpenCV would decode a dozen more, each with its own header to trust).
"""

from __future__ import annotations

import cv2
import numpy as np

from trifuse.app.recording.errors import ImageSizeError
from trifuse.calib.image_header import ImageHeaderError, image_header
from trifuse.calib.rig import MAX_IMAGE_PIXELS

# encoding -> (numpy dtype, channels)
RAW_ENCODINGS: dict[str, tuple[str, int]] = {
    "mono8": ("u1", 1),
    "8UC1": ("u1", 1),
    "mono16": ("u2", 1),
    "16UC1": ("u2", 1),
    "16SC1": ("i2", 1),
    "32FC1": ("f4", 1),
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "8UC3": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
}


def check_size(what: str, width: int, height: int, size: tuple[int, int] | None) -> None:
    """ImageSizeError unless a ``what`` (``"JPEG"``, ``"raw image"`` ...) of ``width`` x
    ``height`` pixels has the rig's ``size`` (width, height), or, with ``size`` None, at
    most :data:`calib.rig.MAX_IMAGE_PIXELS` pixels."""
    if size is not None:
        if (width, height) != tuple(size):
            raise ImageSizeError(
                f"{what} of {width}x{height} pixels, the rig says {size[0]}x{size[1]}"
            )
    elif width * height > MAX_IMAGE_PIXELS:
        raise ImageSizeError(
            f"{what} of {width}x{height} pixels: more than the {MAX_IMAGE_PIXELS} pixels of "
            "the largest image a rig describes"
        )


def compressed_size(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` of a compressed image from its header (``"JPEG"``: the
    first frame header; ``"PNG"``: the IHDR chunk), nothing decoded. ValueError for any
    other format, or a header without a size."""
    try:
        header = image_header(data)
    except ImageHeaderError as exc:
        raise ValueError(f"compressed image: {exc}") from None
    return header.format.upper(), header.width, header.height


def _decode_compressed(data: bytes, flags: int, size: tuple[int, int] | None) -> np.ndarray:
    """OpenCV's decoding of a JPEG/PNG whose header was checked against ``size`` first."""
    fmt, width, height = compressed_size(data)
    check_size(fmt, width, height, size)
    if width == 0 or height == 0:
        raise ValueError(f"corrupt {fmt}: its header says {width}x{height} pixels")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None or image.shape[:2] != (height, width):
        raise ValueError(f"corrupt or unreadable {fmt} ({len(data)} bytes)")
    return image


def raw_plane(
    data: bytes,
    width: int,
    height: int,
    step: int,
    encoding: str,
    big_endian: bool = False,
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """The pixels of a raw image as (H, W) or (H, W, C) in their own dtype (a view where
    possible). ImageSizeError unless ``width`` x ``height`` is the rig's ``size`` (see
    :func:`check_size`); ValueError for an unknown encoding or a size that does not add up."""
    check_size("raw image", width, height, size)
    if encoding not in RAW_ENCODINGS:
        raise ValueError(f"unsupported encoding {encoding!r} (supported: {sorted(RAW_ENCODINGS)})")
    kind, channels = RAW_ENCODINGS[encoding]
    dtype = np.dtype(kind).newbyteorder(">" if big_endian else "<")
    row = width * channels * dtype.itemsize
    if width <= 0 or height <= 0:
        raise ValueError(f"image size {width}x{height}: expected positive sizes")
    if step < row:
        raise ValueError(f"step {step} is less than a row of {width} {encoding} pixels ({row})")
    if len(data) < step * (height - 1) + row:
        raise ValueError(
            f"{len(data)} bytes of data for a {width}x{height} {encoding} image with step "
            f"{step} (expected {step * height})"
        )
    need = step * (height - 1) + row
    if step * height <= len(data):
        rows = np.frombuffer(data, np.uint8, count=step * height).reshape(height, step)
    else:  # the last row without its padding
        rows = np.zeros((height, step), np.uint8)
        rows.reshape(-1)[:need] = np.frombuffer(data, np.uint8, count=need)
    plane = np.ascontiguousarray(rows[:, :row]).view(dtype)
    plane = plane.reshape(height, width, channels) if channels > 1 else plane.reshape(height, width)
    if big_endian and dtype.itemsize > 1:
        plane = plane.astype(dtype.newbyteorder("="))
    return plane


def rgb_from_raw(plane: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a raw colour (or grey) image."""
    if plane.dtype != np.uint8:
        raise ValueError(f"expected an 8-bit colour image, got encoding {encoding!r}")
    if plane.ndim == 2:
        return np.repeat(plane[:, :, None], 3, axis=2)
    if encoding in ("bgr8", "8UC3"):
        return np.array(plane[:, :, 2::-1], order="C")
    if encoding == "bgra8":
        return np.array(plane[:, :, 2::-1], order="C")
    return np.array(plane[:, :, :3], order="C")


def rgb_from_compressed(data: bytes, size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a JPEG/PNG (grey is replicated), its header checked against
    the rig's ``size`` first (:func:`check_size`); ValueError if corrupt."""
    return _decode_compressed(data, cv2.IMREAD_COLOR_RGB, size)


def plane_from_compressed(
    data: bytes, format: str = "", size: tuple[int, int] | None = None
) -> np.ndarray:
    """(H, W) of a single-channel compressed image (8- or 16-bit PNG ...), values as
    stored, its header checked against the rig's ``size`` first (:func:`check_size`). ROS
    ``compressedDepth`` payloads (a 12-byte header before the PNG) are accepted."""
    if "compresseddepth" in format.lower().replace(" ", "") and data[:4] != b"\x89PNG":
        data = data[12:]
    image = _decode_compressed(data, cv2.IMREAD_UNCHANGED, size)
    if image.ndim == 3:
        if not (
            np.array_equal(image[:, :, 0], image[:, :, 1])
            and np.array_equal(image[:, :, 0], image[:, :, 2])
        ):
            raise ValueError("expected a single-channel image, got colour")
        image = image[:, :, 0]
    return image


def values(
    plane: np.ndarray,
    scale: float = 1.0,
    offset: float = 0.0,
    invalid: tuple[float, ...] = (),
) -> np.ndarray:
    """(H, W) float32 ``plane * scale + offset``, NaN where the stored value is one of
    ``invalid`` or the result is not finite (float64 arithmetic, one rounding)."""
    if plane.ndim != 2:
        raise ValueError(f"expected a single-channel image, got shape {plane.shape}")
    if scale == 1.0 and offset == 0.0 and plane.dtype == np.float32:
        out = plane.astype(np.float32, copy=True)
    else:
        out = (plane * np.float64(scale) + np.float64(offset)).astype(np.float32)
    for v in invalid:
        out[plane == v] = np.nan
    out[~np.isfinite(out)] = np.nan
    return out
