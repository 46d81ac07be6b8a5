"""YAML text -> plain values, within limits that every file of the project keeps.

``yaml.safe_load`` builds only plain values, but some text still gets through it badly:
nesting deep enough to exhaust Python's recursion, integers too long to convert and
impossible dates (a bare ``ValueError``), aliases that make a few lines stand for a huge
document (``a1: [*a0, *a0, ...]``, nine levels: a billion values) or for one that contains
itself (``&x [*x]``), and plain size: a 4 MiB list of two million integers took PyYAML's
pure-Python parser five minutes and kept 0.9 GiB before a limit on the result refused it
(issue 29). :func:`parse_yaml` turns all of these into :class:`YamlError`, which the
loaders re-raise as their own error naming the file, and refuses before building
anything:

1. text longer than :data:`MAX_TEXT_CHARS`;
2. text that is not YAML or holds more events than :data:`MAX_VALUES` values can make,
   found by libyaml's C parser without building anything;
3. nesting deeper than :data:`MAX_DEPTH` or more than :data:`MAX_VALUES` values (aliases
   counted at every use), counted from the parser's events as they come;

and only then builds the values, with libyaml's C loader (``yaml.CSafeLoader``) where
PyYAML has it, else the pure-Python one (same values: the scalars are resolved and
constructed by the same Python code).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import yaml
from yaml.events import (
    AliasEvent,
    Event,
    MappingEndEvent,
    MappingStartEvent,
    ScalarEvent,
    SequenceEndEvent,
    SequenceStartEvent,
)

MAX_DEPTH = 100
"""Deepest nesting of mappings and lists accepted."""
MAX_VALUES = 1_000_000
"""Most values a document may hold, counting every use of an alias."""
MAX_TEXT_CHARS = 16 << 20
"""Longest text parsed (16 Mi characters; the project's files are kilobytes, and a
million values at full precision fit)."""

try:  # libyaml's C parser, where PyYAML was built with it
    from yaml import CSafeLoader as _Loader
    from yaml._yaml import CParser as _CParser
except ImportError:  # PyYAML without libyaml: the pure-Python parser, slower
    _Loader = yaml.SafeLoader  # type: ignore[misc, assignment]
    _CParser = None


class YamlError(ValueError):
    """Text that is not a YAML document within the limits; the message says why."""


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load(text)``, or YamlError (the reason, in one line) for text longer
    than :data:`MAX_TEXT_CHARS`, invalid YAML, nesting deeper than :data:`MAX_DEPTH` or
    more than :data:`MAX_VALUES` values (each refused before any value is built)."""
    if len(text) > MAX_TEXT_CHARS:
        raise YamlError(f"{len(text)} characters; expected at most {MAX_TEXT_CHARS}")
    try:
        if _CParser is not None:
            _check_event_count(_CParser(text).raw_parse())  # in C: syntax and count
            _check_events(iter(_CParser(text).get_event, None))
        else:
            _check_events(yaml.parse(text, Loader=yaml.SafeLoader))
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        raise YamlError(" ".join(str(exc).split())) from None
    except ValueError as exc:  # an integer of more than 4300 digits, a date like 2024-13-45
        raise YamlError(" ".join(str(exc).split())) from None


def _check_event_count(count: int) -> None:
    """YamlError when ``count`` events (stream, document and collection ends included)
    make more than MAX_VALUES values: every value takes one event, a collection two."""
    if (count - 4) // 2 > MAX_VALUES:
        raise YamlError(f"more than {MAX_VALUES} values")


def _check_events(events: Iterable[Event]) -> None:
    """YamlError as soon as the document the ``events`` describe holds a value deeper than
    MAX_DEPTH (the root is at depth 0) or more than MAX_VALUES values, counting an alias
    as every value of what it names, at the depth it stands."""
    values = 0
    depth = 0  # the open collections: the depth of the next value
    peak = 0  # the deepest value so far in the innermost open collection
    open_: list[tuple[str | None, int, int]] = []  # (anchor, values before it, outer peak)
    open_anchors: set[str] = set()
    named: dict[str, tuple[int, int]] = {}  # anchor -> (values, levels below it)
    aliased = False
    for event in events:
        kind = event.__class__
        if kind is ScalarEvent:
            values += 1
            if event.anchor is not None:
                named[event.anchor] = (1, 0)
            reach = depth
        elif kind is SequenceEndEvent or kind is MappingEndEvent:
            anchor, before, outer = open_.pop()
            depth -= 1
            if anchor is not None:
                named[anchor] = (values - before, peak - depth)
                open_anchors.discard(anchor)
            peak = max(peak, outer)
            continue
        elif kind is SequenceStartEvent or kind is MappingStartEvent:
            values += 1
            open_.append((event.anchor, values - 1, max(peak, depth)))
            if event.anchor is not None:
                open_anchors.add(event.anchor)
            reach, peak = depth, depth
            depth += 1
        elif kind is AliasEvent:
            aliased = True
            if event.anchor in open_anchors:
                raise YamlError(
                    f"nested deeper than {MAX_DEPTH} levels (an alias inside its own anchor)"
                )
            size, below = named.get(event.anchor, (1, 0))  # unknown: the loader says so
            values += size
            reach = depth + below
        else:  # the stream's and the document's start and end
            continue
        if values > MAX_VALUES:
            why = " (aliases repeating a part of the document?)" if aliased else ""
            raise YamlError(f"more than {MAX_VALUES} values{why}")
        if reach > MAX_DEPTH:
            raise YamlError(f"nested deeper than {MAX_DEPTH} levels")
        if reach > peak:
            peak = reach
