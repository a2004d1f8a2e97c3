"""One frame's stripe centres with any extractor, at any angle, room-lit surfaces taken out.

Split from :mod:`crossline.scan.stripes` (issue 21.3). The extractors profile along the
image columns; where a stripe is steeper than ``ROW_SLOPE`` it is profiled along the rows
instead (:func:`any_angle`), and a frame whose room-lit surfaces stand above the stripe
threshold has its runs found in the frame less its local background
(:func:`with_local_background`). :func:`extract` puts these together for one frame with any of
:data:`EXTRACTORS`; the stage (:mod:`crossline.scan.stripes`) does the same for every frame of
a scan.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.jit import jit as _jit
from crossline.scan.stripe_gaussian import gaussian
from crossline.scan.stripe_grey import grey_centre
from crossline.scan.stripe_levels import _level_and_max, frame_levels
from crossline.scan.stripe_runs import _int_threshold
from crossline.scan.stripe_steger import steger

__all__ = [
    "EXTRACTORS",
    "MIN_STEEP_ROWS",
    "ROW_SLOPE",
    "any_angle",
    "extract",
    "remove_local_background",
    "with_local_background",
]

EXTRACTORS = ("grey_centre", "gaussian", "steger")
ROW_SLOPE = 3.0  # stripes steeper than this (|dv/du|, 72 deg) are profiled along the rows
MIN_STEEP_ROWS = 48  # ... where the steep stretch spans this many rows (not a curve's steep end)


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


def _long_steep(row: np.ndarray, col: np.ndarray, cand: np.ndarray, steep: np.ndarray,
                shape_T: tuple[int, int]) -> np.ndarray:
    """Which candidate row centres lie on a steep stretch spanning ``MIN_STEEP_ROWS`` rows or
    more, most of whose centres are ``steep``.

    The candidates' pixels are marked and joined (8-connected, a row of margin), and
    stretches shorter than that are left to the column profiles: the steep ends of a curve
    (a ball's rim) stay as they were. A stretch is taken or left whole: a stripe whose slope
    hovers about ``ROW_SLOPE`` would otherwise alternate between row and column centres, and
    both traces would break into pieces too short to keep.
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
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    comp = lab[rr, cc]
    mostly = 2 * np.bincount(comp, weights=steep[cand], minlength=n) >= np.bincount(comp, minlength=n)
    tall = stats[:, cv2.CC_STAT_HEIGHT] >= min(MIN_STEEP_ROWS, H // 2)
    out[np.flatnonzero(cand)] = (tall & mostly)[comp]
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
    times the typical run (``max_width`` at most), on the transposed frame. The row centres
    are kept on a steep stretch of ``MIN_STEEP_ROWS`` rows or more where the column run
    through most of their pixels is more than ``ROW_SLOPE`` times their own (all of the
    stretch where it is more than half that: :func:`_long_steep`); the column centres inside
    the runs of the row centres kept give way to them. Returns the
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
    # steeper than ROW_SLOPE: the rows' profiles; a stretch of the stripe that is mostly so
    # is taken whole, down to half that slope (a profile within 27 deg of the stripe's normal)
    keep_r = _long_steep(r["u"], r["v"], lc > 0.5 * ROW_SLOPE * r["width"], lc > ROW_SLOPE * r["width"],
                         imT.shape)
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
