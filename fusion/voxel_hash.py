"""A growable open-addressing hash table from int64 voxel keys to dense int32 indices,
vectorised with numpy (no per-key Python loop).

Keys are inserted once and never removed; the n-th new key gets index n, so the values of
a voxel live at row n of dense arrays beside the table (:mod:`fusion.voxel_map`). Linear
probing; the table doubles when more than a quarter full (12 bytes a slot: 48 bytes a
voxel at most). Lookups and inserts take a batch of keys and loop over probe steps, not
keys: a few steps at that load.
"""

from __future__ import annotations

import numpy as np

EMPTY = np.int64(-1)
"""The key of an empty slot (voxel keys are non-negative)."""
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
MAX_LOAD_INV = 4
"""The table grows when more than 1 / MAX_LOAD_INV of its slots are taken."""


class VoxelHash:
    """int64 keys (>= 0) -> indices 0, 1, 2, ... in order of insertion.

    Args:
        capacity: initial number of slots (rounded up to a power of two, at least 1024).
    """

    def __init__(self, capacity: int = 1 << 16) -> None:
        bits = max(10, int(np.ceil(np.log2(max(capacity, 2)))))
        self._alloc(bits)
        self.size = 0

    def _alloc(self, bits: int) -> None:
        self._bits = bits
        self._keys = np.full(1 << bits, EMPTY, dtype=np.int64)
        self._values = np.zeros(1 << bits, dtype=np.int32)

    @property
    def capacity(self) -> int:
        return len(self._keys)

    @property
    def nbytes(self) -> int:
        return self._keys.nbytes + self._values.nbytes

    def _slots(self, keys: np.ndarray) -> np.ndarray:
        h = keys.astype(np.uint64) * _GOLDEN  # wraps: multiplicative (Fibonacci) hashing
        return (h >> np.uint64(64 - self._bits)).astype(np.int64)

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Indices (N,) int32 of ``keys`` (N,) int64; -1 where absent."""
        keys = np.asarray(keys, dtype=np.int64)
        out = np.full(len(keys), -1, dtype=np.int32)
        slot = self._slots(keys)
        todo = np.arange(len(keys))
        mask = self.capacity - 1
        while len(todo):
            s = slot[todo]
            k = self._keys[s]
            found = k == keys[todo]
            out[todo[found]] = self._values[s[found]]
            go_on = ~found & (k != EMPTY)
            todo = todo[go_on]
            slot[todo] = (s[go_on] + 1) & mask
        return out

    def insert(self, keys: np.ndarray) -> np.ndarray:
        """Insert ``keys`` (N,) int64, distinct and absent; returns their new indices
        (N,) int32: ``size, size + 1, ...`` in the order given."""
        keys = np.asarray(keys, dtype=np.int64)
        if (self.size + len(keys)) * MAX_LOAD_INV > self.capacity:
            self._grow(self.size + len(keys))
        values = np.arange(self.size, self.size + len(keys), dtype=np.int32)
        self._place(keys, values)
        self.size += len(keys)
        return values

    def _place(self, keys: np.ndarray, values: np.ndarray) -> None:
        slot = self._slots(keys)
        todo = np.arange(len(keys))
        mask = self.capacity - 1
        while len(todo):
            s = slot[todo]
            free = self._keys[s] == EMPTY
            # Of several keys wanting one free slot, the first takes it; the others see it
            # taken on the next step and move on.
            _, first = np.unique(s[free], return_index=True)
            won = todo[free][first]
            self._keys[slot[won]] = keys[won]
            self._values[slot[won]] = values[won]
            taken = np.ones(len(todo), dtype=bool)
            taken[np.flatnonzero(free)[first]] = False
            occupied = ~free
            slot[todo[occupied]] = (s[occupied] + 1) & mask
            todo = todo[taken]

    def _grow(self, needed: int) -> None:
        old_keys, old_values = self._keys, self._values
        bits = self._bits
        while (1 << bits) < MAX_LOAD_INV * needed:
            bits += 1
        self._alloc(bits)
        used = old_keys != EMPTY
        self._place(old_keys[used], old_values[used])
