"""Measurement uncertainty: the plane fit's covariance against the scatter of repeated fits, the
Monte Carlo's draws against their covariances, and the Monte Carlo's u against first-order
propagation (GUM's law of propagation) through the same re-triangulation."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from crossline.camera import Camera
from crossline.geometry import fit_plane, matrix_to_rotvec, plane_covariance, plane_tilt_basis
from crossline.io.capture import read_frames_table
from crossline.report import metrics as mt
from crossline.report import uncertainty as uc
from tests.test_report_synthetic import make_capture

N_TRIALS = 400


def _plane_case(rng: np.random.Generator, clusters: int = 0, shared_mm: float = 0.0,
                noise_mm: float = 0.004) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Points of a laser-plane-like patch 150 mm in front of the camera: stripes (clusters)
    across it, each stripe moved by its own shared error (a board pose's)."""
    n = np.array([0.35, 0.1, -0.93])
    n /= np.linalg.norm(n)
    d = 140.0
    E = plane_tilt_basis(n)
    foot = -d * n
    g = max(clusters, 1)
    t = rng.uniform(-15, 15, size=(g, 60))
    s = np.linspace(-12, 12, g)[:, None] + 0 * t
    p = foot + t.reshape(-1, 1) * E[0] + s.reshape(-1, 1) * E[1]
    lab = np.repeat(np.arange(g), 60)
    off = rng.normal(scale=shared_mm, size=g)[lab] if shared_mm else 0.0
    p = p + (off + rng.normal(scale=noise_mm, size=len(p)))[:, None] * n
    return p, n, d, lab


def _params(n_fit: np.ndarray, d_fit: float, n: np.ndarray, d: float) -> np.ndarray:
    if n_fit @ n < 0:
        n_fit, d_fit = -n_fit, -d_fit
    E = plane_tilt_basis(n)
    return np.array([(n_fit - n) @ E[0], (n_fit - n) @ E[1], d_fit - d])


@pytest.mark.parametrize("clustered", [False, True], ids=["independent", "shared-by-pose"])
def test_plane_covariance_predicts_the_scatter_of_repeated_fits(clustered: bool) -> None:
    rng = np.random.default_rng(3)
    est, pred, pred_iid = [], [], []
    for _ in range(N_TRIALS):
        p, n, d, lab = _plane_case(rng, clusters=8, shared_mm=0.01 if clustered else 0.0)
        nf, df = fit_plane(p)
        est.append(_params(nf, df, n, d))
        pred.append(np.diag(plane_covariance(p, nf, df, clusters=lab)))
        pred_iid.append(np.diag(plane_covariance(p, nf, df)))
    emp = np.var(np.array(est), axis=0, ddof=1)
    ratio = np.sqrt(np.mean(pred, axis=0) / emp)
    iid_ratio = np.sqrt(np.mean(pred_iid, axis=0) / emp)
    # 400 trials: the empirical sigma is known to about 4 %
    if clustered:
        # the sandwich from 8 clusters is itself a small-sample estimate: its mean within 25 %;
        # the independent-error covariance alone would claim far too much
        assert np.all(np.abs(ratio - 1) < 0.25), ratio
        assert iid_ratio[2] < 0.5, iid_ratio
    else:
        assert np.all(np.abs(iid_ratio - 1) < 0.1), iid_ratio
        # the larger of two estimates in every direction errs on the safe side, by little
        assert np.all((ratio > 0.95) & (ratio < 1.3)), ratio


def _model(rng: np.random.Generator) -> uc.CalibrationModel:
    from crossline.laser import LaserPlane, LaserPlanes
    from tests.test_report_synthetic import DIST_PAPER, K_PAPER, X_PAPER, laser_plane

    def correlated(sigma: list[float]) -> np.ndarray:  # a random correlation, given sigmas
        A = rng.normal(size=(len(sigma), len(sigma)))
        C = A @ A.T + len(sigma) * np.eye(len(sigma))
        s = 1 / np.sqrt(np.diag(C))
        return np.outer(sigma, sigma) * (C * np.outer(s, s))

    # about a bundle adjustment's: fractions of a pixel, distortion to a few 1e-4
    cam_cov = correlated([0.4, 0.4, 0.3, 0.3, 2e-4, 1e-3, 2e-6, 2e-6, 4e-3])
    planes = LaserPlanes(*(LaserPlane(*laser_plane(L)) for L in "AB"))
    pcov = {L: (plane_tilt_basis(planes[L].normal), np.diag([2e-5, 1e-5, 4e-3]) ** 2) for L in "AB"}
    X_cov = correlated([1e-4] * 3 + [0.01] * 3)
    X = np.asarray(X_PAPER, dtype=np.float64)
    X[:3, :3] = np.linalg.svd(X[:3, :3])[0] @ np.linalg.svd(X[:3, :3])[2]
    return uc.CalibrationModel(Camera(np.array(K_PAPER), np.array(DIST_PAPER), (3072, 2048)),
                               planes, X, cam_cov, pcov, X_cov)


def test_drawn_calibrations_follow_their_covariances() -> None:
    rng = np.random.default_rng(5)
    m = _model(rng)
    cam, pl, xs = [], [], []
    for _ in range(3000):
        c, p, X = uc.draw_calibration(m, rng)
        cam.append([c.fx - m.camera.fx, c.fy - m.camera.fy, c.cx - m.camera.cx,
                    c.cy - m.camera.cy, *(c.dist - m.camera.dist)])
        pl.append(_params(p.A.normal, p.A.d, m.planes.A.normal, m.planes.A.d))
        dX = np.linalg.inv(m.X) @ X
        xs.append([*matrix_to_rotvec(dX[:3, :3]), *dX[:3, 3]])
    for got, want in ((cam, m.camera_cov), (pl, m.plane_cov["A"][1]), (xs, m.X_cov)):
        ratio = np.sqrt(np.diag(np.cov(np.array(got).T)) / np.diag(want))
        assert np.all(np.abs(ratio - 1) < 0.08), ratio  # 3000 draws: sigma to about 1.3 %


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("unc")
    make_capture(root / "raw", root / "interim", scans=("gauge", "ball"), frames=40, rays=200)
    return root / "raw", root / "interim"


def _scan(raw: Path, interim: Path, scan: str, model: uc.CalibrationModel) -> uc.ScanPoints:
    df = pd.read_parquet(interim / "points" / f"{scan}.parquet")
    ft = read_frames_table(raw / "scans" / scan / "frames.csv")
    return uc.scan_points(df[["x", "y", "z"]].to_numpy(), df["laser"].to_numpy(str),
                          df["frame"].to_numpy(), ft.frames, ft.T_base_tool, model)


def _arm_draws(raw: Path, scan: str, processed: Path, draws: int, seed: int = 0):
    """Write draws of the arm's error for ``scan`` from a 0.02 mm arm's prior, as fuse does
    for a scan it does not refine; return them."""
    from crossline.io.arm_draws import ArmDraws, write_arm_draws
    from crossline.scan.refine_prior import ArmPrior, prior_draws

    ft = read_frames_table(raw / "scans" / scan / "frames.csv")
    order = np.argsort(ft.frames)
    prior = ArmPrior.from_precision(0.02)
    d = prior_draws(ft.time_s[order], prior, len(order), draws, np.random.default_rng(seed))
    a = ArmDraws(ft.frames[order].astype(np.int64), ft.T_base_tool[order, :3, 3],
                 (d * prior.sigmas()).astype(np.float32), "prior")
    write_arm_draws(processed / f"{scan}.arm.npz", a)
    return a


def test_arm_draws_move_each_point_with_its_frames_pose_error(synthetic, tmp_path) -> None:
    """A drawn pose error (ω, t) about the flange moves a point as the rigid motion that the
    pose refinement's correction undoes (crossline.scan.refine.correction_transforms), to first
    order; the draws survive their file (float16, scaled) to 1e-3 of their spread; an error
    common to every frame (the whole scan moved rigidly) leaves the ball's size as it was."""
    from crossline.geometry import transform_points
    from crossline.io.arm_draws import ArmDraws, read_arm_draws
    from crossline.scan.refine import correction_transforms

    raw, interim = synthetic
    model = _model(np.random.default_rng(1))
    sp = _scan(raw, interim, "ball", model)
    a = _arm_draws(raw, "ball", tmp_path, draws=8)
    back = read_arm_draws(tmp_path / "ball.arm.npz")
    assert np.array_equal(back.frames, a.frames) and back.kind == "prior"
    assert np.abs(back.draws - a.draws).max() < 1e-3 * a.draws.reshape(-1, 6).std(0).max()
    move = uc.arm_moves(sp, back)
    k = np.searchsorted(back.frames, sp.frame)
    for d in (0, 5):
        e = back.draws[d].astype(np.float64)
        C = correction_transforms(e[:, :3], e[:, 3:], back.origins)
        want = sp.points - transform_points(C, sp.points, k)
        got = move(d)
        assert np.abs(got - want).max() < 1e-3 * np.abs(want).max()
    # one error for all frames, about one origin: a rigid motion of the whole scan
    one = np.broadcast_to(a.draws[:, :1], a.draws.shape) * 50.0
    rigid = ArmDraws(a.frames, np.broadcast_to(a.origins[:1], a.origins.shape), one, "prior")
    own = ArmDraws(a.frames, a.origins, a.draws * 50.0, "prior")  # each frame its own error
    s = uc.sphere_figures(mt.measure_sphere(sp.points, 25.0))
    bare = replace(model, camera_cov=None, plane_cov={}, X_cov=None)
    u_rigid, u_own = (uc.monte_carlo(sp, bare, s, draws=24, seed=2, arm=arm)["diameter_mm"][
        "budget"]["arm"]["u"] for arm in (rigid, own))
    # what is left of the rigid motion is the draws' linearisation (second order in ω)
    assert u_rigid < 0.01 * u_own and u_own > 1e-3


def test_unperturbed_calibration_gives_back_the_points(synthetic) -> None:
    raw, interim = synthetic
    model = _model(np.random.default_rng(1))
    sp = _scan(raw, interim, "gauge", model)
    P = uc.moved_points(sp, model.camera, model.planes, model.X)
    assert np.array_equal(P, sp.points)
    # a hand-eye translation moves each point by its frame's rotation of it, exactly
    X = model.X.copy()
    X[:3, 3] += [0.01, -0.02, 0.03]
    moved = uc.moved_points(sp, model.camera, model.planes, X) - sp.points
    want = np.einsum("nij,j->ni", sp.R_base_tool, [0.01, -0.02, 0.03])
    assert np.allclose(moved, want, atol=1e-9)


@pytest.mark.parametrize("scan", ["gauge", "ball"])
def test_monte_carlo_u_agrees_with_first_order_propagation(synthetic, scan: str) -> None:
    """For the camera alone, the figure is near-linear in the parameters over their small
    covariance: the Monte Carlo's u must match sqrt(g^T C g), g by central differences of the
    same re-triangulation and figure."""
    raw, interim = synthetic
    rng = np.random.default_rng(2)
    model = _model(rng)
    sp = _scan(raw, interim, scan, model)
    P = sp.points
    if scan == "gauge":
        g = mt.measure_gauge_block(P, 20.0, frame=pd.read_parquet(
            interim / "points" / f"{scan}.parquet")["frame"].to_numpy())
        figures, key = uc.gauge_figures(g, P, pd.read_parquet(
            interim / "points" / f"{scan}.parquet")["frame"].to_numpy()), "mean_mm"
    else:
        figures, key = uc.sphere_figures(mt.measure_sphere(P, 25.0)), "diameter_mm"
    ones = np.ones(len(P))
    base = figures(P, ones)[key]
    assert base == pytest.approx((g.figures()["mean_mm"] if scan == "gauge" else
                                  2 * mt.measure_sphere(P, 25.0).radius), abs=1e-9)
    sig = np.sqrt(np.diag(model.camera_cov))
    grad = np.zeros(9)
    for j in range(9):
        vals = []
        for sign in (1, -1):
            step = np.zeros(9)
            step[j] = sign * sig[j]
            Pk = uc.moved_points(sp, model.camera.perturbed(step), model.planes, model.X)
            vals.append(figures(Pk, ones)[key])
        grad[j] = (vals[0] - vals[1]) / (2 * sig[j])
    u_lin = float(np.sqrt(grad @ model.camera_cov @ grad))
    res = uc.monte_carlo(sp, model, figures, draws=400, seed=4)[key]
    u_mc = res["budget"]["camera"]["u"]
    assert u_lin > 0
    # 400 draws: u known to 3.5 %; within 12 % (3.4 sigma) of the linear propagation
    assert u_mc == pytest.approx(u_lin, rel=0.12)
    assert res["value"] == pytest.approx(base)
    assert res["U"] == pytest.approx(2 * res["u"])
    parts = res["budget"]
    assert sum(b["share"] for b in parts.values()) == pytest.approx(1.0)
    # drawn independently, the contributors add in quadrature at least; the frames' bootstrap
    # also changes how a calibration error averages over the frames, which can only add
    quad = np.sqrt(sum(b["u"] ** 2 for b in parts.values()))
    assert res["u"] > 0.9 * quad


def test_report_gives_U_and_decision_where_the_calibration_has_covariances(synthetic,
                                                                            tmp_path) -> None:
    from crossline.report.accuracy import build_report
    from crossline.report.pages import build_pages, fmt_row_value, page_texts

    raw, interim = synthetic
    model = _model(np.random.default_rng(1))
    cal = interim / "calibration"
    cam = json.loads((cal / "camera.json").read_text())
    cam["uncertainty"] = {"covariance": model.camera_cov.tolist()}
    out = tmp_path / "interim"
    (out / "calibration").mkdir(parents=True)
    (out / "points").symlink_to((interim / "points").resolve(), target_is_directory=True)
    (out / "calibration" / "camera.json").write_text(json.dumps(cam))
    las = json.loads((cal / "lasers.json").read_text())
    for L in "AB":
        E, C = model.plane_cov[L]
        # planes that do not follow the camera: the plumbing, not the physics, is tested here
        las[L]["covariance"] = {"tilt_basis": E.tolist(), "matrix": C.tolist(),
                                "camera_jacobian": np.zeros((3, 9)).tolist()}
    (out / "calibration" / "lasers.json").write_text(json.dumps(las))
    he = json.loads((cal / "handeye.json").read_text())
    he["methods"]["refined"]["uncertainty"] = {"covariance_X": model.X_cov.tolist()}
    (out / "calibration" / "handeye.json").write_text(json.dumps(he))
    for scan in ("gauge", "ball"):  # the fuse stage's draws of the arm's error, from its prior
        _arm_draws(raw, scan, tmp_path / "processed", draws=16)
    data = build_report(raw, out, tmp_path / "processed",
                        {"report": {"metrology": {"uncertainty_draws": 60}}})
    m = data.metrics
    unc = m["scans"]["gauge"]["uncertainty"]
    assert unc["draws"] == 60 and "incomplete" not in unc
    assert unc["arm_draws"] == {"draws": 16, "kind": "prior"}
    f = unc["figures"]["mean_mm"]
    assert f["value"] == pytest.approx(m["scans"]["gauge"]["measurement"]["mean_mm"])
    assert all(f["budget"][c]["u"] > 0 for c in uc.CONTRIBUTORS)
    rows = {r["id"]: r for r in m["summary"]}
    for rid in ("gauge_mean_error_mm", "sphere_size_error_mm", "sphere_form_error_mm"):
        r = rows[rid]
        assert r["U"] > 0 and r["k"] == 2
        v = abs(r["value"])
        want = ("conforms" if v + r["U"] <= r["tolerance"] else "does not conform"
                if v - r["U"] > r["tolerance"] else "inconclusive (within U of the limit)")
        assert r["decision"] == want
    assert rows["gauge_mean_error_mm"]["U"] == pytest.approx(f["U"])
    # the validation puts each truth-compared error beside its U: E_n = error / U
    for scan, err, fig in (("gauge", "mean_error_mm", "mean_mm"), ("ball", "diameter_error_mm",
                                                                   "diameter_mm")):
        t = m["scans"][scan]["truth"]
        U = m["scans"][scan]["uncertainty"]["figures"][fig]["U"]
        c = t["uncertainty_coverage"][fig]
        assert c["E_n"] == pytest.approx(t[err] / U, rel=1e-12) and c["U_mm"] == U
        assert c["covered"] == (abs(t[err]) <= U)
    texts = [" ".join(page_texts(p)) for p in build_pages(m, data.plots)]
    assert fmt_row_value(rows["gauge_mean_error_mm"]) in texts[0]
    page = next(t for t in texts if "Measurement uncertainty" in t and "Decision rule" in t)
    assert f"{m['scans']['ball']['truth']['uncertainty_coverage']['diameter_mm']['E_n']:+.2f}" in \
        next(t for t in texts if "Artefacts against their true geometry" in t)
    assert "ISO 14253-1" in page and rows["gauge_mean_error_mm"]["decision"] in page
    # without covariances the contributors are named as missing, the frames still count
    data = build_report(raw, interim, tmp_path / "processed2",
                        {"report": {"metrology": {"uncertainty_draws": 30}}})
    unc = data.metrics["scans"]["gauge"]["uncertainty"]
    assert len(unc["incomplete"]) == 5  # camera, planes A and B, hand-eye, the arm's draws
    assert "gauge.arm.npz" in unc["incomplete"][-1]
    b = unc["figures"]["mean_mm"]["budget"]
    assert b["camera"]["u"] == b["laser_planes"]["u"] == b["handeye"]["u"] == b["arm"]["u"] == 0
    assert b["repeatability"]["u"] > 0


def test_planes_follow_the_camera_they_were_fitted_through() -> None:
    """A laser plane fitted from boards seen with a wrong camera is wrong with it, in the way that
    lets triangulation with both wrong give back the boards' points: the camera Jacobian of the
    plane (boards posed again, stripe pixels carried onto them, plane refitted) must reproduce
    that, so that a drawn camera moves the planes as a real calibration would."""
    from crossline.board import Board
    from crossline.calibrate.lasers import PoseStripe, board_plane_points, camera_jacobian
    from crossline.calibrate.pose import project_board
    from crossline.geometry import make_transform, plane_line_intersection, rotvec_to_matrix
    from crossline.laser import LaserPlane
    from tests.test_report_synthetic import DIST_PAPER, K_PAPER, laser_plane

    cam = Camera(np.array(K_PAPER), np.array(DIST_PAPER), (3072, 2048))
    board = Board("symmetric", 15, 11, 3.75, 1.875, "dark")
    n, d = laser_plane("A")
    stripes, centre = [], np.array([26.25, 18.75, 0.0])
    for k, (rv, z) in enumerate([([0.3, 0.1, 0], 140), ([-0.25, 0.2, 0.1], 150),
                                 ([0.1, -0.3, -0.1], 160), ([-0.1, -0.15, 0.2], 145)]):
        R = rotvec_to_matrix(rv)
        T = make_transform(R, np.array([2.0 * k, -1.0, z]) - R @ centre)
        p0, u = plane_line_intersection(n, d, T[:3, 2], -T[:3, 2] @ T[:3, 3])
        foot = T[:3, 3] + R @ centre
        s = np.linspace(-18, 18, 200)
        line = p0 + ((foot - p0) @ u + s)[:, None] * u
        uv = cam.project(line)
        stripes.append(PoseStripe(line, uv, T, 0.0, "column", 200,
                                  board_points=project_board(cam, board, T), bias_correction=True))
    pts = np.concatenate([st.points for st in stripes])
    inl = np.ones(len(pts), dtype=bool)
    n0, d0 = fit_plane(pts)
    steps = np.array([0.4, 0.4, 0.3, 0.3, 2e-4, 1e-3, 2e-6, 2e-6, 4e-3])
    J = camera_jacobian(cam, board, stripes, inl, np.ones(len(pts)), n0, d0, steps)
    E = plane_tilt_basis(n0)
    err = {"fixed": [], "followed": [], "refit": []}
    for j, dx in enumerate(steps):
        delta = np.zeros(9)
        delta[j] = dx
        wrong = cam.perturbed(delta)
        a, b, dd = J @ delta
        m = n0 + a * E[0] + b * E[1]
        planes = {"fixed": LaserPlane(n0, d0),
                  "followed": LaserPlane(m, (d0 + dd) * np.linalg.norm(m))}
        # what the boards' stripe points are to that camera: its own view of them, and the
        # plane a laser calibration with that camera fits through them
        seen = [board_plane_points(wrong, _posed(wrong, board, st), st.uv) for st in stripes]
        planes["refit"] = LaserPlane(*fit_plane(np.concatenate(seen)))
        for st, sn in zip(stripes, seen, strict=True):
            r = wrong.rays(st.uv)
            for k, pl in planes.items():
                err[k].append(np.linalg.norm(pl.intersect_rays(r) - sn, axis=1))
    rms = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in err.items()}
    # with the plane held fixed a wrong camera puts the stripe off its boards; the plane a
    # calibration with that camera finds keeps it on them to a fraction of that (what is left
    # bends differently on each pose: no plane takes it out); the Jacobian's plane, that refit
    # to first order, recovers most of what the refit takes out (8.1 -> 1.1 um by refit, 1.8 um
    # by the Jacobian when written)
    assert rms["fixed"] > 1e-3, rms
    assert rms["refit"] < 0.5 * rms["fixed"], rms
    assert rms["fixed"] - rms["followed"] > 0.8 * (rms["fixed"] - rms["refit"]), rms


def _posed(camera: Camera, board, st) -> np.ndarray:
    from crossline.calibrate.pose import board_pose

    return board_pose(camera, board, st.board_points, bias_correction=st.bias_correction).T_cam_board


def test_a_gauge_seen_whole_in_few_frames_gets_u_from_the_draws_that_define_it(synthetic) -> None:
    """Heights are referenced per frame; a frame resampling may hold no frame that saw both
    faces (random rig 2's gauge): such a draw leaves the height undefined. It is counted, the
    others give u, and where they are too few u is NaN and the row gets no U (no traceback)."""
    raw, interim = synthetic
    model = _model(np.random.default_rng(5))
    sp = _scan(raw, interim, "gauge", model)
    frame = pd.read_parquet(interim / "points" / "gauge.parquet")["frame"].to_numpy()
    g = mt.measure_gauge_block(sp.points, 20.0, frame=frame)
    assert g.reference == "frame"
    # keep the top face of two frames only: most resamplings of the 40 frames still draw one
    top_frames = np.unique(frame[g.top_mask])
    keep = ~g.top_mask | np.isin(frame, top_frames[:2])
    figures = uc.gauge_figures(replace(g, top_mask=g.top_mask[keep], plate_mask=g.plate_mask[keep]),
                               sp.points[keep], frame[keep])
    sub = replace(sp, points=sp.points[keep], uv=sp.uv[keep], laser=sp.laser[keep],
                  frame_index=sp.frame_index[keep], R_base_tool=sp.R_base_tool[keep], p_tool=sp.p_tool[keep])
    res = uc.monte_carlo(sub, model, figures, draws=60, seed=1)["mean_mm"]
    # P(a frame of 40 is never drawn in 40) = (39/40)^40 = 0.36: both never drawn ~ 0.13
    assert 0 < res["draws_undefined"] < 30
    assert np.isfinite(res["u"]) and res["u"] > 0
    # one frame: the draws that miss it (about 36 %) leave the height undefined
    one = np.isin(frame[keep], top_frames[:1]) | ~g.top_mask[keep]
    fig1 = uc.gauge_figures(replace(g, top_mask=g.top_mask[keep][one], plate_mask=g.plate_mask[keep][one]),
                            sub.points[one], frame[keep][one])
    sub1 = replace(sub, points=sub.points[one], uv=sub.uv[one], laser=sub.laser[one],
                   frame_index=sub.frame_index[one], R_base_tool=sub.R_base_tool[one], p_tool=sub.p_tool[one])
    res1 = uc.monte_carlo(sub1, model, fig1, draws=60, seed=1)["mean_mm"]
    assert 8 < res1["draws_undefined"] < 36 and np.isfinite(res1["u"])
    # a figure that no resampling of the frames defines: u, U and the interval are NaN
    res2 = uc.monte_carlo(sub1, model, lambda P, w: {"x": 0.0 if np.all(w == 1) else np.nan},
                          draws=20, seed=1)["x"]
    assert res2["draws_undefined"] == 20 and np.isnan(res2["u"]) and np.isnan(res2["U"])
    assert np.isnan(res2["interval_95"]).all()


def test_a_resampling_without_the_plate_leaves_the_gauge_height_undefined(synthetic) -> None:
    """Random rig 53's gauge: its plate seen in a few frames only, a frame resampling may draw
    none of them. The height is then undefined for that draw (NaN, counted by monte_carlo),
    where the plate's weights summed to zero and the plane fit raised (no U at all)."""
    raw, interim = synthetic
    model = _model(np.random.default_rng(5))
    sp = _scan(raw, interim, "gauge", model)
    frame = pd.read_parquet(interim / "points" / "gauge.parquet")["frame"].to_numpy()
    g = mt.measure_gauge_block(sp.points, 20.0, frame=frame)
    w = np.ones(len(frame))
    w[g.plate_mask] = 0.0
    assert np.isnan(uc.gauge_figures(g, sp.points, frame)(sp.points, w)["mean_mm"])
    assert np.isfinite(uc.gauge_figures(g, sp.points, frame)(sp.points, np.ones(len(frame)))["mean_mm"])


@pytest.fixture(scope="module")
def dense_ball(tmp_path_factory) -> tuple[Path, Path]:
    """A ball scanned with 1000 points per stripe (about 40 000 points)."""
    root = tmp_path_factory.mktemp("unc_dense")
    make_capture(root / "raw", root / "interim", scans=("ball",), frames=40, rays=1000)
    return root / "raw", root / "interim"


@pytest.mark.parametrize("scan", ["gauge", "ball"])
def test_monte_carlo_on_every_kth_point_gives_the_same_u(synthetic, dense_ball, scan: str) -> None:
    """A long scan's Monte Carlo runs on every k-th of its points (report.metrology
    uncertainty_points): the calibration moves points by smooth functions, so a quarter of
    them must give the figure's u, and each calibration contributor's, as all of them do.
    (The ball's diameter is ill-conditioned on its cap: with 8000 points a quarter gave the
    camera's u 1.3x, with 40 000 within 6 %; the report samples only above 200 000.)"""
    raw, interim = synthetic if scan == "gauge" else dense_ball
    model = _model(np.random.default_rng(2))
    sp = _scan(raw, interim, scan, model)
    P = sp.points
    frame = pd.read_parquet(interim / "points" / f"{scan}.parquet")["frame"].to_numpy()
    if scan == "gauge":
        g = mt.measure_gauge_block(P, 20.0, frame=frame)
        make, key = (lambda subset=None: uc.gauge_figures(g, P, frame, subset=subset)), "mean_mm"
    else:
        s = mt.measure_sphere(P, 25.0)
        make, key = (lambda subset=None: uc.sphere_figures(s, subset=subset)), "diameter_mm"
    assert uc.subsample(len(P), len(P)) is None and uc.subsample(len(P), 0) is None
    sub = uc.subsample(len(P), len(P) // 4)
    assert len(sub) <= len(P) // 4 and np.all(np.diff(sub) == 4 + (len(P) % 4 > 0))
    ft = read_frames_table(raw / "scans" / scan / "frames.csv")
    sp_sub = uc.scan_points(P[sub], sp.laser[sub], frame[sub], ft.frames, ft.T_base_tool, model)
    assert sp_sub.n_frames == sp.n_frames  # every frame still in the sample: the same draws
    whole = uc.monte_carlo(sp, model, make(), draws=60, seed=4)[key]
    part = uc.monte_carlo(sp_sub, model, make(subset=sub), draws=60, seed=4)[key]
    assert part["u"] == pytest.approx(whole["u"], rel=0.1)
    for c in ("camera", "laser_planes"):
        assert whole["budget"][c]["u"] > 0
        assert part["budget"][c]["u"] == pytest.approx(whole["budget"][c]["u"], rel=0.1), c
    assert part["value"] == pytest.approx(whole["value"], abs=3 * whole["u"])
