"""Imports point one way, ``app -> fusion -> calib``, imports inside functions included:
``calib`` imports neither ``fusion`` nor ``app``, ``fusion`` does not import ``app``; inside
``app`` they point down its layers (``cli``/``devtools`` -> ``server`` -> ``workflows``/
``recording`` -> ``sources``/``storage``; the drivers, which talk to a console over the
network, import sources and storage only); no modules import each other in a circle; and
every import names the installed package (``trifuse.calib``, never a bare ``calib``, which a
normal install does not have)."""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pytest

from tests.support import ROOT

FORBIDDEN = {"calib": ("fusion", "app"), "fusion": ("app",)}


def nodes(path: Path) -> tuple[ast.AST, ...]:
    """Every node of ``path``'s syntax tree (each text parsed once a run: the checks
    below read every source file several times)."""
    return _nodes(path.read_text(), str(path))


@cache
def _nodes(text: str, name: str) -> tuple[ast.AST, ...]:
    return tuple(ast.walk(ast.parse(text, name)))


def imported_modules(path: Path) -> set[str]:
    """Every module of the project's packages that ``path`` imports, anywhere in it
    (``from a.b import c`` counts ``a.b`` and, when it is a module, ``a.b.c``)."""
    found = set()
    for node in nodes(path):
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
    for node in nodes(path):
        if isinstance(node, ast.Import):
            found |= {(_package(a.name), node.lineno) for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add((_package(node.module), node.lineno))
    return found


def bare_imports(path: Path) -> list[int]:
    """Lines of ``path`` importing ``app``, ``calib`` or ``fusion`` without ``trifuse.``."""
    lines = []
    for node in nodes(path):
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


# -- the layers inside app -----------------------------------------------------------------

LOW = ("sources", "storage")
MIDDLE = ("workflows", "recording")
MAY_IMPORT: dict[str, tuple[str, ...]] = {
    # The programs: the command line and the developer tools use anything in app.
    "cli": ("devtools", "server", "drivers", *MIDDLE, *LOW),
    "devtools": ("cli", "server", "drivers", *MIDDLE, *LOW),
    # The console (web server, panels, its runtime) runs the workflows and the recordings.
    "server": (*MIDDLE, *LOW),
    # Offline and interactive work on frames and files; neither uses the other.
    "workflows": LOW,
    "recording": LOW,
    # Drivers talk to a console over the network: its protocol's clients, never the console.
    "drivers": LOW,
    # Where frames come from and where files go: each uses the other's types and helpers
    # (storage writes sources' frames; a camera reads its config with storage's reader).
    "sources": ("storage",),
    "storage": ("sources",),
}
"""Part of app (its sub-package) -> the parts it may import. The modules at app's top
(``app/errors.py``, ``app/latest_worker.py``, ...) are its bottom layer: they import no part
and every part may import them."""

ALLOWED: dict[tuple[str, str], str] = {
    # (importing file, imported part): the owner who removes the import; the lead empties
    # this list when their work has landed.
}
"""The imports against the layers that remain while other engineers' work lands."""


def app_part(module: str) -> str | None:
    """``trifuse.app.server.routers.auth`` -> ``server``; ``trifuse.app.errors`` ->
    ``errors``; ``trifuse.app`` -> ``""``; a module outside app -> None."""
    parts = module.split(".")
    if parts[:2] != ["trifuse", "app"]:
        return None
    return parts[2] if len(parts) > 2 else ""


def app_imports(path: Path) -> set[tuple[str, int]]:
    """The part of app (see :func:`app_part`) of every import of app in ``path``, module level
    or not, with its line (``from trifuse.app import x`` counts ``x``)."""
    found = set()
    for node in nodes(path):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
            if node.module == "trifuse.app":
                names = [f"trifuse.app.{a.name}" for a in node.names]
        found |= {(part, node.lineno) for n in names if (part := app_part(n)) is not None}
    return found


def layer_violations(app_dir: Path, allowed: dict[tuple[str, str], str]) -> list[str]:
    """``"<file>:<line> imports <part>"`` for every import of a part of app that the
    importing file's part may not import (:data:`MAY_IMPORT`), except those ``allowed``
    (keyed by the file's path relative to ``app_dir``'s parent, and the part)."""
    base = {p.stem for p in app_dir.glob("*.py")} - {"__init__"}
    wrong = []
    for path in sorted(app_dir.rglob("*.py")):
        rel = path.relative_to(app_dir)
        own = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        may = MAY_IMPORT.get(own, ())  # app's own top-level modules import no part
        name = str(path.relative_to(app_dir.parent))
        for part, line in sorted(app_imports(path)):
            if part in (own, "", *base, *may) or (name, part) in allowed:
                continue
            wrong.append(f"{name}:{line} imports {part}")
    return wrong


def test_every_part_of_app_is_placed_in_a_layer() -> None:
    parts = {p.name for p in (ROOT / "app").iterdir() if (p / "__init__.py").is_file()}
    assert parts == set(MAY_IMPORT)


def test_imports_inside_app_point_down_its_layers() -> None:
    assert layer_violations(ROOT / "app", ALLOWED) == []


def test_every_allowed_exception_is_still_needed() -> None:
    used = {
        (str(path.relative_to(ROOT)), part)
        for path in (ROOT / "app").rglob("*.py")
        for part, _ in app_imports(path)
    }
    assert set(ALLOWED) <= used, set(ALLOWED) - used


def test_the_layer_check_finds_an_import_upwards(tmp_path: Path) -> None:
    app = tmp_path / "app"
    for part, code in {
        "recording": "def f():\n    from trifuse.app.server.runtime import pipeline\n",
        "server": "from trifuse.app.recording import reader\nfrom trifuse.app import cli\n",
        "drivers": "import trifuse.app.server.routers.auth\nimport trifuse.app.errors\n",
        "storage": "from trifuse.app.sources.frames import Frame\nimport trifuse.calib.rig\n",
    }.items():
        (app / part).mkdir(parents=True)
        (app / part / "m.py").write_text(code)
    (app / "errors.py").write_text("from trifuse.app.storage import m\n")
    assert layer_violations(app, {}) == [
        "app/drivers/m.py:1 imports server",
        "app/errors.py:1 imports storage",
        "app/recording/m.py:2 imports server",
        "app/server/m.py:2 imports cli",
    ]
    assert layer_violations(app, {("app/server/m.py", "cli"): "X"}) == [
        "app/drivers/m.py:1 imports server",
        "app/errors.py:1 imports storage",
        "app/recording/m.py:2 imports server",
    ]


# -- the tests themselves -------------------------------------------------------------------


def shared_test_imports(path: Path) -> list[str]:
    """``"<file>:<line> imports <module>"`` for every import in ``path`` of a test module
    (``tests.test_*``) or of ``conftest``: helpers shared by tests live in support modules."""
    wrong = []
    for node in nodes(path):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            if name == "conftest" or name.startswith(("tests.test_", "tests.conftest")):
                wrong.append(f"{path.name}:{node.lineno} imports {name}")
                break
    return wrong


def own_place_paths(path: Path) -> list[int]:
    """Lines of ``path`` that use ``__file__`` (a path built from the file's own place)."""
    return [
        node.lineno for node in nodes(path) if isinstance(node, ast.Name) and node.id == "__file__"
    ]


def test_no_test_imports_another_test_module_or_conftest() -> None:
    paths = sorted((ROOT / "tests").rglob("*.py"))
    wrong = [w for path in paths for w in shared_test_imports(path)]
    assert not wrong, wrong


def test_tests_take_paths_from_support_not_from_their_own_place() -> None:
    """Test modules may move between folders: only support.py (ROOT, DATA_DIR) and
    conftest.py (the checkout on sys.path) use ``__file__``."""
    wrong = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in sorted((ROOT / "tests").rglob("*.py"))
        if path.name not in ("support.py", "conftest.py")
        for line in own_place_paths(path)
    ]
    assert not wrong, wrong


def test_the_test_checks_find_a_shared_test_module_and_an_own_place_path(tmp_path: Path) -> None:
    module = tmp_path / "test_m.py"
    module.write_text(
        "from pathlib import Path\nfrom conftest import DATA_DIR\n"
        "from tests import test_push\nfrom tests.support import ROOT\n"
        "HERE = Path(__file__).parent\n"
    )
    assert shared_test_imports(module) == [
        "test_m.py:2 imports conftest",
        "test_m.py:3 imports tests.test_push",
    ]
    assert own_place_paths(module) == [5]
