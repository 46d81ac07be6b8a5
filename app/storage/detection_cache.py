"""Board detections kept by image content, so an image is searched for the board once.

A calibration session's views are searched when they are taken, again whenever a console
starts on the session, by ``trifuse calibrate`` on the capture (and once more on every run
with other options), by ``trifuse calibrate-range``: the same images, the same board, the
same corners, at 0.1-4 s of CPU an image (a failed search of a 382 x 288 thermal image
tries 24 variants of the detectors). :class:`DetectionCache` keeps each search's result
under a hash of everything it depends on and gives it back for the same input:

- the image's pixels, shape and dtype (as decoded: a copy of a capture, or the same pose
  rendered again, is the same image),
- the board (``board.yaml``'s content, polarity keys included) and the modality,
- the detector's code: every source file of ``calib/`` and the numpy and OpenCV versions
  (:func:`code_fingerprint`), so a change of the detector never returns an old result.

Two layers: the most recent :data:`MEMORY_ENTRIES` results in memory (for the live board
watch, whose frames a simulated head repeats), and on disk (for images of a capture:
:func:`detect_cached`), one small JSON file per result in ``$TRIFUSE_DETECTION_CACHE``,
else ``$XDG_CACHE_HOME/trifuse/detections`` or ``~/.cache/trifuse/detections``;
``TRIFUSE_DETECTION_CACHE=off`` keeps none. Live frames (:func:`detect_remembered`) are
kept in memory only: a camera never shows the same picture twice, and a console watching
for hours would fill the disk with results no one asks for again.

The disk layer is best effort and shared: files are written under a temporary name and
renamed (concurrent processes replace each other's equal files), a file that cannot be
read is a miss (searched again, written again), a directory that cannot be written leaves
the cache in memory only (one log line). Only :data:`KEEP_FINGERPRINTS` code versions are
kept, each at most :data:`MAX_FILES` results (the least recently used go).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import threading
import uuid
from collections import OrderedDict
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

import trifuse.calib
from trifuse.app.storage.user_cache import user_cache_dir
from trifuse.calib.board import Board
from trifuse.calib.detect import Detection
from trifuse.calib.polarity import detect_board_configured

CACHE_ENV = "TRIFUSE_DETECTION_CACHE"
"""Environment variable: the disk cache's directory, or ``off`` to keep none."""
MEMORY_ENTRIES = 512
"""Results kept in memory per process (each a few kB)."""
MAX_FILES = 50_000
"""Results kept on disk per code version (about 2 kB each); beyond it the least recently
used go."""
KEEP_FINGERPRINTS = 2
"""Code versions kept on disk (a developer switching between two branches keeps both)."""
PRUNE_EVERY = 500
"""Files written by a process between two checks of :data:`MAX_FILES`."""
_FORMAT = 1

log = logging.getLogger(__name__)


def default_cache_dir() -> Path | None:
    """``$TRIFUSE_DETECTION_CACHE`` if set (None if it is ``off``), else
    ``$XDG_CACHE_HOME/trifuse/detections`` or ``~/.cache/trifuse/detections``."""
    return user_cache_dir(CACHE_ENV, "detections")


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of the source files of ``calib/`` (the detectors and what they use) and the
    numpy and OpenCV versions."""
    calib = Path(trifuse.calib.__file__).resolve().parent
    h = hashlib.sha256(f"{np.__version__} {cv2.__version__} {_FORMAT}".encode())
    for path in sorted(calib.rglob("*.py")):
        h.update(path.relative_to(calib).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def detection_key(image: np.ndarray, board: Board, modality: str) -> str:
    """The hash (hex) of a search's inputs: the image's pixels, shape and dtype, the board
    file's content, the modality and :func:`code_fingerprint`."""
    a = np.ascontiguousarray(image)
    h = hashlib.blake2b(digest_size=20)
    meta = [code_fingerprint(), modality, a.shape, a.dtype.str, board.to_dict()]
    h.update(json.dumps(meta, sort_keys=True).encode())
    h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def _to_json(det: Detection) -> str:
    corners = None if det.corners is None else det.corners.tolist()
    return json.dumps({"corners": corners, "reason": det.reason, "method": det.method})


def _from_json(text: str) -> Detection:
    """Raises ValueError (or KeyError, TypeError) for what :func:`_to_json` did not write."""
    d = json.loads(text)
    corners = d["corners"]
    if corners is not None:
        corners = np.asarray(corners, dtype=np.float64)
        if corners.ndim != 2 or corners.shape[1] != 2 or not np.all(np.isfinite(corners)):
            raise ValueError("corners: expected (N, 2) finite numbers")
    reason, method = d["reason"], d["method"]
    if not all(v is None or isinstance(v, str) for v in (reason, method)):
        raise TypeError("reason, method: expected text or null")
    if (corners is None) == (reason is None):
        raise ValueError("expected corners or a reason, not both")
    return Detection(corners, reason, method)


def _copied(det: Detection) -> Detection:
    corners = None if det.corners is None else det.corners.copy()
    return Detection(corners, det.reason, det.method)


class DetectionCache:
    """:func:`calib.polarity.detect_board_configured`, with each result kept by the hash of
    its inputs (:func:`detection_key`) in memory and, if ``folder`` is given, on disk.

    Args:
        folder: the disk cache's directory (a folder per code version is made in it);
            None: memory only.
        memory_entries: results kept in memory.

    Thread-safe. A search that raises (a malformed image) is not kept.
    """

    def __init__(self, folder: Path | None, memory_entries: int = MEMORY_ENTRIES) -> None:
        self.folder = None if folder is None else Path(folder) / code_fingerprint()[:24]
        self._base = None if folder is None else Path(folder)
        self._memory: OrderedDict[str, Detection] = OrderedDict()
        self._capacity = memory_entries
        self._lock = threading.Lock()
        self._written = 0
        self._ready = False
        self.lookups = 0
        """Searches asked for (:meth:`detect` calls with an image)."""
        self.hits = 0
        """Of :attr:`lookups`, those answered from memory or disk without a search."""

    def detect(
        self, image: np.ndarray, board: Board, modality: str, keep: bool = True
    ) -> Detection:
        """The board's corners in ``image`` (as :func:`~calib.polarity.detect_board_configured`
        finds them), from the cache when this image was searched before.

        Args:
            keep: also write a new result to disk (False: memory only, for live frames).
        Raises:
            ValueError: what the detector raises for an image it cannot search.
        """
        if not isinstance(image, np.ndarray):  # the detector's own message
            return detect_board_configured(image, board, modality)
        key = detection_key(image, board, modality)
        with self._lock:
            self.lookups += 1
            det = self._memory.get(key)
            if det is not None:
                self.hits += 1
                self._memory.move_to_end(key)
                return _copied(det)
        det = self._read(key)
        hit = det is not None
        if det is None:
            det = detect_board_configured(image, board, modality)
            if keep:
                self._write(key, det)
        with self._lock:
            self.hits += hit
            self._memory[key] = _copied(det)  # the caller may change its corners
            while len(self._memory) > self._capacity:
                self._memory.popitem(last=False)
        return det

    # -- the disk layer ---------------------------------------------------------------

    def _path(self, key: str) -> Path | None:
        return None if self.folder is None else self.folder / f"{key}.json"

    def _read(self, key: str) -> Detection | None:
        path = self._path(key)
        if path is None:
            return None
        try:
            det = _from_json(path.read_text())
            os.utime(path)  # recently used: pruned last
            return det
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError):  # damaged: searched again
            return None

    def _write(self, key: str, det: Detection) -> None:
        path = self._path(key)
        if path is None or not self._prepare():
            return
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")
        try:
            tmp.write_text(_to_json(det))
            os.replace(tmp, path)
        except OSError as exc:
            self._give_up(exc)
            return
        finally:
            tmp.unlink(missing_ok=True)
        with self._lock:
            self._written += 1
            prune = self._written % PRUNE_EVERY == 0
        if prune:
            self.prune()

    def _prepare(self) -> bool:
        """Make this code version's folder (and prune older versions) once; False if the
        disk layer is off or cannot be written."""
        if self._ready or self.folder is None:
            return self.folder is not None
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            os.utime(self.folder)
            old = [d for d in self._base.iterdir() if d.is_dir() and d != self.folder]
            old.sort(key=lambda d: d.stat().st_mtime, reverse=True)
            for d in old[KEEP_FINGERPRINTS - 1 :]:
                shutil.rmtree(d, ignore_errors=True)
        except OSError as exc:
            self._give_up(exc)
            return False
        self._ready = True
        return True

    def _give_up(self, exc: OSError) -> None:
        log.warning(
            "board detections are not kept on disk (%s): %s; each console start and "
            "calibration searches every image again",
            self.folder,
            exc,
        )
        self.folder = None

    def prune(self) -> None:
        """Remove the least recently used results beyond :data:`MAX_FILES` (and temporary
        files left by interrupted writes); best effort."""
        if self.folder is None:
            return
        try:
            files = [(p.stat().st_mtime, p) for p in self.folder.iterdir()]
        except OSError:
            return
        files.sort()
        stale = [p for _t, p in files if p.name.endswith(".tmp")]
        results = [p for _t, p in files if p.suffix == ".json"]
        for p in stale + results[: max(0, len(results) - MAX_FILES)]:
            p.unlink(missing_ok=True)


_caches: dict[Path | None, DetectionCache] = {}
_caches_lock = threading.Lock()


def shared_cache() -> DetectionCache:
    """This process's cache in :func:`default_cache_dir` (read when called: a change of the
    environment gives another cache)."""
    folder = default_cache_dir()
    with _caches_lock:
        cache = _caches.get(folder)
        if cache is None:
            cache = _caches[folder] = DetectionCache(folder)
        return cache


def detect_cached(image: np.ndarray, board: Board, modality: str) -> Detection:
    """:func:`~calib.polarity.detect_board_configured` for an image of a capture: kept in
    memory and on disk (:func:`shared_cache`)."""
    return shared_cache().detect(image, board, modality)


def detect_remembered(image: np.ndarray, board: Board, modality: str) -> Detection:
    """:func:`~calib.polarity.detect_board_configured` for a live frame: results kept in
    memory only (found on disk if a capture's search put them there)."""
    return shared_cache().detect(image, board, modality, keep=False)
