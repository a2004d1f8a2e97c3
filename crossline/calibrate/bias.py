"""Perspective bias of circle centres: where a circle's imaged area centroid lies.

A circle seen in perspective (and through lens distortion) images as a near-ellipse whose
area centroid is *not* the projection of the circle's centre; the difference grows with the
square of the imaged radius (about 0.1 px at 12 px radius, about 1 px for the paper's 35 px
circles on a tilted board). Given a camera and a board pose, :func:`centroid_offsets`
predicts, for every circle, its imaged area centroid minus the projection of its centre, by
projecting densely sampled boundary points (distortion included) and taking the area centroid
of that polygon. Measured centroids minus these offsets are unbiased estimates of the
projected centres, which is what Zhang's method and PnP assume.
"""

from __future__ import annotations

import numpy as np

from crossline.board import Board
from crossline.camera import Camera
from crossline.geometry import rotvec_to_matrix

__all__ = ["centroid_offsets", "polygon_centroids"]


def polygon_centroids(poly: np.ndarray) -> np.ndarray:
    """Area centroids (..., 2) of closed polygons (..., M, 2) (vertices in order, either sense)."""
    x, y = poly[..., 0], poly[..., 1]
    # about the first vertex, which keeps the sums well conditioned far from the origin
    x = x - x[..., :1]
    y = y - y[..., :1]
    xn, yn = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * yn - xn * y
    a = cross.sum(-1)
    cx = ((x + xn) * cross).sum(-1) / (3.0 * a)
    cy = ((y + yn) * cross).sum(-1) / (3.0 * a)
    return np.stack([cx, cy], axis=-1) + poly[..., 0, :]


def centroid_offsets(
    camera: Camera, board: Board, rvec: np.ndarray, tvec: np.ndarray, samples: int = 128
) -> np.ndarray:
    """Imaged area centroid minus projected centre (N, 2) px of every circle, for one board pose.

    ``rvec``, ``tvec`` give ``T_cam_board`` (OpenCV's convention). Chessboards have no bias:
    zeros are returned.
    """
    P = board.object_points()
    if board.pattern == "chessboard":
        return np.zeros((len(P), 2))
    R = rotvec_to_matrix(np.asarray(rvec, dtype=np.float64).reshape(3))
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    a = np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False)
    ring = 0.5 * board.diameter * np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    boundary = (P[:, None, :] + ring[None, :, :]) @ R.T + t  # (N, M, 3) in the camera frame
    centres = P @ R.T + t
    return polygon_centroids(camera.project(boundary)) - camera.project(centres)
