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
_ROWS = 8192  # query rows at a time: ~20 MB of neighbour coordinates


def _slab_normals(reach: np.ndarray, start: int, stop: int, radius: float,
                  viewpoints: np.ndarray | None, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Normals and fallback mask of ``reach[start:stop]`` from neighbours among ``reach``
    (:func:`estimate_normals` for one slab; ``viewpoints`` are those of the core points)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(reach)
    n = stop - start
    normals = np.empty((n, 3))
    degenerate = np.empty(n, dtype=bool)
    for r0 in range(0, n, _ROWS):
        r1 = min(n, r0 + _ROWS)
        C, count = _covariances(reach, tree, reach[start + r0:start + r1], radius, threads)
        w, V = np.linalg.eigh(C)
        del C
        nrm = V[:, :, 0].copy()
        # fewer than 3 neighbours span no plane (Open3D's covariance is then the identity,
        # whose smallest eigenvector is an arbitrary axis: a view direction is better)
        line = (w[:, 1] <= 1e-4 * w[:, 2]) | (count == 2)
        alone = (w[:, 2] <= 0) | (count < 2)
        deg = line | alone
        if viewpoints is not None and deg.any():
            v = viewpoints[r0:r1][deg] - reach[start + r0:start + r1][deg]
            t = V[deg, :, 2]
            m = np.where(alone[deg, None], v, v - np.sum(v * t, axis=1, keepdims=True) * t)
            nrm[deg] = m / np.linalg.norm(m, axis=1, keepdims=True)
        normals[r0:r1], degenerate[r0:r1] = nrm, deg
    return normals, degenerate


def _covariances(points: np.ndarray, tree, query: np.ndarray, radius: float,
                 threads: int) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (M, 3, 3) of each query point's neighbours among ``points`` within
    ``radius`` (at most ``NORMAL_MAX_NN``, nearest first, as Open3D's hybrid search takes
    them), about their own mean, and their count (M,).

    The same neighbours and normals as Open3D's ``estimate_covariances`` (within 1e-7 rad on
    a test surface), but a bounded block of rows at a time, in memory that numpy owns and
    gives back: Open3D's covariances of a whole slab, made on several threads, stayed with
    their allocator's arenas (some 0.2 GB more at every slab of a 3 M-point scan).
    """
    d, j = tree.query(query, k=min(NORMAL_MAX_NN, len(points)),
                      distance_upper_bound=radius, workers=threads)
    d, j = d.reshape(len(query), -1), j.reshape(len(query), -1)
    ok = np.isfinite(d)
    del d
    count = ok.sum(axis=1)
    # a missing neighbour is the nearest one, the query point itself: a zero vector below
    nb = points[np.where(ok, j, j[:, :1])]
    del j, ok
    nb -= query[:, None, :]  # about the query point: small numbers from here on
    c = np.maximum(count, 1)[:, None]
    mean = nb.sum(axis=1) / c
    C = np.matmul(nb.transpose(0, 2, 1), nb) / c[:, :, None] - mean[:, :, None] * mean[:, None, :]
    return C, count


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
