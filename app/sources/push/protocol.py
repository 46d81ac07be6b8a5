"""The push ingest wire protocol: message layout, limits, header framing and parsing.

One *binary* WebSocket message per frame (docs/FORMATS.md, "Push ingest protocol")::

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

The images of the parts are encoded and decoded by :mod:`app.sources.push.codec`.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from trifuse.calib.numbers import is_int
from trifuse.calib.units import KELVIN_PER_COUNT, METRES_PER_COUNT

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
    ("thermal", "image"): KELVIN_PER_COUNT,  # centi-kelvin -> kelvin
    ("tof", "image"): 1.0,  # amplitude counts
    ("tof", "distance"): METRES_PER_COUNT,  # millimetres -> metres
}
"""Default ``scale`` of 16-bit parts: value = counts * scale + offset."""

HEADER_KEYS = {"sensor", "stamp_ns", "ack", "parts"}
PART_KEYS = {"kind", "encoding", "width", "height", "length", "scale", "offset"}


class PushError(ValueError):
    """A push message is not what the protocol expects; the message says what and why."""


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
    unknown = sorted(set(header) - HEADER_KEYS)
    if unknown:
        raise PushError(f"header: unknown keys {unknown} (allowed: {sorted(HEADER_KEYS)})")
    sensor = header.get("sensor")
    if not isinstance(sensor, str) or not sensor:
        raise PushError(f"header: 'sensor' must be a non-empty string, got {sensor!r}")
    stamp = header.get("stamp_ns")
    if not is_int(stamp) or not 0 <= stamp < 2**63:
        raise PushError(f"header: 'stamp_ns' must be an integer in [0, 2^63), got {stamp!r}")
    ack = header.get("ack", False)
    if not isinstance(ack, bool):
        raise PushError(f"header: 'ack' must be true or false, got {ack!r}")
    parts = header.get("parts")
    if not isinstance(parts, list) or not parts or not all(isinstance(p, dict) for p in parts):
        raise PushError("header: 'parts' must be a non-empty list of objects")
    return MessageHeader(sensor, stamp, ack, tuple(parts)), PREFIX.size + hlen


def identify(data: bytes | bytearray | memoryview) -> dict[str, Any]:
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
