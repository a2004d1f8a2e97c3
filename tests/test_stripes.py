"""Stripe-centre extractors on synthetic frames with known centres; the PNG decoder; streaming."""

from __future__ import annotations

import struct
import threading
import zlib

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy.special import erf

from crossline.io.images import ImageError
from crossline.scan.frames import decode_png, fast_decoder_available, map_frames, read_frame
from crossline.scan.stripes import CLOSE, EDGE, MERGED, SATURATED, gaussian, grey_centre, steger

H, W = 120, 200
LEVEL_38 = 0.15 * 255  # a threshold of 38.25 counts


def _cdf(x, s_lo, s_hi):
    """Integral from -inf to x of a two-sided Gaussian of unit peak (sigma s_lo left, s_hi right)."""
    k = np.sqrt(np.pi / 2)
    return np.where(x < 0, s_lo * k * (1 + erf(x / (np.sqrt(2) * s_lo))),
                    s_lo * k + s_hi * k * erf(x / (np.sqrt(2) * s_hi)))


def profile_image(centres, sigma=1.5, peak=150.0, bg=6.0, sigma_hi=None, full=255, noise=0.0,
                  seed=0, dtype=np.uint8) -> np.ndarray:
    """Columns holding pixel-integrated Gaussian stripes centred on rows ``centres[k][col]``.

    ``sigma_hi`` (below the centre, larger rows) makes the profile asymmetric: a two-sided
    Gaussian, whose intensity centroid (what eq. 9 estimates) is not its peak.
    """
    rows = np.arange(H, dtype=float)[:, None]
    img = np.full((H, W), bg)
    s_lo, s_hi = sigma, sigma if sigma_hi is None else sigma_hi
    for c in centres:
        lo, hi = rows - 0.5 - c[None, :], rows + 0.5 - c[None, :]
        img = img + peak * (_cdf(hi, s_lo, s_hi) - _cdf(lo, s_lo, s_hi))
    if noise:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, full).astype(dtype)


def two_sided_centroid(c, s_lo, s_hi):
    """Intensity centroid of a two-sided Gaussian with its peak at ``c``."""
    return c + np.sqrt(2 / np.pi) * (s_hi**2 - s_lo**2) / (s_lo + s_hi)


def phases(seed=1):
    """A stripe centre per column with every sub-pixel phase."""
    return 50.0 + np.random.default_rng(seed).uniform(0, 1, W)


def err_of(c, truth):
    return c["v"] - truth[c["u"].astype(int)]


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_grey_centre_symmetric_is_unbiased(backend):
    t = phases()
    c = grey_centre(profile_image([t]), threshold=0.15, backend=backend)
    assert c["u"].size == W
    e = err_of(c, t)
    assert np.sqrt(np.mean(e**2)) < 0.01
    assert np.all(c["flags"] == 0)


def test_grey_centre_asymmetric_gives_the_centroid():
    t = phases()
    c = grey_centre(profile_image([t], sigma=1.2, sigma_hi=2.0, peak=180), threshold=0.15, pad=3)
    truth = two_sided_centroid(t, 1.2, 2.0)
    assert np.sqrt(np.mean((c["v"] - truth[c["u"].astype(int)]) ** 2)) < 0.03
    # a window cut at the threshold would miss the long tail: the estimate would sit ~0.2 px
    # nearer the peak
    assert abs(np.mean(c["v"] - t[c["u"].astype(int)])) > 0.3


def test_grey_centre_saturated_is_centred_not_anchored():
    t = phases()
    img = profile_image([t], sigma=2.0, peak=900)  # flat top over ~5 rows
    c = grey_centre(img, threshold=0.15)
    e = err_of(c, t)
    assert np.all(c["flags"] & SATURATED)
    assert np.sqrt(np.mean(e**2)) < 0.03
    # the brightest-pixel-anchored window the paper's readers often use is biased here
    v_anchor = []
    for col in range(W):
        r = int(np.argmax(img[:, col]))  # first saturated pixel
        win = np.arange(r - 3, r + 4)
        w = img[win, col].astype(float)
        v_anchor.append((w * win).sum() / w.sum())
    assert np.sqrt(np.mean((np.array(v_anchor) - t) ** 2)) > 0.3


def test_grey_centre_noise():
    t = phases()
    c = grey_centre(profile_image([t], noise=2.0, seed=3), threshold=0.15)
    assert c["u"].size == W
    assert np.sqrt(np.mean(err_of(c, t) ** 2)) < 0.04


def test_two_stripes_close_together_are_both_found():
    t = phases()
    c = grey_centre(profile_image([t, t + 11.0]), threshold=0.15)
    assert c["u"].size == 2 * W
    top = c["v"][0::2] - t
    bot = c["v"][1::2] - (t + 11.0)
    assert np.sqrt(np.mean(top**2)) < 0.05 and np.sqrt(np.mean(bot**2)) < 0.05
    assert not np.any(c["flags"] & MERGED)


def test_merged_detected_among_normal_columns():
    # a crossing: two stripes far apart in most columns, merged in a few
    t = phases()
    t2 = t.copy()
    t2[:150] += 30.0
    t2[150:] += 4.0
    # at 38 counts (0.22 of this stripe's peak above its background): how far the runs of two
    # stripes 4 px apart reach beyond them, and so whether they look merged, depends on it
    c = grey_centre(profile_image([t, t2]), level=LEVEL_38)
    u = c["u"].astype(int)
    assert np.all((c["flags"][u < 150] & MERGED) == 0)
    assert np.all((c["flags"][u >= 150] & MERGED) != 0)


def test_no_stripe():
    img = profile_image([], noise=2.0)
    for c in (grey_centre(img), steger(img)):
        assert c["u"].size == 0 and set(c) >= {"u", "v", "flags", "nx", "ny", "ridge"}


def test_edge_flag():
    t = np.full(W, 1.0)
    c = grey_centre(profile_image([t]), threshold=0.15)
    assert np.all(c["flags"] & EDGE)


def test_sixteen_bit_same_centres():
    t = phases()
    img8 = profile_image([t], noise=1.0)
    img16 = img8.astype(np.uint16) * 257
    a, b = grey_centre(img8, threshold=0.15), grey_centre(img16, threshold=0.15)
    np.testing.assert_allclose(a["v"], b["v"], atol=1e-9)


def test_backends_agree_on_a_crossing_frame():
    rng = np.random.default_rng(4)
    u = np.arange(W, dtype=float)
    img = profile_image([60 + 0.3 * (u - 100), 60 - 0.25 * (u - 100)], noise=2.0, seed=5)
    img[rng.integers(0, H, 50), rng.integers(0, W, 50)] = 255  # hot pixels
    a, b = grey_centre(img, backend="numba"), grey_centre(img, backend="numpy")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


# ----------------------------------------------------------------------------- Gaussian fit
# Images of independent columns (each column its own random centre) are no line: the fit
# across the stripe (on by default) has no direction to follow in them, so the tests of the
# column fit's statistics on such images take the column fit alone (across=False).


def test_gaussian_symmetric_is_unbiased():
    t = phases()
    c = gaussian(profile_image([t]), across=False)
    assert c["u"].size == W and np.all(c["flags"] == 0)
    assert np.sqrt(np.mean(err_of(c, t) ** 2)) < 0.01


@pytest.mark.parametrize("top", [4.0, 6.0, 8.0])
def test_gaussian_stripe_near_the_frame_border_keeps_its_centre(top):
    # a stripe whose tail runs into the border: the window takes the tail up to the border and
    # the background comes from the other side (before, the tail's pixels were the background
    # line's: 0.053 / 0.018 / 0.017 px towards the middle at 4 / 6 / 8 rows from the border)
    t = top + np.random.default_rng(2).uniform(0, 1, W)
    img = profile_image([t], sigma=2.0)
    for im, truth in ((img, t), (img[::-1].copy(), H - 1 - t)):
        c = gaussian(im, across=False)
        e = err_of(c, truth)
        assert c["u"].size == W
        assert abs(np.mean(e)) < 0.002 and np.sqrt(np.mean(e**2)) < 0.006


def speckled_columns(n=4000, contrast=0.15, noise=20.0, peak=20000.0, sigma=2.2, seed=7):
    """16-bit columns of one point-sampled Gaussian stripe with multiplicative (speckle-like)
    and additive noise, the model the fit assumes; returns (image, true centres, model)."""
    rng = np.random.default_rng(seed)
    t = 60.0 + rng.uniform(-0.5, 0.5, n)
    r = np.arange(H, dtype=float)[:, None]
    mu = peak * np.exp(-0.5 * ((r - t[None, :]) / sigma) ** 2)
    img = 500.0 + mu * (1 + contrast * rng.standard_normal(mu.shape)) + noise * rng.standard_normal(mu.shape)
    return np.clip(np.round(img), 0, 65535).astype(np.uint16), t, mu


def wls_bound(mu_col, t, contrast, noise, peak, sigma, pad, threshold=0.15, bg=500.0):
    """Cramer-Rao variance of the centre for weighted least squares with the true weights over
    the fit window (run above the threshold + pad), computed from the model alone."""
    above = np.nonzero(mu_col + bg > threshold * 65535)[0]
    r = np.arange(above[0] - pad, above[-1] + pad + 1)
    z = (r - t) / sigma
    e = np.exp(-0.5 * z * z)
    J = np.stack([e, peak * e * z / sigma, peak * e * z * z / sigma], 1)
    w = 1.0 / (contrast**2 * (peak * e) ** 2 + noise**2)
    return np.linalg.inv(J.T @ (J * w[:, None]))[1, 1]


def test_gaussian_reaches_the_bound_and_estimates_the_noise():
    img, t, mu = speckled_columns()
    # the bound's window is the run above 0.15 of the 16-bit range (9830 counts)
    c, info = gaussian(img, return_info=True, across=False, level=0.15 * 65535)
    assert c["u"].size == t.size
    rms = np.sqrt(np.mean((c["v"] - t[c["u"].astype(int)]) ** 2))
    bound = np.sqrt(np.mean([wls_bound(mu[:, k], t[k], 0.15, 20.0, 20000.0, 2.2, 6) for k in range(300)]))
    # efficient: within 10 % of the bound (measured 4 %); the paper's grey centre is far off it
    assert rms < 1.10 * bound
    g = grey_centre(img, level=0.15 * 65535)
    assert rms < 0.5 * np.sqrt(np.mean((g["v"] - t[g["u"].astype(int)]) ** 2))
    # the noise levels it weighted by were found in the image itself
    assert info["relative_noise"] == pytest.approx(0.15, rel=0.05)
    assert info["noise_dn"] == pytest.approx(20.0, rel=0.1)


def test_gaussian_fixed_relative_noise_is_used():
    img, t, _ = speckled_columns(n=500)
    _, auto = gaussian(img, return_info=True, across=False)
    c, fixed = gaussian(img, relative_noise=0.3, return_info=True, across=False)
    assert fixed["relative_noise"] == 0.3 and auto["relative_noise"] != 0.3
    assert np.sqrt(np.mean((c["v"] - t[c["u"].astype(int)]) ** 2)) < 0.1


def test_gaussian_saturated_leaves_clipped_pixels_out():
    t = phases()
    c = gaussian(profile_image([t], sigma=2.0, peak=900), across=False)  # flat top over ~5 rows
    assert np.all(c["flags"] & SATURATED)
    assert np.sqrt(np.mean(err_of(c, t) ** 2)) < 0.03


def ring_image(radius=100.0, sigma=1.6, peak=150.0, size=(260, 320), ss=4):
    """The lower half of a circle of light (Gaussian profile across it), each pixel
    integrated over its area (ss x ss samples); returns the image and the true row of the
    circle at every column (NaN where the arc does not reach)."""
    h, w = size
    cx, cy = w / 2, 20.0
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    acc = np.zeros((h, w))
    for oy in (np.arange(ss) + 0.5) / ss - 0.5:
        for ox in (np.arange(ss) + 0.5) / ss - 0.5:
            d = np.hypot(xx + ox - cx, yy + oy - cy) - radius
            acc += np.exp(-0.5 * (d / sigma) ** 2) * (yy + oy > cy)
    img = np.clip(np.round(6.0 + peak * acc / ss**2), 0, 255).astype(np.uint8)
    du = np.arange(w) - cx
    q = radius**2 - du**2
    return img, np.where(q > 0, cy + np.sqrt(np.maximum(q, 0.0)), np.nan), du / np.sqrt(np.maximum(q, 1e-9))


def test_gaussian_across_removes_the_bias_of_column_cuts_of_a_curved_stripe():
    """A column cuts a steep, curved stripe obliquely: its profile is skewed towards the centre
    of curvature (rows ~2.5 sigma_col^2 s^2 v'' / (1 + s^2)^2 off). Fitted across the stripe,
    the centre is on the circle."""
    img, t, slope = ring_image()
    col, across = gaussian(img, across=False), gaussian(img)
    u = across["u"].astype(int)
    np.testing.assert_array_equal(u, col["u"].astype(int))
    # single stripes where the arc is no steeper than 3 (the arc's ends run into each other)
    clean = (across["flags"] == 0) & (np.abs(slope[u]) < 3.0)
    steep = clean & (np.abs(slope[u]) > 1.5)
    shallow = clean & (np.abs(slope[u]) < 0.25)
    assert steep.sum() > 20 and shallow.sum() > 20
    ny = 1.0 / np.hypot(1.0, slope[u])
    e_col, e_across = err_of(col, t) * ny, err_of(across, t) * ny  # px normal to the line
    # the column fit is pulled inside the circle by a tenth of a pixel or more (measured 0.30)
    assert np.mean(e_col[steep]) < -0.1
    # measured: mean -0.0006, RMS 0.009 px
    assert abs(np.mean(e_across[steep])) < 0.02 and np.sqrt(np.mean(e_across[steep] ** 2)) < 0.04
    # nearly level stripes are fitted along the column, as before
    np.testing.assert_array_equal(across["v"][shallow], col["v"][shallow])


def test_gaussian_two_close_stripes_and_merged():
    t = phases()
    c = gaussian(profile_image([t, t + 11.0]))
    assert c["u"].size == 2 * W and np.all(c["flags"] & CLOSE) and not np.any(c["flags"] & MERGED)
    assert np.sqrt(np.mean((c["v"][0::2] - t) ** 2)) < 0.05
    assert np.sqrt(np.mean((c["v"][1::2] - t - 11.0) ** 2)) < 0.05
    t2 = t.copy()
    t2[:150] += 30.0
    t2[150:] += 4.0
    c = gaussian(profile_image([t, t2]), level=LEVEL_38)  # as in test_merged_detected_among_normal_columns
    u = c["u"].astype(int)
    assert np.all((c["flags"][u < 150] & MERGED) == 0) and np.all((c["flags"][u >= 150] & MERGED) != 0)


@pytest.mark.parametrize("sep", [10.0, 12.0, 14.0])
@pytest.mark.parametrize("ratio", [1.0, 0.3])
def test_gaussian_two_close_stripes_are_fitted_together(sep, ratio):
    # alone, each window stops at the gap's midpoint and its background line runs through the
    # gap on the other stripe's tail, which pushed the two apart (sigma 2 px, 10 px apart:
    # 0.089 px each, the dim one of a 1 : 0.3 pair 0.10 px; 14 px apart: 0.021 / 0.043 px)
    t = 40.0 + np.random.default_rng(3).uniform(0, 1, W)
    img = profile_image([t], sigma=2.0).astype(float) + profile_image([t + sep], sigma=2.0,
                                                                      peak=150.0 * ratio, bg=0)
    c = gaussian(np.clip(img, 0, 255).astype(np.uint8), across=False)
    assert c["u"].size == 2 * W and np.all(c["flags"] & CLOSE)
    for k, truth in ((0, t), (1, t + sep)):
        e = c["v"][k::2] - truth
        assert abs(np.mean(e)) < 0.005 and np.sqrt(np.mean(e**2)) < 0.02  # 8-bit quantisation


def test_gaussian_sixteen_bit_and_no_stripe():
    t = phases()
    img8 = profile_image([t], noise=1.0)
    a, b = gaussian(img8), gaussian(img8.astype(np.uint16) * 257)
    np.testing.assert_allclose(a["v"], b["v"], atol=1e-9)
    c, info = gaussian(profile_image([], noise=2.0), return_info=True)
    assert c["u"].size == 0 and np.isnan(info["relative_noise"])


def sloped_line_image(slope, v0, sigma=1.4, peak=160.0, noise=0.0, seed=0):
    u = np.arange(W, dtype=float)
    t = v0 + slope * (u - W / 2)
    rows = np.arange(H, dtype=float)[:, None]
    img = np.full((H, W), 6.0)
    cos = 1 / np.sqrt(1 + slope**2)
    sub = np.linspace(-0.45, 0.45, 10)
    acc = sum(np.exp(-0.5 * (((rows + dv) - t[None, :]) * cos / sigma) ** 2) for dv in sub) / sub.size
    img = img + peak * acc
    if noise:
        img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), t


@pytest.mark.parametrize("slope", [0.0, 0.3, -0.6])
def test_steger_sloped_line(slope):
    img, t = sloped_line_image(slope, 60.3, noise=1.0)
    c = steger(img, threshold=0.15, sigma=1.5)
    inner = (c["u"] > 5) & (c["u"] < W - 6) & (c["v"] > 6) & (c["v"] < H - 7)
    expect = np.count_nonzero((t[6:W - 6] > 7) & (t[6:W - 6] < H - 8))
    assert inner.sum() >= 0.95 * expect
    e = err_of(c, t)[inner]
    assert np.sqrt(np.mean(e**2)) < 0.03
    n_true = np.array([-slope, 1.0]) / np.hypot(slope, 1.0)
    assert np.all(np.abs(c["nx"][inner] - n_true[0]) < 0.08)
    assert np.all(c["ny"] > 0) and np.all(c["ridge"] > 0)
    # one centre per column
    assert np.unique(c["u"]).size == c["u"].size
    # width: FWHM of the Gaussian model, 2.355 * 1.4 px (approximate: background not removed)
    assert abs(np.median(c["width_n"][inner]) - 2.3548 * 1.4) < 0.35


@pytest.mark.parametrize("extract", [grey_centre, gaussian])
@pytest.mark.parametrize("slope", [2.0, 3.0, -4.0])
def test_steep_stripe_is_one_stripe_not_merged(extract, slope):
    """A steep stripe's run in a column is long and its neighbours are several rows away: it
    is still one stripe (right normal, not MERGED), whereas a crossing's blob is merged."""
    img, t = sloped_line_image(slope, 60.3)
    c = extract(img)
    inner = (c["v"] > 28) & (c["v"] < 92)
    assert inner.sum() >= 10
    assert not np.any(c["flags"][inner] & MERGED)
    np.testing.assert_allclose(c["ny"][inner], 1 / np.hypot(1, slope), rtol=0.02)
    assert np.sqrt(np.mean(err_of(c, t)[inner] ** 2)) < 0.05


def test_steger_speckled_stripe_one_centre_per_column_on_the_ridge():
    """Speckle makes the flanks of a stripe ridge-like here and there; those weak claims are
    not stripe centres (kept, they gave a second centre in many columns, pixels off the line)."""
    img, t = sloped_line_image(1.2, 60.3, sigma=1.6, peak=180.0)
    rng = np.random.default_rng(11)
    # a multiplicative field correlated over about a pixel, contrast ~0.35
    speckle = np.exp(0.15 * cv2.GaussianBlur(rng.standard_normal(img.shape), (0, 0), 0.55) / 0.2)
    img = 6 + (img - 6.0) * speckle + rng.normal(0, 0.6, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    c = steger(img, threshold=0.15, sigma=2.0)
    inner = (c["u"] > 8) & (c["u"] < W - 9) & (c["v"] > 8) & (c["v"] < H - 9)
    assert np.unique(c["u"][inner]).size == inner.sum()
    assert np.max(np.abs(err_of(c, t)[inner])) < 1.0


def test_steger_two_crossing_lines_far_from_the_crossing():
    u = np.arange(W, dtype=float)
    img1, t1 = sloped_line_image(0.3, 60.0)
    img2, t2 = sloped_line_image(-0.25, 60.0)
    img = np.clip(img1.astype(int) + img2.astype(int) - 6, 0, 255).astype(np.uint8)
    c = steger(img, threshold=0.15, sigma=1.5)
    uu = c["u"].astype(int)
    e = np.minimum(np.abs(c["v"] - t1[uu]), np.abs(c["v"] - t2[uu]))
    far = (np.abs(t1 - t2)[uu] > 15) & (uu > 3) & (uu < W - 4)
    assert far.sum() > 100
    assert np.sqrt(np.mean(e[far] ** 2)) < 0.03
    assert np.count_nonzero(np.abs(t1 - t2)[np.unique(uu[far])] > 15) == np.unique(uu[far]).size
    del u


def test_steger_grey_centre_agree():
    img, _t = sloped_line_image(0.2, 55.7, noise=0.5)
    a, b = grey_centre(img), steger(img, sigma=1.5)
    common = np.intersect1d(a["u"], b["u"])[3:-3]
    va = a["v"][np.searchsorted(a["u"], common)]
    vb = b["v"][np.searchsorted(b["u"], common)]
    assert np.sqrt(np.mean((va - vb) ** 2)) < 0.03


# ----------------------------------------------------------------------------- PNG decoding


def _png(img: np.ndarray, filters: list[int]) -> bytes:
    """A grey PNG of ``img`` whose row r uses PNG filter ``filters[r % len(filters)]``."""
    h, w = img.shape
    depth = 8 if img.dtype == np.uint8 else 16
    raw = img.astype(">u2").view(np.uint8).reshape(h, -1) if depth == 16 else img
    bpp = depth // 8
    out = bytearray()
    prev = np.zeros(raw.shape[1], np.int32)
    for r in range(h):
        x = raw[r].astype(np.int32)
        a = np.concatenate([np.zeros(bpp, np.int32), x[:-bpp]])
        c = np.concatenate([np.zeros(bpp, np.int32), prev[:-bpp]])
        f = filters[r % len(filters)]
        if f == 0:
            y = x
        elif f == 1:
            y = x - a
        elif f == 2:
            y = x - prev
        elif f == 3:
            y = x - (a + prev) // 2
        else:
            p = a + prev - c
            pa, pb, pc = np.abs(p - a), np.abs(p - prev), np.abs(p - c)
            pred = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, prev, c))
            y = x - pred
        out += bytes([f]) + (y & 255).astype(np.uint8).tobytes()
        prev = x

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, depth, 0, 0, 0, 0)
    z = zlib.compress(bytes(out), 6)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", z[:100]) + chunk(b"IDAT", z[100:]) \
        + chunk(b"IEND", b"")


@pytest.mark.skipif(not fast_decoder_available(), reason="numba/imagecodecs not installed")
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("filters", [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4],
                                     [3, 3, 3, 0, 3, 3, 3, 3, 3, 2, 3, 3, 3, 3, 4]])
def test_fast_png_decoder_equals_opencv(dtype, filters):
    rng = np.random.default_rng(7)
    img = rng.integers(0, np.iinfo(dtype).max, (37, 53), dtype=np.int64).astype(dtype)
    img[10:20] = img[10:20] // 64  # some smooth-ish rows
    data = _png(img, filters)
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(ref, img)
    np.testing.assert_array_equal(decode_png(data, "x.png", "fast"), img)
    # transposed: the rows undone straight into the columns (8 bit), or transposed after
    for decoder in ("fast", "opencv"):
        t = decode_png(data, "x.png", decoder, transposed=True)
        assert t.flags.c_contiguous and t.dtype == img.dtype
        np.testing.assert_array_equal(t, img.T)


def test_transposed_frames_give_the_same_centres(tmp_path):
    """The stage's path (frames decoded transposed, extractors told so) = the plain one."""
    rng = np.random.default_rng(11)
    H, W = 120, 301
    u = np.arange(W)
    rows = np.arange(H)[:, None]
    img = 10 + 180 * np.exp(-0.5 * ((rows - (40 + 0.2 * u)) / 1.6) ** 2) \
        + 150 * np.exp(-0.5 * ((rows - (100 - 0.15 * u)) / 1.4) ** 2)
    img = np.clip(img * (1 + 0.1 * rng.standard_normal(img.shape)), 0, 255).astype(np.uint8)
    path = tmp_path / "f.png"
    path.write_bytes(_png(img, [3]))
    imT = read_frame(path, (H, W), transposed=True)
    assert imT.shape == (W, H)
    with pytest.raises(ImageError, match=f"expected {W + 1}x{H} px"):
        read_frame(path, (H, W + 1), transposed=True)
    for a, b in ((gaussian(img), gaussian(imT, transposed=True)),
                 (grey_centre(img), grey_centre(imT, transposed=True))):
        assert a.keys() == b.keys() and a["u"].size > 400
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])


def test_decoders_agree_on_opencv_png():
    rng = np.random.default_rng(8)
    img = np.clip(rng.normal(20, 5, (80, 300)), 0, 255).astype(np.uint8)
    _ok, buf = cv2.imencode(".png", img)
    a = decode_png(buf.tobytes(), "x.png", "auto")
    b = decode_png(buf.tobytes(), "x.png", "opencv")
    np.testing.assert_array_equal(a, img)
    np.testing.assert_array_equal(b, img)


@pytest.mark.parametrize("decoder", ["auto", "opencv"])
def test_corrupt_and_truncated_png_name_the_file(tmp_path, decoder):
    img = np.random.default_rng(9).integers(0, 255, (40, 60)).astype(np.uint8)
    data = _png(img, [1])
    bad = bytearray(data)
    bad[len(bad) // 2] ^= 0xFF
    (tmp_path / "bad.png").write_bytes(bytes(bad))
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    for name in ("bad.png", "cut.png"):
        with pytest.raises(ImageError, match=name):
            read_frame(tmp_path / name, decoder=decoder)
    (tmp_path / "ok.png").write_bytes(data)
    with pytest.raises(ImageError, match="expected 61x40"):
        read_frame(tmp_path / "ok.png", shape=(40, 61), decoder=decoder)


def test_map_frames_keeps_order_and_bounds_memory(tmp_path):
    paths = []
    for i in range(30):
        img = np.full((10, 12), i, np.uint8)
        p = tmp_path / f"{i:06d}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    live = []
    lock = threading.Lock()
    state = {"now": 0}

    def fn(i, img):
        with lock:
            state["now"] += 1
            live.append(state["now"])
        v = int(img[0, 0])
        with lock:
            state["now"] -= 1
        return i, v

    out = []
    for r in map_frames(paths, fn, threads=2, in_flight=3):
        out.append(r)
    assert out == [(i, i) for i in range(30)]
    assert max(live) <= 2


# ----------------------------------------------------------------------------- any sensor, any angle


def line_image(angle_deg, shape=(240, 320), sigma=1.6, peak=170.0, bg=8.0, ss=4, through=None):
    """A straight stripe at ``angle_deg`` (image x towards image y) through ``through`` (default
    the frame's middle), Gaussian across, each pixel integrated over ss x ss samples; float image
    (noise-free) and the line as (point, unit direction)."""
    h, w = shape
    p0 = np.array([w / 2 + 0.37, h / 2 - 0.21]) if through is None else np.asarray(through, float)
    a = np.radians(angle_deg)
    dvec = np.array([np.cos(a), np.sin(a)])
    nvec = np.array([-dvec[1], dvec[0]])
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    acc = np.zeros(shape)
    for oy in (np.arange(ss) + 0.5) / ss - 0.5:
        for ox in (np.arange(ss) + 0.5) / ss - 0.5:
            dn = (xx + ox - p0[0]) * nvec[0] + (yy + oy - p0[1]) * nvec[1]
            acc += np.exp(-0.5 * (dn / sigma) ** 2)
    return bg + peak * acc / ss**2, (p0, nvec)


def normal_error(c, line):
    p0, n = line
    return (c["u"] - p0[0]) * n[0] + (c["v"] - p0[1]) * n[1]


def noisy(img, seed=0, full=255, dtype=np.uint8):
    rng = np.random.default_rng(seed)
    return np.clip(np.round(img + rng.normal(0, 1.0, img.shape) * np.sqrt(0.5 * img + 1)), 0,
                   full).astype(dtype)


@pytest.mark.parametrize("angle", [0.0, 45.0, 90.0, 135.0, 80.0, 100.0])
@pytest.mark.parametrize("extractor", ["gaussian", "grey_centre"])
def test_stripes_at_any_angle(angle, extractor):
    """A stripe along the columns ('|', a '+' cross's other arm) is found as well as a level
    one: profiled along the rows where it is steeper than ROW_SLOPE, every centre in the
    frame's own (u, v), on the true line."""
    from crossline.scan.stripes import extract

    f, line = line_image(angle)
    img = noisy(f, seed=int(angle))
    c = extract(img, extractor, threshold=0.10)
    e = normal_error(c, line)
    # the stripe's length inside the frame, px, and the centres found along it: one per column
    # or per row, whichever the stripe crosses more of (a 45 deg stripe: one per column)
    h, w = img.shape
    a = np.radians(angle)
    length = min(w / max(abs(np.cos(a)), 1e-9), h / max(abs(np.sin(a)), 1e-9))
    expected = length * max(abs(np.cos(a)), abs(np.sin(a)))
    clean = (c["flags"] & (MERGED | EDGE)) == 0
    assert clean.sum() > 0.9 * expected, (clean.sum(), expected)
    assert np.sqrt(np.mean(e[clean] ** 2)) < 0.08
    # the old column-only extraction: a stripe along the columns gives no usable centre
    if abs(np.cos(a)) < 0.2:
        old = extract(img, extractor, threshold=0.10, rows=False)
        ok = (old["flags"] & MERGED) == 0
        assert np.sum(np.abs(normal_error(old, line)[ok]) < 0.5) < 0.1 * expected
        assert np.all(c["axis"][clean] == 1)
    if abs(np.sin(a)) < 0.5:
        assert np.all(c["axis"] == 0)


def test_plus_cross_both_arms():
    """A '+' turned by 10 deg: the level arm by columns, the steep arm by rows, each on its line."""
    from crossline.scan.stripes import extract

    f1, l1 = line_image(10.0)
    f2, l2 = line_image(100.0)
    img = noisy(f1 + f2 - 8.0, seed=3)
    c = extract(img, "gaussian", threshold=0.10)
    good = (c["flags"] & (MERGED | EDGE)) == 0
    e1, e2 = np.abs(normal_error(c, l1)), np.abs(normal_error(c, l2))
    on1, on2 = good & (e1 < 0.5), good & (e2 < 0.5)
    assert on1.sum() > 250 and on2.sum() > 180
    assert np.all(c["axis"][on1 & ~on2] == 0) and np.all(c["axis"][on2 & ~on1] == 1)
    # nothing off both lines but the crossing's merged blob
    off = good & (e1 > 1.0) & (e2 > 1.0)
    assert off.sum() <= 2


def test_twelve_bit_data_in_sixteen_bit_frames_and_exposure(tmp_path):
    """12-bit data in the low bits of 16-bit PNGs, and a frame at 20 % exposure: the stage finds
    the same centres as on the 8-bit frames at full exposure (within the noise), infers the
    data range and says so. The former threshold (0.15 of the container's 65535) found nothing."""
    import yaml

    from crossline.io.images import write_png
    from crossline.scan.stripes import run_extract_stripes
    from tests import scan_synth

    truth = scan_synth.make_capture(tmp_path / "c8", n_frames=6)
    ref = run_extract_stripes(tmp_path / "c8", "plate", tmp_path / "s8.parquet", extractor="gaussian")
    assert ref["data_range"] == {"max": 255, "bits": 8, "source": "8-bit frames"}
    s8 = pq.read_table(tmp_path / "s8.parquet").to_pandas()
    import shutil

    for name, gain in (("c12", 4095 / 255), ("c12_dim", 0.2 * 4095 / 255)):
        root = tmp_path / name
        shutil.copytree(tmp_path / "c8", root)
        rig = yaml.safe_load((root / "rig.yaml").read_text())
        rig["sensor"]["bit_depth"] = 16
        (root / "rig.yaml").write_text(yaml.safe_dump(rig))
        rng = np.random.default_rng(5)
        for f in sorted((root / "scans" / "plate" / "frames").glob("*.png")):
            x = cv2.imread(str(f), cv2.IMREAD_UNCHANGED).astype(float)
            # the signal above the background scaled; sensor noise of the 12-bit camera added
            y = 5.0 * 4095 / 255 + (x - 5.0) * gain + rng.normal(0, 2.0, x.shape)
            write_png(f, np.clip(np.round(y), 0, 4095).astype(np.uint16))
        meta = run_extract_stripes(root, "plate", tmp_path / f"{name}.parquet", extractor="gaussian")
        # inferred from the data: the dim frames never reach 1023, whatever the camera's ADC
        bits = 12 if name == "c12" else 10
        assert meta["data_range"]["max"] == 2**bits - 1 and meta["data_range"]["bits"] == bits
        assert "inferred from the frames" in meta["data_range"]["source"]
        s = pq.read_table(tmp_path / f"{name}.parquet").to_pandas()
        m = s8.merge(s, on=["frame", "u"], suffixes=("_8", ""))
        one = m.groupby(["frame", "u"]).filter(lambda g: len(g) == 1)  # A or B frames: one stripe
        assert len(s) > 0.97 * len(s8)
        d = (one["v"] - one["v_8"]).to_numpy()
        # the same centres within the noise (measured RMS 0.005 / 0.011 px; the 20 % frame has
        # 5x less signal)
        assert abs(np.mean(d)) < 0.005 and np.sqrt(np.mean(d**2)) < (0.02 if name == "c12" else 0.04)
        # against the truth as well
        err = [s.v[(s.frame == f) & (s.lasers == st)].to_numpy()
               - np.interp(s.u[(s.frame == f) & (s.lasers == st)], truth["cols"], truth["v"][f][st])
               for f, st in zip(truth["frames"], truth["states"], strict=True) if st in ("A", "B")]
        err = np.concatenate(err)
        assert np.sqrt(np.mean(err**2)) < (0.1 if name == "c12" else 0.3)
    # the former threshold (0.15 of 65535 = 9830 counts) lies above every 12-bit pixel
    img = cv2.imread(str(tmp_path / "c12" / "scans" / "plate" / "frames" / "000000.png"),
                     cv2.IMREAD_UNCHANGED)
    assert img.max() < 0.15 * 65535


def room_lit_frame(seed=3, noise=12.0):
    """A 16-bit frame: a stripe across a dark table and across a broad face lit by the room,
    brighter than the stripe's threshold, and dimmer on the table than on the face (a light
    block on a dark table): the stripe's true centre row per column, and the face's columns."""
    truth = 60.0 + 0.15 * np.arange(W) + 0.3 * np.sin(np.arange(W) / 9.0)
    rows = np.arange(H, dtype=float)[:, None]
    face = (np.arange(W) >= 80) & (np.arange(W) < 160)
    peak = np.where(face, 9000.0, 2500.0)  # the sheet is brighter on the light face
    lo, hi = rows - 0.5 - truth[None, :], rows + 0.5 - truth[None, :]
    img = 600.0 + peak[None, :] * (_cdf(hi, 2.0, 2.0) - _cdf(lo, 2.0, 2.0)) / (2.0 * np.sqrt(2 * np.pi))
    img[20:110, face] += 3000.0  # the room light on the face: 90 rows, wider than max_width
    img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.round(img), 0, 65535).astype(np.uint16), truth, face


def test_noise_is_the_sensor_s_not_the_scene_s_contrast():
    """The frame's noise comes from neighbouring pixels: a light face on a dark table is scene,
    not noise, and would otherwise lift the threshold above a dim stripe (random rig 1's plate)."""
    from crossline.scan.stripes import frame_levels

    img, _, _ = room_lit_frame(noise=12.0)
    lv = frame_levels(np.ascontiguousarray(img.T), 0.10, 65535.0)
    assert lv["noise"] == pytest.approx(12.0, rel=0.15)
    # the spread of the sample's values, what it was before, is the face's contrast
    assert np.std(img[::5, ::5]) > 50 * 12.0


@pytest.mark.parametrize("extractor", ["gaussian", "grey_centre", "steger"])
def test_stripe_across_a_room_lit_face_is_found_on_the_frame_s_own_pixels(extractor):
    """A surface lit by the room above the threshold swallows the stripe in one wide run; the
    runs are found again in the frame less its local background, the centres fitted on the
    frame itself: on the face as on the table, and as the same stripe without the room light."""
    from crossline.scan.stripes import extract

    img, truth, face = room_lit_frame()
    c = extract(img, extractor, threshold=0.10, data_max=65535.0)
    single = c["flags"] == 0
    u = c["u"][single].astype(int)
    on_face = face[u]
    # every column, but Steger's within its smoothing (3 sigma) of the face's sides, where the
    # room light steps across the columns
    step = np.convolve(np.abs(np.diff(face.astype(int), prepend=face[0])), np.ones(13), "same") > 0
    inner, table = face & ~step, ~face & ~step
    assert np.isin(np.flatnonzero(inner), u).all() and (~on_face).sum() >= 0.95 * (~face).sum()
    if extractor != "steger":
        assert on_face.sum() == face.sum()
    err = c["v"][single] - truth[u]
    tol = {"gaussian": 0.05, "grey_centre": 0.08, "steger": 0.08}[extractor]
    assert np.sqrt(np.mean(err[inner[u]] ** 2)) < tol
    assert np.sqrt(np.mean(err[table[u]] ** 2)) < tol
    # the same frame without the room light: the same centres where the stripe is on the face
    dark = img.astype(np.int64)
    dark[20:110, face] -= 3000
    d = extract(np.clip(dark, 0, 65535).astype(np.uint16), extractor, threshold=0.10, data_max=65535.0)
    sel = inner[u]
    both, ic, idd = np.intersect1d(c["u"][single][sel], d["u"][d["flags"] == 0], return_indices=True)
    assert both.size == inner.sum()
    dv = c["v"][single][sel][ic] - d["v"][d["flags"] == 0][idd]
    assert np.abs(dv).max() < 0.02 if extractor != "steger" else np.abs(dv).max() < 0.05


def test_colour_scan_frames_are_measured_on_the_laser_s_channel(tmp_path) -> None:
    """Without ``sensor.channel`` a colour scan is measured on the channel in which its stripe
    stands highest above the noise: a red laser on a part the room lights white and green is
    red, not the luminance (which mixes in the other channels' noise) nor the green that
    holds the scene's brightest light."""
    from crossline.io.images import write_image, write_png
    from crossline.scan.stripes import scan_channel

    rng = np.random.default_rng(5)
    h, w = 120, 200
    v = np.arange(h)[:, None]
    paths = []
    for k in range(4):
        stripe = 150.0 * np.exp(-0.5 * ((v - 40 - 10 * k) / 2.0) ** 2) * np.ones((1, w))
        rgb = np.empty((h, w, 3))
        rgb[..., 0] = 30 + stripe
        rgb[..., 1] = 30 + 0.08 * stripe
        rgb[..., 1][:, 120:] += 200  # a green-lit patch, brighter than the stripe, no line
        rgb[..., 2] = 30 + 0.05 * stripe
        rgb += rng.normal(0, 3.0, rgb.shape)
        p = tmp_path / f"{k:06d}.png"
        write_image(p, np.clip(rgb, 0, 255).round().astype(np.uint8))
        paths.append(p)
    chosen = scan_channel(paths, None, (h, w))
    assert chosen["name"] == "red" and chosen["source"].startswith("chosen")
    assert chosen["scores"]["red"] > 1.3 * chosen["scores"]["grey"]
    assert scan_channel(paths, "green", (h, w)) == {"name": "green", "source": "rig.yaml sensor.channel"}
    grey = tmp_path / "grey.png"
    write_png(grey, np.full((h, w), 30, np.uint8))
    assert scan_channel([grey], None, (h, w))["name"] is None
    with pytest.raises(ValueError, match=r"000000\.png: image is 200x120 px, expected 100x120 px"):
        scan_channel(paths, None, (h, 100))


def test_colour_capture_stage_measures_the_red_channel_and_gathers_the_choice(tmp_path):
    """The stage on colour frames without ``sensor.channel``: the red laser's channel is chosen,
    the centres are those of the same frames written grey, and the gathered file says which
    channel and why."""
    import shutil

    from crossline.io.images import write_image
    from crossline.scan.stripes import gather_stripes, read_stripes_meta, run_extract_stripes
    from tests import scan_synth

    scan_synth.make_capture(tmp_path / "grey", n_frames=4)
    shutil.copytree(tmp_path / "grey", tmp_path / "rgb")
    rng = np.random.default_rng(2)
    for f in sorted((tmp_path / "rgb" / "scans" / "plate" / "frames").glob("*.png")):
        g = cv2.imread(str(f), cv2.IMREAD_UNCHANGED).astype(float)
        flat = np.full_like(g, 40.0) + rng.normal(0, 2.0, g.shape)  # green, blue: no stripe
        rgb = np.dstack([g, flat, flat + 20.0])
        f.unlink()
        write_image(f, np.clip(np.round(rgb), 0, 255).astype(np.uint8))
    run_extract_stripes(tmp_path / "grey", "plate", tmp_path / "g.parquet", extractor="gaussian")
    part = tmp_path / "p.parquet"
    run_extract_stripes(tmp_path / "rgb", "plate", part, extractor="gaussian")
    gather_stripes([part], tmp_path / "rgb.parquet")
    ch = read_stripes_meta(tmp_path / "rgb.parquet")["channel"]
    assert ch["name"] == "red" and ch["source"].startswith("chosen")
    a = pq.read_table(tmp_path / "g.parquet").to_pandas()
    b = pq.read_table(tmp_path / "rgb.parquet").to_pandas()
    assert len(a) == len(b) and np.array_equal(a["v"].to_numpy(), b["v"].to_numpy())


def _printed_marks(shift: float = 0.0) -> np.ndarray:
    """The room's light on printed marks: bright bars 3 px wide, 23 px apart, at 60 degrees,
    as narrow as a stripe (no local background takes them out), 70 counts above the plate."""
    from tests import scan_synth

    _x0, _y0, w, h = scan_synth.WINDOW
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    t = (xx + shift) * np.cos(np.radians(60.0)) + yy * np.sin(np.radians(60.0))
    return 70.0 * (np.mod(t, 23.0) < 3.0)


def _against_truth(s, truth, frames) -> tuple[int, float]:
    """Centres of ``frames`` farther than 3 px from their true lines, and the others' RMS."""
    far, err = 0, []
    for f in frames:
        g = s[s.frame == f]
        st = truth["states"][f]
        d = np.min([np.abs(g.v.to_numpy() - np.interp(g.u, truth["cols"], truth["v"][f][x]))
                    for x in ("A", "B") if x in st], axis=0)
        far += int(np.count_nonzero(d > 3.0))
        err.append(d[d <= 3.0])
    return far, float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


def test_off_frames_take_the_room_s_light_out_where_it_stood_still(tmp_path):
    """A scan with off frames (A, B, AB, off) under printed marks lit by the room: the marks,
    narrow as a stripe, are found as stripes in every laser frame (about 3500 centres each);
    less the room's light of the off frames on either side, the frames between two off frames
    have none and their centres' error is that of the same scan without the marks. Where the
    marks move between off frames (3 px per frame) nothing is subtracted, and the stage gives
    what it gives without its off frames. Chunks read the off frames of their neighbours and
    join into the same table; an off frame that cannot be read is named."""
    from crossline.errors import CrosslineError
    from crossline.scan.stripes import gather_stripes, run_extract_stripes
    from tests import scan_synth

    pattern = ("A", "B", "AB", "off")
    runs = {}
    for name, ambient in (("clean", None), ("still", lambda i: _printed_marks()),
                          ("moving", lambda i: _printed_marks(3.0 * i))):
        truth = scan_synth.make_capture(tmp_path / name, n_frames=16, pattern=pattern, ambient=ambient)
        for mode in ("ignore", "subtract"):
            out = tmp_path / f"{name}_{mode}.parquet"
            meta = run_extract_stripes(tmp_path / name, "plate", out, extractor="gaussian", off_frames=mode)
            runs[name, mode] = meta, pq.read_table(out).to_pandas()
    # frames 0-2 precede the first off frame (3): one off frame cannot show that nothing moved
    between = [f for f in range(4, 15) if truth["states"][f] != "off"]
    counts = runs["still", "subtract"][0]["counts"]
    assert counts["frames_room_light_subtracted"] == len(between) == 9
    assert counts["frames_room_light_kept"] == 3
    far_marks, _ = _against_truth(runs["still", "ignore"][1], truth, between)
    far, rms = _against_truth(runs["still", "subtract"][1], truth, between)
    far_clean, rms_clean = _against_truth(runs["clean", "ignore"][1], truth, between)
    assert far_marks > 1000 * len(between)
    # no narrow room light, nothing subtracted and no noise added: the same table
    assert runs["clean", "subtract"][1].equals(runs["clean", "ignore"][1])
    assert far <= far_clean + 5
    assert rms < 1.1 * rms_clean
    moving = runs["moving", "subtract"]
    assert moving[0]["counts"]["frames_room_light_subtracted"] == 0
    assert moving[1].equals(runs["moving", "ignore"][1])

    parts = [tmp_path / f"part{i}.parquet" for i in range(3)]
    for i, part in enumerate(parts):
        run_extract_stripes(tmp_path / "still", "plate", part, extractor="gaussian", chunk=(i, 3), threads=2)
    gather_stripes(parts, tmp_path / "gathered.parquet")
    assert pq.read_table(tmp_path / "gathered.parquet").to_pandas().equals(runs["still", "subtract"][1])

    (tmp_path / "still" / "scans" / "plate" / "frames" / "000007.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(CrosslineError, match=r"000007\.png"):
        run_extract_stripes(tmp_path / "still", "plate", tmp_path / "bad.parquet", extractor="gaussian",
                            threads=2)
    assert not (tmp_path / "bad.parquet").exists()


@pytest.mark.parametrize("meta", [b"[1, 2]", b"{not json", b'{"frame_range": "0-3", "counts": {}}'])
def test_gather_refuses_a_chunk_whose_metadata_is_broken(tmp_path, meta):
    """A chunk whose crossline metadata is a list, not JSON, or lacks its frame range is named,
    not a traceback (found by reading gather_stripes for issue 23.2)."""
    import pyarrow as pa

    from crossline.errors import StageError
    from crossline.scan.stripes import STRIPES_SCHEMA, gather_stripes

    path = tmp_path / "part0-of-1.parquet"
    table = pa.Table.from_pylist([], schema=STRIPES_SCHEMA)
    pq.write_table(table.replace_schema_metadata({b"crossline": meta}), path)
    with pytest.raises(StageError, match=r"part0-of-1\.parquet"):
        gather_stripes([path], tmp_path / "out.parquet")
    assert not (tmp_path / "out.parquet").exists()


def speckled_line(slope, H=800, W=400, sigma=1.5, peak=150.0, contrast=0.2, noise=2.0, seed=0,
                  at=(0.5, 0.5)):
    """A stripe through (W at[0], H at[1]) of ``slope`` rows per column under a speckle field
    (log-normal, grain 1 px) and read noise, 8-bit."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(float)
    d = ((v - H * at[1]) - slope * (u - W * at[0])) / np.sqrt(1 + slope**2)
    g = cv2.GaussianBlur(rng.standard_normal((H, W)), (0, 0), 1.0)
    speck = np.exp(contrast / g.std() * g - 0.5 * contrast**2)
    return peak * speck * np.exp(-0.5 * (d / sigma) ** 2) + rng.normal(0, noise, (H, W))


def _traces(c):
    from crossline.scan.centreline import link_traces, trace_position, trace_space

    tu, tv = trace_space(c["u"], c["v"], c["axis"])
    prev = link_traces(np.zeros(tu.size, np.int64), np.full(tu.size, "A"), tu, tv)
    return np.bincount(trace_position(prev, tu, tv)[0])


@pytest.mark.parametrize("slope", [3.2, 3.6, 4.0, 4.2, 4.5, -4.0])
def test_a_stripe_near_the_row_slope_is_one_trace(slope):
    """About ROW_SLOPE rows per column, a stripe's column runs are about ROW_SLOPE times its row
    runs, and speckle moves that ratio about it: taken centre by centre, the stripe alternated
    between row and column centres, and its traces broke into pieces too short to keep (4.2:
    32 traces, 4.5: 127). A steep stretch is now taken whole: one trace, a centre per row."""
    from crossline.scan.stripe_frame import ROW_SLOPE, extract

    assert ROW_SLOPE < abs(slope)
    img = np.clip(np.round(6 + speckled_line(slope)), 0, 255).astype(np.uint8)
    c = extract(img, "gaussian", threshold=0.10)
    sizes = _traces(c)
    assert np.all(c["axis"] == 1) and c["u"].size > 0.95 * img.shape[0]
    assert sizes.max() > 0.98 * c["u"].size


def test_the_dimmer_of_two_crossing_stripes_keeps_its_centres():
    """Both lasers on, one stripe a quarter as bright as the other: against the brighter one's
    peak, the stage's min_peak test took the dimmer one's speckle-dark columns for glints and
    dropped them; each stripe is now held to its own peak (stripe_peaks, by direction)."""
    from crossline.scan.stripes import _frame_work

    H, W = 600, 900
    dim = speckled_line(0.1, H, W, peak=2000.0, contrast=0.3, noise=8.0, seed=1)
    bright = speckled_line(-2.0, H, W, peak=8000.0, contrast=0.3, noise=8.0, seed=2, at=(0.3, 0.5))
    img = np.clip(np.round(400 + dim + bright), 0, 65535).astype(np.uint16)
    params = {"threshold": 0.10, "min_width": 2.0, "max_width": 30.0, "fit_pad": 6, "relative_noise": None,
              "fit_across": True, "min_peak": 0.17}
    c = _frame_work("gaussian", params, 65535.0)(0, np.ascontiguousarray(img.T))
    u, v = c["u"], c["v"]
    on_dim = np.abs((v - H / 2) - 0.1 * (u - W / 2)) < 2.0
    away = np.abs(u - 0.3 * W) > 40  # off the crossing
    cols = np.unique(np.round(u[on_dim & away]))
    assert cols.size > 0.97 * np.sum(np.abs(np.arange(W) - 0.3 * W) > 40)
    # each stripe's own peak: the dimmer one's a quarter of the brighter one's
    from crossline.scan.stripe_levels import stripe_peaks

    peaks = stripe_peaks(c["peak"], c["nx"], c["ny"], 1e9)
    assert np.median(peaks[on_dim & away]) < 0.5 * np.median(peaks[~on_dim])


def test_a_narrow_dim_stripe_beside_a_bright_one_is_found_at_its_own_level():
    """Both lasers on, one stripe narrow (sigma 0.8 px) and a quarter as bright (12-bit data): at
    the level the brighter one sets, the dim one's runs are 1-2 px wide and fall below min_width
    in every other column (a quarter of its columns were lost, its traces broke). It is now
    extracted again at its own level; its centres are as good as where it is alone."""
    from crossline.scan.stripes import _frame_work

    H, W = 600, 900
    params = {"threshold": 0.10, "min_width": 2.0, "max_width": 30.0, "fit_pad": 6, "relative_noise": None,
              "fit_across": True, "min_peak": 0.17}
    work = _frame_work("gaussian", params, 4095.0)
    dim = speckled_line(0.1, H, W, sigma=0.8, peak=540.0, contrast=0.3, noise=13.0, seed=1)
    bright = speckled_line(-2.0, H, W, sigma=2.5, peak=2000.0, contrast=0.3, noise=0.0, seed=2, at=(0.3, 0.5))
    away = np.abs(np.arange(W) - 0.3 * W) > 40  # columns off the crossing

    def on_dim(img, lasers_on):
        frame = np.clip(np.round(102 + img), 0, 4095).astype(np.uint16)
        c = work(0, np.ascontiguousarray(frame.T), lasers_on)
        u, v = c["u"], c["v"]
        d = (v - H / 2) - 0.1 * (u - W / 2)
        sel = (np.abs(d) < 2.0) & away[np.round(u).astype(int).clip(0, W - 1)]
        return np.unique(np.round(u[sel])).size / away.sum(), d[sel].std()

    alone_cols, alone_sd = on_dim(dim, 1)
    one_pass_cols, _ = on_dim(dim + bright, 1)  # as every frame was extracted before
    both_cols, both_sd = on_dim(dim + bright, 2)
    assert one_pass_cols < 0.85 and alone_cols > 0.99
    assert both_cols > 0.99
    assert both_sd < 1.1 * alone_sd


def test_the_stage_counts_the_dim_stripe_centres_it_adds(tmp_path):
    """The stage, on a scan whose laser B is narrow and a fifth as bright as A: the stripes'
    metadata counts the two-laser frames and the centres that the dim stripe's own level
    added, and what it added lies on the true stripes (this scan's X is 26 deg wide, which
    the directions of so narrow a stripe's centres scatter across: it is filled in only in part)."""
    from crossline.scan.stripes import run_extract_stripes
    from tests import scan_synth

    truth = scan_synth.make_capture(tmp_path / "c", n_frames=12, laser_peaks={"A": 200.0, "B": 40.0},
                                    sigma=0.8)
    meta = run_extract_stripes(tmp_path / "c", "plate", tmp_path / "s.parquet", extractor="gaussian",
                               threshold=0.10)
    s = pq.read_table(tmp_path / "s.parquet").to_pandas()
    x0 = scan_synth.WINDOW[0]
    states = np.asarray(truth["states"])
    assert meta["counts"]["frames_dim_stripe"] == np.sum(states == "AB")
    assert meta["counts"]["centres_dim_stripe"] > 0
    assert meta["counts"]["frames"] == len(states)
    off_line = 0
    for i in np.flatnonzero(states == "AB"):
        f = s[s["frame"] == i]
        col = np.round(f["u"]).astype(int) - x0
        d = np.minimum(np.abs(f["v"] - truth["v"][i]["A"][col]), np.abs(f["v"] - truth["v"][i]["B"][col]))
        off_line += int(np.sum(d > 1.5))
    assert off_line == 0
