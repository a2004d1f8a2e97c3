"""Neighbourhood work on big clouds one slab at a time, with the same answer as on the whole.

A 50 000-frame scan holds tens of millions of points; a k-d tree, the neighbour lists and
the 3x3 covariances of all of them at once need several GB. Every per-point question the
fused cloud asks (its k nearest neighbours for the outlier test, its neighbours within a
radius for the normal) only looks a bounded distance around the point. So the cloud is cut
along its longest axis into slabs of about ``SLAB_POINTS`` points each; a slab answers for
its own points ("core") and may look at every point within ``halo`` mm of it along that
axis ("reach"). Wherever the neighbourhood lies within the halo the answer is the one the
whole cloud would give; the k-nearest search checks that and widens the reach for the few
points (isolated outliers) whose k-th neighbour lies farther.

A cloud of up to ``SLAB_POINTS`` points is one slab, in its own order: nothing changes for
small scans.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

__all__ = ["SLAB_POINTS", "Slab", "cuts", "knn_mean_distance", "longest_axis", "slabs",
           "statistical_inliers"]

SLAB_POINTS = 1_000_000  # points a slab answers for: ~0.25 GB of neighbour work at a time
_QUERY_ROWS = 200_000  # rows of a k-nearest query at once (k distances and indices each)


@dataclass(frozen=True)
class Slab:
    """One slab: the indices of the points it answers for (``core``) and of those it may look
    at (``reach``: the core and its halo, sorted along ``axis``; ``core`` is
    ``reach[start:stop]``), and the reach's extent along that axis (±inf at the cloud's ends)."""

    core: np.ndarray
    reach: np.ndarray
    start: int
    stop: int
    axis: int
    lo: float
    hi: float


def slabs(points: np.ndarray, halo: float, target: int = SLAB_POINTS) -> Iterator[Slab]:
    """Slabs of about ``target`` points along the cloud's longest axis, each with the points
    within ``halo`` mm of it; one slab (the cloud in its order) when it holds ``target`` or
    fewer points."""
    p = np.asarray(points)
    n = len(p)
    if n <= target:
        idx = np.arange(n)
        yield Slab(idx, idx, 0, n, 0, -np.inf, np.inf)
        return
    axis = int(np.argmax(np.ptp(p, axis=0)))
    order = np.argsort(p[:, axis], kind="stable")
    if n < 2**31:
        order = order.astype(np.int32)  # 4 B a point less, held while the slabs are worked
    xs = p[order, axis]
    k = -(-n // target)
    bounds = np.linspace(0, n, k + 1).round().astype(np.int64)
    # every slab's reach found now, so that the sorted coordinates go before the work starts
    cuts = []
    for lo, hi in pairwise(bounds.tolist()):
        a = int(np.searchsorted(xs, xs[lo] - halo, "left"))
        b = int(np.searchsorted(xs, xs[hi - 1] + halo, "right"))
        cuts.append((lo, hi, a, b, -np.inf if a == 0 else float(xs[lo] - halo),
                     np.inf if b == n else float(xs[hi - 1] + halo)))
    del xs
    for lo, hi, a, b, x0, x1 in cuts:
        yield Slab(order[lo:hi], order[a:b], lo - a, hi - a, axis, x0, x1)


def longest_axis(points: np.ndarray, index: np.ndarray | None = None,
                 block: int = 1 << 20) -> int:
    """The axis (0, 1, 2) of the largest extent of ``points[index]`` (all without ``index``),
    read a block at a time (no copy of a long scan's points)."""
    p = np.asarray(points)
    n = len(p) if index is None else len(index)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for a in range(0, n, block):
        q = p[a:a + block] if index is None else p[index[a:a + block]]
        lo, hi = np.minimum(lo, q.min(0)), np.maximum(hi, q.max(0))
    return int(np.argmax(hi - lo))


def cuts(x: np.ndarray, target: int, sample: int = 200_000) -> np.ndarray:
    """Edges (k + 1,) that cut the coordinates ``x`` into k = ceil(N / ``target``) slabs of
    about ``target`` points each (quantiles of an even sample of ``x``; -inf and +inf at the
    ends): slab i is ``edges[i] <= x < edges[i + 1]``, without a sort of the whole scan."""
    x = np.asarray(x)
    k = max(1, -(-len(x) // max(int(target), 1)))
    edges = np.quantile(x[::max(1, len(x) // sample)], np.linspace(0, 1, k + 1)).astype(np.float64)
    edges[0], edges[-1] = -np.inf, np.inf
    return edges


def knn_mean_distance(points: np.ndarray, k: int, halo: float, *, threads: int = 1,
                      target: int = SLAB_POINTS) -> np.ndarray:
    """Mean distance (N,) of each point to its ``k`` nearest points, itself included (as
    Open3D's statistical outlier removal counts them), summed nearest first.

    Slab by slab; a point whose k-th neighbour is farther than the edge of its slab's reach
    is searched again in a reach widened to that distance, so the result is the whole
    cloud's.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    out = np.empty(len(p))
    k = min(int(k), len(p))
    for s in slabs(p, halo, target):
        sub = p[s.reach]
        tree = cKDTree(sub)
        core = sub[s.start:s.stop]
        far, kth = [], []
        for r0 in range(0, len(core), _QUERY_ROWS):
            q = core[r0:r0 + _QUERY_ROWS]
            d, _ = tree.query(q, k=k, workers=threads)
            d = d.reshape(len(q), k)
            out[s.core[r0:r0 + len(q)]] = _sequential_mean(d)
            edge = np.minimum(q[:, s.axis] - s.lo, s.hi - q[:, s.axis])
            f = np.flatnonzero(d[:, -1] > edge)
            far.append(r0 + f)
            kth.append(d[f, -1])
        del tree, sub
        unsure = np.concatenate(far) if far else np.zeros(0, np.int64)
        if len(unsure):
            # isolated points: their k-th neighbour lies beyond the halo; look that far
            idx = s.core[unsure]
            # the true k-th distance is at most the one found among fewer points
            reach = float(np.max(np.concatenate(kth)))
            x = p[:, s.axis]
            lo, hi = p[idx, s.axis].min() - reach, p[idx, s.axis].max() + reach
            wide = np.flatnonzero((x >= lo) & (x <= hi))
            d, _ = cKDTree(p[wide]).query(p[idx], k=k, workers=threads)
            out[idx] = _sequential_mean(d.reshape(len(idx), k))
    return out


def _sequential_mean(d: np.ndarray) -> np.ndarray:
    """Row means of (M, k) distances summed left to right (nearest first), as a C++
    ``std::accumulate`` sums them: the same rounding, so the same points fall either side of
    a threshold."""
    acc = np.zeros(len(d))
    for j in range(d.shape[1]):
        acc += d[:, j]
    return acc / d.shape[1]


def statistical_inliers(points: np.ndarray, neighbours: int, std_ratio: float, halo: float, *,
                        threads: int = 1, target: int = SLAB_POINTS) -> np.ndarray:
    """Mask (N,) of the points kept by the statistical outlier test (Open3D's
    ``remove_statistical_outlier``): mean distance to the ``neighbours`` nearest points
    (itself included) above 0 and below the cloud's mean of it plus ``std_ratio`` standard
    deviations (over the points where it is above 0)."""
    m = knn_mean_distance(points, neighbours, halo, threads=threads, target=target)
    valid = m > 0
    n = int(valid.sum())
    if n < 2:
        return valid
    mean = float(np.sum(m[valid])) / n
    std = float(np.sqrt(np.sum((m[valid] - mean) ** 2) / (n - 1)))
    return valid & (m < mean + std_ratio * std)
