"""Imports point one way, ``app -> fusion -> calib``, imports inside functions included:
``calib`` imports neither ``fusion`` nor ``app``, ``fusion`` does not import ``app``; no
modules import each other in a circle; and every import names the installed package
(``trifuse.calib``, never a bare ``calib``, which a normal install does not have)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"calib": ("fusion", "app"), "fusion": ("app",)}


def imported_modules(path: Path) -> set[str]:
    """Every module of the project's packages that ``path`` imports, anywhere in it
    (``from a.b import c`` counts ``a.b`` and, when it is a module, ``a.b.c``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    return found


def module_graph() -> dict[str, set[str]]:
    """Module name -> the project modules it imports (app, fusion, calib)."""
    paths = {}
    for package in ("app", "fusion", "calib"):
        for path in (ROOT / package).rglob("*.py"):
            name = ".".join(("trifuse", *path.relative_to(ROOT).with_suffix("").parts))
            paths[name.removesuffix(".__init__")] = path
    return {m: (imported_modules(p) & paths.keys()) - {m} for m, p in paths.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other in a circle (Tarjan's strongly
    connected components of more than one module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = stack[stack.index(v) :]
            del stack[stack.index(v) :]
            if len(group) > 1:
                found.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_modules_import_each_other_in_a_circle() -> None:
    assert circles(module_graph()) == []


def test_the_circle_check_finds_a_circle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert circles(graph) == [["a", "b", "c"]]


def _package(module: str) -> str:
    """``trifuse.calib.board`` -> ``calib``; anything else -> its top-level name."""
    parts = module.split(".")
    return parts[1] if parts[0] == "trifuse" and len(parts) > 1 else parts[0]


def imported_packages(path: Path) -> set[tuple[str, int]]:
    """The project package (``app``, ``fusion``, ``calib``) or other top-level package of
    every import in ``path`` (module level or not), with its line."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {(_package(a.name), node.lineno) for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add((_package(node.module), node.lineno))
    return found


def bare_imports(path: Path) -> list[int]:
    """Lines of ``path`` importing ``app``, ``calib`` or ``fusion`` without ``trifuse.``."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        if any(n.split(".")[0] in ("app", "calib", "fusion") for n in names):
            lines.append(node.lineno)
    return lines


def test_every_import_names_the_installed_package() -> None:
    wrong = [
        f"{path.relative_to(ROOT)}:{line}"
        for package in ("app", "calib", "fusion", "tests")
        for path in sorted((ROOT / package).rglob("*.py"))
        for line in bare_imports(path)
    ]
    assert not wrong, wrong


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
    module.write_text(
        "def f():\n    from trifuse.fusion.geometry import tof_rays\n    import trifuse.app.cli\n"
        "    import calib.board\n"
    )
    assert imported_packages(module) == {("fusion", 2), ("app", 3), ("calib", 4)}
    assert bare_imports(module) == [4]
