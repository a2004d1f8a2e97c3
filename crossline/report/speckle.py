"""The speckle limit of laser triangulation: how well a stripe centre can be known at all.

A laser stripe on a rough surface is speckled, and the speckle pattern shifts the centroid
of the stripe's image at random, however many photons arrive. Dorsch, Häusler & Herrmann
(Appl. Opt. 33, 1306-1314, 1994) give the centroid's uncertainty in the image plane as
``dx' = C lambda / (2 pi sin u')``, with ``C`` the speckle contrast and ``u'`` the
image-side aperture angle of the observation (``sin u' = 1 / (2 N (1 + m))`` for an f-number
``N`` at magnification ``m``), i.e. ``dx' = C lambda N (1 + m) / pi``; in the object that is
``dx' / m``, and along the triangulation the point moves by ``dx / sin theta``, which gives
their ``dz = C lambda / (2 pi sin u_obs sin theta)``. Divided by the pixel pitch, ``dx'`` is
the speckle's figure for a stripe centre in pixels. It is the intensity centroid's scatter for
a stripe about as wide as the aperture's spot, not a bound on every estimator: drawn as
coherent imaging (``benchmarks/bench_speckle.py``), the centroid's scatter grows with the
square root of the stripe's width, and a profile fitted with weights for multiplicative
noise falls below the figure on narrow stripes.

The sensor adds its own noise: the photon (shot) noise of the stripe and of the background
and the read noise. Its bound on the centre of one column profile is the Cramér-Rao lower
bound (Kay, *Fundamentals of Statistical Signal Processing: Estimation Theory*, 1993, ch. 3;
for a spot or line centre on a pixel detector, Winick, J. Opt. Soc. Am. A 3, 1809-1815, 1986):
pixel ``i`` collects on average ``mu_i = B + A int_pixel exp(-(y - x0)^2 / (2 sigma^2)) dy``
electrons, with variance ``mu_i + r^2`` (Poisson plus Gaussian read noise; the Poisson count
taken as Gaussian of that variance, its dependence on ``x0`` left out, as Mortensen et al.,
Nat. Methods 7, 377-381, 2010, do for localisation), so the Fisher information on ``x0`` is
``I = sum_i (d mu_i / d x0)^2 / (mu_i + r^2)`` and ``var(x0) >= 1 / I``. For a wide,
well-sampled stripe under shot noise alone this is ``sigma^2 / N`` with ``N`` the stripe's
electrons. Speckle multiplies the light and shot noise is drawn afterwards, independently.

Both together, for a stripe of any width (``stripe_bound_px``): the speckle field ``s`` of
contrast ``C`` per pixel multiplies the stripe's light, so pixel ``i`` holds ``mu_i`` with the
covariance ``C^2 L_i L_j rho_ij`` (``L`` the laser's share of ``mu``, ``rho`` the field's
correlation between the pixels, from the grain) plus the sensor's diagonal; as for the sensor
alone, the covariance's own dependence on ``x0`` is left out, so the bound is
``1 / (dmu' Sigma^-1 dmu)``: the variance of the best weighted least-squares profile fit, the
class of estimator the workflow's ``gaussian`` extractor belongs to. Unlike Dorsch's figure
it grows with the stripe's width (a wide stripe holds more grains, each moving its centre) and
shrinks with a grain smaller than a pixel. After the centre lines' smoothing along the stripe,
neighbouring profiles share grains: the smoothed bound carries the field's correlation along
the line, the sensor's part averages as independent noise.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from crossline.optics import grain_px

__all__ = ["centre_bound_px", "field_correlation", "grain_px", "sensor_bound_px", "smoothing_gain",
           "stripe_bound_px"]

PHASES = 8  # sub-pixel positions of the centre the sensor bound is averaged over
CHUNK = 4096  # profiles per block of the sensor bound, at most
BUDGET = 2_000_000  # values per block (profiles x PHASES x pixels), ~16 MB an array
MATRIX_BUDGET = 4_000_000  # values per block of covariance matrices (stripe bound), ~32 MB
WIDE = 2.0  # px: profiles at least this wide are averaged over 2 phases of their centre
WIDEST = 6.0  # px: wider profiles are taken at this width, their bound grown as sqrt(sigma)


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


def sensor_bound_px(peak_e, sigma_px, background_e=0.0, read_noise_e=0.0, prnu=0.0):
    """Cramér-Rao bound (px, 1 sigma) on one column profile's centre from the sensor's noise."""
    # peak_e: the Gaussian's peak (e- per pixel) and sigma_px its std (px) as the light reaches
    # the pixels (PSF included); background_e (e- per pixel), read_noise_e (e-), prnu (the
    # pixels' relative gain spread, a variance (prnu mu)^2); arrays broadcast. The pixels
    # integrate the profile; the variance is averaged over PHASES sub-pixel centre positions.
    a, s, b, r, q = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in
                                           (peak_e, sigma_px, background_e, read_noise_e, prnu)))
    shape = a.shape
    a, s, b, r, q = (x.reshape(-1) for x in (a, s, b, r, q))
    out = np.full(a.size, np.nan)
    ok = (a >= 0) & (s > 0) & (b >= 0) & (r >= 0) & (q >= 0) & np.isfinite(a + s + b + r + q)
    out[(a == 0) & ok] = np.inf
    idx = np.flatnonzero(ok & (a > 0))
    idx = idx[np.argsort(s[idx], kind="stable")]  # narrow profiles first: blocks of like width
    phase = (np.arange(PHASES) + 0.5) / PHASES - 0.5  # x0 - nearest pixel centre
    k = 0
    while k < idx.size:
        j = idx[k : k + CHUNK]
        half = int(np.ceil(8.0 * s[j[-1]])) + 2
        j = j[: max(1, BUDGET // (PHASES * (2 * half + 2)))]
        k += j.size
        edge = np.arange(-half, half + 2) - 0.5  # pixel edges, relative to the nearest centre
        # (profile, phase, edge): the profile's distance from each pixel edge, in sigmas
        t = (edge[None, None, :] - phase[None, :, None]) / s[j, None, None]
        g = np.exp(-0.5 * t * t)
        t0, t1 = t[:, :, :-1], t[:, :, 1:]
        # the profile's share in each pixel, from the tail nearer to it (no cancellation)
        mass = np.where(t0 > 0, ndtr(-t0) - ndtr(-t1), ndtr(t1) - ndtr(t0))
        aj, sj = a[j, None, None], s[j, None, None]
        mu = b[j, None, None] + aj * sj * math.sqrt(2.0 * math.pi) * mass
        dmu = aj * (g[:, :, :-1] - g[:, :, 1:])  # d mu_i / d x0
        var = mu + r[j, None, None] ** 2 + (q[j, None, None] * mu) ** 2
        fisher = np.divide(dmu * dmu, var, out=np.zeros_like(var), where=var > 0).sum(axis=2)
        out[j] = np.sqrt((1.0 / fisher).mean(axis=1))
    return out.reshape(shape) if shape else float(out[0])


def field_correlation(lag_px, grain: float, contrast: float) -> np.ndarray:
    """Correlation of the speckle field's values between pixels ``lag_px`` apart along one axis.

    The field is ``exp(s g - s^2 / 2)``, ``g`` white noise under a Gaussian kernel of sigma
    ``grain`` sampled on the pixels, ``s^2 = log(1 + C^2)``: ``g``'s correlation is the sampled
    kernel's autocorrelation (at a fractional lag, the Gaussian through its value at lag 1), and
    the log-normal's is ``(exp(s^2 r) - 1) / (exp(s^2) - 1)``. Along two axes it is the product.
    """
    lag = np.abs(np.asarray(lag_px, dtype=np.float64))
    if grain <= 0:
        r = (lag == 0).astype(np.float64)
    else:
        import cv2

        reach = int(np.ceil(4 * grain))
        k = cv2.getGaussianKernel(2 * reach + 1, grain, cv2.CV_64F).ravel()
        ac = np.correlate(k, k, "full")[2 * reach:] / float(k @ k)  # lags 0 .. 2 reach
        whole = np.isclose(lag, np.rint(lag), rtol=0.0, atol=1e-9)
        i = np.minimum(np.rint(lag).astype(np.int64), ac.size - 1)
        r = np.where(whole, np.where(np.rint(lag) < ac.size, ac[i], 0.0), ac[1] ** (lag * lag))
    s2 = math.log1p(contrast * contrast)
    return np.expm1(s2 * r) / math.expm1(s2) if s2 > 0 else r


def stripe_bound_px(peak_e, sigma_px, background_e=0.0, read_noise_e=0.0, prnu=0.0, *,
                    contrast: float, grain: float, step_px=1.0, smooth_px: int | None = None,
                    shot: bool = True):
    """Bound (px, 1 sigma) on one profile's centre from speckle and sensor noise together.

    Arguments as :func:`sensor_bound_px`, with the speckle's ``contrast`` per pixel and
    ``grain`` (px, :func:`grain_px`); ``step_px``, the distance along the line from one profile
    to the next (1 / the profile's cosine to the line's normal). Returns the bound of one
    profile and, with ``smooth_px``, of its centre after the quadratic Savitzky-Golay smoothing
    along the stripe over that many profiles (a tuple of arrays, or of floats). ``shot=False``
    leaves the photon noise out (frames whose noise is the read noise alone, in counts).
    """
    from scipy.signal import savgol_coeffs

    a, s, b, r, q, h = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in
                                              (peak_e, sigma_px, background_e, read_noise_e,
                                               prnu, step_px)))
    shape = a.shape
    a, s, b, r, q, h = (x.reshape(-1) for x in (a, s, b, r, q, h))
    one, smooth = np.full(a.size, np.nan), np.full(a.size, np.nan)
    ok = (a >= 0) & (s > 0) & (b >= 0) & (r >= 0) & (q >= 0) & (h > 0)
    ok &= np.isfinite(a + s + b + r + q + h)
    # a profile many pixels wide (a steep line's column cut) is taken at WIDEST: at a fixed
    # peak, speckle, shot and read noise all give a variance that grows as its width, so the
    # bound grows as sqrt(sigma) from there (tested against the sensor's bound at 16 and 40
    # px), and the covariance matrices stay small
    widen = np.sqrt(np.maximum(s, WIDEST) / WIDEST)
    s = np.minimum(s, WIDEST)
    one[(a == 0) & ok], smooth[(a == 0) & ok] = np.inf, np.inf
    w = None
    if smooth_px and int(smooth_px) >= 3:
        n = int(smooth_px) + 1 - int(smooth_px) % 2
        w = savgol_coeffs(n, 2)
        lags = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    idx = np.flatnonzero(ok & (a > 0))
    idx = idx[np.argsort(s[idx], kind="stable")]
    k = 0
    while k < idx.size:
        j = idx[k : k + CHUNK]
        # beyond 6 sigma the profile's slope is below 1e-7 of its peak's; a profile WIDE pixels
        # or wider hardly changes with its centre's phase, so fewer phases are averaged
        half = int(np.ceil(6.0 * s[j[-1]])) + 2
        m = 2 * half + 1
        nph = PHASES if s[j[0]] < WIDE else 2
        if nph == PHASES:
            j = j[s[j] < WIDE]
        phase = (np.arange(nph) + 0.5) / nph - 0.5
        j = j[: max(1, MATRIX_BUDGET // (nph * m * m))]
        k += j.size
        edge = np.arange(-half, half + 2) - 0.5
        t = (edge[None, None, :] - phase[None, :, None]) / s[j, None, None]
        g = np.exp(-0.5 * t * t)
        t0, t1 = t[:, :, :-1], t[:, :, 1:]
        mass = np.where(t0 > 0, ndtr(-t0) - ndtr(-t1), ndtr(t1) - ndtr(t0))
        aj = a[j, None, None]
        light = aj * s[j, None, None] * math.sqrt(2.0 * math.pi) * mass  # the laser's share
        mu = b[j, None, None] + light
        dmu = aj * (g[:, :, :-1] - g[:, :, 1:])
        noise = (mu if shot else 0.0) + r[j, None, None] ** 2 + (q[j, None, None] * mu) ** 2
        rho = field_correlation(np.arange(m)[:, None] - np.arange(m)[None, :], grain, contrast)
        spk = contrast**2 * light[..., :, None] * light[..., None, :] * rho
        cov = spk + noise[..., :, None] * np.eye(m)
        sol = np.linalg.solve(cov, dmu[..., None])[..., 0]
        fisher = np.einsum("...i,...i->...", dmu, sol)
        one[j] = np.sqrt((1.0 / fisher).mean(axis=1))
        if w is not None:
            wt = sol / fisher[..., None]  # the fit's weights on the pixels
            v_spk = np.einsum("...i,...ij,...j->...", wt, spk, wt)
            v_sen = np.einsum("...i,...i,...i->...", wt, noise, wt)
            along = np.einsum("i,nij,j->n", w, field_correlation(
                lags[None] * h[j, None, None], grain, contrast), w)
            smooth[j] = np.sqrt((v_spk * along[:, None] + v_sen * float(w @ w)).mean(axis=1))
    one, smooth = one * widen, smooth * widen
    if not shape:
        return float(one[0]), (float(smooth[0]) if w is not None else None)
    return one.reshape(shape), (smooth.reshape(shape) if w is not None else None)
