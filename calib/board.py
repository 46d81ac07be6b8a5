"""The calibration target: a checkerboard, and its corners in the board frame.

Board frame: origin at the first inner corner, +x along a row of corners (``cols``), +y
down the columns (``rows``), +z into the board (away from a camera that sees its front),
metres. Corners are ordered row-major: index ``r * cols + c`` is at
``(c * square, r * square, 0)``. The square diagonally up-left of corner (0, 0) is black
(on the heated board: high emissivity, so hot in thermal; dark in TOF amplitude). With
an odd number of squares on one side and an even number on the other, the colours fix
the ordering under a half turn. ``thermal_black_is_hot`` says whether the black squares
read hot in thermal images (true for a heated board whose black squares are the
high-emissivity material); the detector needs it to tell the two orderings apart there.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.numbers import finite_float


@dataclass(frozen=True)
class Board:
    """A checkerboard with ``cols x rows`` inner corners and square side ``square_size_m``."""

    cols: int
    rows: int
    square_size_m: float
    thermal_black_is_hot: bool = True

    def __post_init__(self) -> None:
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 2:
                raise ValueError(f"board {name}: expected an integer >= 2, got {v!r}")
        size = self.square_size_m
        if not (finite_float(size) or 0.0) > 0.0:
            raise ValueError(f"board square_size_m: expected a positive number, got {size!r}")
        object.__setattr__(self, "square_size_m", float(self.square_size_m))
        if not isinstance(self.thermal_black_is_hot, bool):
            raise ValueError(
                f"board thermal_black_is_hot: expected true or false, "
                f"got {self.thermal_black_is_hot!r}"
            )

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(cols, rows) as OpenCV's detectors take it."""
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def squares(self) -> tuple[int, int]:
        """Number of squares (across, down)."""
        return (self.cols + 1, self.rows + 1)

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the checkered area in metres."""
        return (self.squares[0] * self.square_size_m, self.squares[1] * self.square_size_m)

    def object_points(self) -> np.ndarray:
        """Inner corners ``(cols * rows, 3)`` in the board frame, metres, row-major."""
        c, r = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.zeros((self.n_corners, 3))
        pts[:, 0] = c.ravel() * self.square_size_m
        pts[:, 1] = r.ravel() * self.square_size_m
        return pts

    def is_black(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Whether board-frame points (x, y) in metres lie on a black square (bool array)."""
        i = np.floor(np.asarray(x_m) / self.square_size_m)
        j = np.floor(np.asarray(y_m) / self.square_size_m)
        return ((i + j) % 2) == 0

    def to_dict(self) -> dict[str, Any]:
        """``board.yaml`` content (the polarity only when it is not the default)."""
        out: dict[str, Any] = {
            "pattern": "checkerboard",
            "inner_corners": [self.cols, self.rows],
            "square_size_m": self.square_size_m,
        }
        if not self.thermal_black_is_hot:
            out["thermal_black_is_hot"] = False
        return out


def board_from_dict(data: Any) -> Board:
    """Parse ``board.yaml`` content; ValueError names what is wrong."""
    if not isinstance(data, Mapping):
        raise ValueError(f"board: expected a mapping, got {type(data).__name__}")
    required = {"pattern", "inner_corners", "square_size_m"}
    allowed = required | {"thermal_black_is_hot"}
    unknown = sorted(set(data) - allowed, key=str)
    if unknown:
        raise ValueError(f"board: unknown key(s) {unknown} (allowed: {sorted(allowed)})")
    missing = sorted(required - set(data))
    if missing:
        raise ValueError(f"board: missing key(s) {missing}")
    if data["pattern"] != "checkerboard":
        raise ValueError(
            f"board pattern: only 'checkerboard' is supported, got {data['pattern']!r}"
        )
    ic = data["inner_corners"]
    if not isinstance(ic, list | tuple) or len(ic) != 2:
        raise ValueError(f"board inner_corners: expected [cols, rows], got {ic!r}")
    return Board(ic[0], ic[1], data["square_size_m"], data.get("thermal_black_is_hot", True))
