"""Where the A and B stripes of a scan cross: the gaps the pose refinement is fitted to.

``find_crossings`` orders the points by stripe (``_stripes``), seeds each pair of an A and a
B stripe at their closest points, fits both stripes locally by quadratic curves
(``_curves``) and takes the closest approach of the two curves (``_closest``): the crossing
point, its normal and the gap along it, in a :class:`Crossings`; ``usable_centres`` says
which centres may make crossings at all. Split from ``crossline.scan.refine`` (issue 21.3),
which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from crossline.tiles import cuts, longest_axis

__all__ = ["Crossings", "find_crossings", "usable_centres"]

HALF_MM = 0.6  # stripe fitted either side of a crossing, mm
MIN_ANGLE_DEG = 30.0  # stripes crossing at a smaller angle are not used
MIN_SPACINGS = 6  # a crossing's stripe curves reach at least this many point spacings either side
_QUERY_ROWS = 500_000  # seeds searched for B neighbours at a time
MAX_WIDTH_RATIO = 2.0  # centres of column cuts longer than this x their laser's median: no crossings
# points searched at once; more are searched a slab of space at a time, so that the search's
# own arrays (~60 B a point: stripe order, k-d tree) stay a few hundred MB on a long scan
SLAB_POINTS = 4_000_000
# a seed whose stripe is this much sparser about it than its laser's median spacing has its
# window refitted from its own spacing (see _search)
SPARSE_FACTOR = 1.5
# ... up to this many times its laser's window: over a longer stretch a curved stripe is no
# quadratic, and the exact ball of tests/test_refine.py holds its crossings on its surface
# up to this growth, not at twice its window
MAX_GROWTH = 1.5


@dataclass(frozen=True)
class Crossings:
    """Where an A stripe of one frame crosses a B stripe of another (K crossings)."""

    frame_a: np.ndarray  # (K,) index into the refinement's frames of the A stripe's frame
    frame_b: np.ndarray  # (K,) likewise for the B stripe
    x: np.ndarray  # (K, 3) crossing point, base frame
    n: np.ndarray  # (K, 3) unit surface normal (A tangent x B tangent), towards the camera
    gap: np.ndarray  # (K,) A curve minus B curve along n, mm
    # (K,) the gap's noise per unit point noise: root of the two fits' prediction variances
    sigma: np.ndarray
    angle: np.ndarray  # (K,) crossing angle between the stripes, rad
    counts: dict[str, int] = field(default_factory=dict)  # candidates lost at each step


def usable_centres(laser: np.ndarray, width: np.ndarray,
                   max_ratio: float = MAX_WIDTH_RATIO) -> np.ndarray:
    """Centres (N,) bool whose column cut is at most ``max_ratio`` x their laser's median cut.

    A cut much longer than its laser's typical one crosses the stripe where it runs steeply
    through the column (or two stripes merged), and a centre fitted along the column is
    biased there, several times more than the centres of shorter cuts
    (``python benchmarks/bench_refine_bias.py`` prints the centres' mean and RMS error in px,
    along the column, against the true centre line by cut length). The Gaussian extractor's
    fit across steep stripes (``stripes.fit_across``) removes most of that bias, and with it
    this filter hardly changes the refined ball (docs/method.md, pose refinement); it stays
    for the other extractors and for merged stripes. Such centres may still be measured
    points, but must not decide a crossing. ``max_ratio`` 0 (or inf) keeps all; a NaN width is kept.
    """
    lab = np.asarray(laser)
    w = np.asarray(width)
    if w.dtype.kind != "f":
        w = w.astype(np.float64)
    keep = np.ones(len(w), bool)
    if not max_ratio or not np.isfinite(max_ratio):
        return keep
    # a long scan's widths as they are (float32: 4 B a point), each laser's copied once
    codes = np.flatnonzero(np.bincount(lab)) if lab.dtype.kind == "u" and len(lab) else np.unique(lab)
    for code in codes:
        sel = lab == code
        ws = w[sel]
        known = ws[np.isfinite(ws)]
        if known.size:
            keep[sel] = ~(ws > max_ratio * float(np.median(known, overwrite_input=True)))
    return keep


def _stripes(frame_pos: np.ndarray, laser: np.ndarray, p: np.ndarray,
             subset: np.ndarray | None = None):
    """Order points by stripe (frame, laser), then along the stripe's principal direction.

    ``frame_pos`` and ``laser`` are those of ``p[subset]`` (all of ``p`` without ``subset``).
    Returns the order (N,), stripe id of each ordered point, and per stripe its start and end
    in the ordered arrays.
    """
    runs = _runs(frame_pos, laser)
    if runs is None:  # frames out of order: one stable sort of the whole scan by stripe
        key = frame_pos.astype(np.int64) * 4 + laser.astype(np.int64)
        perm = np.argsort(key, kind="stable")
        key = key[perm]
        starts = np.flatnonzero(np.diff(key, prepend=key[0] - 1)) if len(key) else []
        runs = np.concatenate([starts, [len(key)]]).astype(np.int64), perm
    return _stripes_in_runs(runs, p, subset)


def _runs(frame_pos: np.ndarray, laser: np.ndarray,
          block: int = 1 << 20) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Where the points come frame after frame (as triangulate writes them; the lasers may
    mix within a frame): the start of each stripe (frame, laser) and the end of the last
    (S + 1,) in the points sorted by stripe, and that stable sort (None: already in it).
    None where the frames are out of order. A block of whole frames at a time: no key array
    or sort of a long scan."""
    n = len(frame_pos)
    fp = frame_pos
    if n == 0:
        return np.zeros(1, np.int64), None
    # blocks of whole frames, about ``block`` points each
    cuts = [0]
    for a in range(block, n, block):
        c = int(np.searchsorted(fp, fp[a], "left"))
        if c > cuts[-1]:
            cuts.append(c)
    cuts.append(n)
    perm = None
    starts = []
    for a, b in pairwise(cuts):
        f = fp[a:b]
        if (np.diff(f) < 0).any() or (b < n and fp[b] < f[-1]):
            return None
        key = f.astype(np.int64) * 4 + laser[a:b]
        if (np.diff(key) < 0).any():  # the lasers mix within a frame: a stable sort by stripe
            if perm is None:
                perm = np.arange(n, dtype=np.int32 if n < 2**31 else np.int64)
            o = np.argsort(key, kind="stable")
            perm[a:b] = a + o
            key = key[o]
        starts.append(a + np.flatnonzero(np.diff(key, prepend=key[0] - 1)))
    return np.concatenate([*starts, [n]]).astype(np.int64), perm


def _stripes_in_runs(runs: tuple[np.ndarray, np.ndarray | None], p: np.ndarray,
                     subset: np.ndarray | None, block: int = 1 << 20):
    """:func:`_stripes` where the points come frame after frame (``runs``, from :func:`_runs`):
    the same sums, axes and order, worked out a block of whole stripes at a time (each
    stripe's points in their own order, its sums in one ``bincount``, so bit for bit), with no
    per-point temporaries of the whole scan; the stripe ids as int32 where they fit."""
    bounds, perm = runs
    start, end = bounds[:-1], bounds[1:]
    S, n = len(start), int(bounds[-1])
    cnt = end - start
    itype = np.int32 if max(n, S) < 2**31 else np.int64
    sid = np.repeat(np.arange(S, dtype=itype), cnt)
    order = np.empty(n, dtype=itype)
    # blocks of whole stripes, about ``block`` points each
    edges = np.unique(np.concatenate([[0], np.searchsorted(bounds, np.arange(block, n, block)),
                                      [S]]))
    for s0, s1 in zip(edges[:-1].tolist(), edges[1:].tolist(), strict=True):
        a, b = int(bounds[s0]), int(bounds[s1])
        idx = np.arange(a, b) if perm is None else perm[a:b]  # positions in the given order
        q = p[idx if subset is None else subset[idx]]
        k = sid[a:b] - s0
        c = cnt[s0:s1]
        mean = np.stack([np.bincount(k, q[:, i], s1 - s0) for i in range(3)], 1) / c[:, None]
        q = [q[:, i] - mean[k, i] for i in range(3)]
        C = np.empty((s1 - s0, 3, 3))
        for i in range(3):
            for j in range(i, 3):
                C[:, i, j] = C[:, j, i] = np.bincount(k, q[i] * q[j], s1 - s0)
        axis = np.linalg.eigh(C)[1][:, :, 2]
        along = q[0] * axis[k, 0]
        for i in (1, 2):
            along += q[i] * axis[k, i]
        order[a:b] = idx[np.lexsort((along, k))]
    return order, sid, start, end


def _curves(p: np.ndarray, seeds: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            half_mm: float, width: int):
    """Quadratic space curves x(s) = c0 + c1 s + c2 s^2 fitted along a stripe around each seed.

    ``p`` are the ordered points, ``seeds`` positions in it, ``lo``/``hi`` the stripe's
    bounds; the window is the stripe's points within ``half_mm`` (3-D; one, or one per seed)
    of the seed among the
    ``width`` neighbours either side in stripe order; ``s`` is the distance along the
    window's principal direction. Returns c (K, 3, 3) with rows c0, c1, c2, the inverse
    normal matrix (K, 3, 3) (the prediction variance of the fit) and whether it is usable
    (enough points, on both sides of the seed).
    """
    off = np.arange(-width, width + 1)
    idx = seeds[:, None] + off[None, :]
    inside = (idx >= lo[:, None]) & (idx < hi[:, None])
    idx = np.clip(idx, lo[:, None], hi[:, None] - 1)
    d = p[idx] - p[seeds][:, None, :]  # (K, W, 3), relative to the seed for conditioning
    half_mm = np.broadcast_to(np.asarray(half_mm, dtype=np.float64), seeds.shape)[:, None]
    m = inside & (np.sum(d * d, axis=2) <= half_mm * half_mm)
    w = m.astype(np.float64)
    n = w.sum(1)
    mu = np.matmul(w[:, None, :], d)[:, 0] / np.maximum(n, 1)[:, None]
    dq = (d - mu[:, None, :]) * w[:, :, None]
    t0 = np.linalg.eigh(np.matmul(np.swapaxes(dq, 1, 2), dq))[1][:, :, 2]
    s = np.matmul(d, t0[:, :, None])[:, :, 0]
    M = np.stack([w, s * w, s * s * w], axis=2)  # (K, W, 3), masked rows are zero
    A = np.matmul(np.swapaxes(M, 1, 2), M)
    s_in = np.where(m, s, np.nan)
    with np.errstate(all="ignore"):
        ok = ((n >= 8) & (np.nanmin(s_in, 1) < -0.4 * half_mm[:, 0])
              & (np.nanmax(s_in, 1) > 0.4 * half_mm[:, 0]))
    A[~ok] = np.eye(3)
    Ainv = np.linalg.inv(A)
    c = np.matmul(Ainv, np.matmul(np.swapaxes(M, 1, 2), d))
    c[:, 0, :] += p[seeds]
    return c, Ainv, ok


def _closest(ca: np.ndarray, cb: np.ndarray, iters: int = 5):
    """Closest points of pairs of quadratic curves (Gauss-Newton from s = r = 0)."""
    K = len(ca)
    s = np.zeros(K)
    r = np.zeros(K)
    for _ in range(iters):
        xa = ca[:, 0] + s[:, None] * ca[:, 1] + (s * s)[:, None] * ca[:, 2]
        xb = cb[:, 0] + r[:, None] * cb[:, 1] + (r * r)[:, None] * cb[:, 2]
        ta = ca[:, 1] + 2 * s[:, None] * ca[:, 2]
        tb = cb[:, 1] + 2 * r[:, None] * cb[:, 2]
        d = xa - xb
        J = np.stack([ta, -tb], axis=2)  # (K, 3, 2)
        JtJ = np.einsum("kia,kib->kab", J, J)
        det = JtJ[:, 0, 0] * JtJ[:, 1, 1] - JtJ[:, 0, 1] ** 2
        g = np.einsum("kia,ki->ka", J, d)
        safe = np.abs(det) > 1e-12
        det = np.where(safe, det, 1.0)
        ds = (JtJ[:, 1, 1] * g[:, 0] - JtJ[:, 0, 1] * g[:, 1]) / det
        dr = (JtJ[:, 0, 0] * g[:, 1] - JtJ[:, 0, 1] * g[:, 0]) / det
        s = np.where(safe, s - ds, s)
        r = np.where(safe, r - dr, r)
    xa = ca[:, 0] + s[:, None] * ca[:, 1] + (s * s)[:, None] * ca[:, 2]
    xb = cb[:, 0] + r[:, None] * cb[:, 1] + (r * r)[:, None] * cb[:, 2]
    ta = ca[:, 1] + 2 * s[:, None] * ca[:, 2]
    tb = cb[:, 1] + 2 * r[:, None] * cb[:, 2]
    return s, r, xa, xb, ta, tb


class _Ordered:
    """Points ``p[index]`` read on demand: ``o[i]`` is ``p[index[i]]`` for an index array ``i``."""

    def __init__(self, p: np.ndarray, index: np.ndarray) -> None:
        self.p, self.index = p, index

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: np.ndarray) -> np.ndarray:
        return self.p[self.index[i]]

    def steps(self, block: int = 1 << 20) -> np.ndarray:
        """Distances (N - 1,) between neighbours in the order, a block at a time (the same
        sums, in the same order, as over whole columns)."""
        n = len(self.index)
        out = np.empty(max(n - 1, 0))
        for a in range(0, n - 1, block):
            q = self.p[self.index[a:a + block + 1]]
            d = np.diff(q[:, 0]) ** 2
            for i in (1, 2):
                d += np.diff(q[:, i]) ** 2
            out[a:a + len(d)] = np.sqrt(d)
        return out


def _local_spacing(po: _Ordered, seeds: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   k: int = 4) -> np.ndarray:
    """Median distance (K,) between neighbours in stripe order among the ``k`` either side of
    each seed, within its stripe's bounds ``lo``/``hi``."""
    off = np.arange(-k, k)
    i = seeds[:, None] + off[None, :]
    ok = (i >= lo[:, None]) & (i + 1 < hi[:, None])
    i = np.clip(i, lo[:, None], np.maximum(hi[:, None] - 2, lo[:, None]))
    # a stripe of one point clips to it, and its i + 1 may be past the last point: masked
    # below, but it must still be read
    d = np.where(ok, np.linalg.norm(po[np.minimum(i + 1, len(po) - 1)] - po[i], axis=2), np.nan)
    out = np.full(len(seeds), np.nan)  # a stripe of one point has no spacing
    some = ok.any(1)
    out[some] = np.nanmedian(d[some], axis=1)
    return out


def _spacings(po: _Ordered, sid: np.ndarray, lo_: np.ndarray) -> tuple[float, dict[int, float]]:
    """Median distance (mm) between neighbouring points of a stripe: over both lasers, and
    each laser's own (``po`` the points in stripe order, ``sid`` their stripes, ``lo_`` their
    laser codes)."""
    # distance between neighbours in the order, a column at a time (no (N, 3) temporaries)
    step = po.steps()
    along = sid[1:] == sid[:-1]
    # medians of the masked copies, sorted in place (np.median would copy each once more)
    spacing = float(np.median(step[along], overwrite_input=True)) if along.any() else 0.05
    # each laser's own point spacing: a stripe that runs steeply through the image, or meets
    # the surface at a grazing angle, is sampled more sparsely than the other, by a factor of
    # a few on some rigs (docs/method.md, pose refinement)
    sp = {}
    for code in (1, 2):
        m = along & (lo_[1:] == code)
        sp[code] = float(np.median(step[m], overwrite_input=True)) if m.any() else spacing
    return spacing, sp


def _windows(spacing: float, sp: dict[int, float], half_mm: float,
             radius_mm: float | None) -> tuple[float, dict[int, float]]:
    """The seeds' search radius and each laser's half window (mm) for these point spacings."""
    if radius_mm is None:
        radius_mm = max(0.1, 3.0 * spacing, sp[1], sp[2])
    # a quadratic needs its points: where a stripe is sampled sparsely (a camera of coarse
    # resolution, or the steeper laser) its window grows to MIN_SPACINGS of them either side,
    # else a HALF_MM window holds too few and no crossing of such a rig is ever fitted
    return radius_mm, {code: max(half_mm, MIN_SPACINGS * sp[code]) for code in (1, 2)}


def _by_slabs(frame_pos: np.ndarray, laser: np.ndarray, points: np.ndarray,
              viewpoints: np.ndarray, *, half_mm: float, radius_mm: float | None,
              min_angle_deg: float, threads: int, subset: np.ndarray | None,
              slab_points: int) -> Crossings:
    """:func:`find_crossings` a slab of space at a time: slabs across the points' longest
    extent, about ``slab_points`` each, each searched with a margin that holds every stripe
    window of a crossing in it; a crossing belongs to the slab whose core holds it.

    The point spacings (hence the windows) are taken once, from the stripes of a sample of
    whole frames, so that every slab fits its curves as the whole scan's search would.
    """
    p = np.asarray(points, dtype=np.float64)
    idx = np.arange(len(p), dtype=np.int64) if subset is None else np.asarray(subset)
    n = len(idx)
    fp_all, lab_all = np.asarray(frame_pos), np.asarray(laser)
    if fp_all.dtype.kind not in "iu" or lab_all.dtype.kind not in "iu":
        raise ValueError("frame_pos and laser must be integer arrays")
    # the spacings from every k-th frame's stripes, about one slab of points
    every = max(1, -(-n // slab_points))
    fp = fp_all if subset is None else fp_all[idx]
    sample = idx[fp % every == 0]
    del fp
    if len(sample) < 16:
        sample = idx
    order, sid, _, _ = _stripes(fp_all[sample], lab_all[sample], p, sample)
    spacing, sp = _spacings(_Ordered(p, sample[order]), sid, lab_all[sample][order])
    del order, sid, sample
    radius, half = _windows(spacing, sp, half_mm, radius_mm)
    # a crossing's seeds lie within half a window of it, their windows a whole one further
    margin = 2.0 * max(half.values()) + radius
    axis = longest_axis(p, idx)
    c = np.empty(n, np.float32)  # the points' coordinate across the slabs (mm; 4 B a point)
    for a in range(0, n, 1 << 20):
        c[a:a + (1 << 20)] = p[idx[a:a + (1 << 20)], axis]
    edges = cuts(c, slab_points)
    nslab = len(edges) - 1
    parts: list[Crossings] = []
    slab_of: list[np.ndarray] = []
    for k in range(nslab):
        e0, e1 = edges[k], edges[k + 1]
        sel = idx[(c >= e0 - margin) & (c < e1 + margin)]
        cr = _search(fp_all, lab_all, p, viewpoints, half_mm=half_mm, radius_mm=radius,
                     min_angle_deg=min_angle_deg, threads=threads, subset=sel,
                     spacings=(spacing, sp))
        del sel
        core = np.flatnonzero((cr.x[:, axis] >= e0) & (cr.x[:, axis] < e1))
        parts.append(cr)
        slab_of.append(core)
    del c
    take = [np.concatenate([getattr(cr, f)[k] for cr, k in zip(parts, slab_of, strict=True)])
            for f in ("frame_a", "frame_b", "x", "n", "gap", "sigma", "angle")]
    slab = np.concatenate([np.full(len(k), i) for i, k in enumerate(slab_of)])
    # a crossing on a slab's edge may come from both neighbours with slightly different seeds:
    # keep the lower slab's
    pair = take[0] * (int(take[1].max(initial=0)) + 1) + take[1]
    o = np.lexsort((slab, pair))
    dup = np.zeros(len(o), bool)
    near = 2 * max(half.values())
    for lag in (1, 2, 3):
        a, b = o[:-lag], o[lag:]
        dup[b] |= ((pair[b] == pair[a]) & (slab[b] != slab[a]) & ~dup[a]
                   & (np.linalg.norm(take[2][b] - take[2][a], axis=1) < near))
    keep = np.sort(np.flatnonzero(~dup))
    counts = {key: sum(cr.counts.get(key, 0) for cr in parts) for key in ("seeds", "fitted", "kept")}
    counts.update(unique=len(keep), slabs=nslab)
    return Crossings(*(t[keep] for t in take), counts)


def _closest_per_cell(x: np.ndarray, pair: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Indices of the closest candidate (least ``dist``, the first on a tie) of each stripe
    ``pair`` in each 2 mm cell of its A point ``x`` (N, 3), ordered by pair, then cell."""
    if len(x) == 0:
        return np.zeros(0, np.int64)
    cell = np.floor(x / 2.0).astype(np.int64)
    cell -= cell.min(0)
    dims = cell.max(0) + 1
    ck = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    o = np.lexsort((dist, ck, pair))
    first = np.ones(len(o), bool)
    first[1:] = (pair[o][1:] != pair[o][:-1]) | (ck[o][1:] != ck[o][:-1])
    return o[first]


def find_crossings(
    frame_pos: np.ndarray,
    laser: np.ndarray,
    points: np.ndarray,
    viewpoints: np.ndarray,
    *,
    half_mm: float = HALF_MM,
    radius_mm: float | None = None,
    min_angle_deg: float = MIN_ANGLE_DEG,
    threads: int = 1,
    subset: np.ndarray | None = None,
    slab_points: int = SLAB_POINTS,
) -> Crossings:
    """Every crossing of an A stripe with a B stripe (of any frame, the same one included).

    ``frame_pos`` (N,) is each point's frame as an index 0..F-1, ``laser`` (N,) its laser
    code (1 = A, 2 = B), ``viewpoints`` (F, 3) the camera centre of each frame (orients the
    normals). Candidates are A points (every other one along the stripe) with a B point
    within ``radius_mm`` (default: 3 point spacings, at least 0.1 mm and one spacing of the
    sparser laser); each pair of stripes keeps its closest candidate per 2 mm cell, the two
    stripes are fitted locally by quadratic curves over ``half_mm`` either side (at least
    ``MIN_SPACINGS`` of that laser's point spacings) and the crossing is the closest approach
    of the two curves; it is kept if it lies within half a window of both seeds, the
    stripes cross at ``min_angle_deg`` or more and the gap is under ``radius_mm``.
    ``subset`` (indices) restricts the search to those points, as passing ``points[subset]``
    (and the others likewise) would, without copies of a long scan's arrays. More than
    ``slab_points`` points are searched a slab of space at a time (:func:`_by_slabs`): the
    search's own arrays (stripe order, k-d tree) then exist for one slab, not the whole scan.
    """
    n = len(points) if subset is None else len(subset)
    if n > max(int(slab_points), 1):
        return _by_slabs(frame_pos, laser, points, viewpoints, half_mm=half_mm,
                         radius_mm=radius_mm, min_angle_deg=min_angle_deg, threads=threads,
                         subset=subset, slab_points=int(slab_points))
    return _search(frame_pos, laser, points, viewpoints, half_mm=half_mm, radius_mm=radius_mm,
                   min_angle_deg=min_angle_deg, threads=threads, subset=subset)


def _search(
    frame_pos: np.ndarray,
    laser: np.ndarray,
    points: np.ndarray,
    viewpoints: np.ndarray,
    *,
    half_mm: float,
    radius_mm: float | None,
    min_angle_deg: float,
    threads: int,
    subset: np.ndarray | None,
    spacings: tuple[float, dict[int, float]] | None = None,
) -> Crossings:
    """:func:`find_crossings` on the points at once; ``spacings`` (all lasers', and each
    laser's median point spacing along a stripe, mm) if already known for the whole scan."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    fp = np.asarray(frame_pos)
    lab = np.asarray(laser)
    if fp.dtype.kind not in "iu" or lab.dtype.kind not in "iu":
        raise ValueError("frame_pos and laser must be integer arrays")
    if subset is not None:
        fp, lab = fp[subset], lab[subset]
    # a long scan's per-point arrays in the narrowest type that holds them (tens of millions
    # of points: each int64 array is 8 B a point)
    small = len(p) < 2**31 and (len(fp) == 0 or int(fp.max()) < 2**31)
    itype = np.int32 if small else np.int64
    order, sid, start, end = _stripes(fp, lab, p, subset)
    order, sid = order.astype(itype, copy=False), sid.astype(itype, copy=False)
    fo, lo_ = fp[order].astype(itype), lab[order].astype(np.int8)
    del fp, lab
    # the points in stripe order by index, not a reordered copy of them (4 B a point, not 24)
    po = _Ordered(p, order if subset is None else subset[order])
    del order
    a = np.flatnonzero(lo_ == 1).astype(itype)
    b = np.flatnonzero(lo_ == 2).astype(itype)
    empty = Crossings(*(np.zeros(0, np.int64),) * 2, np.zeros((0, 3)), np.zeros((0, 3)),
                      np.zeros(0), np.zeros(0), np.zeros(0))
    if len(a) < 8 or len(b) < 8:
        return empty
    spacing, sp = _spacings(po, sid, lo_) if spacings is None else spacings
    del lo_  # not needed past here: the k-d tree below is the peak
    radius_mm, half = _windows(spacing, sp, half_mm, radius_mm)
    tree = cKDTree(po[b])
    # every other A point is enough to seed: the crossing itself is found by the curve fits
    a = a[::2]
    ia_, ib_, dd_ = [], [], []
    n_sid = int(sid.max()) + 1
    for c0 in range(0, len(a), _QUERY_ROWS):  # in blocks: k distances a row are 64 B
        ac = a[c0:c0 + _QUERY_ROWS]
        dist, jj = tree.query(po[ac], k=4, distance_upper_bound=radius_mm, workers=threads)
        hit = np.isfinite(dist)
        ia, ib = np.broadcast_to(ac[:, None], dist.shape)[hit].astype(np.int64), b[jj[hit]]
        # the block's seeds at once (below): on a slow sweep nearly every A point lies near a
        # B stripe of some frame, and the raw pairs of a 70 M-point scan held GBs
        keep = _closest_per_cell(po[ia], sid[ia].astype(np.int64) * n_sid + sid[ib], dist[hit])
        ia_.append(ia[keep])
        ib_.append(ib[keep].astype(np.int64))
        dd_.append(dist[hit][keep])
    del tree
    ia, ib, dd = np.concatenate(ia_), np.concatenate(ib_), np.concatenate(dd_)
    if len(ia) == 0:
        return empty
    # one seed per stripe pair and 2 mm cell: the closest A-B point pair there (the blocks'
    # seeds again: a pair and cell may span two blocks; ties go to the first, as in one pass)
    keep = _closest_per_cell(po[ia], sid[ia].astype(np.int64) * n_sid + sid[ib], dd)
    ia, ib = ia[keep], ib[keep]
    # window slots either side: the half-length in median point spacings, with room for
    # sparser stretches and for a second segment of the stripe interleaved in the order
    width = {code: int(np.clip(np.ceil(1.6 * half[code] / max(min(spacing, sp[code]), 1e-3)), 8, 200))
             for code in (1, 2)}
    fits = {}
    for code, seeds in ((1, ia), (2, ib)):
        lo, hi = start[sid[seeds]], end[sid[seeds]]
        c, Ainv, ok = _curves(po, seeds, lo, hi, half[code], width[code])
        h = np.full(len(seeds), half[code])
        # a stripe sampled more sparsely about its seed than its laser's median spacing says
        # (a steep stripe: dense rows on the table, sparse on the ball) holds too few points
        # there: fitted again over MIN_SPACINGS of its own spacing about the seed
        redo = np.flatnonzero(~ok)
        if redo.size:
            local = _local_spacing(po, seeds[redo], lo[redo], hi[redo])
            h_re = np.clip(MIN_SPACINGS * local, half[code], MAX_GROWTH * half[code])
            grow = np.flatnonzero((h_re > half[code]) & (local > SPARSE_FACTOR * sp[code]))
            if grow.size:
                r = redo[grow]
                w_re = int(np.clip(np.ceil(1.6 * np.max(h_re[grow] / local[grow])), 8, 200))
                c2, A2, ok2 = _curves(po, seeds[r], lo[r], hi[r], h_re[grow], w_re)
                c[r], Ainv[r], ok[r], h[r] = c2, A2, ok2, h_re[grow]
        fits[code] = (c, Ainv, ok, h)
    (ca, Ainv_a, ok_a, ha), (cb, Ainv_b, ok_b, hb) = fits[1], fits[2]
    ok = ok_a & ok_b
    ia, ib, ca, cb, Ainv_a, Ainv_b = ia[ok], ib[ok], ca[ok], cb[ok], Ainv_a[ok], Ainv_b[ok]
    ha, hb = ha[ok], hb[ok]
    s, r, xa, xb, ta, tb = _closest(ca, cb)
    nrm = np.cross(ta, tb)
    sin = np.linalg.norm(nrm, axis=1) / np.maximum(
        np.linalg.norm(ta, axis=1) * np.linalg.norm(tb, axis=1), 1e-300)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    x = 0.5 * (xa + xb)
    fa, fb = fo[ia], fo[ib]
    view = np.asarray(viewpoints, dtype=np.float64)[fa] - x
    nrm *= np.where(np.sum(nrm * view, axis=1) < 0, -1.0, 1.0)[:, None]
    gap = np.sum((xa - xb) * nrm, axis=1)
    lev_a = np.einsum("ka,kab,kb->k", np.stack([np.ones_like(s), s, s * s], 1), Ainv_a,
                      np.stack([np.ones_like(s), s, s * s], 1))
    lev_b = np.einsum("ka,kab,kb->k", np.stack([np.ones_like(r), r, r * r], 1), Ainv_b,
                      np.stack([np.ones_like(r), r, r * r], 1))
    keep = ((np.abs(s) <= 0.5 * ha) & (np.abs(r) <= 0.5 * hb)
            & (sin >= np.sin(np.radians(min_angle_deg))) & (np.abs(gap) <= radius_mm))
    # the same crossing found from two cells: keep the one whose seeds were closest to it
    k = np.flatnonzero(keep)
    pr = (sid[ia[k]].astype(np.int64) * (sid.max() + 1) + sid[ib[k]])
    o = np.lexsort((np.abs(s[k]) + np.abs(r[k]), pr))
    k, pr = k[o], pr[o]
    dup = np.zeros(len(k), bool)
    for lag in (1, 2, 3):
        same = pr[lag:] == pr[:-lag]
        close = np.linalg.norm(x[k[lag:]] - x[k[:-lag]], axis=1) < 2 * max(half[1], half[2])
        dup[lag:] |= same & close & ~dup[:-lag]
    k = np.sort(k[~dup])
    # how many candidates survive each step, for the stats: seeds (closest A-B point pairs),
    # both curve fits usable, crossing inside both windows at a fair angle, not a duplicate
    counts = {"seeds": len(ok), "fitted": int(ok.sum()), "kept": int(keep.sum()), "unique": len(k)}
    return Crossings(fa[k].astype(np.int64), fb[k].astype(np.int64), x[k], nrm[k], gap[k],
                     np.sqrt(lev_a[k] + lev_b[k]),
                     np.arcsin(np.clip(sin[k], 0, 1)), counts)
