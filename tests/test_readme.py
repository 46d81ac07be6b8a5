"""The README's commands: the files they write into the checkout are ignored by git, as
the checkout's own outputs are, so that ``git status`` stays clean after following it."""

from __future__ import annotations

import fnmatch
import itertools
import re
import shlex
from pathlib import Path

from tests.support import ROOT

OUTPUT_OPTIONS = ("--out", "--report", "--plot", "--report-html", "--map-file")


def _readme_outputs() -> set[str]:
    """Relative paths the README's shell blocks pass to an output option."""
    text = (ROOT / "README.md").read_text()
    outputs: set[str] = set()
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.splitlines():
            words = shlex.split(line.split("#")[0])
            for option, value in itertools.pairwise(words):
                if option in OUTPUT_OPTIONS and not value.startswith(("/", "$")):
                    outputs.add(value.rstrip("/"))
    return outputs


def _ignored(path: str, patterns: list[str]) -> bool:
    """Whether a root-anchored ``.gitignore`` pattern (``/name``, ``/name/``) or an
    unanchored one covers ``path`` (its first component for a directory pattern)."""
    first = path.split("/")[0]
    for p in patterns:
        anchored, pattern = p.startswith("/"), p.strip("/")
        candidates = (path, first) if anchored else (path, first, Path(path).name)
        if any(fnmatch.fnmatch(c, pattern) for c in candidates):
            return True
    return False


def test_what_the_readme_writes_is_ignored() -> None:
    patterns = [
        line.strip()
        for line in (ROOT / ".gitignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    outputs = _readme_outputs()
    # the README's commands write these (a check that the parsing found them)
    assert {"captures", "rig.yaml", "survey.mcap", "room.ply", "fused"} <= outputs, outputs
    written = outputs | {f"{Path(o).stem}.map.npz" for o in outputs if o.endswith(".ply")}
    assert [o for o in sorted(written) if not _ignored(o, patterns)] == []
