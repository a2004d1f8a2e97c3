"""Render honesty, small and fast: rays through the distortion, the stripe's centre, speckle, noise."""

from __future__ import annotations

import numpy as np
import pytest

from crossline.geometry import invert_transform
from crossline.sim import arm
from crossline.sim.optics import RayTable, lattice_offsets, pixel_offsets, speckle_field
from crossline.sim.presets import PRESETS
from crossline.sim.render import Light, RigModel, render_image
from crossline.sim.scenes import scan_scene


@pytest.fixture(scope="module")
def paper_model() -> RigModel:
    return RigModel(PRESETS["paper"], bit_depth=16)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_sample_rays_reproject_to_their_sample_positions(preset):
    """Every supersample ray, wherever on the sensor, reprojects to its position (< 1e-4 px)."""
    model = RigModel(PRESETS[preset])
    cam = model.camera
    w, h = cam.image_size
    rng = np.random.default_rng(3)
    # a strip along the top edge and one in the corner: the strongest distortion
    for window in ((0, 0, w, 40), (w - 300, h - 200, 300, 200), model.scan_window):
        table = RayTable(cam, window)
        x0, y0, ww, hh = window
        rows = rng.integers(0, hh, 3000)
        cols = rng.integers(0, ww, 3000)
        # pixel centres
        xy = table.pixel_xy(rows, cols)
        P = np.column_stack([xy, np.ones(len(xy))])
        err = cam.project(P) - np.column_stack([cols + x0, rows + y0])
        assert np.abs(err).max() < 1e-4
        for n in (2, 4):
            offs = pixel_offsets(n)
            sxy = table.sample_xy(rows, cols, offs)
            P = np.concatenate([sxy, np.ones((*sxy.shape[:2], 1))], -1).reshape(-1, 3)
            want = np.stack([cols[:, None] + x0 + offs[None, :, 0],
                             rows[:, None] + y0 + offs[None, :, 1]], -1).reshape(-1, 2)
            assert np.abs(cam.project(P) - want).max() < 1e-4
        offs = lattice_offsets(rows, cols, 8)  # one set of offsets per pixel
        sxy = table.sample_xy(rows, cols, offs)
        P = np.concatenate([sxy, np.ones((*sxy.shape[:2], 1))], -1).reshape(-1, 3)
        want = np.stack([cols[:, None] + x0 + offs[..., 0], rows[:, None] + y0 + offs[..., 1]], -1)
        assert np.abs(cam.project(P) - want.reshape(-1, 2)).max() < 1e-4
        if window == model.scan_window:
            sxy = table.sample_xy_2x2(rows, cols)
            P = np.concatenate([sxy, np.ones((*sxy.shape[:2], 1))], -1).reshape(-1, 3)
            offs = pixel_offsets(2)
            want = np.stack([cols[:, None] + x0 + offs[None, :, 0],
                             rows[:, None] + y0 + offs[None, :, 1]], -1).reshape(-1, 2)
            assert np.abs(cam.project(P) - want).max() < 1e-4


@pytest.mark.parametrize("n", [4, 8])
def test_lattice_samples_resolve_an_edge_along_the_pixel_grid(n: int) -> None:
    """The board views' edge samples: one per cell of an n x n grid, each in its own of n² columns
    and rows, all inside the pixel; a straight edge along the pixel columns is then measured to
    within 1/(2 n²) of its true coverage in every pixel, with no bias over many pixels (a regular
    n x n grid errs by up to 1/(2 n), the same way in every pixel along the edge)."""
    rows, cols = np.divmod(np.arange(5000), 100)
    offs = lattice_offsets(rows, cols, n)
    assert offs.shape == (5000, n * n, 2) and np.abs(offs).max() <= 0.5
    cell = np.floor((offs[0] + 0.5) * n).astype(int)
    assert len({tuple(c) for c in cell}) == n * n  # one sample per cell
    for k in range(2):
        assert len(np.unique(np.round(offs[0, :, k] * n * n, 6))) == n * n  # own column and row
    rng = np.random.default_rng(5)
    edge = rng.uniform(-0.5, 0.5, 5000)  # a vertical edge at du = edge in each pixel
    covered = np.mean(offs[..., 0] < edge[:, None], axis=1)
    err = covered - (edge + 0.5)
    assert np.abs(err).max() <= 1.0 / n**2 + 1e-12
    assert abs(err.mean()) < 0.1 / n**2
    regular = np.mean(pixel_offsets(n)[None, :, 0] < edge[:, None], axis=1) - (edge + 0.5)
    assert np.abs(regular).max() > 0.4 / n


def _frame(model, scan, laser, frame=None):
    rig = model.preset
    spec = next(s for s in rig.scans if s.name == scan)
    scene_b, _, aim = scan_scene(rig, spec)
    _, Tbc = arm.scan_trajectory(rig, spec, aim, spec.frames)
    k = spec.frames // 2 if frame is None else frame
    scene = scene_b.transformed(invert_transform(Tbc[k]))
    dark = Light(0.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), np.zeros(3))
    dn, rows, stats = render_image(model, scene, dark, model.scan_window, (laser,),
                                   np.random.default_rng(0), noise=False, speckle=False)
    return dn, rows[laser], stats


@pytest.mark.parametrize("laser", ["A", "B"])
def test_clean_stripe_centroid_on_a_plane_is_the_true_centreline(paper_model, laser):
    """Noise and speckle off, unsaturated (16 bit): the grey centre per column lies within 0.05 px."""
    dn, rows, _ = _frame(paper_model, "plate", laser)
    img = dn.astype(np.float64) - paper_model.sensor.black
    assert img.max() < 65535 - paper_model.sensor.black  # not saturated
    x0, y0 = paper_model.scan_window[:2]
    vis = rows["visible"]
    assert vis.sum() > 300
    errs = []
    for u, v in zip(rows["u"][vis], rows["v"][vis], strict=True):
        col = img[:, u - x0]
        vv = np.arange(len(col)) + y0
        m = np.abs(vv - v) < 20
        if m.sum() < 40:  # too close to the window's edge
            continue
        errs.append((col[m] * vv[m]).sum() / col[m].sum() - v)
    errs = np.array(errs)
    assert len(errs) > 300
    assert np.abs(errs).max() < 0.05, np.abs(errs).max()


def test_stripe_width_and_level_are_plausible(paper_model):
    """The stripe is a few px wide (1/e^2) and its light lies where the truth says."""
    dn, rows, stats = _frame(paper_model, "plate", "A")
    img = dn.astype(np.float64) - paper_model.sensor.black
    x0 = paper_model.scan_window[0]
    u = rows["u"][rows["visible"]][len(rows["u"]) // 4]
    col = img[:, u - x0]
    above = np.nonzero(col > col.max() * np.exp(-2))[0]
    width = above.max() - above.min() + 1
    assert 4 <= width <= 16  # along the column; the stripe is oblique
    assert stats["band_px"] > 0


@pytest.mark.parametrize("grain", [0.3, 0.55, 1.0, 1.5])
def test_speckle_field_has_the_stated_contrast_per_pixel(grain):
    """Contrast C per pixel for every grain the rigs draw (0.3-1.5 px), sub-pixel ones too."""
    rng = np.random.default_rng(5)
    f = speckle_field(rng, np.ones((400, 400), np.uint8), 0.15, grain)[20:-20, 20:-20]
    assert abs(f.mean() - 1.0) < 0.005
    assert abs(f.std() / f.mean() - 0.15) < 0.003


def test_speckle_field_has_the_stated_contrast_and_grain():
    rng = np.random.default_rng(5)
    mask = np.ones((400, 400), np.uint8)
    f = speckle_field(rng, mask, 0.15, 0.55)
    inner = f[20:-20, 20:-20]
    assert abs(inner.mean() - 1.0) < 0.01
    assert abs(inner.std() / inner.mean() - 0.15) < 0.015
    # correlated over about one pixel: neighbours correlate, pixels 3 apart hardly
    g = np.log(inner)
    g = (g - g.mean()) / g.std()
    c1 = np.mean(g[:, 1:] * g[:, :-1])
    c3 = np.mean(g[:, 3:] * g[:, :-3])
    assert 0.3 < c1 < 0.9
    assert abs(c3) < 0.1
    # outside the band the field is exactly 1
    mask[:, :200] = 0
    f = speckle_field(rng, mask, 0.15, 0.55)
    assert np.all(f[:, :200] == 1.0)


def test_sensor_noise_matches_the_model(paper_model):
    """Flat field: the DN standard deviation is sqrt(shot + read) / gain (8 bit)."""
    model = RigModel(PRESETS["paper"], bit_depth=8)
    s = model.sensor
    e = np.full((300, 300), 4000.0, np.float32)
    dn = s.digitise(e, np.random.default_rng(1), (0, 0, 300, 300)).astype(np.float64)
    want_mean = 4000.0 / s.gain + s.black
    prnu = s.spec.prnu * 4000.0 / s.gain
    want_std = np.sqrt((4000.0 + s.spec.read_noise_e**2) / s.gain**2 + prnu**2 + 1 / 12)
    assert abs(dn.mean() - want_mean) < 0.1
    assert abs(dn.std() - want_std) / want_std < 0.05
    # saturation: far above the full well everything clips to the top code
    dn = s.digitise(np.full((50, 50), 3e4, np.float32), np.random.default_rng(1), (0, 0, 50, 50))
    assert dn.min() >= 254 and np.mean(dn == 255) > 0.99


@pytest.mark.slow
@pytest.mark.parametrize("scan", ["gauge", "ball"])
def test_the_band_holds_all_the_laser_light(paper_model, scan):
    """Tracing every pixel of the frame finds no laser light outside the band (steps, limbs)."""
    from crossline.sim.render import render_band, stripe_truth

    rig = paper_model.preset
    spec = next(s for s in rig.scans if s.name == scan)
    scene_b, _, aim = scan_scene(rig, spec)
    _, Tbc = arm.scan_trajectory(rig, spec, aim, spec.frames)
    scene = scene_b.transformed(invert_transform(Tbc[spec.frames // 2 + 1]))
    sheets = [paper_model.lasers["A"], paper_model.lasers["B"]]
    window = paper_model.scan_window
    mask = np.zeros((window[3], window[2]), np.uint8)
    for sh in sheets:
        mask |= stripe_truth(paper_model, scene, sh, window, truth=False)[0]
    rows, cols = np.nonzero(np.ones_like(mask))
    vals, _ = render_band(paper_model, scene, sheets, window, rows, cols)
    light = vals.sum(0).reshape(mask.shape)
    assert light.max() > 3000  # electrons: there is a stripe
    outside = light[mask == 0]
    assert outside.max() < 1.0  # less than one electron anywhere outside the band
    assert mask.mean() < 0.1  # and the band is a small part of the frame


def test_fast_normals_are_standard_normal_and_independent():
    """Box-Muller draws: N(0, 1) moments and tails, no correlation, reproducible, any length."""
    from scipy import stats

    from crossline.sim.optics import standard_normal_f32

    z = standard_normal_f32(np.random.default_rng(11), 2_000_001)
    assert z.dtype == np.float32 and z.shape == (2_000_001,) and np.isfinite(z).all()
    z64 = z.astype(np.float64)
    assert abs(z64.mean()) < 3e-3 and abs(z64.std() - 1.0) < 3e-3
    assert abs(stats.skew(z64)) < 0.01 and abs(stats.kurtosis(z64)) < 0.02
    assert stats.kstest(z64[:500_000], "norm").pvalue > 1e-3
    # tails: |z| > 3 and > 4 as often as for a true normal (binomial 5 sigma bounds)
    for k in (3.0, 4.0):
        p = 2 * stats.norm.sf(k)
        n = np.count_nonzero(np.abs(z64) > k)
        assert abs(n - p * z.size) < 5 * np.sqrt(p * z.size)
    # the cosine and sine of one word (even, odd entries), and neighbours, are independent
    c, s = z64[0:-1:2], z64[1::2]
    for x, y in ((c, s), (c**2, s**2), (z64[:-1], z64[1:]), (s[:-1], c[1:])):
        assert abs(np.corrcoef(x, y)[0, 1]) < 3e-3
    # same generator state, same draws; into a given buffer too; and a stream: an even
    # number of draws and then the rest are the draws of one call
    out = np.empty(7, np.float32)
    a = standard_normal_f32(np.random.default_rng(3), 7)
    b = standard_normal_f32(np.random.default_rng(3), 7, out=out)
    assert b is out and np.array_equal(a, b)
    rng = np.random.default_rng(3)
    assert np.array_equal(np.concatenate([standard_normal_f32(rng, 4), standard_normal_f32(rng, 3)]), a)


def _digitise_whole(sensor, e, rng, window, noise=True):
    """The sensor model of ``SensorModel.digitise`` as one pass over the whole image."""
    from crossline.sim.optics import standard_normal_f32

    x0, y0, w, h = window
    e = e.astype(np.float32) * sensor.prnu_map[y0 : y0 + h, x0 : x0 + w]
    e = np.maximum(e, np.float32(0.0)).ravel()
    fw, rn = sensor.spec.full_well_e, sensor.spec.read_noise_e
    if noise:
        low = np.nonzero(e < 30.0)[0]
        high = np.nonzero(e > fw - 6.0 * np.sqrt(fw))[0]
        lam, e_high = e[low].astype(np.float64), e[high].astype(np.float64)
        e = e + np.sqrt(e + np.float32(rn**2)) * standard_normal_f32(rng, e.size)
        e[low] = (rng.poisson(lam) + rn * rng.standard_normal(lam.size)).astype(np.float32)
        shot = np.minimum(e_high + np.sqrt(e_high) * rng.standard_normal(e_high.size), fw)
        e[high] = (shot + rn * rng.standard_normal(e_high.size)).astype(np.float32)
    else:
        e = np.minimum(e, np.float32(fw))
    dn = np.clip(np.rint(e * np.float32(1.0 / sensor.gain) + np.float32(sensor.black)), 0, sensor.top)
    return dn.reshape(h, w).astype(np.uint16 if sensor.bits == 16 else np.uint8)


@pytest.mark.parametrize("bits", [8, 16])
def test_digitise_in_bands_of_rows_is_the_whole_image_model(bits):
    """Band by band (cache-sized) gives the same DN, bit for bit, as one whole-image pass."""
    model = RigModel(PRESETS["paper"], bit_depth=bits)
    s = model.sensor
    rng = np.random.default_rng(4)
    # an odd window whose rows do not divide the band size, with dark (Poisson) pixels,
    # pixels near the full well and beyond it
    window = (37, 51, 1201, 157)
    e = rng.uniform(0.0, 9000.0, (window[3], window[2])).astype(np.float32)
    e[:40] = rng.uniform(-5.0, 40.0, (40, window[2]))
    e[-30:] = rng.uniform(9000.0, 14000.0, (30, window[2]))
    for noise in (True, False):
        got = s.digitise(e, np.random.default_rng(9), window, noise=noise)
        want = _digitise_whole(s, e, np.random.default_rng(9), window, noise=noise)
        assert got.dtype == want.dtype and np.array_equal(got, want)


def test_2x2_samples_are_the_full_tensor_product_spline():
    """The 2 x 2 samples (splined along u first, in bands of rows) equal the spline of the
    pixel centres' construction, evaluated at the sample positions in the other order."""
    from crossline.sim.optics import _spline_matrix

    model = RigModel(PRESETS["compact"])
    window = model.scan_window
    x0, y0, w, h = window
    table = RayTable(model.camera, window)
    uc, vc, xy = table._coarse_grid
    Mu = _spline_matrix(uc, x0 - 0.25 + 0.5 * np.arange(2 * w))
    Mv = _spline_matrix(vc, y0 - 0.25 + 0.5 * np.arange(2 * h))
    full = np.stack([Mv @ xy[..., k] @ Mu.T for k in range(2)], -1)  # (2h, 2w, 2)
    rng = np.random.default_rng(2)
    rows, cols = rng.integers(0, h, 5000), rng.integers(0, w, 5000)
    rows[:4], cols[:4] = [0, 0, h - 1, h - 1], [0, w - 1, 0, w - 1]  # the corners
    want = np.stack([full[2 * rows + b, 2 * cols + a] for a, b in ((0, 0), (1, 0), (0, 1), (1, 1))], 1)
    got = table.sample_xy_2x2(rows, cols)
    assert np.abs(got - want).max() < 1e-14  # the same spline, summed in another order
