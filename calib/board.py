"""The calibration target: a checkerboard, and its corners in the board frame.

Board frame: origin at the first inner corner, +x along a row of corners (``cols``), +y
down the columns (``rows``), +z into the board (away from a camera that sees its front),
metres. Corners are ordered row-major: index ``r * cols + c`` is at
``(c * square, r * square, 0)``. The square diagonally up-left of corner (0, 0) is black
(on the heated board: high emissivity, so hot in thermal; dark in TOF amplitude). With
an odd number of squares on one side and an even number on the other, the colours fix
the ordering under a half turn. Other boards look the same turned (:attr:`Board.orderings`):
even x even or odd x odd inner corners under a half turn, a square board under a quarter
turn too; each view's ordering is then decided across sensors from the data
(:func:`calib.polarity.order_views`).

Which squares read dark in a thermal image or in a TOF amplitude image depends on the
board (painted squares on bare aluminium read hot when heated, cold when cooled; some black
inks are bright in the near infrared), so a calibration finds it from the data
(calib.polarity). ``thermal_black_is_hot`` and ``tof_black_is_dark`` are optional
overrides: None (the default, key absent from ``board.yaml``) means "found from the data";
true/false fixes it (the detector then uses it and the calibration only checks it).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from calib.numbers import finite_float

POLARITY_KEYS = ("thermal_black_is_hot", "tof_black_is_dark")
"""The optional polarity overrides of ``board.yaml`` (None: found from the data)."""


@dataclass(frozen=True)
class Board:
    """A checkerboard with ``cols x rows`` inner corners and square side ``square_size_m``."""

    cols: int
    rows: int
    square_size_m: float
    thermal_black_is_hot: bool | None = None
    tof_black_is_dark: bool | None = None

    def __post_init__(self) -> None:
        for name in ("cols", "rows"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 2:
                raise ValueError(f"board {name}: expected an integer >= 2, got {v!r}")
        size = self.square_size_m
        if not (finite_float(size) or 0.0) > 0.0:
            raise ValueError(f"board square_size_m: expected a positive number, got {size!r}")
        object.__setattr__(self, "square_size_m", float(self.square_size_m))
        for name in POLARITY_KEYS:
            v = getattr(self, name)
            if v is not None and not isinstance(v, bool):
                raise ValueError(
                    f"board {name}: expected true or false (or no key: found from the data), "
                    f"got {v!r}"
                )

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(cols, rows) as OpenCV's detectors take it."""
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def orderings(self) -> int:
        """How many orderings of a detection's corners the pattern cannot tell apart: 1
        when the square colours fix it (odd x even inner corners, not square), 2 when a
        half turn maps the pattern, colours included, onto itself (even x even or odd x
        odd), 4 for a square board (quarter turns too; its colours are not used)."""
        if self.cols == self.rows:
            return 4
        return 2 if (self.cols + self.rows) % 2 == 0 else 1

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
        """``board.yaml`` content (a polarity key only when it is set)."""
        out: dict[str, Any] = {
            "pattern": "checkerboard",
            "inner_corners": [self.cols, self.rows],
            "square_size_m": self.square_size_m,
        }
        for name in POLARITY_KEYS:
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out


def board_from_dict(data: Any) -> Board:
    """Parse ``board.yaml`` content; ValueError names what is wrong."""
    if not isinstance(data, Mapping):
        raise ValueError(f"board: expected a mapping, got {type(data).__name__}")
    required = {"pattern", "inner_corners", "square_size_m"}
    allowed = required | set(POLARITY_KEYS)
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
    return Board(
        ic[0],
        ic[1],
        data["square_size_m"],
        data.get("thermal_black_is_hot"),
        data.get("tof_black_is_dark"),
    )
