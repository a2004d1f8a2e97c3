"""The freeform part's truth mesh: a triangulation of its design surface within 0.5 um.

The design surface is exact and analytic (``crossline.sim.scene.FreeformPart``): the
renderer intersects rays with it directly. The truth a report compares clouds with is a
triangle mesh (``truth/part.ply``, base frame, mm, float64 vertices) whose vertices lie on the
design surface and whose triangles deviate from it by less than 0.5 um (chordal error
``l^2 kappa / 8``): vertices are placed along the profile (pole to table) and around the plan
outline at spacings set by the local curvature, so flat regions get few triangles and the
shoulder and corners many. ``tests/test_sim_part.py`` measures the deviation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from crossline.io.atomic import atomic_path
from crossline.sim.scene import FreeformPart

__all__ = ["part_mesh", "write_ply"]


def _profile(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit superellipse of degree 4 in (rho, Z): rho^4 + Z^4 = 1, theta in [0, pi/2]."""
    return np.sqrt(np.abs(np.cos(theta))), np.sqrt(np.abs(np.sin(theta)))


def _plan(psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit superellipse of degree 4 in the plan: cx^4 + cy^4 = 1, psi in [0, 2 pi)."""
    c, s = np.cos(psi), np.sin(psi)
    return np.sign(c) * np.sqrt(np.abs(c)), np.sign(s) * np.sqrt(np.abs(s))


def _curvature_spacing(x: np.ndarray, y: np.ndarray, tol_mm: float) -> np.ndarray:
    """Cumulative 'cost' along a dense planar curve: integral of sqrt(kappa / (8 tol)) ds."""
    dx, dy = np.gradient(x), np.gradient(y)
    ddx, ddy = np.gradient(dx), np.gradient(dy)
    ds = np.hypot(dx, dy)
    kappa = np.abs(dx * ddy - dy * ddx) / np.maximum(ds, 1e-300) ** 3
    rate = np.sqrt(kappa / (8 * tol_mm)) + 1.0 / 2.0  # and at most 2 mm between vertices
    seg = 0.5 * (rate[1:] + rate[:-1]) * np.hypot(np.diff(x), np.diff(y))
    return np.concatenate([[0.0], np.cumsum(seg)])


def _place(param: np.ndarray, cost: np.ndarray) -> np.ndarray:
    n = int(np.ceil(cost[-1])) + 1
    return np.interp(np.linspace(0, cost[-1], n), cost, param)


def part_mesh(part: FreeformPart, tol_mm: float = 0.2e-3) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) in the part's parent frame and triangles (F, 3) of its surface.

    ``tol_mm`` is the chordal error allowed along each of the two grid directions; a
    triangle's deviation is at most about their sum.
    """
    Minv = part.Minv
    # the largest plan radius and height in mm bound the curvature the grid must follow
    scale = np.linalg.svd(Minv, compute_uv=False)
    big, small = scale.max(), scale.min()
    th = np.linspace(0.0, np.pi / 2, 200001)
    rho, Z = _profile(th)
    cost = np.maximum(_curvature_spacing(rho * big, Z * small, tol_mm),
                      _curvature_spacing(rho * small, Z * big, tol_mm))
    cost = np.maximum(cost, _curvature_spacing(rho * big, Z * big, tol_mm))
    theta = _place(th, cost)[::-1]  # pole (pi/2) first, the table (0) last
    ps = np.linspace(0.0, 2 * np.pi, 400001)
    cx, cy = _plan(ps)
    pc = np.maximum(_curvature_spacing(cx * big, cy * small, tol_mm),
                    _curvature_spacing(cx * small, cy * big, tol_mm))
    pc = np.maximum(pc, _curvature_spacing(cx * big, cy * big, tol_mm))
    psi = _place(ps, pc)[:-1]  # closed: drop the repeat of 0
    rho_k, Z_k = _profile(theta)
    cx_j, cy_j = _plan(psi)
    m = len(psi)
    rings = np.stack([np.outer(rho_k[1:], cx_j), np.outer(rho_k[1:], cy_j),
                      np.repeat(Z_k[1:, None], m, axis=1)], axis=-1).reshape(-1, 3)
    X = np.vstack([[0.0, 0.0, 1.0], rings])
    V = part.c + X @ Minv.T
    k = len(theta) - 1
    j = np.arange(m)
    jn = (j + 1) % m
    fan = np.stack([np.zeros(m, np.int64), 1 + j, 1 + jn], axis=1)
    faces = [fan]
    for r in range(k - 1):
        a = 1 + r * m + j
        b = 1 + r * m + jn
        c = 1 + (r + 1) * m + j
        d = 1 + (r + 1) * m + jn
        faces.append(np.stack([a, d, b], 1))
        faces.append(np.stack([a, c, d], 1))
    F = np.vstack(faces)  # counter-clockwise seen from outside: normals point out
    if part.dent is not None:
        V, F = _dented(part, V, F, tol_mm)
    return V, F


def _dented(part: FreeformPart, V: np.ndarray, F: np.ndarray, tol_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with the part's dent pressed in: triangles near it split (midpoints put back on
    the design surface) until their edges follow the dent's curvature within ``tol_mm``, then
    the vertices there moved onto the dented surface."""
    dent = part.dent
    # the dent's largest curvature is depth / sigma^2 (at its bottom)
    edge = max(np.sqrt(8.0 * tol_mm * dent.sigma_mm**2 / dent.depth_mm), 1e-3)
    reach = dent.REACH * dent.sigma_mm
    for _ in range(40):
        tri = V[F]
        lengths = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
        close = (np.linalg.norm(tri - dent.centre, axis=2) < reach + lengths.max(1, keepdims=True)).any(1)
        split = close & (lengths.max(1) > edge)
        if not split.any():
            break
        S = F[split]
        pairs = np.sort(np.stack([S[:, [0, 1]], S[:, [1, 2]], S[:, [2, 0]]], 1).reshape(-1, 2), axis=1)
        uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
        X = part.to_unit(0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]]))
        X /= part.gauge(X)[:, None]
        mid = len(V) + inv.reshape(-1, 3)
        V = np.vstack([V, part.c + X @ part.Minv.T])
        a, b, c = S[:, 0], S[:, 1], S[:, 2]
        ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
        F = np.vstack([F[~split], np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                       np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    near = dent.near(V)
    g = part.design_gradient(V[near])
    inward = -g / np.linalg.norm(g, axis=1, keepdims=True)
    V = V.copy()
    V[near] += part.dent_step(V[near], inward)[:, None] * inward
    return V, F


def write_ply(path: str | Path, V: np.ndarray, F: np.ndarray) -> None:
    """Binary little-endian PLY with float64 vertices, atomically and byte-reproducibly."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment crossline virtual rig: freeform truth, mm\n"
        f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    fv = np.zeros(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    fv["n"] = 3
    fv["i"] = F
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(np.ascontiguousarray(V, dtype="<f8").tobytes())
            fh.write(fv.tobytes())


def write_stl(path: str | Path, V: np.ndarray, F: np.ndarray, title: str = "crossline nominal") -> None:
    """Binary STL (float32, as the format has it; mm), atomically and byte-reproducibly."""
    tri = np.asarray(V, dtype=np.float64)[np.asarray(F)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    rec = np.zeros(len(F), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["n"] = n
    rec["v"] = tri
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(title.encode("ascii")[:80].ljust(80, b" "))
            fh.write(np.uint32(len(F)).astype("<u4").tobytes())
            fh.write(rec.tobytes())
