"""The install layout (pyproject.toml): the folders ``app/``, ``calib/`` and ``fusion/`` are
installed as ``trifuse.app``, ``trifuse.calib`` and ``trifuse.fusion``, with ``static/`` as
``trifuse/static``; every package folder is listed, so a normal (non-editable) install has
every module, and nothing named ``app``, ``calib`` or ``fusion`` lands in site-packages."""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

from tests.support import ROOT

SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
FOLDERS = {"trifuse.app": "app", "trifuse.calib": "calib", "trifuse.fusion": "fusion"}


def package_folders() -> set[str]:
    """``trifuse.<dotted folder>`` of every folder under app/, calib/, fusion/ that holds an
    ``__init__.py``."""
    return {
        "trifuse." + ".".join(init.parent.relative_to(ROOT).parts)
        for top in FOLDERS.values()
        for init in (ROOT / top).rglob("__init__.py")
    }


def test_every_package_folder_is_installed_under_trifuse() -> None:
    listed = set(SETUPTOOLS["packages"])
    assert listed - {"trifuse.static"} == package_folders()
    assert SETUPTOOLS["package-dir"] == {**FOLDERS, "trifuse.static": "static"}
    assert SETUPTOOLS["package-data"] == {"trifuse.static": ["*"]}


def test_the_console_script_and_the_pages_resolve_from_the_package() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    module, _, function = project["scripts"]["trifuse"].partition(":")
    assert callable(getattr(importlib.import_module(module), function))
    from trifuse.app.server.routers.pages import STATIC

    # installed or editable, the pages sit beside the packages: <trifuse>/static
    assert (STATIC / "viewer.html").is_file()
    assert Path(importlib.import_module("trifuse.app").__file__).parents[1] == STATIC.parent
