"""``trifuse rig export`` / ``trifuse rig import``: a rig file in the formats robotics tools
speak (ROS ``camera_info`` + URDF, Kalibr camchain, OpenCV ``FileStorage``) and back
(docs/FORMATS.md, "Rig formats"; the conversions are ``calib.rig_formats``).

Both say what the other side cannot hold: the export what the format lost, the import what
the files did not say and how it was filled in. Nothing is overwritten without ``--force``,
and never the file read. The files are read in a child process
(``app.workflows.rig_import``): one that crashes a parser is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable, Mapping
from pathlib import Path, PurePosixPath
from typing import Any

from trifuse.app.cli.args import EXIT_OK, PROG, Commands, UsageError
from trifuse.app.cli.choices import IMPORT_FORMATS, MODALITIES, RIG_FORMATS
from trifuse.app.cli.files import load_rig_arg
from trifuse.app.cli.output import out

READ_SUFFIXES = (".yaml", ".yml", ".urdf", ".xml")
"""The files ``rig import DIR`` reads from a directory (not its subfolders, not hidden)."""


def add_parser(commands: Commands) -> argparse.ArgumentParser:
    """``rig export RIG.yaml --format F --out PATH [--force] [--strict]`` and ``rig import
    PATH --format F --out RIG.yaml [--eyes] [--reference] [--names] [--modalities]
    [--force]``."""
    rig = commands.add_parser(
        "rig",
        help="export a rig file as ROS, Kalibr, OpenCV or URDF files, or import one",
        description=(
            "Convert between the rig file (docs/FORMATS.md) and the calibration files "
            "robotics tools read: ROS camera_info YAML plus a URDF of the poses (ros), a "
            "Kalibr camchain (kalibr), OpenCV FileStorage YAML (opencv) and a URDF alone "
            "(urdf, export only). Each direction lists what the other side cannot hold."
        ),
        epilog=f"Run '{PROG} rig export --help' or '{PROG} rig import --help' for the options.",
    )
    actions = rig.add_subparsers(title="actions", metavar="ACTION", dest="rig_action")
    export = actions.add_parser(
        "export",
        help="write a rig file in another format",
        description=(
            "Write RIG.yaml in --format and print what the format cannot hold (e.g. the "
            "eye pairs, a thermal imager's radiometry; for kalibr, distortion terms beyond "
            "k1 k2 p1 p2 and how many pixels dropping them moves the farthest image corner). "
            "--out is a directory, created if needed, that must be empty unless --force "
            "(then only the files written are replaced); a format that writes one file "
            "(kalibr: camchain.yaml; urdf) may instead be given a file name with a suffix, "
            "e.g. --out head-camchain.yaml."
        ),
    )
    export.add_argument("rig", metavar="RIG.yaml", help="the rig file to export")
    export.add_argument("--format", required=True, choices=RIG_FORMATS, help="the format")
    export.add_argument(
        "--out",
        required=True,
        metavar="PATH",
        help="output directory (new or empty), or for a one-file format a file name",
    )
    export.add_argument(
        "--force", action="store_true", help="write into a non-empty directory or over a file"
    )
    export.add_argument(
        "--strict",
        action="store_true",
        help="refuse instead of dropping what the format cannot hold of the lens model "
        "(kalibr: a non-zero k3 ... k6)",
    )
    imp = actions.add_parser(
        "import",
        help="make a rig file from files in another format",
        description=(
            "Read PATH (a file, or a directory: its .yaml, .yml, .urdf and .xml files) in "
            "--format, write the rig file --out and print what the files did not say and "
            "how it was filled in (e.g. the eye pairs, the modalities from the sensor "
            "names). The rig file is written atomically and never over an existing file "
            "unless --force."
        ),
    )
    imp.add_argument("path", metavar="PATH", help="the file or directory to import")
    imp.add_argument("--format", required=True, choices=IMPORT_FORMATS, help="the format")
    imp.add_argument("--out", required=True, metavar="RIG.yaml", help="the rig file to write")
    imp.add_argument(
        "--eyes",
        type=eyes_arg,
        metavar="left=COLOR:THERMAL,right=COLOR:THERMAL",
        help="the eye pairs (colour camera and thermal imager of each eye); without them "
        "the rig cannot be fused",
    )
    imp.add_argument(
        "--reference",
        metavar="NAME",
        help="the sensor whose frame is the rig frame (default: the format's base, "
        "e.g. Kalibr's cam0)",
    )
    imp.add_argument(
        "--names",
        type=names_arg,
        metavar="0=NAME,1=NAME",
        help="sensor names by camera index (kalibr: default the first element of each "
        "camera's rostopic, /thermal_left/image_raw -> thermal_left)",
    )
    imp.add_argument(
        "--modalities",
        type=modalities_arg,
        metavar="NAME=MODALITY,...",
        help=f"sensor modalities ({', '.join(MODALITIES)}); default from the name's prefix "
        "(ccd/color/rgb, thermal/lwir, tof/depth; kalibr: else color)",
    )
    imp.add_argument(
        "--allow-no-poses",
        action="store_true",
        help="ros, opencv: accept files without the sensors' poses (all at the rig "
        "frame's origin, listed among what the files did not say)",
    )
    imp.add_argument("--force", action="store_true", help="replace --out if it exists")
    return rig


# -- argument types -----------------------------------------------------------------------------


def _pairs(text: str, expected: str) -> list[tuple[str, str]]:
    """``A=B,C=D`` -> [(A, B), (C, D)]; ArgumentTypeError naming ``expected``."""
    pairs = []
    for item in text.split(","):
        key, sep, value = item.strip().partition("=")
        if not sep or not key.strip() or not value.strip():
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        pairs.append((key.strip(), value.strip()))
    keys = [k for k, _ in pairs]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise argparse.ArgumentTypeError(f"{', '.join(twice)} given twice in {text!r}")
    return pairs


def eyes_arg(text: str) -> dict[str, tuple[str, str]]:
    """``left=COLOR:THERMAL,right=COLOR:THERMAL`` -> {eye: (colour sensor, thermal sensor)}."""
    expected = "EYE=COLOR:THERMAL[,EYE=COLOR:THERMAL] such as left=ccd_left:thermal_left"
    eyes = {}
    for eye, pair in _pairs(text, expected):
        color, sep, thermal = pair.partition(":")
        if not sep or not color or not thermal or ":" in thermal:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        eyes[eye] = (color, thermal)
    return eyes


def names_arg(text: str) -> dict[int, str]:
    """``0=ccd_left,1=ccd_right`` -> {camera index: sensor name}."""
    expected = "INDEX=NAME[,INDEX=NAME] such as 0=ccd_left,1=ccd_right"
    names = {}
    for index, name in _pairs(text, expected):
        if not index.isdigit():
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        names[int(index)] = name
    return names


def modalities_arg(text: str) -> dict[str, str]:
    """``cam0=color,cam1=thermal`` -> {sensor name: modality}."""
    expected = f"NAME=MODALITY[,NAME=MODALITY] with MODALITY one of {', '.join(MODALITIES)}"
    modalities = dict(_pairs(text, expected))
    bad = sorted(m for m in modalities.values() if m not in MODALITIES)
    if bad:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {', '.join(bad)}")
    return modalities


# -- the format modules -------------------------------------------------------------------------


def _format_function(fmt: str, name: str) -> Callable[..., Any]:
    """``export`` or ``import_`` of ``calib.rig_formats.<fmt>_format``; UsageError when that
    module is not part of this version of trifuse."""
    from importlib import import_module

    module_name = f"trifuse.calib.rig_formats.{fmt}_format"
    try:
        module = import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name != module_name:
            raise
        raise UsageError(f"--format {fmt}: not available in this version of trifuse") from None
    return getattr(module, name)


def _options(fmt: str, function: Callable[..., Any], given: Mapping[str, Any]) -> dict[str, Any]:
    """The options the user gave (flag -> (keyword, value), None when not given) that
    ``function`` takes; UsageError naming a flag the format does not take."""
    params = inspect.signature(function).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    options = {}
    for flag, (keyword, value) in given.items():
        if value is None or value is False:
            continue
        if keyword not in params and not takes_any:
            raise UsageError(f"{flag}: the {fmt} format does not take it")
        options[keyword] = value
    return options


# -- files --------------------------------------------------------------------------------------


def _safe_relative(name: str) -> PurePosixPath:
    """A format's relative output path, refused if it would leave the output directory."""
    p = PurePosixPath(name)
    if p.is_absolute() or not p.parts or ".." in p.parts:
        raise ValueError(f"format wrote an unsafe file name {name!r}")
    return p


def export_targets(out_path: Path, names: list[str], force: bool) -> dict[str, Path]:
    """Where each exported file goes: ``out_path`` itself for a single file when it has a
    suffix and is not a directory, else ``out_path/<name>`` (the directory must be new,
    empty, or ``force``). UsageError for a refusal; with no ``names`` (not exported yet),
    only the refusals that do not depend on them."""
    if (out_path.exists() or out_path.is_symlink()) and not out_path.is_dir():
        if not force:
            raise UsageError(
                f"--out {out_path}: exists; refusing to overwrite it (choose a new name, "
                "or --force)"
            )
        if names and not (len(names) == 1 and out_path.suffix):
            raise UsageError(
                f"--out {out_path}: exists and is not a directory; refusing to replace it "
                f"with one ({', '.join(names)} go into a directory)"
            )
    if len(names) == 1 and out_path.suffix and not out_path.is_dir():
        return {names[0]: out_path}
    if out_path.is_dir() and any(out_path.iterdir()) and not force:
        raise UsageError(
            f"--out {out_path}: directory exists and is not empty; refusing to write into it "
            "(choose a new directory, or --force to replace the files written)"
        )
    return {n: out_path.joinpath(*_safe_relative(n).parts) for n in names}


def read_inputs(path: Path) -> dict[str, str]:
    """The files to import: ``path`` itself, or a directory's ``READ_SUFFIXES`` files (by
    name -> text). UsageError when there is nothing to read."""
    from trifuse.app.storage.text import read_text
    from trifuse.calib.errors import RigError

    if path.is_dir():
        found = sorted(
            p
            for p in path.iterdir()
            if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in READ_SUFFIXES
        )
        if not found:
            raise UsageError(f"{path}: a directory without {', '.join(READ_SUFFIXES)} files")
        return {p.name: read_text(p, "file", RigError) for p in found}
    if not path.exists():
        raise UsageError(f"{path}: no such file or directory")
    return {path.name: read_text(path, "file", RigError)}


def _same(a: Path, b: Path) -> bool:
    return a.exists() and b.exists() and a.resolve() == b.resolve()


def print_lost(title: str, lost: list[str]) -> None:
    """``title:`` and one ``  - item`` line each, or ``title: nothing``."""
    if not lost:
        out(f"{title}: nothing")
        return
    out(f"{title}:")
    for item in lost:
        out(f"  - {item}")


# -- the commands -------------------------------------------------------------------------------


def run(args: argparse.Namespace) -> int:
    """``rig export`` or ``rig import``."""
    if args.rig_action == "export":
        return run_export(args)
    if args.rig_action == "import":
        return run_import(args)
    raise UsageError(f"{PROG} rig: expected a command (see '{PROG} rig --help')")


def run_export(args: argparse.Namespace) -> int:
    """Write the rig in ``--format``; say where and what the format lost."""
    from trifuse.app.storage.atomic import atomic_write_text, make_dirs
    from trifuse.calib.rig_formats import export_rig

    rig_path, out_path = Path(args.rig), Path(args.out)
    if not args.force:  # refusals first: the rig file need not exist for them
        export_targets(out_path, [], force=False)
    export = _format_function(args.format, "export")
    options = _options(args.format, export, {"--strict": ("strict", args.strict)})
    rig = load_rig_arg(args.rig)
    exported = export_rig(rig, args.format, **options)
    targets = export_targets(out_path, list(exported.files), args.force)
    for target in targets.values():
        if _same(target, rig_path):
            raise UsageError(f"--out {target}: is the rig file read; refusing to overwrite it")
    for name, target in targets.items():
        make_dirs(target.parent)
        atomic_write_text(target, exported.files[name], overwrite=args.force)
        out(f"wrote {target}")
    print_lost(f"not in the {args.format} files", exported.lost)
    return EXIT_OK


def run_import(args: argparse.Namespace) -> int:
    """Read the files, write the rig file; say what the files did not say."""
    from trifuse.app.storage.rigfile import save_rig
    from trifuse.app.workflows.rig_import import import_rig_isolated

    out_path = Path(args.out)
    if out_path.is_dir():
        raise UsageError(f"--out {out_path}: a directory; expected a rig file name")
    if (out_path.exists() or out_path.is_symlink()) and not args.force:
        raise UsageError(
            f"--out {out_path}: exists; refusing to overwrite it (choose a new name, or --force)"
        )
    in_path = Path(args.path)
    inputs = [in_path] + (sorted(in_path.iterdir()) if in_path.is_dir() else [])
    if any(_same(out_path, p) for p in inputs):
        raise UsageError(f"--out {out_path}: is a file read; refusing to overwrite it")
    import_ = _format_function(args.format, "import_")
    options = _options(
        args.format,
        import_,
        {
            "--eyes": ("eyes", args.eyes),
            "--reference": ("reference", args.reference),
            "--names": ("names", args.names),
            "--modalities": ("modalities", args.modalities),
            "--allow-no-poses": ("allow_no_poses", args.allow_no_poses),
        },
    )
    files = read_inputs(in_path)
    imported = import_rig_isolated(files, args.format, **options)  # a crash is one line
    save_rig(out_path, imported.rig, overwrite=args.force)
    rig = imported.rig
    eyes = ", ".join(f"{e}: {p.color} + {p.thermal}" for e, p in rig.eyes.items()) or "none"
    out(
        f"rig with {len(rig.sensors)} sensors ({', '.join(rig.names)}; reference "
        f"{rig.reference}; eyes {eyes}) written to {out_path}"
    )
    print_lost("not in the files", imported.lost)
    return EXIT_OK
