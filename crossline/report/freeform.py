"""Freeform deviations: signed distance of points to a reference mesh, and their statistics.

``point_triangle_closest`` (closest points on triangles, float64), ``mesh_signed_distance``
(Open3D finds the closest triangle, the distance is recomputed in float64) and
``deviation_stats`` (n, mean, std, RMS, 95th percentile of |dev|, share within a band).
Split from ``crossline.report.metrics`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["deviation_stats", "mesh_signed_distance", "point_triangle_closest"]


# ----------------------------------------------------------------------------- freeform


def point_triangle_closest(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points (N, 3) on triangles (a, b, c) (each (N, 3)) to points p (N, 3), in float64.

    Ericson's region test (Real-Time Collision Detection, 5.1.5), vectorised.
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))
    ab, ac, ap = b - a, c - a, p - a
    d1 = (ab * ap).sum(1)
    d2 = (ac * ap).sum(1)
    bp = p - b
    d3 = (ab * bp).sum(1)
    d4 = (ac * bp).sum(1)
    cp = p - c
    d5 = (ab * cp).sum(1)
    d6 = (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        # edges
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    e_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out = np.where(e_bc[:, None], b + (c - b) * t_bc[:, None], out)
    e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(e_ac[:, None], a + ac * t_ac[:, None], out)
    e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(e_ab[:, None], a + ab * t_ab[:, None], out)
    # vertices (checked last: they take precedence)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


def mesh_signed_distance(
    points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray
) -> np.ndarray:
    """Signed distance (N,) in mm of points (N, 3) to a triangle mesh, positive on the normals' side.

    Open3D's ``RaycastingScene`` (float32) finds each point's closest triangle, in
    coordinates centred on the mesh to keep float32 rounding small; the distance to that
    triangle is then recomputed in float64, so it is exact to ~1e-12 mm whenever the
    closest triangle is right (a wrong one, within float32 rounding, differs by < 1e-5 mm).
    The sign is that of the triangle's normal (vertex order, counter-clockwise).
    """
    import open3d as o3d

    p = np.asarray(points, dtype=np.float64)
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    if len(p) == 0:
        return np.zeros(0)
    c0 = V.mean(0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((V - c0).astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32))
    )
    ans = scene.compute_closest_points(o3d.core.Tensor((p - c0).astype(np.float32)))
    tri = F[ans["primitive_ids"].numpy().astype(np.int64)]
    a, b, c = V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]]
    q = point_triangle_closest(p, a, b, c)
    delta = p - q
    dist = np.linalg.norm(delta, axis=1)
    normal = np.cross(b - a, c - a)
    side = np.sign((delta * normal).sum(1))
    return np.where(side < 0, -dist, dist)


def deviation_stats(dev: np.ndarray, band_mm: float = 0.05) -> dict[str, Any]:
    """Summary of signed deviations (mm): n, mean, std, RMS, 95th percentile of |dev|, share in band."""
    dev = np.asarray(dev, dtype=np.float64)
    if dev.size == 0:
        return {"n": 0}
    return {
        "n": int(dev.size),
        "mean_mm": float(dev.mean()),
        "std_mm": float(dev.std(ddof=1)) if dev.size > 1 else 0.0,
        "rms_mm": float(np.sqrt(np.mean(dev**2))),
        "abs_p95_mm": float(np.percentile(np.abs(dev), 95)),
        "max_abs_mm": float(np.abs(dev).max()),
        "band_mm": band_mm,
        "share_within_band": float(np.mean(np.abs(dev) <= band_mm)),
    }
