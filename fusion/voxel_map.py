"""A thermal 3D map: TOF points accumulated in a world frame as an evidence grid of voxels
that remember temperature and colour (the method's outlook: "local maps with texture
mapping using exactly the same techniques").

Each TOF frame (:meth:`VoxelMap.integrate`) brings points in the TOF frame, the head pose
``T_world_tof`` and, per point, the temperature and colour the fusion sampled for it
(:mod:`fusion.point_attributes`). Per voxel the map keeps:

* occupancy evidence in log-odds: a hit adds ``hit_logodds`` once per frame that has a point
  in the voxel; a miss adds ``miss_logodds`` when a TOF ray passed through the voxel and
  ended beyond it (free space). Misses are found by projection: a voxel in front of the
  depth the TOF measured along its pixel's ray lies on that ray's free stretch, the same
  test a ray traversal makes, at the cost of the voxels checked rather than of the steps
  along 25 k rays. ``free_budget`` voxels are checked per frame, in turn, so the cost is
  bounded whatever the map's size;
* temperature: a recency-weighted mean (each frame's reading weighs ``max(1/n,
  recency)``, so the first readings average and later ones follow change), the maximum, the
  last reading and when it was seen;
* colour: the same recency-weighted mean of RGB;
* the number of points that fell in it.

Memory is bounded by a maximum extent around the world origin (points beyond are dropped
and counted) and a maximum number of voxels (new voxels beyond it are dropped and counted).
Voxels are hashed (:class:`fusion.voxel_hash.VoxelHash`), so only observed space costs.

Frames: ``T_world_tof`` (4, 4) maps TOF-frame points (metres) to the world frame.
Temperatures in kelvin (NaN: not seen by a thermal imager); colours RGB in [0, 255].
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from trifuse.calib.camera import Intrinsics
from trifuse.calib.numbers import finite_float, is_integral
from trifuse.fusion.geometry import Projector32
from trifuse.fusion.voxel_hash import VoxelHash

MAX_VOXELS = 50_000_000
"""The largest ``max_voxels``: about 5.4 GB of memory when full (60 bytes of arrays and at
most 48 of hash table a voxel)."""
MAX_EXTENT_M = 100_000.0
"""The largest ``max_extent_m``, metres (100 km)."""
MAX_ABS_LOGODDS = 100.0
"""The largest magnitude of any log-odds setting (a probability within 1e-43 of 0 or 1)."""


def _check_number(name: str, value: object, lo: float, hi: float, sign: int = 0) -> None:
    """ValueError naming the setting and its bounds unless ``value`` is a finite number
    from ``lo`` to ``hi``; ``sign`` 1: above 0 (not 0) up to ``hi``; -1: below 0 (not 0)
    down to ``lo``."""
    v = finite_float(value)
    if v is not None and lo <= v <= hi and (sign == 0 or v * sign > 0):
        return
    bounds = {
        1: f"a positive number at most {hi:g}",
        -1: f"a negative number at least {lo:g}",
        0: f"a number from {lo:g} to {hi:g}",
    }[sign]
    raise ValueError(f"{name}: expected {bounds}, got {value!r:.40}")


def _check_count(name: str, value: object, lo: int, hi: int) -> None:
    """ValueError naming the setting and its bounds unless ``value`` is an integer in
    ``[lo, hi]``."""
    if not is_integral(value) or not lo <= value <= hi:
        raise ValueError(f"{name}: expected an integer from {lo} to {hi}, got {value!r:.40}")


@dataclass(frozen=True)
class MapSettings:
    """How the map is built.

    Attributes:
        voxel_m: voxel edge, metres.
        max_extent_m: the map covers ``|x|, |y|, |z| <= max_extent_m`` around the world
            origin, metres.
        max_voxels: at most this many voxels are kept; new ones beyond it are dropped.
        recency: the least weight a new temperature or colour reading has in a voxel's
            mean (1: the last reading only; small: a long memory).
        hit_logodds, miss_logodds: evidence added by a frame's hit and by a miss.
        min_logodds, max_logodds: the evidence is clamped to this range (so that a voxel
            can change its mind: a person who walks away is carved out again).
        free_budget: voxels checked for free space per frame.
        free_margin_m: a voxel counts as passed through when it lies at least this far,
            plus ``free_margin_rel`` of the measured range, in front of the measured depth
            (metres; None: two voxel edges).
        free_margin_rel: see ``free_margin_m``.
        occupied_logodds: a voxel is occupied above this evidence (1.0: two frames' hits
            more than misses; one stray hit, e.g. a flying pixel, is not enough).
    """

    voxel_m: float = 0.03
    max_extent_m: float = 40.0
    max_voxels: int = 4_000_000
    recency: float = 0.1
    hit_logodds: float = 0.85
    miss_logodds: float = -0.4
    min_logodds: float = -2.0
    max_logodds: float = 3.5
    free_budget: int = 20_000
    free_margin_m: float | None = None
    free_margin_rel: float = 0.02
    occupied_logodds: float = 1.0

    def __post_init__(self) -> None:
        _check_number("max_extent_m", self.max_extent_m, 0.0, MAX_EXTENT_M, sign=1)
        _check_number("voxel_m", self.voxel_m, 0.0, self.max_extent_m, sign=1)
        _check_count("max_voxels", self.max_voxels, 1, MAX_VOXELS)
        _check_number("recency", self.recency, 0.0, 1.0, sign=1)
        bound = MAX_ABS_LOGODDS
        _check_number("hit_logodds", self.hit_logodds, 0.0, bound, sign=1)
        _check_number("miss_logodds", self.miss_logodds, -bound, 0.0, sign=-1)
        _check_number("min_logodds", self.min_logodds, -bound, 0.0, sign=-1)
        _check_number("max_logodds", self.max_logodds, 0.0, bound, sign=1)
        _check_number("occupied_logodds", self.occupied_logodds, -bound, bound)
        _check_count("free_budget", self.free_budget, 0, MAX_VOXELS)
        if self.free_margin_m is not None:
            _check_number("free_margin_m", self.free_margin_m, 0.0, self.max_extent_m)
        _check_number("free_margin_rel", self.free_margin_rel, 0.0, 1.0)
        if self.max_extent_m / self.voxel_m >= 1 << 19:
            raise ValueError(
                f"max_extent_m / voxel_m: at most {1 << 19} voxels each way, got "
                f"{self.max_extent_m} / {self.voxel_m}"
            )

    @property
    def margin_m(self) -> float:
        return 2.0 * self.voxel_m if self.free_margin_m is None else self.free_margin_m


@dataclass(frozen=True)
class DepthImage:
    """A TOF frame's measured radial distances and its camera model, for free space.

    Attributes:
        distance_m: (H, W) radial distance along each pixel's ray, metres, NaN invalid.
        intrinsics: the TOF's intrinsics (pixel rays, distortion).
    """

    distance_m: np.ndarray
    intrinsics: Intrinsics


@dataclass
class IntegrateStats:
    """What one :meth:`VoxelMap.integrate` did (counts)."""

    points: int = 0
    voxels: int = 0
    new_voxels: int = 0
    outside_extent: int = 0
    dropped_full: int = 0
    free_checked: int = 0
    carved: int = 0


_FIELDS = {
    # name: (dtype, columns, initial value)
    "centre": (np.float32, 3, 0.0),
    "hits": (np.uint32, 0, 0),
    "logodds": (np.float32, 0, 0.0),
    "temp_mean": (np.float32, 0, np.nan),
    "temp_max": (np.float32, 0, np.nan),
    "temp_last": (np.float32, 0, np.nan),
    "temp_n": (np.uint32, 0, 0),
    "last_seen": (np.float64, 0, np.nan),
    "rgb": (np.float32, 3, np.nan),
    "rgb_n": (np.uint32, 0, 0),
}
"""The per-voxel arrays, row n for the voxel of hash index n."""


@dataclass
class VoxelMap:
    """The map (see the module docstring).

    Attributes:
        settings: how it is built.
        path: the head's path: (stamp seconds, T_world_tof (4, 4)) per integrated frame.
        stats: totals since the map was made or reset.
    """

    settings: MapSettings = field(default_factory=MapSettings)
    path: list[tuple[float, np.ndarray]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget everything (the settings stay)."""
        s = self.settings
        self._half = int(np.ceil(s.max_extent_m / s.voxel_m))
        self._side = 2 * self._half + 1
        self._hash = VoxelHash()
        self._arrays: dict[str, np.ndarray] = {}
        self._resize(1 << 14)
        self._cursor = 0
        self.path = []
        self.stats = IntegrateStats()
        self.revision = 0
        """Counts integrations and resets: a display redraws when it changes."""

    # -- storage ------------------------------------------------------------------------

    def _resize(self, rows: int) -> None:
        n = self._hash.size
        for name, (dtype, cols, init) in _FIELDS.items():
            shape = (rows, cols) if cols else (rows,)
            a = np.full(shape, init, dtype=dtype)
            if name in self._arrays:
                a[:n] = self._arrays[name][:n]
            self._arrays[name] = a

    def __len__(self) -> int:
        """The number of voxels (occupied or not)."""
        return self._hash.size

    def __getitem__(self, name: str) -> np.ndarray:
        """The per-voxel array ``name`` (a view of the first ``len(map)`` rows):
        ``centre`` (N, 3) world metres, ``hits``, ``logodds``, ``temp_mean``,
        ``temp_max``, ``temp_last`` (kelvin), ``temp_n``, ``last_seen`` (seconds),
        ``rgb`` (N, 3) float 0-255, ``rgb_n``."""
        return self._arrays[name][: len(self)]

    @property
    def nbytes(self) -> int:
        """Memory held by the map's arrays and hash table, bytes."""
        return self._hash.nbytes + sum(a.nbytes for a in self._arrays.values())

    def occupied(self) -> np.ndarray:
        """(N,) bool: voxels whose evidence says occupied (log-odds above
        ``occupied_logodds``)."""
        return self["logodds"] > self.settings.occupied_logodds

    def keys_of(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The voxel keys (M,) int64 of the points (N, 3) inside the extent, and which
        points (N,) bool those are."""
        q = np.floor(np.asarray(points_world, dtype=np.float64) / self.settings.voxel_m)
        inside = (np.abs(q) <= self._half).all(axis=1)
        ijk = q[inside].astype(np.int64) + self._half
        return (ijk[:, 0] * self._side + ijk[:, 1]) * self._side + ijk[:, 2], inside

    def _centres(self, keys: np.ndarray) -> np.ndarray:
        s = self._side
        ijk = np.stack([keys // (s * s), (keys // s) % s, keys % s], axis=1) - self._half
        return ((ijk + 0.5) * self.settings.voxel_m).astype(np.float32)

    # -- integration --------------------------------------------------------------------

    def integrate(
        self,
        T_world_tof: np.ndarray,
        points_tof: np.ndarray,
        stamp_s: float,
        temperature_k: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
        depth: DepthImage | None = None,
    ) -> IntegrateStats:
        """Add one TOF frame.

        Args:
            T_world_tof: (4, 4) the TOF's pose in the world frame.
            points_tof: (N, 3) or (H, W, 3) points in the TOF frame, metres; NaN rows are
                skipped.
            stamp_s: the frame's time, seconds.
            temperature_k: (N,) or (H, W) kelvin per point, NaN where no thermal imager
                saw it; None: no temperatures.
            rgb: (N, 3) or (H, W, 3) colour per point (0-255), NaN where no colour camera
                saw it; None: no colours.
            depth: the frame's distances for free space; None: hits only.

        Returns:
            What this frame did (also added to :attr:`stats`).
        """
        T = np.asarray(T_world_tof, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"T_world_tof: expected a finite (4, 4) transform, got {T.shape}")
        p = np.asarray(points_tof, dtype=np.float64).reshape(-1, 3)
        n_all = len(p)
        temps = None if temperature_k is None else np.asarray(temperature_k).reshape(-1)
        cols = None if rgb is None else np.asarray(rgb).reshape(-1, 3)
        for name, a in (("temperature_k", temps), ("rgb", cols)):
            if a is not None and len(a) != n_all:
                raise ValueError(f"{name}: expected {n_all} values (one per point), got {len(a)}")
        valid = np.isfinite(p[:, 0]) & np.isfinite(p[:, 1]) & np.isfinite(p[:, 2])
        pw = cv2.transform(p[valid].reshape(-1, 1, 3), T[:3, :]).reshape(-1, 3)
        keys, inside = self.keys_of(pw)
        st = IntegrateStats(points=int(valid.sum()), outside_extent=int((~inside).sum()))
        rows = np.flatnonzero(valid)[inside]  # rows of points_tof that reach the map
        if len(keys):
            self._add_hits(keys, rows, temps, cols, stamp_s, st)
        if depth is not None and self.settings.free_budget > 0 and len(self):
            self._carve(T, depth, st)
        self.path.append((float(stamp_s), T.copy()))
        self.revision += 1
        for name, value in asdict(st).items():
            setattr(self.stats, name, getattr(self.stats, name) + value)
        return st

    def _rows_of(self, keys: np.ndarray, st: IntegrateStats) -> np.ndarray:
        """(N,) rows here of the distinct voxel ``keys`` (N,), adding the new ones in their
        order while ``max_voxels`` leaves room (-1: dropped; ``st.new_voxels`` and
        ``st.dropped_full`` count them)."""
        index = self._hash.lookup(keys)
        new = np.flatnonzero(index < 0)
        room = self.settings.max_voxels - len(self)
        if len(new) > room:
            st.dropped_full = int(len(new) - room)
            new = new[:room]
        if len(new):
            if len(self) + len(new) > len(self._arrays["hits"]):
                self._resize(max(2 * len(self._arrays["hits"]), len(self) + len(new)))
            index[new] = self._hash.insert(keys[new])
            self._arrays["centre"][index[new]] = self._centres(keys[new])
        st.new_voxels = len(new)
        return index

    def _add_hits(
        self,
        keys: np.ndarray,
        rows: np.ndarray,
        temps: np.ndarray | None,
        cols: np.ndarray | None,
        stamp_s: float,
        st: IntegrateStats,
    ) -> None:
        s = self.settings
        uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        index = self._rows_of(uniq, st)
        kept = index >= 0
        st.voxels = int(kept.sum())
        v = index[kept]
        a = self._arrays
        a["hits"][v] += counts[kept].astype(np.uint32)
        a["logodds"][v] = np.minimum(a["logodds"][v] + s.hit_logodds, s.max_logodds)
        a["last_seen"][v] = stamp_s
        n = len(uniq)
        if temps is not None:
            t = temps[rows]
            ok = np.isfinite(t)
            g, t = inverse[ok], t[ok].astype(np.float64)
            count = np.bincount(g, minlength=n)
            sel = (count > 0) & kept
            mean = np.bincount(g, weights=t, minlength=n)[sel] / count[sel]
            top = np.full(n, -np.inf)
            np.maximum.at(top, g, t)
            vi = index[sel]
            self._blend("temp_mean", "temp_n", vi, mean)
            a["temp_max"][vi] = np.fmax(a["temp_max"][vi], top[sel])
            a["temp_last"][vi] = mean
        if cols is not None:
            c = cols[rows]
            ok = np.isfinite(c[:, 0])
            g, c = inverse[ok], c[ok].astype(np.float64)
            count = np.bincount(g, minlength=n)
            sel = (count > 0) & kept
            mean = (
                np.stack(
                    [np.bincount(g, weights=c[:, ch], minlength=n)[sel] for ch in range(3)], axis=1
                )
                / count[sel, None]
            )
            self._blend("rgb", "rgb_n", index[sel], mean)

    def _blend(self, name: str, count_name: str, rows: np.ndarray, reading: np.ndarray) -> None:
        """The recency-weighted mean: each reading weighs ``max(1 / n, recency)``."""
        a = self._arrays
        a[count_name][rows] += 1
        w = np.maximum(1.0 / a[count_name][rows], self.settings.recency).astype(np.float32)
        if reading.ndim == 2:
            w = w[:, None]
        old = np.nan_to_num(a[name][rows])
        a[name][rows] = old + w * (reading - old)

    def _carve(self, T_world_tof: np.ndarray, depth: DepthImage, st: IntegrateStats) -> None:
        """Misses for up to ``free_budget`` voxels (in turn) lying in front of the
        measured depth along their pixel's ray."""
        s = self.settings
        n = len(self)
        budget = min(s.free_budget, n)
        if self._cursor >= n:
            self._cursor = 0
        sel = (np.arange(budget) + self._cursor) % n
        self._cursor = (self._cursor + budget) % n
        project = Projector32(depth.intrinsics, np.linalg.inv(T_world_tof))
        uv, rows, _ = project(self._arrays["centre"][sel])
        st.free_checked = len(rows)
        h, w = depth.distance_m.shape
        u = np.rint(uv[:, 0])
        v = np.rint(uv[:, 1])
        ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        sel = sel[rows[ok]]
        # The nearest depth of the pixel and its neighbours: a voxel of a slanted surface
        # seen through the neighbouring pixel is not free space.
        near = _nearest_depth(depth.distance_m)
        d = near[v[ok].astype(np.intp), u[ok].astype(np.intp)]
        c = self._arrays["centre"][sel] - T_world_tof[:3, 3].astype(np.float32)
        r = np.sqrt((c * c).sum(axis=1))
        with np.errstate(invalid="ignore"):
            free = r < d - (s.margin_m + s.free_margin_rel * d)
        carved = sel[free]
        lo = self._arrays["logodds"]
        lo[carved] = np.maximum(lo[carved] + s.miss_logodds, s.min_logodds)
        st.carved = len(carved)

    # -- merging ------------------------------------------------------------------------

    def merge(self, other: VoxelMap) -> IntegrateStats:
        """Add another map built from frames that came after this map's (in place).

        A long recording is mapped in consecutive pieces (perhaps on different machines)
        and the pieces merged in their order: ``merged = piece0; merged.merge(piece1);
        merged.merge(piece2); ...``. The result is deterministic (the same maps give the
        same arrays, row order included) and reads as if ``other``'s frames had been
        integrated after this map's:

        * voxels: ``other``'s voxels this map lacks are appended in ``other``'s row order;
          those beyond ``max_voxels`` (the last ones in that order) are dropped and
          counted (``dropped_full``);
        * ``hits``, ``temp_n``, ``rgb_n``: summed; ``logodds``: summed, clamped to
          ``[min_logodds, max_logodds]``;
        * ``temp_mean``, ``rgb``: the recency-weighted means combined as if ``other``'s
          readings were blended after this map's: ``lam * a + (1 - lam) * b`` with ``lam =
          prod_{k=1..n_b} (1 - max(1 / (n_a + k), recency))`` (see
          :func:`_prior_weight`), ``a``, ``n_a`` this map's mean and count, ``b``, ``n_b``
          the other's (NaN where neither saw the voxel);
        * ``temp_max``: the larger; ``temp_last``: ``other``'s where it has a reading,
          else this map's; ``last_seen`` (seconds): ``other``'s where it saw the voxel,
          else this map's;
        * :attr:`path`: this map's then ``other``'s (copies of its (4, 4) poses);
          :attr:`stats`: the field-wise sum of both, but ``new_voxels`` counts the voxels
          this merge appended (not those ``other`` made that this map had) and
          ``dropped_full`` adds this merge's;
          :attr:`revision` goes up by one; the free-space cursor stays.

        Merging differs slightly from integrating every frame into one map:

        * free space seen in ``other``'s frames does not carve voxels only this map has
          (and the free-space budget took voxels in turn in each piece separately);
        * ``logodds`` is clamped once, after the sum, not after each frame;
        * a mean is exactly the sequential one while ``n_a + n_b <= 1 / recency`` (the
          weighting is then a plain running mean); beyond that ``b`` weighed ``other``'s
          own first readings ``1 / k`` where a sequential build gives ``max(1 / (n_a +
          k), recency)``, so ``other``'s early readings count a little more;
        * float32 rounding: the means agree to a few float32 units in the last place.

        Args:
            other: a map with the same settings; it is not changed (``other`` is not
                ``self``).

        Returns:
            ``voxels`` (``len(other)``), ``new_voxels`` (appended) and ``dropped_full``
            (``other``'s voxels left out: the map was full); the other counts are 0.

        Raises:
            ValueError: the settings differ, or ``other`` is this map.
        """
        if other is self:
            raise ValueError("merge: a map cannot be merged into itself")
        if self.settings != other.settings:
            a, b = asdict(self.settings), asdict(other.settings)
            diff = ", ".join(f"{k} {a[k]!r} != {b[k]!r}" for k in a if a[k] != b[k])
            raise ValueError(f"merge: the maps' settings differ ({diff})")
        s = self.settings
        keys = other.keys_of(other["centre"].astype(np.float64))[0]
        st = IntegrateStats(voxels=len(other))
        index = self._rows_of(keys, st)  # other's voxels new here are added in its order
        src = np.flatnonzero(index >= 0)  # rows of other that reach this map
        v = index[src]  # their rows here (distinct: other's keys are)
        a = self._arrays
        o = {name: other[name][src] for name in _FIELDS if name != "centre"}
        a["hits"][v] += o["hits"]
        a["logodds"][v] = np.clip(a["logodds"][v] + o["logodds"], s.min_logodds, s.max_logodds)
        for mean, count in (("temp_mean", "temp_n"), ("rgb", "rgb_n")):
            n_a, n_b = a[count][v], o[count]
            a[mean][v] = _merge_means(a[mean][v], n_a, o[mean], n_b, s.recency)
            a[count][v] = n_a + n_b
        a["temp_max"][v] = np.fmax(a["temp_max"][v], o["temp_max"])
        a["temp_last"][v] = np.where(o["temp_n"] > 0, o["temp_last"], a["temp_last"][v])
        a["last_seen"][v] = np.where(np.isfinite(o["last_seen"]), o["last_seen"], a["last_seen"][v])
        self.path = self.path + [(t, T.copy()) for t, T in other.path]
        for name, value in asdict(other.stats).items():
            setattr(self.stats, name, getattr(self.stats, name) + value)
        self.stats.new_voxels += st.new_voxels - other.stats.new_voxels
        self.stats.dropped_full += st.dropped_full
        self.revision += 1
        return st

    # -- reading ------------------------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """Copies of every per-voxel array (see :meth:`__getitem__`) plus ``keys`` (N,)
        int64 and the path (``path_stamp_s`` (P,), ``path_T_world_tof`` (P, 4, 4))."""
        out = {name: self[name].copy() for name in _FIELDS}
        out["keys"] = self.keys_of(self["centre"].astype(np.float64))[0]
        out["path_stamp_s"] = np.array([t for t, _ in self.path], dtype=np.float64)
        out["path_T_world_tof"] = np.array([T for _, T in self.path], dtype=np.float64).reshape(
            -1, 4, 4
        )
        return out

    @classmethod
    def from_arrays(cls, settings: MapSettings, arrays: dict[str, np.ndarray]) -> VoxelMap:
        """A map from :meth:`arrays` (e.g. read back from a file)."""
        m = cls(settings)
        keys = np.asarray(arrays["keys"], dtype=np.int64)
        n = len(keys)
        if n > settings.max_voxels:
            raise ValueError(f"map: {n} voxels, more than max_voxels {settings.max_voxels}")
        if len(np.unique(keys)) != n:
            raise ValueError("map: voxel keys repeat")
        if n and (keys.min() < 0 or keys.max() >= m._side**3):
            raise ValueError("map: voxel keys outside the extent of these settings")
        m._resize(max(n, 1 << 14))
        m._hash.insert(keys)
        for name, (dtype, cols, _) in _FIELDS.items():
            a = np.asarray(arrays[name])
            want = (n, cols) if cols else (n,)
            if a.shape != want:
                raise ValueError(f"map: {name} has shape {a.shape}, expected {want}")
            m._arrays[name][:n] = a.astype(dtype)
        stamps = np.asarray(arrays.get("path_stamp_s", np.zeros(0)), dtype=np.float64)
        poses = np.asarray(arrays.get("path_T_world_tof", np.zeros((0, 4, 4))), dtype=np.float64)
        m.path = [(float(t), T) for t, T in zip(stamps, poses.reshape(-1, 4, 4), strict=True)]
        m.revision = 1
        return m


def _prior_weight(n_a: np.ndarray, n_b: np.ndarray, recency: float) -> np.ndarray:
    """The weight (float64, broadcast shape) left to a recency-weighted mean of ``n_a``
    readings after ``n_b`` more are blended in (see :meth:`VoxelMap._blend`):
    ``prod_{k=1..n_b} (1 - max(1 / (n_a + k), recency))``, in closed form.

    The first ``k1`` steps, those with ``n_a + k <= 1 / recency``, weigh ``1 / (n_a + k)``
    and their factors ``(n_a + k - 1) / (n_a + k)`` telescope to ``n_a / (n_a + k1)``; the
    remaining ``n_b - k1`` weigh ``recency``: ``(1 - recency) ** (n_b - k1)``. (Where ``1 /
    (n_a + k)`` equals ``recency`` up to rounding, both forms give the same factor.) 1 where
    ``n_b`` is 0; 0 where ``n_a`` is 0 and ``n_b`` is not.
    """
    n_a = np.asarray(n_a, dtype=np.float64)
    n_b = np.asarray(n_b, dtype=np.float64)
    k1 = np.clip(np.floor(1.0 / recency) - n_a, 0.0, n_b)
    head = np.divide(n_a, n_a + k1, out=np.ones(np.broadcast(n_a, k1).shape), where=k1 > 0)
    return head * (1.0 - recency) ** (n_b - k1)


def _merge_means(
    a: np.ndarray, n_a: np.ndarray, b: np.ndarray, n_b: np.ndarray, recency: float
) -> np.ndarray:
    """Recency-weighted means ``a`` (N,) or (N, C) float32 of ``n_a`` (N,) readings and
    ``b`` of ``n_b`` later ones, combined (float32): ``lam * a + (1 - lam) * b`` with
    ``lam`` from :func:`_prior_weight`; ``a`` where ``n_b`` is 0, ``b`` where ``n_a`` is 0
    (NaN where both are)."""
    lam = _prior_weight(n_a, n_b, recency)
    if a.ndim == 2:
        lam = lam[:, None]
    with np.errstate(invalid="ignore"):
        out = (lam * a + (1.0 - lam) * b).astype(np.float32)
    only_a, only_b = n_b == 0, (n_a == 0) & (n_b > 0)
    out[only_a] = a[only_a]
    out[only_b] = b[only_b]
    return out


def _nearest_depth(distance_m: np.ndarray) -> np.ndarray:
    """(H, W) the smallest valid distance in each pixel's 3 x 3 neighbourhood (NaN: none)."""
    d = np.where(np.isfinite(distance_m), distance_m, np.inf).astype(np.float32)
    near = cv2.erode(d, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    near[~np.isfinite(near)] = np.nan
    return near
