"""Metrology on synthetic points with known answers: exact first, then noisy with known statistics."""

from __future__ import annotations

import numpy as np
import pytest

from crossline.camera import Camera
from crossline.geometry import make_transform, rotvec_to_matrix, transform_points
from crossline.report import metrics as mt

K = np.array([[5145.362, 0.0, 1517.375], [0.0, 5153.664, 1023.363], [0.0, 0.0, 1.0]])
DIST = np.array([-0.09903, 0.195427, -0.000065974, -0.0000978477, 0.41673])


def pose(seed: int = 1) -> np.ndarray:
    """A rigid transform far from the identity (so no result can lean on the axes)."""
    rng = np.random.default_rng(seed)
    return make_transform(rotvec_to_matrix(rng.normal(size=3) * 0.6), rng.uniform(-400, 400, 3))


def gauge_scene(n=40000, height=20.0, noise=0.0, seed=0, size=(35.0, 9.0), extent=(70.0, 50.0),
                tilt=0.0):
    """Points of a block on a plate (plate z = 0) in the scene frame, with laser labels.

    ``tilt`` (rad) tilts the top face about the block's long axis through its centre line.
    """
    rng = np.random.default_rng(seed)
    P = rng.uniform([-extent[0] / 2, -extent[1] / 2], [extent[0] / 2, extent[1] / 2], size=(n, 2))
    inside = (np.abs(P[:, 0]) < size[0] / 2) & (np.abs(P[:, 1]) < size[1] / 2)
    plate = np.column_stack([P[~inside], np.zeros((~inside).sum())])
    Q = rng.uniform([-size[0] / 2, -size[1] / 2], [size[0] / 2, size[1] / 2], size=(n // 3, 2))
    top = np.column_stack([Q, height + np.tan(tilt) * Q[:, 1]])
    m = n // 20
    side = np.column_stack([rng.uniform(-1, 1, m) * size[0] / 2, np.full(m, size[1] / 2),
                            rng.uniform(0, height, m)])
    pts = np.vstack([plate, top, side])
    lab = np.where(rng.random(len(pts)) < 0.5, "A", "B")
    if noise:
        pts = pts + rng.normal(scale=noise, size=pts.shape)
    return pts, lab


def sphere_scene(n=30000, diameter=25.0, noise=0.0, seed=0, stem=True):
    """Points of the visible part of a ball on a stem over a plate; returns points, labels, centre."""
    rng = np.random.default_rng(seed)
    r = diameter / 2
    c = np.array([0.0, 0.0, r + 15.0])
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    parts = [v[v[:, 2] > -0.3] * r + c]
    if stem:
        m = n // 10
        a = rng.uniform(0, 2 * np.pi, m)
        st = np.column_stack([4 * np.cos(a), 4 * np.sin(a), rng.uniform(0, 15 + 0.2 * r, m)])
        parts.append(st[np.linalg.norm(st - c, axis=1) > r])
        P = rng.uniform(-40, 40, size=(n // 2, 2))
        P = P[np.hypot(P[:, 0], P[:, 1]) > 4]
        parts.append(np.column_stack([P, np.zeros(len(P))]))
    pts = np.vstack(parts)
    lab = np.where(rng.random(len(pts)) < 0.5, "A", "B")
    if noise:
        pts = pts + rng.normal(scale=noise, size=pts.shape)
    return pts, lab, c


# ----------------------------------------------------------------------------- basics


def test_robust_sigma_of_gaussian():
    x = np.random.default_rng(0).normal(scale=0.7, size=200000)
    assert mt.robust_sigma(x) == pytest.approx(0.7, rel=0.01)
    # about zero (a mismatch whose true value is zero), 10 % outliers move it little: the
    # median of |y| is where 0.9 P(|x| < q) = 1/2
    from scipy.stats import norm

    y = np.concatenate([x[:180000], np.full(20000, 50.0)])
    assert mt.robust_sigma(y, about=0.0) == pytest.approx(1.4826 * 0.7 * norm.ppf(0.5 + 0.25 / 0.9), rel=0.01)
    # and a shared offset counts as spread
    assert mt.robust_sigma(x + 0.7, about=0.0) > 1.5 * mt.robust_sigma(x + 0.7)


def test_ransac_plane_ignores_outliers_exactly():
    rng = np.random.default_rng(2)
    T = pose(2)
    on = np.column_stack([rng.uniform(-30, 30, (3000, 2)), np.zeros(3000)])
    off = rng.uniform(-30, 30, (1500, 3))  # 1/3 clutter, none of it within the band
    off[:, 2] += np.sign(off[:, 2]) * 0.05
    pts = transform_points(T, np.vstack([on, off]))
    n, d, inl = mt.ransac_plane(pts, 0.01, seed=0)
    n_true = T[:3, 2]
    assert abs(abs(n @ n_true) - 1) < 1e-12
    assert np.abs(pts[:3000] @ n + d).max() < 1e-9
    assert inl[:3000].all() and inl[3000:].mean() < 0.01


def test_plane_offset_of_parallel_planes():
    n = np.array([0.0, 0.6, 0.8])
    off, ang = mt.plane_offset((n, -1.0), (n, -1.25), np.array([3.0, 4.0, 5.0]))
    assert off == pytest.approx(0.25, abs=1e-12) and ang == pytest.approx(0, abs=1e-12)
    # b's normal flipped: the same plane, the same offset
    off2, _ = mt.plane_offset((n, -1.0), (-n, 1.25), np.zeros(3))
    assert off2 == pytest.approx(0.25, abs=1e-12)


# ----------------------------------------------------------------------------- plane


def test_plane_exact_in_any_pose():
    rng = np.random.default_rng(3)
    T = pose(3)
    pts = transform_points(T, np.column_stack([rng.uniform(-40, 40, (5000, 2)), np.zeros(5000)]))
    f = mt.measure_plane(pts).figures()
    assert f["rms_mm"] < 1e-9 and f["flatness_mm"] < 1e-8
    assert f["share_within_band"] == 1.0


def test_plane_noisy_statistics():
    rng = np.random.default_rng(4)
    sigma = 0.025  # ±0.05 mm is then ±2 sigma: 95.45 % inside
    n = 200000
    local = np.column_stack([rng.uniform(-40, 40, (n, 2)), rng.normal(scale=sigma, size=n)])
    f = mt.measure_plane(transform_points(pose(4), local), band_mm=0.05).figures()
    assert f["rms_mm"] == pytest.approx(sigma, rel=0.01)
    # binomial standard error of the share: sqrt(p(1-p)/n) = 0.00047
    assert f["share_within_band"] == pytest.approx(0.9545, abs=0.002)
    assert f["flatness_95_mm"] == pytest.approx(2 * 1.95996 * sigma, rel=0.02)
    assert f["flatness_mm"] > f["flatness_95_mm"]


def test_plane_flatness_of_a_known_step():
    # every point twice, once 0.03 mm higher: LSQ plane in the middle, full range 0.03 mm
    rng = np.random.default_rng(5)
    xy = rng.uniform(-20, 20, (2000, 2))
    local = np.vstack([np.column_stack([xy, np.zeros(2000)]), np.column_stack([xy, np.full(2000, 0.03)])])
    f = mt.measure_plane(transform_points(pose(5), local)).figures()
    assert f["flatness_mm"] == pytest.approx(0.03, abs=1e-6)
    assert f["rms_mm"] == pytest.approx(0.015, abs=1e-5)


# ----------------------------------------------------------------------------- gauge block


@pytest.mark.parametrize("use_up", [False, True])
def test_gauge_exact_in_any_pose(use_up):
    pts, _ = gauge_scene()
    T = pose(6)
    up = T[:3, 2] if use_up else None
    g = mt.measure_gauge_block(transform_points(T, pts), 20.0, up=up)
    f = g.figures()
    assert f["mean_mm"] == pytest.approx(20.0, abs=1e-9)
    assert f["std_mm"] < 1e-9
    assert f["central_length_mm"] == pytest.approx(20.0, abs=1e-9)
    assert f["length_variation_mm"] < 1e-9 and f["parallelism_deg"] < 1e-7
    assert f["n"] > 5000 and f["n_plate"] > 20000


def test_gauge_plate_plane_trims_the_foot_of_an_unscanned_wall():
    """The top face scanned on half its width only, the plate on a narrow patch beside the
    block: the top's outline leaves the foot of the block's wall outside its margin, and the
    stripe's mixed points there (up to 0.15 mm high, 3 % of the plate's) tilt a
    least-squares plate plane towards them; the plate's plane trims them (no frames: the
    heights against that plane)."""
    rng = np.random.default_rng(11)
    n_top, n_plate, n_foot = 6000, 20000, 600
    top = np.column_stack([rng.uniform(-15, 15, n_top), rng.uniform(-4.5, 0.0, n_top),
                           np.full(n_top, 20.0)])
    plate = np.column_stack([rng.uniform(-15, 15, n_plate), rng.uniform(4.5, 12.0, n_plate),
                             np.zeros(n_plate)])
    foot = np.column_stack([rng.uniform(-15, 15, n_foot), rng.uniform(4.5, 4.8, n_foot),
                            rng.uniform(0.005, 0.15, n_foot)])
    pts = np.vstack([top, plate, foot]) + rng.normal(scale=0.003, size=(n_top + n_plate + n_foot, 3))
    g = mt.measure_gauge_block(transform_points(pose(12), pts), 20.0,
                               up=pose(12)[:3, 2])
    assert abs(g.figures()["mean_mm"] - 20.0) < 0.001
    assert np.degrees(mt.angle_between(g.plate_normal, pose(12)[:3, 2])) < 0.001


def test_gauge_edges_are_left_out():
    pts, _ = gauge_scene(seed=7)
    rng = np.random.default_rng(7)
    # the stripe running over the edges: points 0.1 mm low within 0.3 mm of the top's outline,
    # and 0.1 mm high on the plate within 0.3 mm of the block's foot
    t = rng.uniform(-17.5, 17.5, 3000)
    e = rng.uniform(0, 0.3, 3000)
    top_edge = np.column_stack([t, 4.5 - e, np.full(3000, 19.9)])
    foot = np.column_stack([t, 4.5 + e, np.full(3000, 0.1)])
    bad = np.vstack([pts, top_edge, foot])
    f = mt.measure_gauge_block(bad, 20.0, edge_margin_mm=1.0).figures()
    assert f["mean_mm"] == pytest.approx(20.0, abs=1e-9)
    # the same points, no margin: the edges pull the mean down (so the margin matters)
    f0 = mt.measure_gauge_block(bad, 20.0, edge_margin_mm=0.0).figures()
    assert f0["mean_mm"] < 20.0 - 0.002


def test_gauge_tilted_top_face():
    tilt = np.radians(0.01)  # 0.01° about the long axis: 9 mm wide face
    pts, _ = gauge_scene(tilt=tilt, seed=8)
    f = mt.measure_gauge_block(transform_points(pose(8), pts), 20.0, edge_margin_mm=1.0).figures()
    assert f["parallelism_deg"] == pytest.approx(0.01, rel=1e-6)
    # over the usable top face (9 - 2 mm margin wide) the height varies by tan(tilt) * 7 mm
    assert f["length_variation_mm"] == pytest.approx(np.tan(tilt) * 7.0, rel=0.02)
    assert f["central_length_mm"] == pytest.approx(20.0, abs=2e-5)


def test_gauge_noisy_statistics():
    sigma = 0.006
    pts, _ = gauge_scene(n=120000, noise=sigma, seed=9)
    f = mt.measure_gauge_block(transform_points(pose(9), pts), 20.0).figures()
    assert abs(f["mean_mm"] - 20.0) < 4 * f["sem_mm"] + 1e-6
    assert f["std_mm"] == pytest.approx(sigma, rel=0.03)
    assert f["sem_mm"] == pytest.approx(f["std_mm"] / np.sqrt(f["n"]))
    assert f["error_mm"] == pytest.approx(f["mean_mm"] - 20.0)


def test_gauge_without_second_face_fails_clearly():
    rng = np.random.default_rng(10)
    flat = np.column_stack([rng.uniform(-30, 30, (5000, 2)), np.zeros(5000)])
    with pytest.raises(ValueError, match="second face"):
        mt.measure_gauge_block(flat, 20.0)


def test_gauge_a_against_b():
    pts, lab = gauge_scene(seed=11)
    # laser A measures heights 0.1 % too large: A - B = 0.02 mm
    scaled = pts.copy()
    scaled[lab == "A", 2] *= 1.001
    T = pose(11)
    P = transform_points(T, scaled)
    g = mt.measure_gauge_block(P, 20.0)
    ab = mt.compare_lasers("gauge_block", P, lab, gauge=g).figures()
    assert ab["A"]["mean_mm"] == pytest.approx(20.02, abs=1e-9)
    assert ab["B"]["mean_mm"] == pytest.approx(20.0, abs=1e-9)
    assert ab["A_minus_B"]["height_mm"] == pytest.approx(0.02, abs=1e-9)
    # both lasers see the plate at z = 0: no offset between their plate planes
    assert ab["A_minus_B"]["plate_offset_mm"] == pytest.approx(0.0, abs=1e-9)


def test_a_against_b_refuses_a_line():
    rng = np.random.default_rng(12)
    a = np.column_stack([rng.uniform(-30, 30, (3000, 2)), np.zeros(3000)])
    b = np.column_stack([rng.uniform(-30, 30, 3000), np.full(3000, 1.0), np.zeros(3000)])
    P = np.vstack([a, b])
    lab = np.array(["A"] * 3000 + ["B"] * 3000)
    r = mt.measure_plane(P)
    with pytest.raises(ValueError, match="along a line"):
        mt.compare_lasers("plane", P, lab, plane=r)


def test_plane_a_against_b_offset():
    rng = np.random.default_rng(13)
    xy = rng.uniform(-30, 30, (6000, 2))
    lab = np.where(np.arange(6000) % 2 == 0, "A", "B")
    z = np.where(lab == "A", 0.004, 0.0)  # laser A's plane 4 µm higher
    T = pose(13)
    P = transform_points(T, np.column_stack([xy, z]))
    r = mt.measure_plane(P, up=T[:3, 2])
    ab = mt.compare_lasers("plane", P, lab, plane=r).figures()
    assert ab["A_minus_B"]["plane_offset_mm"] == pytest.approx(0.004, abs=1e-9)
    assert ab["A_minus_B"]["plane_angle_deg"] < 1e-6


# ----------------------------------------------------------------------------- sphere


def test_sphere_exact():
    pts, _, c = sphere_scene(stem=False)
    T = pose(14)
    s = mt.measure_sphere(transform_points(T, pts), 25.0)
    f = s.figures()
    assert np.linalg.norm(s.centre - transform_points(T, c[None])[0]) < 1e-9
    assert f["size_error_mm"] == pytest.approx(0.0, abs=1e-9)
    assert f["form_error_mm"] < 1e-9


def test_sphere_among_stem_and_plate():
    pts, _, c = sphere_scene(stem=True)
    s = mt.measure_sphere(pts, 25.0)
    f = s.figures()
    # only the stem's points within a micrometre of the ball can survive the trimming
    assert np.linalg.norm(s.centre - c) < 1e-6
    assert abs(f["size_error_mm"]) < 1e-6
    assert f["n"] < f["n_total"]


def test_sphere_noisy_statistics():
    sigma = 0.005
    pts, lab, c = sphere_scene(n=60000, noise=sigma, seed=15)
    s = mt.measure_sphere(pts, 25.0)
    f = s.figures()
    assert abs(f["size_error_mm"]) < 0.001
    assert np.linalg.norm(s.centre - c) < 0.001
    assert f["rms_mm"] == pytest.approx(sigma, rel=0.03)
    # 95 % of a normal distribution within ±1.96 sigma: D95 range = 3.92 sigma
    assert f["form_error_d95_mm"] == pytest.approx(3.92 * sigma, rel=0.05)
    assert f["form_error_mm"] > f["form_error_d95_mm"]
    # VDI/VDE 2634-2 discards at most 0.3 %: 99.7 % within ±2.97 sigma, a range of 5.94 sigma
    assert f["form_error_vdi_mm"] == pytest.approx(5.94 * sigma, rel=0.06)
    assert f["form_error_d95_mm"] < f["form_error_vdi_mm"] < f["form_error_mm"]
    ab = mt.compare_lasers("sphere", pts, lab, sphere=s).figures()
    assert abs(ab["A_minus_B"]["diameter_mm"]) < 0.002


def test_sphere_among_a_wide_table():
    """A ball whose points are 6 % of the scan's (a table seen all around it, as a steep
    stripe's long sweep over the table gives): four points drawn from all of them are on the
    ball once in 4e4 draws, so the ball is found from the neighbourhoods of single points."""
    rng = np.random.default_rng(21)
    pts, _, c = sphere_scene(n=3000, stem=False, noise=0.002, seed=21)
    ball = pts[np.abs(np.linalg.norm(pts - c, axis=1) - 12.5) < 0.05]
    table = np.column_stack([rng.uniform(-150, 150, (45000, 2)), rng.normal(0.0, 0.002, 45000)])
    table = table[np.linalg.norm(table[:, :2] - c[:2], axis=1) > 15]
    P = np.vstack([table, ball])
    assert len(ball) < 0.07 * len(P)
    s = mt.measure_sphere(P, 25.0)
    assert np.linalg.norm(s.centre - c) < 0.001 and abs(s.figures()["size_error_mm"]) < 0.002
    assert s.figures()["n"] >= 0.99 * len(ball)


def test_sphere_wrong_nominal_fails_clearly():
    pts, _, _ = sphere_scene(stem=False)
    with pytest.raises(ValueError, match="no sphere of radius"):
        mt.measure_sphere(pts, 40.0)


def ball_bar_scene(length=55.0, diameter=25.0, noise=0.0, seed=0, T=None, n=30000):
    """Two balls on stems over a plate, ``length`` apart (the second 6 mm higher: an inclined
    bar), moved by ``T``; returns points and both true centres."""
    pts, _, c = sphere_scene(n=n, diameter=diameter, noise=0.0, seed=seed)
    # the second ball: the first's points (ball and stem only; the plate once) shifted along
    # the bar, so the scene holds two balls of identical shape
    shift = np.array([length * np.sqrt(1 - (6.0 / length) ** 2), 0.0, 6.0])
    on_plate = pts[:, 2] == 0.0
    P = np.vstack([pts, pts[~on_plate] + shift])
    # the plate must not run through the second ball's region: drop plate points under it
    near2 = (np.hypot(P[:, 0] - shift[0], P[:, 1]) < 4) & (P[:, 2] == 0.0)
    P = P[~near2]
    cs = np.array([c, c + shift])
    rng = np.random.default_rng(seed + 1)
    if noise:
        P = P + rng.normal(scale=noise, size=P.shape)
    if T is not None:
        P, cs = transform_points(T, P), transform_points(T, cs)
    return P, cs


def test_ball_bar_exact_in_any_pose():
    T = pose(21)
    P, cs = ball_bar_scene(T=T)
    b = mt.measure_ball_bar(P, 25.0, 55.0)
    f = b.figures()
    true = np.linalg.norm(cs[0] - cs[1])
    assert true == pytest.approx(55.0, abs=1e-9)
    assert f["length_mm"] == pytest.approx(true, abs=1e-6)
    assert f["length_error_mm"] == pytest.approx(0.0, abs=1e-6)
    # ball 1 is the one with the smaller base-frame x, and each ball is its own true one
    order = np.argsort(cs[:, 0])
    for k in range(2):
        assert np.linalg.norm(b.balls[k].centre - cs[order[k]]) < 1e-6
        assert abs(f["balls"][k]["size_error_mm"]) < 1e-6
    # the two balls' points are disjoint, and neither takes the plate
    assert not np.any(b.balls[0].inlier_mask & b.balls[1].inlier_mask)
    assert f["n"] == int(b.inlier_mask.sum()) < len(P)


def test_ball_bar_noisy_length_and_its_monte_carlo_figure():
    sigma = 0.005
    P, cs = ball_bar_scene(noise=sigma, seed=3, n=40000)
    b = mt.measure_ball_bar(P, 25.0, 55.0)
    # each centre from ~25 000 points of a cap: far below the noise
    assert abs(b.length - np.linalg.norm(cs[0] - cs[1])) < 0.001
    # the uncertainty's figure: the report's value on its own points, and a centre moved by
    # a known vector along the bar changes the length by that much
    from crossline.report import uncertainty as uc

    fig = uc.ball_bar_figures(b)
    w = np.ones(len(P))
    assert fig(P, w)["length_mm"] == pytest.approx(b.length, abs=1e-9)
    u = (b.balls[1].centre - b.balls[0].centre) / b.length
    Q = P.copy()
    Q[b.balls[1].inlier_mask] += 0.01 * u
    assert fig(Q, w)["length_mm"] == pytest.approx(b.length + 0.01, abs=1e-7)


def test_ball_bar_without_its_second_ball_fails_clearly():
    pts, _, _ = sphere_scene(stem=True)
    with pytest.raises(ValueError, match=r"where the second ball should be|no second ball"):
        mt.measure_ball_bar(pts, 25.0, 55.0)
    # a bar far longer than its nominal: the second ball is not where it should be
    P, _ = ball_bar_scene(length=100.0)
    with pytest.raises(ValueError, match="second ball"):
        mt.measure_ball_bar(P, 25.0, 55.0)
    # one whose near side is within reach is measured as it is (its SD then fails the check)
    P, _ = ball_bar_scene(length=80.0)
    assert mt.measure_ball_bar(P, 25.0, 55.0).length == pytest.approx(80.0, abs=1e-6)


# ----------------------------------------------------------------------------- freeform


def test_point_triangle_closest_against_dense_sampling():
    rng = np.random.default_rng(16)
    a, b, c = rng.normal(size=(3, 3))
    p = rng.normal(size=(200, 3)) * 2
    q = mt.point_triangle_closest(p, *(np.repeat(x[None], len(p), 0) for x in (a, b, c)))
    # q lies on the triangle (barycentric coordinates in [0, 1])
    M = np.column_stack([b - a, c - a])
    uv, *_ = np.linalg.lstsq(M, (q - a).T, rcond=None)
    assert (uv > -1e-9).all() and (uv.sum(0) < 1 + 1e-9).all()
    # and no sample of the triangle is closer
    s = np.linspace(0, 1, 201)
    U, V = np.meshgrid(s, s)
    ok = U + V <= 1
    samples = a + U[ok, None] * (b - a) + V[ok, None] * (c - a)
    d_best = np.min(np.linalg.norm(p[:, None] - samples[None], axis=2), axis=1)
    d_q = np.linalg.norm(p - q, axis=1)
    assert (d_q <= d_best + 1e-12).all()
    assert (d_best - d_q < 0.02).all()


def test_mesh_signed_distance_is_float64_exact_far_from_origin():
    # a 100 mm square at z = 500 mm, 1000 mm from the origin: float32 alone resolves ~6e-5 mm
    corner = np.array([1000.0, 1000.0, 500.0])
    V = np.array([[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0]], float) + corner
    F = np.array([[0, 1, 2], [0, 2, 3]])
    rng = np.random.default_rng(17)
    xy = rng.uniform(1, 99, (2000, 2)) + 1000
    h = rng.uniform(-1e-4, 1e-4, 2000)
    d = mt.mesh_signed_distance(np.column_stack([xy, 500 + h]), V, F)
    assert np.abs(d - h).max() < 1e-10
    # beside the square: distance to its edge, positive above
    d2 = mt.mesh_signed_distance(np.array([[1000 - 3.0, 1050, 504.0]]), V, F)
    assert d2[0] == pytest.approx(5.0, abs=1e-10)


# ----------------------------------------------------------------------------- against truth


def test_calibration_errors_vanish_for_the_truth_and_scale_with_it():
    cam = Camera(K, DIST, (3072, 2048))
    vol = mt.volume_points(cam, region=(207, 624, 2658, 800))
    assert vol[:, 2].min() == pytest.approx(115) and vol[:, 2].max() == pytest.approx(185)
    assert mt.camera_error(cam, cam, vol)["rms_px"] == 0.0
    shifted = Camera(K + np.array([[0, 0, 0.5], [0, 0, 0], [0, 0, 0]]), DIST, (3072, 2048))
    e = mt.camera_error(shifted, cam, vol)
    assert e["rms_px"] == pytest.approx(0.5, abs=1e-9) and e["dcx_px"] == pytest.approx(0.5)

    n = np.array([-0.659905, -0.551732, 0.51])
    n /= np.linalg.norm(n)
    d = -68.7215 / np.linalg.norm([-0.659905, -0.551732, 0.51])
    assert mt.laser_plane_error((n, d), (n, d), cam)["rms_mm"] < 1e-12
    e = mt.laser_plane_error((n, d + 0.01), (n, d), cam)
    assert e["rms_mm"] == pytest.approx(0.01, abs=1e-12) and e["angle_deg"] == 0.0
    assert e["n_points"] > 100

    T = pose(18)
    dT = make_transform(rotvec_to_matrix([0, 0, np.radians(0.01)]), [0.003, 0.0, 0.004])
    e = mt.transform_error(T @ dT, T, vol)
    assert e["rotation_deg"] == pytest.approx(0.01, rel=1e-6)
    assert e["rms_mm"] > 0.004  # a rotation adds to the 5 µm shift
    assert mt.transform_error(T, T, vol)["rms_mm"] < 1e-12


def test_a_principal_point_error_is_a_turn_of_the_frame_and_a_focal_error_is_not():
    from crossline.geometry import matrix_to_rotvec

    cam = Camera(K, DIST, (3072, 2048))
    vol = mt.volume_points(cam, region=(207, 624, 2658, 800))
    # cx off by 0.8 px: rays turned about the y axis by 0.8 / fx rad, nearly all of it
    shifted = Camera(K + np.array([[0, 0, 0.8], [0, 0, 0], [0, 0, 0]]), DIST, (3072, 2048))
    e = mt.camera_error(shifted, cam, vol)
    rv = matrix_to_rotvec(np.asarray(e["frame_free"]["R_cam_est_cam"]))
    assert np.linalg.norm(rv) == pytest.approx(0.8 / K[0, 0], rel=0.02)
    assert abs(rv[1]) / np.linalg.norm(rv) > 0.999
    assert e["rms_px"] == pytest.approx(0.8, abs=1e-9) and e["frame_free"]["rms_px"] < 0.02
    # a focal length 0.1 % long scales the image about the centre: no rotation undoes it
    longer = Camera(K * np.array([[1.001, 1, 1], [1, 1.001, 1], [1, 1, 1]]), DIST, (3072, 2048))
    e = mt.camera_error(longer, cam, vol)
    assert e["frame_free"]["rms_px"] > 0.8 * e["rms_px"] > 0.3


def test_deviation_stats():
    d = np.array([-0.06, -0.01, 0.0, 0.02, 0.05])
    s = mt.deviation_stats(d, band_mm=0.05)
    assert s["share_within_band"] == pytest.approx(0.8)
    assert s["max_abs_mm"] == pytest.approx(0.06)
    assert s["rms_mm"] == pytest.approx(np.sqrt(np.mean(d**2)))


def test_fit_plane_agrees_with_the_svd_fit():
    from crossline.geometry import fit_plane as fit_plane_svd

    rng = np.random.default_rng(19)
    local = np.column_stack([rng.uniform(-40, 40, (50000, 2)), rng.normal(scale=0.006, size=50000)])
    pts = transform_points(pose(19), local)
    n1, d1 = mt.fit_plane(pts)
    n2, d2 = fit_plane_svd(pts)
    assert np.abs(n1 - n2).max() < 1e-12 and abs(d1 - d2) < 1e-9


def test_sphere_by_incidence_finds_a_grazing_bias():
    pts, _, c = sphere_scene(stem=False, n=40000, seed=20)
    view = c + np.array([0.0, 0.0, 150.0])  # one camera straight above the ball
    r = pts - c
    v = view - pts
    inc = np.degrees(np.arccos(np.sum(r * v, 1) / np.linalg.norm(r, axis=1) / np.linalg.norm(v, axis=1)))
    # points seen beyond 70° of incidence read 10 µm outwards
    biased = pts + (inc > 70)[:, None] * 0.010 * r / np.linalg.norm(r, axis=1)[:, None]
    s = mt.measure_sphere(biased, 25.0)
    out = mt.sphere_by_incidence(biased, s, np.repeat(view[None], len(pts), 0), max_incidence_deg=60)
    assert s.figures()["size_error_mm"] > 0.002  # the bias inflates the full fit
    assert abs(out["size_error_steep_mm"]) < 1e-9  # the steep points alone are exact
    means = {b["from_deg"]: b["mean_residual_mm"] for b in out["bands"]}
    # the full fit spreads the step over every band, but it stays a step at 70°
    assert means[70.0] - means[60.0] > 0.005


def test_gauge_referenced_per_frame_cancels_pose_errors():
    """Each frame's pose error moves its plate and top points together: referencing every
    height to the plate seen in the same frame removes it, the plate plane does not."""
    pts, lab = gauge_scene(n=60000, seed=11)
    rng = np.random.default_rng(11)
    frame = rng.integers(0, 200, len(pts))
    offset = rng.normal(scale=0.008, size=200)  # per-frame error along the plate normal, mm
    moved = pts + np.column_stack([np.zeros((len(pts), 2)), offset[frame]])
    plane = mt.measure_gauge_block(moved, 20.0).figures()
    assert plane["std_mm"] == pytest.approx(0.008, rel=0.15)
    g = mt.measure_gauge_block(moved, 20.0, frame=frame)
    f = g.figures()
    assert f["reference"] == "frame"
    # exact but for the tilt the random offsets give the plate plane fit (~1e-6 mm)
    assert f["mean_mm"] == pytest.approx(20.0, abs=1e-6) and f["std_mm"] < 1e-5
    assert f["plane_reference_std_mm"] == pytest.approx(plane["std_mm"], rel=0.05)
    assert f["frame_offset_std_mm"] == pytest.approx(np.std(offset, ddof=1), rel=0.05)
    ab = mt.compare_lasers("gauge_block", moved, lab, gauge=g)
    assert abs(ab.difference["height_mm"]) < 1e-6  # the same plate-fit tilt as above


def _swept_gauge(crossed: bool, drift_mm: float = 0.04, H: float = 10.0, seed: int = 3):
    """A 16 mm block on a plate swept by 60 frames of a sheet x - m y - 0.8 z = x0 (m = 1; crossed:
    m = 0.3 every other frame, the other laser), each frame raised by an arm error that drifts
    by ``drift_mm`` over the sweep. The oblique sheet meets the top 0.8 H to the side of where
    it meets the plate, so the plate's tilt about the stripes enters the heights."""
    rng = np.random.default_rng(seed)
    pts, frames = [], []
    for f, x0 in enumerate(np.linspace(-20, 20, 60)):
        m = 0.3 if crossed and f % 2 else 1.0
        y = rng.uniform(-25, 25, 500)
        x_top = x0 + m * y + 0.8 * H
        top = (np.abs(x_top) < 8) & (np.abs(y) < 8)
        x = np.where(top, x_top, x0 + m * y)
        seen = top | ~((np.abs(x) < 8) & (np.abs(y) < 8))  # the plate under the block is hidden
        z = np.where(top, H, 0.0) + drift_mm * (x0 + 20) / 40 + rng.normal(scale=0.001, size=500)
        pts.append(np.column_stack([x, y, z])[seen])
        frames.append(np.full(int(seen.sum()), f))
    return np.vstack(pts), np.concatenate(frames)


def test_gauge_plate_normal_from_each_frames_stripes():
    """A drifting arm error tilts the plate plane fitted over all frames about the stripes;
    an oblique sheet meets the top beside where it meets the plate, so heights along that
    normal err by the tilt times that offset, however each frame is referenced. Crossed
    stripes give the normal from each frame's own shape, which the error does not tilt."""
    pts, frame = _swept_gauge(crossed=True)
    g = mt.measure_gauge_block(pts, 10.0, frame=frame)
    assert g.normal_from == "frames"
    assert g.figures()["mean_mm"] == pytest.approx(10.0, abs=3e-4)
    assert np.degrees(mt.angle_between(g.plate_normal, [0, 0, 1])) < 0.001
    # the plane fit's normal, tilted by the drift: the same per-frame heights 6.5 um off
    n, d = mt.fit_plane(pts[g.plate_mask])
    n, d = (n, d) if n[2] > 0 else (-n, -d)
    fp = frame[g.plate_mask]
    off = np.bincount(fp, pts[g.plate_mask] @ n + d, 60) / np.maximum(np.bincount(fp, minlength=60), 1)
    h = pts[g.top_mask] @ n + d - off[frame[g.top_mask]]
    assert abs(h.mean() - 10.0) > 5e-3
    # one laser: its stripes are parallel and do not tell the tilt about them; the plane fit
    # is kept, with its error (the arm's, which only a crossing stripe can tell)
    pts1, frame1 = _swept_gauge(crossed=False)
    g1 = mt.measure_gauge_block(pts1, 10.0, frame=frame1)
    assert g1.normal_from == "plane" and abs(g1.figures()["mean_mm"] - 10.0) > 5e-3


def test_gauge_plate_normal_from_short_crossing_stripes():
    """In every frame a second laser's stripe crosses the first at right angles on the block's
    top only, 3 mm long (a near-vertical stripe on a narrow block): it spans the plane less
    than 1 % as much as the long stripes do, yet tells its normal to within its noise; the
    frames' normal is taken and the drift does not tilt the heights."""
    from crossline.report.gauge_block import gauge_groups

    pts, frame = _swept_gauge(crossed=False)
    rng = np.random.default_rng(4)
    extra = []
    for f, x0 in enumerate(np.linspace(-20, 20, 60)):
        y = rng.uniform(-1.5, 1.5, 60)
        x = np.full(60, 0.5 * x0)  # along y, on the top (|x| < 8)
        z = 10.0 + 0.04 * (x0 + 20) / 40 + rng.normal(scale=0.001, size=60)
        extra.append((np.column_stack([x, y, z]), np.full(60, f)))
    pts = np.vstack([pts, *(e[0] for e in extra)])
    frame = np.concatenate([frame, *(e[1] for e in extra)])
    g = mt.measure_gauge_block(pts, 10.0, frame=frame)
    both, group = gauge_groups(frame, g.plate_mask, g.top_mask)
    q = pts[both]
    for k in np.unique(group):
        q[group == k] -= q[group == k].mean(0)
    ev = np.linalg.eigvalsh(q.T @ q)
    assert ev[1] < 0.01 * ev[2]  # spanned, but by short stripes
    assert g.normal_from == "frames"
    assert g.figures()["mean_mm"] == pytest.approx(10.0, abs=3e-4)


def test_gauge_falls_back_to_the_plate_plane_where_no_frame_sees_both_faces():
    """Top and plate never in one frame (a block as tall as the measuring range): the heights
    are the paper's, to the plate plane, and the result says why they are not per frame."""
    pts, _ = gauge_scene(seed=12)
    on_top = pts[:, 2] > 10
    frame = np.where(on_top, 1, 2)
    g = mt.measure_gauge_block(pts, 20.0, frame=frame)
    plane = mt.measure_gauge_block(pts, 20.0)
    f = g.figures()
    assert g.reference == "plane" and g.frame_offsets is None
    assert "not per frame" in f["reference_note"] and "only 0 top points" in f["reference_note"]
    assert f["mean_mm"] == plane.figures()["mean_mm"] and f["n"] == plane.figures()["n"]
    assert f["mean_mm"] == pytest.approx(20.0, abs=5e-4)
    assert "reference_note" not in plane.figures()


def test_label_errors_against_true_lines():
    """Two true lines crossing at u = 50; three points carry the wrong laser, one of them in the
    crossing band; points where both lines are within reach are not checked."""
    from crossline.report.metrics import label_errors

    u = np.arange(100)
    ta, tb = 100 + 0.5 * (u - 50), 100 - 0.5 * (u - 50)
    lab = np.array(["A"] * 100 + ["B"] * 100)
    lab[[10, 160, 44]] = ["B", "A", "B"]  # 44: 6 columns from the crossing, lines 6 px apart
    r = label_errors(np.zeros(200, int), lab, np.r_[u, u] + 0.2, np.r_[ta, tb] + 0.3,
                     np.zeros(200, int), np.array(["A"] * 100 + ["B"] * 100), np.r_[u, u],
                     np.r_[ta, tb])
    # distances across the lines (slopes +-0.5: the row difference / 1.118): an A point at
    # (u + 0.2, ta(u) + 0.3) is |u - 49.6| / 1.118 from line B, within 3 px for u = 47..52; a
    # B point is |u - 50.2| / 1.118 from line A, within 3 px for u = 47..53: 13 left unchecked
    assert r["checked"] == 200 - 13
    assert r["wrong"] == 3 and r["wrong_in_crossing_band"] == 2 and r["wrong_away_from_crossing"] == 1
    assert r["wrong_rate"] == pytest.approx(3 / 187)
    # their centre error, across line A: (0.3 - 0.5 * 0.2) / 1.118 px, every point
    assert r["centre_error"]["A"]["mean_px"] == pytest.approx(0.2 / np.hypot(1, 0.5))


def test_label_errors_measure_a_steep_line_across_it():
    """A stripe 86 deg from the rows (14.3 rows per column), its centres at fractional columns
    with a known scatter across the line: the centre error is that scatter, not the scatter
    times the slope that the nearest column's row would give."""
    from crossline.report.metrics import label_errors

    rng = np.random.default_rng(3)
    slope = np.tan(np.radians(86.0))
    tu = np.arange(100, 160)
    tv = 400 + slope * (tu - 100)
    # the centres, one per row, moved across the line by N(0, 0.05 px)
    vv = np.arange(410.0, 1200.0)
    uu = 100 + (vv - 400) / slope
    e = rng.normal(0.0, 0.05, vv.size)
    n = np.array([-slope, 1.0]) / np.hypot(1.0, slope)  # unit normal (u, v) of the line
    uu, vv = uu + e * n[0], vv + e * n[1]
    far_b = np.full(tu.size, 5000.0)  # laser B out of reach
    r = label_errors(np.zeros(vv.size, int), np.array(["A"] * vv.size), uu, vv,
                     np.zeros(2 * tu.size, int), np.array(["A"] * tu.size + ["B"] * tu.size),
                     np.r_[tu, tu], np.r_[tv, far_b])
    assert r["checked"] == vv.size and r["wrong"] == 0
    c = r["centre_error"]["A"]
    assert c["sigma_px"] == pytest.approx(0.05, rel=0.1)
    assert abs(c["mean_px"]) < 0.01


def test_label_errors_use_the_nearest_row_of_a_line_that_crosses_a_column_twice():
    """Laser A lights a step: two segments 40 rows apart in the same columns. Points on either
    segment are scored against their own segment, not the first row listed."""
    from crossline.report.metrics import label_errors

    u = np.arange(60)
    low, high, b = np.full(60, 300.0), np.full(60, 260.0), np.full(60, 100.0)
    tf = np.zeros(180, int)
    tl = np.array(["A"] * 120 + ["B"] * 60)
    tu, tv = np.r_[u, u, u], np.r_[low, high, b]
    # the points: both A segments labelled A, the B line labelled B, two B points mislabelled A
    lab = np.array(["A"] * 120 + ["B"] * 60)
    lab[[125, 150]] = "A"
    r = label_errors(tf, lab, tu + 0.1, tv + 0.2, tf, tl, tu, tv)
    assert r["checked"] == 180
    assert r["wrong"] == 2 and r["wrong_away_from_crossing"] == 2


def test_plane_depth_range_of_a_tilted_plane():
    """A plane z = a + b y seen by a pinhole camera: along the ray through normalised (x, y),
    z = a / (1 - b y), so the depth range over the sensor is set by its top and bottom rows."""
    from crossline.report.metrics import plane_depth_range

    K = np.array([[1000.0, 0, 640], [0, 1000.0, 400], [0, 0, 1]])
    cam = Camera(K, np.zeros(5), (1280, 800))
    a, b = 150.0, 0.4
    n = np.array([0.0, -b, 1.0])
    n_unit, d = n / np.linalg.norm(n), -a / np.linalg.norm(n)
    y = (np.array([0.0, 799.0]) - 400) / 1000
    expect = sorted(a / (1 - b * y))
    got = plane_depth_range(cam, [(n_unit, d)], quantiles=(0.0, 1.0))
    assert got == pytest.approx(expect, rel=1e-9)
    # a window of rows 300-499 sees a narrower range; a plane behind the camera, none
    y = (np.array([300.0, 499.0]) - 400) / 1000
    got = plane_depth_range(cam, [(n_unit, d)], region=(0, 300, 1280, 200), quantiles=(0.0, 1.0))
    assert got == pytest.approx(sorted(a / (1 - b * y)), rel=1e-9)
    assert plane_depth_range(cam, [(np.array([0.0, 0, 1]), 150.0)]) is None
