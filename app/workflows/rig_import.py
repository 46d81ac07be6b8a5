"""A rig imported from untrusted files in a child process (issue 29).

``calib.rig_formats.import_rig`` checks what it can before a native parser sees the text
(``calib.rig_formats.filestorage_text``, ``calib.yaml_text``), but OpenCV's FileStorage
and libyaml are C and C++: a file that still finds a way to crash one of them must not
take the console (or the CLI) down with it. :func:`import_rig_isolated` runs the import
in a child process, with its address space capped (``RLIMIT_AS``) and a time limit, and
turns a child that dies of a signal, runs out of memory or time into a one-line
:class:`RigError`.

The child is forked from multiprocessing's ``forkserver``: a fresh interpreter (nothing is
forked from a threaded server) started at the first isolated call, which has imported the
rig formats (numpy, OpenCV, PyYAML) once. A child then starts in about 20 ms, where a
``spawn`` child (a new interpreter importing numpy and OpenCV each time) took 0.2 s idle
and 0.35 s busy; the fork server costs an idle process of about 50 MB (and
multiprocessing's resource tracker, 13 MB) from the first import on. Like a ``spawn``
child, each child runs the parent's ``__main__`` (as ``__mp_main__``): a script that
imports rigs must guard its top level with ``if __name__ == "__main__":``.
"""

from __future__ import annotations

import multiprocessing
import pickle
import resource
import signal
import sys
from collections.abc import Callable, Mapping
from functools import partial
from importlib import import_module
from multiprocessing.connection import Connection
from typing import Any, TypeVar

from trifuse.calib.errors import RigError
from trifuse.calib.rig_formats import IMPORT_FORMATS, Imported, RigFormat, import_rig

T = TypeVar("T")

TIMEOUT_S = 30.0
"""Longest a rig import may take (a legitimate one takes well under a second, the child's
start included)."""
MEMORY_BYTES = 512 << 20
"""Address space the import may add to what the child holds once it has imported the
format's modules (a legitimate import adds a few MiB)."""


SERVER_PRELOAD = (
    __name__,
    *(f"trifuse.calib.rig_formats.{fmt}_format" for fmt in IMPORT_FORMATS),
)
"""What the fork server imports before it forks a child (this module and the formats)."""


def import_rig_isolated(
    files: Mapping[str, str],
    fmt: RigFormat,
    *,
    timeout_s: float = TIMEOUT_S,
    memory_bytes: int = MEMORY_BYTES,
    **options: object,
) -> Imported:
    """``calib.rig_formats.import_rig(files, fmt, **options)`` in a child process.

    Args:
        files: file name -> text, as ``import_rig`` takes them.
        fmt: the format (``ros``, ``kalibr``, ``opencv``).
        timeout_s: seconds the child may take, its start included.
        memory_bytes: address space the import may use beyond the child's own.
        options: ``import_rig``'s options (``eyes``, ``modalities``, ...).

    Returns:
        What ``import_rig`` returns.

    Raises:
        ValueError, RigError: as ``import_rig`` raises them (the same type and message).
        RigError: the child was killed by a signal (a file that crashes a parser), ran
            out of memory or time, or ended without an answer; the message says which.
        RuntimeError: the import failed otherwise (a bug), with the child's error.
    """
    preload = (f"trifuse.calib.rig_formats.{fmt}_format",) if fmt in IMPORT_FORMATS else ()
    return run_isolated(
        partial(import_rig, dict(files), fmt, **options),
        what=f"rig import ({fmt})",
        preload=preload,
        timeout_s=timeout_s,
        memory_bytes=memory_bytes,
    )


def run_isolated(
    call: Callable[[], T],
    *,
    what: str,
    preload: tuple[str, ...] = (),
    timeout_s: float = TIMEOUT_S,
    memory_bytes: int = MEMORY_BYTES,
) -> T:
    """``call()`` in a child of the fork server: its result, or the ValueError it raised.

    ``call`` must pickle (a module-level function, or a ``functools.partial`` of one).
    The child imports the modules ``preload`` names, caps its address space at what it
    then holds plus ``memory_bytes``, and calls. ``what`` names the work in messages.
    Raises RigError (child killed, out of memory or time, no answer) or RuntimeError
    (another exception in the child), as :func:`import_rig_isolated` says."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(SERVER_PRELOAD))  # read when the server starts
    ours, theirs = ctx.Pipe(duplex=False)
    child = ctx.Process(
        target=_child,
        args=(theirs, call, preload, memory_bytes),
        name="trifuse-isolated",
        daemon=True,
    )
    child.start()
    theirs.close()
    try:
        answered = ours.poll(timeout_s)
        reply = ours.recv() if answered else None
    except (EOFError, OSError):  # the child ended without a word
        answered, reply = True, None
    finally:
        ours.close()
        child.join(1.0 if answered else 0.0)
        if child.is_alive():
            child.kill()
            child.join()
    if not answered:
        raise RigError(f"{what}: took longer than {timeout_s:g} s; stopped")
    if reply is None:
        code = child.exitcode
        if code is not None and code < 0:
            name = signal.Signals(-code).name
            raise RigError(
                f"{what}: its process was killed by {name} (a file that crashes the parser?); "
                "nothing was imported"
            )
        raise RigError(f"{what}: its process ended (status {code}) without an answer")
    kind, value = reply
    if kind == "ok":
        return value
    if kind == "raised":
        raise value
    if kind == "memory":
        raise RigError(f"{what}: needed more than {memory_bytes >> 20} MiB of memory; refused")
    raise RuntimeError(f"{what} failed: {value}")


def _child(
    conn: Connection, call: Callable[[], Any], preload: tuple[str, ...], memory_bytes: int
) -> None:
    """The child: import ``preload``, cap the address space, call, send the outcome."""
    try:
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a crash leaves no core file
        for name in preload:
            import_module(name)
        _quiet_opencv()
        limit = _address_space() + memory_bytes
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        reply: tuple[str, Any] = ("ok", call())
    except MemoryError:
        reply = ("memory", None)
    except ValueError as exc:
        try:  # the parent re-raises it: it must come back whole
            reply = ("raised", pickle.loads(pickle.dumps(exc)))
        except Exception:
            reply = ("raised", ValueError(str(exc)))
    except Exception as exc:  # a bug: the parent raises RuntimeError with it
        reply = ("failed", f"{type(exc).__name__}: {exc}")
    try:
        conn.send(reply)
    except MemoryError:
        conn.send(("memory", None))
    except Exception as exc:  # an answer that does not pickle
        conn.send(("failed", f"cannot send the answer: {type(exc).__name__}: {exc}"))
    conn.close()


def _quiet_opencv() -> None:
    """Keep OpenCV's own warnings (on stderr) out of the one-line messages, if loaded."""
    cv2 = sys.modules.get("cv2")
    if cv2 is not None:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _address_space() -> int:
    """This process's address space now, bytes (``VmSize``)."""
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize in /proc/self/status")
