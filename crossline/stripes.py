"""Stripe centres of laser frames: the paper's grey-centre (eq. 9-13) and Steger's detector.

Both extractors work column by column, as the paper does: every image column ``u`` may hold
several stripe *segments* (an AB frame of the cross has two), each found as a run of pixels
above the threshold, and each gives one centre ``v`` (sub-pixel row). Pixel coordinates
inside this module are frame-local; :func:`run_extract_stripes` adds the scan window's
offset so that every stored centre is in full-sensor pixels.

Grey-centre (:func:`grey_centre`). Eq. 9 weights rows by intensity over the stripe region
``S``. Here ``S`` is the run above the threshold extended by ``pad`` pixels on each side (so
the stripe's tails are inside: a window cut at the threshold biases asymmetric stripes), and
the weights are the intensity minus the local background (the lower of the two means of the
two pixels just outside the window, so a neighbouring stripe on one side does not inflate
it). Nothing is anchored on the brightest pixel, so saturated (flat-topped) stripes are
centred on their middle. Two segments in one column never share pixels: each window stops
at the midpoint of the gap to its neighbour (flag ``CLOSE``). A run much wider than the
frame's typical stripe, or wider than ``max_width``, is two stripes merged (near the
crossing of A and B): it is flagged ``MERGED``, never split or averaged silently.

Steger (:func:`steger`). Gaussian smoothing (``sigma``), Hessian by central differences of
the smoothed image at the candidate pixels only (the runs above the threshold: the band
around the stripes), the normal ``n`` as the eigenvector of the most negative eigenvalue,
and the sub-pixel ridge along ``n`` by one Newton step; the ridge point is carried along
the line to the pixel's column (``v = r + t / n_y``), and the pixel whose column crossing
lies inside it is the one kept. Each centre carries its normal, ridge strength
(``-lambda``) and a width from the Gaussian line model.

Columns of a centre table (dict of arrays, one entry per centre): ``u, v`` (px), ``strength``
(background-subtracted summed intensity, counts; Steger: smoothed intensity at the ridge),
``peak`` (brightest pixel, counts), ``width`` (run length above threshold along the column,
px), ``width_n`` (width across the stripe, px: grey-centre ``width * |n_y|``, Steger the
FWHM of the Gaussian model), ``nx, ny`` (unit normal, ``ny >= 0``), ``ridge`` (Steger's
ridge strength, NaN for grey-centre) and ``flags`` (bits below).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from crossline.atomic import atomic_path
from crossline.errors import CrosslineError, StageError
from crossline.framestream import map_frames

try:
    import numba as _numba
except ImportError:  # pragma: no cover - depends on the environment
    _numba = None

log = logging.getLogger(__name__)

__all__ = [
    "CLOSE",
    "COLUMNS",
    "EDGE",
    "EXTRACTORS",
    "FLAG_NAMES",
    "FRAMES_PER_GROUP",
    "MERGED",
    "SATURATED",
    "STRIPES_SCHEMA",
    "empty_centres",
    "extract",
    "gather_stripes",
    "grey_centre",
    "read_stripes_meta",
    "run_extract_stripes",
    "steger",
]

MERGED = 1  # a run too wide for one stripe: two stripes merged (near the crossing)
CLOSE = 2  # another segment in the same column so near that the windows were clipped
SATURATED = 4  # a pixel of the window at full scale
EDGE = 8  # the run touches the top or bottom of the frame (the stripe may be cut)
FLAG_NAMES = {MERGED: "merged", CLOSE: "close", SATURATED: "saturated", EDGE: "edge"}

EXTRACTORS = ("grey_centre", "steger")
MERGE_FACTOR = 1.5  # a run wider than this many times the frame's median width is merged
BG_PIXELS = 2  # pixels beyond each end of a window that estimate the local background
NEIGHBOUR_DV = 2.5  # largest row step between the same stripe in adjacent columns, px
FRAMES_PER_GROUP = 64  # parquet row group = frames [64k, 64k + 64) of the scan

COLUMNS = ("u", "v", "strength", "peak", "width", "width_n", "nx", "ny", "ridge", "flags")
_F32 = ("strength", "peak", "width", "width_n", "nx", "ny", "ridge")

STRIPES_SCHEMA = pa.schema(
    [
        ("frame", pa.int64()),
        ("lasers", pa.string()),
        ("u", pa.float64()),
        ("v", pa.float64()),
        *[(c, pa.float32()) for c in _F32],
        ("flags", pa.uint8()),
    ]
)
_META_KEY = b"crossline"


def empty_centres() -> dict[str, np.ndarray]:
    """A centre table with no rows."""
    out = {c: np.empty(0, np.float64) for c in COLUMNS}
    out["flags"] = np.empty(0, np.uint8)
    return out


def full_scale(dtype: np.dtype) -> float:
    """Largest value of an image's sample type (255 for 8-bit, 65535 for 16-bit)."""
    dtype = np.dtype(dtype)
    if dtype.kind not in "ui":
        raise ValueError(f"stripe images must be unsigned integers, got {dtype}")
    return float(np.iinfo(dtype).max)


# ----------------------------------------------------------------------------- runs


def _int_threshold(thr: float, dtype: np.dtype) -> np.generic:
    """The integer t with ``I > t`` exactly when ``I > thr`` (a float compare is 10x slower)."""
    return np.dtype(dtype).type(min(np.floor(thr), np.iinfo(dtype).max))


def _runs(imT: np.ndarray, thr: float, min_width: float) -> tuple[np.ndarray, ...]:
    """Vertical runs above ``thr`` of the transposed image (one image column per row of ``imT``).

    Returns (col, r0, r1) with r1 inclusive, sorted by column then row; runs shorter than
    ``min_width`` are dropped.
    """
    H = imT.shape[1]
    idx = np.flatnonzero(imT > _int_threshold(thr, imT.dtype))
    if idx.size == 0:
        z = np.empty(0, np.int64)
        return z, z, z
    # a run ends where the flat index jumps, or where the next pixel starts a new column
    brk = np.flatnonzero((np.diff(idx) != 1) | (idx[1:] % H == 0)) + 1
    first = np.concatenate([[0], brk])
    last = np.concatenate([brk - 1, [idx.size - 1]])
    s, e = idx[first], idx[last]
    col = s // H
    r0 = s - col * H
    r1 = e - col * H
    keep = (r1 - r0 + 1) >= min_width
    return col[keep], r0[keep], r1[keep]


def _gaps(col: np.ndarray, r0: np.ndarray, r1: np.ndarray, H: int) -> tuple[np.ndarray, np.ndarray]:
    """Free pixels above and below each run, up to its neighbour in the column or the border."""
    gap_up = r0.astype(np.int64)  # pixels between the border and the run
    gap_dn = (H - 1 - r1).astype(np.int64)
    if col.size > 1:
        same = col[1:] == col[:-1]
        between = r0[1:] - r1[:-1] - 1
        gap_dn[:-1] = np.where(same, between, gap_dn[:-1])
        gap_up[1:] = np.where(same, between, gap_up[1:])
    return gap_up, gap_dn


def _slopes(u: np.ndarray, v: np.ndarray, H: int) -> np.ndarray:
    """Local slope dv/du of each centre from the nearest centres of the adjacent columns.

    Centres must be sorted by (u, v). A centre with no neighbour gets slope 0.
    """
    n = u.size
    if n == 0:
        return np.empty(0)
    big = 4.0 * (H + 1)
    key = u * big + v
    vals = []
    for du in (-1.0, 1.0):
        q = (u + du) * big + v
        j = np.searchsorted(key, q)
        best = np.full(n, np.inf)
        bv = np.full(n, np.nan)
        for jj in (j - 1, j):
            ok = (jj >= 0) & (jj < n)
            jc = np.clip(jj, 0, n - 1)
            d = np.where(ok & (u[jc] == u + du), np.abs(v[jc] - v), np.inf)
            better = d < best
            best = np.where(better, d, best)
            bv = np.where(better, v[jc], bv)
        vals.append(np.where(best <= NEIGHBOUR_DV, bv, np.nan))
    left, right = vals
    slope = np.where(
        np.isfinite(left) & np.isfinite(right),
        (right - left) / 2.0,
        np.where(np.isfinite(right), right - v, np.where(np.isfinite(left), v - left, 0.0)),
    )
    return slope


# ----------------------------------------------------------------------------- grey centre


def _jit(fn):
    """Compile ``fn`` with numba (nogil, cached) when numba is installed; else leave it Python."""
    if _numba is None:  # pragma: no cover - numba is a dependency; this keeps imports working
        return fn
    return _numba.njit(cache=True, nogil=True, boundscheck=False)(fn)


@_jit
def _runs_nb(idx: np.ndarray, H: int, min_width: float):  # pragma: no cover - compiled
    """numba twin of :func:`_runs` from the flat indices above the threshold."""
    n = idx.size
    col = np.empty(n, np.int64)
    r0 = np.empty(n, np.int64)
    r1 = np.empty(n, np.int64)
    k = 0
    s = 0
    for i in range(1, n + 1):
        if i == n or idx[i] != idx[i - 1] + 1 or idx[i] % H == 0:
            a = idx[s]
            b = idx[i - 1]
            c = a // H
            if b - a + 1 >= min_width:
                col[k] = c
                r0[k] = a - c * H
                r1[k] = b - c * H
                k += 1
            s = i
    return col[:k], r0[:k], r1[:k]


@_jit
def _windows_nb(flat, H, col, r0, r1, pad, bg_pixels, full):  # pragma: no cover - compiled
    """numba twin of the window phase of :func:`_grey_centre_numpy` (same arithmetic)."""
    k = col.size
    v = np.empty(k)
    sw = np.empty(k)
    peak = np.empty(k)
    flags = np.zeros(k, np.uint8)
    near = 2 * (pad + bg_pixels)
    for i in range(k):
        c = col[i]
        gu = r0[i]
        gd = H - 1 - r1[i]
        if i > 0 and col[i - 1] == c:
            gu = r0[i] - r1[i - 1] - 1
            if gu < near:
                flags[i] |= 2
        if i + 1 < k and col[i + 1] == c:
            gd = r0[i + 1] - r1[i] - 1
            if gd < near:
                flags[i] |= 2
        if r0[i] == 0 or r1[i] == H - 1:
            flags[i] |= 8
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


@_jit
def _slopes_nb(col, v, W, max_dv):  # pragma: no cover - compiled
    """numba twin of :func:`_slopes` (centres sorted by column, then row)."""
    k = col.size
    start = np.zeros(W + 2, np.int64)
    for i in range(k):
        start[col[i] + 2] += 1
    for c in range(1, W + 2):
        start[c] += start[c - 1]
    # start[c + 1] .. start[c + 2] are the centres of column c
    slope = np.zeros(k)
    for i in range(k):
        c = col[i]
        nb = np.empty(2)
        for side in range(2):
            cc = c - 1 if side == 0 else c + 1
            best = np.inf
            bv = np.nan
            if 0 <= cc < W:
                for j in range(start[cc + 1], start[cc + 2]):
                    d = abs(v[j] - v[i])
                    if d < best:
                        best = d
                        bv = v[j]
            nb[side] = bv if best <= max_dv else np.nan
        left = nb[0]
        right = nb[1]
        if np.isfinite(left) and np.isfinite(right):
            slope[i] = (right - left) / 2.0
        elif np.isfinite(right):
            slope[i] = right - v[i]
        elif np.isfinite(left):
            slope[i] = v[i] - left
    return slope


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


BACKENDS = ("auto", "numba", "numpy")


def _use_numba(backend: str) -> bool:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numba" and _numba is None:
        raise RuntimeError("backend 'numba' needs the numba package")
    return _numba is not None and backend != "numpy"


def grey_centre(
    img: np.ndarray,
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    pad: int = 2,
    backend: str = "auto",
) -> dict[str, np.ndarray]:
    """Grey-centre (eq. 9) of every stripe segment of every column of a grey frame.

    ``threshold`` is a fraction of full scale; ``min_width``/``max_width`` bound a run's
    length along the column (px); ``pad`` is how far the window reaches beyond the run.
    ``backend``: ``numba`` (compiled kernels), ``numpy`` (vectorised) or ``auto`` (numba if
    installed); both give the same centres. Returns a centre table (module doc) in
    frame-local pixels, sorted by (u, v).
    """
    full = full_scale(img.dtype)
    thr = threshold * full
    imT = np.ascontiguousarray(cv2.transpose(img))
    W, H = imT.shape
    flat = imT.reshape(-1)
    nb = _use_numba(backend)
    if nb:
        col, r0, r1 = _runs_nb(np.flatnonzero(imT > _int_threshold(thr, imT.dtype)), H, float(min_width))
    else:
        col, r0, r1 = _runs(imT, thr, min_width)
    k = col.size
    if k == 0:
        return empty_centres()
    if nb:
        v, sw, peak, flags = _windows_nb(flat, H, col, r0, r1, int(pad), BG_PIXELS, full)
    else:
        v, sw, peak, flags = _grey_windows_numpy(flat, H, col, r0, r1, int(pad), BG_PIXELS, full)
    good = np.isfinite(v)
    u = col.astype(np.float64)
    width = (r1 - r0 + 1).astype(np.float64)
    vv = np.where(good, v, 0.5 * (r0 + r1))
    slope = _slopes_nb(col, vv, W, NEIGHBOUR_DV) if nb else _slopes(u, vv, H)
    ny = 1.0 / np.sqrt(1.0 + slope * slope)
    nx = -slope * ny
    width_n = width * ny
    # merged stripes: wider than max_width, or than MERGE_FACTOR x the typical stripe here
    clean = (flags & (CLOSE | EDGE)) == 0
    typical = np.median(width_n[clean]) if clean.any() else np.median(width_n)
    flags[(width > max_width) | (width_n > MERGE_FACTOR * typical)] |= MERGED
    out = {
        "u": u, "v": v, "strength": sw, "peak": peak, "width": width, "width_n": width_n,
        "nx": nx, "ny": ny, "ridge": np.full(k, np.nan), "flags": flags,
    }
    if good.all():
        return out
    return {c: a[good] for c, a in out.items()}


# ----------------------------------------------------------------------------- Steger


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
) -> dict[str, np.ndarray]:
    """Steger's Hessian line detector, one centre per stripe per column (module doc).

    Candidates are the pixels of the runs above ``threshold`` (fraction of full scale) of
    at least ``min_width`` px; ``sigma`` is the Gaussian scale in px. Returns a centre table
    in frame-local pixels, sorted by (u, v).
    """
    full = full_scale(img.dtype)
    thr = threshold * full
    H, W = img.shape
    imT = np.ascontiguousarray(cv2.transpose(img))
    if _numba is not None:
        col, r0, r1 = _runs_nb(np.flatnonzero(imT > _int_threshold(thr, imT.dtype)), H, float(min_width))
    else:  # pragma: no cover - numba is a dependency
        col, r0, r1 = _runs(imT, thr, min_width)
    k = col.size
    if k == 0:
        return empty_centres()
    g = _smooth_band(img, col, r0, r1, sigma)
    if _numba is not None:
        seg, r, dv, g0, lam, nx, ny = _steger_nb(g, col, r0, r1)
    else:  # pragma: no cover - numba is a dependency
        seg, r, dv, g0, lam, nx, ny = _steger_nb.__wrapped__(g, col, r0, r1) \
            if hasattr(_steger_nb, "__wrapped__") else _steger_nb(g, col, r0, r1)
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
    flat = imT.reshape(-1)
    nrun = (r1 - r0 + 1).astype(np.int64)
    rstart = np.concatenate([[0], np.cumsum(nrun)[:-1]])
    rseg = np.repeat(np.arange(k), nrun)
    peak_run = np.maximum.reduceat(
        flat[col[rseg] * H + r0[rseg] + (np.arange(int(nrun.sum())) - rstart[rseg])], rstart
    ).astype(np.float64)
    flags_run[peak_run >= full] |= SATURATED
    per_run = np.bincount(seg, minlength=k)
    wn_run = width_run * _run_ny(col, r0, r1, W)
    typical = np.median(wn_run)
    merged_run = (width_run > max_width) | (wn_run > MERGE_FACTOR * typical)
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
    slope = _slopes_nb(col, mid, W, NEIGHBOUR_DV)
    return 1.0 / np.sqrt(1.0 + slope * slope)


def extract(
    img: np.ndarray,
    extractor: str = "grey_centre",
    *,
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    sigma: float = 2.0,
    pad: int = 2,
) -> dict[str, np.ndarray]:
    """Centre table of one frame with the chosen extractor (``grey_centre`` or ``steger``)."""
    if extractor == "grey_centre":
        return grey_centre(img, threshold, min_width, max_width, pad)
    if extractor == "steger":
        return steger(img, threshold, min_width, max_width, sigma)
    raise ValueError(f"unknown extractor {extractor!r}; expected one of {EXTRACTORS}")


# ----------------------------------------------------------------------------- stage


def _table(frame: int, state: str, c: dict[str, np.ndarray], du: float, dv: float) -> pa.Table:
    n = c["u"].size
    cols = {
        "frame": pa.array(np.full(n, frame, np.int64)),
        "lasers": pa.array([state] * n, pa.string()),
        "u": pa.array(c["u"].astype(np.float64) + du),
        "v": pa.array(c["v"].astype(np.float64) + dv),
    }
    for name in _F32:
        cols[name] = pa.array(c[name].astype(np.float32))
    cols["flags"] = pa.array(c["flags"].astype(np.uint8))
    return pa.table(cols, schema=STRIPES_SCHEMA)


def _chunk_bounds(n_frames: int, chunk: tuple[int, int]) -> tuple[int, int]:
    i, n = chunk
    if n < 1 or not 0 <= i < n:
        raise StageError(f"chunk must be (i, n) with 0 <= i < n, got {chunk}")
    return i * n_frames // n, (i + 1) * n_frames // n


class _GroupedWriter:
    """Parquet writer whose row groups hold the frames ``[64k, 64k + 64)`` of a scan.

    The same rows give the same file whether they come from one run or from gathered
    chunks: a row group is a maximal run of rows whose ``frame // FRAMES_PER_GROUP`` is
    equal, whichever process wrote them.
    """

    def __init__(self, path: Path):
        # dictionary encoding only where values repeat: on float columns it costs 3x the time
        self.writer = pq.ParquetWriter(path, STRIPES_SCHEMA, compression="zstd",
                                       use_dictionary=["frame", "lasers", "flags"],
                                       write_statistics=["frame"])
        self.buf: list[pa.Table] = []
        self.group: int | None = None
        self.rows = 0

    def add(self, table: pa.Table) -> None:
        if table.num_rows == 0:
            return
        g = int(table.column("frame")[0].as_py()) // FRAMES_PER_GROUP
        if self.group is not None and g != self.group:
            self.flush()
        self.group = g
        self.buf.append(table)

    def flush(self) -> None:
        if self.buf:
            t = pa.concat_tables(self.buf).combine_chunks()
            self.writer.write_table(t, row_group_size=t.num_rows)
            self.rows += t.num_rows
        self.buf = []

    def close(self, meta: dict[str, Any]) -> None:
        self.flush()
        self.writer.add_key_value_metadata({_META_KEY: json.dumps(meta, sort_keys=True)})
        self.writer.close()


def _frame_work(extractor: str, params: dict[str, Any]):
    def fn(i: int, img: np.ndarray) -> dict[str, np.ndarray]:
        return extract(img, extractor, **params)

    return fn


def run_extract_stripes(
    capture: str | Path,
    scan: str,
    out: str | Path,
    *,
    extractor: str = "grey_centre",
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    sigma: float = 2.0,
    chunk: tuple[int, int] = (0, 1),
    threads: int = 1,
    pad: int = 2,
    decoder: str = "auto",
) -> dict[str, Any]:
    """Extract the stripe centres of one scan's frames (or one chunk of them) to parquet.

    Frames are read once and streamed through ``threads`` worker threads; centres are
    stored in full-sensor pixels with the frame's laser state. The parquet's schema
    metadata (key ``crossline``) holds the parameters and counts. Returns that metadata.
    """
    from crossline.capture import open_capture

    if extractor not in EXTRACTORS:
        raise StageError(f"unknown extractor {extractor!r}; expected one of {EXTRACTORS}")
    if not 0 < threshold < 1:
        raise StageError(f"threshold is a fraction of full scale in (0, 1), got {threshold}")
    cap = open_capture(capture)
    if scan not in cap.scans:
        raise StageError(f"capture {cap.root}: no scan {scan!r} (known: {sorted(cap.scans)})")
    sc = cap.scans[scan]
    win = cap.rig.scan_window
    lo, hi = _chunk_bounds(len(sc.frames), chunk)
    frames = sc.frames[lo:hi]
    states = sc.lasers[lo:hi]
    params = {"threshold": threshold, "min_width": min_width, "max_width": max_width}
    if extractor == "steger":
        params["sigma"] = sigma
    else:
        params["pad"] = int(pad)
    meta: dict[str, Any] = {
        "scan": scan, "extractor": extractor, "params": params,
        "scan_window": [win.x, win.y, win.width, win.height],
        "frames_in_scan": len(sc.frames),
    }
    counts = {"frames": 0, "frames_without_stripe": 0, "centres": 0,
              **{f"flag_{name}": 0 for name in FLAG_NAMES.values()}}
    t0 = time.perf_counter()
    paths = [sc.frame_path(f) for f in frames]
    with atomic_path(out) as tmp:
        writer = _GroupedWriter(tmp)
        it = map_frames(paths, _frame_work(extractor, params), shape=(win.height, win.width),
                        threads=threads, decoder=decoder)
        try:
            for j, c in enumerate(it):
                counts["frames"] += 1
                nc = c["u"].size
                counts["frames_without_stripe"] += nc == 0
                counts["centres"] += nc
                for bit, name in FLAG_NAMES.items():
                    counts[f"flag_{name}"] += int(np.count_nonzero(c["flags"] & bit))
                writer.add(_table(int(frames[j]), str(states[j]), c, win.x, win.y))
        except CrosslineError as exc:
            raise StageError(f"scan {scan}: {exc}") from exc
        if chunk[1] == 1 and counts["centres"] == 0:
            raise StageError(
                f"scan {scan}: no stripe found in any of its {counts['frames']} frames "
                f"(threshold {threshold} of full scale); are the lasers on, is the exposure right?"
            )
        meta["counts"] = counts
        meta["chunk"] = list(chunk)
        meta["frame_range"] = [lo, hi]
        writer.close(meta)
    dt = time.perf_counter() - t0
    log.info("scan %s: %d frames, %d centres, %.1f frames/s (%s, %d threads)", scan,
             counts["frames"], counts["centres"], counts["frames"] / max(dt, 1e-9), extractor, threads)
    return meta


def read_stripes_meta(path: str | Path) -> dict[str, Any]:
    """The parameters and counts stored in a stripes parquet's schema metadata."""
    md = pq.ParquetFile(path).metadata.metadata or {}
    if _META_KEY not in md:
        raise StageError(f"{path}: not a stripes file (no crossline metadata)")
    return json.loads(md[_META_KEY])


def iter_stripe_groups(path: str | Path) -> Iterator[pd.DataFrame]:
    """The row groups of a stripes parquet, in order, as DataFrames."""
    pf = pq.ParquetFile(path)
    for g in range(pf.num_row_groups):
        yield pf.read_row_group(g).to_pandas()


def gather_stripes(chunks: Iterable[str | Path], out: str | Path) -> dict[str, Any]:
    """Join chunk files of one scan into the table an unsplit run writes (same bytes)."""
    chunks = [Path(c) for c in chunks]
    if not chunks:
        raise StageError("gather-stripes: no chunk files given")
    metas = [read_stripes_meta(c) for c in chunks]
    order = sorted(range(len(chunks)), key=lambda k: metas[k]["frame_range"][0])
    chunks = [chunks[k] for k in order]
    metas = [metas[k] for k in order]
    first = metas[0]
    for c, m in zip(chunks, metas, strict=True):
        for key in ("scan", "extractor", "params", "scan_window", "frames_in_scan"):
            if m[key] != first[key]:
                raise StageError(f"{c}: {key} {m[key]!r} differs from {chunks[0]}'s {first[key]!r}")
    pos = 0
    for c, m in zip(chunks, metas, strict=True):
        if m["frame_range"][0] != pos:
            raise StageError(f"{c}: covers frames {m['frame_range']}, expected to start at {pos} "
                             f"(a chunk is missing or repeated)")
        pos = m["frame_range"][1]
    if pos != first["frames_in_scan"]:
        raise StageError(f"chunks cover {pos} of the scan's {first['frames_in_scan']} frames")
    counts: dict[str, int] = {}
    for m in metas:
        for k, v in m["counts"].items():
            counts[k] = counts.get(k, 0) + int(v)
    meta = {k: first[k] for k in ("scan", "extractor", "params", "scan_window", "frames_in_scan")}
    meta["counts"] = counts
    meta["chunk"] = [0, 1]
    meta["frame_range"] = [0, pos]
    if counts["centres"] == 0:
        raise StageError(f"scan {first['scan']}: no stripe found in any of its {counts['frames']} frames")
    with atomic_path(out) as tmp:
        writer = _GroupedWriter(tmp)
        for c in chunks:
            pf = pq.ParquetFile(c)
            for g in range(pf.num_row_groups):
                t = pf.read_row_group(g).replace_schema_metadata(None).cast(STRIPES_SCHEMA)
                writer.add(t)
        writer.close(meta)
    return meta
