"""The rig in the formats robotics tools speak (issue 21; docs/FORMATS.md, "Rig formats"):
ROS ``camera_info``, Kalibr camchain, OpenCV ``FileStorage`` and a URDF fragment.

Pure text in, text out (the CLI, ``app/cli/rig.py``, reads and writes the files). Each
format module provides

* ``export(rig: Rig, **options) -> Exported``: the files (relative path -> text) and what
  the format could not hold;
* ``import_(files: Mapping[str, str], **options) -> Imported`` (not ``urdf``): a rig from
  the files (file name -> text) and what the files did not say (and how it was filled in).

A round trip through a format reproduces the rig to 1e-9 in every number it can hold;
everything else is listed in ``lost``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal, get_args

from trifuse.calib.rig import Rig

RigFormat = Literal["ros", "kalibr", "opencv", "urdf"]
RIG_FORMATS: tuple[RigFormat, ...] = get_args(RigFormat)
IMPORT_FORMATS: tuple[RigFormat, ...] = ("ros", "kalibr", "opencv")


@dataclass(frozen=True)
class Exported:
    """A rig written in a format.

    Attributes:
        files: relative path -> text of each file.
        lost: what the format cannot hold, one sentence each (e.g. "range_correction of
            tof: ROS camera_info has no range correction").
    """

    files: dict[str, str]
    lost: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Imported:
    """A rig read from a format.

    Attributes:
        rig: the rig.
        lost: what the files did not say and how it was filled in, one sentence each.
    """

    rig: Rig
    lost: list[str] = field(default_factory=list)


def export_rig(rig: Rig, fmt: RigFormat, **options: object) -> Exported:
    """``rig`` in format ``fmt`` (see the module docstring); ValueError for an unknown one."""
    return _module(fmt).export(rig, **options)


def import_rig(files: Mapping[str, str], fmt: RigFormat, **options: object) -> Imported:
    """A rig from ``files`` (name -> text) in format ``fmt``; ValueError for an unknown
    format or one that cannot be imported (``urdf``), RigError for files that do not make
    a rig."""
    if fmt not in IMPORT_FORMATS:
        raise ValueError(f"format: expected one of {IMPORT_FORMATS} to import, got {fmt!r}")
    return _module(fmt).import_(files, **options)


def _module(fmt: str):
    if fmt not in RIG_FORMATS:
        raise ValueError(f"format: expected one of {RIG_FORMATS}, got {fmt!r}")
    from importlib import import_module

    return import_module(f"trifuse.calib.rig_formats.{fmt}_format")
