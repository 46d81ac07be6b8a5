"""Where an offline job over recordings runs: ``--ray [ADDRESS]`` and ``--chunk-s`` of
``trifuse fuse`` and ``trifuse map`` (:mod:`app.recording.jobs`)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from trifuse.app.cli.args import UsageError, non_negative
from trifuse.app.cli.choices import DEFAULT_CHUNK_S

if TYPE_CHECKING:
    from trifuse.app.recording.jobs import Runner

LOCAL_RAY = "local"


def add_cluster_arguments(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]`` and ``--chunk-s S``."""
    parser.add_argument(
        "--ray",
        nargs="?",
        const=LOCAL_RAY,
        metavar="ADDRESS",
        help="run the pieces as Ray tasks: on a new Ray instance on this machine (no "
        "ADDRESS), or on a running cluster (HOST:PORT, ray://HOST:PORT or auto). Needs the "
        "[ray] extra; every node must see the recordings at the same path. The output is "
        "the same bytes as without --ray",
    )
    parser.add_argument(
        "--chunk-s",
        type=non_negative,
        default=DEFAULT_CHUNK_S,
        metavar="S",
        help="split each recording into pieces of S seconds (by its MCAP index), which run "
        "in parallel under --ray; 0: one piece per recording. The output depends on it, "
        "not on where the pieces run (default: %(default)s)",
    )


def pieces_text(chunk_s: float) -> str:
    """``--chunk-s`` in words."""
    return f"{chunk_s:g} s each" if chunk_s > 0 else "one per recording"


@contextmanager
def open_runner(args: argparse.Namespace) -> Iterator[Runner]:
    """The runner ``--ray`` names (the local one without it); a Ray instance it started
    is shut down at the end."""
    from trifuse.app.recording.jobs import LocalRunner, RayRunner

    if args.ray is None:
        yield LocalRunner()
        return
    if args.ray != LOCAL_RAY and (args.ray.endswith(".mcap") or Path(args.ray).exists()):
        raise UsageError(
            f"--ray {args.ray}: that is a file, not a cluster's address; put --ray after the "
            "recordings (or give it an address: --ray HOST:PORT)"
        )
    try:
        runner = RayRunner(None if args.ray == LOCAL_RAY else args.ray)
    except ImportError as exc:
        raise UsageError(str(exc)) from None
    except ConnectionError as exc:
        raise UsageError(
            f"--ray {args.ray}: cannot connect to the cluster ({exc}); is its head running, "
            "and if it uses Ray's token authentication, does this machine have its token "
            "(RAY_AUTH_MODE=token, and the head's ~/.ray/auth_token here or RAY_AUTH_TOKEN)?"
        ) from None
    with runner:
        yield runner
