"""The calibration target: a checkerboard, a ChArUco board or an asymmetric circle grid, and
its detectable points in the board frame.

Board frame: origin at the first detectable point, +x along a row of points (``cols``), +y
down the columns (``rows``), +z into the board (away from a camera that sees its front),
metres.

Checkerboard: points are the inner corners, row-major: index ``r * cols + c`` is at
``(c * square, r * square, 0)``. The square diagonally up-left of corner (0, 0) is black
(on the heated board: high emissivity, so hot in thermal; dark in TOF amplitude). With
an odd number of squares on one side and an even number on the other, the colours fix
the ordering under a half turn. Other boards look the same turned (:attr:`Board.orderings`):
even x even or odd x odd inner corners under a half turn, a square board under a quarter
turn too; each view's ordering is then decided across sensors from the data
(:func:`calib.board_ordering.order_views`).

ChArUco (``pattern="charuco"``): a checkerboard of ``(cols + 1) x (rows + 1)`` squares with
ArUco markers in its white squares (OpenCV's ``cv2.aruco.CharucoBoard``); points are its
inner corners, indexed as OpenCV's corner ids (row-major, the same as the checkerboard's)
and placed as the checkerboard's (OpenCV's board frame shifted by one square so that the
first inner corner is the origin). The markers fix the ordering (``orderings`` 1) and a
view may see a subset of the corners (:attr:`Board.partial_views`): its detection has NaN
rows for the corners not seen. ``inverted``: white markers on black squares (the whole
print inverted).

Asymmetric circle grid (``pattern="asymmetric_circles"``): ``rows`` rows of ``cols``
circles, odd rows shifted by half a period, as OpenCV's ``CALIB_CB_ASYMMETRIC_GRID``:
point ``r * cols + c`` is at ``((2 c + r % 2) s, r s, 0)`` with ``s = square_size_m``
(``spacing_m`` in ``board.yaml``). The circles are the pattern's marks (:meth:`Board.is_black`:
dark in colour; hot in thermal when heated, cold when cooled). The number of rows must be
odd: with an even one a half turn maps the grid onto itself and the order is undecidable
from one image.

Symmetric circle grid (``pattern="symmetric_circles"``): ``rows`` rows of ``cols`` circles,
point ``r * cols + c`` at ``(c s, r s, 0)`` (OpenCV's ``CALIB_CB_SYMMETRIC_GRID``). Like an
even x even checkerboard it looks the same turned half round (a square one quarter round
too): each view's ordering is decided across sensors from the data.

Which marks read dark in a thermal image or in a TOF amplitude image depends on the
board (painted squares on bare aluminium read hot when heated, cold when cooled; some black
inks are bright in the near infrared), so a calibration finds it from the data
(calib.polarity). ``thermal_black_is_hot`` and ``tof_black_is_dark`` are optional
overrides: None (the default, key absent from ``board.yaml``) means "found from the data";
true/false fixes it (the detector then uses it and the calibration only checks it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from trifuse.calib.numbers import finite_float, is_int

POLARITY_KEYS = ("thermal_black_is_hot", "tof_black_is_dark")
"""The optional polarity overrides of ``board.yaml`` (None: found from the data)."""
PATTERNS = ("checkerboard", "charuco", "asymmetric_circles", "symmetric_circles")
"""The board patterns trifuse detects."""
MIN_POSE_POINTS = 6
"""Fewest points of a partial view (ChArUco) for a board pose and a place in Zhang's method:
the 4 of a homography plus 2 to spare against one corner astray (OpenCV's ChArUco
examples use 4-6; the OpenCV baseline here uses 6)."""
MIN_SPREAD = 0.25
"""The points of a view must not lie on one line: the smaller principal spread of their
board positions (standard deviation, in squares) must be at least this (two rows of
corners: 0.5)."""


def aruco_dictionary(name: str) -> Any:
    """OpenCV's predefined ArUco dictionary called ``name`` (e.g. ``"DICT_4X4_1000"``).

    Raises:
        ValueError: not one of OpenCV's predefined dictionaries.
    """
    if (
        not isinstance(name, str)
        or not name.startswith("DICT_")
        or not isinstance(getattr(cv2.aruco, name, None), int)
    ):
        raise ValueError(
            f"board dictionary: expected an OpenCV predefined ArUco dictionary such as "
            f"'DICT_4X4_1000', got {name!r}"
        )
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@dataclass(frozen=True)
class Board:
    """A calibration target with ``cols x rows`` detectable points (see the module doc).

    Attributes:
        cols, rows: detectable points per row and number of rows (checkerboard and
            ChArUco: inner corners; circles: OpenCV's pattern size).
        square_size_m: side of a square (circles: the grid's spacing ``s``), metres.
        thermal_black_is_hot, tof_black_is_dark: polarity overrides (None: from the data).
        pattern: one of :data:`PATTERNS`.
        marker_size_m: ChArUco: side of a marker, metres (< ``square_size_m``).
        dictionary: ChArUco: OpenCV's predefined dictionary name.
        inverted: ChArUco: white markers on black squares.
        legacy: ChArUco: OpenCV's legacy layout (before 4.6; differs for an even number of
            rows of squares).
        circle_diameter_m: circles: diameter, metres (< the nearest neighbour's distance).
    """

    cols: int
    rows: int
    square_size_m: float
    thermal_black_is_hot: bool | None = None
    tof_black_is_dark: bool | None = None
    pattern: str = field(default="checkerboard", kw_only=True)
    marker_size_m: float | None = field(default=None, kw_only=True)
    dictionary: str | None = field(default=None, kw_only=True)
    inverted: bool = field(default=False, kw_only=True)
    legacy: bool = field(default=False, kw_only=True)
    circle_diameter_m: float | None = field(default=None, kw_only=True)

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(
                f"board pattern: expected one of {list(PATTERNS)}, got {self.pattern!r}"
            )
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if not is_int(v) or v < 2:
                raise ValueError(f"board {name}: expected an integer >= 2, got {v!r}")
        size = self.square_size_m
        if not (finite_float(size) or 0.0) > 0.0:
            raise ValueError(f"board square_size_m: expected a positive number, got {size!r}")
        object.__setattr__(self, "square_size_m", float(self.square_size_m))
        for name in (*POLARITY_KEYS, "inverted", "legacy"):
            v = getattr(self, name)
            if v is not None and not isinstance(v, bool):
                raise ValueError(
                    f"board {name}: expected true or false"
                    f"{' (or no key: found from the data)' if name in POLARITY_KEYS else ''}, "
                    f"got {v!r}"
                )
        own = {
            "checkerboard": (),
            "charuco": ("marker_size_m", "dictionary"),
            "asymmetric_circles": ("circle_diameter_m",),
            "symmetric_circles": ("circle_diameter_m",),
        }[self.pattern]
        for name in ("marker_size_m", "dictionary", "circle_diameter_m"):
            if (getattr(self, name) is not None) != (name in own):
                need = "expected" if name in own else "unexpected"
                raise ValueError(
                    f"board {name}: {need} for a {self.pattern} board, got {getattr(self, name)!r}"
                )
        if self.pattern != "charuco" and (self.inverted or self.legacy):
            raise ValueError(f"board inverted/legacy: only for a charuco board, not {self.pattern}")
        if self.pattern == "charuco":
            self._check_charuco()
        if self.is_circles:
            self._check_circles()

    def _check_charuco(self) -> None:
        marker = finite_float(self.marker_size_m)
        if marker is None or not 0.0 < marker < self.square_size_m:
            raise ValueError(
                f"board marker_size_m: markers must fit the squares (0 < marker < square "
                f"{self.square_size_m:g} m), got {self.marker_size_m!r}"
            )
        object.__setattr__(self, "marker_size_m", marker)
        d = aruco_dictionary(self.dictionary)  # type: ignore[arg-type]
        sx, sy = self.squares
        need, have = (sx * sy) // 2, int(d.bytesList.shape[0])
        if need > have:
            raise ValueError(
                f"board dictionary: {self.dictionary} has {have} markers, a {sx}x{sy}-square "
                f"ChArUco board needs {need}"
            )

    def _check_circles(self) -> None:
        dia = finite_float(self.circle_diameter_m)
        # Nearest neighbours: asymmetric, one row and one column apart; symmetric, in a row.
        gap = self.square_size_m * (np.sqrt(2.0) if self.pattern == "asymmetric_circles" else 1)
        if dia is None or not 0.0 < dia < gap:
            raise ValueError(
                f"board circle_diameter_m: circles overlap or touch (expected 0 < diameter < "
                f"{gap:.4g} m, the nearest centres' distance at spacing {self.square_size_m:g} m), "
                f"got {self.circle_diameter_m!r}"
            )
        object.__setattr__(self, "circle_diameter_m", dia)
        if self.pattern == "asymmetric_circles" and self.rows % 2 == 0:
            raise ValueError(
                f"board points: an asymmetric circle grid with an even number of rows "
                f"({self.cols}x{self.rows}) looks the same turned half round, so its points' "
                f"order cannot be told; expected an odd number of rows (OpenCV's is 4x11)"
            )

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(cols, rows) as OpenCV's detectors take it."""
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        """Number of detectable points (corners or circle centres)."""
        return self.cols * self.rows

    @property
    def is_circles(self) -> bool:
        """A circle grid (asymmetric or symmetric): its points are circle centres."""
        return self.pattern in ("asymmetric_circles", "symmetric_circles")

    @property
    def partial_views(self) -> bool:
        """Whether a view may see a subset of the points (ChArUco): its detection then has
        NaN rows for the points not seen."""
        return self.pattern == "charuco"

    @property
    def orderings(self) -> int:
        """How many orderings of a detection's points the pattern cannot tell apart: 1
        when the square colours fix it (odd x even inner corners, not square), the markers
        (ChArUco) or the layout (asymmetric circles: an odd number of rows, see
        :class:`Board`); 2 when a half turn maps the pattern, colours included, onto itself
        (checkerboard even x even or odd x odd; any symmetric circle grid), 4 for a square
        checkerboard or symmetric circle grid (quarter turns too; colours not used)."""
        if self.pattern == "charuco":
            return 1
        if self.pattern == "asymmetric_circles":
            return 1
        if self.cols == self.rows:
            return 4
        if self.pattern == "symmetric_circles":
            return 2
        return 2 if (self.cols + self.rows) % 2 == 0 else 1

    @property
    def squares(self) -> tuple[int, int]:
        """Number of squares (across, down) of a checkerboard or ChArUco board."""
        return (self.cols + 1, self.rows + 1)

    def extent_m(self) -> tuple[float, float, float, float]:
        """The patterned area ``(x0, y0, x1, y1)`` in the board frame, metres: the squares
        (checkerboard, ChArUco), or the circles' bounding box."""
        s = self.square_size_m
        if self.pattern == "asymmetric_circles":
            r = 0.5 * float(self.circle_diameter_m)  # type: ignore[arg-type]
            width = (2 * (self.cols - 1) + (1 if self.rows > 1 else 0)) * s
            return (-r, -r, width + r, (self.rows - 1) * s + r)
        if self.pattern == "symmetric_circles":
            r = 0.5 * float(self.circle_diameter_m)  # type: ignore[arg-type]
            return (-r, -r, (self.cols - 1) * s + r, (self.rows - 1) * s + r)
        return (-s, -s, self.cols * s, self.rows * s)

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the patterned area (:meth:`extent_m`) in metres."""
        x0, y0, x1, y1 = self.extent_m()
        return (x1 - x0, y1 - y0)

    def object_points(self) -> np.ndarray:
        """Detectable points ``(cols * rows, 3)`` in the board frame, metres, row-major."""
        c, r = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.zeros((self.n_corners, 3))
        if self.pattern == "asymmetric_circles":
            pts[:, 0] = (2 * c.ravel() + r.ravel() % 2) * self.square_size_m
        else:
            pts[:, 0] = c.ravel() * self.square_size_m
        pts[:, 1] = r.ravel() * self.square_size_m
        return pts

    def is_black(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Whether board-frame points (x, y) in metres lie on the pattern's dark marks (bool
        array of their broadcast shape): black squares (checkerboard; outside the squares
        the pattern continues), black squares and marker cells (ChArUco, the other way
        round when ``inverted``; outside the squares the background: white, or black when
        inverted), inside a circle (circle grids)."""
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        s = self.square_size_m
        if self.is_circles:
            return self._in_circle(x, y)
        if self.pattern == "charuco":
            return self._charuco_black(x, y)
        i = np.floor(x / s)
        j = np.floor(y / s)
        return ((i + j) % 2) == 0

    def _charuco_black(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """:meth:`is_black` of a ChArUco board, exact: squares and marker cells computed
        from the board frame coordinates (markers centred in their squares)."""
        where, bits = _charuco_layout(self)
        s, m = self.square_size_m, float(self.marker_size_m)  # type: ignore[arg-type]
        sy, sx = where.shape
        cells = bits.shape[1]
        X, Y = np.broadcast_arrays(x + s, y + s)  # OpenCV's board frame
        i, j = np.floor(X / s).astype(np.int64), np.floor(Y / s).astype(np.int64)
        inside = (i >= 0) & (i < sx) & (j >= 0) & (j < sy)
        k = np.where(inside, where[np.clip(j, 0, sy - 1), np.clip(i, 0, sx - 1)], -1)
        dark = inside & (k < 0)  # black squares (no marker)
        lx, ly = X - i * s - 0.5 * (s - m), Y - j * s - 0.5 * (s - m)
        in_m = (k >= 0) & (lx >= 0) & (lx < m) & (ly >= 0) & (ly < m)
        ci = np.clip(np.floor(lx / m * cells).astype(np.int64), 0, cells - 1)
        cj = np.clip(np.floor(ly / m * cells).astype(np.int64), 0, cells - 1)
        dark[in_m] = bits[k[in_m], cj[in_m], ci[in_m]]
        return np.where(inside, dark ^ self.inverted, self.inverted)

    def _in_circle(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        s, radius = self.square_size_m, 0.5 * float(self.circle_diameter_m)  # type: ignore[arg-type]
        x, y = np.broadcast_arrays(x, y)
        out = np.zeros(x.shape, dtype=bool)
        r0 = np.round(y / s)
        asym = self.pattern == "asymmetric_circles"
        for dr in (-1.0, 0.0, 1.0) if asym else (0.0,):
            r = r0 + dr
            odd = np.mod(r, 2.0) if asym else 0.0
            c = np.round((x / s - odd) / 2.0) if asym else np.round(x / s)
            ok = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.cols)
            d2 = (x - ((2.0 * c + odd) if asym else c) * s) ** 2 + (y - r * s) ** 2
            out |= ok & (d2 <= radius * radius)
        return out

    def describe(self) -> str:
        """The board in words, one line, e.g. ``checkerboard 9 x 6 inner corners of 60 mm``,
        ``ChArUco 10 x 7 squares of 60 mm, markers 45 mm DICT_4X4_50, inverted``,
        ``asymmetric circle grid 4 x 11, spacing 60 mm, circles 42 mm`` (the polarity keys
        are not described)."""
        mm = f"{self.square_size_m * 1000:g} mm"
        if self.pattern == "charuco":
            sx, sy = self.squares
            marker = float(self.marker_size_m) * 1000  # type: ignore[arg-type]
            text = f"ChArUco {sx} x {sy} squares of {mm}, markers {marker:g} mm {self.dictionary}"
            return text + ", inverted" * self.inverted + ", legacy layout" * self.legacy
        if self.is_circles:
            dia = float(self.circle_diameter_m) * 1000  # type: ignore[arg-type]
            kind = self.pattern.split("_")[0]
            return f"{kind} circle grid {self.cols} x {self.rows}, spacing {mm}, circles {dia:g} mm"
        return f"checkerboard {self.cols} x {self.rows} inner corners of {mm}"

    def pose_problem(self, seen: np.ndarray) -> str | None:
        """Why the points marked in ``seen`` ((N,) bool, board order) cannot give a board
        pose, or None: fewer than :data:`MIN_POSE_POINTS`, or all on one line."""
        n = int(np.count_nonzero(seen))
        if n < MIN_POSE_POINTS:
            return f"only {n} corner(s) of {self.n_corners}: at least {MIN_POSE_POINTS} are needed"
        xy = self.object_points()[np.asarray(seen, dtype=bool), :2]
        xy = xy - xy.mean(axis=0)
        spread = float(np.sqrt(max(np.linalg.eigvalsh(xy.T @ xy / n)[0], 0.0)))
        if spread < MIN_SPREAD * self.square_size_m:
            return f"its {n} corners lie on one line: a pose needs them spread over the plane"
        return None

    def opencv_charuco(self) -> Any:
        """OpenCV's ``cv2.aruco.CharucoBoard`` for a ChArUco board (OpenCV's frame: origin
        at the squares' top-left corner, one square up-left of this board frame's)."""
        if self.pattern != "charuco":
            raise ValueError(f"board: expected a charuco board, got {self.pattern}")
        b = cv2.aruco.CharucoBoard(
            self.squares,
            self.square_size_m,
            self.marker_size_m,
            aruco_dictionary(self.dictionary),  # type: ignore[arg-type]
        )
        b.setLegacyPattern(self.legacy)
        return b

    def to_dict(self) -> dict[str, Any]:
        """``board.yaml`` content (a polarity key only when it is set)."""
        out: dict[str, Any] = {"pattern": self.pattern}
        if self.pattern == "checkerboard":
            out |= {"inner_corners": [self.cols, self.rows], "square_size_m": self.square_size_m}
        elif self.pattern == "charuco":
            out |= {
                "squares": list(self.squares),
                "square_size_m": self.square_size_m,
                "marker_size_m": self.marker_size_m,
                "dictionary": self.dictionary,
            }
            if self.inverted:
                out["inverted"] = True
            if self.legacy:
                out["legacy"] = True
        else:  # circle grids
            out |= {
                "points": [self.cols, self.rows],
                "spacing_m": self.square_size_m,
                "circle_diameter_m": self.circle_diameter_m,
            }
        for name in POLARITY_KEYS:
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out


@lru_cache(maxsize=8)
def _charuco_layout(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """A ChArUco board's markers: ``(sy, sx)`` int, the index into the second array of the
    marker in each square (-1: none, a black square), and ``(n, cells, cells)`` bool, each
    marker's cells (True: black; one-bit border included) from OpenCV's
    ``generateImageMarker``. Read-only."""
    d = aruco_dictionary(board.dictionary)  # type: ignore[arg-type]
    cells = int(d.markerSize) + 2
    s, m = board.square_size_m, float(board.marker_size_m)  # type: ignore[arg-type]
    sx, sy = board.squares
    ob = board.opencv_charuco()
    where = np.full((sy, sx), -1, dtype=np.int64)
    bits = []
    for k, (mid, corners) in enumerate(zip(np.ravel(ob.getIds()), ob.getObjPoints(), strict=True)):
        x0, y0 = np.asarray(corners, dtype=np.float64).reshape(4, 3)[0, :2]  # top-left
        where[int((y0 + 0.5 * m) // s), int((x0 + 0.5 * m) // s)] = k
        bits.append(cv2.aruco.generateImageMarker(d, int(mid), cells, borderBits=1) < 128)
    cells_bits = np.stack(bits) if bits else np.zeros((0, cells, cells), dtype=bool)
    where.setflags(write=False)
    cells_bits.setflags(write=False)
    return where, cells_bits


def _pair(data: Mapping, key: str, what: str) -> tuple[Any, Any]:
    v = data[key]
    if not isinstance(v, list | tuple) or len(v) != 2:
        raise ValueError(f"board {key}: expected [{what}], got {v!r}")
    return v[0], v[1]


_KEYS = {
    "checkerboard": ({"inner_corners", "square_size_m"}, set()),
    "charuco": (
        {"squares", "square_size_m", "marker_size_m", "dictionary"},
        {"inverted", "legacy"},
    ),
    "asymmetric_circles": ({"points", "spacing_m", "circle_diameter_m"}, set()),
    "symmetric_circles": ({"points", "spacing_m", "circle_diameter_m"}, set()),
}


def board_from_dict(data: Any) -> Board:
    """Parse ``board.yaml`` content; ValueError names what is wrong."""
    if not isinstance(data, Mapping):
        raise ValueError(f"board: expected a mapping, got {type(data).__name__}")
    pattern = data.get("pattern")
    if not isinstance(pattern, str) or pattern not in _KEYS:
        raise ValueError(f"board pattern: expected one of {list(PATTERNS)}, got {pattern!r}")
    required, optional = _KEYS[pattern]
    required = required | {"pattern"}
    allowed = required | optional | set(POLARITY_KEYS)
    unknown = sorted(set(data) - allowed, key=str)
    if unknown:
        raise ValueError(
            f"board: unknown key(s) {unknown} for a {pattern} board (allowed: {sorted(allowed)})"
        )
    missing = sorted(required - set(data))
    if missing:
        raise ValueError(f"board: missing key(s) {missing} for a {pattern} board")
    polarity = {k: data.get(k) for k in POLARITY_KEYS}
    if pattern == "checkerboard":
        cols, rows = _pair(data, "inner_corners", "cols, rows")
        return Board(cols, rows, data["square_size_m"], **polarity)
    if pattern == "charuco":
        sx, sy = _pair(data, "squares", "squares across, squares down")
        for v in (sx, sy):
            if not is_int(v) or v < 3:
                raise ValueError(
                    f"board squares: expected two integers >= 3, got {data['squares']!r}"
                )
        return Board(
            sx - 1,
            sy - 1,
            data["square_size_m"],
            **polarity,
            pattern="charuco",
            marker_size_m=data["marker_size_m"],
            dictionary=data["dictionary"],
            inverted=data.get("inverted", False),
            legacy=data.get("legacy", False),
        )
    cols, rows = _pair(data, "points", "points per row, rows")
    return Board(
        cols,
        rows,
        data["spacing_m"],
        **polarity,
        pattern=pattern,
        circle_diameter_m=data["circle_diameter_m"],
    )
