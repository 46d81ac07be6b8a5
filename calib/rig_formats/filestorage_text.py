"""A check of OpenCV ``FileStorage`` text before ``cv2.FileStorage`` reads it (issue 29).

OpenCV's FileStorage parsers (YAML, XML and JSON) are recursive: every level of nesting is
a C++ stack frame, and some 40,000 levels (``[[[[...``, ``<a><a><a>...``, ``a: b: c: ...``
or ever deeper indentation) overflow the stack and kill the whole process with SIGSEGV,
which no ``try`` catches; a 372-byte zip holds such a file. :func:`check_filestorage_text`
refuses text that could nest deeper than :data:`MAX_NESTING` (a rig file nests 3 levels),
is longer than :data:`MAX_TEXT_CHARS`, holds control characters or base64 data, without
parsing it.

Base64 data (``FileStorage.BASE64``: YAML ``!!binary``, XML ``type_id="binary"``, JSON
``"$base64$..."``) is refused as well: a block whose header names no element type (spaces,
a count alone) sends OpenCV's reader into an endless loop, in all three formats.

The nesting is bounded from above (:func:`nesting_bound`) by the rules of OpenCV's parsers
(``modules/core/src/persistence_{yml,xml,json}.cpp``), for the format OpenCV picks: JSON
when the text starts with ``{``, XML with ``<?xml``, else YAML (after a UTF-8 byte order
mark). Everything after a carriage return on a line is skipped by OpenCV (but inside a
JSON ``/* */`` comment) and here.

* JSON: exact. Strings (``"..."`` on one line, ``\\`` escaping a character) and comments
  (``//``, ``/* */``) are skipped; every other ``[ {`` opens a level and ``] }`` closes
  one.
* XML: exact. ``<name`` opens a level and ``</`` closes one, except in ``<!-- -->``
  comments (OpenCV's XML text cannot hold a ``<``).
* YAML flow (``[ ]``, ``{ }``): every ``[ {`` opens a level, except on a line that is a
  comment. A ``] }`` closes one except where it may be text: after a quote, ``#`` or
  ``!`` on its line (OpenCV's quoted strings, comments and tags are one line) or before
  the line's last ``:`` (a key). Elsewhere it closes a level, or it is in a block scalar,
  where OpenCV is in no flow at all: the bound stays above OpenCV's depth.
* YAML block (indentation): OpenCV nests a block collection only at a column right of
  its parent's, at the start of a line or after ``:``, ``-`` (not a number's sign) or a
  tag on it. Every such column counts as a level until a line starts left of it (a line
  inside a flow starts right of every open block level: OpenCV requires it).
"""

from __future__ import annotations

import re

from trifuse.calib.errors import RigError

MAX_NESTING = 32
"""Largest bound on the nesting accepted (OpenCV's and trifuse's calibration files: 3 to
6; OpenCV crashes at about 40,000)."""
MAX_TEXT_CHARS = 1_000_000
"""Longest text accepted (a sensor's file is under a kilobyte, OpenCV's calibration
sample's output with every view's corners a few dozen kilobytes)."""

_CONTROL_RE = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f]")
"""Control characters OpenCV's parsers do not take (tab, newline and return aside)."""
_BASE64_RE = re.compile(r"!\S*binary|type_id\s*=\s*[\"'][^\"'<>]*(?:binary|&)|\$base64\$")
"""Where base64 data may start: a YAML ``!!binary`` tag (or ``!^binary``, ``!<...binary>``),
an XML ``type_id="binary"`` (or one with an entity), a JSON ``"$base64$..."`` string (or
any text that looks so)."""
_JSON_TOKEN_RE = re.compile(
    rb'"(?:[^"\\\n\r]|\\[^\n\r])*"|//[^\n]*|/\*.*?(?:\*/|\Z)|\r[^\n]*|[\[\]{}\n]|["/]',
    re.DOTALL,
)
"""JSON's tokens that matter: strings, comments, the rest of a line after a return,
brackets, newlines, and a quote or slash that starts no string or comment (an error)."""
_XML_TOKEN_RE = re.compile(rb"<!--.*?(?:-->|\Z)|</|<[A-Za-z0-9_][^<>]*>?", re.DOTALL)
_BRACKET_RE = re.compile(rb"[\[\]{}]")
_OPENERS = (b"[", b"{")
_CLOSERS = (b"]", b"}")
_YAML_TEXT_AFTER_RE = re.compile(rb"['\"#!]")
"""After one of these on a line a YAML ``]`` or ``}`` may be text (string, comment, tag)."""
_YAML_LINE_RE = re.compile(rb"^( *)([^ \n\r#][^\n\r]*)[^\n]*", re.MULTILINE)
"""A YAML line but a blank or comment one; group 2 starts at its first character and
ends at a return (OpenCV skips the rest of a line after one)."""
_YAML_VALUE_MARK_RE = re.compile(rb"[:!-]")
_YAML_VALUE_AFTER_RE = re.compile(rb"(?::|-(?![0-9.])|!\S*) *(?=[^ ])")
"""Where a YAML block collection may start inside a line: after a key's ``:``, a
sequence item's ``-`` (a ``-`` before a digit or ``.`` is a number's sign) or a tag."""


class _TooDeep(Exception):
    """Raised inside the scans as soon as the bound passes the cap."""


def check_filestorage_text(text: object, source: str) -> None:
    """RigError naming ``source`` unless ``text`` is a str that ``cv2.FileStorage`` may
    read without risk: at most :data:`MAX_TEXT_CHARS` characters, no control characters
    but tab, newline and return, not blank, no base64 data, and nesting bounded by
    :data:`MAX_NESTING` (see the module docstring). Linear in the text's length; a deep
    text is refused as soon as the bound passes the cap."""
    if not isinstance(text, str):
        raise RigError(f"{source}: expected text, got {type(text).__name__}")
    if len(text) > MAX_TEXT_CHARS:
        raise RigError(f"{source}: {len(text)} characters; expected at most {MAX_TEXT_CHARS}")
    if not text.strip() or _CONTROL_RE.search(text):
        raise RigError(f"{source}: not an OpenCV FileStorage file (empty or binary)")
    if _BASE64_RE.search(text):
        raise RigError(
            f"{source}: holds base64 (binary) data, which OpenCV's reader can loop on for "
            "ever; write the file without FileStorage.BASE64"
        )
    if nesting_bound(text, cap=MAX_NESTING) > MAX_NESTING:
        raise RigError(
            f"{source}: nested deeper than {MAX_NESTING} levels (an OpenCV calibration file "
            "nests 3); refused before OpenCV reads it"
        )


def filestorage_format(text: str) -> str:
    """``"json"``, ``"xml"`` or ``"yaml"``: the parser ``cv2.FileStorage`` picks for
    ``text`` in memory (by its first characters after a UTF-8 byte order mark)."""
    start = text.removeprefix("\ufeff")
    if start.startswith("{"):
        return "json"
    if start.startswith("<?xml"):
        return "xml"
    return "yaml"


def nesting_bound(text: str, cap: int | None = None) -> int:
    """An upper bound on the nesting depth OpenCV's parser reaches on ``text`` without
    base64 data (a root mapping holding a scalar is 1), by the rules in the module
    docstring. With ``cap``, the scan stops as soon as the bound passes it and returns
    ``cap + 1``."""
    data = text.removeprefix("\ufeff").encode("utf-8", "surrogatepass")
    scan = {"json": _json_bound, "xml": _xml_bound, "yaml": _yaml_bound}
    limit = cap if cap is not None else len(data) + 1
    try:
        return scan[filestorage_format(text)](data, limit)
    except _TooDeep:
        return limit + 1


def _json_bound(data: bytes, limit: int) -> int:
    depth = peak = 0
    broken = False  # after a quote or slash that starts nothing, up to the line's end
    for m in _JSON_TOKEN_RE.finditer(data):
        token = m.group()
        if token in _OPENERS:
            depth += 1
            if depth > peak:
                peak = depth
                if peak > limit:
                    raise _TooDeep
        elif token in _CLOSERS:
            if not broken and depth:
                depth -= 1
        elif token == b"\n":
            broken = False
        elif token in (b'"', b"/"):
            broken = True
    return peak


def _xml_bound(data: bytes, limit: int) -> int:
    depth = peak = 0
    for m in _XML_TOKEN_RE.finditer(data):
        token = m.group()
        if token.startswith(b"<!--"):
            continue
        if token == b"</":
            depth = max(depth - 1, 0)
            continue
        depth += 1
        if depth > peak:
            peak = depth
            if peak > limit:
                raise _TooDeep
        if token.endswith(b"/>"):
            depth -= 1
    return peak


def _yaml_bound(data: bytes, limit: int) -> int:
    flow = peak = 0
    block: list[int] = []  # increasing columns where a block level may be open
    for found in _YAML_LINE_RE.finditer(data):  # lines but blank and comment ones
        col = found.start(2) - found.start()
        line = data[found.start() : found.end(2)]
        while block and block[-1] > col:
            block.pop()
        if not block or block[-1] < col:
            block.append(col)
        if _YAML_VALUE_MARK_RE.search(line, col):
            for m in _YAML_VALUE_AFTER_RE.finditer(line, col):
                if m.end() > block[-1]:
                    block.append(m.end())
        if _BRACKET_RE.search(line, col):
            text_from = _YAML_TEXT_AFTER_RE.search(line, col)
            cut = text_from.start() if text_from else len(line)
            key_end = line.rfind(b":")
            for m in _BRACKET_RE.finditer(line, col):
                if m.group() in _OPENERS:
                    flow += 1
                    peak = max(peak, flow + len(block))
                    if peak > limit:
                        raise _TooDeep
                elif flow and key_end < m.start() < cut:
                    flow -= 1
        peak = max(peak, flow + len(block))
        if peak > limit:
            raise _TooDeep
    return peak
