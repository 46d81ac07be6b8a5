"""Text from outside the program shown in Viser's markdown, literally and inertly (issue 29).

Viser's markdown is not inert. ``GuiMarkdownHandle.content`` turns every ``![alt](path)``
in the text into a read of ``path`` on the server (any image file the console may read,
absolute or relative), sent as a ``data:`` URL to every browser; and the client renders
links, autolinks, GFM's bare ``www.`` / ``http://`` / e-mail links and raw HTML
unsanitised. So every string that did not come from the program itself (file names,
sensor and eye names, view and rig names, paths, exception messages, which often echo
their input, a driver's reasons) goes through :func:`md_text` before it is put into a
panel's markdown. Plain-text GUI fields (labels, hints, dropdown options, scene labels,
notifications) are not markdown in Viser's client and need nothing.
"""

from __future__ import annotations

import re

MAX_CHARS = 2000
"""Longer text is cut (with an ellipsis): an exception can echo a whole file."""

_CONTROLS = {code: " " for code in (*range(0x20), *range(0x7F, 0xA0))}
"""Line breaks, tabs, NUL and the other control characters, as spaces."""

_SYNTAX = re.compile(
    r"""(?x)
    [!#&*+<=>\[\\\]`|~]                      # syntax wherever they are
    | (?<![A-Za-z0-9])[-_.] | [-_.](?![A-Za-z0-9])  # - _ . unless inside a word
    | (?<=[0-9])\)                          # 1) (a list item)
    """
)
"""The ASCII punctuation :func:`md_text` escapes. Left as they are: ``( ) / : @ , ; ? ' "
% $ ^ { }``, which are syntax only after a ``[`` or ``<`` (link destinations, footnotes,
HTML, autolinks), and ``-``, ``_`` and ``.`` between two letters or digits (``ccd_left``,
``rig-0001``, ``short.mcap``), which CommonMark reads literally."""

_BARE_LINK = re.compile(r"(?i)(?<=:)(?=//)|(?<=www)(?=\.)|(?<=@)")
"""Where GFM's bare links (``http://``, ``www.``, ``a@b.c``) get a word joiner (U+2060,
invisible). remark-gfm, Viser's client's, finds them in the text after escapes are
resolved, so escaping cannot stop them; the joiner breaks its patterns."""
WORD_JOINER = "\u2060"


def md_text(value: object, max_chars: int = MAX_CHARS) -> str:
    """``str(value)`` for a markdown paragraph or table cell, shown as it is and inert.

    CommonMark reads a backslash-escaped ASCII punctuation character as that literal
    character. Escaping every one that could start or take part in syntax (:data:`_SYNTAX`)
    means no image, link, link reference, autolink, raw HTML, entity, emphasis, code span,
    heading, list or table cell border can form, and ``![`` never occurs, which is what
    Viser's server-side image pattern looks for; an invisible word joiner breaks GFM's
    bare links (:data:`_BARE_LINK`). Line breaks become spaces and leading and trailing
    spaces go, so the text cannot start a new block (nor an indented code block). Text
    beyond ``max_chars`` characters is replaced by ``…``.

    Not for code spans: backslashes are literal there, and Viser's pattern still matches
    inside them, so outside text never goes between backticks.
    """
    text = str(value)
    if len(text) > max_chars:
        text = text[:max_chars] + "…"
    text = _BARE_LINK.sub(WORD_JOINER, text.translate(_CONTROLS).strip())
    return _SYNTAX.sub(r"\\\g<0>", text)


def md_cells(rows: list[list[str]]) -> list[list[str]]:
    """Every cell of a table's rows through :func:`md_text`."""
    return [[md_text(cell) for cell in row] for row in rows]
