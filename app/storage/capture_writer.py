"""Writing capture directories (the layout is in :mod:`app.storage.capture`, which reads
them): the board, the starting rig, and views of PNG images, every file atomically and a
view complete or not at all."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.storage.atomic import atomic_write_bytes, fsync_dir, make_dirs, umask
from trifuse.app.storage.capture import (
    BOARD_FILE,
    DISTANCE_SUFFIX,
    RIG_FILE,
    CaptureError,
    ViewExistsError,
    check_name,
)
from trifuse.calib.board import Board
from trifuse.calib.rig import Rig, rig_to_yaml
from trifuse.calib.units import encode_amplitude, encode_distance, encode_thermal

# -- low-level file writing -----------------------------------------------------------------


def _encode_png(image: np.ndarray, what: str) -> bytes:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise CaptureError(f"{what}: OpenCV could not encode the image as PNG")
    return buf.tobytes()


def _write_same_or_fail(path: Path, text: str, what: str) -> Path:
    """Write ``text`` unless ``path`` holds it already; refuse to replace other content."""
    if path.exists():
        try:
            existing = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise CaptureError(f"{path}: exists and cannot be read: {exc.strerror}") from None
        if existing == text:
            return path
        raise CaptureError(f"{path}: exists with a different {what}; refusing to overwrite it")
    atomic_write_bytes(path, text.encode("utf-8"))
    return path


# -- encoding one sensor's images -----------------------------------------------------------


def _check_image(
    image: Any, sensor: str, modality: str, size: tuple[int, int] | None, what: str
) -> np.ndarray:
    """Check a frame's image array against the in-memory conventions and the rig's size."""
    if not isinstance(image, np.ndarray):
        raise CaptureError(f"{what}: expected a numpy array, got {type(image).__name__}")
    if modality == "color":
        if image.dtype != np.uint8 or not (
            image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
        ):
            raise CaptureError(
                f"{what}: expected a colour image (H, W, 3) uint8 RGB or (H, W) "
                f"uint8 grey, got shape {image.shape} {image.dtype}"
            )
    elif image.ndim != 2 or not (
        np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)
    ):
        raise CaptureError(
            f"{what}: expected a {modality} image (H, W) of numbers, "
            f"got shape {image.shape} {image.dtype}"
        )
    if size is not None and (image.shape[1], image.shape[0]) != size:
        raise CaptureError(
            f"{what}: expected {size[0]}x{size[1]} (width x height) as the rig says for "
            f"sensor {sensor!r}, got {image.shape[1]}x{image.shape[0]}"
        )
    return image


def _encode_frame(
    frame: Frame, sensor: str, modality: str, size: tuple[int, int] | None, where: str
) -> dict[str, bytes]:
    """PNG bytes of one sensor's frame, keyed by file name."""
    what = f"{where}: sensor {sensor!r}"
    image = _check_image(frame.image, sensor, modality, size, f"{what} image")
    files: dict[str, bytes] = {}
    if modality == "color":
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
        files[f"{sensor}.png"] = _encode_png(bgr, what)
    elif modality == "thermal":
        if frame.distance_m is not None:
            raise CaptureError(f"{what}: a thermal frame has no distance image, got one")
        files[f"{sensor}.png"] = _encode_png(encode_thermal(image), what)
    else:
        files[f"{sensor}.png"] = _encode_png(encode_amplitude(image), what)
        if frame.distance_m is not None:
            dist = frame.distance_m
            if not isinstance(dist, np.ndarray) or dist.shape != image.shape:
                got = dist.shape if isinstance(dist, np.ndarray) else type(dist).__name__
                raise CaptureError(
                    f"{what}: expected distance_m of the amplitude's shape {image.shape}, got {got}"
                )
            files[f"{sensor}{DISTANCE_SUFFIX}.png"] = _encode_png(encode_distance(dist), what)
    return files


# -- writing --------------------------------------------------------------------------------


def write_board(capture_dir: str | Path, board: Board) -> Path:
    """Write ``board.yaml`` into ``capture_dir`` (created if needed); return its path.

    Writing the same board again is a no-op; a different existing board raises CaptureError.
    """
    capture_dir = Path(capture_dir)
    make_dirs(capture_dir)
    text = yaml.safe_dump(board.to_dict(), sort_keys=False, default_flow_style=None)
    return _write_same_or_fail(capture_dir / BOARD_FILE, text, "board")


def write_rig(capture_dir: str | Path, rig: Rig) -> Path:
    """Write the starting rig ``rig.yaml`` into ``capture_dir``; return its path.

    Writing the same rig again is a no-op; a different existing rig raises CaptureError.
    """
    capture_dir = Path(capture_dir)
    make_dirs(capture_dir)
    return _write_same_or_fail(capture_dir / RIG_FILE, rig_to_yaml(rig), "rig")


def write_view(capture_dir: str | Path, view_name: str, frames: FrameSet, rig: Rig) -> Path:
    """Write one view (a folder of PNG images, one per sensor) and return the folder's path.

    Args:
        capture_dir: the capture directory (created if needed).
        view_name: the folder name, e.g. ``"0001"``; an existing folder of that name raises
            :class:`ViewExistsError` (a capture is never overwritten).
        frames: the frames to write; every sensor must be in ``rig``. Colour (H, W, 3)
            uint8 RGB (or (H, W) grey) -> 8-bit PNG; thermal kelvin -> 16-bit PNG in
            centi-kelvin (rounded, clipped, NaN -> 0); TOF amplitude -> 16-bit ``<tof>.png``
            (rounded, clipped) and, if ``distance_m`` is set, radial distance -> 16-bit
            ``<tof>_distance.png`` in millimetres with 0 = invalid.
        rig: gives each sensor's modality and image size (checked before anything is written).

    The images are encoded first, then written into a hidden staging folder (each file
    atomically) that is renamed to ``view_name``: a reader never sees half a view.
    """
    capture_dir = Path(capture_dir)
    check_name(view_name, "view name")
    target = capture_dir / view_name
    if target.exists():
        raise ViewExistsError(
            f"{target}: view exists already; refusing to overwrite a capture "
            "(choose another view name)"
        )
    if not frames.frames:
        raise CaptureError(f"view {view_name!r}: expected at least one frame, got none")

    encoded: dict[str, bytes] = {}
    for sensor, frame in frames.frames.items():
        check_name(sensor, "sensor name")
        if sensor.endswith(DISTANCE_SUFFIX):
            raise CaptureError(
                f"sensor {sensor!r}: names ending in {DISTANCE_SUFFIX!r} are "
                "reserved for TOF distance images"
            )
        if sensor not in rig:
            raise CaptureError(
                f"view {view_name!r}: sensor {sensor!r} is not in the rig (sensors: {rig.names})"
            )
        s = rig[sensor]
        encoded.update(
            _encode_frame(frame, sensor, s.modality, s.image_size, f"view {view_name!r}")
        )

    make_dirs(capture_dir)
    staging = Path(tempfile.mkdtemp(prefix=f".{view_name}.", suffix=".partial", dir=capture_dir))
    try:
        staging.chmod(0o777 & ~umask())
        for name, data in encoded.items():
            atomic_write_bytes(staging / name, data)
        fsync_dir(staging)
        if target.exists():  # appeared while we were encoding
            raise ViewExistsError(
                f"{target}: view exists already; refusing to overwrite a "
                "capture (choose another view name)"
            )
        os.rename(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    fsync_dir(capture_dir)
    return target
