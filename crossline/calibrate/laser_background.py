"""What laser minus background subtracts: the lasers-off image at the laser image's exposure,
or, with the laser always on, the laser image with its stripe removed.

``ambient_model`` fits ``laser ≈ a · board + b`` off the stripe (the same scene at another
exposure); ``remove_stripe`` takes the stripe out of a laser image by a grey opening (the
pieces of a stripe cut by dark circles joined by ``_on_long_line``); ``_robust_noise`` is the
noise level both the stripe removal and the stripe's threshold stand ``NOISE_K`` sigmas above.
Split from ``crossline.calibrate.lasers`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

import cv2
import numpy as np

from crossline.robust import robust_sigma

__all__ = ["NOISE_K", "ambient_model", "remove_stripe"]

NOISE_K = 8.0  # the stripe stands this many noise sigmas above the laser-minus-board difference
MIN_PIECE_ELONGATION = 2.2  # a stripe piece is longer than wide by this; corner residues 1.3-1.8
STRIPE_OPEN_FRACTION = 0.012  # laser always on: the opening that removes the stripe, x sensor size


def _robust_noise(x: np.ndarray) -> float:
    """Robust sigma of a sample: 1.4826 MAD, or the RMS within 5 of it where the data are
    quantised to a fraction of a count (MAD 0); at least sqrt(1/12)."""
    x = np.asarray(x, dtype=np.float64).ravel()
    d = x - np.median(x)
    mad = robust_sigma(x)
    near = d[np.abs(d) <= 5.0 * max(mad, 1.0)]
    rms = float(np.sqrt(np.mean(near**2))) if near.size else 0.0
    return max(mad, rms, float(np.sqrt(1.0 / 12.0)))


def remove_stripe(laser_image: np.ndarray, kernel_px: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The laser image without its stripe, for a pose with the laser always on, and the mask.

    A grey opening with a disc wider than the stripe (``kernel_px``, default
    ``STRIPE_OPEN_FRACTION`` of the sensor's long side) removes every bright structure narrower
    than the disc: the stripe, not the board's squares or circles. The stripe is where the
    image stands above its opening by ``NOISE_K`` noise sigmas and a tenth of the stripe's own
    level, on components that are long (a tenth of the image's short side); only those pixels
    (grown by the stripe's width, for its tails) are replaced by the opening. The result
    stands in for the lasers-off image: the board is found in it, and laser minus it is the
    stripe.
    """
    img = np.asarray(laser_image)
    h, w = img.shape
    k = kernel_px or max(15, round(STRIPE_OPEN_FRACTION * max(h, w)) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    opened = cv2.morphologyEx(img, cv2.MORPH_OPEN, disc)
    top = img.astype(np.float32) - opened.astype(np.float32)
    sub = top[::5, ::5]
    noise = _robust_noise(sub)
    level = float(np.quantile(top, 0.999)) if top.size else 0.0
    thr = max(NOISE_K * noise, 0.1 * level)
    cand = (top > thr).astype(np.uint8)
    _n, lab, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    length = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    long_ = length >= 0.1 * min(h, w)
    long_[0] = False
    long_ |= _on_long_line(cand, lab, length, 0.1 * min(h, w))
    mask = long_[lab].astype(np.uint8)
    if long_.any():
        # the stripe's tails reach beyond the pixels above a tenth of its level: grow the mask
        # by the stripe's own width (its area over its length), 2 px at least
        width = float(np.max(stats[long_, cv2.CC_STAT_AREA] / length[long_]))
        g = 2 * max(2, round(width)) + 1
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (g, g)))
    mask = mask.astype(bool)
    return np.where(mask, opened, img).astype(img.dtype), mask


def _on_long_line(cand: np.ndarray, lab: np.ndarray, length: np.ndarray, min_len: float) -> np.ndarray:
    """Components that lie on one long straight line with others: a stripe cut into pieces.

    A stripe that crosses dark circles (or dark squares) is dim there and falls apart into
    pieces each shorter than a stripe must be; a probabilistic Hough transform that bridges
    gaps up to the same length joins them. Pieces shorter than 10 px (noise) are not taken.
    """
    keep = np.zeros(len(length), bool)
    if len(length) < 3:
        return keep
    lines = cv2.HoughLinesP(cand * np.uint8(255), 1, np.pi / 720, threshold=max(20, int(min_len / 4)),
                            minLineLength=min_len, maxLineGap=min_len)
    if lines is None:
        return keep
    on = np.zeros_like(cand)
    for x0, y0, x1, y1 in lines[:, 0]:
        cv2.line(on, (int(x0), int(y0)), (int(x1), int(y1)), 1, 3)
    hit = np.unique(lab[(on > 0) & (cand > 0)])
    keep[hit] = True
    keep[0] = False
    keep &= length >= 10
    # a piece of stripe is a segment, long for its width; the residues that the opening leaves
    # at a chessboard's corners are X-shaped blobs, which also line up (along the board's
    # rows) but are about as wide as long: elongation from each component's second moments
    ys, xs = np.nonzero(lab)
    ids = lab[ys, xs]
    n = np.bincount(ids, minlength=len(length)).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.bincount(ids, xs, len(length)) / n
        my = np.bincount(ids, ys, len(length)) / n
        dx, dy = xs - mx[ids], ys - my[ids]
        cxx = np.bincount(ids, dx * dx, len(length)) / n
        cyy = np.bincount(ids, dy * dy, len(length)) / n
        cxy = np.bincount(ids, dx * dy, len(length)) / n
        root = np.sqrt(np.maximum((cxx - cyy) ** 2 / 4 + cxy**2, 0.0))
        big, small = (cxx + cyy) / 2 + root, (cxx + cyy) / 2 - root
        elongation = np.sqrt(big / np.maximum(small, 1.0 / 12.0))  # a 1-px-wide line: L / 1
    keep &= np.nan_to_num(elongation) >= MIN_PIECE_ELONGATION
    return keep


def ambient_model(board_image: np.ndarray, laser_image: np.ndarray, step: int = 3) -> tuple[float, float]:
    """``(a, b)`` with ``laser ≈ a · board + b`` off the stripe: the same scene at another exposure.

    A robust start (a line through the medians of the laser image in bins of the board
    image's level, which the few stripe pixels cannot move), then least squares on a
    subsample without the pixels beyond 3 robust sigmas (the stripe, saturated pixels).
    """
    x = board_image[::step, ::step].astype(np.float64).ravel()
    y = laser_image[::step, ::step].astype(np.float64).ravel()
    edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, 33)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(len(edges) - 2, 0))
    bins = [k for k in range(len(edges) - 1) if np.count_nonzero(idx == k) >= 10]
    if len(bins) >= 2:
        xm = np.array([np.median(x[idx == k]) for k in bins])
        ym = np.array([np.median(y[idx == k]) for k in bins])
        a, b = np.polyfit(xm, ym, 1)
    else:  # a flat lasers-off image: only an offset
        a, b = 0.0, float(np.median(y))
    for _ in range(3):
        r = y - (a * x + b)
        sigma = max(robust_sigma(r), 0.5)
        keep = np.abs(r - np.median(r)) <= 3.0 * sigma
        if keep.sum() < 3 or np.ptp(x[keep]) == 0:
            break
        a, b = np.polyfit(x[keep], y[keep], 1)
    return float(a), float(b)
