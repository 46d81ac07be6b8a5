"""Imports point one way, ``app -> fusion -> calib``, imports inside functions included:
``calib`` imports neither ``fusion`` nor ``app``, ``fusion`` does not import ``app``."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"calib": ("fusion", "app"), "fusion": ("app",)}


def imported_packages(path: Path) -> set[tuple[str, int]]:
    """Top-level package of every import in ``path`` (module level or not), with its line."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {(a.name.split(".")[0], node.lineno) for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add((node.module.split(".")[0], node.lineno))
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_imports_point_one_way(package: str) -> None:
    wrong = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for path in sorted((ROOT / package).rglob("*.py"))
        for name, line in imported_packages(path)
        if name in FORBIDDEN[package]
    ]
    assert not wrong, wrong


def test_the_check_sees_imports_inside_functions(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from fusion.geometry import tof_rays\n    import app.cli\n")
    assert imported_packages(module) == {("fusion", 2), ("app", 3)}
