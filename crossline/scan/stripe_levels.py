"""Intensity levels of a stripe frame: sample range, background, noise floor and threshold.

Split from :mod:`crossline.scan.stripes` (issue 21.3), whose module doc describes the
extractors. Every extractor thresholds a frame alike: a stripe's run is the pixels above
``background + threshold (peak - background)``, never below ``NOISE_K`` noise sigmas over the
background (:func:`frame_levels`), and a pixel at the sensor's data range is clipped
(:func:`full_scale`, :func:`data_bits_for`). The levels are measured in each frame, here; the
stage stores them per frame, and the colour-channel choice scores channels by their noise.
"""

from __future__ import annotations

import numpy as np

from crossline.robust import MAD_TO_SIGMA

__all__ = [
    "DATA_BITS",
    "LEVEL_STEP",
    "MIN_STRIPE_COLUMNS",
    "NOISE_K",
    "PEAK_QUANTILE",
    "data_bits_for",
    "direction_bins",
    "frame_levels",
    "full_scale",
    "stripe_peaks",
]

DATA_BITS = (8, 10, 12, 14, 16)  # ADC ranges a camera may write into its images' containers
NOISE_K = 6.0  # a stripe stands at least this many background-noise sigmas above the background
PEAK_QUANTILE = 0.9  # the stripe's peak: this quantile of the stripe columns' brightest pixels
MIN_STRIPE_COLUMNS = 3  # fewer columns above the noise floor: the frame holds no stripe
LEVEL_STEP = 5  # background and noise from every 5th pixel of every 5th column
ORIENT_BIN_DEG = 5.0  # stripe_peaks: centres binned by their stripe's direction
ORIENT_WINDOW_DEG = 20.0  # ... and a stripe's peak taken over the directions this close to its own
MIN_STRIPE_CENTRES = 20  # fewer centres in that window: the frame's peak is the reference


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
    mad = MAD_TO_SIGMA * float(np.searchsorted(np.cumsum(dh), 0.5 * dh.sum()))
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


def direction_bins(nx: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """Each centre's stripe direction, binned by ``ORIENT_BIN_DEG`` over 0-180 deg from its profile's
    normal ``(nx, ny)``; -1 where that is undefined."""
    theta = np.degrees(np.arctan2(ny, nx)) % 180.0
    nb = round(180.0 / ORIENT_BIN_DEG)
    out = np.full(theta.shape, -1, np.int64)
    ok = np.isfinite(theta)
    out[ok] = np.minimum((theta[ok] / ORIENT_BIN_DEG).astype(np.int64), nb - 1)
    return out


def stripe_peaks(peak: np.ndarray, nx: np.ndarray, ny: np.ndarray, frame_peak: float) -> np.ndarray:
    """The peak of the stripe each centre lies on, for the frame's ``min_peak`` test.

    Two lasers on in one frame may differ several times in brightness (their power, the
    surface's angle to each); against the brighter one's peak, the other's centres would be
    taken for glints and dropped. The stripes cross, so a centre's stripe is told by its
    direction (the profile's normal ``nx, ny``): the centres are binned by direction
    (``ORIENT_BIN_DEG``), and a centre's stripe peak is the highest ``PEAK_QUANTILE``
    quantile of the bins within ``ORIENT_WINDOW_DEG`` of its own, where those bins hold at
    least ``MIN_STRIPE_CENTRES`` centres, never above ``frame_peak``; elsewhere ``frame_peak``.
    """
    peak = np.asarray(peak, dtype=np.float64)
    out = np.full(peak.size, float(frame_peak))
    bins = direction_bins(nx, ny)
    ok = (bins >= 0) & np.isfinite(peak)
    if ok.sum() < MIN_STRIPE_CENTRES:
        return out
    nb = round(180.0 / ORIENT_BIN_DEG)
    b = bins[ok]
    p = peak[ok]
    srt = p[np.lexsort((p, b))]  # by bin, then by peak
    counts = np.bincount(b, minlength=nb)
    starts = np.cumsum(counts) - counts
    q = np.full(nb, -np.inf)
    has = counts > 0
    q[has] = srt[starts[has] + np.floor(PEAK_QUANTILE * (counts[has] - 1)).astype(np.int64)]
    w = round(ORIENT_WINDOW_DEG / ORIENT_BIN_DEG)
    near_q = np.max([np.roll(q, j) for j in range(-w, w + 1)], axis=0)  # directions wrap at 180
    near_n = np.sum([np.roll(counts, j) for j in range(-w, w + 1)], axis=0)
    ref = np.where((near_n >= MIN_STRIPE_CENTRES) & np.isfinite(near_q),
                   np.minimum(near_q, float(frame_peak)), float(frame_peak))
    out[ok] = ref[b]
    return out
