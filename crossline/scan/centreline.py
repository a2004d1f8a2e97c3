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

from crossline.jit import jit

__all__ = ["ROW_OFFSET", "blocked_ends", "half_amplitude_columns", "image_space", "join_traces",
           "link_traces", "smooth_along", "trace_position", "trace_space"]

# where the row-profiled centres' columns start in trace space: beyond any image column, so
# that a steep stripe's trace never meets a column-profiled one (sensors are < 2**17 px wide)
ROW_OFFSET = float(1 << 17)


def trace_space(u: np.ndarray, v: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres as (column, row) of the grid their profiles were taken on, where every stripe
    is a function of an integer column: a centre profiled along its image column (``axis``
    0) keeps ``(u, v)``; one profiled along its row (1: a steep stripe, ``v`` an integer) is
    ``(v + ROW_OFFSET, u)``, so its trace runs down the image rows. Linking, trimming,
    smoothing and the A/B matching work on these; :func:`image_space` turns a row back."""
    steep = np.asarray(axis) == 1
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    return np.where(steep, v + ROW_OFFSET, u), np.where(steep, u, v)


def image_space(u: np.ndarray, v: np.ndarray, axis: np.ndarray,
                row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image ``(u, v)`` of centres whose trace-space row (:func:`trace_space`) is now ``row``
    (e.g. smoothed): the profiled coordinate takes it, the other stays."""
    steep = np.asarray(axis) == 1
    return (np.where(steep, row, np.asarray(u, dtype=np.float64)),
            np.where(steep, np.asarray(v, dtype=np.float64), row))


def _keys(frame: np.ndarray, laser: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer column keys (frame, laser, column) and the integer column of each centre."""
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    lasers, lid = np.unique(np.asarray(laser).astype(str), return_inverse=True)
    span = int(col.max() - col.min() + 3) if col.size else 1
    key = (np.asarray(frame, dtype=np.int64) * len(lasers) + lid) * span + (col - col.min() + 1)
    return key, col


def _link_py(ks: np.ndarray, order: np.ndarray, v: np.ndarray, max_step: float, max_kink: float,
             prev: np.ndarray) -> None:
    """``link_traces`` on keys ``ks`` already in ``order`` (sorted by key); writes ``prev``."""
    n = v.size
    best = np.full(n, np.inf)
    # the centre of key - 1 nearest in row within max_step; ties: the smaller row, then the first
    p0 = -1  # the previous key's group order[p0:p1]
    p1 = -1
    i = 0
    while i < n:
        j = i
        while j < n and ks[j] == ks[i]:
            j += 1
        if p0 >= 0 and ks[p0] == ks[i] - 1:
            for a in range(i, j):
                ia = order[a]
                bd = np.inf
                bi = -1
                for b in range(p0, p1):
                    ib = order[b]
                    d = abs(v[ib] - v[ia])
                    if d < bd or (d == bd and bi >= 0 and v[ib] < v[bi]):
                        bd = d
                        bi = ib
                if bi >= 0 and bd <= max_step:
                    prev[ia] = bi
                    best[ia] = bd
        p0 = i
        p1 = j
        i = j
    # no fork: of two centres continuing the same one, the farther (then the later) starts a trace
    nxt = np.full(n, -1, np.int64)
    for i in range(n):
        q = prev[i]
        if q >= 0:
            k = nxt[q]
            if k < 0 or best[i] < best[k]:
                if k >= 0:
                    prev[k] = -1
                nxt[q] = i
            else:
                prev[i] = -1
    # a jump is a link whose step is out of line with the steps on both sides of it (a side
    # without a link counts as out of line; a link with neither side is kept)
    jump = np.zeros(n, np.bool_)
    for i in range(n):
        q = prev[i]
        if q < 0:
            continue
        step = v[i] - v[q]
        has_side = False
        off_before = True
        off_after = True
        if prev[q] >= 0:
            has_side = True
            off_before = not (abs(step - (v[q] - v[prev[q]])) <= max_kink)
        k = nxt[i]
        if k >= 0:
            has_side = True
            off_after = not (abs(step - (v[k] - v[i])) <= max_kink)
        jump[i] = has_side and off_before and off_after
    for i in range(n):
        if jump[i]:
            prev[i] = -1


_link = jit(_link_py)


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
    order = np.argsort(key, kind="stable")
    _link(key[order], order, np.asarray(v, dtype=np.float64), float(max_step_px), float(max_kink_px),
          prev)
    return prev


def _trace_position_py(prev: np.ndarray, col: np.ndarray, v: np.ndarray, along: bool):
    """:func:`trace_position` on integer columns (``along``: scale by the trace's slope)."""
    n = prev.size
    root = np.full(n, -1, np.int64)
    path = np.empty(n, np.int64)
    for i in range(n):  # follow each chain up to a centre whose trace is known, or its start
        k = 0
        j = i
        while root[j] < 0 and prev[j] >= 0:
            path[k] = j
            k += 1
            j = prev[j]
        r = root[j] if root[j] >= 0 else j
        root[j] = r
        for m in range(k):
            root[path[m]] = r
    last = col.copy()
    for i in range(n):
        if col[i] > last[root[i]]:
            last[root[i]] = col[i]
    start = np.empty(n)
    end = np.empty(n)
    for i in range(n):
        start[i] = float(col[i] - col[root[i]])
        end[i] = float(last[root[i]] - col[i])
    if along and n:
        total = np.zeros(n)
        count = np.zeros(n)
        for i in range(n):
            if prev[i] >= 0:
                total[root[i]] += abs(v[i] - v[prev[i]])
                count[root[i]] += 1.0
        for i in range(n):
            slope = total[root[i]] / max(count[root[i]], 1.0)
            factor = np.sqrt(1.0 + slope**2)
            start[i] = start[i] * factor
            end[i] = end[i] * factor
    return root, start, end


_trace_position = jit(_trace_position_py)


def trace_position(
    prev: np.ndarray, u: np.ndarray, v: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trace id and the distance from the trace's start and to its end, for each centre.

    Distances are in columns, or with ``v`` in pixels along the stripe (columns times
    sqrt(1 + slope^2), the slope being the trace's mean step in rows per column).
    """
    n = len(prev)
    col = np.rint(np.asarray(u, dtype=np.float64)).astype(np.int64)
    vv = np.zeros(n) if v is None else np.asarray(v, dtype=np.float64)
    root, start, end = _trace_position(np.asarray(prev, dtype=np.int64), col, vv, v is not None)
    return root, start, end


def join_traces(
    trace: np.ndarray, along: np.ndarray, u: np.ndarray, v: np.ndarray, *,
    max_gap_px: float = 5.0, max_turn_deg: float = 20.0, max_offset_px: float = 1.5,
    end_points: int = 5,
) -> np.ndarray:
    """Trace ids (per centre) with the traces that continue one another in the image joined.

    A stripe whose slope passes the switch between column and row profiles (a curve on a ball)
    is two traces in trace space (:func:`trace_space`), end to end in the image, often with a
    centre or two between them that link to neither. Two traces of ``end_points`` centres or
    more are joined where an end of one lies within ``max_gap_px`` (image px) of an end of the
    other, ahead of it (off the line of its last centres by ``max_offset_px`` at most, each
    way), and the two run on within ``max_turn_deg``. Where two stripes meet, their ends point
    the same way, or lie side by side: they are not joined. Each end joins one other, the
    nearest. ``along`` orders the centres of a trace (its trace-space column); ``trace`` as
    :func:`trace_position` gives it. Returns, per centre, the smallest trace id of its group.
    """
    trace = np.asarray(trace, dtype=np.int64)
    ids, inv = np.unique(trace, return_inverse=True)
    inv = inv.reshape(-1)
    nt = ids.size
    if nt < 2:
        return trace.copy()
    order = np.lexsort((np.asarray(along, dtype=np.float64), inv))
    first = np.searchsorted(inv[order], np.arange(nt), side="left")
    last = np.searchsorted(inv[order], np.arange(nt), side="right") - 1
    long_ = np.flatnonzero(last - first >= end_points - 1)
    if long_.size < 2:
        return trace.copy()
    xy = np.stack([np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)], axis=1)[order]
    a, b = first[long_], last[long_]
    k = end_points - 1
    pos = np.concatenate([xy[a], xy[b]])  # the long traces' ends, and their outward directions
    out = np.concatenate([xy[a] - xy[a + k], xy[b] - xy[b - k]])
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    out = out / np.where(norm > 0, norm, np.inf)
    owner = np.concatenate([long_, long_])
    gap = pos[None, :, :] - pos[:, None, :]  # from end i to end j
    dist = np.linalg.norm(gap, axis=2)
    cos_turn = np.cos(np.radians(max_turn_deg))
    reach_i = np.einsum("ik,ijk->ij", out, gap)  # how far ahead of end i end j lies
    reach_j = -np.einsum("jk,ijk->ij", out, gap)  # and end i of end j
    off_i = np.abs(out[:, None, 0] * gap[:, :, 1] - out[:, None, 1] * gap[:, :, 0])
    off_j = np.abs(out[None, :, 0] * gap[:, :, 1] - out[None, :, 1] * gap[:, :, 0])
    ok = (dist <= max_gap_px) & (owner[:, None] != owner[None, :]) & (-(out @ out.T) >= cos_turn)
    ok &= (reach_i > 0) & (reach_j > 0) & (off_i <= max_offset_px) & (off_j <= max_offset_px)
    ii, jj = np.nonzero(np.triu(ok, 1))
    parent = np.arange(nt)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    used = np.zeros(pos.shape[0], bool)
    for m in np.argsort(dist[ii, jj], kind="stable"):  # nearest first, an end joins once
        i, j = ii[m], jj[m]
        if used[i] or used[j]:
            continue
        used[i] = used[j] = True
        ra, rb = root(owner[i]), root(owner[j])
        parent[max(ra, rb)] = min(ra, rb)
    group = np.array([root(i) for i in range(nt)])
    return ids[group][inv]


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
    order = np.argsort(bkey, kind="stable")  # any blocker of a key near the row will do
    bkey, bv = bkey[order], np.asarray(block_v, dtype=np.float64)[order]
    q = np.asarray(frame, dtype=np.int64) * span + col + 1
    return _blocked(np.asarray(trace, dtype=np.int64), col, q, np.asarray(v, dtype=np.float64),
                    bkey, bv, float(max_step_px))


@jit
def _blocked(trace, col, q, v, bkey, bv, max_step):  # pragma: no cover - compiled
    """:func:`blocked_ends` on keys: ``q`` each centre's (frame, column) key, ``bkey`` the
    blockers' keys (sorted), ``bv`` their rows."""
    n = col.size
    first = np.full(n, np.iinfo(np.int64).max)
    last = np.full(n, -1)
    for i in range(n):
        first[trace[i]] = min(first[trace[i]], col[i])
        last[trace[i]] = max(last[trace[i]], col[i])
    start_hit = np.zeros(n, np.bool_)
    end_hit = np.zeros(n, np.bool_)
    for i in range(n):
        for side in range(2):  # the column before the trace's first, after its last
            if side == 0 and col[i] != first[trace[i]]:
                continue
            if side == 1 and col[i] != last[trace[i]]:
                continue
            key = q[i] - 1 if side == 0 else q[i] + 1
            j = np.searchsorted(bkey, key)
            while j < bkey.size and bkey[j] == key:
                if abs(bv[j] - v[i]) <= max_step:
                    if side == 0:
                        start_hit[trace[i]] = True
                    else:
                        end_hit[trace[i]] = True
                    break
                j += 1
    out_start = np.empty(n, np.bool_)
    out_end = np.empty(n, np.bool_)
    for i in range(n):
        out_start[i] = start_hit[trace[i]]
        out_end[i] = end_hit[trace[i]]
    return out_start, out_end


def _local_quadratic_py(ks: np.ndarray, order: np.ndarray, v: np.ndarray, h: int,
                        out: np.ndarray, ok: np.ndarray) -> None:
    """Value at each key of the least-squares quadratic through v at keys within +-h (sorted).

    Centres whose window holds fewer than three keys, or a singular one, are left as they are.
    """
    n = ks.size
    lo = 0
    for a in range(n):
        k0 = ks[a]
        while ks[lo] < k0 - h:
            lo += 1
        s0 = s1 = s2 = s3 = s4 = 0.0
        t0 = t1 = t2 = 0.0
        b = lo
        while b < n and ks[b] <= k0 + h:
            if b == lo or ks[b] != ks[b - 1]:  # one centre per key, as a column holds one
                k = float(ks[b] - k0)
                vk = v[order[b]]
                s0 += 1.0
                s1 += k
                s2 += k * k
                s3 += k * k * k
                s4 += k * k * k * k
                t0 += vk
                t1 += vk * k
                t2 += vk * (k * k)
            b += 1
        # value at k = 0 of the quadratic fit: first row of the inverse normal matrix (Cramer)
        c00 = s2 * s4 - s3 * s3
        c01 = s2 * s3 - s1 * s4
        c02 = s1 * s3 - s2 * s2
        det = s0 * c00 + s1 * c01 + s2 * c02
        if s0 >= 3 and abs(det) > 1e-9:
            out[order[a]] = (c00 * t0 + c01 * t1 + c02 * t2) / det
            ok[order[a]] = True


_local_quadratic = jit(_local_quadratic_py)


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
    out = v.copy()
    ok = np.zeros(len(v), dtype=bool)
    _local_quadratic(key[order], order, v, h, out, ok)
    return out, ok


def half_amplitude_columns(window: int) -> float:
    """Period, in columns, of the ripple that :func:`smooth_along` passes at half its amplitude.

    The lateral resolution the smoothing leaves along the stripe: the frequency response of
    the local quadratic over ``window`` columns (Savitzky–Golay, centred) falls to 0.5 at
    this period (5.2 columns for 7; inf for 1 or 3, which leave every column as it is).
    """
    if window <= 3:
        return float("inf")
    from scipy.optimize import brentq
    from scipy.signal import savgol_coeffs

    c = savgol_coeffs(window, 2)
    k = np.arange(window) - window // 2
    # the response falls monotonically from 1 at f = 0 to below 0.5 by the Nyquist frequency
    f = brentq(lambda f: float(np.cos(2.0 * np.pi * f * k) @ c) - 0.5, 1e-9, 0.5, xtol=1e-12)
    return float(1.0 / f)
