"""Compiled window kernels of the grey centre and the Gaussian fit, and the flag bits they set.

Split from :mod:`crossline.scan.stripes` (issue 21.3). Each run above the threshold is
widened into a window along its column, up to half the gap to a neighbouring run
(:func:`_gaps_nb`, which sets ``CLOSE`` and ``EDGE``). The grey centre sums each window
(:func:`_windows_nb`; its numpy twin :func:`_grey_windows_numpy` gives the same centres); the
Gaussian fit puts a background line under it (:func:`_gauss_windows_nb`,
:func:`_background_line_nb`), fits a Gaussian in it (:func:`_gauss_solve_nb`), and two
Gaussians in the shared window of two close runs (:func:`_gauss_pairs_nb`). The drivers are
:func:`crossline.scan.stripe_grey.grey_centre` and
:func:`crossline.scan.stripe_gaussian.gaussian`.

Why these share one file: numba caches each kernel on disk and invalidates that cache only when
the kernel's own file changes, not when a kernel it calls or a module constant it reads changes
in another file. These kernels call one another (both window kernels ``_gaps_nb``, the pair
fit the background line) and set the flag bits (as the literals 2, 4, 8 and the global
``MERGED``), so they and the flag bits live together.
"""

from __future__ import annotations

import numpy as np

from crossline.jit import jit as _jit
from crossline.scan.stripe_runs import _gaps

__all__ = [
    "CLOSE",
    "EDGE",
    "FLAG_NAMES",
    "MERGED",
    "SATURATED",
]

MERGED = 1  # a run too wide for one stripe: two stripes merged (near the crossing)
CLOSE = 2  # another segment in the same column so near that the windows were clipped
SATURATED = 4  # a pixel of the window at full scale
EDGE = 8  # the run touches the top or bottom of the frame (the stripe may be cut)
FLAG_NAMES = {MERGED: "merged", CLOSE: "close", SATURATED: "saturated", EDGE: "edge"}


@_jit
def _gaps_nb(col, r0, r1, H, near):  # pragma: no cover - compiled
    """numba twin of :func:`_gaps`, with the CLOSE flag (gap under ``near``) and EDGE.

    A window may take half the gap to a neighbouring run but all of it to the border, where
    nothing shares the pixels: the gaps to the border are returned doubled, so that half of
    each gap is the room a window has on that side.
    """
    k = col.size
    gaps_up = 2 * r0.astype(np.int64)
    gaps_dn = 2 * (H - 1 - r1).astype(np.int64)
    flags = np.zeros(k, np.uint8)
    for i in range(k):
        if i > 0 and col[i - 1] == col[i]:
            gaps_up[i] = r0[i] - r1[i - 1] - 1
            if gaps_up[i] < near:
                flags[i] |= 2
        if i + 1 < k and col[i + 1] == col[i]:
            gaps_dn[i] = r0[i + 1] - r1[i] - 1
            if gaps_dn[i] < near:
                flags[i] |= 2
        if r0[i] == 0 or r1[i] == H - 1:
            flags[i] |= 8
    return gaps_up, gaps_dn, flags


@_jit
def _windows_nb(flat, H, col, r0, r1, pad, bg_pixels, full):  # pragma: no cover - compiled
    """numba twin of the window phase of :func:`_grey_centre_numpy` (same arithmetic)."""
    k = col.size
    v = np.empty(k)
    sw = np.empty(k)
    peak = np.empty(k)
    gaps_up, gaps_dn, flags = _gaps_nb(col, r0, r1, H, 2 * (pad + bg_pixels))
    for i in range(k):
        c = col[i]
        gu = gaps_up[i]
        gd = gaps_dn[i]
        lo = r0[i] - min(pad, gu // 2)
        hi = r1[i] + min(pad, gd // 2)
        base = c * H
        b0 = 0.0
        b1 = 0.0
        for j in range(1, bg_pixels + 1):
            b0 += flat[base + min(max(lo - j, 0), H - 1)]
            b1 += flat[base + min(max(hi + j, 0), H - 1)]
        bg = min(b0 / bg_pixels, b1 / bg_pixels)
        s = 0.0
        sr = 0.0
        pk = 0.0
        for r in range(lo, hi + 1):
            val = float(flat[base + r])
            w = val - bg
            if w > 0.0:
                s += w
                sr += w * (r - lo)
            if val > pk:
                pk = val
        sw[i] = s
        v[i] = lo + sr / s if s > 0.0 else np.nan
        peak[i] = pk
        if pk >= full:
            flags[i] |= 4
    return v, sw, peak, flags


def _grey_windows_numpy(flat, H, col, r0, r1, pad, bg_pixels, full):
    """Window phase of the grey centre, vectorised: (v, summed weight, peak, flags)."""
    k = col.size
    gap_up, gap_dn = _gaps(col, r0, r1, H)
    lo = r0 - np.minimum(pad, gap_up // 2)
    hi = r1 + np.minimum(pad, gap_dn // 2)
    flags = np.zeros(k, np.uint8)
    # a neighbour whose window or background pixels overlap ours
    near = 2 * (pad + bg_pixels)
    close = np.zeros(k, bool)
    if k > 1:
        same = col[1:] == col[:-1]
        close[1:] |= same & (gap_up[1:] < near)
        close[:-1] |= same & (gap_dn[:-1] < near)
    flags[close] |= CLOSE
    flags[(r0 == 0) | (r1 == H - 1)] |= EDGE
    base = col * H
    # background: the lower of the means of the pixels just outside each end of the window
    b0 = np.zeros(k)
    b1 = np.zeros(k)
    for j in range(1, bg_pixels + 1):
        b0 += flat[base + np.clip(lo - j, 0, H - 1)]
        b1 += flat[base + np.clip(hi + j, 0, H - 1)]
    bg = np.minimum(b0 / bg_pixels, b1 / bg_pixels)
    n = (hi - lo + 1).astype(np.int64)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    seg = np.repeat(np.arange(k), n)
    off = np.arange(int(n.sum())) - start[seg]  # row offset inside the window
    vals = flat[base[seg] + lo[seg] + off].astype(np.float64)
    w = np.maximum(vals - bg[seg], 0.0)
    sw = np.add.reduceat(w, start)
    swr = np.add.reduceat(w * off, start)
    peak = np.maximum.reduceat(vals, start)
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.where(sw > 0, lo + swr / sw, np.nan)
    flags[peak >= full] |= SATURATED
    return v, sw, peak, flags


@_jit
def _gauss_windows_nb(flat, H, col, r0, r1, ext, nbg):  # pragma: no cover - compiled
    """Fit window, background line and background residual variance of every run.

    Returns (lo, hi, bc, bs, bvar, flags): rows lo..hi of the window, the line
    ``bc + bs (r - r0)``, its residual variance (NaN with fewer than 4 pixels), CLOSE and EDGE.
    """
    k = col.size
    bvar = np.full(k, np.nan)
    lo_w = np.empty(k, np.int64)
    hi_w = np.empty(k, np.int64)
    bc = np.zeros(k)  # background line: bg(r) = bc + bs * (r - r0)
    bs = np.zeros(k)
    gaps_up, gaps_dn, flags = _gaps_nb(col, r0, r1, H, 2 * (ext + nbg))
    # windows and background lines
    for i in range(k):
        c = col[i]
        gu = gaps_up[i]
        gd = gaps_dn[i]
        # the window and its background pixels stay on this run's side of the gap's midpoint;
        # a steep stripe's long run has long tails along the column: the reach grows with it.
        # Where the stripe's tail runs into the frame's border, the window takes it all, up to
        # the border, and the background comes from the other side: cut at the reach less the
        # background pixels, the tail's pixels would be the background and pull the centre
        # off the border (random rig 0's ball, whose B stripe runs along the window's top)
        reach = max(ext, (r1[i] - r0[i] + 1) // 2)
        if gu // 2 - nbg < reach and not (i > 0 and col[i - 1] == c):
            lo = 0
        else:
            lo = r0[i] - max(min(reach, gu // 2 - nbg), 0)
        if gd // 2 - nbg < reach and not (i + 1 < k and col[i + 1] == c):
            hi = H - 1
        else:
            hi = r1[i] + max(min(reach, gd // 2 - nbg), 0)
        lo_w[i] = lo
        hi_w[i] = hi
        bc[i], bs[i], bvar[i] = _background_line_nb(flat, c * H, H, lo, hi, nbg, r0[i])
    return lo_w, hi_w, bc, bs, bvar, flags


@_jit
def _background_line_nb(flat, base, H, lo, hi, nbg, x0):  # pragma: no cover - compiled
    """Background line ``bc + bs (r - x0)`` through the ``nbg`` pixels beyond each end of rows
    ``lo..hi`` of the column starting at ``flat[base]`` (a constant where those lie on one side
    only); returns (bc, bs, residual variance: NaN with fewer than 4 pixels)."""
    n = 0
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    sxy = 0.0
    for j in range(1, nbg + 1):
        for r in (lo - j, hi + j):
            if 0 <= r < H:
                x = float(r - x0)
                y = float(flat[base + r])
                n += 1
                sx += x
                sy += y
                sxx += x * x
                sxy += x * y
    if n == 0:
        return 0.0, 0.0, np.nan
    bc = sy / n
    bs = 0.0
    det = n * sxx - sx * sx
    if det > 1e-9 * max(n * sxx, 1.0) and n >= 4:
        bs = (n * sxy - sx * sy) / det
        bc = (sy - bs * sx) / n
    if n < 4:
        return bc, bs, np.nan
    ss = 0.0
    for j in range(1, nbg + 1):
        for r in (lo - j, hi + j):
            if 0 <= r < H:
                e = float(flat[base + r]) - bc - bs * (r - x0)
                ss += e * e
    return bc, bs, ss / (n - 2)


@_jit
def _gauss_solve_nb(flat, H, col, r0, lo_w, hi_w, bc, bs, noise2, rel2, full, iters,
                    residuals, a_io, c_io, s_io, ok_io, flags):  # pragma: no cover - compiled
    """Gauss-Newton fit of each window's Gaussian (a, c, s), in place in a_io, c_io, s_io.

    The start is the window's intensity centroid and second moment. With
    ``residuals``, returns per window the sum of squared relative residuals of its bright
    pixels (model above half its peak) and their count, for the estimate of the relative noise.
    """
    k = col.size
    rel_ss = np.zeros(k)
    rel_n = np.zeros(k)
    for i in range(k):
        base = col[i] * H
        lo = lo_w[i]
        hi = hi_w[i]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        a = 0.0
        for r in range(lo, hi + 1):
            val = float(flat[base + r])
            if val >= full:
                flags[i] |= 4
            y = val - bc[i] - bs[i] * (r - r0[i])
            if y > 0.0:
                s0 += y
                s1 += y * r
                s2 += y * r * r
            if y > a:
                a = y
        if s0 <= 0.0:
            ok_io[i] = False
            continue
        c = s1 / s0
        s = np.sqrt(max(s2 / s0 - c * c, 0.25))
        c_start = c
        ok = True
        used = 0
        for _ in range(iters):
            m00 = m01 = m02 = m11 = m12 = m22 = 0.0
            g0 = g1 = g2 = 0.0
            used = 0
            # exp(-z^2 / 2) at consecutive rows by a recurrence: two exponentials per window
            inv = 1.0 / (s * s)
            z = (lo - c) / s
            e = np.exp(-0.5 * z * z)
            q = np.exp(-(lo - c + 0.5) * inv)
            qq = np.exp(-inv)
            for r in range(lo, hi + 1):
                val = float(flat[base + r])
                if val < full:  # a clipped value says only "at least full scale"
                    z = (r - c) / s
                    yh = a * e
                    w = 1.0 / (rel2 * yh * yh + noise2)
                    res = val - bc[i] - bs[i] * (r - r0[i]) - yh
                    j1 = yh * z / s
                    j2 = j1 * z
                    m00 += w * e * e
                    m01 += w * e * j1
                    m02 += w * e * j2
                    m11 += w * j1 * j1
                    m12 += w * j1 * j2
                    m22 += w * j2 * j2
                    g0 += w * e * res
                    g1 += w * j1 * res
                    g2 += w * j2 * res
                    used += 1
                e *= q
                q *= qq
            if used < 4:
                ok = False
                break
            # 3 x 3 solve by the adjugate (symmetric positive definite)
            c00 = m11 * m22 - m12 * m12
            c01 = m02 * m12 - m01 * m22
            c02 = m01 * m12 - m02 * m11
            det = m00 * c00 + m01 * c01 + m02 * c02
            if not det > 0.0:
                ok = False
                break
            c11 = m00 * m22 - m02 * m02
            c12 = m01 * m02 - m00 * m12
            c22 = m00 * m11 - m01 * m01
            da = (c00 * g0 + c01 * g1 + c02 * g2) / det
            dc = (c01 * g0 + c11 * g1 + c12 * g2) / det
            ds = (c02 * g0 + c12 * g1 + c22 * g2) / det
            # damped: one step never moves the centre by more than a pixel
            f = 1.0
            if abs(dc) > 1.0:
                f = 1.0 / abs(dc)
            if abs(ds) > 0.5 * s:
                f = min(f, 0.5 * s / abs(ds))
            a += f * da
            c += f * dc
            s += f * ds
            if a <= 0.0 or s < 0.3 or s > hi - lo + 1 or abs(c - c_start) > 3.0:
                ok = False
                break
            if abs(f * dc) < 1e-4 and abs(f * ds) < 1e-4:
                break
        ok = ok and lo <= c <= hi
        ok_io[i] = ok
        if not ok:
            continue
        a_io[i] = a
        c_io[i] = c
        s_io[i] = s
        if not residuals:
            continue
        # relative residuals where the stripe is bright, above half its peak (|z| < 1.18);
        # the sensor's share removed
        ss = 0.0
        nb = 0
        for r in range(max(lo, int(np.ceil(c - 1.1775 * s))), min(hi, int(np.floor(c + 1.1775 * s))) + 1):
            val = float(flat[base + r])
            z = (r - c) / s
            yh = a * np.exp(-0.5 * z * z)
            if val < full and yh > 0.5 * a:
                d = (val - bc[i] - bs[i] * (r - r0[i]) - yh) / yh
                ss += d * d - noise2 / (yh * yh)
                nb += 1
        # three parameters were fitted to `used` values: scale the residuals back up
        if nb > 0 and used > 3:
            rel_ss[i] = ss * used / (used - 3)
            rel_n[i] = nb
    return rel_ss, rel_n


@_jit
def _gauss_pairs_nb(flat, H, col, r0, r1, lo_w, hi_w, near, nbg, noise2, rel2, full, iters,
                    a_io, c_io, s_io, ok_io, flags):  # pragma: no cover - compiled
    """Joint fit of two close stripes in one column: two Gaussians on one background line.

    Each pair of runs closer than ``near`` (flag CLOSE) with no third close run beside them is
    fitted over one window, from the upper run's window start ``lo_w`` to the lower run's end
    ``hi_w``, on a background line through the ``nbg`` pixels beyond both ends: each alone,
    its window stops at the gap's midpoint and its background line runs through the gap, on
    the other stripe's tail, which pushes the two apart (0.09 px each at 10 px apart, sigma
    2). Starts from the single fits in ``a_io, c_io, s_io`` and replaces them where the joint
    fit converges within 1.5 px of them; pairs with a merged run are left as they are.
    """
    k = col.size
    p = np.zeros(6)
    J = np.zeros(6)
    d = np.zeros(6)
    M = np.zeros((6, 6))
    L = np.zeros((6, 6))
    g = np.zeros(6)
    for i in range(k - 1):
        if col[i + 1] != col[i] or r0[i + 1] - r1[i] - 1 >= near or not (ok_io[i] and ok_io[i + 1]):
            continue
        if (flags[i] | flags[i + 1]) & MERGED:  # a merged run is two stripes already
            continue
        if i > 0 and col[i - 1] == col[i] and r0[i] - r1[i - 1] - 1 < near:
            continue
        if i + 2 < k and col[i + 2] == col[i] and r0[i + 2] - r1[i + 1] - 1 < near:
            continue
        base = col[i] * H
        lo = lo_w[i]
        hi = hi_w[i + 1]
        bc, bs, _ = _background_line_nb(flat, base, H, lo, hi, nbg, lo)
        p[0] = a_io[i]
        p[1] = c_io[i]
        p[2] = s_io[i]
        p[3] = a_io[i + 1]
        p[4] = c_io[i + 1]
        p[5] = s_io[i + 1]
        c1_0 = p[1]
        c2_0 = p[4]
        ok = True
        for _ in range(iters):
            M[:, :] = 0.0
            g[:] = 0.0
            used = 0
            for r in range(lo, hi + 1):
                val = float(flat[base + r])
                if val >= full:
                    continue
                z1 = (r - p[1]) / p[2]
                z2 = (r - p[4]) / p[5]
                e1 = np.exp(-0.5 * z1 * z1)
                e2 = np.exp(-0.5 * z2 * z2)
                y1 = p[0] * e1
                y2 = p[3] * e2
                yh = y1 + y2
                w = 1.0 / (rel2 * yh * yh + noise2)
                res = val - bc - bs * (r - lo) - yh
                J[0] = e1
                J[1] = y1 * z1 / p[2]
                J[2] = J[1] * z1
                J[3] = e2
                J[4] = y2 * z2 / p[5]
                J[5] = J[4] * z2
                for u in range(6):
                    g[u] += w * J[u] * res
                    for v in range(u, 6):
                        M[u, v] += w * J[u] * J[v]
                used += 1
            if used < 8:
                ok = False
                break
            for u in range(6):
                for v in range(u):
                    M[u, v] = M[v, u]
            # Cholesky: the normal matrix is positive definite unless the pair is degenerate
            for u in range(6):
                acc = M[u, u]
                for t in range(u):
                    acc -= L[u, t] * L[u, t]
                if not acc > 0.0:
                    ok = False
                    break
                L[u, u] = np.sqrt(acc)
                for v in range(u + 1, 6):
                    acc = M[v, u]
                    for t in range(u):
                        acc -= L[v, t] * L[u, t]
                    L[v, u] = acc / L[u, u]
            if not ok:
                break
            for u in range(6):
                acc = g[u]
                for t in range(u):
                    acc -= L[u, t] * d[t]
                d[u] = acc / L[u, u]
            for u in range(5, -1, -1):
                acc = d[u]
                for t in range(u + 1, 6):
                    acc -= L[t, u] * d[t]
                d[u] = acc / L[u, u]
            # damped as the single fit: a step moves no centre by more than a pixel
            f = 1.0
            for u in (1, 4):
                if abs(d[u]) > 1.0:
                    f = min(f, 1.0 / abs(d[u]))
            for u in (2, 5):
                if abs(d[u]) > 0.5 * p[u]:
                    f = min(f, 0.5 * p[u] / abs(d[u]))
            for u in range(6):
                p[u] += f * d[u]
            if (p[0] <= 0.0 or p[3] <= 0.0 or p[2] < 0.3 or p[5] < 0.3
                    or abs(p[1] - c1_0) > 1.5 or abs(p[4] - c2_0) > 1.5):
                ok = False
                break
            if max(abs(d[1]), abs(d[2]), abs(d[4]), abs(d[5])) * f < 1e-4:
                break
        if not ok or not (lo <= p[1] < p[4] <= hi):
            continue
        a_io[i], c_io[i], s_io[i] = p[0], p[1], p[2]
        a_io[i + 1], c_io[i + 1], s_io[i + 1] = p[3], p[4], p[5]
