"""Live cameras read through OpenCV's ``cv2.VideoCapture``.

:class:`CameraSource` opens one device per sensor (a V4L2 index or path, a video file, an
image sequence such as ``frame_%03d.png``, a stream URL) and runs one reader thread per
device. Each reader keeps only the newest frame of its sensor (:class:`NewestFrameSlots`):
a consumer that is slower than the cameras gets the newest frames and never a backlog.

* Colour devices deliver BGR (OpenCV's default conversion); frames become RGB uint8.
* Thermal devices are opened with ``CAP_PROP_CONVERT_RGB = 0`` (and FOURCC ``Y16`` on
  V4L2 devices) so that 16-bit radiometric counts arrive unchanged; they become kelvin as
  ``counts * scale + offset`` (default: centi-kelvin, ``scale = 0.01``), with 0 counts
  meaning "no reading" (NaN), as in the capture format. An 8-bit thermal device can be
  read too, but its values are only kelvin if ``scale``/``offset`` make them so.
* TOF cameras are not read through OpenCV: push them with the push ingest
  (:mod:`app.sources.push`).

Time stamps are the host's clock (``time.time_ns()``) when ``grab()`` returned, so the
frames of all devices (and of pushed frames stamped with the same clock) compare.

A device that cannot be opened, or opens but delivers no frame within ``open_timeout_s``,
is an error at construction naming the sensor and the device (``strict=False`` opens the
others and reports it in :meth:`CameraSource.status`). A device that stops delivering
later (end of a file, no frame for ``stall_timeout_s``) ends its reader: the sensor simply
stops appearing (a :class:`~app.sources.base.FrameSetAssembler` reports it missing) while
the others go on, and :meth:`CameraSource.status` says why.

Configuration (``--live CONFIG``, docs/FORMATS.md "Live camera configuration")::

    format: trifuse-cameras/1
    sensors:
      ccd_left:     {device: 0, modality: color, width: 1280, height: 960, fps: 30}
      thermal_left: {device: /dev/video4, modality: thermal, scale: 0.01, offset: 0.0}
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trifuse.app.sources.base import FrameSource
from trifuse.app.sources.frames import Frame
from trifuse.app.sources.slots import NewestFrameSlots
from trifuse.app.storage.text import read_text
from trifuse.calib.numbers import finite_float, is_int
from trifuse.calib.rig import Rig, modality_of_name
from trifuse.calib.units import KELVIN_PER_COUNT
from trifuse.calib.yaml_text import YamlError, parse_yaml

CAMERA_CONFIG_FORMAT = "trifuse-cameras/1"

BACKENDS: dict[str, int] = {
    "any": cv2.CAP_ANY,
    "v4l2": cv2.CAP_V4L2,
    "ffmpeg": cv2.CAP_FFMPEG,
    "gstreamer": cv2.CAP_GSTREAMER,
    "images": cv2.CAP_IMAGES,
}
"""Config ``backend`` names -> OpenCV ``CAP_*`` API preferences."""

_SENSOR_KEYS = {
    "device",
    "modality",
    "backend",
    "width",
    "height",
    "fps",
    "fourcc",
    "scale",
    "offset",
    "max_rate_hz",
    "loop",
}
_TOP_KEYS = {"format", "sensors", "open_timeout_s", "stall_timeout_s"}


class CameraError(ValueError):
    """A camera configuration is wrong or a device cannot be opened or read.

    The message names the sensor, the device and what went wrong.
    """


# -- newest-frame slots ---------------------------------------------------------------------


@dataclass(frozen=True)
class CameraConfig:
    """How to read one sensor through ``cv2.VideoCapture``.

    Attributes:
        sensor: sensor id (as in the rig).
        device: a device index (``0``), a device path (``/dev/video2``), a video file, an
            image sequence pattern (``frames/thermal_%04d.png``) or a stream URL.
        modality: ``color`` or ``thermal``.
        backend: ``any`` (default; ``images`` for a pattern with ``%``), ``v4l2``,
            ``ffmpeg``, ``gstreamer`` or ``images``.
        width, height: requested image size (devices), pixels; None = the device's default.
        fps: requested frame rate (devices), Hz.
        fourcc: requested pixel format, four characters (e.g. ``MJPG``); thermal devices
            on V4L2 default to ``Y16``.
        scale, offset: thermal only: kelvin = counts * scale + offset (default centi-kelvin).
        max_rate_hz: read at most this often (files and image sequences, which OpenCV
            reads as fast as it can decode); None = as fast as the device delivers.
        loop: files and image sequences: start again at the end instead of stopping.
    """

    sensor: str
    device: int | str
    modality: str = "color"
    backend: str = "any"
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    fourcc: str | None = None
    scale: float = KELVIN_PER_COUNT
    offset: float = 0.0
    max_rate_hz: float | None = None
    loop: bool = False

    def __post_init__(self) -> None:
        where = f"sensor {self.sensor!r}"
        if not isinstance(self.sensor, str) or not self.sensor:
            raise CameraError(f"sensor: expected a non-empty name, got {self.sensor!r}")
        if not (is_int(self.device) or isinstance(self.device, str)):
            raise CameraError(
                f"{where}: device: expected an index (0, 1, ...), a path or a URL, "
                f"got {self.device!r}"
            )
        if isinstance(self.device, int) and self.device < 0:
            raise CameraError(f"{where}: device: expected an index >= 0, got {self.device}")
        if self.modality == "tof":
            raise CameraError(
                f"{where}: TOF cameras are not read through OpenCV; push their frames "
                "with the push ingest (docs/FORMATS.md, 'Push ingest protocol')"
            )
        if self.modality not in ("color", "thermal"):
            raise CameraError(
                f"{where}: modality: expected 'color' or 'thermal', got {self.modality!r}"
            )
        if not isinstance(self.backend, str) or self.backend not in BACKENDS:
            raise CameraError(
                f"{where}: backend: expected one of {sorted(BACKENDS)}, got {self.backend!r}"
            )
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is not None and (not is_int(v) or v <= 0):
                raise CameraError(f"{where}: {name}: expected a positive integer, got {v!r}")
        for name in ("fps", "max_rate_hz"):
            v = getattr(self, name)
            if v is not None and not _positive(v):
                raise CameraError(f"{where}: {name}: expected a positive number, got {v!r}")
        if self.fourcc is not None and (not isinstance(self.fourcc, str) or len(self.fourcc) > 4):
            raise CameraError(
                f"{where}: fourcc: expected up to four characters, got {self.fourcc!r}"
            )
        if not _finite(self.scale) or self.scale == 0 or not _finite(self.offset):
            raise CameraError(
                f"{where}: scale/offset: expected finite numbers (scale not 0), "
                f"got {self.scale!r}/{self.offset!r}"
            )
        if not isinstance(self.loop, bool):
            raise CameraError(f"{where}: loop: expected true or false, got {self.loop!r}")

    @property
    def api(self) -> int:
        """The OpenCV API preference to open the device with."""
        if self.backend == "any" and isinstance(self.device, str) and "%" in self.device:
            return cv2.CAP_IMAGES  # FFMPEG reads 16-bit PNG sequences as 8-bit
        return BACKENDS[self.backend]

    @property
    def is_file(self) -> bool:
        """A video file or image sequence (ends; can loop), not a live device or stream."""
        if not isinstance(self.device, str) or "://" in self.device:
            return False
        if "%" in self.device:
            return True
        p = Path(self.device)
        return p.is_file() and not str(p).startswith("/dev/")

    def describe(self) -> str:
        return f"sensor {self.sensor!r} (device {self.device!r})"


def _finite(v: Any) -> bool:
    return finite_float(v) is not None


def _positive(v: Any) -> bool:
    return _finite(v) and v > 0


@dataclass(frozen=True)
class CamerasConfig:
    """A ``trifuse-cameras/1`` file: the devices and the timeouts."""

    sensors: tuple[CameraConfig, ...]
    open_timeout_s: float = 10.0
    stall_timeout_s: float = 2.0
    path: Path | None = field(default=None, compare=False)


def cameras_config_from_dict(
    data: Any, base_dir: str | Path | None = None, where: str = "camera config"
) -> CamerasConfig:
    """Parse a camera configuration (see docs/FORMATS.md, "Live camera configuration").

    Relative file paths (not URLs, not ``/dev/...``) are taken relative to ``base_dir``.
    Raises CameraError naming ``where``, the sensor and the key.
    """
    if not isinstance(data, Mapping):
        raise CameraError(f"{where}: expected a mapping, got {type(data).__name__}")
    unknown = sorted(set(data) - _TOP_KEYS, key=str)
    if unknown:
        raise CameraError(f"{where}: unknown keys {unknown} (allowed: {sorted(_TOP_KEYS)})")
    if data.get("format") != CAMERA_CONFIG_FORMAT:
        raise CameraError(
            f"{where}: format: expected {CAMERA_CONFIG_FORMAT!r}, got {data.get('format')!r}"
        )
    sensors = data.get("sensors")
    if not isinstance(sensors, Mapping) or not sensors:
        raise CameraError(f"{where}: sensors: expected a non-empty mapping of sensor -> device")
    timeouts = {}
    for key in ("open_timeout_s", "stall_timeout_s"):
        if key in data:
            if not _positive(data[key]):
                raise CameraError(f"{where}: {key}: expected a positive number, got {data[key]!r}")
            timeouts[key] = float(data[key])
    configs = []
    for name, entry in sensors.items():
        if not isinstance(entry, Mapping):
            raise CameraError(
                f"{where}: sensors.{name}: expected a mapping with at least 'device', got {entry!r}"
            )
        bad = sorted(set(entry) - _SENSOR_KEYS, key=str)
        if bad:
            raise CameraError(
                f"{where}: sensors.{name}: unknown keys {bad} (allowed: {sorted(_SENSOR_KEYS)})"
            )
        if "device" not in entry:
            raise CameraError(f"{where}: sensors.{name}: missing 'device'")
        kwargs = dict(entry)
        device = kwargs["device"]
        if (
            isinstance(device, str)
            and base_dir is not None
            and "://" not in device
            and not Path(device).is_absolute()
        ):
            kwargs["device"] = str(Path(base_dir) / device)
        if "modality" not in kwargs:
            modality = modality_of_name(str(name))
            if modality is None:
                raise CameraError(
                    f"{where}: sensors.{name}: missing 'modality' (color or thermal) and the "
                    "name does not tell it"
                )
            kwargs["modality"] = modality
        for key in ("fps", "max_rate_hz", "scale", "offset"):
            if _finite(kwargs.get(key)):
                kwargs[key] = float(kwargs[key])
        try:
            configs.append(CameraConfig(sensor=str(name), **kwargs))
        except CameraError as exc:
            raise CameraError(f"{where}: {exc}") from None
    return CamerasConfig(tuple(configs), **timeouts)


def load_cameras_config(path: str | Path) -> CamerasConfig:
    """Read a ``trifuse-cameras/1`` YAML file; CameraError messages start with its path."""
    path = Path(path)
    text = read_text(path, "camera config", CameraError)
    try:
        data = parse_yaml(text)
    except YamlError as exc:
        raise CameraError(f"{path}: not valid YAML: {exc}") from None
    cfg = cameras_config_from_dict(data, base_dir=path.parent, where=str(path))
    return CamerasConfig(cfg.sensors, cfg.open_timeout_s, cfg.stall_timeout_s, path)


# -- pixel conversion -----------------------------------------------------------------------


def color_to_rgb(image: np.ndarray, what: str = "image") -> np.ndarray:
    """An OpenCV frame (BGR, BGRA or grey, 8- or 16-bit) -> (H, W, 3) uint8 RGB."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise CameraError(f"{what}: expected 8-bit colour samples, got {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.ndim == 3 and image.shape[2] == 1:
        return cv2.cvtColor(image[..., 0], cv2.COLOR_GRAY2RGB)
    raise CameraError(f"{what}: expected a BGR, BGRA or grey image, got shape {image.shape}")


def counts_to_kelvin(
    image: np.ndarray,
    scale: float,
    offset: float,
    size: tuple[int, int] | None = None,
    what: str = "image",
) -> np.ndarray:
    """Raw thermal counts -> (H, W) float32 kelvin: ``counts * scale + offset``, NaN at 0.

    Accepts (H, W) uint16 or uint8, 3 identical channels, or the raw Y16 buffer some
    backends return with ``CONVERT_RGB = 0`` (uint8 of ``2 * W * H`` bytes, reshaped with
    ``size`` = (width, height)).
    """
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.dtype == np.uint8 and size is not None and image.size == 2 * size[0] * size[1]:
        if image.ndim != 2 or image.shape != (size[1], size[0]):
            image = np.ascontiguousarray(image).view("<u2").reshape(size[1], size[0])
    if image.ndim == 3:
        if image.shape[2] >= 3 and all(
            np.array_equal(image[..., 0], image[..., c]) for c in range(1, 3)
        ):
            image = image[..., 0]
        else:
            raise CameraError(
                f"{what}: expected single-channel thermal counts, got a colour image of shape "
                f"{image.shape} (a false-colour stream holds no temperatures: configure the "
                "device for Y16/raw output)"
            )
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise CameraError(
            f"{what}: expected (H, W) 8- or 16-bit thermal counts, got shape {image.shape} "
            f"{image.dtype}"
        )
    kelvin = (image.astype(np.float64) * scale + offset).astype(np.float32)
    kelvin[image == 0] = np.nan
    return kelvin


# -- the reader threads ---------------------------------------------------------------------


@dataclass
class DeviceStatus:
    """What became of one device.

    Attributes:
        sensor, device: which one.
        state: ``opening``, ``running``, ``stopped`` (ended: see ``reason``) or ``failed``
            (never opened: see ``reason``).
        reason: why it stopped or failed ('' while fine).
        frames: frames read so far.
        size: (width, height) of the frames, once known.
    """

    sensor: str
    device: int | str
    state: str = "opening"
    reason: str = ""
    frames: int = 0
    size: tuple[int, int] | None = None


class _Reader:
    def __init__(
        self,
        cfg: CameraConfig,
        slots: NewestFrameSlots,
        stop: threading.Event,
        stall_timeout_s: float,
    ) -> None:
        self.cfg = cfg
        self.slots = slots
        self.stop = stop
        self.stall_timeout_s = stall_timeout_s
        self.status = DeviceStatus(cfg.sensor, cfg.device)
        self.opened = threading.Event()  # set when open succeeded or failed
        self.thread = threading.Thread(target=self._run, name=f"camera-{cfg.sensor}", daemon=True)
        self._size_hint: tuple[int, int] | None = None

    def _open(self) -> cv2.VideoCapture:
        cfg = self.cfg
        cap = cv2.VideoCapture(cfg.device, cfg.api)
        if not cap.isOpened():
            cap.release()
            raise CameraError(
                f"{cfg.describe()}: OpenCV cannot open it "
                f"(backend {cfg.backend}; a missing device, a wrong path, or no permission?)"
            )
        if cfg.modality == "thermal":
            cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)  # keep 16-bit counts (False where unsupported)
            fourcc = cfg.fourcc
            if fourcc is None and not cfg.is_file and cfg.api in (cv2.CAP_ANY, cv2.CAP_V4L2):
                fourcc = "Y16"
            if fourcc:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc.ljust(4)))
        elif cfg.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*cfg.fourcc.ljust(4)))
        if cfg.width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, cfg.width)
        if cfg.height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height)
        if cfg.fps is not None:
            cap.set(cv2.CAP_PROP_FPS, cfg.fps)
        w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self._size_hint = (w, h) if w > 0 and h > 0 else None
        return cap

    def _convert(self, image: np.ndarray) -> np.ndarray:
        what = self.cfg.describe()
        if self.cfg.modality == "color":
            return color_to_rgb(image, what)
        return counts_to_kelvin(image, self.cfg.scale, self.cfg.offset, self._size_hint, what)

    def _read(self, cap: cv2.VideoCapture) -> tuple[np.ndarray, int] | None:
        if not cap.grab():
            return None
        stamp = time.time_ns()
        ok, image = cap.retrieve()
        if not ok or image is None or image.size == 0:
            return None
        return image, stamp

    def _deliver(self, image: np.ndarray, stamp: int) -> None:
        converted = self._convert(image)
        self.status.frames += 1
        self.status.size = (converted.shape[1], converted.shape[0])
        self.slots.put(Frame(self.cfg.sensor, stamp, converted))

    def _run(self) -> None:
        cfg = self.cfg
        cap = None
        try:
            try:
                cap = self._open()
                first = self._read(cap)
                if first is None:
                    raise CameraError(f"{cfg.describe()}: opened, but delivered no frame")
                self._deliver(*first)
            except Exception as exc:
                self.status.state = "failed"
                self.status.reason = str(exc)
                return
            finally:
                self.opened.set()
            self.status.state = "running"
            period = None if cfg.max_rate_hz is None else 1.0 / cfg.max_rate_hz
            next_read = time.monotonic() + (period or 0.0)
            last_good = time.monotonic()
            while not self.stop.is_set():
                if period is not None:
                    wait = next_read - time.monotonic()
                    if wait > 0 and self.stop.wait(wait):
                        break
                    next_read = max(next_read + period, time.monotonic())
                got = self._read(cap)
                if got is None:
                    if cfg.is_file and cfg.loop:
                        cap.release()  # reopening rewinds every backend (seeking does not)
                        cap = self._open()
                        got = self._read(cap)
                        if got is None:
                            raise CameraError(f"{cfg.describe()}: cannot read it again to loop")
                    elif cfg.is_file:
                        self.status.reason = f"{cfg.describe()}: end of file"
                        break
                    elif time.monotonic() - last_good > self.stall_timeout_s:
                        self.status.reason = (
                            f"{cfg.describe()}: no frame for {self.stall_timeout_s:g} s; "
                            "stopped reading it"
                        )
                        break
                    else:
                        self.stop.wait(0.005)
                        continue
                self._deliver(*got)
                last_good = time.monotonic()
        except Exception as exc:
            self.status.reason = f"{cfg.describe()}: {exc}"
        finally:
            if self.status.state != "failed":
                self.status.state = "stopped"
                if not self.status.reason:
                    self.status.reason = "closed"
            if cap is not None:
                cap.release()
            self.slots.finish(cfg.sensor)


class CameraSource(FrameSource):
    """Cameras read through OpenCV, one reader thread per device (see the module docstring).

    Args:
        config: a :class:`CamerasConfig`, a path to a ``trifuse-cameras/1`` file, or a
            sequence of :class:`CameraConfig`.
        rig: the rig the cameras belong to (optional; its sensor names and modalities must
            match the configuration).
        strict: a device that cannot be opened raises CameraError (naming every such
            device); with False the others run and :meth:`status` reports it.
        open_timeout_s, stall_timeout_s: override the configuration's timeouts.

    Attributes:
        sensors: the configured sensors (including any that failed to open).
        rig: the rig, if given.
    """

    def __init__(
        self,
        config: CamerasConfig | str | Path | Sequence[CameraConfig],
        *,
        rig: Rig | None = None,
        strict: bool = True,
        open_timeout_s: float | None = None,
        stall_timeout_s: float | None = None,
    ) -> None:
        if isinstance(config, str | Path):
            config = load_cameras_config(config)
        elif not isinstance(config, CamerasConfig):
            config = CamerasConfig(tuple(config))
        if not config.sensors:
            raise CameraError("camera config: no sensors")
        names = [c.sensor for c in config.sensors]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise CameraError(f"camera config: sensors configured twice: {dupes}")
        if rig is not None:
            for c in config.sensors:
                if c.sensor not in rig:
                    raise CameraError(
                        f"{c.describe()}: not a sensor of the rig (sensors: {rig.names})"
                    )
                if rig[c.sensor].modality != c.modality:
                    raise CameraError(
                        f"{c.describe()}: configured as {c.modality}, but the rig says "
                        f"{rig[c.sensor].modality}"
                    )
        self.rig = rig
        self.sensors = names
        self.config = config
        open_timeout = open_timeout_s if open_timeout_s is not None else config.open_timeout_s
        stall = stall_timeout_s if stall_timeout_s is not None else config.stall_timeout_s
        self._stop = threading.Event()
        self._slots = NewestFrameSlots(names, end_when_finished=True)
        self._readers = {
            c.sensor: _Reader(c, self._slots, self._stop, stall) for c in config.sensors
        }
        for r in self._readers.values():
            r.thread.start()
        deadline = time.monotonic() + open_timeout
        for r in self._readers.values():
            if not r.opened.wait(max(0.0, deadline - time.monotonic())):
                r.status.state = "failed"
                r.status.reason = (
                    f"{r.cfg.describe()}: did not open and deliver a frame within "
                    f"{open_timeout:g} s"
                )
                self._slots.finish(r.cfg.sensor)
        failed = [r.status.reason for r in self._readers.values() if r.status.state == "failed"]
        if failed and strict:
            self.close()
            raise CameraError("; ".join(failed))

    def frames(self) -> Iterator[Frame]:
        """The newest frame of each sensor as it comes (oldest stamp first among the
        newest); ends when every device has stopped or on :meth:`close`."""
        return self._slots.frames()

    def take(self, timeout_s: float | None = None) -> Frame | None:
        """One frame (see :meth:`NewestFrameSlots.take`), or None on timeout / end."""
        return self._slots.take(timeout_s)

    def status(self) -> dict[str, DeviceStatus]:
        """Per sensor: state, reason, frames read, size (see :class:`DeviceStatus`); a
        snapshot."""
        return {s: dataclasses.replace(r.status) for s, r in self._readers.items()}

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per sensor: frames received, delivered, dropped (see :meth:`NewestFrameSlots.stats`)."""
        return self._slots.stats()

    def close(self) -> None:
        """Stop the readers and release the devices (idempotent)."""
        self._stop.set()
        self._slots.close()
        for r in self._readers.values():
            if r.thread.is_alive() and r.thread is not threading.current_thread():
                r.thread.join(timeout=5.0)
