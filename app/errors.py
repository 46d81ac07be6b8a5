"""How the program words an exception it reports instead of raising (a status line, a
panel, a log): one home for the text, so every report reads the same."""

from __future__ import annotations


class ControlError(RuntimeError):
    """A control that does not apply now (replay control on a live source, a second
    recording, stop without a recording); the REST API answers 409 with the message."""


def describe_error(exc: BaseException) -> str:
    """``"<type name>: <message>"`` of ``exc`` (only the type name when the message is
    empty), e.g. ``"ValueError: rig: no sensor 'tof'"``."""
    text = str(exc)
    name = type(exc).__name__
    return f"{name}: {text}" if text else name
