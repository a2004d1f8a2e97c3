"""The calibration board: circle grids (symmetric, asymmetric) and chessboards.

Board frame: origin at the first circle centre (chessboard: first inner corner), points on
``z = 0``. Symmetric grid and chessboard: point (r, c) at ``(c·spacing, r·spacing, 0)``;
asymmetric grid, OpenCV's layout: ``((2c + r mod 2)·spacing, r·spacing, 0)``. Points are
ordered row by row, as ``cv2.findCirclesGrid`` and ``cv2.findChessboardCorners`` return
them for ``patternSize = (cols, rows)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

__all__ = ["PATTERNS", "Board"]

PATTERNS = ("symmetric", "asymmetric", "chessboard")


@dataclass(frozen=True)
class Board:
    """A planar calibration target as described under ``board:`` in ``rig.yaml``."""

    pattern: Literal["symmetric", "asymmetric", "chessboard"]
    cols: int
    rows: int
    spacing: float
    diameter: float | None = None
    circles: Literal["dark", "light"] = "dark"

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(f"board pattern must be one of {PATTERNS}, got {self.pattern!r}")
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"board needs at least 2 cols and 2 rows, got {self.cols}x{self.rows}")
        if not self.spacing > 0:
            raise ValueError(f"board spacing must be > 0 mm, got {self.spacing}")
        if self.pattern != "chessboard":
            if self.diameter is None or not 0 < self.diameter < self.spacing * (
                2 if self.pattern == "asymmetric" else 1
            ):
                raise ValueError(
                    f"circle diameter must be > 0 and smaller than the spacing, got {self.diameter}"
                )
            if self.circles not in ("dark", "light"):
                raise ValueError(f"board circles must be 'dark' or 'light', got {self.circles!r}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's ``patternSize``: (points per row, rows)."""
        return (self.cols, self.rows)

    @property
    def n_points(self) -> int:
        """Number of circle centres (or inner corners)."""
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """Board points (rows·cols, 3) in mm, in OpenCV's detection order."""
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        r = r.ravel().astype(np.float64)
        c = c.ravel().astype(np.float64)
        x = (2 * c + r % 2) * self.spacing if self.pattern == "asymmetric" else c * self.spacing
        return np.column_stack([x, r * self.spacing, np.zeros_like(x)])

    def extent(self) -> tuple[float, float]:
        """Size (x, y) in mm spanned by the point centres."""
        p = self.object_points()
        return float(p[:, 0].max()), float(p[:, 1].max())

    @classmethod
    def parse(cls, spec: str) -> Board:
        """A board from ``pattern:COLSxROWS:spacing[:diameter[:dark|light]]``, e.g.
        ``chessboard:12x9:4`` or ``asymmetric:7x13:2.5:1.5:light`` (mm; chessboards: inner
        corners and square size)."""
        form = "pattern:COLSxROWS:spacing[:diameter[:dark|light]]"
        parts = spec.strip().split(":")
        if len(parts) < 3 or len(parts) > 5:
            raise ValueError(f"board {spec!r}: expected {form}, e.g. chessboard:12x9:4")
        pattern, size, *rest = parts
        try:
            cols, rows = (int(v) for v in size.lower().split("x"))
            nums = [float(v) for v in rest[:2]]
        except ValueError:
            raise ValueError(f"board {spec!r}: expected {form}, e.g. chessboard:12x9:4") from None
        circles = rest[2] if len(rest) == 3 else "dark"
        if pattern == "chessboard" and len(nums) > 1:
            raise ValueError(f"board {spec!r}: a chessboard has no circle diameter")
        diameter = nums[1] if len(nums) > 1 else None
        if pattern in ("symmetric", "asymmetric") and diameter is None:
            raise ValueError(f"board {spec!r}: a circle grid needs its circle diameter ({form})")
        return cls(pattern, cols, rows, nums[0], diameter, circles)  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        """The ``board:`` mapping of ``rig.yaml``."""
        d: dict[str, Any] = {
            "pattern": self.pattern,
            "cols": self.cols,
            "rows": self.rows,
            "spacing": self.spacing,
        }
        if self.pattern != "chessboard":
            d["diameter"] = self.diameter
            d["circles"] = self.circles
        return d
