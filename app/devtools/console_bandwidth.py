"""What the 3D console (``/console/``) sends per second, by kind of message, in each of its
bandwidth modes (``full``, ``low``: ``/api/console/settings``); no root needed.

Headless Chromium (Playwright) opens ``/console/`` as an operator's browser does;
Playwright hands over every frame its WebSocket receives (``framereceived``: Viser's client
runs its WebSocket in a Web Worker, which the DevTools protocol's page session does not
see, Playwright's WebSocket events do), and :class:`ViserTally` decodes each as Viser 1.1.1
frames it: a window of messages per WebSocket message, laid out as

- 8 bytes: length of the msgpack payload (little-endian uint64), 8 bytes: length of its
  zstd-compressed form, the compressed msgpack ``{"messages": [...], "timestampSec": ...,
  "binaryBufferLengths": [...]}``;
- the binary buffers (numpy arrays: point positions and colours ...), each at an 8-byte
  aligned offset, replaced in the messages by ``{"__binary_index": i, "dtype": "<f4"}``.

Each message gets the bytes of the binary buffers it refers to plus a share of the rest of
the frame (the headers, the compressed msgpack, the padding) in proportion to the size of
its own msgpack encoding; the shares of a frame sum to its payload. The kinds
(:data:`KINDS`):

- ``cloud``: point cloud nodes, created (``PointCloudMessage``) or updated
  (``SceneNodeUpdateMessage`` to a node created as a point cloud);
- ``scene_images``: image nodes in the 3D scene (the sensors' live images under their
  frustums, the board's plate);
- ``gui_images``: image elements of the GUI panels (the Feeds folder);
- ``other``: everything else (markdown, numbers, frames, the camera ...).

Figures are WebSocket payload bytes (the framing, TCP/IP and TLS add a few per cent; the
``link`` benchmark counts what the link's device carries).

Run it on its own (starts a console on the simulated inspection room, about a minute)::

    .venv/bin/python -m trifuse.app.devtools.console_bandwidth [SECONDS]
"""

from __future__ import annotations

import json
import statistics
import time
import urllib.request
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np
import zstandard

KINDS = ("cloud", "scene_images", "gui_images", "other")
"""What the bytes are attributed to (module docstring)."""
UPDATE_KINDS = {"cloud": "cloud", "scene_images": "scene_image", "gui_images": "gui_image"}
"""Kinds whose updates are counted -> the prefix of their figures."""
MODES = ("full", "low")
"""The console's bandwidth modes, measured in this order."""
SETTINGS_ROUTE = "/api/console/settings"
"""``GET``/``PUT`` ``{"bandwidth": "full" | "low"}``."""
CONNECTED = "() => !document.body.innerText.includes('Connecting...')"
SETTLE_S = 4.0
"""After the page has connected or the mode changed, before a window starts (seconds)."""
VIEWPORT = {"width": 800, "height": 600}
"""Small: larger canvases crawl under software WebGL."""


@dataclass(frozen=True)
class TalliedMessage:
    """One Viser message the browser received.

    Attributes:
        t: when its frame was handed over, ``time.monotonic()`` seconds.
        kind: one of :data:`KINDS`.
        type: Viser's message type name, e.g. ``SceneNodeUpdateMessage``.
        target: the scene node's name or the GUI element's uuid ("" for neither).
        nbytes: its share of the frame's payload, bytes.
        points: points it carries (cloud messages with positions), else 0.
        image_size: (width, height) pixels of the JPEG/PNG it carries, else None.
    """

    t: float
    kind: str
    type: str
    target: str
    nbytes: float
    points: int = 0
    image_size: tuple[int, int] | None = None


def _align8(n: int) -> int:
    return (n + 7) & ~7


def split_frame(payload: bytes) -> tuple[list[dict[str, Any]], list[memoryview], int]:
    """One Viser WebSocket message -> (its messages as dicts, its binary buffers, the
    bytes of the frame that are not binary buffers: headers, compressed msgpack, padding).

    Raises:
        ValueError: a payload that is not a Viser frame (or one cut short).
    """
    if len(payload) < 16:
        raise ValueError(f"a Viser frame has a 16-byte header, got {len(payload)} bytes")
    inner_len = int.from_bytes(payload[:8], "little")
    comp_len = int.from_bytes(payload[8:16], "little")
    if 16 + comp_len > len(payload):
        raise ValueError("the frame is shorter than its compressed payload")
    try:
        inner = zstandard.ZstdDecompressor().decompress(
            payload[16 : 16 + comp_len], max_output_size=inner_len
        )
        window = msgspec.msgpack.decode(inner)
    except (zstandard.ZstdError, msgspec.DecodeError) as exc:
        raise ValueError(f"not a Viser frame: {exc}") from None
    lengths = [int(n) for n in window.get("binaryBufferLengths", ())]
    view = memoryview(payload)
    buffers, offset = [], 16 + comp_len
    for n in lengths:
        offset = _align8(offset)
        if offset + n > len(payload):
            raise ValueError("the frame is shorter than its binary buffers")
        buffers.append(view[offset : offset + n])
        offset += n
    return list(window.get("messages", ())), buffers, len(payload) - sum(lengths)


def _placeholders(value: Any, key: str = "") -> Iterator[tuple[str, int, str]]:
    """(key, binary index, dtype) of every binary placeholder inside ``value``."""
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            yield key, int(value["__binary_index"]), str(value["dtype"])
            return
        for k, v in value.items():
            yield from _placeholders(v, str(k))
    elif isinstance(value, list | tuple):
        for v in value:
            yield from _placeholders(v, key)


def _image_bytes(message: dict[str, Any]) -> bytes | None:
    """The encoded image (``_data``) a create or update message carries, if any."""
    for holder in (message.get("props"), message.get("updates")):
        if isinstance(holder, dict):
            data = holder.get("_data")
            if isinstance(data, bytes | bytearray | memoryview) and len(data) > 0:
                return bytes(data)
    return None


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) pixels of a JPEG or PNG, read from its header; None otherwise."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        seg = int.from_bytes(data[i + 2 : i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            h = int.from_bytes(data[i + 5 : i + 7], "big")
            w = int.from_bytes(data[i + 7 : i + 9], "big")
            return w, h
        i += 2 + seg
    return None


@dataclass
class ViserTally:
    """Decodes the frames one browser receives from Viser and attributes their bytes
    (module docstring). It remembers which node names are point clouds or images and
    which GUI uuids are images, from the messages that create them, so it must see the
    frames from the connection's first on.

    Attributes:
        messages: every decoded message, in order of arrival.
        frames: (time, payload bytes) of every frame, decodable or not.
        undecoded_bytes: payload bytes of frames that were not Viser frames.
    """

    messages: list[TalliedMessage] = field(default_factory=list)
    frames: list[tuple[float, int]] = field(default_factory=list)
    undecoded_bytes: int = 0
    cloud_nodes: set[str] = field(default_factory=set)
    image_nodes: set[str] = field(default_factory=set)
    gui_images: set[str] = field(default_factory=set)

    def _kind(self, m: dict[str, Any]) -> tuple[str, str]:
        kind, name = str(m.get("type", "")), str(m.get("name", m.get("uuid", "")))
        if kind == "PointCloudMessage":
            self.cloud_nodes.add(name)
            return "cloud", name
        if kind == "ImageMessage":
            self.image_nodes.add(name)
            return "scene_images", name
        if kind == "GuiImageMessage":
            self.gui_images.add(name)
            return "gui_images", name
        if kind in ("SceneNodeUpdateMessage", "RemoveSceneNodeMessage"):
            if name in self.cloud_nodes:
                return "cloud", name
            if name in self.image_nodes:
                return "scene_images", name
        if kind in ("GuiUpdateMessage", "GuiRemoveMessage") and name in self.gui_images:
            return "gui_images", name
        return "other", name

    def add_frame(self, payload: bytes, t: float) -> list[TalliedMessage]:
        """Tally one WebSocket message received at ``t`` (seconds); returns its messages
        (none for a frame that is not Viser's: its bytes go to :attr:`undecoded_bytes`)."""
        self.frames.append((t, len(payload)))
        try:
            messages, buffers, rest = split_frame(payload)
        except ValueError:
            self.undecoded_bytes += len(payload)
            return []
        own = [len(msgspec.msgpack.encode(m)) for m in messages]
        scale = rest / max(sum(own), 1)
        out = []
        for m, size in zip(messages, own, strict=True):
            kind, target = self._kind(m)
            nbytes, points = size * scale, 0
            for key, i, dtype in _placeholders(m):
                n = buffers[i].nbytes if i < len(buffers) else 0
                nbytes += n
                if key == "points" and kind == "cloud":
                    points = n // (3 * np.dtype(dtype).itemsize)
            data = _image_bytes(m) if kind in ("scene_images", "gui_images") else None
            size_px = image_size(data) if data is not None else None
            out.append(
                TalliedMessage(t, kind, str(m.get("type", "")), target, nbytes, points, size_px)
            )
        self.messages.extend(out)
        return out

    def figures(self, start: int, stop: int, seconds: float) -> dict[str, float]:
        """Over messages ``[start, stop)`` received in ``seconds``: ``{kind}_mbit_s`` for
        each of :data:`KINDS` and ``total_mbit_s``; for the cloud, the scene images and the
        GUI images (``cloud``, ``scene_image``, ``gui_image``): ``_updates_per_s`` (messages
        carrying points or a picture), ``_kb_per_update`` (all bytes of that kind over the
        updates: a cloud's colours come in a message of their own), and the median points
        (``cloud_points``) or picture width (``scene_image_width_px`` ...) of an update."""
        window = self.messages[start:stop]
        out: dict[str, float] = {}
        for kind in KINDS:
            b = sum(m.nbytes for m in window if m.kind == kind)
            out[f"{kind}_mbit_s"] = b * 8 / seconds / 1e6
        out["total_mbit_s"] = sum(out[f"{k}_mbit_s"] for k in KINDS)
        for kind, prefix in UPDATE_KINDS.items():
            updates = [m for m in window if m.kind == kind and (m.points or m.image_size)]
            kb = sum(m.nbytes for m in window if m.kind == kind) / 1e3
            out[f"{prefix}_updates_per_s"] = len(updates) / seconds
            out[f"{prefix}_kb_per_update"] = kb / len(updates) if updates else 0.0
            if kind == "cloud":
                counts = [m.points for m in updates]
                out["cloud_points"] = statistics.median(counts) if counts else 0.0
            else:
                widths = [m.image_size[0] for m in updates if m.image_size]
                out[f"{prefix}_width_px"] = statistics.median(widths) if widths else 0.0
        return out


def _rest(console_url: str, token: str | None, path: str, body: Any = None) -> Any:
    """A REST call as a script makes it (``Authorization: token``, no proxies); its JSON."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        console_url + path, data=data, method="GET" if body is None else "PUT"
    )
    if token:
        req.add_header("Authorization", f"token {token}")
    if data is not None:
        req.add_header("Content-Type", "application/json")
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    with opener.open(req, timeout=10.0) as r:
        return json.loads(r.read())


def set_console_bandwidth(console_url: str, token: str | None, mode: str) -> str:
    """``PUT /api/console/settings {"bandwidth": mode}``; returns the mode now set."""
    return str(_rest(console_url, token, SETTINGS_ROUTE, {"bandwidth": mode})["bandwidth"])


def get_console_bandwidth(console_url: str, token: str | None) -> str:
    """The console's bandwidth mode (``GET /api/console/settings``)."""
    return str(_rest(console_url, token, SETTINGS_ROUTE)["bandwidth"])


class ConsolePage:
    """``/console/`` open in a new page of ``browser`` (Playwright, Chromium), every frame
    its WebSocket receives tallied (:attr:`tally`) from the connection's first on.

    Args:
        browser: a Playwright ``Browser`` (Chromium: the DevTools protocol is needed).
        console_url: the console's base URL, e.g. ``http://127.0.0.1:8000``.
        token: its token (None: it runs without one).
    """

    def __init__(self, browser: Any, console_url: str, token: str | None) -> None:
        self.tally = ViserTally()
        self.page = browser.new_page(viewport=VIEWPORT)
        try:
            self.page.on("websocket", self._socket)
            query = f"?token={token}" if token else ""
            self.page.goto(f"{console_url}/console/{query}")
            self.page.wait_for_function(CONNECTED)
        except BaseException:
            self.close()
            raise

    def _socket(self, ws: Any) -> None:
        """Tally the binary frames of every WebSocket the page opens (Viser's client opens
        its WebSocket in a Web Worker: Playwright's WebSocket events include it)."""

        def frame(payload: str | bytes) -> None:
            if isinstance(payload, bytes):  # Viser sends binary frames only
                self.tally.add_frame(payload, time.monotonic())

        ws.on("framereceived", frame)

    def window(self, seconds: float) -> tuple[int, int, float]:
        """Wait ``seconds`` (the page runs on); (first, last + 1) message index of what
        arrived meanwhile and the seconds it took."""
        start, t0 = len(self.tally.messages), time.monotonic()
        self.page.wait_for_timeout(seconds * 1e3)
        return start, len(self.tally.messages), time.monotonic() - t0

    def close(self) -> None:
        self.page.close()


def measure_console(
    browser: Any,
    console_url: str,
    token: str | None,
    seconds: float,
    modes: Sequence[str] = MODES,
    settle_s: float = SETTLE_S,
) -> dict[str, float]:
    """What ``/console/`` receives in each bandwidth mode, in one page: the mode is set
    over REST (:func:`set_console_bandwidth`), ``settle_s`` seconds pass, then ``seconds``
    are measured; the console's mode is restored at the end.

    Returns:
        ``load_mb``: megabytes received from the page's connection to the end of the first
        settling time (the scene's initial state); per mode ``M``: ``M_{kind}_mbit_s`` for
        each of :data:`KINDS`, ``M_total_mbit_s`` (WebSocket payload, Mbit/s) and
        :meth:`ViserTally.figures`' rates and sizes (``M_cloud_points``,
        ``M_scene_image_kb_per_update`` ...).
    """
    was = get_console_bandwidth(console_url, token)
    out: dict[str, float] = {}
    page = ConsolePage(browser, console_url, token)
    try:
        for i, mode in enumerate(modes):
            set_console_bandwidth(console_url, token, mode)
            page.page.wait_for_timeout(settle_s * 1e3)
            if i == 0:
                out["load_mb"] = sum(n for _, n in page.tally.frames) / 1e6
            start, stop, dt = page.window(seconds)
            out.update({f"{mode}_{k}": v for k, v in page.tally.figures(start, stop, dt).items()})
    finally:
        page.close()
        set_console_bandwidth(console_url, token, was)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Start a console on the simulated inspection room, measure both modes, print JSON."""
    import os
    import sys
    import tempfile
    from pathlib import Path

    from trifuse.app.devtools.browser_console import headless_chromium, require_chromium
    from trifuse.app.devtools.console_process import ConsoleProcess, prewarm_pose_cache

    args = list(sys.argv[1:] if argv is None else argv)
    seconds = float(args[0]) if args else 15.0
    require_chromium("console bandwidth")
    prewarm_pose_cache()
    with tempfile.TemporaryDirectory(prefix="trifuse-console-bw-") as tmp:
        console = ConsoleProcess(
            ["--workdir", str(Path(tmp) / "work")],
            env=dict(os.environ),
            log_path=Path(tmp) / "serve.log",
            timeout_s=300.0,
        )
        with console, headless_chromium() as browser:
            figures = measure_console(browser, console.url, console.token, seconds)
    figures["load_1min"] = os.getloadavg()[0]
    print(json.dumps({k: round(v, 3) for k, v in figures.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
