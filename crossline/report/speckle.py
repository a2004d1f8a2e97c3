"""The speckle limit of laser triangulation: how well a stripe centre can be known at all.

A laser stripe on a rough surface is speckled, and the speckle pattern shifts the centroid
of the stripe's image at random, however many photons arrive. Dorsch, Häusler & Herrmann
(Appl. Opt. 33, 1306-1314, 1994) give the centroid's uncertainty in the image plane as
``dx' = C lambda / (2 pi sin u')``, with ``C`` the speckle contrast and ``u'`` the
image-side aperture angle of the observation (``sin u' = 1 / (2 N (1 + m))`` for an f-number
``N`` at magnification ``m``), i.e. ``dx' = C lambda N (1 + m) / pi``; in the object that is
``dx' / m``, and along the triangulation the point moves by ``dx / sin theta``, which gives
their ``dz = C lambda / (2 pi sin u_obs sin theta)``. Divided by the pixel pitch, ``dx'`` is
the bound on a stripe centre in pixels: no extractor can do better on one profile.
"""

from __future__ import annotations

import math

__all__ = ["centre_bound_px", "smoothing_gain"]


def centre_bound_px(contrast: float, wavelength_nm: float, f_number: float, pixel_um: float,
                    magnification: float = 0.0) -> float:
    """Speckle-limited 1-sigma uncertainty of one stripe centre, in pixels (Dorsch et al. 1994)."""
    if not (contrast >= 0 and wavelength_nm > 0 and f_number > 0 and pixel_um > 0
            and magnification >= 0):
        raise ValueError("speckle bound: contrast >= 0 and positive wavelength, f-number, pitch")
    dx_um = contrast * wavelength_nm * 1e-3 * f_number * (1.0 + magnification) / math.pi
    return dx_um / pixel_um


def smoothing_gain(window_px: int) -> float:
    """Noise gain of a centre smoothed along its stripe by a quadratic Savitzky-Golay fit over
    ``window_px`` columns (the centre value), for noise independent from column to column.

    Speckle grains span about a column or two, so the bound on smoothed centres lies between
    ``centre_bound_px * smoothing_gain`` (independent columns) and ``centre_bound_px``.
    """
    from scipy.signal import savgol_coeffs

    w = int(window_px)
    if w < 3:
        return 1.0
    w += 1 - w % 2  # an odd window, as the smoothing uses
    return float(math.sqrt(float((savgol_coeffs(w, 2) ** 2).sum())))
