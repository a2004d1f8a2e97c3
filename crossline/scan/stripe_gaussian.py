"""The speckle-aware Gaussian profile fit of every stripe segment of every column of a frame.

Split from :mod:`crossline.scan.stripes` (issue 21.3), whose module doc describes the
method: a Gaussian on a background line, fitted with the weights of maximum likelihood under
speckle and sensor noise (both measured in the frame), steep stripes fitted again across the
stripe, close pairs fitted together. Here are the driver, :func:`gaussian`, and the fit across
the stripe (:func:`_refit_across`, on profiles sampled along the normal by
:func:`_normal_profiles_nb`); the fits along the column, single and of close pairs, are
kernels of :mod:`crossline.scan.stripe_kernels`.
"""

from __future__ import annotations

import numpy as np

from crossline.jit import jit as _jit
from crossline.scan.stripe_kernels import (
    CLOSE,
    EDGE,
    MERGED,
    SATURATED,
    _gauss_pairs_nb,
    _gauss_solve_nb,
    _gauss_windows_nb,
)
from crossline.scan.stripe_levels import _level_and_max, full_scale
from crossline.scan.stripe_runs import (
    _candidate_runs,
    _columns,
    _merged,
    _run_peaks,
    _slopes_nb,
    empty_centres,
)

__all__ = [
    "ACROSS_SLOPE",
    "BG_FIT_PIXELS",
    "RELATIVE_NOISE_SAMPLE",
    "RELATIVE_NOISE_START",
    "gaussian",
]

BG_FIT_PIXELS = 3  # gaussian: pixels beyond each end of a window that the background line is fitted to
RELATIVE_NOISE_START = 0.15  # gaussian: relative (speckle) noise of the first fit, before it is estimated
RELATIVE_NOISE_SAMPLE = 4  # gaussian: every 4th clean stripe profile of a frame estimates it
ACROSS_SLOPE = 0.3  # gaussian: stripes steeper than this (|dv/du|) are refitted across the stripe


@_jit
def _normal_profiles_nb(flat, H, W, col, v, nx, ny, half, nbg, full):  # pragma: no cover - compiled
    """Profiles across the stripe through each centre, sampled bilinearly at 1 px steps.

    Profile ``i`` runs from ``(col, v) - (half + nbg) n`` to ``(col, v) + (half + nbg) n``
    (``2 (half + nbg) + 1`` samples). Each sample is the mean over the stripe's length that
    one column holds (``1 / n_y`` px along the tangent, at most 1 px apart), so a profile
    sees the pixels that the column's own cut sees; a sample touching a clipped pixel is set
    to full scale (the fit leaves it out). Returns the profiles (flattened), the background
    line of each (``bc + bs q`` at sample ``q``, fitted to the ``nbg`` samples beyond each
    end) and whether the whole profile lies inside the frame.
    """
    k = col.size
    n = 2 * (half + nbg) + 1
    prof = np.zeros(k * n)
    bc = np.zeros(k)
    bs = np.zeros(k)
    inside = np.ones(k, np.bool_)
    for i in range(k):
        length = 1.0 / ny[i]
        m = max(1, int(np.ceil(length - 1e-9)))
        for q in range(n):
            t = float(q - half - nbg)
            acc = 0.0
            clipped = False
            for j in range(m):
                tau = (j + 0.5) * length / m - 0.5 * length
                x = col[i] + t * nx[i] + tau * ny[i]
                y = v[i] + t * ny[i] - tau * nx[i]
                x0 = int(np.floor(x))
                y0 = int(np.floor(y))
                if x0 < 0 or y0 < 0 or x0 + 1 >= W or y0 + 1 >= H:
                    inside[i] = False
                    break
                fx = x - x0
                fy = y - y0
                p00 = float(flat[x0 * H + y0])
                p01 = float(flat[x0 * H + y0 + 1])
                p10 = float(flat[(x0 + 1) * H + y0])
                p11 = float(flat[(x0 + 1) * H + y0 + 1])
                if max(max(p00, p01), max(p10, p11)) >= full:
                    clipped = True
                acc += ((1.0 - fx) * ((1.0 - fy) * p00 + fy * p01)
                        + fx * ((1.0 - fy) * p10 + fy * p11))
            if not inside[i]:
                break
            prof[i * n + q] = full if clipped else acc / m
        if not inside[i]:
            continue
        m0 = 0.0
        sx = 0.0
        sy = 0.0
        sxx = 0.0
        sxy = 0.0
        for j in range(nbg):
            for q in (j, n - 1 - j):
                y = prof[i * n + q]
                m0 += 1.0
                sx += q
                sy += y
                sxx += q * q
                sxy += q * y
        det = m0 * sxx - sx * sx
        bs[i] = (m0 * sxy - sx * sy) / det
        bc[i] = (sy - bs[i] * sx) / m0
    return prof, bc, bs, inside


def _refit_across(flat: np.ndarray, H: int, W: int, col: np.ndarray, v: np.ndarray, nx: np.ndarray,
                  ny: np.ndarray, half: int, noise2: float, rel2: float, full: float,
                  iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian fit of the profile across the stripe (along ``n``) at each listed centre.

    Returns the row where the fitted ridge crosses the centre's column, the amplitude and
    sigma across the stripe, and which refits are kept: converged, within a pixel of the
    start, and as wide as the frame's other refits (0.6-1.6x their median: otherwise the
    profile ran into another stripe or a shadow edge).
    """
    nbg = BG_FIT_PIXELS
    prof, bc, bs, inside = _normal_profiles_nb(flat, H, W, col, v, nx, ny, half, nbg, full)
    m = col.size
    n = 2 * (half + nbg) + 1
    a = np.zeros(m)
    c = np.zeros(m)
    s = np.zeros(m)
    ok = inside.copy()
    _gauss_solve_nb(prof, n, np.arange(m, dtype=np.int64), np.zeros(m, np.int64),
                    np.full(m, nbg, np.int64), np.full(m, n - 1 - nbg, np.int64), bc, bs, noise2,
                    rel2, full, iterations, False, a, c, s, ok, np.zeros(m, np.uint8))
    t = c - (half + nbg)  # offset of the ridge from the start, along n
    keep = ok & (np.abs(t) <= 1.0)
    if keep.any():
        typical = np.median(s[keep])
        keep &= (s > 0.6 * typical) & (s < 1.6 * typical)
    # along the line from the ridge point back to the centre's column (Steger's v = r + t / n_y)
    return v + t / ny, a, s, keep


def gaussian(
    img: np.ndarray,
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    pad: int = 6,
    relative_noise: float | None = None,
    iterations: int = 10,
    return_info: bool = False,
    transposed: bool = False,
    across: bool = True,
    *,
    data_max: float | None = None,
    level: float | None = None,
    detect: np.ndarray | None = None,
) -> dict[str, np.ndarray] | tuple[dict[str, np.ndarray], dict[str, float]]:
    """Weighted least-squares Gaussian profile of every stripe segment of every column.

    Each run above the threshold (``threshold``, ``level``, ``data_max`` as for
    :func:`grey_centre`) is widened on each side by ``pad``
    px or half its length, whichever is more (never past the midpoint of the gap to a
    neighbouring run, less the background pixels); a background line is
    fitted to the ``BG_FIT_PIXELS`` pixels beyond each end; the profile
    ``a exp(-(v - c)^2 / 2 s^2)`` is fitted by Gauss-Newton with the weights of maximum
    likelihood, ``1 / (r^2 yhat^2 + sigma_n^2)``: laser speckle is multiplicative (relative
    noise ``r``), sensor noise additive (``sigma_n``, from the background lines of the frame);
    clipped pixels are left out. ``relative_noise=None`` estimates ``r`` from the frame itself:
    every ``RELATIVE_NOISE_SAMPLE``-th clean profile is fitted with ``r = 0.15`` first, the
    relative residuals of their bright pixels give ``r``, then every profile is fitted with it.
    With ``across``, stripes steeper than ``ACROSS_SLOPE`` rows per column (slope from the
    neighbouring columns' centres) are fitted again across the stripe (``stripes`` module doc), which
    removes the column cut's bias towards the centre of curvature of a curved stripe. The
    window's intensity centroid is the start; a refit that does not converge within a pixel
    of it, or whose width is off the frame's other refits, is fitted along its column instead.
    Returns a centre table (``stripes`` module doc) in frame-local pixels, sorted by (u, v)
    (``strength``: the fitted profile's integral, ``width_n``: its FWHM across the stripe),
    and with ``return_info`` also ``{"noise_dn": sigma_n, "relative_noise": r}``.
    ``transposed``: ``img`` is the frame as (width, height), and ``detect`` where the runs
    are found, as for :func:`grey_centre`.
    """
    full_scale(img.dtype)  # unsigned integers only
    imT = _columns(img, transposed)
    src = imT if detect is None else _columns(detect, transposed)
    thr, full = _level_and_max(src, threshold, level, data_max)
    W, H = imT.shape
    flat = imT.reshape(-1)
    col, r0, r1 = _candidate_runs(src, thr, min_width)
    k = col.size
    if k == 0:
        return (empty_centres(), {"noise_dn": float("nan"), "relative_noise": float("nan")}) \
            if return_info else empty_centres()
    lo, hi, bc, bs, bvar, flags = _gauss_windows_nb(flat, H, col, r0, r1, int(pad), BG_FIT_PIXELS)
    # one sensor-noise level per frame: the median of the background lines' residual variances
    # (a chi-square of 4 degrees of freedom has its median at 0.84 of its mean), at least the
    # quantisation's 1/12
    good_bg = np.isfinite(bvar)
    noise2 = max(float(np.median(bvar[good_bg])) / 0.84 if good_bg.any() else 1.0, 1.0 / 12.0)
    a = np.zeros(k)
    c = np.zeros(k)
    s = np.zeros(k)
    ok = np.ones(k, bool)
    rel = RELATIVE_NOISE_START if relative_noise is None else float(relative_noise)
    if relative_noise is None:
        # the relative noise from a sample of the clean single stripes (close ones and those
        # at the border are not clean Gaussians), fitted first with a start value
        sub = np.flatnonzero((flags & (CLOSE | EDGE)) == 0)[::RELATIVE_NOISE_SAMPLE]
        if sub.size:
            fl = flags[sub].copy()
            a1, c1, s1 = np.zeros(sub.size), np.zeros(sub.size), np.zeros(sub.size)
            ok1 = np.ones(sub.size, bool)
            rel_ss, rel_n = _gauss_solve_nb(flat, H, col[sub], r0[sub], lo[sub], hi[sub], bc[sub],
                                            bs[sub], noise2, rel * rel, full, int(iterations),
                                            True, a1, c1, s1, ok1, fl)
            clean = ok1 & ((fl & SATURATED) == 0) & (rel_n > 0)
            if clean.any():
                rel = float(np.sqrt(max(rel_ss[clean].sum() / rel_n[clean].sum(), 0.0)))
    # with ``across``, the windows' intensity centroids (no Gauss-Newton step) find the
    # stripes' slopes; only the centres not refitted across are fitted along their column
    _gauss_solve_nb(flat, H, col, r0, lo, hi, bc, bs, noise2, rel * rel, full,
                    0 if across else int(iterations), False, a, c, s, ok, flags)
    u = col.astype(np.float64)
    width = (r1 - r0 + 1).astype(np.float64)
    slope = _slopes_nb(col, np.where(ok, c, 0.5 * (r0 + r1)), W, width)
    ny = 1.0 / np.sqrt(1.0 + slope * slope)
    nx = -slope * ny
    peak = _run_peaks(flat, H, col, r0, r1)
    clean = (flags & (CLOSE | EDGE)) == 0
    wn_run = width * ny
    typical = np.median(wn_run[clean]) if clean.any() else np.median(wn_run)
    flags[_merged(src, col, r0, r1, width, wn_run, thr, max_width, clean)] |= MERGED
    if across:
        # a column cuts a steep, curved stripe obliquely: the profile along it is skewed
        # towards the centre of curvature and its fitted centre with it (by ~2.5 sigma_col^2
        # s^2 v'' / (1 + s^2)^2 rows); across the stripe the profile is symmetric
        single = (flags & (CLOSE | EDGE | MERGED)) == 0
        steep = np.flatnonzero(ok & (np.abs(slope) >= ACROSS_SLOPE) & single)
        refit = np.zeros(k, bool)
        if steep.size:
            half = int(np.ceil(0.5 * typical)) + int(pad)
            v_x, a_x, s_x, keep = _refit_across(flat, H, W, col[steep], c[steep], nx[steep], ny[steep],
                                                half, noise2, rel * rel, full, int(iterations))
            done = steep[keep]
            c[done], a[done], s[done] = v_x[keep], a_x[keep], s_x[keep] / ny[done]
            refit[done] = True
        along = np.flatnonzero(ok & ~refit)
        if along.size:
            a1, c1, s1, ok1, fl = a[along], c[along], s[along], ok[along], flags[along]
            _gauss_solve_nb(flat, H, col[along], r0[along], lo[along], hi[along], bc[along], bs[along],
                            noise2, rel * rel, full, int(iterations), False, a1, c1, s1, ok1, fl)
            a[along], c[along], s[along], ok[along], flags[along] = a1, c1, s1, ok1, fl
    # two stripes close in one column (the cross's arms near their crossing): fitted together
    if np.any(flags & CLOSE):
        _gauss_pairs_nb(flat, H, col, r0, r1, lo, hi, 2 * (int(pad) + BG_FIT_PIXELS), BG_FIT_PIXELS,
                        noise2, rel * rel, full, int(iterations), a, c, s, ok, flags)
    v = np.where(ok, c, np.nan)
    s_n = s * ny  # sigma across the stripe
    out = {
        "u": u, "v": v, "strength": a * s * np.sqrt(2.0 * np.pi),
        "peak": peak, "width": width,
        "width_n": 2.0 * np.sqrt(2.0 * np.log(2.0)) * s_n, "nx": nx, "ny": ny,
        "ridge": np.full(k, np.nan), "flags": flags,
    }
    if not ok.all():
        out = {name: x[ok] for name, x in out.items()}
    if return_info:
        return out, {"noise_dn": float(np.sqrt(noise2)), "relative_noise": rel}
    return out
