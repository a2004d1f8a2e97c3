"""Stripe centres of laser frames: the paper's grey-centre (eq. 9-13), a speckle-aware Gaussian
fit, and Steger's detector.

All three work column by column, as the paper does: every image column ``u`` may hold
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

Gaussian fit (:func:`gaussian`). Laser speckle, not the sensor, limits a stripe centre: it
multiplies the stripe by a random field of contrast 0.1-0.3 (Dorsch, Häusler & Herrmann,
Appl. Opt. 33, 1994), while the sensor adds noise of a fraction of a DN. Under that noise the
intensity centroid is far from efficient (it leans on the bright core, whose errors are
largest). The fit models the profile as ``a exp(-(v - c)^2 / 2 s^2)`` over the run widened by
``pad`` px or half the run's length, whichever is more (a steep stripe's long run has long
tails along the column), never past the gap's midpoint to a neighbouring run less the
background pixels, on a background line fitted beyond both ends, and weights each pixel by the
inverse of its variance ``r^2 yhat^2 + sigma_n^2`` (relative noise ``r``, sensor noise
``sigma_n``), which is maximum likelihood for that noise; clipped pixels carry no weight.
Both noise levels are measured in the frame: ``sigma_n`` from the residuals of the
background lines, ``r`` from the relative residuals of the bright pixels of a first fit.
On the virtual rigs it finds the speckle contrast they render (0.15, 0.20) and stays within
5 % of the Cramér-Rao bound of the centre (``tests/test_stripes.py``). A column cuts a steep
stripe obliquely, and where the stripe is curved (a ball, a cylinder, the edge of a part) the
profile along the column is skewed towards the centre of curvature, and its fitted centre with
it: by about ``2.5 sigma_col^2 s^2 v'' / (1 + s^2)^2`` rows for slope ``s`` and curvature
``v''`` (0.3 px normal to the line on a ring of 100 px radius at slopes 1.5-3, tested), which
makes a ball small. So stripes steeper than ``ACROSS_SLOPE`` are fitted again *across* the
stripe (``across=True``): the profile is sampled bilinearly along the normal (each sample the
mean over the stripe length one column holds, so it sees the column's pixels), fitted with
the same weighted Gaussian, and the ridge carried along the line back to the column
(``v = c + t / n_y``, as Steger does).

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

from crossline.errors import CrosslineError, StageError
from crossline.io.atomic import atomic_path
from crossline.jit import HAVE_NUMBA
from crossline.jit import jit as _jit
from crossline.scan.frames import map_frames

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
    "gaussian",
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

EXTRACTORS = ("grey_centre", "gaussian", "steger")
MERGE_FACTOR = 1.5  # a run wider than this many times the frame's median width is merged
BG_PIXELS = 2  # pixels beyond each end of a window that estimate the local background
BG_FIT_PIXELS = 3  # gaussian: pixels beyond each end of a window that the background line is fitted to
RELATIVE_NOISE_START = 0.15  # gaussian: relative (speckle) noise of the first fit, before it is estimated
RELATIVE_NOISE_SAMPLE = 4  # gaussian: every 4th clean stripe profile of a frame estimates it
NEIGHBOUR_DV = 2.5  # largest row step between the same stripe in adjacent columns, px
STEEP_LENGTH_RATIO = 0.67  # runs of a steep stripe in adjacent columns differ in length by less
RIDGE_FRACTION = 0.5  # Steger: a run's ridge claims weaker than this share of its strongest are dropped
ACROSS_SLOPE = 0.3  # gaussian: stripes steeper than this (|dv/du|) are refitted across the stripe
ROW_SLOPE = 4.0  # stripes steeper than this (|dv/du|, 76 deg) are profiled along the rows
MIN_STEEP_ROWS = 48  # ... where the steep stretch spans this many rows (not a curve's steep end)
FRAMES_PER_GROUP = 64  # parquet row group = frames [64k, 64k + 64) of the scan
DATA_BITS = (8, 10, 12, 14, 16)  # ADC ranges a camera may write into its images' containers
NOISE_K = 6.0  # a stripe stands at least this many background-noise sigmas above the background
PEAK_QUANTILE = 0.9  # the stripe's peak: this quantile of the stripe columns' brightest pixels
MIN_STRIPE_COLUMNS = 3  # fewer columns above the noise floor: the frame holds no stripe
LEVEL_STEP = 5  # background and noise from every 5th pixel of every 5th column
DATA_RANGE_FRAMES = 16  # frames spread over a scan that the data range is inferred from
CHANNEL_DISC_PX = 31  # wider than a stripe (3-12 px, more where it grazes a surface)

COLUMNS = ("u", "v", "strength", "peak", "width", "width_n", "nx", "ny", "ridge", "flags", "axis")
_F32 = ("strength", "peak", "width", "width_n", "nx", "ny", "ridge")

STRIPES_SCHEMA = pa.schema(
    [
        ("frame", pa.int64()),
        ("lasers", pa.string()),
        ("u", pa.float64()),
        ("v", pa.float64()),
        *[(c, pa.float32()) for c in _F32],
        ("flags", pa.uint8()),
        ("axis", pa.uint8()),
    ]
)
_META_KEY = b"crossline"


def empty_centres() -> dict[str, np.ndarray]:
    """A centre table with no rows."""
    out = {c: np.empty(0, np.float64) for c in COLUMNS if c != "axis"}
    out["flags"] = np.empty(0, np.uint8)
    return out


def full_scale(dtype: np.dtype) -> float:
    """Largest value of an image's sample type (255 for 8-bit, 65535 for 16-bit)."""
    dtype = np.dtype(dtype)
    if dtype.kind not in "ui":
        raise ValueError(f"stripe images must be unsigned integers, got {dtype}")
    return float(np.iinfo(dtype).max)


def data_bits_for(max_value: float) -> int:
    """Fewest ADC bits (one of :data:`DATA_BITS`) whose range ``0 .. 2^b - 1`` holds ``max_value``."""
    for b in DATA_BITS:
        if max_value <= 2**b - 1:
            return b
    return DATA_BITS[-1]


def frame_levels(imT: np.ndarray, threshold: float, data_max: float | None = None) -> dict[str, float]:
    """The intensity levels of one frame (as (width, height)) that set its stripe threshold.

    ``background`` is the median of a sparse sample (the stripes cover a few per cent of a
    frame). ``noise`` is the sensor's: from differences of vertically adjacent pixels of the
    sample's columns, which a scene's own contrast (a light part on a dark table, a surface lit
    by the room) does not reach, the RMS of those within 5 robust sigmas over sqrt(2)
    (robust where the data are quantised to a fraction of a count; at least the quantisation's
    ``sqrt(1/12)``). ``peak`` is the ``PEAK_QUANTILE`` quantile of the brightest pixel of the
    columns whose brightest pixel stands ``NOISE_K`` noise sigmas above the background (the
    columns that hold a stripe). The threshold ``level`` is ``background + threshold (peak -
    background)``, never below ``background + NOISE_K noise``; a frame without stripe columns
    has ``level = inf``. ``data_max`` (default: the frame's own maximum rounded up to a whole
    number of bits) is the saturation level.
    """
    # by histograms of the sample: integer data, and a sort of it would cost a frame's fit
    sample = imT[::LEVEL_STEP]
    hist = np.bincount(np.ascontiguousarray(sample[:, ::LEVEL_STEP]).ravel())
    half = 0.5 * hist.sum()
    bg = float(np.searchsorted(np.cumsum(hist), half))
    a = sample[:, 0:-1:LEVEL_STEP]
    d = np.abs(a.astype(np.int32) - sample[:, 1::LEVEL_STEP][:, : a.shape[1]]).ravel()
    dh = np.bincount(d)
    dv = np.arange(dh.size, dtype=np.float64)
    mad = 1.4826 * float(np.searchsorted(np.cumsum(dh), 0.5 * dh.sum()))
    near = dv <= 5.0 * max(mad, 1.0)
    noise = float(np.sqrt((dh[near] * dv[near] ** 2).sum() / max(dh[near].sum(), 1) / 2.0))
    noise = max(noise, float(np.sqrt(1.0 / 12.0)))
    cm = imT.max(axis=1)
    top = float(cm.max()) if cm.size else 0.0
    if data_max is None:
        data_max = 255.0 if imT.dtype == np.uint8 else float(2 ** data_bits_for(top) - 1)
    stripe_cols = cm[cm > bg + NOISE_K * noise]
    if stripe_cols.size < MIN_STRIPE_COLUMNS:
        peak, level = float("nan"), float("inf")
    else:
        peak = float(np.quantile(stripe_cols, PEAK_QUANTILE))
        level = max(bg + threshold * (peak - bg), bg + NOISE_K * noise)
    return {"background": bg, "noise": noise, "peak": peak, "level": level, "data_max": float(data_max)}


def _level_and_max(imT: np.ndarray, threshold: float, level: float | None,
                   data_max: float | None) -> tuple[float, float]:
    """The absolute threshold and saturation level of a frame: given, or from its statistics."""
    if level is not None:
        top = float(np.iinfo(imT.dtype).max) if imT.dtype == np.uint8 else None
        if data_max is None:
            data_max = top if top is not None else float(2 ** data_bits_for(float(imT.max())) - 1)
        return float(level), float(data_max)
    lv = frame_levels(imT, threshold, data_max)
    return lv["level"], lv["data_max"]


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


# ----------------------------------------------------------------------------- grey centre


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


def grey_centre(
    img: np.ndarray,
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    pad: int = 2,
    backend: str = "auto",
    transposed: bool = False,
    *,
    data_max: float | None = None,
    level: float | None = None,
    detect: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Grey-centre (eq. 9) of every stripe segment of every column of a grey frame.

    ``threshold`` is a fraction of the stripe's peak above the background, with a floor at
    ``NOISE_K`` noise sigmas (:func:`frame_levels`), or ``level`` the threshold in counts;
    ``data_max`` is the sensor's saturation level (default: inferred from the frame's
    maximum, :func:`frame_levels`). ``min_width``/``max_width`` bound a run's
    length along the column (px); ``pad`` is how far the window reaches beyond the run.
    ``backend``: ``numba`` (compiled kernels), ``numpy`` (vectorised) or ``auto`` (numba if
    installed); both give the same centres. ``transposed``: ``img`` is the frame as
    (width, height), e.g. from ``read_frame(..., transposed=True)`` (same centres, no
    transpose here). ``detect``, an image of the same layout (the frame less its local
    background, say), is where the runs above ``level`` are found instead of ``img``; the
    profiles are always ``img``'s. Returns a centre table (module doc) in frame-local pixels,
    sorted by (u, v).
    """
    full_scale(img.dtype)  # unsigned integers only
    imT = _columns(img, transposed)
    src = imT if detect is None else _columns(detect, transposed)
    thr, full = _level_and_max(src, threshold, level, data_max)
    W, H = imT.shape
    flat = imT.reshape(-1)
    nb = _use_numba(backend)
    col, r0, r1 = _candidate_runs(src, thr, min_width, nb)
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
    slope = _slopes_nb(col, vv, W, width) if nb else _slopes(u, vv, H, width)
    ny = 1.0 / np.sqrt(1.0 + slope * slope)
    nx = -slope * ny
    width_n = width * ny
    # merged stripes: wider than max_width, or than MERGE_FACTOR x the typical stripe here
    flags[_merged(src, col, r0, r1, width, width_n, thr, max_width, (flags & (CLOSE | EDGE)) == 0)] |= MERGED
    out = {
        "u": u, "v": v, "strength": sw, "peak": peak, "width": width, "width_n": width_n,
        "nx": nx, "ny": ny, "ridge": np.full(k, np.nan), "flags": flags,
    }
    if good.all():
        return out
    return {c: a[good] for c, a in out.items()}


# ----------------------------------------------------------------------------- Gaussian fit


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
    neighbouring columns' centres) are fitted again across the stripe (module doc), which
    removes the column cut's bias towards the centre of curvature of a curved stripe. The
    window's intensity centroid is the start; a refit that does not converge within a pixel
    of it, or whose width is off the frame's other refits, is fitted along its column instead.
    Returns a centre table (module doc) in frame-local pixels, sorted by (u, v)
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
    *,
    data_max: float | None = None,
    level: float | None = None,
    detect: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Steger's Hessian line detector, one centre per stripe per column (module doc).

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


# ----------------------------------------------------------------------------- any angle


@_jit
def _run_lengths_nb(imT, thr, q0, q1):  # pragma: no cover - compiled
    """Length of the run above ``thr`` along the second axis of ``imT`` through each pixel
    ``imT[q0[i], q1[i]]`` (0 where that pixel is not above it, or lies outside)."""
    A, B = imT.shape
    out = np.zeros(q0.size, np.int64)
    for i in range(q0.size):
        a = q0[i]
        b = q1[i]
        if a < 0 or a >= A or b < 0 or b >= B or not imT[a, b] > thr:
            continue
        lo = b
        while lo > 0 and imT[a, lo - 1] > thr:
            lo -= 1
        hi = b
        while hi < B - 1 and imT[a, hi + 1] > thr:
            hi += 1
        out[i] = hi - lo + 1
    return out


@_jit
def _has_long_run_nb(imT, thr, stride, longest):  # pragma: no cover - compiled
    """Whether any ``stride``-th row of ``imT`` holds a run above ``thr`` longer than ``longest``."""
    A, B = imT.shape
    for a in range(0, A, stride):
        n = 0
        for b in range(B):
            if imT[a, b] > thr:
                n += 1
                if n > longest:
                    return True
            else:
                n = 0
    return False


def _long_steep(row: np.ndarray, col: np.ndarray, cand: np.ndarray, shape_T: tuple[int, int]) -> np.ndarray:
    """Which candidate row centres lie on a steep stretch spanning ``MIN_STEEP_ROWS`` rows or more.

    The candidates' pixels are marked and joined (8-connected; a stripe steeper than
    ``ROW_SLOPE`` moves less than a pixel per row), and stretches shorter than that are left
    to the column profiles: the steep ends of a curve (a ball's rim) stay as they were.
    """
    W, H = shape_T
    out = np.zeros(row.size, bool)
    if not cand.any():
        return out
    rr = row[cand].astype(np.int64)
    cc = np.round(col[cand]).astype(np.int64).clip(0, W - 1)
    mask = np.zeros((H, W), np.uint8)
    mask[rr, cc] = 1
    mask = cv2.dilate(mask, np.ones((3, 1), np.uint8))  # bridge a row whose fit failed
    _n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    tall = stats[:, cv2.CC_STAT_HEIGHT] >= min(MIN_STEEP_ROWS, H // 2)
    out[np.flatnonzero(cand)] = tall[lab[rr, cc]]
    return out


def _swap_axes(c: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A centre table of the transposed frame in the frame's own (u, v), normals with ny >= 0."""
    out = dict(c)
    out["u"], out["v"] = c["v"], c["u"]
    nx, ny = c["ny"], c["nx"]
    sign = np.where(ny < 0, -1.0, 1.0)
    out["nx"], out["ny"] = nx * sign, ny * sign
    return out


def any_angle(columns_fn, imT: np.ndarray, level: float, max_width: float,
              detect: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Centres of stripes at any angle: profiles along the columns, and along the rows where
    the stripe is steeper than ``ROW_SLOPE``.

    ``columns_fn(a, d)`` extracts the centres of an image given as (width, height), profiling
    along its second axis, from the runs above the absolute threshold ``level`` of ``d`` (the
    same layout; ``None``: of ``a``); ``detect`` is that image for the frame. It runs on the frame
    (``imT``, the frame as (width, height)) and, when that finds stripes steeper than
    ``ROW_SLOPE`` rows per column or the frame holds column runs longer than ``ROW_SLOPE``
    times the typical run (``max_width`` at most), on the transposed frame. Each
    row centre is kept where the column run through its pixel is more than ``ROW_SLOPE`` times
    its own, on a steep stretch of ``MIN_STEEP_ROWS`` rows or more (:func:`_long_steep`); the
    column centres inside the runs of the row centres kept give way to them. Returns the
    centre table with ``axis`` (0: profile along the column, ``u`` integer; 1: along the row,
    ``v`` integer), sorted by (u, v).
    """
    c = columns_fn(imT, detect)
    n = c["u"].size
    c["axis"] = np.zeros(n, np.uint8)
    if not np.isfinite(level):
        return c
    src = imT if detect is None else detect
    thr = _int_threshold(level, src.dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.abs(c["nx"] / c["ny"])
    # a steep stripe's column runs are long (a fit may have failed on them: look at the runs);
    # every second column is enough for a stripe two pixels wide
    typical = float(np.median(c["width"])) if n else 2.0
    longest = int(min(max_width, ROW_SLOPE * typical))
    if not (np.any(slope > ROW_SLOPE) or _has_long_run_nb(src, thr, 2, longest)):
        return c
    imR = np.ascontiguousarray(cv2.transpose(imT))  # the frame as (height, width)
    r = columns_fn(imR, None if detect is None else np.ascontiguousarray(cv2.transpose(detect)))
    # the column run through each row centre's pixel
    lc = _run_lengths_nb(src, thr, np.round(r["v"]).astype(np.int64), r["u"].astype(np.int64))
    keep_r = lc > ROW_SLOPE * r["width"]
    keep_r &= _long_steep(r["u"], r["v"], keep_r, imT.shape)
    if not keep_r.any():
        return c
    # the steep stretches the rows profile are theirs: a column centre whose pixel lies in one
    # of their runs (a pixel of margin: the flanks, where noise crosses the threshold) goes
    W, H = imT.shape
    half = 0.5 * r["width"][keep_r] + 1.0
    c0 = np.floor(r["v"][keep_r] - half).astype(np.int64)
    n_px = np.ceil(r["v"][keep_r] + half).astype(np.int64) - c0 + 1
    first = np.repeat(np.cumsum(n_px) - n_px, n_px)
    start = np.repeat(c0, n_px) + (np.arange(int(n_px.sum())) - first)
    taken = np.zeros((H, W), bool)
    taken[np.repeat(r["u"][keep_r].astype(np.int64), n_px), start.clip(0, W - 1)] = True
    cu = c["u"].astype(np.int64)
    cv_ = np.round(c["v"]).astype(np.int64).clip(0, H - 1)
    keep_c = ~taken[cv_, cu]
    r = _swap_axes({k: x[keep_r] for k, x in r.items()})
    r["axis"] = np.ones(int(keep_r.sum()), np.uint8)
    out = {k: np.concatenate([c[k][keep_c], r[k]]) for k in c}
    o = np.lexsort((out["v"], out["u"]))
    return {k: x[o] for k, x in out.items()}


def remove_local_background(imT: np.ndarray, max_width: float) -> np.ndarray:
    """The frame (as (width, height)) less its local background: a grey opening by a square a
    little wider than ``max_width`` (the widest stripe run) keeps what is broad, a surface lit
    by the room or a light part on a dark table, and takes away what is narrow, the stripes;
    the difference is the stripes alone on a background near 0 (a white top-hat)."""
    k = 2 * int(np.ceil(0.5 * max_width)) + 1
    opened = cv2.morphologyEx(imT, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    return cv2.subtract(imT, opened)


def with_local_background(
    any_angle_at, imT: np.ndarray, levels: dict[str, float], threshold: float, max_width: float
) -> tuple[dict[str, np.ndarray], dict[str, float], np.ndarray | None]:
    """Centres of a frame whose room-lit surfaces may stand above the stripe threshold.

    ``any_angle_at(img, level, detect)`` extracts the centres of ``img`` (as (width, height))
    from the runs above the absolute threshold ``level`` of ``detect`` (``None``: of ``img``);
    ``levels`` are the frame's (:func:`frame_levels`). It runs on the frame first; where that
    finds runs wider than ``max_width`` (a surface lit by the room above the threshold, the
    stripe inside it), it runs again with the runs found in the frame less its local
    background (:func:`remove_local_background`), at that image's own levels (``threshold`` as
    for the frame); the profiles are fitted on the frame itself either way, so the centres do
    not depend on how the background was taken out. Returns the centres, the levels of the
    image the runs were found in and that image where it is not the frame (else ``None``).
    Frames without such surfaces pay nothing.
    """
    c = any_angle_at(imT, levels["level"], None)
    # the runs themselves, not the centres: an extractor may drop a run it cannot fit; a lit
    # surface spans many columns, every 4th is looked at
    if not np.isfinite(levels["level"]) or not (
            np.any(c["width"] > max_width)
            or _has_long_run_nb(imT, _int_threshold(levels["level"], imT.dtype), 4, int(max_width))):
        return c, levels, None
    top = remove_local_background(imT, max_width)
    lv = frame_levels(top, threshold, levels["data_max"])
    return any_angle_at(imT, lv["level"], top), lv, top


def extract(
    img: np.ndarray,
    extractor: str = "grey_centre",
    *,
    threshold: float = 0.15,
    min_width: float = 2.0,
    max_width: float = 30.0,
    sigma: float = 2.0,
    pad: int = 2,
    fit_pad: int = 6,
    relative_noise: float | None = None,
    fit_across: bool = True,
    data_max: float | None = None,
    level: float | None = None,
    rows: bool = True,
) -> dict[str, np.ndarray]:
    """Centre table of one frame (height, width) with the chosen extractor (one of
    :data:`EXTRACTORS`); with ``rows``, stripes at any angle (:func:`any_angle`)."""
    if extractor not in EXTRACTORS:
        raise ValueError(f"unknown extractor {extractor!r}; expected one of {EXTRACTORS}")
    imT = np.ascontiguousarray(cv2.transpose(np.ascontiguousarray(img)))
    lv, dm = _level_and_max(imT, threshold, level, data_max)
    kw = {"threshold": threshold, "min_width": min_width, "max_width": max_width,
          "data_max": dm, "level": lv}

    def fn_at(level_: float):
        k_ = {**kw, "level": level_}

        def fn(a: np.ndarray, d: np.ndarray | None = None) -> dict[str, np.ndarray]:
            if extractor == "grey_centre":
                return grey_centre(a, pad=pad, transposed=True, detect=d, **k_)
            if extractor == "gaussian":
                return gaussian(a, pad=fit_pad, relative_noise=relative_noise, across=fit_across,
                                transposed=True, detect=d, **k_)
            return steger(np.ascontiguousarray(cv2.transpose(a)), sigma=sigma, detect=_rows_of(d), **k_)
        return fn

    if not rows:
        c = fn_at(lv)(imT)
        c["axis"] = np.zeros(c["u"].size, np.uint8)
        return c
    if level is not None:  # an absolute threshold given: no background of the frame's own
        return any_angle(fn_at(lv), imT, lv, max_width)
    return with_local_background(lambda a, lvl, d: any_angle(fn_at(lvl), a, lvl, max_width, d),
                                 imT, frame_levels(imT, threshold, dm), threshold, max_width)[0]


def _rows_of(d: np.ndarray | None) -> np.ndarray | None:
    """A detection image given as (width, height) in the (height, width) layout Steger takes."""
    return None if d is None else np.ascontiguousarray(cv2.transpose(d))


# ----------------------------------------------------------------------------- stage


def _table(frame: int, state: str, c: dict[str, np.ndarray], du: float, dv: float) -> pa.Table:
    n = c["u"].size
    cols = {
        "frame": pa.array(np.full(n, frame, np.int64)),
        "lasers": pa.repeat(pa.scalar(state, pa.string()), n),
        "u": pa.array(c["u"].astype(np.float64) + du),
        "v": pa.array(c["v"].astype(np.float64) + dv),
    }
    for name in _F32:
        cols[name] = pa.array(c[name].astype(np.float32))
    cols["flags"] = pa.array(c["flags"].astype(np.uint8))
    cols["axis"] = pa.array(c["axis"].astype(np.uint8) if "axis" in c else np.zeros(n, np.uint8))
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


def _frame_work(extractor: str, params: dict[str, Any], data_max: float):
    """The per-frame function of the stage; it takes frames transposed, (width, height)."""
    kw = {"threshold": params["threshold"], "min_width": params["min_width"],
          "max_width": params["max_width"], "data_max": data_max}

    def work(i: int, imT: np.ndarray) -> dict[str, Any]:
        lv = frame_levels(imT, params["threshold"], data_max)
        info: dict[str, Any] = {"levels": lv}

        def fn_at(level: float):
            first = [True]

            def fn(a: np.ndarray, d: np.ndarray | None = None) -> dict[str, np.ndarray]:
                if extractor == "gaussian":
                    c, inf = gaussian(a, pad=params["fit_pad"], relative_noise=params["relative_noise"],
                                      across=params["fit_across"], return_info=True, transposed=True,
                                      level=level, detect=d, **kw)
                    if first[0]:  # the column pass's (not the rows'): the frame's noise
                        info["fit"], first[0] = inf, False
                    return c
                if extractor == "grey_centre":
                    return grey_centre(a, pad=params["pad"], transposed=True, level=level, detect=d, **kw)
                return steger(np.ascontiguousarray(cv2.transpose(a)), sigma=params["sigma"],
                              level=level, detect=_rows_of(d), **kw)  # Steger smooths the image itself
            return fn

        mw = params["max_width"]
        c, lv, top = with_local_background(
            lambda a, level, d: any_angle(fn_at(level), a, level, mw, d), imT, lv, params["threshold"], mw)
        info["levels"], info["local_background"] = lv, top is not None
        mp = params.get("min_peak")
        if mp and c["u"].size and np.isfinite(lv["peak"]):
            peak = c["peak"]
            if top is not None:  # the levels are the background-free image's: so the heights
                W, H = top.shape
                peak = top[np.round(c["u"]).astype(np.int64).clip(0, W - 1),
                           np.round(c["v"]).astype(np.int64).clip(0, H - 1)]
            bright = peak >= lv["background"] + mp * (lv["peak"] - lv["background"])
            if not bright.all():
                c = {k: x[bright] for k, x in c.items()}
        return {**c, "_info": info}

    return work


def _data_range(paths: list[Path], data_bits: int | None, shape, decoder: str,
                channel: str | None = None) -> dict[str, Any]:
    """The sensor's data range: ``rig.yaml``'s ``sensor.data_bits``, else inferred.

    Inferred from the largest value over up to ``DATA_RANGE_FRAMES`` frames spread evenly over
    the whole scan (the same frames for every chunk, so chunks agree), rounded up to
    ``2^b - 1`` for the fewest bits ``b`` of :data:`DATA_BITS` that hold it; an 8-bit container
    holds 8 bits.
    """
    from crossline.scan.frames import read_frame

    if data_bits is not None:
        return {"max": 2 ** int(data_bits) - 1, "bits": int(data_bits), "source": "rig.yaml sensor.data_bits"}
    if not paths:
        return {"max": 255, "bits": 8, "source": "no frames"}
    idx = _sample_frames(len(paths))
    top = 0
    for k in idx:
        img = read_frame(paths[k], shape, decoder, True, channel)
        if img.dtype == np.uint8:
            return {"max": 255, "bits": 8, "source": "8-bit frames"}
        top = max(top, int(img.max()))
    bits = data_bits_for(top)
    return {"max": 2**bits - 1, "bits": bits,
            "source": f"inferred from the frames (largest value {top} over {idx.size} frames)"}


def _sample_frames(n: int) -> np.ndarray:
    """Indices of up to ``DATA_RANGE_FRAMES`` frames spread evenly over a scan of ``n`` frames
    (the same for every chunk of the scan, so that chunks agree)."""
    return np.unique(np.linspace(0, n - 1, min(DATA_RANGE_FRAMES, n)).round().astype(int))


def scan_channel(paths: list[Path], channel: str | None, shape) -> dict[str, Any]:
    """The colour channel a scan's stripes are measured on: ``rig.yaml``'s, else chosen.

    Chosen (colour frames, no ``sensor.channel``) as the channel of red, green, blue and the
    luminance in which the stripes stand highest above their surroundings (the 99.9 %
    quantile of the frame less its opening by a disc of ``CHANNEL_DISC_PX``, wider than a
    stripe) in units of the channel's own noise (:func:`frame_levels`), summed over the frames
    the data range is inferred from: a red laser on a part lit white by the room stands out in
    red, not in the luminance that mixes in the other channels' noise, nor in a channel the
    room lights brightly. Grey frames have no choice to make.
    """
    from crossline.io.images import ImageError, read_image_channels

    if channel is not None:
        return {"name": channel, "source": "rig.yaml sensor.channel"}
    if not paths:
        return {"name": None, "source": "no frames"}
    names = ("red", "green", "blue", "grey")
    score = np.zeros(len(names))
    d = CHANNEL_DISC_PX // 2 | 1  # on every second pixel
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    for k in _sample_frames(len(paths)):
        rgb = read_image_channels(paths[k])  # a bad file raises ImageError naming it
        if rgb.shape[2] == 1:
            return {"name": None, "source": "grey frames"}
        if rgb.shape[:2] != tuple(shape):
            raise ImageError(f"{paths[k]}: image is {rgb.shape[1]}x{rgb.shape[0]} px, expected "
                             f"{shape[1]}x{shape[0]} px")
        grey = cv2.cvtColor(np.ascontiguousarray(rgb[:, :, ::-1]), cv2.COLOR_BGR2GRAY)
        for j, img in enumerate((rgb[:, :, 0], rgb[:, :, 1], rgb[:, :, 2], grey)):
            # a stripe is a ridge narrower than the disc: the opening takes it away, and what
            # stands above the opening is the stripe, not a patch the room lights brightly
            # (on every second pixel: a stripe at least 3 px wide keeps its peak)
            sub = np.ascontiguousarray(img[::2, ::2])
            ridge = sub.astype(np.float32) - cv2.morphologyEx(sub, cv2.MORPH_OPEN, disc)
            top = float(np.quantile(ridge, 0.999))
            score[j] += top / frame_levels(np.ascontiguousarray(img.T), 0.5)["noise"]
    best = int(np.argmax(score))
    shown = ", ".join(f"{n} {v:.0f}" for n, v in zip(names, score, strict=True))
    return {"name": names[best], "source": f"chosen: stripe over noise summed over frames ({shown})",
            "scores": dict(zip(names, score.round(3).tolist(), strict=True))}


def run_extract_stripes(
    capture: str | Path,
    scan: str,
    out: str | Path,
    *,
    extractor: str = "grey_centre",
    threshold: float = 0.10,
    min_width: float = 2.0,
    max_width: float = 30.0,
    sigma: float = 2.0,
    chunk: tuple[int, int] = (0, 1),
    threads: int = 1,
    pad: int = 2,
    fit_pad: int = 6,
    relative_noise: float | None = None,
    fit_across: bool = True,
    decoder: str = "auto",
    min_peak: float = 0.17,
) -> dict[str, Any]:
    """Extract the stripe centres of one scan's frames (or one chunk of them) to parquet.

    Frames are read once and streamed through ``threads`` worker threads; centres are
    stored in full-sensor pixels with the frame's laser state. The parquet's schema
    metadata (key ``crossline``) holds the parameters and counts. Returns that metadata.
    ``extractor`` defaults to the paper's grey centre; the workflow's config uses the
    Gaussian fit.
    """
    from crossline.io.capture import open_capture

    if extractor not in EXTRACTORS:
        raise StageError(f"unknown extractor {extractor!r}; expected one of {EXTRACTORS}")
    if not 0 < threshold < 1:
        raise StageError(f"threshold is a fraction of the stripe's peak above the background, "
                         f"in (0, 1), got {threshold}")
    cap = open_capture(capture)
    if scan not in cap.scans:
        raise StageError(f"capture {cap.root}: no scan {scan!r} (known: {sorted(cap.scans)})")
    sc = cap.scans[scan]
    win = cap.rig.scan_window
    lo, hi = _chunk_bounds(len(sc.frames), chunk)
    frames = sc.frames[lo:hi]
    states = sc.lasers[lo:hi]
    params = {"threshold": threshold, "min_width": min_width, "max_width": max_width, "min_peak": min_peak}
    if extractor == "steger":
        params["sigma"] = sigma
    elif extractor == "gaussian":
        params["fit_pad"] = int(fit_pad)
        params["relative_noise"] = None if relative_noise is None else float(relative_noise)
        params["fit_across"] = bool(fit_across)
    else:
        params["pad"] = int(pad)
    meta: dict[str, Any] = {
        "scan": scan, "extractor": extractor, "params": params,
        "scan_window": [win.x, win.y, win.width, win.height],
        "frames_in_scan": len(sc.frames),
    }
    counts = {"frames": 0, "frames_without_stripe": 0, "frames_local_background": 0, "centres": 0,
              **{f"flag_{name}": 0 for name in FLAG_NAMES.values()}}
    t0 = time.perf_counter()
    noise: list[tuple[int, float, float]] = []
    levels: list[tuple[int, float, float, float, float]] = []
    paths = [sc.frame_path(f) for f in frames]
    sensor = cap.rig.sensor
    try:
        scan_paths = [sc.frame_path(f) for f in sc.frames]
        chosen = scan_channel(scan_paths, getattr(sensor, "channel", None), (win.height, win.width))
        channel = chosen["name"]
        rng_ = _data_range([sc.frame_path(f) for f in sc.frames], getattr(sensor, "data_bits", None),
                           (win.height, win.width), decoder, channel)
    except CrosslineError as exc:
        raise StageError(f"scan {scan}: {exc}") from exc
    meta["data_range"] = rng_
    meta["channel"] = chosen
    if chosen["source"].startswith("chosen"):
        log.info("scan %s: colour frames measured on the %s channel (%s)", scan, channel, chosen["source"])
    log.info("scan %s: data range 0..%d (%d bits, %s)", scan, rng_["max"], rng_["bits"], rng_["source"])
    fit = _frame_work(extractor, params, float(rng_["max"]))
    transposed = True

    def work(j: int, img: np.ndarray) -> tuple[dict[str, Any], pa.Table, dict[str, int]]:
        # the table and the flag counts are made in the worker thread too: the loop below,
        # which the workers wait on, only writes
        c = fit(j, img)
        flags = {name: int(np.count_nonzero(c["flags"] & bit)) for bit, name in FLAG_NAMES.items()}
        return c, _table(int(frames[j]), str(states[j]), c, win.x, win.y), flags

    with atomic_path(out) as tmp:
        writer = _GroupedWriter(tmp)
        it = map_frames(paths, work, shape=(win.height, win.width), threads=threads, decoder=decoder,
                        transposed=transposed, channel=channel)
        try:
            for j, (c, table, flags) in enumerate(it):
                counts["frames"] += 1
                nc = c["u"].size
                counts["frames_without_stripe"] += nc == 0
                counts["frames_local_background"] += bool(c["_info"]["local_background"])
                counts["centres"] += nc
                for name, k in flags.items():
                    counts[f"flag_{name}"] += k
                info = c["_info"]
                lv = info["levels"]
                levels.append((int(frames[j]), lv["background"], lv["noise"], lv["peak"], lv["level"]))
                if "fit" in info and nc:
                    noise.append((int(frames[j]), info["fit"]["noise_dn"], info["fit"]["relative_noise"]))
                writer.add(table)
        except CrosslineError as exc:
            raise StageError(f"scan {scan}: {exc}") from exc
        if chunk[1] == 1 and counts["centres"] == 0:
            bg = np.median([r[1] for r in levels]) if levels else float("nan")
            nz = np.median([r[2] for r in levels]) if levels else float("nan")
            raise StageError(
                f"scan {scan}: no stripe found in any of its {counts['frames']} frames: no column "
                f"of a frame holds a pixel {NOISE_K:g} noise sigmas above the background "
                f"(background {bg:.1f}, noise {nz:.2f} counts, data range 0..{rng_['max']}); "
                f"are the lasers on, is the exposure right?"
            )
        meta["counts"] = counts
        meta["levels"] = _level_columns(levels)
        if extractor == "gaussian":  # what the fit found in each frame: sensor noise, speckle
            meta["noise"] = _noise_columns(noise)
        meta["chunk"] = list(chunk)
        meta["frame_range"] = [lo, hi]
        writer.close(meta)
    dt = time.perf_counter() - t0
    log.info("scan %s: %d frames, %d centres, %.1f frames/s (%s, %d threads); %d frames had room-lit "
             "surfaces above the threshold and were extracted less their local background", scan,
             counts["frames"], counts["centres"], counts["frames"] / max(dt, 1e-9), extractor, threads,
             counts["frames_local_background"])
    return meta


def _level_columns(rows: list[tuple[int, float, float, float, float]]) -> dict[str, list]:
    """Per-frame intensity levels (background, noise, stripe peak, threshold) as JSON columns."""
    def r(x: float) -> float | None:
        return round(float(x), 3) if np.isfinite(x) else None

    return {"frame": [x[0] for x in rows], "background": [r(x[1]) for x in rows],
            "noise": [r(x[2]) for x in rows], "peak": [r(x[3]) for x in rows],
            "threshold": [r(x[4]) for x in rows]}


def _noise_columns(rows: list[tuple[int, float, float]]) -> dict[str, list]:
    """Per-frame noise estimates of the gaussian extractor as JSON columns."""
    return {"frame": [r[0] for r in rows],
            "background_noise_dn": [round(float(r[1]), 5) for r in rows],
            "relative_noise": [round(float(r[2]), 5) for r in rows]}


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
        for key in ("scan", "extractor", "params", "scan_window", "frames_in_scan", "data_range"):
            if m.get(key) != first.get(key):
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
    for key in ("data_range", "channel"):
        if key in first:
            meta[key] = first[key]
    for key in ("noise", "levels"):
        if key in first:
            meta[key] = {c: [x for m in metas for x in m[key][c]] for c in first[key]}
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
