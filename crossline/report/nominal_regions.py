"""The deviations' statistics and their out-of-tolerance regions (connected clusters).

``deviation_summary`` (step 3 of :mod:`crossline.report.nominal`'s docstring): statistics
of signed deviations and the points beyond tolerance grouped into regions (``_regions``, one
sign at a time), connected within a radius that spans a line scan's gap between stripes
(``line_gap_mm``). Split from ``crossline.report.nominal`` (issue 21.3), which re-exports
``deviation_summary``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["deviation_summary", "line_gap_mm"]


def _regions(
    points: np.ndarray, dev: np.ndarray, mask: np.ndarray, radius: float
) -> list[dict[str, Any]]:
    """Connected clusters (within ``radius``) of the masked points, one sign at a time."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    out: list[dict[str, Any]] = []
    # an excess next to a dent is a second defect, not the same one: cluster each sign alone
    for sel in (mask & (dev < 0), mask & (dev > 0)):
        idx = np.flatnonzero(sel)
        if len(idx) == 0:
            continue
        pairs = cKDTree(points[idx]).query_pairs(radius, output_type="ndarray")
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
        _, label = connected_components(g, directed=False)
        order = np.argsort(label, kind="stable")
        bounds = np.flatnonzero(np.diff(label[order])) + 1
        for members in np.split(idx[order], bounds):
            dv = dev[members]
            a = np.abs(dv)
            j = int(np.argmax(a))
            deep = np.argsort(a, kind="stable")[::-1][: max(1, math.ceil(0.1 * len(a)))]
            out.append({
                "n": len(members),
                "centroid_mm": points[members].mean(0).tolist(),
                "extreme_mm": float(dv[j]),
                "extreme_at_mm": points[members[j]].tolist(),
                "depth_mm": float(np.sign(dv[j]) * np.median(a[deep])),
                # where it is deepest: less noisy than the extreme point, and unlike the
                # centroid not pulled aside where the stripes cross one side of the defect
                "depth_at_mm": points[members[deep]].mean(0).tolist(),
            })
    out.sort(key=lambda g: (-abs(g["extreme_mm"]), g["centroid_mm"]))
    for i, g in enumerate(out, start=1):
        g["id"] = i
    return out


def line_gap_mm(points: np.ndarray, frames: np.ndarray, probes: int = 4000, seed: int = 0) -> float:
    """How far apart a line scan's lines lie: twice the 95th percentile, over sampled points, of
    the distance to the nearest point of another frame (a point between two lines is at most
    half their spacing from one; mm; 0 with fewer than two frames).

    A scan samples densely along each stripe and sparsely across them; a defect seen on
    neighbouring stripes is one defect. The nearest point of another frame is found with trees
    of random halves of the frames (eight draws: any one other frame falls in the probe's
    opposite half at least once with probability 1 - 2^-8)."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(frames).reshape(-1)
    uniq, fi = np.unique(f, return_inverse=True)
    if len(uniq) < 2:
        return 0.0
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(p), min(probes, len(p)), replace=False)
    best = np.full(len(pick), np.inf)
    for _ in range(8):
        half = rng.integers(0, 2, len(uniq)).astype(bool)[fi]
        for side in (False, True):
            mine = np.flatnonzero(half[pick] == side)
            other = p[half != side]
            if len(mine) and len(other):
                d, _ = cKDTree(other).query(p[pick[mine]])
                best[mine] = np.minimum(best[mine], d)
    best = best[np.isfinite(best)]
    return 2.0 * float(np.percentile(best, 95)) if best.size else 0.0


def deviation_summary(
    dev: np.ndarray,
    *,
    tolerance_mm: float,
    points: np.ndarray | None = None,
    n_largest: int = 10,
    cluster_radius_mm: float | None = None,
    max_distance_mm: float | None = None,
    frames: np.ndarray | None = None,
) -> dict[str, Any]:
    """Statistics of signed deviations (mm) and the largest out-of-tolerance regions, JSON-ready.

    Points farther than ``max_distance_mm`` (when given) are not on the part (table,
    fixture) and, with non-finite deviations, are left out of everything but ``n_excluded``.
    With ``points`` (N, 3), the points beyond ±``tolerance_mm`` are grouped into regions:
    connected within ``cluster_radius_mm`` (default: 5 median point spacings, or with
    ``frames`` (N,), each point's frame, the scan's :func:`line_gap_mm` where larger), excess and
    lack apart; each has its centroid, point count, extreme deviation and its location, and
    a robust depth (the median of its 10 % largest deviations, signed) and where that is
    (``depth_at_mm``, the mean of those points). The ``n_largest``
    regions with the largest extreme deviation are returned, largest first (``n_regions``
    counts them all).
    """
    from scipy.spatial import cKDTree

    dev = np.asarray(dev, dtype=np.float64).reshape(-1)
    tol = float(tolerance_mm)
    if not tol > 0:
        raise ValueError("tolerance_mm must be positive")
    keep = np.isfinite(dev)
    if max_distance_mm is not None:
        keep &= np.abs(dev) <= float(max_distance_mm)
    d = dev[keep]
    out: dict[str, Any] = {
        "n": int(d.size),
        "n_excluded": int(dev.size - d.size),
        "tolerance_mm": tol,
        "max_distance_mm": None if max_distance_mm is None else float(max_distance_mm),
    }
    if d.size == 0:
        return out | {"share_within_tolerance": None, "regions": []}
    p025, p50, p975 = np.percentile(d, [2.5, 50.0, 97.5])
    out |= {
        "mean_mm": float(d.mean()),
        "std_mm": float(d.std(ddof=1)) if d.size > 1 else 0.0,
        "rms_mm": float(np.sqrt(np.mean(d**2))),
        "min_mm": float(d.min()),
        "max_mm": float(d.max()),
        "p2_5_mm": float(p025),
        "p50_mm": float(p50),
        "p97_5_mm": float(p975),
        "share_within_tolerance": float(np.mean(np.abs(d) <= tol)),
    }
    if points is None:
        out["regions"] = None
        return out
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) != len(dev):
        raise ValueError(f"points ({len(p)}) and deviations ({len(dev)}) differ in number")
    p = p[keep]
    if cluster_radius_mm is None:
        spacing = 0.0
        if len(p) > 1:
            # the median spacing is as well known from 20 000 points as from millions
            probe = p
            if len(p) > 20_000:
                probe = p[np.random.default_rng(0).choice(len(p), 20_000, replace=False)]
            nn, _ = cKDTree(p).query(probe, k=2)
            spacing = float(np.median(nn[:, 1]))
        radius = 5.0 * spacing
        if frames is not None:
            # a defect that neighbouring stripes cross is one region, however far apart they lie
            gap = line_gap_mm(p, np.asarray(frames).reshape(-1)[keep])
            out["line_gap_mm"] = gap
            radius = max(radius, gap)
    else:
        radius = float(cluster_radius_mm)
    regions = _regions(p, d, np.abs(d) > tol, radius)
    out["cluster_radius_mm"] = radius
    out["n_regions"] = len(regions)
    out["regions"] = regions[: max(0, int(n_largest))]
    return out
