"""Where trifuse keeps what it can compute again: a folder of the user's cache directory."""

from __future__ import annotations

import os
from pathlib import Path

OFF = ("off", "0", "no", "false")
"""Values of a cache's environment variable that keep no cache on disk (any case)."""


def user_cache_dir(env_var: str, name: str) -> Path | None:
    """``$<env_var>`` if set (None if it is one of :data:`OFF`), else
    ``$XDG_CACHE_HOME/trifuse/<name>`` or ``~/.cache/trifuse/<name>``."""
    env = os.environ.get(env_var)
    if env:
        return None if env.lower() in OFF else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "trifuse" / name
