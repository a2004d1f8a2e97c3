"""The speckle bound on a stripe centre (Dorsch, Häusler & Herrmann 1994), by hand, the
sensor's Cramér-Rao bound against Monte Carlo fits and its closed-form limits, and the bound of
speckle and sensor together against the workflow's extractor on rendered speckle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crossline.report.speckle import (
    centre_bound_px,
    field_correlation,
    sensor_bound_px,
    smoothing_gain,
    stripe_bound_px,
)


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


def test_stripe_bound_without_speckle_is_the_sensor_bound():
    peak, sigma = np.array([300.0, 2000.0, 50.0]), np.array([0.9, 2.0, 3.5])
    one, smooth = stripe_bound_px(peak, sigma, 20.0, 4.0, 0.01, contrast=0.0, grain=0.7,
                                  smooth_px=7)
    # the sensor's bound averages 8 phases of the centre in its pixel; profiles 2 px and wider
    # are averaged over 2 here (where the phase changes the bound by less than 1e-4)
    assert one == pytest.approx(sensor_bound_px(peak, sigma, 20.0, 4.0, 0.01), rel=1e-4)
    assert one[0] == pytest.approx(sensor_bound_px(peak[0], sigma[0], 20.0, 4.0, 0.01), rel=1e-9)
    assert smooth == pytest.approx(one * smoothing_gain(7), rel=1e-10)
    # a steep line's column cut, 16 and 40 px wide: taken at 6 px and grown as sqrt(sigma)
    for wide in (16.0, 40.0):
        got, _ = stripe_bound_px(2000.0, wide, 20.0, 4.0, contrast=0.0, grain=0.7)
        assert got == pytest.approx(sensor_bound_px(2000.0, wide, 20.0, 4.0), rel=3e-3)
    # speckle only adds: more contrast, a larger bound
    lo, _ = stripe_bound_px(peak, sigma, 20.0, 4.0, contrast=0.05, grain=0.7)
    hi, _ = stripe_bound_px(peak, sigma, 20.0, 4.0, contrast=0.2, grain=0.7)
    assert np.all(one < lo) and np.all(lo < hi)


def test_field_correlation_is_the_rendered_fields():
    """The correlation the bound assumes, against the renderer's field measured: lags 0-3 px
    along rows and columns, two grains."""
    from crossline.sim.optics import speckle_field

    rng = np.random.default_rng(3)
    for grain in (0.55, 1.2):
        f = speckle_field(rng, np.ones((600, 600), np.uint8), 0.2, grain).astype(np.float64)
        f = f[20:-20, 20:-20] - f[20:-20, 20:-20].mean()
        for lag in (1, 2, 3):
            got = 0.5 * ((f[:, lag:] * f[:, :-lag]).mean() + (f[lag:] * f[:-lag]).mean()) / f.var()
            assert got == pytest.approx(float(field_correlation(lag, grain, 0.2)), abs=0.01)
        assert float(field_correlation(0, grain, 0.2)) == 1.0


@pytest.mark.parametrize("grain,sigma", [(0.55, 2.0), (1.0, 3.0), (0.3, 1.2)])
def test_stripe_bound_against_rendered_speckle(grain, sigma):
    """Horizontal stripes drawn with the renderer's speckle field (contrast 0.15) and read noise,
    centred by the workflow's extractor: its scatter is the bound's within 15 %, for one
    profile and after the centre lines' quadratic smoothing over 7 columns, where neighbouring
    columns share grains (independent columns would give 0.58x the one-profile bound, which
    the finest grain comes near; the coarsest's smoothed bound is 0.85x its one-profile
    bound). Dorsch's figure, width-blind, is 0.79x the bound in the third case."""
    from scipy.signal import savgol_filter

    from crossline.scan.stripe_frame import extract
    from crossline.sim.optics import speckle_field

    rng = np.random.default_rng(11)
    h, w, peak, read, contrast = 64, 400, 200.0, 0.6, 0.15
    v0 = rng.uniform(28.0, 36.0, 60)  # each frame's line row, anywhere in its pixel
    one, smooth = [], []
    for v in v0:
        rows = np.arange(h, dtype=np.float64)[:, None]
        # the pixels integrate the Gaussian profile
        from scipy.special import ndtr
        mass = ndtr((rows + 0.5 - v) / sigma) - ndtr((rows - 0.5 - v) / sigma)
        light = np.repeat(peak * sigma * math.sqrt(2 * math.pi) * mass, w, axis=1)
        lit = light * speckle_field(rng, (light > 0.01 * peak).astype(np.uint8), contrast, grain)
        img = np.clip(np.rint(lit + 2.0 + read * rng.standard_normal(lit.shape)), 0, 255)
        c = extract(img.astype(np.uint8), "gaussian", threshold=0.15)
        order = np.argsort(c["u"])
        u, e = c["u"][order], c["v"][order] - v
        keep = (u >= 8) & (u < w - 8)
        assert keep.sum() > 0.9 * (w - 16)
        one.append(e[keep])
        smooth.append(savgol_filter(e, 7, 2)[keep])
    b1, bs = stripe_bound_px(peak, sigma, 0.0, math.hypot(read, 1 / math.sqrt(12)),
                             contrast=contrast, grain=grain, smooth_px=7, shot=False)
    for got, bound in ((np.concatenate(one), b1), (np.concatenate(smooth), bs)):
        robust = 1.4826 * np.median(np.abs(got - np.median(got)))
        assert 0.85 * bound < robust < 1.15 * bound, (robust, bound)


def test_line_cosines_of_flat_steep_and_stepped_lines():
    """The cosines the validation turns the truth's column sigma and a profile's bound with
    (the line's normal to the column and to the row): a 30 deg line, an 86 deg one, and a
    column where the line steps to another surface (the gentler side is the line's)."""
    from crossline.report.scan_truth import _line_cosines

    u = np.arange(40)
    for deg in (30.0, 86.0):
        t = np.tan(np.radians(deg))
        cc, cp = _line_cosines(np.zeros(40, np.int64), u, 100 + t * u)
        assert cc == pytest.approx(np.full(40, np.cos(np.radians(deg))))
        assert cp == pytest.approx(np.full(40, np.sin(np.radians(deg))))
    # a flat line that jumps 200 rows at column 20 (a step), and a second line 300 rows below
    v = np.where(u < 20, 100.0, 300.0)
    cc, cp = _line_cosines(np.zeros(80, np.int64), np.r_[u, u], np.r_[v, v + 300.0])
    assert cc == pytest.approx(np.ones(80)) and cp == pytest.approx(np.zeros(80))


def test_steep_stripe_bound_is_its_column_profiles(tmp_path):
    """A stripe at 70 deg to the rows whose run along a column fits the extractor's window is
    centred column by column (axis 0), each column holding 2.9 px of the line: its scatter is
    the column profile's bound (within 15 %), well below a row profile's, which holds about
    one pixel of it; the validation takes the bound of the profile each point was found on."""
    import pandas as pd

    from crossline.report.scan_truth import _sensor_profiles
    from crossline.scan.stripe_frame import extract
    from crossline.sim.optics import speckle_field

    rng = np.random.default_rng(5)
    t = math.radians(70.0)
    h, w, ss, sigma, peak_e, gain, read, bg, contrast = 200, 300, 4, 2.0, 3500.0, 0.15, 6.0, 9.0, 0.2
    y = (np.arange(h * ss) + 0.5) / ss - 0.5
    x = (np.arange(w * ss) + 0.5) / ss - 0.5
    errs, axes = [], []
    for _ in range(20):
        v0 = rng.uniform(95.0, 105.0)
        d = (y[:, None] - v0 - math.tan(t) * (x[None, :] - w / 2)) * math.cos(t)
        light = (peak_e * np.exp(-0.5 * (d / sigma) ** 2)).reshape(h, ss, w, ss).mean(axis=(1, 3))
        lit = light * speckle_field(rng, (light > 1e-3 * peak_e).astype(np.uint8), contrast, 0.3) + bg
        e = lit + np.sqrt(lit) * rng.standard_normal(lit.shape) + read * rng.standard_normal(lit.shape)
        c = extract(np.clip(np.rint(e / gain + 400), 0, 65535).astype(np.uint16), "gaussian",
                    threshold=0.1)
        dd = (c["v"] - v0 - math.tan(t) * (c["u"] - w / 2)) * math.cos(t)
        keep = (c["v"] > 20) & (c["v"] < h - 20)
        errs.append(dd[keep])
        axes.append(c["axis"][keep])
    e = np.concatenate(errs)
    assert np.all(np.concatenate(axes) == 0)
    robust = 1.4826 * np.median(np.abs(e - np.median(e)))
    r = math.hypot(read, gain / math.sqrt(12))
    col, _ = stripe_bound_px(peak_e, sigma / math.cos(t), bg, r, contrast=contrast, grain=0.3)
    row, _ = stripe_bound_px(peak_e, sigma / math.sin(t), bg, r, contrast=contrast, grain=0.3)
    col, row = col * math.cos(t), row * math.sin(t)
    assert 0.85 * col < robust < 1.15 * col, (robust, col)
    assert robust < 0.75 * row

    # the validation's profiles: the truth's column sigma turned by the found point's axis
    u = np.arange(100, 140)
    truth = pd.DataFrame({"frame": 0, "laser": "A", "u": u, "v": 100.0 + math.tan(t) * (u - 100),
                          "visible": True, "peak_e": peak_e, "sigma_px": sigma / math.cos(t),
                          "background_e": bg})
    sensor = {"read_noise_e": read, "gain_e_per_dn": 0.0, "psf_sigma_px": 0.0}
    got = {}
    for ax in (0, 1):
        truth.to_parquet(path := tmp_path / f"centrelines_{ax}.parquet")
        found = {"A": (u.astype(np.int64), np.full(u.size, ax, np.int8))}
        got[ax] = _sensor_profiles(path, sensor, found)["A"]
    assert got[0]["cosine"] == pytest.approx(np.full(got[0]["cosine"].size, math.cos(t)), rel=1e-6)
    assert got[1]["cosine"] == pytest.approx(np.full(got[1]["cosine"].size, math.sin(t)), rel=1e-6)
    assert np.median(got[0]["sigma_px"]) == pytest.approx(sigma / math.cos(t), rel=1e-3)


def test_stripe_spacing_along_column_and_row_profiled_stripes(tmp_path):
    """The lateral resolution's spacing: laser A column-profiled, 0.1 mm per column with a
    two-column gap (not a step of one profile) and a second piece in the same columns; laser
    B row-profiled, 0.2 mm per row."""
    import pandas as pd

    from crossline.report.scan_truth import stripe_spacing_mm

    u = np.r_[np.arange(20), np.arange(22, 40)].astype(np.float64)
    a = pd.DataFrame({"frame": 3, "laser": "A", "u": u, "v": 100.0 + 0.3 * u,
                      "x": 0.1 * u, "y": 0.03 * u, "z": 0.0, "axis": np.uint8(0)})
    r = np.arange(30, dtype=np.float64)
    b = pd.DataFrame({"frame": 3, "laser": "B", "u": 50.0 + 0.1 * r, "v": r,
                      "x": 0.0, "y": 0.2 * r, "z": 0.0, "axis": np.uint8(1)})
    # a second piece of A in the same frame and columns, 40 px below and 50 mm away (the
    # table behind a ball): a piece's neighbour is its own, not the other piece's
    a2 = a.assign(v=a["v"] + 40.0, z=50.0, x=0.1 * u + 0.001)
    path = tmp_path / "points.parquet"
    pd.concat([a, a2, b]).sample(frac=1.0, random_state=1).to_parquet(path)
    got = stripe_spacing_mm(path)
    assert got["A"] == pytest.approx(math.hypot(0.1, 0.03), rel=1e-9)
    assert got["B"] == pytest.approx(0.2, rel=1e-9)
