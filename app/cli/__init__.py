"""The ``trifuse`` command line.

Each command is a module here with ``add_parser(commands)``, which adds its argparse
subparser and returns the one that runs, beside ``run(args) -> int``, its handler;
:func:`build_parser` asks each to add itself, in the order ``trifuse --help`` lists them,
and points the parser at the handler. Bad arguments and bad input (``ValueError`` and its
subclasses ``CaptureError``, ``RigError`` ...) print one line to stderr and exit 2;
operating-system errors (permissions, a full disk) exit 1 the same way. No traceback reaches
the user for either.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from trifuse.app.cli import (
    analyze,
    balance_thermal,
    bench,
    calibrate,
    calibrate_range,
    check,
    compare,
    fuse,
    measure,
    record,
    rig,
    serve,
    simulate,
)
from trifuse.app.cli import map as map_command
from trifuse.app.cli.args import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, PROG, Parser, UsageError

__all__ = ["EXIT_FAILURE", "EXIT_OK", "EXIT_USAGE", "PROG", "UsageError", "build_parser", "main"]

COMMANDS = (
    simulate,
    calibrate,
    compare,
    rig,
    calibrate_range,
    balance_thermal,
    serve,
    bench,
    analyze,
    record,
    fuse,
    measure,
    map_command,
    check,
)
"""The command modules, in the order of ``trifuse --help``."""


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("trifuse")
    except Exception:  # not installed: running from a source tree
        return "(source tree)"


class _VersionAction(argparse.Action):
    """``--version``: argparse's, but the version is looked up only when asked for (the
    package metadata takes longer to read than the rest of the parser to build)."""

    def __init__(self, option_strings: list[str], dest: str, help: str | None = None) -> None:
        super().__init__(
            option_strings, argparse.SUPPRESS, nargs=0, default=argparse.SUPPRESS, help=help
        )

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: object,
        option_string: str | None = None,
    ) -> None:
        print(f"{parser.prog} {_version()}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    """The ``trifuse`` parser; each command sets ``func`` to its handler."""
    parser = Parser(
        prog=PROG,
        description="Calibrate and operate a colour / thermal / time-of-flight sensor head.",
        epilog=f"Run '{PROG} COMMAND --help' for a command's options.",
    )
    parser.add_argument(
        "--version", action=_VersionAction, help="show program's version number and exit"
    )
    commands = parser.add_subparsers(title="commands", metavar="COMMAND", dest="command")
    for command in COMMANDS:
        command.add_parser(commands).set_defaults(func=command.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``trifuse`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if getattr(args, "func", None) is None:
            sub = f" {args.command}" if getattr(args, "command", None) else ""
            raise UsageError(f"{PROG}{sub}: expected a command (see '{PROG}{sub} --help')")
        return int(args.func(args))
    except SystemExit as exc:  # --help and --version
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    except UsageError as exc:
        message = str(exc)  # argparse's and some commands' messages name the command
        named = message.startswith((f"{PROG}:", f"{PROG} "))
        print(message if named else f"{PROG}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as exc:  # CaptureError, RigError, CalibrationError, ...
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (OSError, RuntimeError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
