"""The top view of a scan: its points binned into an image of mean height, by blocks of rows.

The scan page shows the cloud from above, coloured by height, as the mean height in cells of
a regular grid. A long scan's projected coordinates would be 12 B a point held until the
pages are drawn; ``top_view`` projects the points a block of rows at a time and keeps only
the image (and the coordinates where a later page needs them: the freeform's deviation map).
``binned_image`` is the same binning of coordinates already at hand.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["binned_image", "top_view"]

MAX_BINS = 320  # cells along the longer side at most
_BLOCK = 1 << 20  # rows at a time


def _grid(lo: np.ndarray, hi: np.ndarray, n: int, max_bins: int) -> tuple[np.ndarray, list]:
    """Cell counts (2,) and ranges of the grid over [lo, hi]: cells of about two points each on
    average (sparse stripes would print as dust), at most ``max_bins`` along the longer side."""
    span = np.maximum(hi - lo, 1e-6)
    cell = max(span.max() / max_bins, float(np.sqrt(span[0] * span[1] * 2.0 / max(n, 1))))
    nb = np.maximum(np.ceil(span / cell).astype(int), 1)
    return nb, [[lo[0], lo[0] + nb[0] * cell], [lo[1], lo[1] + nb[1] * cell]]


def _image(s: np.ndarray, c: np.ndarray, rng: list) -> tuple[np.ndarray, tuple]:
    with np.errstate(invalid="ignore", divide="ignore"):
        img = (s / c).T
    return img, (rng[0][0], rng[0][1], rng[1][0], rng[1][1])


def binned_image(xy: np.ndarray, h: np.ndarray, max_bins: int = MAX_BINS) -> tuple[np.ndarray, tuple]:
    """Mean of h on a regular grid over xy: image (ny, nx) with NaN where empty, and extent."""
    nb, rng = _grid(xy.min(0), xy.max(0), len(xy), max_bins)
    s, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=nb, range=rng, weights=h)
    c, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=nb, range=rng)
    return _image(s, c, rng)


def top_view(points: np.ndarray, M: np.ndarray, offset: np.ndarray, *, from_low: bool = False,
             keep_xy: bool = False, max_bins: int = MAX_BINS) -> dict[str, Any]:
    """``points @ M.T + offset`` (x, y, height) binned: ``{"image", "extent"}``, plus ``"xy"``
    (N, 2) float32 with ``keep_xy``. ``from_low`` measures the heights from the 0.5th
    percentile of all of them (a surface with no reference plane)."""
    P = np.asarray(points, dtype=np.float64)
    n = len(P)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    xy = np.empty((n, 2), np.float32) if keep_xy else None
    h32 = np.empty(n, np.float32) if from_low else None
    for a in range(0, n, _BLOCK):
        t = P[a:a + _BLOCK] @ M.T + offset
        lo, hi = np.minimum(lo, t[:, :2].min(0)), np.maximum(hi, t[:, :2].max(0))
        if xy is not None:
            xy[a:a + len(t)] = t[:, :2]
        if h32 is not None:
            h32[a:a + len(t)] = t[:, 2]
    base = float(np.percentile(h32, 0.5)) if h32 is not None and n else 0.0
    del h32
    nb, rng = _grid(lo, hi, n, max_bins)
    s, c = np.zeros(nb), np.zeros(nb)
    for a in range(0, n, _BLOCK):
        t = P[a:a + _BLOCK] @ M.T + offset
        s += np.histogram2d(t[:, 0], t[:, 1], bins=nb, range=rng, weights=t[:, 2] - base)[0]
        c += np.histogram2d(t[:, 0], t[:, 1], bins=nb, range=rng)[0]
    img, extent = _image(s, c, rng)
    out: dict[str, Any] = {"image": img, "extent": extent}
    if xy is not None:
        out["xy"] = xy
    return out
