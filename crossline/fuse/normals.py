"""The fused cloud's normals, one slab at a time: from the neighbours' covariance, then oriented.

``_slab_normals`` gives the normals of one slab's core points from their neighbours within
the radius (at most ``NORMAL_MAX_NN``), with the view direction where the neighbours lie
along a line or there are none; ``orient_normals`` flips normals to face their viewpoints
(or the dominant side). :func:`crossline.fuse.estimate_normals` and the fuse stage's
normals towards the camera stay in :mod:`crossline.fuse.cloud`, which cuts the cloud into
slabs (:mod:`crossline.tiles`). Split from that module (issue 21.3); the package
``crossline.fuse`` re-exports these names.
"""

from __future__ import annotations

import numpy as np

__all__ = ["orient_normals"]

NORMAL_MAX_NN = 100  # neighbours at most per normal: a stripe alone would give too few


def _slab_normals(reach: np.ndarray, start: int, stop: int, radius: float,
                  viewpoints: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Normals and fallback mask of ``reach[start:stop]`` from neighbours among ``reach``
    (:func:`estimate_normals` for one slab; ``viewpoints`` are those of the core points)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(reach))
    pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius),
                                                                  max_nn=NORMAL_MAX_NN))
    C = np.asarray(pcd.covariances)[start:stop]
    del pcd
    w, V = np.linalg.eigh(C)
    normals = V[:, :, 0].copy()
    line = w[:, 1] <= 1e-4 * w[:, 2]
    alone = w[:, 2] <= 0
    degenerate = line | alone
    if viewpoints is not None and degenerate.any():
        v = viewpoints[degenerate] - reach[start:stop][degenerate]
        t = V[degenerate, :, 2]
        n = np.where(alone[degenerate, None], v, v - np.sum(v * t, axis=1, keepdims=True) * t)
        normals[degenerate] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return normals, degenerate


def orient_normals(
    points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray | None
) -> np.ndarray:
    """Normals (N, 3) flipped to face their viewpoints (N, 3); without viewpoints, to face the
    mean direction of the unoriented normals' dominant sign (a consistent, if arbitrary, side)."""
    n = np.asarray(normals, dtype=np.float64).copy()
    if viewpoints is not None and np.isfinite(viewpoints).all():
        flip = np.sum(n * (viewpoints - points), axis=1) < 0
    else:
        # the dominant axis of the normals, signed so that most point to +z of the base frame
        ref = np.linalg.svd(n, full_matrices=False)[2][0]
        ref = ref if ref[2] >= 0 else -ref
        flip = n @ ref < 0
    n[flip] *= -1
    return n
