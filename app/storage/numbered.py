"""Numbered file names: the first free one of a series, or the number after the highest used.

Three series are used in the work directory and beside the user's files:

- :func:`suffixed_names`: ``stem``, ``stem-2``, ``stem-3``, ... (saved maps, recordings,
  deleted views, recovered recordings);
- :func:`backup_names`: ``path.~1~``, ``path.~2~``, ... (GNU ``cp``'s numbered backups of a
  rig file an update replaces);
- :func:`next_number`: one more than the highest number in use (views ``0001``, rig
  versions ``rig-0001``), so a number once used is never taken again.

:func:`first_free` picks the first name of a series that is not taken. Where two writers
may race for a name, iterate over the series and create each candidate exclusively
(``O_EXCL``, ``os.link``) instead; a name found free may be taken before it is used.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def first_free(candidates: Iterable[T], taken: Callable[[T], bool]) -> T:
    """The first of ``candidates`` for which ``taken`` is False.

    Raises:
        FileExistsError: every candidate is taken (a finite series ran out).
    """
    for candidate in candidates:
        if not taken(candidate):
            return candidate
    raise FileExistsError("every numbered name of the series is taken")


def suffixed_names(stem: str, ext: str = "", limit: int | None = None) -> Iterator[str]:
    """``stem + ext``, then ``stem-2 + ext``, ``stem-3 + ext``, ...: ``limit`` names at most
    (None: endless). E.g. ``suffixed_names("20261129-031500", ".mcap", 9_999)``."""
    numbers = itertools.count(1) if limit is None else range(1, limit + 1)
    for k in numbers:
        yield f"{stem}{ext}" if k == 1 else f"{stem}-{k}{ext}"


def backup_names(path: Path) -> Iterator[Path]:
    """``path.~1~``, ``path.~2~``, ... beside ``path`` (GNU ``cp``'s numbered backups),
    endless."""
    for n in itertools.count(1):
        yield path.with_name(f"{path.name}.~{n}~")


def next_number(used: Iterable[int]) -> int:
    """One more than the highest of ``used``; 1 when none is."""
    return max([0, *used]) + 1
