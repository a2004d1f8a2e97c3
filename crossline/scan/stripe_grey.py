"""The paper's grey centre (eq. 9-13) of every stripe segment of every column of a frame.

Split from :mod:`crossline.scan.stripes` (issue 21.3), whose module doc describes the
method (windows widened by ``pad``, the local background, ``CLOSE`` and ``MERGED``). This is
the driver, :func:`grey_centre`: the runs come from :mod:`crossline.scan.stripe_runs`, the
window sums from :mod:`crossline.scan.stripe_kernels` (numba, or the numpy twin: same centres).
"""

from __future__ import annotations

import numpy as np

from crossline.scan.stripe_kernels import CLOSE, EDGE, MERGED, _grey_windows_numpy, _windows_nb
from crossline.scan.stripe_levels import _level_and_max, full_scale
from crossline.scan.stripe_runs import (
    BG_PIXELS,
    _candidate_runs,
    _columns,
    _merged,
    _slopes,
    _slopes_nb,
    _use_numba,
    empty_centres,
)

__all__ = [
    "grey_centre",
]


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
    profiles are always ``img``'s. Returns a centre table (``stripes`` module doc) in frame-local pixels,
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
