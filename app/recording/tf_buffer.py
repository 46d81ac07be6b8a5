"""A small tf2 buffer (issue 36): the transforms a robot publishes on ``/tf`` and
``/tf_static``, and the pose of one frame in another at a time (the head's ``T_world_rig``
for the thermal map).

Each message says ``T_parent_child`` (the child's pose in the parent, tf2's convention).
A static edge keeps its newest transform; a dynamic one its last :data:`KEEP` transforms,
and a lookup takes each dynamic edge's transform nearest the time asked within
``tolerance_ns`` (no interpolation: the TOF's 15 Hz against a robot's 30-100 Hz odometry).
Frames are joined through any chain of edges, either way round.

Pure: transforms in, poses out; one lock (the reading thread adds, the console looks up).
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

KEEP = 200
"""Transforms kept per dynamic edge (a few seconds of a robot's odometry)."""


class TfBuffer:
    """See the module doc."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._static: dict[tuple[str, str], np.ndarray] = {}
        self._dynamic: dict[tuple[str, str], deque[tuple[int, np.ndarray]]] = {}

    def add(self, parent: str, child: str, stamp_ns: int, T: np.ndarray, static: bool) -> None:
        """``T_parent_child`` (4, 4) at ``stamp_ns``."""
        T = np.asarray(T, dtype=np.float64)
        with self._lock:
            if static:
                self._static[(parent, child)] = T
            else:
                self._dynamic.setdefault((parent, child), deque(maxlen=KEEP)).append(
                    (int(stamp_ns), T)
                )

    def _edge(self, key: tuple[str, str], stamp_ns: int, tolerance_ns: int) -> np.ndarray | None:
        if key in self._static:
            return self._static[key]
        history = self._dynamic.get(key)
        if not history:
            return None
        t, T = min(history, key=lambda item: abs(item[0] - stamp_ns))
        return T if abs(t - stamp_ns) <= tolerance_ns else None

    def lookup(
        self, target: str, source: str, stamp_ns: int, tolerance_ns: int = 100_000_000
    ) -> np.ndarray | None:
        """``T_target_source`` (4, 4) at ``stamp_ns`` through the edges known, or None when
        the frames are not joined or an edge has no transform within ``tolerance_ns``."""
        with self._lock:
            edges = [*self._static, *self._dynamic]
            neighbours: dict[str, list[tuple[str, tuple[str, str], bool]]] = {}
            for parent, child in edges:  # (next frame, edge, walked from parent to child)
                neighbours.setdefault(parent, []).append((child, (parent, child), True))
                neighbours.setdefault(child, []).append((parent, (parent, child), False))
            # breadth first from target: T_target_frame for each frame reached
            poses = {target: np.eye(4)}
            queue = deque([target])
            while queue and source not in poses:
                frame = queue.popleft()
                for nxt, key, forward in neighbours.get(frame, []):
                    if nxt in poses:
                        continue
                    T = self._edge(key, stamp_ns, tolerance_ns)
                    if T is None:
                        continue
                    step = T if forward else np.linalg.inv(T)  # T_frame_next
                    poses[nxt] = poses[frame] @ step
                    queue.append(nxt)
            return poses.get(source)
