"""Calibration board textures: circle grids (symmetric, asymmetric; dark or light) and chessboards.

A texture maps points of the board's face (board coordinates: origin at the first circle
centre or inner corner, circles on z = 0) to an albedo and to the distance (mm) to the
nearest albedo edge; the renderer supersamples the pixels whose footprint reaches an edge.
Circles are exact circles on the plane: their images are the perspective (and distorted)
images of circles, nothing is drawn in the image.
"""

from __future__ import annotations

import numpy as np

from crossline.sim.presets import BoardSpec

__all__ = ["board_texture"]


def board_texture(spec: BoardSpec, offset: np.ndarray):
    """Texture of local points (board = local + offset) -> (albedo, edge distance or None).

    The returned function takes local points (N, 3); its attribute ``xy(x, y, edges)`` takes
    their first two coordinates (all a face texture reads) as separate arrays.
    """
    b = spec.board
    s = b.spacing
    light, dark = spec.light_albedo, spec.dark_albedo
    xmin, ymin, xmax, ymax = spec.plate_rect()
    off = np.asarray(offset, dtype=np.float64)

    def border(x, y):
        return np.minimum(np.minimum(x - xmin, xmax - x), np.minimum(y - ymin, ymax - y))

    if b.pattern == "chessboard":

        def tex_xy(lx, ly, edges: bool = True):
            x = lx + off[0]
            y = ly + off[1]
            # squares span [-s, cols*s] x [-s, rows*s]; inner corners at (c s, r s)
            ix = np.floor(x / s)
            iy = np.floor(y / s)
            inside = (ix >= -1) & (ix <= b.cols - 1) & (iy >= -1) & (iy <= b.rows - 1)
            black = ((ix + iy) % 2 == 0) & inside
            a = np.where(black, dark, light)
            if not edges:
                return a, None
            fx = x / s - ix
            fy = y / s - iy
            e_in = s * np.minimum(np.minimum(fx, 1 - fx), np.minimum(fy, 1 - fy))
            # outside the squares: distance to the squares' outline
            dx = np.maximum.reduce([-s - x, x - b.cols * s, np.zeros_like(x)])
            dy = np.maximum.reduce([-s - y, y - b.rows * s, np.zeros_like(y)])
            e_out = np.hypot(dx, dy)
            e = np.where(inside, e_in, e_out)
            return a, np.minimum(e, border(x, y))

        return _with_local(tex_xy)

    R = b.diameter / 2
    in_albedo, out_albedo = (dark, light) if b.circles == "dark" else (light, dark)

    def tex_xy(lx, ly, edges: bool = True):
        x = lx + off[0]
        y = ly + off[1]
        if b.pattern == "asymmetric":
            best = np.full(len(x), np.inf)
            r0 = np.rint(y / s)
            for dr in (-1, 0, 1):
                r = np.clip(r0 + dr, 0, b.rows - 1)
                shift = (r % 2) * s
                c = np.clip(np.rint((x - shift) / (2 * s)), 0, b.cols - 1)
                cx = 2 * c * s + shift
                dx, dy = x - cx, y - r * s
                best = np.minimum(best, dx * dx + dy * dy)
        else:  # the nearest circle centre is the nearest grid node
            r = np.clip(np.rint(y / s), 0, b.rows - 1)
            c = np.clip(np.rint(x / s), 0, b.cols - 1)
            dx, dy = x - c * s, y - r * s
            best = dx * dx + dy * dy
        a = np.where(best <= R * R, in_albedo, out_albedo)
        if not edges:
            return a, None
        return a, np.minimum(np.abs(np.sqrt(best) - R), border(x, y))

    return _with_local(tex_xy)


def _with_local(tex_xy):
    """The texture as a function of local points (N, 3), with ``.xy(x, y, edges)`` beside it."""

    def tex(local, edges: bool = True):
        return tex_xy(local[:, 0], local[:, 1], edges)

    tex.xy = tex_xy
    return tex
