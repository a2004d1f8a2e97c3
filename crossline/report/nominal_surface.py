"""The nominal mesh as a surface to measure against: closed or not, closest points, signed distance.

``_Surface`` holds a triangle mesh with Open3D's float32 ``RaycastingScene``, built in
coordinates centred on the mesh; each closest point is recomputed in float64 on the triangle
the scene found (``crossline.report.metrics.point_triangle_closest``), and the sign comes from
the parity of ray crossings on a closed mesh (``_is_closed``), else from the side of the closest
triangle. Split from ``crossline.report.nominal`` (issue 21.3), whose docstring says how
precise this is.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crossline.report.metrics import point_triangle_closest


def _is_closed(F: np.ndarray) -> bool:
    """True if every undirected edge of the triangles is shared by exactly two of them."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e[:, 0] * (int(F.max()) + 1) + e[:, 1], return_counts=True)
    return bool((counts == 2).all())


class _Surface:
    """A triangle mesh with its float32 ray-casting scene, centred for precision."""

    def __init__(self, V: np.ndarray, F: np.ndarray) -> None:
        import open3d as o3d

        self.V = np.asarray(V, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        if self.V.ndim != 2 or self.V.shape[1] != 3 or self.F.ndim != 2 or self.F.shape[1] != 3:
            raise ValueError("vertices and triangles must be (V, 3) and (F, 3)")
        if len(self.F) == 0:
            raise ValueError("the nominal mesh has no triangles")
        if self.F.min() < 0 or self.F.max() >= len(self.V) or not np.isfinite(self.V).all():
            raise ValueError("the nominal mesh has non-finite vertices or triangle indices out of range")
        # float32 loses precision with distance from the origin: centre on the mesh
        self.c0 = 0.5 * (self.V.min(0) + self.V.max(0))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor((self.V - self.c0).astype(np.float32)),
            o3d.core.Tensor(self.F.astype(np.uint32)),
        )
        a, b, c = (self.V[self.F[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.normals = n / np.linalg.norm(n, axis=1, keepdims=True)
        self.normals = np.nan_to_num(self.normals)
        self.closed = _is_closed(self.F)
        self.diagonal = float(np.linalg.norm(self.V.max(0) - self.V.min(0)))

    def _query(self, p: np.ndarray) -> Any:
        import open3d as o3d

        return o3d.core.Tensor((p - self.c0).astype(np.float32))

    def closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest points (N, 3) float64 on the mesh and the index of their triangle."""
        ans = self.scene.compute_closest_points(self._query(p))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        vid = self.F[tri]
        q = point_triangle_closest(p, self.V[vid[:, 0]], self.V[vid[:, 1]], self.V[vid[:, 2]])
        return q, tri

    def signed(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed distance (N,), closest points (N, 3) and triangle normals (N, 3)."""
        q, tri = self.closest(p)
        delta = p - q
        dist = np.linalg.norm(delta, axis=1)
        n = self.normals[tri]
        if self.closed:
            # parity of ray crossings: right whatever the triangles' winding, and also at
            # sharp edges where one face's normal can point the wrong way
            inside = self.scene.compute_occupancy(self._query(p), nsamples=3).numpy() > 0.5
        else:
            inside = (delta * n).sum(1) < 0
        return np.where(inside, -dist, dist), q, n
