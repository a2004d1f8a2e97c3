"""The board's albedo in a laser stripe: its light and dark classes and the gain that takes
it out (step 3 of :mod:`crossline.calibrate.lasers`' docstring).

``_light_mask`` is the lasers-off image's light class (Otsu); ``albedo_gain`` fits the
classes' albedo ratio on the stripe's own peaks and, with the sensor's black level it implies,
the per-pixel gain that brings the stripe everywhere to its level on the board's plate.
Split from ``crossline.calibrate.lasers`` (issue 21.3), which re-exports these names.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from crossline.calibrate.detect import to_uint8
from crossline.robust import robust_sigma

__all__ = ["albedo_gain"]

def _light_mask(board_image: np.ndarray) -> np.ndarray:
    """The board image's light albedo class (Otsu's threshold on the lasers-off image, stretched
    between its own percentiles: the data's range, not the container's)."""
    _, mask = cv2.threshold(to_uint8(board_image), 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return mask.astype(bool)


def albedo_gain(
    diff: np.ndarray,
    ambient: np.ndarray,
    plate: np.ndarray,
    other: np.ndarray,
    area: np.ndarray,
    axis: str,
    floor: float,
    clearance_px: Any,
    degree: int = 3,
    min_samples: int = 8,
) -> tuple[np.ndarray, dict] | None:
    """Per-pixel gain that takes the board's albedo out of laser minus ambient, and its figures.

    The stripe is laser irradiance times albedo; the ambient image (lasers-off, scaled to the
    laser image's exposure) is room light times albedo plus the sensor's black level ``c``,
    which is not known. The stripe's own peak in each profile (log), fitted as a smooth
    function along the stripe (Legendre, ``degree``) plus a step on the ``other`` class, gives
    the classes' albedo ratio ``r``; with the classes' ambient levels ``S_p`` (``plate``) and
    ``S_o``, ``r = (S_o - c) / (S_p - c)`` gives ``c``. The gain ``(S_p - c) / (ambient - c)``
    brings the stripe everywhere to its level on the plate, through the blur of the edges too
    (to first order). None when either class has fewer than ``min_samples`` profiles whose
    peak is 2 px clear of the edges, or the classes differ too little to need it.
    """
    d = diff if axis == "column" else diff.T
    am = area if axis == "column" else area.T
    masked = np.where(am, d, -np.inf)
    rows = np.argmax(masked, axis=0)
    cols = np.arange(d.shape[1])
    peak = masked[rows, cols]
    ok = np.isfinite(peak) & (peak > floor)
    if ok.sum() < 2 * min_samples:
        return None
    cols, rows, peak = cols[ok], rows[ok], peak[ok]
    uv = np.column_stack([cols, rows]) if axis == "column" else np.column_stack([rows, cols])
    iu, iv = uv[:, 0], uv[:, 1]
    on_other, on_plate = other[iv, iu], plate[iv, iu]
    keep = (on_other | on_plate) & (clearance_px(uv.astype(np.float64)) >= 2.0)
    if (keep & on_other).sum() < min_samples or (keep & on_plate).sum() < min_samples:
        return None
    s = cols[keep].astype(np.float64)
    s = 2.0 * (s - s.min()) / max(float(np.ptp(s)), 1.0) - 1.0
    A = np.column_stack([np.polynomial.legendre.legvander(s, degree), on_other[keep]])
    y = np.log(peak[keep])
    inl = np.ones(len(y), bool)
    for _ in range(4):  # speckle and glints: profiles far off the fit say nothing of the albedo
        coef = np.linalg.lstsq(A[inl], y[inl], rcond=None)[0]
        res = y - A @ coef
        sig = robust_sigma(res[inl]) or 1e-6
        inl = np.abs(res) <= 3.0 * sig
    r = float(np.exp(coef[-1]))
    s_p = float(np.median(ambient[plate & area]))
    s_o = float(np.median(ambient[other & area]))
    if (r < 1.0) != (s_o < s_p) or abs(1.0 - r) < 0.05:
        return None
    c = (s_o - r * s_p) / (1.0 - r)
    lowest = min(s_o, s_p)
    if not c < lowest:  # the stripe and the ambient disagree: no gain rather than a wrong one
        return None
    shade = np.maximum(ambient - c, 0.25 * (lowest - c))
    return ((s_p - c) / shade).astype(np.float32), {"ratio": r, "black_level": c,
                                                    "profiles": int(inl.sum())}
