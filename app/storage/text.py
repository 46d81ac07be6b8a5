"""Reading a text file with an error that names it and says what went wrong."""

from __future__ import annotations

from pathlib import Path


def read_text(path: Path, what: str, error: type[Exception]) -> str:
    """The UTF-8 text of ``path``, else ``error`` with a message starting with the path.

    Args:
        path: the file.
        what: what the file is, for the message, e.g. ``"rig file"``.
        error: the caller's exception type (its constructor takes the message).

    Raises:
        error: ``"<path>: cannot read <what>: <reason>"`` when the file cannot be read
            (missing, a folder, no permission, a path the OS cannot take such as one with
            a NUL byte), ``"<path>: <what> is not UTF-8 text: <reason> at byte <n>"`` when
            its bytes are not UTF-8.
    """
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: {what} is not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    except ValueError as exc:  # a path the OS cannot take (a NUL byte)
        raise error(f"{path}: cannot read {what}: {exc}") from None
