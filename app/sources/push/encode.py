"""Encoding push messages (the client side): images to parts, a frame to one message.

The message layout is :mod:`app.sources.push.protocol`'s; the console decodes with
:mod:`app.sources.push.decode`.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame
from trifuse.app.sources.push.protocol import (
    DEFAULT_SCALE,
    ENCODINGS,
    Part,
    PushError,
    encode_message,
)
from trifuse.calib.rig import MODALITIES
from trifuse.calib.units import UINT16_MAX


def _imencode(ext: str, image: np.ndarray, params: Sequence[int] = ()) -> bytes:
    ok, buf = cv2.imencode(ext, image, list(params))
    if not ok:
        raise PushError(f"OpenCV could not encode a {image.shape} {image.dtype} image as {ext}")
    return buf.tobytes()


def encode_part(
    kind: str,
    image: np.ndarray,
    encoding: str,
    *,
    scale: float | None = None,
    offset: float | None = None,
    jpeg_quality: int = 90,
    default_scale: float = 1.0,
) -> Part:
    """Encode one image.

    Colour (``jpeg``, ``png``, ``raw8``): (H, W, 3) uint8 RGB. 16-bit (``png16``,
    ``raw16``): a uint16 array is sent as raw counts unchanged (with ``scale``/``offset``
    if given); any other numeric array as ``counts = round((value - offset) / scale)``
    clipped to 0..65535, NaN -> 0 (``scale`` defaulting to ``default_scale``, and then
    always written into the header). ``raw32f``: the values as little-endian float32.
    """
    image = np.asarray(image)
    if encoding in ("jpeg", "png", "raw8"):
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise PushError(
                f"{kind}: {encoding} needs an (H, W, 3) uint8 RGB image, got shape "
                f"{image.shape} {image.dtype}"
            )
        h, w = image.shape[:2]
        if encoding == "raw8":
            data = np.ascontiguousarray(image).tobytes()
        else:
            bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
            params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if encoding == "jpeg" else []
            data = _imencode(".jpg" if encoding == "jpeg" else ".png", bgr, params)
        return Part(kind, encoding, w, h, data)
    if image.ndim != 2:
        raise PushError(f"{kind}: {encoding} needs an (H, W) image, got shape {image.shape}")
    h, w = image.shape
    if encoding == "raw32f":
        data = np.ascontiguousarray(image, dtype="<f4").tobytes()
        return Part(kind, encoding, w, h, data)
    if encoding not in ("png16", "raw16"):
        raise PushError(f"{kind}: unknown encoding {encoding!r}")
    if image.dtype == np.uint16:
        counts = image
    else:
        s = default_scale if scale is None else scale
        o = 0.0 if offset is None else offset
        v = (np.asarray(image, dtype=np.float64) - o) / s
        v = np.where(np.isfinite(v), v, 0.0)
        counts = np.clip(np.rint(v), 0, UINT16_MAX).astype(np.uint16)
        scale, offset = s, offset  # always explicit: the receiver's default may differ
    if encoding == "png16":
        data = _imencode(".png", counts, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    else:
        data = np.ascontiguousarray(counts, dtype="<u2").tobytes()
    return Part(kind, encoding, w, h, data, scale, offset)


def _guess_modality(frame: Frame) -> str:
    if frame.distance_m is not None:
        return "tof"
    if frame.image.ndim == 3:
        return "color"
    raise PushError(
        f"frame of {frame.sensor!r}: a single-channel image without a distance may be "
        "thermal or a TOF amplitude: pass modality='thermal' or 'tof'"
    )


def encode_frame(
    frame: Frame,
    modality: str | None = None,
    *,
    color_encoding: str = "jpeg",
    jpeg_quality: int = 90,
    value_encoding: str = "png16",
    ack: bool = False,
) -> bytes:
    """One :class:`Frame` as a push message.

    Args:
        frame: colour (H, W, 3) uint8 RGB; thermal (H, W) kelvin; TOF amplitude (H, W)
            with ``distance_m`` (H, W) metres (NaN invalid) or None.
        modality: ``color``, ``thermal`` or ``tof``; guessed when the frame tells it
            (3 channels: colour; a distance: TOF).
        color_encoding: ``jpeg`` (default, ``jpeg_quality``), ``png`` or ``raw8``.
        value_encoding: thermal and TOF: ``png16`` (default: centi-kelvin, amplitude
            counts, millimetres, as in capture directories), ``raw16`` (same counts,
            uncompressed) or ``raw32f`` (float32, exact). A uint16 image is sent as raw
            counts unchanged (receiver's default scale).
        ack: ask the console to acknowledge the message.
    """
    modality = modality or _guess_modality(frame)
    if modality not in MODALITIES:
        raise PushError(f"modality: expected one of {list(MODALITIES)}, got {modality!r}")
    if modality == "color":
        if color_encoding not in ENCODINGS["color"]:
            raise PushError(
                f"color_encoding: expected one of {ENCODINGS['color']}, got {color_encoding!r}"
            )
        parts = [encode_part("image", frame.image, color_encoding, jpeg_quality=jpeg_quality)]
    else:
        if value_encoding not in ENCODINGS[modality]:
            raise PushError(
                f"value_encoding: expected one of {ENCODINGS[modality]}, got {value_encoding!r}"
            )
        parts = [
            encode_part(
                "image",
                frame.image,
                value_encoding,
                default_scale=DEFAULT_SCALE[(modality, "image")],
            )
        ]
        if modality == "tof" and frame.distance_m is not None:
            parts.append(
                encode_part(
                    "distance",
                    frame.distance_m,
                    value_encoding,
                    default_scale=DEFAULT_SCALE[("tof", "distance")],
                )
            )
    return encode_message(frame.sensor, frame.stamp_ns, parts, ack=ack)
