"""A stripe much dimmer than the frame's peak, found at its own level.

Two lasers on in one frame may differ several times in brightness; at the level the brighter
one sets, a narrow dim stripe breaks up. :func:`with_dim_stripes` extracts such a frame again
at the dim stripe's level and adds that pass's centres in the dim stripe's directions
(:mod:`crossline.scan.stripes` calls it in frames with more than one laser on);
:func:`centre_heights` gives the centres' peaks that the stage's ``min_peak`` test uses.
"""

from __future__ import annotations

import numpy as np

from crossline.scan.stripe_levels import MIN_STRIPE_CENTRES, NOISE_K, direction_bins, stripe_peaks

__all__ = ["DIM_SHARE", "DIM_STRIPE", "centre_heights", "with_dim_stripes"]

DIM_STRIPE = 0.6  # a stripe peaking below this fraction of the frame's peak is found at its own level
DIM_SHARE = 0.15  # ... where it holds this share of the frame's centres (a stripe, not a grazing end)


def centre_heights(c: dict[str, np.ndarray], top: np.ndarray | None) -> np.ndarray:
    """The centres' peaks in the image their runs were found in (the frame, or ``top``, the
    frame less its local background, on whose levels the thresholds then are)."""
    if top is None:
        return c["peak"]
    W, H = top.shape
    return top[np.round(c["u"]).astype(np.int64).clip(0, W - 1),
               np.round(c["v"]).astype(np.int64).clip(0, H - 1)]


def _pixels(c: dict[str, np.ndarray], W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    """The centres' pixels, one more than their (u, v) (clipped to a border of one pixel)."""
    return (np.round(c["u"]).astype(np.int64).clip(-1, W) + 1,
            np.round(c["v"]).astype(np.int64).clip(-1, H) + 1)


def with_dim_stripes(
    c: dict[str, np.ndarray], lv: dict[str, float], top: np.ndarray | None, threshold: float, again,
    shape: tuple[int, int],
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray | None]:
    """A frame's centres (``c``, found at the levels ``lv`` of ``top`` or the frame, of ``shape``
    (width, height)), with a stripe much dimmer than the frame's peak filled in at its own level.

    Two lasers on in one frame may differ several times in brightness. At the level the
    brighter one sets, a narrow dim stripe's runs are a pixel or two wide, below ``min_width``
    in every other column, and its traces break. Where a stripe (told by its direction,
    :func:`stripe_peaks`) peaks less than ``DIM_STRIPE`` of the frame's peak above the
    background and holds ``DIM_SHARE`` of the centres at least (the dim, grazing end of a stripe
    on a curved surface does not), the frame is extracted again at the dim stripe's own level,
    ``background + threshold (its peak - background)`` (never below the noise floor), by
    ``again(level, fraction)`` (``fraction``: its peak's of the frame's, above the background).
    The centres of that pass in the dim stripe's directions are added where the first pass has
    none within a pixel along their profile; the first pass's stay as they were. Returns the
    centres and, for each, the dim stripe's peak where that pass added it (else NaN), which the
    ``min_peak`` test holds it to, and their :func:`stripe_peaks` where it computed them for the
    centres it returns (else ``None``). The stripes are told apart by direction, as a cross's two
    lines are; two stripes within ``stripe_levels.ORIENT_WINDOW_DEG`` of each other, or a narrow
    dim stripe whose centres' directions scatter that far, are filled in only in part.
    """
    nan = np.full(c["u"].size, np.nan)
    bg, top_peak = lv["background"], lv["peak"]
    cut = bg + DIM_STRIPE * (top_peak - bg)
    h = centre_heights(c, top)
    if h.size < MIN_STRIPE_CENTRES or not np.any(h < cut):
        return c, nan, None
    ref = stripe_peaks(h, c["nx"], c["ny"], top_peak)
    none = (c, nan, ref)  # the first pass's centres, as they are
    dim = ref < cut
    if dim.sum() < max(MIN_STRIPE_CENTRES, DIM_SHARE * dim.size):
        return none
    dim_peak = float(ref[dim].min())
    fraction = (dim_peak - bg) / (top_peak - bg)
    level = max(bg + threshold * fraction * (top_peak - bg), bg + NOISE_K * lv["noise"])
    if not level < lv["level"]:
        return none
    c2 = again(level, fraction)
    if not c2["u"].size:
        return none
    # a first-pass centre holds its pixel and the next ones along its profile (column or row)
    W, H = shape
    near = np.zeros((W + 2, H + 2), bool)  # a border of one pixel
    iu, iv = _pixels(c, W, H)
    along_row = c["axis"] == 1
    for d in (-1, 0, 1):
        near[iu + d * along_row, iv + d * ~along_row] = True
    add = np.isin(direction_bins(c2["nx"], c2["ny"]), np.unique(direction_bins(c["nx"], c["ny"])[dim]))
    add &= ~near[_pixels(c2, W, H)]
    if not add.any():
        return none
    out = {k: np.concatenate([c[k], c2[k][add]]) for k in c}
    own = np.concatenate([nan, np.full(int(add.sum()), dim_peak)])
    o = np.lexsort((out["v"], out["u"]))
    return {k: x[o] for k, x in out.items()}, own[o], None
