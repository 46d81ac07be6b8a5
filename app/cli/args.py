"""What every ``trifuse`` command shares about its arguments: the program name, the exit
codes, :class:`UsageError` and the parser that raises it, and the argparse types that check
a value as it is parsed (each refuses with one line saying what it expected)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, TypeVar

PROG = "trifuse"
EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2

T = TypeVar("T", int, float)


class UsageError(Exception):
    """Bad command-line arguments; the message is one line for the user."""


class Parser(argparse.ArgumentParser):
    """argparse, but errors raise UsageError (one line, no usage dump, no sys.exit)."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def checked(
    convert: Callable[[str], T],
    accept: Callable[[T], bool],
    expected: str,
    refused: str | None = None,
    show_value: bool = False,
) -> Callable[[str], T]:
    """An argparse type: ``convert(text)`` when ``accept`` takes it.

    Text that does not convert is refused with "expected EXPECTED, got 'TEXT'"; a value
    ``accept`` refuses with "expected REFUSED (default: EXPECTED), got 'TEXT'", or the
    value itself instead of the text when ``show_value``.
    """

    def parse(text: str) -> T:
        try:
            value = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not accept(value):
            shown = value if show_value else repr(text)
            raise argparse.ArgumentTypeError(f"expected {refused or expected}, got {shown}")
        return value

    return parse


def _finite_positive(value: float) -> bool:
    return math.isfinite(value) and value > 0


positive_int = checked(int, lambda v: v >= 1, "a positive integer", show_value=True)
seed = checked(int, lambda v: v >= 0, "an integer >= 0", show_value=True)
jpeg_quality = checked(int, lambda v: 1 <= v <= 100, "an integer 1..100", show_value=True)
positive_float = checked(float, _finite_positive, "a positive number")
non_negative = checked(
    float, lambda v: math.isfinite(v) and v >= 0, "a number >= 0", "a finite number >= 0"
)
positive = checked(float, _finite_positive, "a number > 0", "a finite number > 0")
positive_seconds = checked(
    float,
    _finite_positive,
    "a number of seconds > 0",
    "a finite number of seconds > 0",
)


def bounded_int(low: int, high: int) -> Callable[[str], int]:
    """An argparse type: an integer in ``[low, high]``."""
    return checked(int, lambda v: low <= v <= high, f"an integer from {low} to {high}")


def bounded_seconds(low: float, high: float) -> Callable[[str], float]:
    """An argparse type: seconds in ``[low, high]``."""
    return checked(
        float, lambda v: low <= v <= high, f"a number of seconds from {low:g} to {high:g}"
    )


def add_every_argument(parser: argparse.ArgumentParser, what: str) -> None:
    """``--every N`` (default 1: all): ``what`` says what every N-th is, e.g. "use every
    N-th frame set"."""
    parser.add_argument(
        "--every",
        type=positive_int,
        default=1,
        metavar="N",
        help=f"{what} (default: %(default)s: all)",
    )


def board_size(text: str) -> tuple[int, int]:
    """``COLSxROWS`` inner corners, at least 2x2 (a board that looks the same turned, such
    as 4x6 or 6x6, is ordered from the data: calib.board_ordering.order_views)."""
    parts = text.lower().split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected COLSxROWS inner corners such as 9x6, got {text!r}"
        ) from None
    if min(cols, rows) < 2:
        raise argparse.ArgumentTypeError(f"expected at least 2x2 inner corners, got {text!r}")
    return cols, rows


def board_size_or_file(text: str) -> tuple[int, int] | Path:
    """``COLSxROWS`` (:func:`board_size`), or the path of a board file (``*.yaml`` /
    ``*.yml``, read later)."""
    if text.lower().endswith((".yaml", ".yml")):
        return Path(text)
    return board_size(text)


def sensor_count(text: str) -> tuple[str, int]:
    """``SENSOR=N``, N >= 0: ``(sensor name, N)``."""
    name, sep, count = text.partition("=")
    try:
        n = int(count)
    except ValueError:
        n = -1
    if not sep or not name or n < 0:
        raise argparse.ArgumentTypeError(f"expected SENSOR=N (N >= 0), got {text!r}")
    return name, n


def tof_pixel(text: str) -> tuple[float, float]:
    """``U,V``: a TOF pixel, two finite numbers (pixels)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        u, v = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a TOF pixel as U,V (two numbers, e.g. 87.5,71.5), got {text!r}"
        ) from None
    if not (math.isfinite(u) and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected finite pixel coordinates, got {text!r}")
    return u, v


Commands = argparse._SubParsersAction
"""What ``add_subparsers`` returns: each command module's ``add_parser`` adds its parser."""
