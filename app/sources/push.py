"""Push ingest: on-robot drivers send frames to the console over a WebSocket.

The protocol (docs/FORMATS.md, "Push ingest protocol") is one *binary* WebSocket message
per frame::

    offset 0      4 bytes   magic b"TFP1" (trifuse push, version 1)
    offset 4      4 bytes   H = length of the header, unsigned 32-bit little-endian
    offset 8      H bytes   header: a JSON object, UTF-8
    offset 8 + H  the rest  payload: the parts' bytes, concatenated in header order

The header names the sensor, the time stamp and the parts (a TOF frame has two: its
amplitude ``image`` and its ``distance``)::

    {"sensor": "thermal_left", "stamp_ns": 1712345678901234567, "ack": false,
     "parts": [{"kind": "image", "encoding": "png16", "width": 382, "height": 288,
                "length": 81234, "scale": 0.01, "offset": 0.0}]}

The server answers a message only when it rejects it, or when the header asks for an
acknowledgement (``"ack": true``), with a JSON *text* message
``{"seq": n, "ok": false, "error": "...", ...}`` / ``{"seq": n, "ok": true, ...}`` where ``n``
counts the connection's messages from 1. A rejected message changes nothing else: the
connection and the other sensors carry on.

Server side: :class:`PushSource` (a :class:`~app.sources.base.FrameSource` whose frames are
the pushed ones, newest frame wins per sensor) and :func:`make_push_router` (the WebSocket
endpoint ``/ingest`` for the console's FastAPI app). Client side: :func:`encode_frame`,
:func:`encode_message`, :class:`PushClient` (blocking) and :class:`AsyncPushClient`.

Only the server part imports FastAPI (inside :func:`make_push_router`); a driver needs
numpy, OpenCV and ``websockets``.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from app.sources.base import FrameSource
from app.sources.frames import Frame
from app.sources.slots import NewestFrameSlots
from calib.numbers import check_finite
from calib.rig import MODALITIES, Rig

if TYPE_CHECKING:
    from fastapi import APIRouter

MAGIC = b"TFP1"
"""First four bytes of every push message (protocol version 1)."""
PREFIX = struct.Struct("<4sI")
"""Magic and header length, little-endian."""
DEFAULT_MAX_MESSAGE_BYTES = 16 * 1024 * 1024
MAX_HEADER_BYTES = 64 * 1024
DEFAULT_MAX_PIXELS = 1 << 25
MAX_SIDE_PX = 16384
MAX_SCALE_OR_OFFSET = 1e30
"""Largest ``scale``/``offset`` of a 16-bit part (65535 * 1e30 + 1e30 fits a float32)."""
INGEST_PATH = "/ingest"

ENCODINGS: dict[str, tuple[str, ...]] = {
    "color": ("jpeg", "png", "raw8"),
    "thermal": ("png16", "raw16", "raw32f"),
    "tof": ("png16", "raw16", "raw32f"),
}
"""Encodings each modality accepts (a TOF's distance too)."""

DEFAULT_SCALE: dict[tuple[str, str], float] = {
    ("thermal", "image"): 0.01,  # centi-kelvin -> kelvin
    ("tof", "image"): 1.0,  # amplitude counts
    ("tof", "distance"): 0.001,  # millimetres -> metres
}
"""Default ``scale`` of 16-bit parts: value = counts * scale + offset."""

_ZERO_INVALID = {("thermal", "image"), ("tof", "distance")}  # 16-bit 0 counts -> NaN
_HEADER_KEYS = {"sensor", "stamp_ns", "ack", "parts"}
_PART_KEYS = {"kind", "encoding", "width", "height", "length", "scale", "offset"}
_BYTES_PER_PIXEL = {"raw8": 3, "raw16": 2, "raw32f": 4}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


class PushError(ValueError):
    """A push message is not what the protocol expects; the message says what and why."""


class PushRejected(RuntimeError):
    """The console rejected a message the client sent (its error reply)."""

    def __init__(self, reply: Mapping[str, Any]) -> None:
        super().__init__(str(reply.get("error", reply)))
        self.reply = dict(reply)


# -- encoding (client side) -----------------------------------------------------------------


@dataclass(frozen=True)
class Part:
    """One encoded image of a push message.

    Attributes:
        kind: ``image`` (colour RGB, thermal temperature, TOF amplitude) or ``distance``
            (TOF radial distance).
        encoding: ``jpeg``, ``png``, ``raw8`` (colour); ``png16``, ``raw16``, ``raw32f``
            (thermal and TOF).
        width, height: image size, pixels.
        data: the encoded bytes.
        scale, offset: 16-bit encodings only: value = counts * scale + offset (None: the
            receiver's default for the kind).
    """

    kind: str
    encoding: str
    width: int
    height: int
    data: bytes
    scale: float | None = None
    offset: float | None = None

    def header(self) -> dict[str, Any]:
        h: dict[str, Any] = {
            "kind": self.kind,
            "encoding": self.encoding,
            "width": self.width,
            "height": self.height,
            "length": len(self.data),
        }
        if self.scale is not None:
            h["scale"] = self.scale
        if self.offset is not None:
            h["offset"] = self.offset
        return h


def encode_message(
    sensor: str, stamp_ns: int, parts: Sequence[Part], *, ack: bool = False
) -> bytes:
    """Frame the parts as one push message: magic, header length, JSON header, payload."""
    header: dict[str, Any] = {
        "sensor": sensor,
        "stamp_ns": int(stamp_ns),
        "parts": [p.header() for p in parts],
    }
    if ack:
        header["ack"] = True
    head = json.dumps(header, separators=(",", ":"), allow_nan=False).encode("utf-8")
    return b"".join([PREFIX.pack(MAGIC, len(head)), head, *(p.data for p in parts)])


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
        counts = np.clip(np.rint(v), 0, 65535).astype(np.uint16)
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


# -- decoding (server side) -----------------------------------------------------------------


@dataclass(frozen=True)
class MessageHeader:
    """The parsed header of a push message."""

    sensor: str
    stamp_ns: int
    ack: bool
    parts: tuple[dict[str, Any], ...]


def parse_header(
    data: bytes | bytearray | memoryview, max_message_bytes: int
) -> tuple[MessageHeader, int]:
    """Check the framing and parse the JSON header; returns it and the payload offset."""
    if len(data) > max_message_bytes:
        raise PushError(
            f"message of {len(data)} bytes exceeds the limit of {max_message_bytes} bytes"
        )
    if len(data) < PREFIX.size:
        raise PushError(
            f"message of {len(data)} bytes is shorter than the {PREFIX.size}-byte prefix "
            f"(magic {MAGIC!r} + header length)"
        )
    magic, hlen = PREFIX.unpack_from(data, 0)
    if magic != MAGIC:
        raise PushError(f"expected the magic {MAGIC!r} at the start, got {bytes(magic)!r}")
    if hlen > MAX_HEADER_BYTES or PREFIX.size + hlen > len(data):
        raise PushError(
            f"header length {hlen} is larger than the message allows "
            f"({len(data) - PREFIX.size} bytes follow the prefix, at most {MAX_HEADER_BYTES})"
        )
    try:
        header = json.loads(bytes(data[PREFIX.size : PREFIX.size + hlen]).decode("utf-8"))
    except ValueError as exc:  # not UTF-8, not JSON, or an integer of more than 4300 digits
        raise PushError(f"header is not UTF-8 JSON: {exc}") from None
    except RecursionError:
        raise PushError("header is not UTF-8 JSON: nested too deeply") from None
    if not isinstance(header, dict):
        raise PushError(f"header: expected a JSON object, got {type(header).__name__}")
    unknown = sorted(set(header) - _HEADER_KEYS)
    if unknown:
        raise PushError(f"header: unknown keys {unknown} (allowed: {sorted(_HEADER_KEYS)})")
    sensor = header.get("sensor")
    if not isinstance(sensor, str) or not sensor:
        raise PushError(f"header: 'sensor' must be a non-empty string, got {sensor!r}")
    stamp = header.get("stamp_ns")
    if isinstance(stamp, bool) or not isinstance(stamp, int) or not 0 <= stamp < 2**63:
        raise PushError(f"header: 'stamp_ns' must be an integer in [0, 2^63), got {stamp!r}")
    ack = header.get("ack", False)
    if not isinstance(ack, bool):
        raise PushError(f"header: 'ack' must be true or false, got {ack!r}")
    parts = header.get("parts")
    if not isinstance(parts, list) or not parts or not all(isinstance(p, dict) for p in parts):
        raise PushError("header: 'parts' must be a non-empty list of objects")
    return MessageHeader(sensor, stamp, ack, tuple(parts)), PREFIX.size + hlen


def _png_info(data: bytes, what: str) -> tuple[int, int, int, int]:
    """(width, height, bit depth, colour type) from a PNG's IHDR chunk."""
    if len(data) < 33 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise PushError(f"{what}: not a PNG (no PNG signature and IHDR chunk)")
    w, h, depth, ctype = struct.unpack_from(">IIBB", data, 16)
    return w, h, depth, ctype


def _jpeg_size(data: bytes, what: str) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame segment."""
    if data[:2] != b"\xff\xd8":
        raise PushError(f"{what}: not a JPEG (no start-of-image marker)")
    i = 2
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise PushError(f"{what}: corrupt JPEG (expected a marker at byte {i})")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):
            i += 2
            continue
        (seg_len,) = struct.unpack_from(">H", data, i + 2)
        if marker in _JPEG_SOF:
            if i + 9 > n:
                break
            h, w = struct.unpack_from(">HH", data, i + 5)
            return w, h
        if marker == 0xDA:
            break
        i += 2 + seg_len
    raise PushError(f"{what}: corrupt JPEG (no start-of-frame segment)")


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
        if encoding == "jpeg":
            fw, fh = _jpeg_size(data, what)
        else:
            fw, fh, depth, ctype = _png_info(data, what)
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


# -- the source -----------------------------------------------------------------------------


class PushSource(FrameSource):
    """Frames pushed by on-robot drivers: one newest-frame slot per sensor.

    Args:
        rig: the rig whose sensors may be pushed (names, modalities, image sizes).
        sensors: without a rig: sensor name -> modality (``color``, ``thermal``, ``tof``);
            with a rig: a subset of its sensors to accept.
        image_sizes: without a rig: sensor -> (width, height) to enforce (optional).
        max_message_bytes: larger messages are rejected (default 16 MiB). The WebSocket
            server must let such messages through to be answered: run uvicorn with
            ``ws_max_size`` above this (:func:`uvicorn_ws_max_size`); beyond *its* limit
            the server closes the connection (code 1009).
        max_pixels: largest image (width * height) a part may declare.

    Attributes:
        sensors, rig: as for every source.
        modalities: sensor -> modality.
        image_sizes: sensor -> (width, height), where known.
    """

    def __init__(
        self,
        rig: Rig | None = None,
        *,
        sensors: Mapping[str, str] | Sequence[str] | None = None,
        image_sizes: Mapping[str, tuple[int, int]] | None = None,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_pixels: int = DEFAULT_MAX_PIXELS,
    ) -> None:
        if rig is not None:
            names = list(rig.names) if sensors is None else list(sensors)
            unknown = [s for s in names if s not in rig]
            if unknown:
                raise ValueError(f"sensors: {unknown} are not in the rig (sensors: {rig.names})")
            self.modalities = {s: rig[s].modality for s in names}
            self.image_sizes = {s: tuple(rig[s].image_size) for s in names}
        else:
            if not isinstance(sensors, Mapping) or not sensors:
                raise ValueError(
                    "sensors: without a rig, expected a mapping of sensor name -> modality"
                )
            bad = {s: m for s, m in sensors.items() if m not in MODALITIES}
            if bad:
                raise ValueError(
                    f"sensors: modalities must be one of {list(MODALITIES)}, got {bad}"
                )
            self.modalities = dict(sensors)
            self.image_sizes = {s: tuple(v) for s, v in (image_sizes or {}).items()}
            unknown = sorted(set(self.image_sizes) - set(self.modalities))
            if unknown:
                raise ValueError(f"image_sizes: {unknown} are not among the sensors")
        if max_message_bytes <= PREFIX.size:
            raise ValueError(
                f"max_message_bytes: expected > {PREFIX.size}, got {max_message_bytes}"
            )
        self.rig = rig
        self.sensors = list(self.modalities)
        self.max_message_bytes = int(max_message_bytes)
        self.max_pixels = int(max_pixels)
        self._slots = NewestFrameSlots(self.sensors)
        self._lock = threading.Lock()
        self._rejected = 0
        self._connections = 0
        self._last_error = ""
        # per known sensor: [rejected, since_accepted, last_error, last_rejected_s, accepted_s]
        self._by_sensor: dict[str, list[Any]] = {s: [0, 0, "", None, None] for s in self.sensors}

    # -- decoding -----------------------------------------------------------------------

    def decode(self, data: bytes | bytearray | memoryview) -> tuple[MessageHeader, Frame]:
        """Validate and decode one message into a Frame (not stored). Raises PushError."""
        header, pos = parse_header(data, self.max_message_bytes)
        sensor = header.sensor
        where = f"sensor {sensor!r} at stamp_ns {header.stamp_ns}"
        modality = self.modalities.get(sensor)
        if modality is None:
            raise PushError(f"unknown sensor {sensor!r}: this console accepts {self.sensors}")
        kinds = ("image", "distance") if modality == "tof" else ("image",)
        seen: dict[str, dict[str, Any]] = {}
        total = 0
        for i, part in enumerate(header.parts):
            pwhere = f"{where}, part {i}"
            unknown = sorted(set(part) - _PART_KEYS)
            if unknown:
                raise PushError(f"{pwhere}: unknown keys {unknown} (allowed: {sorted(_PART_KEYS)})")
            kind = part.get("kind")
            if kind not in kinds:
                raise PushError(
                    f"{pwhere}: kind must be one of {list(kinds)} for a {modality} sensor, "
                    f"got {kind!r}"
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
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise PushError(f"{pwhere}: '{key}' must be a non-negative integer, got {v!r}")
            w, h = part["width"], part["height"]
            if not (0 < w <= MAX_SIDE_PX and 0 < h <= MAX_SIDE_PX) or w * h > self.max_pixels:
                raise PushError(
                    f"{pwhere}: bad size {w}x{h} (width x height): each side 1..{MAX_SIDE_PX}, "
                    f"at most {self.max_pixels} pixels"
                )
            want = self.image_sizes.get(sensor)
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

    def accept(
        self, data: bytes | bytearray | memoryview, last_stamps: dict[str, int] | None = None
    ) -> tuple[MessageHeader, Frame, bool]:
        """Decode one message and store its frame as the sensor's newest.

        ``last_stamps`` (per connection: sensor -> latest accepted stamp) rejects a frame
        not newer than the previous one of its sensor on the same connection. Returns the
        header, the frame, and whether it replaced an unread frame. Raises PushError (the
        message is then counted as rejected and nothing is stored).
        """
        if self._slots.closed:
            raise PushError("the console's push source is closed")
        try:
            header, frame = self.decode(data)
            if last_stamps is not None:
                prev = last_stamps.get(frame.sensor)
                if prev is not None and frame.stamp_ns <= prev:
                    raise PushError(
                        f"sensor {frame.sensor!r}: stamp_ns {frame.stamp_ns} is not after the "
                        f"previous frame's {prev} on this connection"
                    )
                last_stamps[frame.sensor] = frame.stamp_ns
        except PushError as exc:
            sensor = _identify(data).get("sensor")
            with self._lock:
                self._rejected += 1
                self._last_error = str(exc)
                entry = self._by_sensor.get(sensor) if isinstance(sensor, str) else None
                if entry is not None:  # counted per sensor only for this console's sensors
                    entry[0] += 1
                    entry[1] += 1
                    entry[2] = str(exc)
                    entry[3] = time.monotonic()
            raise
        replaced = self._slots.put(frame)
        with self._lock:
            entry = self._by_sensor[frame.sensor]
            entry[1] = 0
            entry[4] = time.monotonic()
        return header, frame, replaced

    # -- the stream ---------------------------------------------------------------------

    def frames(self) -> Iterator[Frame]:
        """Pushed frames as they come: each sensor's newest, oldest stamp first; a slow
        consumer skips frames (newest wins). Ends on :meth:`close`."""
        return self._slots.frames()

    def take(self, timeout_s: float | None = None) -> Frame | None:
        """One frame, or None on timeout or after :meth:`close`."""
        return self._slots.take(timeout_s)

    def peek(self, sensor: str) -> Frame | None:
        """The unread newest frame of ``sensor``, left in place (None if none)."""
        return self._slots.peek(sensor)

    def stats(self) -> dict[str, Any]:
        """``sensors`` (per sensor received/delivered/dropped/last stamp), ``rejected``
        messages, open ``connections``, the ``last_error``, and ``rejected_by_sensor``: per
        sensor of this console, messages ``rejected``, rejected ``since_accepted`` (its
        last accepted frame), its ``last_error`` and the ``time.monotonic()`` seconds of
        the ``last_rejected_s`` and ``last_accepted_s`` messages (None before any)."""
        with self._lock:
            return {
                "sensors": self._slots.stats(),
                "rejected": self._rejected,
                "connections": self._connections,
                "last_error": self._last_error,
                "rejected_by_sensor": {
                    s: {
                        "rejected": e[0],
                        "since_accepted": e[1],
                        "last_error": e[2],
                        "last_rejected_s": e[3],
                        "last_accepted_s": e[4],
                    }
                    for s, e in self._by_sensor.items()
                },
            }

    def _connection(self, delta: int) -> None:
        with self._lock:
            self._connections += delta

    @property
    def closed(self) -> bool:
        return self._slots.closed

    def close(self) -> None:
        """End the stream; later messages are rejected and connections closed."""
        self._slots.close()


def uvicorn_ws_max_size(source: PushSource) -> int:
    """A ``ws_max_size`` for uvicorn that lets messages somewhat above the source's limit
    reach it (so that they are answered with an error instead of closing the connection)."""
    return source.max_message_bytes + max(1 << 20, source.max_message_bytes // 4)


# -- the WebSocket endpoint -----------------------------------------------------------------


def make_push_router(
    source: PushSource,
    *,
    path: str = INGEST_PATH,
) -> APIRouter:
    """A FastAPI router with the push ingest WebSocket endpoint at ``path``. The console's
    authentication and Origin checks (app/server/routers/auth.py) guard it like every route.

    Each binary message is decoded in a worker thread (the event loop stays free) and its
    frame stored in the source; messages of one connection are handled in order. A bad
    message gets a text reply ``{"seq", "ok": false, "error", "sensor"?, "stamp_ns"?}`` and
    the connection goes on; ``"ack": true`` in a header gets ``{"seq", "ok": true, "sensor",
    "stamp_ns", "replaced"}``.
    """
    from fastapi import APIRouter, WebSocket, WebSocketDisconnect
    from starlette.concurrency import run_in_threadpool

    router = APIRouter()

    async def ingest(websocket: WebSocket) -> None:
        await websocket.accept()
        source._connection(+1)
        seq = 0
        last_stamps: dict[str, int] = {}
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                seq += 1
                data = message.get("bytes")
                if source.closed:
                    await websocket.close(code=1001, reason="console push source closed")
                    return
                if data is None:
                    await websocket.send_text(
                        json.dumps(
                            {
                                "seq": seq,
                                "ok": False,
                                "error": "expected binary push messages (magic TFP1), got text",
                            }
                        )
                    )
                    continue
                try:
                    header, frame, replaced = await run_in_threadpool(
                        source.accept, data, last_stamps
                    )
                except PushError as exc:
                    reply: dict[str, Any] = {"seq": seq, "ok": False, "error": str(exc)}
                    reply.update(_identify(data))
                    await websocket.send_text(json.dumps(reply))
                    continue
                if header.ack:
                    await websocket.send_text(
                        json.dumps(
                            {
                                "seq": seq,
                                "ok": True,
                                "sensor": frame.sensor,
                                "stamp_ns": frame.stamp_ns,
                                "replaced": replaced,
                            }
                        )
                    )
        except WebSocketDisconnect:
            return
        finally:
            source._connection(-1)

    # This module postpones annotations (strings); FastAPI resolves them in the module's
    # globals, where WebSocket is not imported (drivers do not need FastAPI): give it the class.
    ingest.__annotations__ = {"websocket": WebSocket, "return": None}
    router.add_api_websocket_route(path, ingest, name="push_ingest")
    return router


def _identify(data: bytes) -> dict[str, Any]:
    """Sensor and stamp of a (possibly bad) message, where its header gives them."""
    try:
        magic, hlen = PREFIX.unpack_from(data, 0)
        if magic != MAGIC or hlen > MAX_HEADER_BYTES:
            return {}
        header = json.loads(bytes(data[PREFIX.size : PREFIX.size + hlen]))
    except Exception:
        return {}
    if not isinstance(header, dict):
        return {}
    return {k: header[k] for k in ("sensor", "stamp_ns") if isinstance(header.get(k), str | int)}


# -- clients --------------------------------------------------------------------------------


def _modality_lookup(modalities: Mapping[str, str] | Rig | None) -> Mapping[str, str]:
    if modalities is None:
        return {}
    if isinstance(modalities, Rig):
        return {s: modalities[s].modality for s in modalities.names}
    return dict(modalities)


def _parse_reply(text: str | bytes) -> dict[str, Any]:
    try:
        reply = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {"ok": False, "error": f"unreadable reply {text!r:.200}"}
    return reply if isinstance(reply, dict) else {"ok": False, "error": f"reply {reply!r}"}


def _with_token(headers: Mapping[str, str] | None, token: str | None) -> dict[str, str]:
    """``headers`` plus the console's ``Authorization`` header when there is a token."""
    out = dict(headers or {})
    if token:
        out["Authorization"] = f"token {token}"
    return out


class PushClient:
    """A blocking push client (``websockets.sync``): connect, send frames, read replies.

    Args:
        url: the console's ingest URL, e.g. ``ws://console:8000/ingest``.
        modalities: sensor -> modality, or the rig (tells thermal from TOF amplitude).
        encode_options: passed to :func:`encode_frame` (``color_encoding``,
            ``jpeg_quality``, ``value_encoding``).
        open_timeout_s: connection timeout.
        additional_headers: more HTTP headers for the connection.
        token: the console's token (sent as ``Authorization: token ...``).

    Error replies to messages sent without ``ack`` arrive later; they are collected in
    :attr:`errors` (checked on every send, never blocking) and handed to ``on_error``.
    """

    def __init__(
        self,
        url: str,
        modalities: Mapping[str, str] | Rig | None = None,
        *,
        encode_options: Mapping[str, Any] | None = None,
        open_timeout_s: float = 10.0,
        additional_headers: Mapping[str, str] | None = None,
        on_error: Any = None,
        token: str | None = None,
    ) -> None:
        from websockets.sync.client import connect

        self.url = url
        self.modalities = _modality_lookup(modalities)
        self.encode_options = dict(encode_options or {})
        self.errors: list[dict[str, Any]] = []
        self.on_error = on_error
        self.sent = 0
        self.sent_bytes = 0
        self._ws = connect(
            url,
            open_timeout=open_timeout_s,
            compression=None,  # JPEG/PNG payloads do not compress
            proxy=None,
            max_size=1 << 20,
            additional_headers=_with_token(additional_headers, token),
        )

    def _note(self, reply: dict[str, Any]) -> None:
        if not reply.get("ok", False):
            self.errors.append(reply)
            if self.on_error is not None:
                self.on_error(reply)

    def poll(self) -> None:
        """Read the replies that have arrived (errors go to :attr:`errors`), never blocking."""
        while True:
            try:
                text = self._ws.recv(timeout=0)
            except TimeoutError:
                return
            self._note(_parse_reply(text))

    def send_bytes(
        self, message: bytes, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Send one encoded message. With ``ack`` (the header must ask for it, or an error
        reply is awaited) wait for its reply: return it, or raise PushRejected."""
        self.poll()
        self._ws.send(message)
        self.sent += 1
        self.sent_bytes += len(message)
        seq = self.sent
        if not ack:
            return None
        while True:
            reply = _parse_reply(self._ws.recv(timeout=timeout_s))
            if reply.get("seq") == seq:
                if not reply.get("ok", False):
                    raise PushRejected(reply)
                return reply
            self._note(reply)

    def send(
        self, frame: Frame, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Encode and send one frame (see :meth:`send_bytes`)."""
        message = encode_frame(
            frame, self.modalities.get(frame.sensor), ack=ack, **self.encode_options
        )
        return self.send_bytes(message, ack=ack, timeout_s=timeout_s)

    def close(self) -> None:
        self._ws.close()

    def __enter__(self) -> PushClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncPushClient:
    """The asyncio twin of :class:`PushClient` (``websockets.asyncio``)::

    async with AsyncPushClient(url, rig) as client:
        await client.send(frame)
    """

    def __init__(
        self,
        url: str,
        modalities: Mapping[str, str] | Rig | None = None,
        *,
        encode_options: Mapping[str, Any] | None = None,
        open_timeout_s: float = 10.0,
        additional_headers: Mapping[str, str] | None = None,
        token: str | None = None,
    ) -> None:
        self.url = url
        self.modalities = _modality_lookup(modalities)
        self.encode_options = dict(encode_options or {})
        self.open_timeout_s = open_timeout_s
        self.additional_headers = _with_token(additional_headers, token)
        self.errors: list[dict[str, Any]] = []
        self.sent = 0
        self._ws: Any = None

    async def connect(self) -> AsyncPushClient:
        from websockets.asyncio.client import connect

        self._ws = await connect(
            self.url,
            open_timeout=self.open_timeout_s,
            compression=None,
            proxy=None,
            max_size=1 << 20,
            additional_headers=self.additional_headers,
        )
        return self

    async def __aenter__(self) -> AsyncPushClient:
        return await self.connect()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def poll(self) -> None:
        """Collect the replies that have arrived, never blocking."""
        import asyncio

        while True:
            try:
                text = await asyncio.wait_for(self._ws.recv(), timeout=0.0001)
            except TimeoutError:
                return
            reply = _parse_reply(text)
            if not reply.get("ok", False):
                self.errors.append(reply)

    async def send_bytes(
        self, message: bytes, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Send one encoded message; with ``ack`` wait for its reply (PushRejected on error)."""
        import asyncio

        await self._ws.send(message)
        self.sent += 1
        seq = self.sent
        if not ack:
            return None
        while True:
            reply = _parse_reply(await asyncio.wait_for(self._ws.recv(), timeout_s))
            if reply.get("seq") == seq:
                if not reply.get("ok", False):
                    raise PushRejected(reply)
                return reply
            if not reply.get("ok", False):
                self.errors.append(reply)

    async def send(
        self, frame: Frame, *, ack: bool = False, timeout_s: float = 10.0
    ) -> dict[str, Any] | None:
        """Encode and send one frame."""
        message = encode_frame(
            frame, self.modalities.get(frame.sensor), ack=ack, **self.encode_options
        )
        return await self.send_bytes(message, ack=ack, timeout_s=timeout_s)

    async def close(self) -> None:
        if self._ws is not None:
            await self._ws.close()
