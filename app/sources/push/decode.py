"""Decoding push messages (the console's side): every header field and part checked
against the console's sensors and limits, then the images decoded to the in-memory
convention (colour (H, W, 3) uint8 RGB; thermal kelvin, TOF amplitude and distance metres
as (H, W) float32, NaN where invalid).

The message layout is :mod:`app.sources.push.protocol`'s; drivers encode with
:mod:`app.sources.push.encode`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.protocol import (
    DEFAULT_SCALE,
    ENCODINGS,
    MAX_SCALE_OR_OFFSET,
    MAX_SIDE_PX,
    PART_KEYS,
    MessageHeader,
    PushError,
    parse_header,
)
from trifuse.calib.image_header import ImageHeaderError, image_header
from trifuse.calib.numbers import check_finite, is_int

_ZERO_INVALID = {("thermal", "image"), ("tof", "distance")}  # 16-bit 0 counts -> NaN
_BYTES_PER_PIXEL = {"raw8": 3, "raw16": 2, "raw32f": 4}


def decode_message(
    data: bytes | bytearray | memoryview,
    modalities: Mapping[str, str],
    image_sizes: Mapping[str, tuple[int, int]],
    *,
    max_message_bytes: int,
    max_pixels: int,
) -> tuple[MessageHeader, Frame]:
    """Validate and decode one message into a Frame. Raises PushError.

    Args:
        data: the whole message.
        modalities: sensor -> modality (``color``, ``thermal``, ``tof``) of the sensors
            the console accepts.
        image_sizes: sensor -> (width, height) to enforce, pixels (where known).
        max_message_bytes: larger messages are rejected.
        max_pixels: largest image (width * height) a part may declare.
    """
    header, pos = parse_header(data, max_message_bytes)
    sensor = header.sensor
    where = f"sensor {sensor!r} at stamp_ns {header.stamp_ns}"
    modality = modalities.get(sensor)
    if modality is None:
        raise PushError(f"unknown sensor {sensor!r}: this console accepts {list(modalities)}")
    seen: dict[str, dict[str, Any]] = {}
    total = 0
    for i, part in enumerate(header.parts):
        kind = _check_part(
            part, f"{where}, part {i}", sensor, modality, seen, image_sizes.get(sensor), max_pixels
        )
        seen[kind] = part
        total += part["length"]
    if "image" not in seen:
        raise PushError(f"{where}: no 'image' part")
    if pos + total != len(data):
        raise PushError(
            f"{where}: the parts' lengths add up to {total} bytes, the payload has "
            f"{len(data) - pos}"
        )
    if "distance" in seen and (seen["distance"]["width"], seen["distance"]["height"]) != (
        seen["image"]["width"],
        seen["image"]["height"],
    ):
        raise PushError(f"{where}: the distance and the amplitude image differ in size")
    arrays = {}
    view = memoryview(data)
    for i, part in enumerate(header.parts):
        n = part["length"]
        chunk = bytes(view[pos : pos + n])
        pos += n
        arrays[part["kind"]] = decode_part(
            modality, part, chunk, f"{where}, part {i} ({part['kind']})"
        )
    frame = Frame(sensor, header.stamp_ns, arrays["image"], arrays.get("distance"))
    return header, frame


def _check_part(
    part: Mapping[str, Any],
    pwhere: str,
    sensor: str,
    modality: str,
    seen: Mapping[str, Any],
    want: tuple[int, int] | None,
    max_pixels: int,
) -> str:
    """Check one part's header (``seen``: the kinds before it; ``want``: the sensor's
    (width, height), if known); returns its kind. Raises PushError."""
    kinds = ("image", "distance") if modality == "tof" else ("image",)
    unknown = sorted(set(part) - PART_KEYS)
    if unknown:
        raise PushError(f"{pwhere}: unknown keys {unknown} (allowed: {sorted(PART_KEYS)})")
    kind = part.get("kind")
    if kind not in kinds:
        raise PushError(
            f"{pwhere}: kind must be one of {list(kinds)} for a {modality} sensor, got {kind!r}"
        )
    if kind in seen:
        raise PushError(f"{pwhere}: a second {kind!r} part")
    encoding = part.get("encoding")
    if encoding not in ENCODINGS[modality]:
        raise PushError(
            f"{pwhere} ({kind}): encoding must be one of {list(ENCODINGS[modality])} "
            f"for a {modality} sensor, got {encoding!r}"
        )
    for key in ("width", "height", "length"):
        v = part.get(key)
        if not is_int(v) or v < 0:
            raise PushError(f"{pwhere}: '{key}' must be a non-negative integer, got {v!r}")
    w, h = part["width"], part["height"]
    if not (0 < w <= MAX_SIDE_PX and 0 < h <= MAX_SIDE_PX) or w * h > max_pixels:
        raise PushError(
            f"{pwhere}: bad size {w}x{h} (width x height): each side 1..{MAX_SIDE_PX}, "
            f"at most {max_pixels} pixels"
        )
    if want is not None and (w, h) != want:
        raise PushError(
            f"{pwhere}: bad size: expected {want[0]}x{want[1]} (width x height) for "
            f"{sensor!r}, got {w}x{h}"
        )
    if ("scale" in part or "offset" in part) and encoding not in ("png16", "raw16"):
        raise PushError(
            f"{pwhere}: 'scale'/'offset' apply to 16-bit encodings only, not {encoding}"
        )
    if "scale" in part and _number(part["scale"], f"{pwhere}: scale") == 0:
        raise PushError(f"{pwhere}: scale must not be 0")
    if "offset" in part:
        _number(part["offset"], f"{pwhere}: offset")
    return kind


def _number(value: Any, what: str) -> float:
    number = check_finite(value, what, PushError)
    if abs(number) > MAX_SCALE_OR_OFFSET:
        raise PushError(
            f"{what}: expected a finite number of magnitude at most {MAX_SCALE_OR_OFFSET:g} "
            f"(16-bit counts * scale + offset must fit a float32), got {value!r}"
        )
    return number


def decode_part(modality: str, part: Mapping[str, Any], data: bytes, what: str) -> np.ndarray:
    """Check one part's header against its bytes and decode it to the in-memory convention
    (colour (H, W, 3) uint8 RGB; otherwise (H, W) float32 values, NaN where invalid)."""
    kind = part["kind"]
    encoding = part["encoding"]
    w, h = part["width"], part["height"]
    if encoding in _BYTES_PER_PIXEL:
        want = w * h * _BYTES_PER_PIXEL[encoding]
        if len(data) != want:
            raise PushError(f"{what}: {encoding} {w}x{h} needs {want} bytes, got {len(data)}")
    if encoding == "raw8":
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3).copy()
    if encoding == "raw32f":
        return np.frombuffer(data, dtype="<f4").reshape(h, w).astype(np.float32)
    if encoding in ("jpeg", "png", "png16"):
        try:
            header = image_header(data)
        except ImageHeaderError as exc:
            raise PushError(f"{what}: {exc}") from None
        fw, fh, depth, ctype = header.width, header.height, header.bit_depth, header.png_colour_type
        if header.format != ("jpeg" if encoding == "jpeg" else "png"):
            raise PushError(f"{what}: {encoding} data that is a {header.format.upper()}")
        if encoding != "jpeg":
            if encoding == "png16" and (depth != 16 or ctype != 0):
                raise PushError(
                    f"{what}: png16 needs a 16-bit grey PNG, got bit depth {depth}, colour "
                    f"type {ctype}"
                )
            if encoding == "png" and depth != 8:
                raise PushError(f"{what}: png needs an 8-bit PNG, got bit depth {depth}")
        if (fw, fh) != (w, h):
            raise PushError(
                f"{what}: the header says {w}x{h} (width x height), the {encoding} data is "
                f"{fw}x{fh}"
            )
        flags = cv2.IMREAD_UNCHANGED if encoding == "png16" else cv2.IMREAD_COLOR
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
        if image is None or image.shape[:2] != (h, w):
            raise PushError(f"{what}: corrupt {encoding} data (OpenCV could not decode it)")
        if encoding != "png16":
            return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        counts = image
    else:  # raw16
        counts = np.frombuffer(data, dtype="<u2").reshape(h, w)
    scale = part.get("scale", DEFAULT_SCALE[(modality, kind)])
    offset = part.get("offset", 0.0)
    values = (counts.astype(np.float64) * scale + offset).astype(np.float32)
    if (modality, kind) in _ZERO_INVALID:
        values[counts == 0] = np.nan
    return values
