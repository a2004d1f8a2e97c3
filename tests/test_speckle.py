"""The speckle bound on a stripe centre (Dorsch, Häusler & Herrmann 1994), by hand, and the
sensor's Cramér-Rao bound against Monte Carlo fits and its closed-form limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crossline.report.speckle import centre_bound_px, combined_bound_px, sensor_bound_px, smoothing_gain


def test_centre_bound_by_hand():
    # C lambda N (1 + m) / pi: 0.15 x 0.405 um x 8 x 1.085 / pi = 0.1679 um, 0.0700 px of 2.4 um
    assert centre_bound_px(0.15, 405.0, 8.0, 2.4, 0.085) == pytest.approx(
        0.15 * 0.405 * 8.0 * 1.085 / math.pi / 2.4, rel=1e-12)
    assert centre_bound_px(0.15, 405.0, 8.0, 2.4, 0.085) == pytest.approx(0.0700, abs=1e-4)
    # fully developed speckle (C = 1) through an f/2 lens on 5 um pixels at 650 nm
    assert centre_bound_px(1.0, 650.0, 2.0, 5.0) == pytest.approx(0.0828, abs=1e-4)
    assert centre_bound_px(0.0, 650.0, 2.0, 5.0) == 0.0
    with pytest.raises(ValueError):
        centre_bound_px(0.15, 405.0, 0.0, 2.4)


def test_smoothing_gain_is_the_centre_noise_of_a_quadratic_fit():
    # Savitzky-Golay, quadratic, 7 points: centre weights (-2, 3, 6, 7, 6, 3, -2) / 21
    assert smoothing_gain(7) == pytest.approx(math.sqrt(147 / 441), rel=1e-12)
    rng = np.random.default_rng(0)
    x = rng.standard_normal((200000, 7))
    w = np.array([-2, 3, 6, 7, 6, 3, -2]) / 21
    assert np.std(x @ w) == pytest.approx(smoothing_gain(7), rel=0.01)
    assert smoothing_gain(1) == 1.0 and smoothing_gain(6) == smoothing_gain(7)


def _gauss_profiles(x0, a, s, b, pix):
    """Mean electrons of pixels ``pix`` (centres) under a Gaussian of peak a, sigma s at x0 over b,
    the pixels integrating it; and the derivatives by (a, x0, s, b): arrays (n, pixels, 4)."""
    from scipy.special import ndtr

    lo = (pix[None, :] - 0.5 - x0[:, None]) / s[:, None]
    hi = lo + 1.0 / s[:, None]
    k = math.sqrt(2.0 * math.pi)
    mass = ndtr(hi) - ndtr(lo)
    glo, ghi = np.exp(-0.5 * lo * lo), np.exp(-0.5 * hi * hi)
    mu = b[:, None] + a[:, None] * s[:, None] * k * mass
    d_a = s[:, None] * k * mass
    d_x0 = a[:, None] * (glo - ghi)
    d_s = a[:, None] * (k * mass + (glo * lo - ghi * hi))  # d/ds of s * int over the pixel
    d_b = np.ones_like(mu)
    return mu, np.stack([d_a, d_x0, d_s, d_b], axis=-1)


@pytest.mark.parametrize(("peak", "sigma", "background", "read"), [
    (800.0, 1.3, 20.0, 6.0),  # a bright, narrow stripe: shot noise of the stripe
    (200.0, 2.5, 40.0, 8.0),  # a fainter, wide stripe: background and read noise matter
])
def test_sensor_bound_against_monte_carlo_fits(peak, sigma, background, read):
    """Many noisy profiles (Poisson electrons plus Gaussian read noise), each fitted by
    iteratively reweighted least squares in all four parameters (peak, centre, sigma,
    background; near-efficient, as maximum likelihood): the centres' variance is the bound's.
    With M fits the sample variance has a relative standard error sqrt(2 / M) (1 % at
    M = 20 000): 5 % is 5 standard errors, and covers the small excess of a four-parameter
    fit at a finite signal-to-noise ratio."""
    rng = np.random.default_rng(7)
    m = 20000
    pix = np.arange(-int(6 * sigma) - 3, int(6 * sigma) + 4, dtype=np.float64)
    x_true = rng.uniform(-0.5, 0.5, m)  # the centre anywhere in its pixel
    ones = np.ones(m)
    mu, _ = _gauss_profiles(x_true, peak * ones, sigma * ones, background * ones, pix)
    data = rng.poisson(mu) + read * rng.standard_normal(mu.shape)
    p = np.stack([peak * ones, x_true, sigma * ones, background * ones], axis=1)  # start at truth
    for _ in range(12):  # Gauss-Newton, weights from the current model
        mu, J = _gauss_profiles(p[:, 1], p[:, 0], p[:, 2], p[:, 3], pix)
        w = 1.0 / (np.maximum(mu, 0.0) + read**2)
        H = np.einsum("npi,np,npj->nij", J, w, J)
        g = np.einsum("npi,np,np->ni", J, w, data - mu)
        p += np.linalg.solve(H, g[:, :, None])[:, :, 0]
    err = p[:, 1] - x_true
    assert abs(err.mean()) < 4 * err.std() / math.sqrt(m)  # unbiased
    bound = sensor_bound_px(peak, sigma, background, read)
    assert err.std() ** 2 == pytest.approx(bound**2, rel=0.05)


def test_sensor_bound_closed_forms():
    # shot noise alone, a wide well-sampled stripe: var = sigma^2 / N, N = peak sqrt(2 pi) sigma
    # electrons (the pixels widen it by 1/12 px^2: 0.1 % in sigma at sigma = 6 px)
    peak, sigma = 2000.0, 6.0
    n = peak * math.sqrt(2.0 * math.pi) * sigma
    assert sensor_bound_px(peak, sigma) == pytest.approx(sigma / math.sqrt(n), rel=2e-3)
    # read noise alone (r >> signal): var = r^2 / sum (d mu / d x0)^2 = 2 sigma r^2 / (sqrt(pi) A^2)
    r = 1e4
    assert sensor_bound_px(peak, 12.0, 0.0, r) == pytest.approx(
        math.sqrt(2.0 * 12.0 * r * r / (math.sqrt(math.pi) * peak * peak)), rel=2e-3)
    # four times the light halves the bound under shot noise
    assert sensor_bound_px(4 * peak, sigma) == pytest.approx(0.5 * sensor_bound_px(peak, sigma), rel=1e-9)
    # arrays broadcast; no light: no bound; nonsense: NaN
    got = sensor_bound_px(np.array([[500.0], [0.0]]), np.array([1.0, 2.0]), 10.0, 5.0)
    assert got.shape == (2, 2) and np.all(np.isfinite(got[0])) and np.all(np.isinf(got[1]))
    assert math.isnan(sensor_bound_px(100.0, -1.0))
    # speckle and sensor: variances add
    assert combined_bound_px(0.03, 0.04) == pytest.approx(0.05)


def test_line_cosines_of_flat_steep_and_stepped_lines():
    """The cosines the validation turns the truth's column sigma and a profile's bound with:
    a 30 deg line (column profile), an 86 deg one (row profile), and a column where the line
    steps to another surface (the gentler side is the line's)."""
    from crossline.report.scan_truth import _line_cosines

    u = np.arange(40)
    for deg in (30.0, 86.0):
        t = np.tan(np.radians(deg))
        cc, cp = _line_cosines(np.zeros(40, np.int64), u, 100 + t * u)
        assert cc == pytest.approx(np.full(40, np.cos(np.radians(deg))))
        assert cp == pytest.approx(np.full(40, max(np.cos(np.radians(deg)), np.sin(np.radians(deg)))))
    # a flat line that jumps 200 rows at column 20 (a step), and a second line 300 rows below
    v = np.where(u < 20, 100.0, 300.0)
    cc, cp = _line_cosines(np.zeros(80, np.int64), np.r_[u, u], np.r_[v, v + 300.0])
    assert cc == pytest.approx(np.ones(80)) and cp == pytest.approx(np.ones(80))
