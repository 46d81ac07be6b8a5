"""The last published pictures by ``seq``, for benchmarks that compare what a viewer shows
with what the console fused (``trifuse bench --only link``).

Off unless the console runs with ``TRIFUSE_BENCH_KEEP_FRAMES=N`` (N pictures, 1-1000): the
hub then keeps the BGR picture of its last N frames (:class:`KeptFrames`; each 2560 x 960
picture takes 7.4 MB, so N = 100 holds 740 MB) and ``GET /api/stream/frame/{seq}.png``
returns frame ``seq``'s picture as PNG (404 when it is gone or keeping is off).
"""

from __future__ import annotations

import collections
import os
import threading

import numpy as np

ENV = "TRIFUSE_BENCH_KEEP_FRAMES"
MAX_KEPT = 1000


class KeptFrames:
    """The BGR pictures of the last ``size`` frames published with one (any thread).

    Pictures are the hub's own (read-only, never written again): nothing is copied; a
    repeated picture is one array under several ``seq``.
    """

    def __init__(self, size: int) -> None:
        if not 1 <= size <= MAX_KEPT:
            raise ValueError(f"{ENV}: expected 1-{MAX_KEPT} pictures, got {size}")
        self._lock = threading.Lock()
        self._frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self.size = size

    @classmethod
    def from_env(cls) -> KeptFrames | None:
        """As :data:`ENV` asks, None when it is unset or empty; ValueError when it is not
        a number of pictures."""
        value = os.environ.get(ENV, "").strip()
        if not value:
            return None
        try:
            size = int(value)
        except ValueError:
            raise ValueError(f"{ENV}: expected a number of pictures, got {value!r}") from None
        return cls(size)

    def add(self, seq: int, bgr: np.ndarray | None) -> None:
        """Keep frame ``seq``'s picture ``bgr`` (nothing when None), forgetting the oldest
        beyond ``size``."""
        if bgr is None:
            return
        with self._lock:
            self._frames[seq] = bgr
            while len(self._frames) > self.size:
                self._frames.popitem(last=False)

    def get(self, seq: int) -> np.ndarray | None:
        """Frame ``seq``'s (H, W, 3) uint8 BGR picture, or None when it is not kept."""
        with self._lock:
            return self._frames.get(seq)
