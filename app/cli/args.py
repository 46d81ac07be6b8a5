"""What every ``trifuse`` command shares about its arguments: the program name, the exit
codes, :class:`UsageError` and the parser that raises it, and the argparse types that check
a value as it is parsed (each refuses with one line saying what it expected).

Building the parser imports nothing heavy (numpy, OpenCV, the fusion): ``trifuse --help``
and a refused argument answer at once. Choices owned by other modules are copied in
:mod:`app.cli.choices`."""

from __future__ import annotations

import argparse
import difflib
import math
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

if TYPE_CHECKING:
    from trifuse.app.sources.sim.drift import SensorDrift
    from trifuse.calib.rig import Rig

PROG = "trifuse"
EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2

T = TypeVar("T", int, float)


class UsageError(Exception):
    """Bad command-line arguments; the message is one line for the user."""


class Parser(argparse.ArgumentParser):
    """argparse, but errors raise UsageError (one line, no usage dump, no sys.exit) naming
    the command whose arguments were wrong, with close matches for a misspelt option,
    command or choice ("did you mean --out?")."""

    _given: tuple[str, ...] = ()
    """The arguments this parser was last given (a command's parser: those after its name)."""
    late_help: Callable[[], None] | None = None
    """Called before the help is formatted: fills in help text that needs an import the
    parser otherwise does without (``bench --only``'s list of benchmarks)."""

    def format_help(self) -> str:
        if self.late_help is not None:
            self.late_help()
        return super().format_help()

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self._given = tuple(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> argparse.Namespace:
        """As argparse, but arguments no parser took are refused by the command they were
        given to, which names them and its own help."""
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            command = chosen_command(self, namespace)
            unknown = command.unknown_options(extras)
            if unknown:
                command.error(unknown_options_message(command, unknown))
            command.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace

    def error(self, message: str) -> NoReturn:
        # A misspelt option explains what follows it (a required option missing, its value
        # taken for a positional argument): it is named first, with the close match.
        unknown = self.unknown_options(self._given)
        if unknown:
            message = unknown_options_message(self, unknown)
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        """argparse's check of a choice (a command's name, ``--scenario`` ...), with the
        closest choice suggested when the value is not one."""
        try:
            super()._check_value(action, value)
        except argparse.ArgumentError as exc:
            close = closest(value, action.choices) if isinstance(value, str) else None
            if close is None:
                raise
            head, sep, rest = exc.message.partition(" (choose from ")
            raise argparse.ArgumentError(
                action, f"{head}, did you mean {close!r}?{sep}{rest}"
            ) from None

    def unknown_options(self, given: Sequence[str]) -> list[str]:
        """The options in ``given`` this parser does not know (as written, without a
        ``=VALUE``), in order. A parser with commands looks only before the command (what
        follows is the command's); nothing after ``--`` is an option."""
        known = self._option_string_actions
        has_commands = any(isinstance(a, argparse._SubParsersAction) for a in self._actions)
        unknown = []
        for arg in given:
            if arg == "--":
                break
            if not _looks_like_option(arg):
                if has_commands:
                    break
                continue
            name = arg.split("=", 1)[0]
            if name in known or arg[:2] in known:  # --out=x, -h, a short option's value: -p80
                continue
            if (
                self.allow_abbrev
                and name.startswith("--")
                and any(o.startswith(name) for o in known)
            ):
                continue  # an abbreviation argparse takes (or calls ambiguous itself)
            unknown.append(name)
        return unknown


_NEGATIVE_NUMBER = re.compile(r"^-\d+$|^-\d*\.\d+$")


def _looks_like_option(arg: str) -> bool:
    """Whether argparse reads ``arg`` as an option (not a value such as ``-`` or ``-3``)."""
    return arg.startswith("-") and arg != "-" and not _NEGATIVE_NUMBER.match(arg) and " " not in arg


def closest(word: str, candidates: Any) -> str | None:
    """The candidate most like ``word`` (a typo's correction), or None if none is close."""
    matches = difflib.get_close_matches(word, [str(c) for c in candidates], n=1, cutoff=0.6)
    return matches[0] if matches else None


def unknown_options_message(parser: argparse.ArgumentParser, unknown: list[str]) -> str:
    """``unknown option --ouy; did you mean --out?`` (several: each with its close match)."""
    close = [closest(u, parser._option_string_actions) for u in unknown]
    if len(unknown) == 1:
        return f"unknown option {unknown[0]}" + (f"; did you mean {close[0]}?" if close[0] else "")
    named = [f"{u} (did you mean {c}?)" if c else u for u, c in zip(unknown, close, strict=True)]
    return f"unknown options {', '.join(named)}"


def chosen_command(parser: argparse.ArgumentParser, namespace: argparse.Namespace) -> Parser:
    """The parser of the command ``namespace`` chose (``trifuse rig export``'s for
    ``rig export ...``), or ``parser`` itself when it chose none."""
    while True:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                name = getattr(namespace, action.dest, None)
                if name in action.choices:
                    parser = action.choices[name]
                    break
        else:
            return parser  # type: ignore[return-value]


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
port_number = checked(
    int, lambda v: 1 <= v <= 65535, "a port number from 1 to 65535", show_value=True
)
listen_port = checked(
    int,
    lambda v: 0 <= v <= 65535,
    "a port number from 1 to 65535, or 0 for any free port",
    show_value=True,
)
"""A port to listen on: 0 lets the system choose a free one (say which it was)."""
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


def share_of_a_core(text: str) -> float:
    """An argparse type: a share of one core in ``[0.01, 1]``."""
    return checked(float, lambda v: 0.01 <= v <= 1.0, "a share of one core from 0.01 to 1")(text)


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


def sim_drift_arg(text: str | None, rig: Rig, command: str, option: str) -> SensorDrift | None:
    """The sensor drift of ``option`` (``SENSOR:RX,RY,RZ[@AT_S]``,
    :func:`~app.sources.sim.drift.parse_drift`) for the simulated head's ``rig``, or None
    without one; a UsageError of ``trifuse COMMAND`` with the parser's message for text it
    refuses or a sensor the rig does not have."""
    if text is None:
        return None
    from trifuse.app.sources.sim.drift import moved_rig, parse_drift

    try:
        drift = parse_drift(text)
        moved_rig(rig, drift)  # the sensor is the rig's
    except ValueError as exc:
        raise UsageError(f"{PROG} {command}: {option}: {exc}") from None
    return drift


Commands = argparse._SubParsersAction
"""What ``add_subparsers`` returns: each command module's ``add_parser`` adds its parser."""
