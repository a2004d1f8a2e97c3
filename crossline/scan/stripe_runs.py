"""Runs above the threshold along each image column, and what the extractors share about them.

Split from :mod:`crossline.scan.stripes` (issue 21.3). Every extractor starts from the same
runs: vertical runs of pixels above the frame's threshold, in the frame as (width, height), one
image column per row (:func:`_candidate_runs`: numba :func:`_runs_nb` or numpy :func:`_runs`);
the free pixels between neighbouring runs of a column (:func:`_gaps`); the stripe's local slope
from the adjacent columns (:func:`_slopes`, :func:`_slopes_nb`); each run's brightest pixel
(:func:`_run_peaks`) and the test for two stripes merged into one run (:func:`_merged`). Also
here: the centre table's columns (:data:`COLUMNS`, :func:`empty_centres`; the table is described
in :mod:`crossline.scan.stripes`) and the choice of backend (numba or numpy).

The numba kernels here call no kernel of another file and read only this file's constants:
numba's on-disk cache is invalidated by edits to a kernel's own file only.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.jit import HAVE_NUMBA
from crossline.jit import jit as _jit

__all__ = [
    "BACKENDS",
    "BG_PIXELS",
    "COLUMNS",
    "MERGE_FACTOR",
    "NEIGHBOUR_DV",
    "STEEP_LENGTH_RATIO",
    "empty_centres",
]

COLUMNS = ("u", "v", "strength", "peak", "width", "width_n", "nx", "ny", "ridge", "flags", "axis")
MERGE_FACTOR = 1.5  # a run wider than this many times the frame's median width is merged
BG_PIXELS = 2  # pixels beyond each end of a window that estimate the local background
NEIGHBOUR_DV = 2.5  # largest row step between the same stripe in adjacent columns, px
STEEP_LENGTH_RATIO = 0.67  # runs of a steep stripe in adjacent columns differ in length by less


def empty_centres() -> dict[str, np.ndarray]:
    """A centre table with no rows."""
    out = {c: np.empty(0, np.float64) for c in COLUMNS if c != "axis"}
    out["flags"] = np.empty(0, np.uint8)
    return out


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
    """Free pixels above and below each run up to its neighbour in the column, and twice those
    up to the border (a window takes half the gap to a neighbour, all of it to the border)."""
    gap_up = 2 * r0.astype(np.int64)
    gap_dn = 2 * (H - 1 - r1).astype(np.int64)
    if col.size > 1:
        same = col[1:] == col[:-1]
        between = r0[1:] - r1[:-1] - 1
        gap_dn[:-1] = np.where(same, between, gap_dn[:-1])
        gap_up[1:] = np.where(same, between, gap_up[1:])
    return gap_up, gap_dn


def _slopes(u: np.ndarray, v: np.ndarray, H: int, width: np.ndarray) -> np.ndarray:
    """Local slope dv/du of each centre from the nearest centres of the adjacent columns.

    A neighbour is the same stripe if it lies within NEIGHBOUR_DV rows, or, for a steep stripe
    (whose runs are long and move by about their length per column), within the run's length
    with a run of similar length (a merged crossing next to a single stripe is not similar).
    Centres must be sorted by (u, v); ``width`` is each centre's run length. A centre with
    no neighbour gets slope 0.
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
        bw = np.full(n, np.nan)
        for jj in (j - 1, j):
            ok = (jj >= 0) & (jj < n)
            jc = np.clip(jj, 0, n - 1)
            d = np.where(ok & (u[jc] == u + du), np.abs(v[jc] - v), np.inf)
            better = d < best
            best = np.where(better, d, best)
            bv = np.where(better, v[jc], bv)
            bw = np.where(better, width[jc], bw)
        with np.errstate(invalid="ignore"):
            similar = (bw >= STEEP_LENGTH_RATIO * width) & (width >= STEEP_LENGTH_RATIO * bw)
            same = (best <= NEIGHBOUR_DV) | ((best <= width) & similar)
        vals.append(np.where(same, bv, np.nan))
    left, right = vals
    slope = np.where(
        np.isfinite(left) & np.isfinite(right),
        (right - left) / 2.0,
        np.where(np.isfinite(right), right - v, np.where(np.isfinite(left), v - left, 0.0)),
    )
    return slope


def _run_peaks(flat: np.ndarray, H: int, col: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Brightest value of each run of the flattened transposed image."""
    nrun = (r1 - r0 + 1).astype(np.int64)
    rstart = np.concatenate([[0], np.cumsum(nrun)[:-1]])
    rseg = np.repeat(np.arange(col.size), nrun)
    idx = col[rseg] * H + r0[rseg] + (np.arange(int(nrun.sum())) - rstart[rseg])
    return np.maximum.reduceat(flat[idx], rstart).astype(np.float64)


def _candidate_runs(src: np.ndarray, thr: float, min_width: float, nb: bool = True) -> tuple[np.ndarray, ...]:
    """The runs (col, r0, r1) above ``thr`` of an image as (width, height), at least ``min_width`` long."""
    if nb:
        return _runs_nb(np.flatnonzero(src > _int_threshold(thr, src.dtype)), src.shape[1], float(min_width))
    return _runs(src, thr, min_width)


def _merged(src: np.ndarray, col: np.ndarray, r0: np.ndarray, r1: np.ndarray, width: np.ndarray,
            width_n: np.ndarray, thr: float, max_width: float, clean: np.ndarray | None = None) -> np.ndarray:
    """Runs too wide for one stripe (``MERGED``): wider than ``max_width``, or across the stripe
    (``width_n``) wider than ``MERGE_FACTOR`` times the frame's typical single stripe.

    A run's width above a threshold grows with its height over it, as ``2 sigma sqrt(2 ln(A /
    t))`` for a Gaussian profile of height ``A`` over a threshold ``t`` above the local
    background: a bright stripe on a light face is wider above a frame's threshold than the
    same sheet on a dark plate. Widths are compared after dividing that growth out (``A / t``
    at least 2), the background being the darker of the pixels ``BG_PIXELS`` beyond each end.
    ``src`` is the image (as (width, height)) the runs were found in, ``clean`` marks the runs
    the typical width is taken from (default: all).
    """
    H = src.shape[1]
    flat = src.reshape(-1)
    peak = _run_peaks(flat, H, col, r0, r1)
    base = col * H
    bg = np.minimum(flat[base + np.maximum(r0 - BG_PIXELS, 0)],
                    flat[base + np.minimum(r1 + BG_PIXELS, H - 1)]).astype(np.float64)
    ratio = (peak - bg) / np.maximum(thr - bg, 1.0)
    wn = width_n / np.sqrt(2.0 * np.log(np.maximum(ratio, 2.0)))
    pick = wn[clean] if clean is not None and clean.any() else wn
    typical = float(np.median(pick)) if pick.size else 0.0
    return (width > max_width) | (wn > MERGE_FACTOR * typical)


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
def _slopes_nb(col, v, W, width):  # pragma: no cover - compiled
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
            bw = np.nan
            if 0 <= cc < W:
                for j in range(start[cc + 1], start[cc + 2]):
                    d = abs(v[j] - v[i])
                    if d < best:
                        best = d
                        bv = v[j]
                        bw = width[j]
            similar = bw >= STEEP_LENGTH_RATIO * width[i] and width[i] >= STEEP_LENGTH_RATIO * bw
            same = best <= NEIGHBOUR_DV or (best <= width[i] and similar)
            nb[side] = bv if same else np.nan
        left = nb[0]
        right = nb[1]
        if np.isfinite(left) and np.isfinite(right):
            slope[i] = (right - left) / 2.0
        elif np.isfinite(right):
            slope[i] = right - v[i]
        elif np.isfinite(left):
            slope[i] = v[i] - left
    return slope


BACKENDS = ("auto", "numba", "numpy")


def _columns(img: np.ndarray, transposed: bool) -> np.ndarray:
    """The frame with each image column contiguous: (width, height), C order."""
    if transposed:
        return np.ascontiguousarray(img)
    return np.ascontiguousarray(cv2.transpose(img))


def _use_numba(backend: str) -> bool:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numba" and not HAVE_NUMBA:
        raise RuntimeError("backend 'numba' needs the numba package")
    return HAVE_NUMBA and backend != "numpy"
