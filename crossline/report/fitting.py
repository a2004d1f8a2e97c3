"""Plane and sphere fitting shared by the report's metrology: least-squares and RANSAC.

The lowest of the metrology modules: ``MIN_POINTS`` (fewest points for a figure),
``robust_sigma`` (:mod:`crossline.robust`'s), the total-least-squares ``fit_plane``,
``laser_codes`` (A/B labels as codes), and the RANSAC searches ``ransac_plane`` and
``ransac_sphere`` (fixed seed, so every result is reproducible) that the artefact
measurements start from. Split from ``crossline.report.metrics`` (issue 21.3), which
re-exports these names.
"""

from __future__ import annotations

import numpy as np

from crossline.robust import robust_sigma

__all__ = ["MIN_POINTS", "fit_plane", "laser_codes", "masked_blocks", "ransac_plane", "ransac_sphere",
           "robust_sigma"]

MIN_POINTS = 20  # fewest points for a figure to be reported at all


def _subsample(n: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of at most ``size`` of ``n`` items (all of them when n <= size)."""
    if n <= size:
        return np.arange(n)
    return np.sort(rng.choice(n, size=size, replace=False))


_BLOCK = 1 << 20  # rows at a time of a scan's points


def fit_plane(points: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Total-least-squares plane ``n · p + d = 0`` of points (N, 3) (those of ``mask`` (N,)
    where given), oriented so that ``d <= 0``.

    The same plane as ``crossline.geometry.fit_plane`` (which takes the SVD of the whole
    N × 3 matrix), from the 3 × 3 scatter matrix of the centred points instead: ten times
    quicker on the half-million points of a scan, and as exact for clouds of mm size
    (tests compare the two). A block of rows at a time: no copy of a long scan's points.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"fit_plane needs an (N, 3) array with N >= 3, got shape {p.shape}")
    m = None if mask is None else np.asarray(mask, dtype=bool)
    count = len(p) if m is None else int(m.sum())
    if count < 3:
        raise ValueError(f"fit_plane needs an (N, 3) array with N >= 3, got {count} points")
    total = np.zeros(3)
    for q in masked_blocks(p, m):
        total += q.sum(axis=0)
    c = total / count
    S = np.zeros((3, 3))
    for q in masked_blocks(p, m):
        q = q - c
        S += q.T @ q
    _, V = np.linalg.eigh(S)
    n = V[:, 0]
    d = -float(n @ c)
    if d > 0:
        n, d = -n, -d
    return n, d


def masked_blocks(points: np.ndarray, mask: np.ndarray | None, block: int = _BLOCK):
    """The rows of ``points`` (those of ``mask`` where given), a block at a time."""
    for a in range(0, len(points), block):
        q = points[a:a + block]
        yield q if mask is None else q[mask[a:a + block]]


def laser_codes(laser: np.ndarray) -> np.ndarray:
    """Laser of each point as uint8 codes 1 = A, 2 = B, 0 = other, from codes or labels."""
    lab = np.asarray(laser)
    if lab.dtype.kind in "OUS":
        s = lab.astype(str)
        return np.select([s == "A", s == "B"], [1, 2], 0).astype(np.uint8)
    return lab.astype(np.uint8, copy=False)


def _orient(n: np.ndarray, d: float, up: np.ndarray | None) -> tuple[np.ndarray, float]:
    if up is not None and float(n @ up) < 0:
        return -n, -d
    return n, d


# ----------------------------------------------------------------------------- RANSAC


def ransac_plane(
    points: np.ndarray,
    threshold: float,
    *,
    iterations: int = 300,
    sample: int = 20000,
    seed: int = 0,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane of points (N, 3): RANSAC on a subsample, then least squares on the inliers.

    Returns the unit normal, ``d`` and the inlier mask (N,) (``|distance| < threshold``).
    The candidates are scored together (one matrix product), so 300 iterations on 20 000
    points take milliseconds.
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) < 3:
        raise ValueError(f"ransac_plane needs at least 3 points, got {len(p)}")
    rng = np.random.default_rng(seed)
    sub = p[_subsample(len(p), sample, rng)]
    c0 = sub.mean(0)
    q = sub - c0
    tri = rng.integers(0, len(q), size=(iterations, 3))
    a, b, c = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12 * max(1.0, float(np.abs(q).max()) ** 2)
    if not ok.any():
        raise ValueError("ransac_plane: all samples are degenerate (collinear points)")
    n = n[ok] / norm[ok, None]
    d = -np.sum(n * a[ok], axis=1)
    score = np.zeros(len(n), dtype=np.int64)
    for s in range(0, len(n), 64):  # bounded memory: (sample, 64) distances at a time
        score[s : s + 64] = (np.abs(q @ n[s : s + 64].T + d[s : s + 64]) < threshold).sum(0)
    best = int(np.argmax(score))
    nb, db = n[best], float(d[best] - n[best] @ c0)
    inl = np.abs(p @ nb + db) < threshold
    for _ in range(3):  # least squares on the inliers, then re-select: converges in 1-2 steps
        if inl.sum() < 3:
            break
        nb, db = fit_plane(p[inl])
        new = np.abs(p @ nb + db) < threshold
        if np.array_equal(new, inl):
            break
        inl = new
    return nb, db, inl


def _spheres_from_4(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (M, 3), radii (M,) and validity (M,) of spheres through point quadruples (M, 4, 3)."""
    A = np.concatenate([2 * p, np.ones((*p.shape[:2], 1))], axis=2)
    rhs = (p**2).sum(2)
    det = np.linalg.det(A)
    scale = np.abs(p - p.mean(1, keepdims=True)).max(axis=(1, 2)) ** 3 + 1e-30
    ok = np.abs(det) > 1e-9 * scale
    sol = np.zeros((len(p), 4))
    sol[ok] = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
    c = sol[:, :3]
    r2 = sol[:, 3] + (c**2).sum(1)
    ok &= r2 > 0
    return c, np.sqrt(np.where(ok, r2, 0.0)), ok


def ransac_sphere(
    points: np.ndarray,
    radius: float,
    threshold: float,
    *,
    iterations: int = 2000,
    sample: int = 20000,
    radius_tolerance: float = 0.1,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Sphere of about the nominal ``radius`` among points (N, 3) (stem, plate and all).

    Spheres through point quadruples whose radius is within ``radius_tolerance`` (relative)
    of the nominal one are scored by their points within ``threshold``. Half the quadruples
    are drawn from all the points, half from the ball-sized neighbourhood of a random point:
    where the ball holds a tenth of the points or less (a table seen around it), four points
    drawn from all of them are on the ball once in ten thousand draws, four neighbours of a
    point on the ball most of the time. Returns the best candidate's centre and its inlier
    mask (N,).
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    if len(p) < 4:
        raise ValueError(f"ransac_sphere needs at least 4 points, got {len(p)}")
    rng = np.random.default_rng(seed)
    sub = p[_subsample(len(p), sample, rng)]
    c0 = sub.mean(0)
    q = sub - c0
    n_far = iterations - iterations // 2
    quad = q[rng.integers(0, len(q), size=(n_far, 4))]
    seeds = rng.integers(0, len(q), size=iterations // 2)
    near = cKDTree(q).query_ball_point(q[seeds], r=radius, return_sorted=False)
    local = [np.r_[s, np.asarray(nb)[rng.integers(0, len(nb), 3)]] for s, nb in zip(seeds, near, strict=True)
             if len(nb) >= 4]
    if local:
        quad = np.concatenate([quad, q[np.asarray(local)]])
    c, r, ok = _spheres_from_4(quad)
    ok &= np.abs(r - radius) < radius_tolerance * radius
    if not ok.any():
        raise ValueError(
            f"ransac_sphere: no sphere of radius {radius:g} mm ± {100 * radius_tolerance:g} % "
            f"among {len(p)} points"
        )
    c = c[ok]
    score = np.zeros(len(c), dtype=np.int64)
    for s in range(0, len(c), 64):
        dist = np.linalg.norm(q[:, None, :] - c[None, s : s + 64], axis=2)
        score[s : s + 64] = (np.abs(dist - radius) < threshold).sum(0)
    centre = c[int(np.argmax(score))] + c0
    inl = np.abs(np.linalg.norm(p - centre, axis=1) - radius) < threshold
    return centre, inl
