"""YAML text -> plain values, within limits that every file of the project keeps.

``yaml.safe_load`` builds only plain values, but some text still gets through it badly:
nesting deep enough to exhaust Python's recursion (``RecursionError``), integers too long
to convert and impossible dates (a bare ``ValueError``), and aliases that make a few lines
stand for a huge document (``a1: [*a0, *a0, ...]``, nine levels: a billion values) or for
one that contains itself (``&x [*x]``); whatever walks such a result (a validator, an error
message's ``repr``) then never ends or overflows. :func:`parse_yaml` turns all of these into
:class:`YamlError`, which the loaders re-raise as their own error naming the file.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import yaml

MAX_DEPTH = 100
"""Deepest nesting of mappings and lists accepted."""
MAX_VALUES = 1_000_000
"""Most values a document may hold, counting every use of an alias."""


class YamlError(ValueError):
    """Text that is not a YAML document within the limits; the message says why."""


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load(text)``, or YamlError (the reason, in one line) for invalid YAML,
    nesting deeper than :data:`MAX_DEPTH` or more than :data:`MAX_VALUES` values."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise YamlError(" ".join(str(exc).split())) from None
    except RecursionError:
        raise YamlError(f"nested deeper than {MAX_DEPTH} levels") from None
    except ValueError as exc:  # an integer of more than 4300 digits, a date like 2024-13-45
        raise YamlError(str(exc)) from None
    _check_size(data)
    return data


def _check_size(data: Any) -> None:
    """YamlError if ``data`` nests deeper than MAX_DEPTH or holds more than MAX_VALUES
    values (aliases counted at every use; a self-containing value nests without end)."""
    stack: list[tuple[Any, int]] = [(data, 0)]
    count = 0
    while stack:
        value, depth = stack.pop()
        count += 1
        if count > MAX_VALUES:
            raise YamlError(
                f"more than {MAX_VALUES} values (aliases repeating a part of the document?)"
            )
        if depth > MAX_DEPTH:
            raise YamlError(
                f"nested deeper than {MAX_DEPTH} levels (an alias inside its own anchor?)"
            )
        if isinstance(value, Mapping):
            stack.extend((k, depth + 1) for k in value)
            stack.extend((v, depth + 1) for v in value.values())
        elif isinstance(value, list | tuple | set | frozenset):
            stack.extend((v, depth + 1) for v in value)
