"""Steger's Hessian line detector: one centre per stripe per column of a frame.

Split from :mod:`crossline.scan.stripes` (issue 21.3), whose module doc describes the
method. Here are :func:`steger`, the Gaussian smoothing of the band around the runs alone
(:func:`_smooth_band`), the Hessian kernel (:func:`_steger_nb`) and the stripe's normal per
run for the merge test (:func:`_run_ny`).
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.jit import HAVE_NUMBA
from crossline.jit import jit as _jit
from crossline.scan.stripe_kernels import CLOSE, EDGE, MERGED, SATURATED
from crossline.scan.stripe_levels import _level_and_max, full_scale
from crossline.scan.stripe_runs import (
    _candidate_runs,
    _gaps,
    _merged,
    _run_peaks,
    _slopes_nb,
    empty_centres,
)

__all__ = [
    "RIDGE_FRACTION",
    "steger",
]

RIDGE_FRACTION = 0.5  # Steger: a run's ridge claims weaker than this share of its strongest are dropped


def _smooth_band(img: np.ndarray, col: np.ndarray, r0: np.ndarray, r1: np.ndarray,
                 sigma: float, block: int = 128) -> np.ndarray:
    """Gaussian-smoothed float32 image, computed only around the runs (elsewhere undefined).

    Each block of ``block`` columns is smoothed over the row intervals that hold runs (plus
    two rows for the Hessian's differences), with the kernel's reach as margin, so the values
    there equal a full-frame ``GaussianBlur`` with reflected borders.
    """
    H, W = img.shape
    reach = int(np.ceil(3.0 * sigma))
    kern = cv2.getGaussianKernel(2 * reach + 1, sigma, cv2.CV_32F)
    g = np.empty((H, W), np.float32)
    nb = (W + block - 1) // block
    blk = col // block
    # row occupancy per block by a difference array, dilated by the rows the Hessian reads
    lo = np.maximum(r0 - 2, 0)
    hi = np.minimum(r1 + 3, H)
    diff = np.bincount(blk * (H + 1) + lo, minlength=nb * (H + 1)) - np.bincount(
        blk * (H + 1) + hi, minlength=nb * (H + 1))
    occ = np.cumsum(diff.reshape(nb, H + 1), axis=1)[:, :H] > 0
    edges = np.diff(np.pad(occ, ((0, 0), (1, 1))).astype(np.int8), axis=1)
    bi, starts = np.nonzero(edges == 1)
    _, ends = np.nonzero(edges == -1)
    for b, a, e in zip(bi.tolist(), starts.tolist(), ends.tolist(), strict=True):
        # one column more on each side: the Hessian of a block's edge column reads them
        c0, c1 = max(b * block - 1, 0), min((b + 1) * block + 1, W)
        ra, rb = max(a - reach, 0), min(e + reach, H)
        ca, cb = max(c0 - reach, 0), min(c1 + reach, W)
        sm = cv2.sepFilter2D(img[ra:rb, ca:cb], cv2.CV_32F, kern, kern,
                             borderType=cv2.BORDER_REFLECT)
        g[a:e, c0:c1] = sm[a - ra : e - ra, c0 - ca : c1 - ca]
    return g


@_jit
def _steger_nb(g, col, r0, r1):  # pragma: no cover - compiled
    """Hessian at each run pixel (+1 row each side); the pixels that hold a ridge crossing.

    Returns (run index, row, dv, smoothed value, lambda, nx, ny) of the accepted pixels.
    """
    H, W = g.shape
    n = 0
    for i in range(col.size):
        n += r1[i] - r0[i] + 3
    seg = np.empty(n, np.int64)
    row = np.empty(n, np.int64)
    dvs = np.empty(n)
    g0s = np.empty(n)
    lams = np.empty(n)
    nxs = np.empty(n)
    nys = np.empty(n)
    k = 0
    for i in range(col.size):
        c = col[i]
        if c < 1 or c > W - 2:
            continue
        for r in range(max(r0[i] - 1, 1), min(r1[i] + 1, H - 2) + 1):
            g0 = np.float64(g[r, c])
            gl = np.float64(g[r, c - 1])
            gr = np.float64(g[r, c + 1])
            gu = np.float64(g[r - 1, c])
            gd = np.float64(g[r + 1, c])
            rx = 0.5 * (gr - gl)
            ry = 0.5 * (gd - gu)
            rxx = gr + gl - 2.0 * g0
            ryy = gd + gu - 2.0 * g0
            rxy = 0.25 * (np.float64(g[r + 1, c + 1]) - np.float64(g[r + 1, c - 1])
                          - np.float64(g[r - 1, c + 1]) + np.float64(g[r - 1, c - 1]))
            lam = 0.5 * (rxx + ryy) - np.sqrt(0.25 * (rxx - ryy) ** 2 + rxy * rxy)
            if not lam < 0.0:
                continue
            # eigenvector of lam: (rxy, lam - rxx) or (lam - ryy, rxy), the better conditioned
            ex = rxy
            ey = lam - rxx
            fx = lam - ryy
            fy = rxy
            if ex * ex + ey * ey < fx * fx + fy * fy:
                ex = fx
                ey = fy
            nrm = np.sqrt(ex * ex + ey * ey)
            if nrm == 0.0:
                continue
            nx = ex / nrm
            ny = ey / nrm
            if ny < 0.0:
                nx = -nx
                ny = -ny
            if ny < 0.5:
                continue
            t = -(rx * nx + ry * ny) / lam
            dv = t / ny
            # a crossing on the border between two pixels may be claimed by neither (the
            # Newton step of a Gaussian is biased at |dv| = 0.5); accept a little more and
            # keep the nearest claim per ridge afterwards
            if abs(dv) > 0.6:
                continue
            seg[k] = i
            row[k] = r
            dvs[k] = dv
            g0s[k] = g0
            lams[k] = lam
            nxs[k] = nx
            nys[k] = ny
            k += 1
    return seg[:k], row[:k], dvs[:k], g0s[:k], lams[:k], nxs[:k], nys[:k]


def steger(
    img: np.ndarray,
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    sigma: float = 2.0,
    *,
    data_max: float | None = None,
    level: float | None = None,
    detect: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Steger's Hessian line detector, one centre per stripe per column (``stripes`` module doc).

    Candidates are the pixels of the runs above the threshold (``threshold``, ``level``,
    ``data_max`` and ``detect`` as for :func:`grey_centre`) of
    at least ``min_width`` px; ``sigma`` is the Gaussian scale in px. Returns a centre table
    in frame-local pixels, sorted by (u, v).
    """
    full_scale(img.dtype)  # unsigned integers only
    H, W = img.shape
    imT = np.ascontiguousarray(cv2.transpose(img))
    src = imT if detect is None else np.ascontiguousarray(cv2.transpose(detect))
    thr, full = _level_and_max(src, threshold, level, data_max)
    col, r0, r1 = _candidate_runs(src, thr, min_width, HAVE_NUMBA)
    k = col.size
    if k == 0:
        return empty_centres()
    g = _smooth_band(img, col, r0, r1, sigma)
    seg, r, dv, g0, lam, nx, ny = _steger_nb(g, col, r0, r1)  # Python where numba is missing
    # a run's real ridges are strong; on the flanks of a speckled stripe the Hessian is barely
    # negative and a Newton step can land inside its own pixel: such claims (weaker than
    # RIDGE_FRACTION of the run's strongest ridge) are not ridges
    if seg.size:
        strongest = np.zeros(k)
        np.minimum.at(strongest, seg, lam)
        strong = lam <= RIDGE_FRACTION * strongest[seg]
        seg, r, dv, g0, lam, nx, ny = (a[strong] for a in (seg, r, dv, g0, lam, nx, ny))
    v = r + dv
    u = col[seg].astype(np.float64)
    # one centre per ridge per column: accepted pixels within a pixel are the same ridge;
    # keep the one whose crossing lies nearest its centre
    if u.size > 1:
        same = np.concatenate([[False], (u[1:] == u[:-1]) & (v[1:] - v[:-1] < 1.0)])
        grp = np.cumsum(~same) - 1
        order = np.lexsort((np.abs(dv), grp))
        first = np.concatenate([[True], grp[order][1:] != grp[order][:-1]])
        keep = np.sort(order[first])
        seg, u, v, g0, lam, nx, ny = (a[keep] for a in (seg, u, v, g0, lam, nx, ny))
    ridge = -lam
    # Gaussian line model: the second difference across a Gaussian of variance S^2 at its
    # peak is 2 g0 (exp(-1 / (2 S^2)) - 1), so S^2 = -1 / (2 ln(1 - ridge / (2 g0)));
    # minus the smoothing's sigma^2 and the pixel's 1/12, an FWHM (approximate: the
    # background is not subtracted)
    with np.errstate(invalid="ignore", divide="ignore"):
        s_tot2 = -1.0 / (2.0 * np.log(np.clip(1.0 - ridge / (2.0 * g0), 1e-12, 1.0 - 1e-12)))
    width_n = 2.0 * np.sqrt(2.0 * np.log(2.0)) * np.sqrt(
        np.maximum(s_tot2 - sigma * sigma - 1.0 / 12.0, 0.0))
    # per-run context shared by its centres: run length, peak, flags
    width_run = (r1 - r0 + 1).astype(np.float64)
    gap_up, gap_dn = _gaps(col, r0, r1, H)
    flags_run = np.zeros(k, np.uint8)
    flags_run[(r0 == 0) | (r1 == H - 1)] |= EDGE
    near = 2 * int(np.ceil(3 * sigma))
    if k > 1:
        same_col = col[1:] == col[:-1]
        flags_run[1:][same_col & (gap_up[1:] < near)] |= CLOSE
        flags_run[:-1][same_col & (gap_dn[:-1] < near)] |= CLOSE
    peak_run = _run_peaks(imT.reshape(-1), H, col, r0, r1)
    flags_run[peak_run >= full] |= SATURATED
    per_run = np.bincount(seg, minlength=k)
    merged_run = _merged(src, col, r0, r1, width_run, width_run * _run_ny(col, r0, r1, W), thr, max_width)
    # a merged run that Steger resolved into two ridges is two close stripes, not a blob
    flags_run[merged_run & (per_run <= 1)] |= MERGED
    flags_run[merged_run & (per_run >= 2)] |= CLOSE
    return {
        "u": u, "v": v, "strength": g0, "peak": peak_run[seg], "width": width_run[seg],
        "width_n": width_n, "nx": nx, "ny": ny, "ridge": ridge, "flags": flags_run[seg],
    }


def _run_ny(col: np.ndarray, r0: np.ndarray, r1: np.ndarray, W: int) -> np.ndarray:
    """|n_y| of each run's stripe from the run middles of the adjacent columns."""
    mid = 0.5 * (r0 + r1).astype(np.float64)
    slope = _slopes_nb(col, mid, W, (r1 - r0 + 1).astype(np.float64))
    return 1.0 / np.sqrt(1.0 + slope * slope)
