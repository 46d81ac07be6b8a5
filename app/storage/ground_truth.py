"""The simulator's ground truth beside a capture directory (``trifuse-ground-truth/1``):
``ground_truth.yaml`` (the board and each view's board pose) and ``ground_truth_rig.yaml``
(the rig the views were rendered with, a normal rig file)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from trifuse.app.storage.atomic import atomic_write_bytes
from trifuse.app.storage.capture import CaptureError, check_name, read_yaml_file
from trifuse.app.storage.rigfile import load_rig, save_rig
from trifuse.calib.board import Board, board_from_dict
from trifuse.calib.rig import Rig
from trifuse.calib.transforms import rigidity_problem

GROUND_TRUTH_FILE = "ground_truth.yaml"
GROUND_TRUTH_RIG_FILE = "ground_truth_rig.yaml"
GROUND_TRUTH_FORMAT = "trifuse-ground-truth/1"


def write_ground_truth(
    capture_dir: str | Path,
    rig: Rig,
    views: Iterable[tuple[str, np.ndarray]],
    board: Board,
) -> tuple[Path, Path]:
    """Write the simulator's ground truth: ``ground_truth_rig.yaml`` and ``ground_truth.yaml``.

    Args:
        capture_dir: the capture directory.
        rig: the rig the views were rendered with (a normal rig file).
        views: (view name, ``T_rig_board``) pairs; ``T_rig_board`` is the (4, 4) board pose in
            the rig frame, metres.
        board: the checkerboard.

    Returns:
        The paths of ``ground_truth.yaml`` and ``ground_truth_rig.yaml``. Existing files are
        never replaced (CaptureError).
    """
    capture_dir = Path(capture_dir)
    gt_path = capture_dir / GROUND_TRUTH_FILE
    rig_path = capture_dir / GROUND_TRUTH_RIG_FILE
    for p in (gt_path, rig_path):
        if p.exists():
            raise CaptureError(f"{p}: exists already; refusing to overwrite ground truth")
    poses: dict[str, Any] = {}
    for name, T in views:
        check_name(name, "view name")
        problem = rigidity_problem(T)
        if problem is not None:
            raise CaptureError(f"view {name!r}: T_rig_board is not a rigid transform: {problem}")
        if name in poses:
            raise CaptureError(f"view {name!r}: listed twice in the ground truth")
        poses[name] = {"T_rig_board": np.asarray(T, dtype=np.float64).tolist()}
    data = {
        "format": GROUND_TRUTH_FORMAT,
        "rig": GROUND_TRUTH_RIG_FILE,
        "board": board.to_dict(),
        "views": poses,
    }
    save_rig(rig_path, rig, overwrite=True)
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    atomic_write_bytes(gt_path, text.encode("utf-8"))
    return gt_path, rig_path


@dataclass
class GroundTruth:
    """What the simulator rendered: the rig, the board and each view's board pose.

    Attributes:
        rig: the ground-truth rig.
        board: the checkerboard.
        T_rig_board: view name -> (4, 4) float64 board pose in the rig frame, metres.
    """

    rig: Rig
    board: Board
    T_rig_board: dict[str, np.ndarray] = field(default_factory=dict)


def load_ground_truth(capture_dir: str | Path) -> GroundTruth:
    """Read ``ground_truth.yaml`` (and the rig file it names); CaptureError names the defect."""
    capture_dir = Path(capture_dir)
    path = capture_dir / GROUND_TRUTH_FILE
    data = read_yaml_file(path, "ground truth")
    if not isinstance(data, dict):
        raise CaptureError(f"{path}: expected a mapping, got {type(data).__name__}")
    expected = {"format", "rig", "board", "views"}
    if set(data) != expected:
        raise CaptureError(f"{path}: expected keys {sorted(expected)}, got {sorted(data, key=str)}")
    if data["format"] != GROUND_TRUTH_FORMAT:
        raise CaptureError(
            f"{path}: field 'format': expected {GROUND_TRUTH_FORMAT!r}, got {data['format']!r}"
        )
    rig_name = data["rig"]
    if not isinstance(rig_name, str) or Path(rig_name).name != rig_name:
        raise CaptureError(f"{path}: field 'rig': expected a file name beside it, got {rig_name!r}")
    rig = load_rig(capture_dir / rig_name)
    try:
        board = board_from_dict(data["board"])
    except ValueError as exc:
        raise CaptureError(f"{path}: field 'board': {exc}") from None
    views = data["views"] or {}
    if not isinstance(views, dict):
        raise CaptureError(
            f"{path}: field 'views': expected a mapping of view name to pose, "
            f"got {type(views).__name__}"
        )
    poses: dict[str, np.ndarray] = {}
    for name, entry in views.items():
        if not isinstance(entry, dict) or set(entry) != {"T_rig_board"}:
            raise CaptureError(
                f"{path}: view {name!r}: expected {{T_rig_board: 4x4}}, got {entry!r}"
            )
        problem = rigidity_problem(entry["T_rig_board"])
        if problem is not None:
            raise CaptureError(f"{path}: view {name!r}: T_rig_board: {problem}")
        poses[str(name)] = np.asarray(entry["T_rig_board"], dtype=np.float64)
    return GroundTruth(rig=rig, board=board, T_rig_board=poses)
