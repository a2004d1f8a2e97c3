"""Synthetic board views and stripes for tests of the calibration stages (not a simulator).

Independent of ``crossline.sim``: a small ray tracer that renders a board (circle grid or
chessboard) through a :class:`Camera` by supersampling each pixel, tracing each sample's ray
to the board plane, and optionally a laser sheet of Gaussian thickness on the board. It
exists so that detection and calibration can be tested exactly before and beside the real
simulator; the end-to-end tests use ``crossline.sim``.
"""

from __future__ import annotations

import numpy as np

from crossline.board import Board
from crossline.camera import Camera
from crossline.geometry import invert_transform, make_transform, rotvec_to_matrix

__all__ = ["look_at", "render_view", "sample_rays", "view_poses"]


def sample_rays(camera: Camera, supersample: int = 3, rows: slice | None = None) -> np.ndarray:
    """Unit rays (H, W, s*s, 3) through a grid of s×s sub-pixel positions of every pixel.

    The distortion is inverted exactly at pixel centres and carried to the sub-pixel
    positions with its local derivative (the second-order term is ~1e-7 px here).
    """
    w, h = camera.image_size
    s = supersample
    sub = (np.arange(s) + 0.5) / s - 0.5
    r = np.arange(h)[rows] if rows is not None else np.arange(h)
    lo, hi = max(int(r[0]) - 1, 0), min(int(r[-1]) + 2, h)  # one row of margin for derivatives
    v, u = np.mgrid[lo:hi, 0:w].astype(np.float64)
    xy = camera.undistort(np.stack([u, v], -1).reshape(-1, 2)).reshape(hi - lo, w, 2)
    dxy_dv, dxy_du = np.gradient(xy, axis=(0, 1))
    k = slice(int(r[0]) - lo, int(r[0]) - lo + len(r))
    xy, dxy_du, dxy_dv = xy[k], dxy_du[k], dxy_dv[k]
    du = np.tile(sub, s)  # sub-pixel offsets, row-major over (dv, du)
    dv = np.repeat(sub, s)
    pts = (xy[:, :, None, :] + du[None, None, :, None] * dxy_du[:, :, None, :]
           + dv[None, None, :, None] * dxy_dv[:, :, None, :])
    d = np.concatenate([pts, np.ones((*pts.shape[:-1], 1))], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _board_albedo(board: Board, xy: np.ndarray, light: float, dark: float, table: float) -> np.ndarray:
    """Albedo at board points (..., 2): light board, dark features, ``table`` off the board."""
    x, y = xy[..., 0], xy[..., 1]
    s = board.spacing
    ex, ey = board.extent()
    m = 1.5 * s
    on_board = (x > -m) & (x < ex + m) & (y > -m) & (y < ey + m)
    if board.pattern == "chessboard":
        inside = (x > -s) & (x < ex + s) & (y > -s) & (y < ey + s)
        feature = inside & ((np.floor(x / s) + np.floor(y / s)) % 2 == 0)
    else:
        R = 0.5 * board.diameter
        feature = np.zeros(x.shape, dtype=bool)
        r0 = np.floor(y / s)
        for dr in (0, 1):
            r = np.clip(r0 + dr, 0, board.rows - 1)
            if board.pattern == "asymmetric":
                c = np.clip(np.round((x - (r % 2) * s) / (2 * s)), 0, board.cols - 1)
                cx = (2 * c + r % 2) * s
            else:
                c = np.clip(np.round(x / s), 0, board.cols - 1)
                cx = c * s
            feature |= (x - cx) ** 2 + (y - r * s) ** 2 <= R * R
    fg, bgv = (dark, light) if board.circles == "dark" or board.pattern == "chessboard" else (light, dark)
    return np.where(on_board, np.where(feature, fg, bgv), table)


def render_view(
    camera: Camera,
    board: Board,
    T_cam_board: np.ndarray,
    *,
    supersample: int = 3,
    light: float = 200.0,
    dark: float = 30.0,
    table: float = 70.0,
    blur_sigma: float = 0.8,
    noise: float = 0.0,
    gradient: float = 0.0,
    laser_plane: tuple[np.ndarray, float] | None = None,
    laser_sigma_mm: float = 0.05,
    laser_peak: float = 0.0,
    ambient: float = 0.0,
    rng: np.random.Generator | None = None,
    rays: np.ndarray | None = None,
) -> np.ndarray:
    """8-bit image of the board at ``T_cam_board`` (and of a laser sheet on it if given).

    ``gradient`` is a relative illumination slope across the image width; ``laser_plane``
    ``(n, d)`` in the camera frame with a Gaussian sheet of ``laser_sigma_mm`` adds
    ``laser_peak × albedo/light`` at the board; ``ambient`` is a constant added everywhere.
    """
    import cv2

    T_board_cam = invert_transform(T_cam_board)
    n = T_cam_board[:3, 2]
    t = T_cam_board[:3, 3]
    w, h = camera.image_size
    img = np.empty((h, w))
    block = max(1, 2_000_000 // (w * supersample * supersample))
    for r0 in range(0, h, block):
        rows = slice(r0, min(h, r0 + block))
        ry = sample_rays(camera, supersample, rows) if rays is None else rays[rows]
        lam = (n @ t) / (ry @ n)  # distance along each ray to the board plane
        pts_cam = ry * lam[..., None]
        pts = pts_cam @ T_board_cam[:3, :3].T + T_board_cam[:3, 3]
        alb = _board_albedo(board, pts[..., :2], light, dark, table)
        val = alb
        if laser_plane is not None:
            ln, ld = laser_plane
            dist = pts_cam @ np.asarray(ln) + ld
            val = val + laser_peak * (alb / light) * np.exp(-0.5 * (dist / laser_sigma_mm) ** 2)
        img[rows] = val.mean(axis=-1)
    if gradient:
        img = img * (1.0 + gradient * (np.arange(w) / w - 0.5))[None, :]
    img = img + ambient
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if noise > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """``T_world_cam`` of a camera at ``eye`` looking at ``target`` (camera y roughly along ``up``×-1)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, dtype=np.float64), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]), eye)


def view_poses(
    board: Board, n: int, distance: float, max_tilt_deg: float = 35.0, seed: int = 0,
    spread: float = 0.15, roll_deg: float = 15.0,
) -> np.ndarray:
    """``T_cam_board`` (n, 4, 4) of varied views of the board's centre from about ``distance`` mm."""
    rng = np.random.default_rng(seed)
    ex, ey = board.extent()
    centre = np.array([ex / 2, ey / 2, 0.0])
    out = []
    for k in range(n):
        tilt = np.radians(max_tilt_deg) * np.sqrt((k + 0.5) / n)
        az = 2 * np.pi * k * 0.618034 + rng.uniform(-0.3, 0.3)
        direction = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        d = distance * rng.uniform(0.9, 1.1)
        target = centre + np.r_[rng.uniform(-spread, spread, 2) * [ex, ey], 0.0]
        T_board_cam = look_at(centre + d * direction, target, up=(0.0, -1.0, 0.0))
        roll = rotvec_to_matrix(np.array([0, 0, np.radians(rng.uniform(-roll_deg, roll_deg))]))
        T_board_cam = T_board_cam @ make_transform(roll, np.zeros(3))
        out.append(invert_transform(T_board_cam))
    return np.array(out)
