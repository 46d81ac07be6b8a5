"""The capture directory on disk: checkerboard views of every sensor, written and read back.

Layout (docs/FORMATS.md)::

    captures/
      board.yaml               # the checkerboard (calib.board)
      rig.yaml                 # optional starting rig (names, modalities, sizes, nominal poses)
      ground_truth.yaml        # optional, simulated captures only (trifuse-ground-truth/1)
      ground_truth_rig.yaml    # optional, the rig the simulator rendered with
      0001/                    # one folder per view, any name, sorted by name
        ccd_left.png           # colour: 8-bit RGB or grey, PNG, JPG or PPM
        thermal_left.png       # thermal: 16-bit PNG, centi-kelvin (0 = no reading); 8-bit
                               # grey, or false colour (a palette, mapped back: not kelvin)
        tof.png                # TOF amplitude: 8- or 16-bit PNG
        tof_distance.png       # TOF radial distance: 16-bit PNG, millimetres, 0 = invalid

In memory the images follow docs/CONVENTIONS.md: colour (H, W, 3) uint8 RGB, thermal
(H, W) float32 kelvin, TOF amplitude (H, W) float32 and TOF radial distance (H, W) float32
metres with NaN where invalid. BGR exists only at the OpenCV encode/decode calls.

This module holds the format and reads it. :mod:`app.storage.capture_writer` writes it:
every file atomically (temporary file in the same directory, fsync, rename), and a view
appears complete or not at all (it is assembled in a hidden staging folder that is renamed
into place). :mod:`app.storage.ground_truth` reads and writes the ground truth files.
Reading is lazy: :func:`load_capture` checks the directory and the image
headers (sizes, bit depths) without decoding pixels; :meth:`CaptureView.frame` decodes one
image when asked, so 30 views x 5 sensors cost the memory of what the caller keeps.

An image file that cannot be read (empty, not an image, cut short, corrupted:
:class:`UnreadableImageError`) costs its view that image only: found when indexing, it is
set aside (:attr:`CaptureView.unreadable`) and its view keeps its other sensors; found when
decoding, :meth:`CaptureView.frame` raises it and sets the file aside too. A damaged PNG or
PNM is recognised before OpenCV decodes it (:func:`calib.image_header.image_damage`), and
OpenCV's own complaints are kept off the terminal (:func:`quiet_opencv`): the caller names
the file instead.
"""

from __future__ import annotations

import mmap
import os
import re
import threading
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame, FrameSet
from trifuse.app.storage.rigfile import load_rig
from trifuse.app.storage.text import read_text
from trifuse.calib.board import Board, board_from_dict
from trifuse.calib.image_header import ImageHeaderError, image_damage, image_header, pnm_header
from trifuse.calib.palette_inverse import PaletteError, PaletteFit, invert_palette
from trifuse.calib.rig import MODALITY_PREFIXES, Modality, Rig, modality_of_name
from trifuse.calib.units import kelvin_from_counts, metres_from_counts
from trifuse.calib.yaml_text import YamlError, parse_yaml
from trifuse.fusion.palettes import PALETTE_NAMES, palette

BOARD_FILE = "board.yaml"
RIG_FILE = "rig.yaml"

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm")
DISTANCE_SUFFIX = "_distance"
"""A TOF sensor's distance image is ``<sensor>_distance.png`` beside ``<sensor>.png``."""

ThermalEncoding = Literal["centikelvin", "counts"]

_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


class CaptureError(ValueError):
    """A capture directory, view or image is not what the format expects.

    The message names the file or folder, what was expected and what was found.
    """


class ViewExistsError(CaptureError):
    """A view folder of that name exists already; captures are never overwritten."""


class UnreadableImageError(CaptureError):
    """An image file that cannot be read or decoded: empty, not an image, cut short or
    corrupted (not one of another size or kind than the capture wants: that is a plain
    CaptureError). Its view can do without it (see the module docstring).

    Attributes:
        path: the file.
        why: what is wrong with it, without the path (the message is ``"<path>: <why>"``).
    """

    def __init__(self, path: Path, why: str) -> None:
        super().__init__(f"{path}: {why}")
        self.path = path
        self.why = why

    def __reduce__(self) -> tuple[type[UnreadableImageError], tuple[Path, str]]:
        return type(self), (self.path, self.why)


@dataclass(frozen=True)
class UnreadableImage:
    """An image file set aside: its view goes on without it.

    Attributes:
        sensor: whose image it is.
        path: the file.
        why: what is wrong with it (:attr:`UnreadableImageError.why`).
        distance: it is the TOF sensor's distance image (the sensor keeps its amplitude
            image), not the sensor's image itself.
    """

    sensor: str
    path: Path
    why: str
    distance: bool = False

    def describe(self) -> str:
        """``unreadable image <file name>, skipped: <why>`` (the view is said elsewhere)."""
        return f"unreadable image {self.path.name}, skipped: {self.why}"


# -- names and modalities -------------------------------------------------------------------


def modality_from_name(sensor: str) -> Modality:
    """Modality of a sensor from its name prefix (used when a capture has no rig.yaml):
    :func:`calib.rig.modality_of_name`, and CaptureError for any other name."""
    modality = modality_of_name(sensor)
    if modality is None:
        prefixes = ", ".join(f"{p}*" for p, _ in MODALITY_PREFIXES)
        raise CaptureError(
            f"sensor {sensor!r}: cannot tell its modality from the name (expected a prefix "
            f"among {prefixes}); add a rig.yaml to the capture directory that names the sensor"
        )
    return modality


def check_name(name: str, what: str) -> None:
    """CaptureError unless ``name`` (of a view or sensor: ``what``) can name a file."""
    if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
        raise CaptureError(
            f"{what} {name!r}: expected a file name of letters, digits, '.', '_' or '-' "
            "not starting with '.', '_' or '-'"
        )


# -- image headers --------------------------------------------------------------------------


@dataclass(frozen=True)
class ImageFile:
    """One image file of a view, as its header describes it (pixels not decoded).

    Attributes:
        path: the file.
        width, height: pixels.
        bit_depth: bits per sample (8 or 16).
        channels: samples per pixel as OpenCV decodes it (1 grey, 2 grey+alpha, 3, 4).
        format: ``"png"``, ``"jpeg"`` or ``"pnm"`` (binary PGM or PPM).
    """

    path: Path
    width: int
    height: int
    bit_depth: int
    channels: int
    format: Literal["png", "jpeg", "pnm"]


def read_image_header(path: str | Path) -> ImageFile:
    """Size, bit depth and channels of a PNG, JPEG or binary PGM/PPM file from its header
    (the file is mapped, not read: a JPEG's frame header may follow large metadata segments).
    A PNG or PNM cut short is found here too (:func:`calib.image_header.image_damage`
    without CRCs: a PNG's last bytes, its chunk headers only when those are not IEND).

    Raises UnreadableImageError naming the file when it cannot be read, is empty, is
    neither format or is cut short.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise UnreadableImageError(path, "not an image: an empty file")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                header = pnm_header(data) if data[:1] == b"P" else image_header(data)
                damage = image_damage(data, header, crc=False)
    except OSError as exc:
        raise UnreadableImageError(path, f"cannot read image: {exc.strerror}") from None
    except ImageHeaderError as exc:
        if "expected JPEG or PNG" in str(exc) or "expected a binary PGM" in str(exc):
            raise UnreadableImageError(path, f"not an image: {exc}") from None
        raise UnreadableImageError(path, str(exc)) from None
    if damage is not None:
        raise UnreadableImageError(path, damage)
    return ImageFile(
        path, header.width, header.height, header.bit_depth, header.channels, header.format
    )


# -- decoding -------------------------------------------------------------------------------

_quiet_lock = threading.Lock()
_quiet_depth = 0
_loud_level: int | None = None


@contextmanager
def quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's own log (``[ WARN ...]``, ``[ERROR ...]`` lines on stderr) while
    inside, as long as any thread is inside (the level is the process's); the level before
    the first entry is restored when the last one leaves."""
    global _quiet_depth, _loud_level
    with _quiet_lock:
        if _quiet_depth == 0:
            _loud_level = cv2.utils.logging.getLogLevel()
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        _quiet_depth += 1
    try:
        yield
    finally:
        with _quiet_lock:
            _quiet_depth -= 1
            if _quiet_depth == 0 and _loud_level is not None:
                cv2.utils.logging.setLogLevel(_loud_level)


def _decode(info: ImageFile) -> np.ndarray:
    """Decode a file with OpenCV (unchanged depth and channels); UnreadableImageError if
    it cannot be read, is damaged (checked first: :func:`calib.image_header.image_damage`,
    CRCs too) or does not decode."""
    try:
        data = np.fromfile(info.path, dtype=np.uint8)
    except OSError as exc:
        raise UnreadableImageError(info.path, f"cannot read image: {exc.strerror}") from None
    if not data.size:
        raise UnreadableImageError(info.path, "not an image: an empty file")
    try:
        header = pnm_header(data) if data[:1].tobytes() == b"P" else image_header(data)
    except ImageHeaderError as exc:  # changed since it was indexed
        raise UnreadableImageError(info.path, str(exc)) from None
    damage = image_damage(data, header)
    if damage is not None:
        raise UnreadableImageError(info.path, damage)
    try:
        with quiet_opencv():
            image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # e.g. a header claiming more pixels than OpenCV decodes
        raise UnreadableImageError(
            info.path, f"OpenCV refuses to decode a {info.width}x{info.height} image ({exc.err})"
        ) from None
    if image is None:
        raise UnreadableImageError(
            info.path, "corrupt or unreadable image (OpenCV cannot decode it)"
        )
    if image.shape[:2] != (info.height, info.width):
        raise CaptureError(
            f"{info.path}: decoded {image.shape[1]}x{image.shape[0]}, "
            f"but the header says {info.width}x{info.height}"
        )
    return image


def _single_channel(image: np.ndarray, info: ImageFile, what: str) -> np.ndarray:
    """(H, W) of a grey image; a 3/4-channel image is accepted only if its colours are grey."""
    if image.ndim == 2:
        return image
    if image.shape[2] in (3, 4) and _is_grey(image):
        return image[:, :, 0]
    if image.shape[2] == 2:
        return image[:, :, 0]
    raise CaptureError(
        f"{info.path}: expected a single-channel {what} image, got "
        f"{image.shape[2]} channels with colour (a false-colour image holds no "
        "values)"
    )


def _is_grey(image: np.ndarray) -> bool:
    """Whether a (H, W, 3 or 4) image's three colour channels are equal."""
    first = image[:, :, 0]
    return np.array_equal(first, image[:, :, 1]) and np.array_equal(first, image[:, :, 2])


@cache
def known_palettes() -> dict[str, np.ndarray]:
    """The project's own palettes (:mod:`fusion.palettes`) as the known palettes a
    false-colour thermal image is first compared with (then calib's built-in ones:
    :func:`calib.palette_inverse.builtin_palettes`). ``black_hot`` is left out: it is the
    grey ramp reversed, so a grey image reads white-hot (dark = cold)."""
    return {name: palette(name) for name in PALETTE_NAMES if name != "black_hot"}


def _thermal_from_palette(image: np.ndarray, info: ImageFile) -> tuple[np.ndarray, PaletteFit]:
    """An 8-bit false-colour thermal image (BGR or BGRA as decoded) -> its palette
    position, (H, W) float32 0-255, and how it was read; CaptureError naming the file when
    its colours follow no known palette and no single curve."""
    if image.dtype != np.uint8:
        raise CaptureError(
            f"{info.path}: a {image.dtype} colour thermal image: expected a grey one "
            "(16-bit centi-kelvin or counts, or 8-bit) or an 8-bit false-colour one"
        )
    code = cv2.COLOR_BGR2RGB if image.shape[2] == 3 else cv2.COLOR_BGRA2RGB
    try:
        return invert_palette(cv2.cvtColor(image, code), known_palettes())
    except PaletteError as exc:
        raise CaptureError(
            f"{info.path}: a false-colour thermal image that cannot be read back: {exc}"
        ) from None


def decode_color(info: ImageFile) -> np.ndarray:
    """8-bit colour or grey PNG/JPG -> (H, W, 3) uint8 RGB (grey is replicated to RGB)."""
    image = _decode(info)
    if image.dtype != np.uint8:
        raise CaptureError(
            f"{info.path}: expected an 8-bit colour or grey image, got {image.dtype} samples"
        )
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    code = {2: None, 3: cv2.COLOR_BGR2RGB, 4: cv2.COLOR_BGRA2RGB}[image.shape[2]]
    if code is None:  # grey + alpha
        return cv2.cvtColor(np.ascontiguousarray(image[:, :, 0]), cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(image, code)


def decode_thermal(info: ImageFile, encoding: ThermalEncoding = "centikelvin") -> np.ndarray:
    """Thermal image -> (H, W) float32 (:func:`read_thermal` without how a palette was read)."""
    return read_thermal(info, encoding)[0]


def read_thermal(
    info: ImageFile, encoding: ThermalEncoding = "centikelvin"
) -> tuple[np.ndarray, PaletteFit | None]:
    """Thermal image -> (H, W) float32, and how a false-colour image was read (else None).

    16-bit with ``encoding="centikelvin"`` (the format's default): kelvin, counts / 100, with
    0 (no reading) -> NaN. 16-bit with ``encoding="counts"`` and any 8-bit grey image: the
    stored values as float32, *not* kelvin (enough to detect a board, not to read
    temperatures). An 8-bit false-colour image (3 or 4 channels that differ): its palette
    position 0-255 (:func:`calib.palette_inverse.invert_palette`), *not* kelvin either;
    CaptureError naming the file when its colours follow no known palette and no single
    curve.
    """
    image = _decode(info)
    if image.ndim == 3 and image.shape[2] in (3, 4) and not _is_grey(image):
        return _thermal_from_palette(image, info)
    image = _single_channel(image, info, "thermal")
    if image.dtype == np.uint16 and encoding == "centikelvin":
        return kelvin_from_counts(image), None
    return image.astype(np.float32), None


def decode_amplitude(info: ImageFile) -> np.ndarray:
    """TOF amplitude (8- or 16-bit) -> (H, W) float32 of the stored values."""
    return _single_channel(_decode(info), info, "TOF amplitude").astype(np.float32)


def decode_distance(info: ImageFile) -> np.ndarray:
    """16-bit millimetres, 0 = invalid -> (H, W) float32 metres with NaN where invalid."""
    image = _single_channel(_decode(info), info, "TOF distance")
    if image.dtype != np.uint16:
        raise CaptureError(
            f"{info.path}: expected a 16-bit distance image in millimetres, got "
            f"{image.dtype} samples"
        )
    return metres_from_counts(image)


# -- reading --------------------------------------------------------------------------------


@dataclass(frozen=True)
class SensorFiles:
    """The files of one sensor in one view.

    Attributes:
        sensor: sensor id.
        modality: ``color``, ``thermal`` or ``tof``.
        image: the image (colour, thermal, or TOF amplitude).
        distance: TOF only: the radial distance image, if the view has one.
    """

    sensor: str
    modality: Modality
    image: ImageFile
    distance: ImageFile | None = None


@dataclass
class CaptureView:
    """One view: a folder with some sensors' images. Pixels are decoded on request.

    Attributes:
        name: the folder name.
        path: the folder.
        files: sensor id -> its files, in sensor order (rig order, else sorted by name).
        thermal_encoding: how 16-bit thermal images are read (see :func:`read_thermal`).
        palettes: thermal sensor -> how its false-colour image was read back, filled in by
            :meth:`frame` (the values are palette positions, not kelvin).
        unreadable: the image files set aside, in the order found: when indexing (their
            sensor is then not in :attr:`files`, or a TOF sensor there without its distance
            image) and when :meth:`frame` met one.
    """

    name: str
    path: Path
    files: dict[str, SensorFiles]
    thermal_encoding: ThermalEncoding = "centikelvin"
    palettes: dict[str, PaletteFit] = field(default_factory=dict)
    unreadable: list[UnreadableImage] = field(default_factory=list)

    @property
    def sensors(self) -> list[str]:
        """Sensor ids present in this view."""
        return list(self.files)

    def __contains__(self, sensor: object) -> bool:
        return sensor in self.files

    def thermal_is_kelvin(self, sensor: str) -> bool:
        """Whether ``frame(sensor).image`` is in kelvin (16-bit centi-kelvin thermal file)."""
        f = self._files(sensor)
        return (
            f.modality == "thermal"
            and f.image.bit_depth == 16
            and self.thermal_encoding == "centikelvin"
        )

    def _files(self, sensor: str) -> SensorFiles:
        try:
            return self.files[sensor]
        except KeyError:
            raise KeyError(
                f"view {self.name!r} has no image of sensor {sensor!r} (has: {self.sensors})"
            ) from None

    def frame(self, sensor: str, *, distance: bool = True) -> Frame:
        """Decode one sensor's image(s) into a Frame (``stamp_ns`` 0: captures carry no time).

        Colour -> (H, W, 3) uint8 RGB; thermal -> (H, W) float32 (kelvin for 16-bit files,
        see :meth:`thermal_is_kelvin`; palette positions 0-255 for a false-colour image,
        noted in :attr:`palettes`); TOF -> amplitude (H, W) float32 and, if present and
        ``distance`` asks for it, ``distance_m`` (H, W) float32 metres, NaN where invalid.
        Raises UnreadableImageError naming the file if it cannot be decoded (and sets it
        aside in :attr:`unreadable`), CaptureError if it is false-colour with colours that
        cannot be read back.
        """
        f = self._files(sensor)
        info = f.image
        try:
            if f.modality == "color":
                return Frame(sensor, 0, decode_color(info))
            if f.modality == "thermal":
                image, fit = read_thermal(info, self.thermal_encoding)
                if fit is not None:
                    self.palettes[sensor] = fit
                return Frame(sensor, 0, image)
            amplitude = decode_amplitude(info)
            if f.distance is None or not distance:
                return Frame(sensor, 0, amplitude)
            info = f.distance
            return Frame(sensor, 0, amplitude, decode_distance(info))
        except UnreadableImageError as exc:
            self.set_aside(UnreadableImage(sensor, exc.path, exc.why, info is f.distance))
            raise

    def set_aside(self, image: UnreadableImage) -> None:
        """Add ``image`` to :attr:`unreadable` (once)."""
        if image not in self.unreadable:
            self.unreadable.append(image)

    def frames(self, sensors: Iterable[str] | None = None) -> FrameSet:
        """Decode the view's images (all, or the given sensors) into a FrameSet (stamp 0)."""
        names = self.sensors if sensors is None else list(sensors)
        return FrameSet(0, {s: self.frame(s) for s in names})


@dataclass
class Capture:
    """A capture directory: the board, the optional starting rig, and the views.

    Attributes:
        path: the directory.
        board: the checkerboard (``board.yaml``).
        rig: the starting rig (``rig.yaml``), or None if the directory has none.
        views: the views sorted by folder name.
        modalities: every sensor seen (or named by the rig) -> its modality.
    """

    path: Path
    board: Board
    rig: Rig | None
    views: list[CaptureView]
    modalities: dict[str, Modality]

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self) -> Iterator[CaptureView]:
        return iter(self.views)

    @property
    def sensors(self) -> list[str]:
        """Sensors that appear in at least one view (rig order, else sorted by name)."""
        seen = {s for v in self.views for s in v.files}
        return [s for s in self.modalities if s in seen]

    @property
    def unreadable(self) -> list[tuple[CaptureView, UnreadableImage]]:
        """The image files set aside so far (:attr:`CaptureView.unreadable`), by view."""
        return [(v, u) for v in self.views for u in v.unreadable]

    def view(self, name: str) -> CaptureView:
        """The view of that folder name."""
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(f"{self.path}: no view {name!r} (views: {[v.name for v in self.views]})")

    def views_with(self, sensor: str) -> list[CaptureView]:
        """Views that hold an image of ``sensor``."""
        return [v for v in self.views if sensor in v.files]

    def check_sizes(self, rig: Rig) -> None:
        """CaptureError at the first image whose size (read from its header, no pixel
        decoded) is not what ``rig`` says of its sensor: a rig of another head is refused
        before anything is allocated for it."""
        for view in self.views:
            for sensor, files in view.files.items():
                if sensor not in rig:
                    continue
                want = rig[sensor].image_size
                for info in (files.image, files.distance):
                    if info is not None and (info.width, info.height) != want:
                        raise CaptureError(
                            f"{info.path}: the rig says sensor {sensor!r} takes "
                            f"{want[0]}x{want[1]} images (width x height), this one is "
                            f"{info.width}x{info.height}: a rig of another head?"
                        )

    def palette_report(self) -> dict[str, dict[str, Any]]:
        """The false-colour thermal images read so far (:attr:`CaptureView.palettes`), per
        sensor, as the report's ``palette_images``: ``views`` (how many), ``palette`` (its
        name, ``own curve`` when no known palette fitted and the image's own colour curve
        was read; several as ``iron (10 of 12), own curve (2 of 12)``), ``radiometric``
        (always False), ``worst_mean_distance_rgb`` and ``worst_share_on_palette`` (the
        poorest fit of an image to its palette) and ``note`` (one sentence for people).
        Empty when no image was false colour."""
        fits: dict[str, list[PaletteFit]] = {}
        for view in self.views:
            for sensor, fit in view.palettes.items():
                fits.setdefault(sensor, []).append(fit)
        report: dict[str, dict[str, Any]] = {}
        for sensor in (s for s in self.modalities if s in fits):
            per_view = fits[sensor]
            names = Counter(f.palette for f in per_view)
            words = {f.palette: f.what for f in per_view}
            several = len(names) > 1
            report[sensor] = {
                "views": len(per_view),
                "palette": ", ".join(
                    f"{n} ({k} of {len(per_view)})" if several else n for n, k in names.items()
                ),
                "radiometric": False,
                "worst_mean_distance_rgb": max(f.mean_distance_rgb for f in per_view),
                "worst_share_on_palette": min(f.share_on_palette for f in per_view),
                "note": (
                    f"{sensor}: {len(per_view)} false-colour image(s), "
                    + "; ".join(
                        words[n] + (f" in {k}" if several else "") for n, k in names.items()
                    )
                    + ": read back as palette positions 0-255 for geometry; values not radiometric"
                ),
            }
        return report

    def summary(self) -> str:
        """A few lines for people: views, sensors and how many views each one is in."""
        lines = [
            f"{self.path}: {len(self.views)} views, board {self.board.describe()}, "
            f"{'starting rig rig.yaml' if self.rig else 'no rig.yaml'}"
        ]
        for s in self.sensors:
            lines.append(f"  {s} ({self.modalities[s]}): in {len(self.views_with(s))} views")
        if unreadable := self.unreadable:
            lines.append(f"  unreadable images, skipped ({len(unreadable)}):")
            lines += [f"    {v.name}/{u.path.name}: {u.why}" for v, u in unreadable]
        return "\n".join(lines)


def read_yaml_file(path: Path, what: str) -> Any:
    """The parsed YAML of a capture's ``what`` file (e.g. ``"board"``); CaptureError
    naming the path when it is missing, unreadable, not UTF-8 or not YAML."""
    if not path.is_file():
        raise CaptureError(f"{path}: missing {what} file")
    text = read_text(path, f"{what} file", CaptureError)
    try:
        return parse_yaml(text)
    except YamlError as exc:
        raise CaptureError(f"{path}: {what} file is not valid YAML: {exc}") from None


def load_board(capture_dir: str | Path) -> Board:
    """Read ``board.yaml`` of a capture directory; CaptureError names the path and the defect."""
    path = Path(capture_dir) / BOARD_FILE
    if not path.is_file():
        raise CaptureError(
            f"{path}: missing; a capture directory needs board.yaml describing the checkerboard, "
            "e.g. '{pattern: checkerboard, inner_corners: [9, 6], square_size_m: 0.025}'"
        )
    return load_board_file(path)


def load_board_file(path: str | Path) -> Board:
    """Read a board file (``board.yaml`` layout); CaptureError names the path and the defect."""
    path = Path(path)
    data = read_yaml_file(path, "board")
    try:
        return board_from_dict(data)
    except ValueError as exc:
        raise CaptureError(f"{path}: {exc}") from None


def _scan_view(
    path: Path, rig: Rig | None, modalities: dict[str, Modality], thermal_encoding: ThermalEncoding
) -> CaptureView:
    """Index one view folder; check names, modalities and (with a rig) image sizes."""
    images: dict[str, Path] = {}
    distances: dict[str, Path] = {}
    for entry in sorted(path.iterdir()):
        if entry.name.startswith(".") or not entry.is_file():
            continue
        if entry.suffix.lower() not in IMAGE_SUFFIXES:
            continue  # notes, metadata: not images of this format
        stem = entry.stem
        target = images
        if stem.endswith(DISTANCE_SUFFIX):
            stem = stem[: -len(DISTANCE_SUFFIX)]
            target = distances
        if stem in target:
            raise CaptureError(
                f"{path}: two images of sensor {stem!r} "
                f"({target[stem].name} and {entry.name}); keep one"
            )
        target[stem] = entry

    files: dict[str, SensorFiles] = {}
    unreadable: list[UnreadableImage] = []
    for sensor in sorted(images.keys() | distances.keys()):
        if rig is not None:
            if sensor not in rig:
                f = images.get(sensor) or distances[sensor]
                raise CaptureError(
                    f"{f}: sensor {sensor!r} is not in the capture's rig.yaml "
                    f"(sensors: {rig.names})"
                )
            modality = rig[sensor].modality
        else:
            try:
                modality = modality_from_name(sensor)
            except CaptureError as exc:
                raise CaptureError(f"{images.get(sensor) or distances[sensor]}: {exc}") from None
        if sensor not in images:
            raise CaptureError(
                f"{distances[sensor]}: a distance image needs its amplitude image "
                f"{sensor}.png beside it; none found"
            )
        try:
            image = read_image_header(images[sensor])
        except UnreadableImageError as exc:
            unreadable.append(UnreadableImage(sensor, exc.path, exc.why))
            modalities.setdefault(sensor, modality)
            continue
        distance = None
        if sensor in distances:
            try:
                distance = read_image_header(distances[sensor])
            except UnreadableImageError as exc:
                if modality != "tof":
                    raise CaptureError(
                        f"{exc.path}: only TOF sensors have distance images; "
                        f"{sensor!r} is {modality}"
                    ) from None
                unreadable.append(UnreadableImage(sensor, exc.path, exc.why, distance=True))
        if distance is not None and modality != "tof":
            raise CaptureError(
                f"{distance.path}: only TOF sensors have distance images; {sensor!r} is {modality}"
            )
        if distance is not None and distance.format != "png":
            raise CaptureError(
                f"{distance.path}: expected a 16-bit PNG distance image, got a "
                "JPEG (lossy compression corrupts distances)"
            )
        if rig is not None:
            want = rig[sensor].image_size
            for info in (image, distance):
                if info is not None and (info.width, info.height) != want:
                    raise CaptureError(
                        f"{info.path}: expected {want[0]}x{want[1]} (width x height) for sensor "
                        f"{sensor!r} as rig.yaml says, got {info.width}x{info.height}"
                    )
        elif distance is not None and (distance.width, distance.height) != (
            image.width,
            image.height,
        ):
            raise CaptureError(
                f"{distance.path}: expected the amplitude image's size "
                f"{image.width}x{image.height}, got "
                f"{distance.width}x{distance.height}"
            )
        modalities.setdefault(sensor, modality)
        files[sensor] = SensorFiles(sensor, modality, image, distance)
    return CaptureView(path.name, path, files, thermal_encoding, unreadable=unreadable)


def load_view(capture_dir: str | Path, name: str, rig: Rig) -> CaptureView:
    """Index one view folder of a capture whose sensors ``rig`` names, without scanning
    the other views (CaptureError names the path and the defect)."""
    path = Path(capture_dir) / name
    if not path.is_dir():
        raise CaptureError(f"{path}: no such view folder")
    modalities: dict[str, Modality] = {n: s.modality for n, s in rig.sensors.items()}
    return _scan_view(path, rig, modalities, "centikelvin")


def load_capture(
    capture_dir: str | Path,
    *,
    thermal_encoding: ThermalEncoding = "centikelvin",
    verify: bool = False,
) -> Capture:
    """Index a capture directory (board, optional starting rig, views); pixels stay on disk.

    Args:
        capture_dir: the directory.
        thermal_encoding: how 16-bit thermal PNGs are read: ``"centikelvin"`` (the format)
            or ``"counts"`` (raw sensor counts, returned as float32 values, not kelvin).
        verify: also decode every image once (slower) so that corrupt pixel data is found
            now rather than when a view is read: such a file is set aside as those found
            when indexing are (taken out of its view's files).

    Every folder not starting with ``.`` is a view; files at the top level (board.yaml,
    rig.yaml, ground_truth*.yaml, anything else) and hidden folders (e.g. a view being
    written) are not. An image file that cannot be read is set aside, not raised (see the
    module docstring; :attr:`Capture.unreadable` lists them). Raises CaptureError (or
    RigError for a bad rig.yaml) naming the path for anything else.
    """
    capture_dir = Path(capture_dir)
    if not capture_dir.is_dir():
        what = "not a directory" if capture_dir.exists() else "no such directory"
        raise CaptureError(f"{capture_dir}: expected a capture directory, {what}")
    if thermal_encoding not in ("centikelvin", "counts"):
        raise CaptureError(
            f"thermal_encoding: expected 'centikelvin' or 'counts', got {thermal_encoding!r}"
        )
    board = load_board(capture_dir)
    rig_path = capture_dir / RIG_FILE
    rig = load_rig(rig_path) if rig_path.exists() else None

    modalities: dict[str, Modality] = {}
    if rig is not None:
        modalities.update({n: s.modality for n, s in rig.sensors.items()})
    view_dirs = sorted(
        (p for p in capture_dir.iterdir() if p.is_dir() and not p.name.startswith(".")),
        key=lambda p: p.name,
    )
    views = [_scan_view(p, rig, modalities, thermal_encoding) for p in view_dirs]
    if rig is None:
        modalities = dict(sorted(modalities.items()))
    order = {name: i for i, name in enumerate(modalities)}
    for v in views:  # each view's sensors in the capture's order (rig order, else by name)
        v.files = dict(sorted(v.files.items(), key=lambda kv: order[kv[0]]))
    capture = Capture(capture_dir, board, rig, views, modalities)
    if verify:
        for v in views:
            for s in v.sensors:
                try:
                    v.frame(s)
                except UnreadableImageError as exc:
                    files = v.files[s]
                    if files.distance is not None and exc.path == files.distance.path:
                        v.files[s] = SensorFiles(s, files.modality, files.image)
                    else:
                        del v.files[s]
    return capture
