"""Stripe centre lines: link the centres of one laser in one frame column by column into
traces, trim the ends of each trace, and optionally smooth along it.

Why: where a stripe ends (the edge of a surface, a shadow, the end of the fan) its cross
section is cut off and the centre of the remaining part is biased by up to a pixel or two;
the first and last few columns of every trace are therefore not measurements. Along a trace,
the true centre line of a smooth surface varies smoothly, while speckle makes the centres
scatter from column to column: a Savitzky–Golay fit over a few columns (a local quadratic,
so curvature is kept) trades lateral resolution for precision, which the user chooses.

All functions take parallel arrays (one entry per centre) and return arrays.
"""

from __future__ import annotations

import numpy as np

__all__ = ["blocked_ends", "link_traces", "smooth_along", "trace_position"]


def _keys(frame: np.ndarray, laser: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer column keys (frame, laser, column) and the integer column of each centre."""
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    lasers, lid = np.unique(np.asarray(laser).astype(str), return_inverse=True)
    span = int(col.max() - col.min() + 3) if col.size else 1
    key = (np.asarray(frame, dtype=np.int64) * len(lasers) + lid) * span + (col - col.min() + 1)
    return key, col


def link_traces(
    frame: np.ndarray,
    laser: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    max_step_px: float = 8.0,
    max_kink_px: float = 1.5,
) -> np.ndarray:
    """Index of the centre in the previous column of the same trace (-1 where a trace starts).

    A centre continues a trace if, in the same frame, for the same laser, the previous image
    column holds a centre within ``max_step_px`` rows (a steep stripe moves several rows per
    column); the nearest such centre is taken. A centre is continued by one centre at most,
    the nearest (where two stripes meet, a trace does not fork into both). A link whose step
    differs from the step before it by more than ``max_kink_px`` rows is cut: the stripe
    jumped (an edge, a step), and the two sides are separate traces.
    """
    n = len(u)
    prev = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return prev
    key, _ = _keys(frame, laser, u)
    v = np.asarray(v, dtype=np.float64)
    order = np.lexsort((v, key))
    ks = key[order]
    lo = np.searchsorted(ks, key - 1, side="left")
    hi = np.searchsorted(ks, key - 1, side="right")
    best = np.full(n, np.inf)
    for k in range(int((hi - lo).max(initial=0))):
        cand = lo + k
        ok = cand < hi
        j = order[np.where(ok, cand, 0)]
        d = np.where(ok, np.abs(v[j] - v), np.inf)
        better = (d < best) & (d <= max_step_px)
        prev[better] = j[better]
        best[better] = d[better]
    has = np.flatnonzero(prev >= 0)
    if has.size > 1:  # two centres continuing the same one: the farther starts a trace
        o = has[np.lexsort((best[has], prev[has]))]
        prev[o[1:][prev[o[1:]] == prev[o[:-1]]]] = -1
    # a jump is a link whose step is out of line with the steps on both sides of it
    step = np.where(prev >= 0, v - v[np.maximum(prev, 0)], np.nan)
    nxt = np.full(n, -1, dtype=np.int64)
    nxt[prev[prev >= 0]] = np.flatnonzero(prev >= 0)
    before = np.where(prev >= 0, step[np.maximum(prev, 0)], np.nan)
    after = np.where(nxt >= 0, step[np.maximum(nxt, 0)], np.nan)
    with np.errstate(invalid="ignore"):
        off_before = ~(np.abs(step - before) <= max_kink_px)  # NaN (no neighbour) counts as off
        off_after = ~(np.abs(step - after) <= max_kink_px)
    has_side = np.isfinite(before) | np.isfinite(after)
    jump = (prev >= 0) & has_side & off_before & off_after
    prev[jump] = -1
    return prev


def trace_position(
    prev: np.ndarray, u: np.ndarray, v: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trace id and the distance from the trace's start and to its end, for each centre.

    Distances are in columns, or with ``v`` in pixels along the stripe (columns times
    sqrt(1 + slope^2), the slope being the trace's mean step in rows per column).
    """
    n = len(prev)
    root = np.where(prev >= 0, prev, np.arange(n))
    while True:  # pointer jumping: log2(longest trace) rounds
        nxt = root[root]
        if np.array_equal(nxt, root):
            break
        root = nxt
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    last = col.copy()
    np.maximum.at(last, root, col)
    start, end = (col - col[root]).astype(np.float64), (last[root] - col).astype(np.float64)
    if v is not None and n:
        v = np.asarray(v, dtype=np.float64)
        has = prev >= 0
        steps = np.zeros(n)
        steps[has] = np.abs(v[has] - v[prev[has]])
        total = np.bincount(root, weights=steps, minlength=n)
        count = np.bincount(root, weights=has.astype(np.float64), minlength=n)
        slope = total[root] / np.maximum(count[root], 1.0)
        factor = np.sqrt(1.0 + slope**2)
        start, end = start * factor, end * factor
    return root, start, end


def blocked_ends(
    trace: np.ndarray, frame: np.ndarray, u: np.ndarray, v: np.ndarray,
    block_frame: np.ndarray, block_u: np.ndarray, block_v: np.ndarray, max_step_px: float = 8.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Whether each centre's trace starts / ends against a blocker (per centre, broadcast).

    A trace that stops because the next column holds a blocker near its row (a merged run at
    the crossing of A and B, where both stripes are in one blob) has not reached the end of
    its stripe: its cross-section is not cut off there, the other stripe is beside it.
    """
    n = len(u)
    if n == 0 or len(block_u) == 0:
        return np.zeros(n, bool), np.zeros(n, bool)
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    bcol = np.rint(np.asarray(block_u, dtype=np.float64)).astype(np.int64)
    span = int(max(col.max(), bcol.max())) + 3
    bkey = np.asarray(block_frame, dtype=np.int64) * span + bcol + 1
    order = np.lexsort((np.asarray(block_v, dtype=np.float64), bkey))
    bkey, bv = bkey[order], np.asarray(block_v, dtype=np.float64)[order]
    first = np.full(n, np.iinfo(np.int64).max)
    last = np.full(n, -1)
    np.minimum.at(first, trace, col)
    np.maximum.at(last, trace, col)
    out = []
    for end, du in ((first, -1), (last, 1)):
        at_end = col == end[trace]
        q = np.asarray(frame, dtype=np.int64) * span + col + du + 1
        lo = np.searchsorted(bkey, q, side="left")
        hi = np.searchsorted(bkey, q, side="right")
        near = np.zeros(n, bool)
        for k in range(int((hi - lo).max(initial=0))):
            j = np.minimum(lo + k, bkey.size - 1)
            near |= (lo + k < hi) & (np.abs(bv[j] - v) <= max_step_px)
        hit = np.zeros(n, bool)
        np.logical_or.at(hit, trace, at_end & near)
        out.append(hit[trace])
    return out[0], out[1]


def smooth_along(
    trace: np.ndarray, u: np.ndarray, v: np.ndarray, window: int
) -> tuple[np.ndarray, np.ndarray]:
    """Local quadratic (Savitzky–Golay) smoothing of ``v`` along each trace over ``window`` columns.

    Each centre's row is the value at its column of the least-squares quadratic through the
    centres of its trace within ``window // 2`` columns on either side; near a trace's end the
    window is the part that exists (one-sided at the very end: no noisier than the raw row).
    Returns the smoothed rows and a mask of the centres that had at least three columns to fit
    (the others keep their row and are marked False).
    """
    v = np.asarray(v, dtype=np.float64)
    if window <= 1:
        return v.copy(), np.ones(len(v), dtype=bool)
    if window % 2 == 0:
        raise ValueError(f"the smoothing window must be an odd number of columns, got {window}")
    h = window // 2
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    span = int(col.max() - col.min() + 2 * h + 3) if col.size else 1
    key = trace.astype(np.int64) * span + (col - col.min() + h + 1)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    # moments of the offsets k present in the window, and of the rows there
    m = np.zeros((5, len(v)))
    t = np.zeros((3, len(v)))
    for k in range(-h, h + 1):
        i = np.minimum(np.searchsorted(ks, key + k), max(len(ks) - 1, 0))
        hit = (ks[i] == key + k) if len(ks) else np.zeros(len(v), bool)
        w = hit.astype(np.float64)
        vk = np.where(hit, v[order[i]], 0.0)
        for p_ in range(5):
            m[p_] += w * float(k) ** p_
        for p_ in range(3):
            t[p_] += w * vk * float(k) ** p_
    # value at k = 0 of the quadratic fit: first row of the inverse normal matrix (Cramer)
    s0, s1, s2, s3, s4 = m
    c00 = s2 * s4 - s3 * s3
    c01 = s2 * s3 - s1 * s4
    c02 = s1 * s3 - s2 * s2
    det = s0 * c00 + s1 * c01 + s2 * c02
    ok = (s0 >= 3) & (np.abs(det) > 1e-9)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (c00 * t[0] + c01 * t[1] + c02 * t[2]) / det
    return np.where(ok, out, v), ok
