"""The simulated head's pose cache: which scenario times share one rendering, and the
rendered poses kept on disk across runs.

Poses: the scenario time is sampled at ``render_hz`` over ``loop_s``
(:func:`sample_poses`); samples that give the same head pose (or the same ``scene_key``)
share one rendering. A scenario with a sensor drift (``drift``:
:class:`~app.sources.sim.drift.SensorDrift`) has each sample in two states, before the
drift and after it, which never share a rendering.

Disk cache: rendered poses are also kept on disk, one ``.npz`` file per pose (about 8.4
MB uncompressed for the default head), so a restarted console has every pose at once
(loading one takes a few ms). The directory is :func:`default_cache_dir`
(``$XDG_CACHE_HOME/trifuse/sim``, ``~/.cache/trifuse/sim``, or ``$TRIFUSE_SIM_CACHE``;
``TRIFUSE_SIM_CACHE=off`` keeps none), one folder per scenario (:func:`cache_folder`),
named by a hash of the scenario (the default one by its seed and quality, another by its
``cache_key()``; scenarios without one are not cached on disk), the delivered sensors, the
simulator's source code and the numpy and OpenCV versions; each file is named by its
pose's scenario time (:func:`pose_file`). Files are written to a temporary name and
renamed, so concurrent consoles share the folder safely; a file that cannot be read or
holds the wrong shapes is deleted and the pose rendered again. Only the
:data:`CACHE_KEEP` most recently used folders are kept.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from trifuse.app.sources.frames import Frame
from trifuse.app.storage.user_cache import user_cache_dir
from trifuse.calib.rig import Rig

CACHE_ENV = "TRIFUSE_SIM_CACHE"
"""Environment variable: the disk cache's directory, or ``off`` to keep no disk cache."""
CACHE_KEEP = 4
"""Scenario directories kept in the disk cache; older ones (least recently used) go."""
_CACHE_FORMAT = 1
# What the pictures depend on besides the scenario's parameters: the simulator's code.
_SIM_CODE = (
    "app/sources/sim/*.py",
    "app/sources/frames.py",
    "calib/board.py",
    "calib/camera.py",
    "calib/rig.py",
    "calib/transforms.py",
)


@dataclass(frozen=True)
class PoseSamples:
    """The cache's samples of scenario time and the distinct poses they show.

    Attributes:
        sample_t: scenario time of each sample, seconds (``i / render_hz``).
        sample_pose: the pose each sample shows (an index into ``pose_t``); with a drift,
            before it.
        pose_t: the representative scenario time of each pose (its first sample), seconds.
        pose_T: (4, 4) the head pose of each pose (world frame of the scenario), or None
            where the scenario has no ``T_world_rig``.
        pose_drifted: whether each pose is rendered with the scenario's sensor drift
            (``render(t, sensors, drifted=...)``); all False without one.
        drifted_sample_pose: the pose each sample shows once the drift is active; None for
            a scenario without a drift.
    """

    sample_t: list[float]
    sample_pose: list[int]
    pose_t: list[float]
    pose_T: list[np.ndarray | None]
    pose_drifted: list[bool]
    drifted_sample_pose: list[int] | None = None

    def pose_of(self, sample: int, drifted: bool) -> int:
        """The pose sample ``sample`` shows with the drift active (``drifted``) or not."""
        if drifted and self.drifted_sample_pose is not None:
            return self.drifted_sample_pose[sample]
        return self.sample_pose[sample]


def sample_poses(scenario: Any, samples: int, render_hz: float) -> PoseSamples:
    """``samples`` samples of scenario time, ``1 / render_hz`` seconds apart; samples with
    equal ``scene_key(t)`` (if the scenario has one) or equal head pose
    ``T_world_rig(t)`` (to 1e-9) share a pose; without either every sample is its own.

    A scenario with a sensor drift (a ``drift`` not None: from ``drift.at_s`` of the
    stream's scenario time on, which keeps counting while the samples loop) has a second
    pose per sample, the drifted one; a sample gets a pose before the drift only if a
    time before ``at_s`` can show it (every sample if ``at_s`` is beyond the loop), else
    its ``sample_pose`` is the drifted one too. Poses of the two states never share.
    """
    sample_t = [i / render_hz for i in range(samples)]
    pose_t: list[float] = []
    pose_T: list[np.ndarray | None] = []
    pose_drifted: list[bool] = []
    pose_fn = getattr(scenario, "T_world_rig", None)
    key_fn = getattr(scenario, "scene_key", None)
    drift = getattr(scenario, "drift", None)
    seen: dict[Any, int] = {}

    def pose(t: float, drifted: bool) -> int:
        T = None if pose_fn is None else np.asarray(pose_fn(t), dtype=np.float64)
        if key_fn is not None:
            key = key_fn(t)
        else:
            key = None if T is None else tuple(np.round(T, 9).ravel().tolist())
        if key is not None and drift is not None:
            key = (drifted, key)
        match = seen.get(key) if key is not None else None
        if match is None:
            match = len(pose_t)
            pose_t.append(t)
            pose_T.append(T)
            pose_drifted.append(drifted)
            if key is not None:
                seen[key] = match
        return match

    if drift is None:
        sample_pose = [pose(t, False) for t in sample_t]
        return PoseSamples(sample_t, sample_pose, pose_t, pose_T, pose_drifted)
    loop_s = samples / render_hz
    # A stream time s < at_s shows sample round(s * render_hz): up to half a sample past it.
    before = [
        drift.at_s > 0 and (drift.at_s >= loop_s or t <= drift.at_s + 0.5 / render_hz)
        for t in sample_t
    ]
    undrifted = [pose(t, False) if b else -1 for t, b in zip(sample_t, before, strict=True)]
    drifted = [pose(t, True) for t in sample_t]
    sample_pose = [u if u >= 0 else d for u, d in zip(undrifted, drifted, strict=True)]
    return PoseSamples(sample_t, sample_pose, pose_t, pose_T, pose_drifted, drifted)


# -- the disk cache -------------------------------------------------------------------------


def default_cache_dir() -> Path | None:
    """Where rendered poses are kept across runs: ``$TRIFUSE_SIM_CACHE`` if set (None if
    it is ``off``), else ``$XDG_CACHE_HOME/trifuse/sim`` or ``~/.cache/trifuse/sim``."""
    return user_cache_dir(CACHE_ENV, "sim")


@lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of the simulator's source files and the numeric libraries' versions."""
    root = Path(__file__).resolve().parents[3]
    h = hashlib.sha256(f"{np.__version__} {cv2.__version__} {_CACHE_FORMAT}".encode())
    for pattern in _SIM_CODE:
        for path in sorted(root.glob(pattern)):
            h.update(path.relative_to(root).as_posix().encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def scenario_key(scenario: Any, default_seed: int | None) -> str | None:
    """What identifies a scenario's pictures: the default scenario by its seed, quality and
    sensor drift, another by its ``cache_key()``; None if it has none (no disk cache then)."""
    if default_seed is not None:
        live = getattr(scenario, "live", False)
        drift = getattr(scenario, "drift", None)
        if drift is None:
            return f"InspectionScenario(seed={default_seed}, live={live})"
        return f"InspectionScenario(seed={default_seed}, live={live}, drift={drift!r})"
    key_fn = getattr(scenario, "cache_key", None)
    if key_fn is None:
        return None
    return f"{type(scenario).__module__}.{type(scenario).__qualname__}:{key_fn()!r}"


def prune_cache(base: Path, keep: Path) -> None:
    """Remove all but the :data:`CACHE_KEEP` most recently used scenario directories (never
    ``keep``) and temporary files older than an hour in ``keep``; best effort."""
    try:
        dirs = [d for d in base.iterdir() if d.is_dir() and d != keep]
        dirs.sort(key=lambda d: d.stat().st_mtime, reverse=True)
        for d in dirs[CACHE_KEEP - 1 :]:
            shutil.rmtree(d, ignore_errors=True)
        for tmp in keep.glob(".*.tmp"):
            if time.time() - tmp.stat().st_mtime > 3600:
                tmp.unlink(missing_ok=True)
    except OSError:
        pass


def save_pose(path: Path, frames: Mapping[str, Frame]) -> None:
    """Write a pose's images to ``path`` (.npz, uncompressed) atomically: a temporary file
    in the same directory, then a rename, so a reader never sees a partial file and
    concurrent writers of the same pose simply replace each other's equal files."""
    arrays: dict[str, np.ndarray] = {}
    for name, f in frames.items():
        arrays[f"{name}.image"] = f.image
        if f.distance_m is not None:
            arrays[f"{name}.distance"] = f.distance_m
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _check_image(rig: Rig, sensor: str, a: np.ndarray, distance: bool = False) -> bool:
    w, h = rig[sensor].image_size
    if rig[sensor].modality == "color" and not distance:
        return a.dtype == np.uint8 and a.shape == (h, w, 3)
    return a.dtype == np.float32 and a.shape == (h, w)


def load_pose(path: Path, rig: Rig, sensors: Sequence[str]) -> dict[str, Frame] | None:
    """The frames of a cached pose, or None if the file is missing, unreadable or not what
    ``rig``'s ``sensors`` deliver (a damaged file is removed, to be rendered again)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            frames = {}
            for s in sensors:
                image = z[f"{s}.image"]
                has_distance = f"{s}.distance" in z.files
                distance = z[f"{s}.distance"] if has_distance else None
                ok = _check_image(rig, s, image)
                if rig[s].modality == "tof":
                    ok = ok and distance is not None and _check_image(rig, s, distance, True)
                if not ok:
                    raise ValueError(f"{path}: {s}: unexpected image shape or type")
                frames[s] = Frame(s, 0, image, distance)
            return frames
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass
        return None


def cache_folder(
    cache_dir: str | os.PathLike[str] | bool | None,
    scenario_id: str | None,
    sensors: Sequence[str],
    keep_truth: bool,
) -> Path | None:
    """The scenario's folder in the disk cache, made and marked as used now (older
    folders pruned); None for no disk cache, or if the folder cannot be made.

    Args:
        cache_dir: the cache's directory; None: :func:`default_cache_dir` for a scenario
            that can be cached (``scenario_id`` not None) without ``keep_truth``; True:
            :func:`default_cache_dir`; False: no disk cache.
        scenario_id: :func:`scenario_key` of the scenario.
        sensors: the delivered sensors, in order.
        keep_truth: whether the source keeps per-pixel truth (not cached on disk).
    """
    base: Path | None = None
    if cache_dir is None:
        if scenario_id is not None and not keep_truth:
            base = default_cache_dir()
    elif cache_dir is not False:
        if scenario_id is None:
            raise ValueError(
                "cache_dir: only the default scenario or one with cache_key() can be cached on disk"
            )
        base = default_cache_dir() if cache_dir is True else Path(cache_dir)
    if base is None:
        return None
    key = json.dumps([scenario_id, list(sensors), code_fingerprint()])
    folder = base / hashlib.sha256(key.encode()).hexdigest()[:24]
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)
        prune_cache(base, folder)
    except OSError:
        return None
    return folder


def pose_file(folder: Path, t_s: float, drifted: bool = False) -> Path:
    """The file of the pose at scenario time ``t_s`` (seconds) in a scenario's folder;
    ``drifted``: the pose rendered with the scenario's sensor drift."""
    return folder / f"pose-{round(t_s * 1e6)}us{'-drifted' if drifted else ''}.npz"
