"""A surface mesh of the fused cloud (Open3D): Poisson or ball pivoting.

``make_mesh``: Poisson, trimmed where nothing was measured, or ball pivoting at radii of a
few point spacings; the fuse stage writes it as STL when asked (``mesh``). Split from the fuse
stage's module (issue 21.3; now :mod:`crossline.fuse.cloud`); the package ``crossline.fuse``
re-exports this name.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from crossline.fuse import FusedCloud

__all__ = ["make_mesh"]


def make_mesh(cloud: FusedCloud, method: str, *, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Surface mesh (vertices, triangles) of the cloud by Poisson or ball pivoting (Open3D).

    Poisson vertices farther than 3 point spacings from every point, or over the sparsest
    support (lowest 2 % densities), are removed: Poisson closes the surface where nothing was
    measured. Ball pivoting uses radii of 1, 2 and 4 times the median point spacing.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points))
    pcd.normals = o3d.utility.Vector3dVector(cloud.normals)
    if method == "poisson":
        # one thread: Open3D's parallel Poisson solver is not reproducible (different bytes
        # from run to run with 2 threads); a mesh is an optional by-product, so bytes win
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=9, n_threads=1
        )
        dens = np.asarray(dens)
        # Poisson closes the surface where nothing was measured: drop what lies far from
        # every point (beyond 3 point spacings) and the sparsest support
        spacing = float(np.median(np.asarray(pcd.compute_nearest_neighbor_distance())))
        dist, _ = cKDTree(cloud.points).query(np.asarray(mesh.vertices), k=1, workers=threads)
        far = dist > 3 * spacing
        mesh.remove_vertices_by_mask(far | (dens < np.quantile(dens, 0.02)))
    elif method == "ball_pivoting":
        spacing = float(np.median(np.asarray(pcd.compute_nearest_neighbor_distance())))
        radii = o3d.utility.DoubleVector([spacing, 2 * spacing, 4 * spacing])
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
    else:
        raise ValueError(f"unknown mesh method {method!r}; expected poisson or ball_pivoting")
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy()
