"""Robust scale: the standard deviation of normal errors from their median absolute deviation.

One rule for every stage that must tell the spread of good data from a minority of outliers
(a glint, a wrong pair, a bad view): ``MAD_TO_SIGMA`` times the median absolute deviation,
which for normal errors is their standard deviation and which outliers move little.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MAD_TO_SIGMA", "robust_sigma"]

MAD_TO_SIGMA = 1.4826  # 1 / the normal's 75 % quantile: the MAD of normal errors is 0.6745 sigma


def robust_sigma(x: np.ndarray, about: float | None = None) -> float:
    """Standard deviation of ``x`` from its median absolute deviation (``MAD_TO_SIGMA`` · MAD).

    The deviations are taken from ``about``: by default the median of ``x``; ``0.0`` for errors
    whose true value is zero (a mismatch, a residual), so a shared offset counts as spread.
    NaN for an empty ``x``.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return float("nan")
    centre = np.median(x) if about is None else about
    return float(MAD_TO_SIGMA * np.median(np.abs(x - centre)))
