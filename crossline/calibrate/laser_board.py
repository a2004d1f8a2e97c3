"""The board in a laser-calibration image: its plane, its usable area, its albedo edges.

``board_plane_points`` meets the rays through pixels with the board plane (step 4 of
:mod:`crossline.calibrate.lasers`' docstring); ``edge_clearance`` is the distance (mm) from
board points to the nearest albedo edge (circle rims, square edges) or the usable area's edge,
and ``_board_area`` the pixels that see that area. Split from ``crossline.calibrate.lasers``
(issue 21.3), which re-exports these names.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.board import Board
from crossline.camera import Camera

__all__ = ["board_plane_points", "edge_clearance"]

def board_plane_points(camera: Camera, T_cam_board: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) where the rays through pixels (N, 2) meet the board plane."""
    r = camera.rays(np.asarray(uv, dtype=np.float64).reshape(-1, 2))
    n = T_cam_board[:3, 2]
    lam = (n @ T_cam_board[:3, 3]) / (r @ n)
    return r * lam[:, None]


def edge_clearance(board: Board, xy: np.ndarray, board_margin: float | None = None,
                   pattern: bool = True) -> np.ndarray:
    """Distance (mm) from board points (N, 2) to the nearest albedo edge; < 0 off the board.

    Albedo edges are circle rims (circle grids) or square edges (chessboards); with
    ``pattern`` False only the edge of the board's usable area counts. That area is the grid's
    bounding box grown by ``board_margin`` (default: one circle diameter beyond the outer
    centres; the chessboard's outer squares).
    """
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    s = board.spacing
    ex, ey = board.extent()
    m = _margin(board) if board_margin is None else board_margin
    inside = np.minimum.reduce([x + m, y + m, ex + m - x, ey + m - y])
    if not pattern:
        return inside
    if board.pattern == "chessboard":
        kx = np.clip(np.round(x / s), -1, board.cols)
        ky = np.clip(np.round(y / s), -1, board.rows)
        dx = np.where((y > -s) & (y < board.rows * s), np.abs(x - kx * s), np.inf)
        dy = np.where((x > -s) & (x < board.cols * s), np.abs(y - ky * s), np.inf)
        clear = np.minimum(dx, dy)
    else:
        R = 0.5 * board.diameter
        clear = np.full(x.shape, np.inf)
        r0 = np.floor(y / s)
        for dr in (-1, 0, 1, 2):
            r = np.clip(r0 + dr, 0, board.rows - 1)
            if board.pattern == "asymmetric":
                c0 = np.round((x - (r % 2) * s) / (2 * s))
                cands = [np.clip(c0 + dc, 0, board.cols - 1) for dc in (-1, 0, 1)]
                cx = [(2 * c + r % 2) * s for c in cands]
            else:
                c0 = np.round(x / s)
                cx = [np.clip(c0 + dc, 0, board.cols - 1) * s for dc in (-1, 0, 1)]
            for cxx in cx:
                clear = np.minimum(clear, np.abs(np.hypot(x - cxx, y - r * s) - R))
    return np.where(inside < 0, inside, np.minimum(clear, inside))


def _margin(board: Board) -> float:
    """How far the board's usable area reaches beyond the outer points (mm)."""
    return board.spacing if board.pattern == "chessboard" else float(board.diameter)


def _board_area(camera: Camera, T_cam_board: np.ndarray, board: Board, shape: tuple[int, int]) -> np.ndarray:
    """The pixels (bool mask) that see the board's usable area (``edge_clearance`` >= 0)."""
    ex, ey = board.extent()
    m = _margin(board)
    t = np.linspace(0.0, 1.0, 64, endpoint=False)
    x0, x1, y0, y1 = -m, ex + m, -m, ey + m
    xs = np.concatenate([x0 + (x1 - x0) * t, np.full_like(t, x1), x1 - (x1 - x0) * t, np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + (y1 - y0) * t, np.full_like(t, y1), y1 - (y1 - y0) * t])
    P = np.column_stack([xs, ys, np.zeros_like(xs)]) @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    uv = camera.project(P)  # the outline through the lens: 256 points, distortion included
    mask = np.zeros(shape, np.uint8)
    cv2.fillPoly(mask, [np.round(uv * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)
